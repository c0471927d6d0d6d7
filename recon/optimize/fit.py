"""The fit as one function of captures: geometry stage (remeshing) -> simplify -> unwrap + bake
-> texture stage (fit.material 'lambert') or material stage ('pbr').

The run folder (where the captures come from, where checkpoints and the fitted scene go) is the
fit stage's business, recon/stages/fit.py; here the checkpoint files are plain paths.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import torch

from recon.config.run_config import FitConfig
from recon.io.datasets import CaptureSet
from recon.optimize.checkpoint import History, load_checkpoint
from recon.optimize.geometry_stage import run_geometry_stage
from recon.optimize.material_stage import PbrTextureResult
from recon.optimize.scene_model import LightModel
from recon.optimize.texture_stage import TextureResult, run_texture_stage
from recon.render.shading import Lighting, sh_basis

ENVIRONMENT_SIZE = (64, 128)
# Half-size of the visual hull's grid over the normalised object's half-size.
HULL_MARGIN = 1.5


@dataclass(frozen=True)
class FitCheckpoints:
    """The fit's two checkpoint files: the geometry stage's and the texture (or pbr) stage's."""

    geometry: Path
    texture: Path

    def resume_point(self) -> tuple[str, int] | None:
        """(stage, last step) of the newest checkpoint, for History's truncate_after; None when
        there is none."""
        state = load_checkpoint(self.texture) or load_checkpoint(self.geometry)
        if state is None:
            return None
        stage = "texture" if state["stage"].startswith("texture") else "geometry"
        return stage, state["step"] - 1


def fit_scene(
    captures: CaptureSet,
    config: FitConfig,
    device: torch.device,
    seed: int,
    checkpoints: FitCheckpoints,
    history: History,
    resume: bool = False,
    hull_radius: float | None = None,
) -> TextureResult | PbrTextureResult:
    """Fit a textured mesh and a light to captures (cameras in the frame the fit works in).

    resume: continue from the checkpoints. hull_radius: half-size of the visual hull's carving
    grid (None: visual_hull's default).
    """
    geometry = run_geometry_stage(
        captures,
        config,
        device,
        seed,
        checkpoints.geometry,
        history,
        resume=resume,
        hull_radius=hull_radius,
    )
    texture_resume = resume and checkpoints.texture.exists()
    if config.material == "pbr":
        # The pbr material (base colour, roughness, metalness, environment map): its own stage,
        # recon/optimize/material_stage.py.
        from recon.optimize.material_stage import run_pbr_texture_stage

        return run_pbr_texture_stage(
            captures,
            geometry,
            config,
            device,
            seed,
            checkpoints.texture,
            history,
            resume=texture_resume,
        )
    return run_texture_stage(
        captures,
        geometry,
        config,
        device,
        seed,
        checkpoints.texture,
        history,
        resume=texture_resume,
    )


def environment_map_from_light(light: LightModel, size=ENVIRONMENT_SIZE) -> torch.Tensor:
    """The fitted SH radiance on an equirectangular grid [h, w, 3] (row 0 looks up; azimuth from
    +x toward +z), for viewing the light in any HDR viewer."""
    height, width = size
    theta = (torch.arange(height) + 0.5) * torch.pi / height
    phi = (torch.arange(width) + 0.5) * 2 * torch.pi / width
    theta, phi = torch.meshgrid(theta, phi, indexing="ij")
    directions = torch.stack(
        [torch.sin(theta) * torch.cos(phi), torch.cos(theta), torch.sin(theta) * torch.sin(phi)], -1
    )
    return (sh_basis(directions) @ light.sh.detach().cpu()).clamp_min(0)


def read_fitted_light(light_file: Path, device: torch.device) -> Lighting:
    """A fitted light record (light/light.json of a run) as recon Lighting."""
    return Lighting.from_json(json.loads(Path(light_file).read_text()), device)
