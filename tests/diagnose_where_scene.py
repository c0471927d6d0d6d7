"""The where/gap test scene shared by the diagnosis tests: a textured torus rendered by recon's
Renderer as the fitted scene ("rendered"), and helpers that apply one known effect to it with
plain torch ops ("observed")."""

from __future__ import annotations

import math
from pathlib import Path

import torch

from data_synth.shapes import torus
from recon.camera import orbit_cameras
from recon.config.run_config import DiagnoseConfig
from recon.diagnose.data import DiagnosisData, build_diagnosis_data
from recon.diagnose.domains import DOMAINS
from recon.render.renderer import Renderer, RenderOutput
from recon.render.shading import DirectionalLight, Lighting

REPO_ROOT = Path(__file__).resolve().parents[2]
SIZE = 48
SETTINGS = DiagnoseConfig()
VIEWS = 6
SUN_DIRECTION = (0.4, 0.8, 0.5)
# A little sensor noise on every "observed" image, so no test relies on an exact residual.
BACKGROUND_NOISE = 0.003
# Domains that localise an effect; frequency only says structured or white.
LOCATING = [domain for domain in DOMAINS if domain != "frequency"]


class Scene:
    """The 'fitted' scene: a textured torus under a sun, and its render from VIEWS cameras."""

    def __init__(self) -> None:
        mesh = torus(resolution=24)
        steps = torch.linspace(0, 1, 64)
        u, v = torch.meshgrid(steps, steps, indexing="xy")
        # A smooth pattern: texture edges exist but are not sharper than a pixel or two.
        pattern = 0.5 + 0.35 * torch.sin(2 * math.pi * 3 * u) * torch.sin(2 * math.pi * 2 * v)
        mesh.texture = torch.stack([pattern, 0.8 * pattern + 0.1, 0.6 * (1 - pattern) + 0.2], -1)
        self.mesh = mesh
        self.cameras = orbit_cameras(
            VIEWS, (SIZE, SIZE), distance=2.6, fov_x_deg=40, elevation_deg=30
        )
        self.lighting = sun_lighting(1.0)
        self.output = render(self)

    def data(self, observed: torch.Tensor, alpha: torch.Tensor | None = None) -> DiagnosisData:
        alpha = self.output.alpha if alpha is None else alpha
        return build_diagnosis_data(
            observed, alpha, self.output, self.cameras, self.lighting, self.mesh
        )


def sun_lighting(sun_scale: float) -> Lighting:
    lighting = Lighting.constant(0.35)
    irradiance = torch.tensor([1.6, 1.5, 1.4]) * sun_scale
    lighting.directional = [DirectionalLight(torch.tensor(SUN_DIRECTION), irradiance)]
    return lighting


def render(scene: Scene, lighting: Lighting | None = None) -> RenderOutput:
    lighting = scene.lighting if lighting is None else lighting
    return Renderer(texture_filter="linear").render(scene.mesh, scene.cameras, lighting)


def make_scene() -> Scene:
    torch.set_num_threads(1)
    return Scene()


def noisy(image: torch.Tensor, sigma: float = BACKGROUND_NOISE, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return image + sigma * torch.randn(image.shape, generator=generator)


def gaussian_blur(image: torch.Tensor, sigma: float) -> torch.Tensor:
    """[B, H, W, C] blurred by a separable Gaussian (zero padding, like a lens on black)."""
    radius = math.ceil(3 * sigma)
    offsets = torch.arange(-radius, radius + 1, dtype=torch.float32)
    kernel = torch.exp(-(offsets**2) / (2 * sigma**2))
    kernel = kernel / kernel.sum()
    planes = image.permute(0, 3, 1, 2)
    channels = planes.shape[1]
    horizontal = kernel.view(1, 1, 1, -1).repeat(channels, 1, 1, 1)
    vertical = kernel.view(1, 1, -1, 1).repeat(channels, 1, 1, 1)
    planes = torch.nn.functional.conv2d(planes, horizontal, padding=(0, radius), groups=channels)
    planes = torch.nn.functional.conv2d(planes, vertical, padding=(radius, 0), groups=channels)
    return planes.permute(0, 2, 3, 1)


def radial_vignetting(height: int, width: int, strength: float = 0.6) -> torch.Tensor:
    """[1, H, W, 1] falloff 1 - strength r^2 (r = 1 at the image corner)."""
    rows, columns = torch.meshgrid(
        torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij"
    )
    radius_squared = ((columns - width / 2) ** 2 + (rows - height / 2) ** 2) / (
        (width / 2) ** 2 + (height / 2) ** 2
    )
    return (1 - strength * radius_squared)[None, :, :, None]


def scores(analysis: dict) -> dict[str, float]:
    return {domain: analysis[domain]["score"] for domain in DOMAINS}
