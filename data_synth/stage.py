"""The synth stage: render the reference scene from the capture rig into a dataset folder.

Writes, in the run folder: dataset/ (NeRF-synthetic layout: transforms_{split}.json, RGBA PNG and
linear EXR per view, optional depth/normal EXR), ground_truth/ beside it (reference mesh,
lighting, injected effects) and a contact sheet of the training views.

The physical order of the capture chain: light transport while rendering (recon's renderer, or
Mitsuba when a light-transport effect is on), then the camera/optics/sensor/response effects on
linear radiance, then 8-bit quantisation when the PNG is written.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import torch
from tqdm import tqdm

from data_synth.effects.base import LIGHT_TRANSPORT, AppliedEffect, Capture
from data_synth.material import WorldMaterial, world_material
from data_synth.rigs import make_cameras
from data_synth.scene import WorldLighting, build_lighting, build_mesh, lighting_to_json
from recon.camera import Cameras
from recon.config.run_config import EffectConfig, LightingConfig, RunConfig
from recon.errors import ReconError
from recon.io.atomic import atomic_write_json
from recon.io.checkpoints import load_checkpoint, save_checkpoint
from recon.io.datasets import FLAT_FIELD_SPLIT, LINE_TARGET_SPLIT, write_nerf_synthetic
from recon.io.images import save_contact_sheet, write_exr
from recon.io.meshes import save_mesh
from recon.io.run_folder import RunPaths
from recon.mesh.mesh import Mesh
from recon.render.antialias import build_topology
from recon.render.renderer import Renderer

# Views rendered per batch: bounds memory at large resolutions.
VIEWS_PER_BATCH = 8
SPLIT_ORDER = ("train", "val", "test")


@dataclass
class SynthOptions:
    """How the stage was asked to run beyond the config (CLI flags).

    withhold: pick this many effects at random (seeded) with random plausible strengths, in
        addition to the config's; their names and parameters go only to truth_out.
    truth_out: where the withheld truth is written (outside the dataset and the run folder's
        ground_truth/, which then says only that effects were withheld).
    """

    withhold: int = 0
    truth_out: Path | None = None


@dataclass
class RenderedViews:
    """Premultiplied linear colour [B, H, W, 3], coverage [B, H, W, 1], camera depth and world
    normals [B, H, W, 1 / 3] (0 on background)."""

    colors: torch.Tensor
    alphas: torch.Tensor
    depth: torch.Tensor
    normals: torch.Tensor

    def _clamped(self) -> RenderedViews:
        """Radiance clamped at 0 and coverage into [0, 1] (antialiasing can overshoot)."""
        return replace(self, colors=self.colors.clamp_min(0), alphas=self.alphas.clamp(0, 1))


def render_views_own(
    mesh: Mesh,
    cameras: Cameras,
    world: WorldLighting,
    description: str,
    views_per_batch: int = VIEWS_PER_BATCH,
) -> RenderedViews:
    """recon's own renderer, in batches of views_per_batch, with a progress bar."""
    renderer = Renderer()
    topology = build_topology(mesh.faces, mesh.verts.shape[0])
    parts: list[RenderedViews] = []
    with torch.no_grad():
        for start in tqdm(
            range(0, len(cameras), views_per_batch), desc=description, unit="batch", leave=False
        ):
            output = renderer.render(
                mesh, cameras[start : start + views_per_batch], world.lighting, topology=topology
            )
            parts.append(
                RenderedViews(
                    output.color.clamp_min(0).cpu(),
                    output.alpha.clamp(0, 1).cpu(),
                    output.depth.cpu(),
                    output.normals.cpu(),
                )
            )
    return RenderedViews(
        *(torch.cat([getattr(p, f) for p in parts]) for f in RenderedViews.__dataclass_fields__)
    )


def _light_transport_names(effects: list[EffectConfig]) -> list[EffectConfig]:
    return [effect for effect in effects if effect.name in LIGHT_TRANSPORT]


def relit_effects(effects: list[EffectConfig], lighting: LightingConfig) -> list[EffectConfig]:
    """The effects for a relight split: the shadows effect's disk sun (which replaces the scene's
    directional lights) moves to the relight light's first sun, with its irradiance, keeping its
    own angular size. A shadows world is about how the sun casts shadows; under a second light
    the sun is that light's, which the diagnosis knows (lighting_relight.json). Without a sun in
    the relight light the effect is left as it is."""
    if not lighting.suns:
        return list(effects)
    sun = lighting.suns[0]
    x, y, z = (float(value) for value in sun.direction)
    length = math.sqrt(x * x + y * y + z * z)
    relit = []
    for effect in effects:
        if effect.name == "shadows":
            parameters = dict(effect.parameters)
            parameters["elevation_deg"] = math.degrees(math.asin(max(-1.0, min(1.0, y / length))))
            parameters["azimuth_deg"] = math.degrees(math.atan2(x, z))
            parameters["irradiance"] = sum(float(value) for value in sun.irradiance) / 3.0
            effect = replace(effect, parameters=parameters)
        relit.append(effect)
    return relit


def render_split(
    mesh: Mesh,
    cameras: Cameras,
    world: WorldLighting,
    config: RunConfig,
    effects: list[EffectConfig],
    description: str,
    device: torch.device,
    material: WorldMaterial | None = None,
    supersampling: int = 1,
) -> RenderedViews:
    """Render one split with the configured backend (Mitsuba for light-transport effects;
    'own' renders the 'specular' effect with recon's split-sum shading).

    material: the specular effect's material (data_synth.material.world_material), whose
    roughness map both backends render when it is textured.
    supersampling: cameras are at this many times the output resolution per side (their
    pixels are averaged down later): Mitsuba's samples per pixel are divided by its square."""
    backend = config.capture.backend
    # The same samples per batch as at the output resolution: a supersampled batch of 8 views
    # at 512 px held 5.4 GB against 0.85 GB without supersampling.
    batch = max(1, VIEWS_PER_BATCH // supersampling**2)
    light_transport = _light_transport_names(effects)
    traced = [effect.name for effect in light_transport if effect.name != "specular"]
    if backend == "own" and traced:
        raise ReconError(
            f"capture.backend: 'own' cannot render light-transport effects {traced}; use "
            "'auto' or 'mitsuba'"
        )
    if backend == "own" and light_transport:
        from data_synth.material import render_views_pbr

        if material is None:
            raise ReconError("render_split: the 'specular' effect needs its world material")
        outputs = render_views_pbr(
            mesh,
            material,
            cameras.to(device),
            world,
            config.capture.own_specular,
            batch,
            description,
        )
        return RenderedViews(
            *(
                torch.cat([getattr(output, name) for output in outputs]).cpu()
                for name in ("color", "alpha", "depth", "normals")
            )
        )._clamped()
    if backend == "mitsuba" or light_transport:
        from data_synth.effects.light_transport import mitsuba_options_for
        from data_synth.mitsuba_backend import MitsubaOptions, render_mitsuba

        options = mitsuba_options_for(
            light_transport,
            MitsubaOptions(
                spp=max(1, config.capture.mitsuba_spp // supersampling**2), seed=config.seed
            ),
            material=config.scene.material,
        )
        if material is not None and material.textured:
            options = replace(options, roughness_map=material.roughness)
        colors, alphas = render_mitsuba(mesh.to("cpu"), cameras, world, options)
        if not config.capture.write_depth_normals:
            return RenderedViews(colors, alphas, torch.zeros_like(alphas), torch.zeros_like(colors))
        # The path tracer gives no depth/normal buffers: take them from recon's rasterizer.
        geometry = render_views_own(mesh, cameras.to(device), world, description, batch)
        return RenderedViews(colors, alphas, geometry.depth, geometry.normals)
    return render_views_own(mesh, cameras.to(device), world, description, batch)


def synth_stage(
    config: RunConfig,
    paths: RunPaths,
    device: torch.device,
    withhold: int = 0,
    truth_out: str | Path | None = None,
    withhold_effects: list[str] | None = None,
    resume: bool = False,
) -> dict:
    """Entry point 'synth' of the recon.stages group (see SynthOptions for the keywords).

    withhold_effects: withhold exactly these effects (random plausible strengths) instead of
    drawing withhold of them at random (the blind benchmark chooses its cases).
    resume: continue an interrupted synthesis. After each split the stage records the splits
    it finished, its random states and the realised effects (RunPaths.synth_progress, with the
    withhold options it was started with), so a resumed run skips finished splits, rewrites the
    split it was interrupted in, and ends with the same files as an uninterrupted run."""
    progress = load_checkpoint(paths.synth_progress) if resume else None
    if progress is not None:
        withhold, truth_out, withhold_effects = progress["options"]
    options = SynthOptions(withhold, None if truth_out is None else Path(truth_out))
    # Separate streams: switching an effect on must not move the cameras, and vice versa.
    generator = torch.Generator().manual_seed(config.seed)
    effect_generator = torch.Generator().manual_seed(config.seed + 104729)
    mesh = build_mesh(config.scene).to(device)
    world = build_lighting(config.scene.lighting)
    world.lighting = world.lighting.to(device)
    capture_config = config.capture
    withheld: list[EffectConfig] = []
    if withhold_effects:
        from data_synth.withhold import sample_effects

        withheld = sample_effects(
            list(withhold_effects),
            torch.Generator().manual_seed(config.seed + 7919),
            make_cameras(capture_config.cameras, 1, torch.Generator().manual_seed(0)),
        )
    elif options.withhold:
        from data_synth.effects.base import ADDABLE
        from data_synth.withhold import choose_withheld_effects

        # recon's own backend cannot render light transport: never withhold what it can't make.
        candidates = (
            tuple(name for name in ADDABLE if name not in LIGHT_TRANSPORT)
            if capture_config.backend == "own"
            else ADDABLE
        )
        withheld = choose_withheld_effects(
            options.withhold,
            config.seed,
            exclude=[e.name for e in capture_config.effects],
            candidates=candidates,
            # Pixel-scale strengths follow the real image size and field of view.
            cameras=make_cameras(capture_config.cameras, 1, torch.Generator().manual_seed(0)),
        )
    if withheld and options.truth_out is None:
        raise ReconError("--withhold needs --truth-out PATH (the truth never goes in the dataset)")
    if withheld and options.truth_out.resolve().is_relative_to(paths.root.resolve()):
        raise ReconError(
            f"--truth-out {options.truth_out}: must lie outside the run folder {paths.root}, "
            "or the diagnosis could read it"
        )
    effects = list(capture_config.effects) + withheld
    image_effects = _image_effects(effects)
    # The glossy material (and its roughness map) both backends render and the truth records.
    material = world_material(effects, config.scene.material, mesh)
    counts = {
        "train": capture_config.train_views,
        "val": capture_config.val_views,
        "test": capture_config.test_views,
    }
    summary: dict = {"splits": {}}
    realised: dict[str, list[dict]] = {}
    sheet_images: list[torch.Tensor] = []
    test_cameras = None
    background = torch.tensor(capture_config.background)
    splits = [(split, counts[split]) for split in SPLIT_ORDER if counts[split] > 0]
    if capture_config.relight.views > 0:
        splits.append(("relight", capture_config.relight.views))
    done: list[str] = []
    if progress is not None:
        done = list(progress["done"])
        generator.set_state(progress["generator"])
        effect_generator.set_state(progress["effect_generator"])
        summary, realised = progress["summary"], progress["realised"]
        sheet_images, test_cameras = list(progress["sheet_images"]), progress["test_cameras"]

    def record_progress() -> None:
        save_checkpoint(
            paths.synth_progress,
            {
                "options": (
                    withhold,
                    None if truth_out is None else str(truth_out),
                    withhold_effects,
                ),
                "done": done,
                "generator": generator.get_state(),
                "effect_generator": effect_generator.get_state(),
                "summary": summary,
                "realised": realised,
                "sheet_images": sheet_images,
                "test_cameras": test_cameras,
            },
        )

    if progress is None:
        record_progress()
    for offset, (split, count) in enumerate(splits):
        if split in done:
            continue
        if split == "relight":
            # The test cameras (or as many as asked, from the same rig) under another light.
            cameras = (
                test_cameras[:count]
                if test_cameras is not None and len(test_cameras) >= count
                else make_cameras(capture_config.cameras, count, generator, offset=offset)
            )
            split_world = build_lighting(capture_config.relight.lighting)
            split_world.lighting = split_world.lighting.to(device)
        else:
            cameras = make_cameras(capture_config.cameras, count, generator, offset=offset)
            split_world = world
        if split == "test":
            test_cameras = cameras
        split_effects = (
            relit_effects(effects, capture_config.relight.lighting)
            if split == "relight"
            else effects
        )
        factor = supersampling(image_effects, capture_config.distortion_supersampling)
        height, width = cameras.image_size
        render_cameras = (
            cameras.with_image_size((height * factor, width * factor)) if factor > 1 else cameras
        )
        rendered = render_split(
            mesh,
            render_cameras,
            split_world,
            config,
            split_effects,
            f"synth {split}",
            device,
            material,
            supersampling=factor,
        )
        # Depth and normals stay the ideal camera's buffers: one sample per output pixel
        # (copied, so that the supersampled buffers are freed).
        rendered = replace(
            rendered,
            depth=rendered.depth[:, factor // 2 :: factor, factor // 2 :: factor].clone(),
            normals=rendered.normals[:, factor // 2 :: factor, factor // 2 :: factor].clone(),
        )
        capture = Capture(rendered.colors, rendered.alphas, render_cameras, pixel_scale=factor)
        applied: list[AppliedEffect] = []
        if image_effects:
            from data_synth.effects.registry import apply_effects

            # Leaves the capture at the output resolution, on the split's own cameras (or the
            # ones a pose error records).
            applied = apply_effects(capture, image_effects, effect_generator)
        realised[split] = [{"name": item.name, "parameters": item.parameters} for item in applied]
        write_nerf_synthetic(
            paths.dataset,
            split,
            capture.cameras,
            capture.images,
            capture.alpha,
            write_exr=capture_config.write_exr,
            # Resumed: this split's files are this run's own, from the interrupted attempt.
            force=resume,
        )
        if split == "relight":
            # The relight split's light is a known capture condition (a light stage, a second
            # lamp), not a hidden effect: it goes beside the views so that the diagnosis can
            # relight the fitted albedo with it.
            atomic_write_json(paths.dataset_layout.relight_lighting, lighting_to_json(split_world))
        if capture_config.write_depth_normals:
            for index in range(len(cameras)):
                write_exr(
                    paths.dataset / split / f"r_{index}_depth.exr", rendered.depth[index], ["Z"]
                )
                write_exr(
                    paths.dataset / split / f"r_{index}_normal.exr",
                    rendered.normals[index],
                    ["X", "Y", "Z"],
                )
        summary["splits"][split] = len(cameras)
        if split == "train":
            sheet_images = list((capture.images + (1 - capture.alpha) * background)[:16])
        done.append(split)
        record_progress()
    if capture_config.flat_field.views > 0:
        from data_synth.flat_field import write_flat_field

        realised[FLAT_FIELD_SPLIT] = write_flat_field(
            paths.dataset, capture_config, effects, config.seed, force=resume
        )
        summary["splits"][FLAT_FIELD_SPLIT] = capture_config.flat_field.views
    if capture_config.line_target.views > 0:
        from data_synth.line_target import write_line_target

        realised[LINE_TARGET_SPLIT] = write_line_target(
            paths.dataset, capture_config, effects, config.seed, force=resume
        )
        summary["splits"][LINE_TARGET_SPLIT] = capture_config.line_target.views
    if capture_config.contact_sheet and sheet_images:
        save_contact_sheet(sheet_images, paths.contact_sheet, columns=4)
    # A withheld specular effect stays out of the run folder's truth, its material with it.
    shown_material = material if not any(effect.name == "specular" for effect in withheld) else None
    _write_ground_truth(paths, mesh, world, effects, realised, withheld, options, shown_material)
    summary["effects"] = [effect.name for effect in effects if effect not in withheld]
    # Finished: env.json's stage record says so from here on; the progress file has done its job.
    paths.synth_progress.unlink(missing_ok=True)
    return summary


def supersampling(image_effects: list, factor: int) -> int:
    """Samples per output pixel side a split is rendered with: the config's factor where an
    effect acts on the optical image (ImageEffect.supersampled: a lens distortion), else 1."""
    return factor if any(getattr(effect, "supersampled", False) for effect in image_effects) else 1


def _image_effects(effects: list[EffectConfig]) -> list:
    """World effect objects for the camera/optics/sensor/response effects (not light transport,
    which configures the renderer instead)."""
    chosen = [effect for effect in effects if effect.name not in LIGHT_TRANSPORT]
    if not chosen:
        return []
    from data_synth.effects.registry import make_world_effect

    return [make_world_effect(effect.name, dict(effect.parameters)) for effect in chosen]


def _write_ground_truth(
    paths: RunPaths,
    mesh: Mesh,
    world: WorldLighting,
    effects: list[EffectConfig],
    realised: dict[str, list[dict]],
    withheld: list[EffectConfig],
    options: SynthOptions,
    material: WorldMaterial | None = None,
) -> None:
    """Reference mesh, lighting and effects beside the dataset; withheld effects only in
    options.truth_out, so a diagnoser that reads the run folder learns nothing about them. With
    a specular material and a textured mesh the reference mesh carries its roughness and
    metalness maps (map_Pr / map_Pm: recon.io.meshes.load_material_maps reads them)."""
    paths.ground_truth.mkdir(parents=True, exist_ok=True)
    maps = material.maps() if material is not None and mesh.texture is not None else None
    save_mesh(paths.reference_mesh, mesh.to("cpu"), material_maps=maps)
    atomic_write_json(paths.truth_lighting, lighting_to_json(world))
    if world.environment_map is not None:
        write_exr(paths.truth_environment, world.environment_map)
    withheld_names = {effect.name for effect in withheld}

    def records(keep) -> dict:
        return {
            split: [item for item in items if keep(item["name"])]
            for split, items in realised.items()
        }

    light_transport = {
        effect.name: dict(effect.parameters) for effect in effects if effect.name in LIGHT_TRANSPORT
    }
    if withheld:
        atomic_write_json(
            paths.truth_effects,
            {
                "effects": [e.name for e in effects if e.name not in withheld_names],
                "withheld": True,
                "realised": records(lambda name: name not in withheld_names),
            },
        )
        options.truth_out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_json(
            options.truth_out,
            {
                "withheld": [
                    {"name": effect.name, "parameters": dict(effect.parameters)}
                    for effect in withheld
                ],
                "realised": records(lambda name: name in withheld_names),
                "light_transport": {
                    name: value for name, value in light_transport.items() if name in withheld_names
                },
            },
        )
    else:
        atomic_write_json(
            paths.truth_effects,
            {
                "effects": [effect.name for effect in effects],
                "withheld": False,
                "realised": records(lambda name: True),
                "light_transport": light_transport,
            },
        )
