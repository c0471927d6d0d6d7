"""Stage 2 with the `pbr` material (fit.material: pbr): after simplify + unwrap + bake, optimise
base colour, roughness and metalness textures, an environment map and the vertex positions on
the fixed topology, shading with the split-sum GGX model (recon.render.pbr).

The geometry stage stays Lambertian (its per-vertex albedo absorbs highlights; the silhouettes
drive the shape); its light seeds the environment map: the SH radiance plus the sun spread over
a small lobe of the same irradiance.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from tqdm import tqdm

from recon.config.run_config import FitConfig
from recon.effects.forward import apply_camera_effects, apply_image_effects
from recon.errors import ReconError
from recon.io.datasets import CaptureSet
from recon.io.images import read_exr
from recon.io.meshes import load_material_maps, load_mesh
from recon.mesh.mesh import Mesh
from recon.mesh.uv import dilate
from recon.optimize.checkpoint import (
    History,
    random_states,
    restore_random_states,
    save_checkpoint,
)
from recon.optimize.geometry_stage import GeometryResult
from recon.optimize.large_steps import UniformAdam
from recon.optimize.scene_model import (
    FitEffects,
    LightModel,
    image_loss,
    sample_views,
    step_record,
    texture_total_variation,
)
from recon.optimize.sun_light import ShadowMap, ShadowSettings, reclaim_sun, split_sun
from recon.optimize.texture_stage import LOG_EVERY, start_texture_stage
from recon.render.environment import (
    PrefilteredEnvironment,
    latlong_directions,
    prefilter_environment,
    project_to_sh,
)
from recon.render.environment_seed import backproject_highlights
from recon.render.interpolate import interpolate_packed
from recon.render.lobe_sampling import SampledEnvironment
from recon.render.renderer import Renderer, RenderOutput, SurfaceBuffers
from recon.render.shading import DirectionalLight, sh_basis, sh_irradiance
from recon.render.texture import build_mip_pyramid

# Roughness below this is a mirror narrower than any texel of the environment a fit can afford.
MINIMUM_ROUGHNESS = 0.04
# The geometry stage's sun is spread over a lobe this many environment texels wide.
SUN_LOBE_TEXELS = 1.5
# Largest x or y of the tangent-space normal map.
MAXIMUM_NORMAL_SLOPE = 0.8
# A log-parameterised environment starts no texel below this radiance (log 0 is -inf).
ENVIRONMENT_FLOOR = 1e-3


@dataclass
class PbrTextureResult:
    """The `pbr` texture stage's result.

    mesh: the final mesh; mesh.texture is the base colour [h, w, 3].
    material: [h, w, 2] roughness, metalness on the same UVs, or [h, w, 5] with a
    tangent-space normal map (x, y, z) after them (fit.pbr.normal_map).
    environment: [he, we, 3] lat-long radiance of the fitted light.
    light: an SH light equivalent to the environment (for Lambertian consumers).
    specular_level, prefilter_levels, diffuse_weighting: the shading settings the fit used.
    lobe_samples, lobe_filter_width: the full-lobe shading's samples per pixel and filter
    (recon.render.lobe_sampling; lobe_samples 0: the split sum).
    light_frame: 'world', or 'camera' when the environment is fixed to the camera (turntable
    captures, fit.light.frame): its directions are then OpenCV camera axes of each view.
    suns: directional lights split off the environment (fit.pbr.sun_lights), shaded with the
    exact BRDF and shadowed by shadow maps with the settings shadow (recon.optimize.sun_light).
    """

    mesh: Mesh
    material: torch.Tensor
    environment: torch.Tensor
    light: LightModel
    specular_level: float
    prefilter_levels: int
    effects: FitEffects | None = None
    diffuse_weighting: str = "none"
    light_frame: str = "world"
    lobe_samples: int = 0
    lobe_filter_width: float = 0.5
    suns: list[DirectionalLight] = field(default_factory=list)
    shadow: ShadowSettings = field(default_factory=ShadowSettings)

    def shading_environment(self) -> PrefilteredEnvironment | SampledEnvironment:
        """The environment as the fit shaded with it: split sum, or the full lobe per pixel
        (lobe_samples > 0, fit.pbr.lobe_steps)."""
        prefiltered = prefilter_environment(self.environment, self.prefilter_levels)
        if self.lobe_samples > 0:
            return SampledEnvironment(prefiltered, self.lobe_samples, self.lobe_filter_width)
        return prefiltered

    def material_texture(self) -> torch.Tensor:
        """[h, w, 5] base colour, roughness, metalness (+ normal map: [h, w, 8]): what
        Renderer.shade_pbr samples."""
        return torch.cat([self.mesh.texture, self.material], dim=-1)

    def render(self, renderer: Renderer, cameras, background: float = 0.0) -> RenderOutput:
        """Render the fitted scene (no effects) from cameras, e.g. held-out views."""
        buffers = renderer.surface_buffers(self.mesh, cameras)
        texture = self.material_texture()
        return renderer.shade_pbr(
            buffers,
            cameras.centers(),
            texture,
            self.shading_environment(),
            specular_level=self.specular_level,
            background=background,
            mip_pyramid=build_mip_pyramid(texture),
            diffuse_weighting=self.diffuse_weighting,
            light_frame=self.light_frame,
            directional=self.suns,
            directional_visibility=shadowed_suns(buffers, self.suns, self.shadow),
        )


def shadowed_suns(
    buffers: SurfaceBuffers,
    suns: list[DirectionalLight],
    shadow: ShadowSettings,
    maps: list[ShadowMap] | None = None,
) -> list[torch.Tensor]:
    """Visibility [N, 1] of each sun from the buffers' covered pixels: its shadow map in maps,
    or one drawn of the buffers' mesh along it (recon.optimize.sun_light)."""
    if not suns:
        return []
    mesh = buffers.mesh
    if maps is None:
        maps = [
            ShadowMap.draw(mesh.verts, mesh.faces, sun.direction_to_light, shadow) for sun in suns
        ]
    points = interpolate_packed(mesh.verts, buffers.fragments, mesh.faces)
    return [shadow_map.visibility(points, buffers.normals, shadow) for shadow_map in maps]


def _sun_moved(maps: list[ShadowMap], suns: list[DirectionalLight], resolution: int) -> bool:
    """Whether a sun turned by more than 1 / resolution radians from its map's direction: the
    shadow of the far side of the mesh's bounding sphere then moves by over half a texel."""
    for shadow_map, sun in zip(maps, suns, strict=True):
        drawn = -shadow_map.frames.axes[0, 2]
        now = torch.nn.functional.normalize(sun.direction_to_light.detach(), dim=0).to(drawn)
        if float((drawn * now).sum().clamp(-1, 1)) < math.cos(1.0 / resolution):
            return True
    return False


def environment_from_light(light: LightModel, size: tuple[int, int]) -> torch.Tensor:
    """A lat-long map [h, w, 3] of a SH (+ sun) light: the SH radiance, clamped at 0, plus the
    sun as a narrow lobe whose integral over solid angle is the sun's irradiance."""
    directions, _ = latlong_directions(*size, device=light.sh.device)
    radiance = (sh_basis(directions.reshape(-1, 3)) @ light.sh.detach()).clamp_min(0)
    return radiance.reshape(*size, 3) + sun_lobe_environment(light, size)


def sun_lobe_environment(light: LightModel, size: tuple[int, int]) -> torch.Tensor:
    """The light's sun as a lat-long map [h, w, 3]: a lobe SUN_LOBE_TEXELS wide whose integral
    over solid angle is the sun's irradiance (zero without a sun)."""
    directions, solid_angle = latlong_directions(*size, device=light.sh.device)
    if not light.with_sun:
        return directions.new_zeros(*size, 3)
    sun = light.lighting().directional[0]
    width = SUN_LOBE_TEXELS * math.pi / size[0]
    cosine = directions.reshape(-1, 3) @ sun.direction_to_light.detach()
    lobe = torch.exp((cosine - 1) / (width * width))
    lobe = lobe / (lobe * solid_angle.reshape(-1)).sum()
    return (lobe[:, None] * sun.irradiance.detach()).reshape(*size, 3)


def highlight_environment(
    renderer: Renderer,
    mesh: Mesh,
    cameras,
    images: torch.Tensor,
    masks: torch.Tensor,
    prior: torch.Tensor,
    roughness: float,
    specular_level: float,
    prior_weight: float,
    light_frame: str = "world",
    views_per_batch: int = 4,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The highlights seed (fit.pbr.environment_seed): prior [h, w, 3] plus the training views'
    specular excess back-projected along reflection directions
    (recon.render.environment_seed.backproject_highlights), and the factor [3] that keeps the
    diffuse shading of the base colour mesh.texture where it was under prior.

    The excess is measured against the diffuse shading of the base colour under prior; pixels
    on the silhouette (mask < 1) do not vote. A brighter seed raises the irradiance too, so the
    base colour, baked under prior, is rescaled by sum(b E_prior) / sum(b E_seed) over the
    voting pixels (one factor per channel: the light's level is fixed by the specular
    reflectance, which the base colour does not scale).
    images: [B, H, W, 3], masks: [B, H, W, 1] at the cameras' resolution.
    """
    observed, base, normals, to_viewer = [], [], [], []
    material = torch.cat([mesh.texture, torch.zeros_like(mesh.texture[..., :2])], dim=-1)
    with torch.no_grad():
        for start in range(0, len(cameras), views_per_batch):
            views = torch.arange(start, min(start + views_per_batch, len(cameras)))
            batch = cameras[views.to(cameras.device)]
            buffers = renderer.surface_buffers(mesh, batch)
            fragments = buffers.fragments
            covered = fragments.covered_index
            albedo = renderer.shade_pbr(
                buffers, batch.centers(), material, None, antialias_edges=False
            ).albedo
            inside = masks[views].reshape(-1)[covered] >= 0.999
            positions = interpolate_packed(mesh.verts, fragments, mesh.faces)
            centers = batch.centers().to(positions.dtype)[fragments.covered_batch]
            view_directions = torch.nn.functional.normalize(centers - positions, dim=-1)
            view_normals = buffers.normals
            if light_frame == "camera":
                # The environment's directions are each view's OpenCV camera axes.
                rotation = buffers.world_to_cam[fragments.covered_batch][:, :3, :3]
                view_normals = (rotation @ view_normals[..., None])[..., 0]
                view_directions = (rotation @ view_directions[..., None])[..., 0]
            observed.append(images[views].reshape(-1, 3)[covered][inside])
            base.append(albedo.reshape(-1, 3)[covered][inside])
            normals.append(view_normals[inside])
            to_viewer.append(view_directions[inside])
        observed, base = torch.cat(observed), torch.cat(base)
        normals, to_viewer = torch.cat(normals), torch.cat(to_viewer)
        prior_irradiance = sh_irradiance(normals, project_to_sh(prior))
        environment = backproject_highlights(
            observed,
            base / math.pi * prior_irradiance,
            normals,
            to_viewer,
            prior,
            roughness,
            specular_level,
            prior_weight,
        )
        seed_irradiance = sh_irradiance(normals, project_to_sh(environment))
        scale = (base * prior_irradiance).sum(0) / (base * seed_irradiance).sum(0).clamp_min(1e-8)
    return environment, scale


def light_from_environment(
    environment: torch.Tensor, frame: str = "world", suns: list[DirectionalLight] | None = None
) -> LightModel:
    """A LightModel with the environment's order-2 SH projection, in the same frame; with suns
    the first is its sun and further ones are added to the SH as delta lights."""
    suns = suns or []
    light = LightModel(with_sun=bool(suns), frame=frame).to(environment.device)
    with torch.no_grad():
        coefficients = project_to_sh(environment.detach())
        for sun in suns[1:]:
            direction = torch.nn.functional.normalize(sun.direction_to_light.detach(), dim=0)
            coefficients = (
                coefficients
                + sh_basis(direction[None])[0][:, None] * (sun.irradiance.detach()[None])
            )
        light.sh.copy_(coefficients)
        if suns:
            light.sun_direction.copy_(suns[0].direction_to_light.detach())
            light.sun_log_irradiance.copy_(suns[0].irradiance.detach().clamp_min(1e-8).log())
    return light


def pbr_light_record(result: PbrTextureResult, environment_file: str) -> dict:
    """The light record of a `pbr` fit: its environment's order-2 SH (for Lambertian consumers,
    as a Lambertian fit writes it), the pbr settings, and the environment map's file name
    (beside the record)."""
    record = result.light.to_json()
    record.update(
        {
            "material": "pbr",
            "environment_file": environment_file,
            "specular_level": result.specular_level,
            "prefilter_levels": result.prefilter_levels,
            "diffuse_weighting": result.diffuse_weighting,
            "lobe_samples": result.lobe_samples,
            "lobe_filter_width": result.lobe_filter_width,
        }
    )
    if result.suns:
        record["suns"] = [
            {
                "direction_to_light": sun.direction_to_light.detach().cpu().tolist(),
                "irradiance": sun.irradiance.detach().cpu().tolist(),
            }
            for sun in result.suns
        ]
        record["shadow"] = asdict(result.shadow)
    return record


def read_pbr_result(
    light_file: Path, mesh_file: Path, device: torch.device | str = "cpu"
) -> PbrTextureResult | None:
    """A `pbr` fit (pbr_light_record's record in light_file, the mesh with its roughness and
    metallic maps in mesh_file) as a PbrTextureResult, or None when the fit was Lambertian (its
    light record names no 'pbr') or there is no light record."""
    light_file, mesh_file = Path(light_file), Path(mesh_file)
    if not light_file.exists():
        return None
    record = json.loads(light_file.read_text())
    if record.get("material") != "pbr":
        return None
    maps = load_material_maps(mesh_file)
    environment_path = light_file.parent / record["environment_file"]
    missing = []
    if maps is None:
        missing.append(f"the roughness/metallic maps (map_Pr, map_Pm) of {mesh_file}")
    if not environment_path.exists():
        missing.append(str(environment_path))
    if missing:
        raise ReconError(
            f"{light_file}: names the pbr material, but {' and '.join(missing)} "
            "are missing (rerun the fit stage)"
        )
    mesh = load_mesh(mesh_file).to(device)
    environment = read_exr(environment_path)[..., :3].to(device)
    suns = [
        DirectionalLight(
            torch.tensor(sun["direction_to_light"], dtype=torch.float32, device=device),
            torch.tensor(sun["irradiance"], dtype=torch.float32, device=device),
        )
        for sun in record.get("suns", [])
    ]
    shadow = ShadowSettings(**record["shadow"]) if suns else ShadowSettings()
    return PbrTextureResult(
        mesh,
        maps.to(device),
        environment,
        light_from_environment(environment, record.get("frame", "world"), suns),
        float(record["specular_level"]),
        int(record["prefilter_levels"]),
        diffuse_weighting=record.get("diffuse_weighting", "none"),
        light_frame=record.get("frame", "world"),
        lobe_samples=int(record.get("lobe_samples", 0)),
        lobe_filter_width=float(record.get("lobe_filter_width", 0.5)),
        suns=suns,
        shadow=shadow,
    )


def run_pbr_texture_stage(
    captures: CaptureSet,
    geometry: GeometryResult,
    config: FitConfig,
    device: torch.device,
    seed: int,
    checkpoint_path: Path,
    history: History,
    resume: bool = False,
    effects: FitEffects | None = None,
    resolution: int | None = None,
    warm_start: PbrTextureResult | None = None,
) -> PbrTextureResult:
    """The `pbr` counterpart of run_texture_stage (same steps, views, learning rates and
    checkpoint cadence from config.texture; material and light settings from config.pbr).
    Camera and image effects apply around the render; shading effects are Lambertian add-ons
    and are refused.

    warm_start: a fitted pbr result to start from (a warm-started refit, recon.diagnose.refit):
    its mesh, base colour, material maps (on its own texel grid, so the start renders exactly
    as the fit) and environment; no simplify + unwrap, no environment seeding, no warm-up."""
    settings, pbr = config.texture, config.pbr
    if effects is None:
        effects = geometry.effects or FitEffects(config.effects, len(captures.cameras), device)
    shading_effects = [module.name for module in effects.modules if module.stage == "shading"]
    if shading_effects:
        raise ReconError(
            f"fit.effects: {shading_effects} are shading effects of the Lambertian model; "
            "fit.material 'pbr' models specular reflection itself (drop them or use 'lambert')"
        )
    generator = torch.Generator().manual_seed(seed + 1)
    start = start_texture_stage(
        captures,
        geometry,
        config,
        device,
        checkpoint_path,
        resume,
        resolution,
        None if warm_start is None else warm_start.mesh.to(device),
    )
    mesh, coverage, start_step, checkpoint = (
        start.mesh,
        start.coverage,
        start.start_step,
        start.checkpoint,
    )
    cameras, images, masks = start.cameras, start.images, start.masks
    renderer, topology = start.renderer, start.topology
    preconditioner, latent = start.preconditioner, start.latent
    size = tuple(pbr.environment_size)
    base_color = torch.nn.Parameter(mesh.texture.clone())
    height, width = mesh.texture.shape[:2]
    initial = [max(pbr.initial_roughness, MINIMUM_ROUGHNESS), pbr.initial_metalness]
    # Roughness and metalness are seen only where a highlight falls: optimised on a coarser
    # grid (fit.pbr.material_texture_size) and upsampled, so every texel is constrained.
    material_size = pbr.material_texture_size or height
    material_shape = (material_size, round(material_size * width / height) or 1)
    material = torch.nn.Parameter(
        torch.tensor(initial, device=device).expand(*material_shape, 2).clone()
    )

    # The optional tangent-space normal map: its (x, y) on the base colour's grid, z >= 0 follows.
    normal_slopes = torch.nn.Parameter(
        torch.zeros(height, width, 2 if pbr.normal_map else 0, device=device)
    )
    if warm_start is not None:
        # The fitted maps on the base colour's grid (upsampled and dilated by the fit): the
        # refit starts from exactly the fitted material.
        material = torch.nn.Parameter(warm_start.material[..., :2].to(device).clone())
        if pbr.normal_map and warm_start.material.shape[-1] >= 5:
            normal_slopes.data.copy_(warm_start.material[..., 2:4].to(device))

    def full_material() -> torch.Tensor:
        """The material [h, w, 2] (or [h, w, 5] with the normal map) on the base colour's
        texel grid."""
        upsampled = material
        if material.shape[:2] != (height, width):
            upsampled = torch.nn.functional.interpolate(
                material.permute(2, 0, 1)[None], size=(height, width), mode="bilinear"
            )[0].permute(1, 2, 0)
        if not pbr.normal_map:
            return upsampled
        z = (1 - normal_slopes.square().sum(-1, keepdim=True)).clamp_min(1e-4).sqrt()
        return torch.cat([upsampled, normal_slopes, z], dim=-1)

    # A camera-frame light (turntable captures) seeds, and stays, a camera-frame environment.
    light_frame = config.light.frame
    if warm_start is not None:
        seed_environment = warm_start.environment.to(device)
    else:
        seed_environment = environment_from_light(geometry.light, size).to(device)
    if pbr.environment_seed == "highlights" and checkpoint is None and warm_start is None:
        seed_environment, base_scale = highlight_environment(
            renderer,
            mesh,
            cameras,
            images,
            masks,
            seed_environment,
            initial[0],
            pbr.specular_level,
            pbr.environment_seed_prior_weight,
            light_frame,
        )
        with torch.no_grad():
            base_color.mul_(base_scale).clamp_(0, 1)
    shadow = ShadowSettings(
        pbr.shadow_map_resolution,
        pbr.shadow_bias_texels,
        pbr.shadow_slope_bias_texels,
        pbr.shadow_softness_texels,
    )
    if pbr.sun_lights and light_frame != "world":
        raise ReconError(
            f"fit.pbr.sun_lights: {pbr.sun_lights} suns need a world-frame light (their shadow "
            f"maps are drawn in the world), but fit.light.frame is {light_frame!r}"
        )
    # The suns leave the map: the split-sum path would shade them without visibility and
    # through the SH's ringing irradiance (recon/optimize/sun_light.py). The geometry stage's
    # sun is the first (its lobe taken back out of the map), brightest spots the others.
    sun_directions, sun_irradiances = [], []
    if warm_start is not None and pbr.sun_lights:
        # A refit starts from the fitted suns: the fitted environment no longer holds them.
        for sun in warm_start.suns[: pbr.sun_lights]:
            sun_directions.append(sun.direction_to_light.detach().to(device))
            sun_irradiances.append(sun.irradiance.detach().to(device))
    elif pbr.sun_lights and geometry.light.with_sun:
        sun = geometry.light.lighting().directional[0]
        lobe = sun_lobe_environment(geometry.light, size).to(device)
        seed_environment = (seed_environment - lobe).clamp_min(ENVIRONMENT_FLOOR)
        sun_directions.append(sun.direction_to_light.detach().to(device))
        sun_irradiances.append(sun.irradiance.detach().to(device))
    fitted_suns = len(sun_directions) if warm_start is not None else 0
    while len(sun_directions) < pbr.sun_lights:
        seed_environment, direction, irradiance = split_sun(seed_environment, pbr.sun_cone_degrees)
        sun_directions.append(direction)
        sun_irradiances.append(irradiance)
    for index, direction in enumerate(sun_directions[fitted_suns:], start=fitted_suns):
        # A Lambertian geometry stage leaves most of a sun in its SH (the smooth lobe mimics
        # the irradiance): without this the environment keeps it, unshadowed.
        seed_environment, reclaimed = reclaim_sun(
            seed_environment, direction, pbr.sun_reclaim_share
        )
        seed_environment = seed_environment.clamp_min(ENVIRONMENT_FLOOR)
        sun_irradiances[index] = sun_irradiances[index] + reclaimed
    sun_direction = torch.nn.Parameter(
        torch.stack(sun_directions) if sun_directions else torch.zeros(0, 3, device=device)
    )
    sun_log_irradiance = torch.nn.Parameter(
        torch.stack(sun_irradiances).clamp_min(ENVIRONMENT_FLOOR).log()
        if sun_irradiances
        else torch.zeros(0, 3, device=device)
    )

    def current_suns() -> list[DirectionalLight]:
        return [
            DirectionalLight(
                torch.nn.functional.normalize(sun_direction[index], dim=0),
                sun_log_irradiance[index].exp(),
            )
            for index in range(pbr.sun_lights)
        ]

    # 'log': Adam's steps are relative, so a softbox 100x brighter than the room is reached in
    # as many steps as the room itself (linear steps of the learning rate would need hundreds).
    log_environment = pbr.environment_parameterization == "log"
    environment_parameter = torch.nn.Parameter(
        seed_environment.clamp_min(ENVIRONMENT_FLOOR).log() if log_environment else seed_environment
    )

    def current_environment() -> torch.Tensor:
        return environment_parameter.exp() if log_environment else environment_parameter

    position_optimizer = UniformAdam([latent], lr=settings.learning_rate)
    texture_optimizer = torch.optim.Adam(
        [
            {"params": [base_color], "lr": settings.texture_learning_rate},
            {"params": [material], "lr": pbr.material_learning_rate},
            {"params": [normal_slopes], "lr": pbr.material_learning_rate},
        ]
    )
    light_optimizer = torch.optim.Adam(
        [
            {"params": [environment_parameter], "lr": pbr.environment_learning_rate},
            {"params": [sun_direction, sun_log_irradiance], "lr": pbr.sun_learning_rate},
        ]
    )
    if checkpoint is not None:
        material.data.copy_(checkpoint["material"].to(device))
        if "normal_slopes" in checkpoint:  # checkpoints from before the normal map lack it
            normal_slopes.data.copy_(checkpoint["normal_slopes"].to(device))
        saved = checkpoint["environment"].to(device)
        if log_environment:
            saved = saved.clamp_min(ENVIRONMENT_FLOOR).log()
        environment_parameter.data.copy_(saved)
        if pbr.sun_lights:
            sun_direction.data.copy_(checkpoint["sun_direction"].to(device))
            sun_log_irradiance.data.copy_(checkpoint["sun_log_irradiance"].to(device))
        effects.load_state_dict(checkpoint["effects"])
        position_optimizer.load_state_dict(checkpoint["position_optimizer"])
        texture_optimizer.load_state_dict(checkpoint["texture_optimizer"])
        light_optimizer.load_state_dict(checkpoint["light_optimizer"])
        restore_random_states(checkpoint["random"], generator)

    def save(step: int, stage: str = "texture") -> None:
        save_checkpoint(
            checkpoint_path,
            {
                "stage": stage,
                "step": step,
                "material_model": "pbr",
                "verts": preconditioner.from_latent(latent).detach().cpu(),
                "latent": latent.detach().cpu(),
                "faces": mesh.faces.cpu(),
                "uvs": mesh.uvs.cpu(),
                "uv_faces": mesh.uv_faces.cpu(),
                "texture": base_color.detach().cpu(),
                "material": material.detach().cpu(),
                "normal_slopes": normal_slopes.detach().cpu(),
                "environment": current_environment().detach().cpu(),
                "sun_direction": sun_direction.detach().cpu(),
                "sun_log_irradiance": sun_log_irradiance.detach().cpu(),
                "coverage": coverage.cpu(),
                "position_optimizer": position_optimizer.state_dict(),
                "texture_optimizer": texture_optimizer.state_dict(),
                "light_optimizer": light_optimizer.state_dict(),
                "effects": effects.state_dict(),
                "random": random_states(generator),
            },
        )

    # After texture.steps split-sum steps, fit.pbr.lobe_steps shade the full lobe per pixel.
    total_steps = settings.steps + pbr.lobe_steps
    shadow_maps: list[ShadowMap] | None = None
    started = time.perf_counter()
    bar = tqdm(
        range(start_step, total_steps),
        desc="fit pbr texture",
        initial=start_step,
        total=total_steps,
        unit="step",
    )
    for step in bar:
        lobe = step >= settings.steps
        if lobe and step == max(start_step, settings.steps):
            # The refinement moves everything gently (fit.pbr.lobe_*): with one view per step the
            # full rates make the roughness jitter by +-0.04 from step to step.
            texture_optimizer.param_groups[0]["lr"] = (
                settings.texture_learning_rate * pbr.lobe_learning_rate_scale
            )
            for group in texture_optimizer.param_groups[1:]:
                group["lr"] = pbr.material_learning_rate * pbr.lobe_learning_rate_scale
            for group in light_optimizer.param_groups:
                group["lr"] = pbr.environment_learning_rate * pbr.lobe_learning_rate_scale
        views_per_step = pbr.lobe_views_per_step if lobe else settings.views_per_step
        views = sample_views(len(cameras), views_per_step, generator).to(device)
        verts = preconditioner.from_latent(latent)
        if lobe:
            # The full-lobe steps refine material and light on the settled shape: one view per
            # step and the samples' sensitivity to the normals move the vertices off it.
            verts = verts.detach()
        current = Mesh(verts, mesh.faces, uvs=mesh.uvs, uv_faces=mesh.uv_faces, texture=base_color)
        batch_cameras = apply_camera_effects(effects.modules, cameras[views], views)
        buffers = renderer.surface_buffers(current, batch_cameras, topology)
        texture = torch.cat([base_color, full_material()], dim=-1)
        environment = current_environment()
        shading_environment = prefilter_environment(environment, pbr.prefilter_levels)
        if lobe:
            # Fresh per-pixel shifts of the sample points each step: the lobe's sampling error
            # averages out over steps instead of biasing every step alike.
            shifts = torch.rand(
                int(buffers.fragments.covered_index.numel()), 2, generator=generator
            )
            shading_environment = SampledEnvironment(
                shading_environment, pbr.lobe_samples, pbr.lobe_filter_width, shifts.to(device)
            )
        suns = current_suns()
        if suns and (
            shadow_maps is None
            or (step - start_step) % pbr.shadow_map_every == 0
            or _sun_moved(shadow_maps, suns, shadow.resolution)
        ):
            # Redrawn every few steps (the vertices move little between them), and whenever a
            # sun has turned far enough to move its shadows by half a texel.
            shadow_maps = [
                ShadowMap.draw(verts.detach(), mesh.faces, sun.direction_to_light, shadow)
                for sun in suns
            ]
        output = renderer.shade_pbr(
            buffers,
            batch_cameras.centers(),
            texture,
            shading_environment,
            specular_level=pbr.specular_level,
            mip_pyramid=build_mip_pyramid(texture),
            diffuse_weighting=pbr.diffuse_weighting,
            light_frame=light_frame,
            directional=suns,
            directional_visibility=shadowed_suns(buffers, suns, shadow, shadow_maps),
        )
        color, alpha = apply_image_effects(
            effects.modules, output.color, output.alpha, batch_cameras, views
        )
        color_loss = image_loss(color, images[views])
        mask_loss = (alpha - masks[views]).abs().mean()
        regulariser = (
            settings.smoothness_weight * texture_total_variation(base_color)
            + pbr.material_smoothness_weight * texture_total_variation(material)
            + pbr.environment_smoothness_weight * texture_total_variation(environment)
            + pbr.environment_whiteness_weight
            * (environment - environment.mean(-1, keepdim=True)).abs().mean()
        )
        if pbr.normal_map:
            regulariser = regulariser + pbr.normal_map_smoothness_weight * (
                texture_total_variation(normal_slopes)
            )
        loss = color_loss + settings.mask_weight * mask_loss + regulariser
        position_optimizer.zero_grad()
        texture_optimizer.zero_grad()
        light_optimizer.zero_grad()
        effects.zero_grad()
        loss.backward()
        if not lobe:
            position_optimizer.step()
        if step < pbr.material_warmup_steps and warm_start is None:
            # The environment settles first around the starting roughness (docs/decisions/0180).
            material.grad = None
        texture_optimizer.step()
        light_optimizer.step()
        effects.step(1.0)
        with torch.no_grad():
            base_color.clamp_(0, 1)
            material[..., 0].clamp_(MINIMUM_ROUGHNESS, 1)
            material[..., 1].clamp_(0, 1)
            # Tilts up to about 55 degrees: a map that lays the normal flat explains nothing.
            normal_slopes.clamp_(-MAXIMUM_NORMAL_SLOPE, MAXIMUM_NORMAL_SLOPE)
            if not log_environment:
                environment_parameter.clamp_min_(0)
        if step % LOG_EVERY == 0 or step == total_steps - 1:
            record = step_record(
                "texture",
                step,
                {
                    "loss": loss,
                    "color_loss": color_loss,
                    "mask_loss": mask_loss,
                    # Followed through the run: the split sum trades it against the light's blur.
                    "roughness_median": material[..., 0].median(),
                },
                color,
                images[views],
                cameras.image_size,
                int(mesh.faces.shape[0]),
                time.perf_counter() - started,
            )
            history.log(record)
            bar.set_postfix(loss=f"{record['loss']:.4f}")
        if (step + 1) % config.checkpoint_every == 0:
            save(step + 1)
    bar.close()
    with torch.no_grad():
        final_base = dilate(base_color.detach(), coverage)
        final_material = dilate(full_material().detach(), coverage)
        final_environment = current_environment().detach().clone()
        final_suns = [
            DirectionalLight(sun.direction_to_light.detach(), sun.irradiance.detach())
            for sun in current_suns()
        ]
    final = Mesh(
        preconditioner.from_latent(latent).detach(),
        mesh.faces,
        uvs=mesh.uvs,
        uv_faces=mesh.uv_faces,
        texture=final_base,
    )
    save(total_steps, stage="texture_done")
    return PbrTextureResult(
        final,
        final_material,
        final_environment,
        light_from_environment(final_environment, light_frame, final_suns),
        pbr.specular_level,
        pbr.prefilter_levels,
        effects,
        pbr.diffuse_weighting,
        light_frame,
        pbr.lobe_samples if pbr.lobe_steps > 0 else 0,
        pbr.lobe_filter_width,
        final_suns,
        shadow,
    )
