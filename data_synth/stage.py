"""The synth stage: render the reference scene from the capture rig into a dataset folder.

Writes, in the run folder: dataset/ (NeRF-synthetic layout: transforms_{split}.json, RGBA PNG and
linear EXR per view), ground_truth/ beside it (reference mesh, lighting, injected effects) and a
contact sheet of the training views.
"""

from __future__ import annotations

import torch
from tqdm import tqdm

from data_synth.rigs import make_cameras
from data_synth.scene import build_lighting, build_mesh, lighting_to_json
from recon.camera import Cameras
from recon.config.run_config import RunConfig
from recon.io.atomic import atomic_write_json
from recon.io.datasets import write_nerf_synthetic
from recon.io.images import save_contact_sheet
from recon.io.meshes import save_mesh
from recon.mesh.mesh import Mesh
from recon.render.antialias import build_topology
from recon.render.renderer import Renderer
from recon.render.shading import Lighting

# Views rendered per batch: bounds memory at large resolutions.
VIEWS_PER_BATCH = 8
SPLIT_ORDER = ("train", "val", "test")


def render_views(
    mesh: Mesh, cameras: Cameras, lighting: Lighting, description: str
) -> tuple[torch.Tensor, torch.Tensor]:
    """Premultiplied linear colour [B, H, W, 3] and coverage [B, H, W, 1], with a progress bar."""
    renderer = Renderer()
    topology = build_topology(mesh.faces, mesh.verts.shape[0])
    colors, alphas = [], []
    with torch.no_grad():
        for start in tqdm(
            range(0, len(cameras), VIEWS_PER_BATCH),
            desc=description,
            unit="batch",
            leave=False,
        ):
            output = renderer.render(
                mesh, cameras[start : start + VIEWS_PER_BATCH], lighting, topology=topology
            )
            colors.append(output.color.clamp_min(0).cpu())
            alphas.append(output.alpha.clamp(0, 1).cpu())
    return torch.cat(colors), torch.cat(alphas)


def synth_stage(config: RunConfig, paths, device: torch.device) -> dict:
    """Entry point 'synth' of the recon.stages group."""
    generator = torch.Generator().manual_seed(config.seed)
    mesh = build_mesh(config.scene).to(device)
    lighting = build_lighting(config.scene.lighting).to(device)
    capture = config.capture
    counts = {"train": capture.train_views, "val": capture.val_views, "test": capture.test_views}
    summary = {}
    sheet_images = []
    for offset, split in enumerate(SPLIT_ORDER):
        if counts[split] == 0:
            continue
        cameras = make_cameras(capture.cameras, counts[split], generator, offset=offset)
        colors, alphas = render_views(mesh, cameras.to(device), lighting, f"synth {split}")
        background = torch.tensor(capture.background)
        composited = colors + (1 - alphas) * background
        write_nerf_synthetic(
            paths.dataset,
            split,
            cameras,
            colors,
            alphas,
            write_exr=capture.write_exr,
        )
        summary[split] = len(cameras)
        if split == "train":
            sheet_images = list(composited[:16])
    if capture.contact_sheet and sheet_images:
        save_contact_sheet(sheet_images, paths.contact_sheet, columns=4)
    paths.ground_truth.mkdir(parents=True, exist_ok=True)
    save_mesh(paths.ground_truth / "reference.obj", mesh.to("cpu"))
    atomic_write_json(paths.ground_truth / "lighting.json", lighting_to_json(lighting))
    atomic_write_json(paths.ground_truth / "effects.json", {"effects": []})
    return summary
