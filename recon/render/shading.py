"""Lambertian shading under spherical-harmonic environment light plus directional lights.

Light is described by the SH coefficients of the incident radiance L(w) = sum_lm c_lm Y_lm(w)
(real SH, bands 0..2, 9 coefficients per channel). A Lambertian surface with albedo rho reflects
rho / pi * E(n), where the irradiance E(n) = sum_lm A_l c_lm Y_lm(n) with the clamped-cosine
convolution weights A_0 = pi, A_1 = 2 pi / 3, A_2 = pi / 4 (Ramamoorthi and Hanrahan 2001).
A constant environment of radiance 1 therefore has c_00 = sqrt(4 pi) and shades albedo as is.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import torch

from recon.errors import ReconError

SH_COEFFICIENT_COUNT = 9
# Clamped-cosine convolution weight per coefficient (band 0, three of band 1, five of band 2).
_BAND_WEIGHTS = (math.pi,) + (2 * math.pi / 3,) * 3 + (math.pi / 4,) * 5


def sh_basis(directions: torch.Tensor) -> torch.Tensor:
    """Real SH basis Y_lm up to band 2: [..., 3] unit directions -> [..., 9].

    Order: Y00, Y1-1 (y), Y10 (z), Y11 (x), Y2-2 (xy), Y2-1 (yz), Y20, Y21 (xz), Y22 (x^2-y^2).
    """
    x, y, z = directions.unbind(-1)
    return torch.stack(
        [
            torch.full_like(x, 0.28209479177387814),
            0.4886025119029199 * y,
            0.4886025119029199 * z,
            0.4886025119029199 * x,
            1.0925484305920792 * x * y,
            1.0925484305920792 * y * z,
            0.31539156525252005 * (3 * z * z - 1),
            1.0925484305920792 * x * z,
            0.5462742152960396 * (x * x - y * y),
        ],
        dim=-1,
    )


def sh_irradiance(normals: torch.Tensor, sh_coefficients: torch.Tensor) -> torch.Tensor:
    """Irradiance E(n) [..., C] for unit normals [..., 3] and radiance SH coefficients [9, C]."""
    if sh_coefficients.ndim != 2 or sh_coefficients.shape[0] != SH_COEFFICIENT_COUNT:
        raise ReconError(
            f"sh_coefficients: expected shape [9, C], got {tuple(sh_coefficients.shape)}"
        )
    weights = torch.tensor(_BAND_WEIGHTS, dtype=normals.dtype, device=normals.device)
    return sh_basis(normals) @ (sh_coefficients * weights[:, None])


@dataclass
class DirectionalLight:
    """A distant light: direction_to_light [3] (world, toward the light), irradiance [C]."""

    direction_to_light: torch.Tensor
    irradiance: torch.Tensor


@dataclass
class PointLight:
    """A small emitter at position [3] (world) with intensity [C] (W/sr-like units).

    emitter_normal [3] or None: a one-sided area light approximated at its centre; it emits
    intensity * max(0, cos) toward the half-space its normal faces (None = isotropic bulb).
    """

    position: torch.Tensor
    intensity: torch.Tensor
    emitter_normal: torch.Tensor | None = None


@dataclass
class Lighting:
    """SH environment [9, C] plus optional directional and point lights (world space)."""

    sh_coefficients: torch.Tensor
    directional: list[DirectionalLight] = field(default_factory=list)
    points: list[PointLight] = field(default_factory=list)
    # 'world': directions, positions and the environment are in world space. 'camera': they
    # are in each view's OpenCV camera axes (x right, y down, z forward): a light fixed to the
    # camera, as in a turntable capture; Renderer.shade turns the normals into camera axes.
    frame: str = "world"

    def __post_init__(self) -> None:
        if self.frame not in ("world", "camera"):
            raise ReconError(f"lighting.frame: expected 'world' or 'camera', got {self.frame!r}")

    @staticmethod
    def constant(radiance: float | list[float] = 1.0, channels: int = 3, device="cpu") -> Lighting:
        """A uniform environment of the given radiance (per channel)."""
        values = torch.as_tensor(radiance, dtype=torch.float32, device=device).expand(channels)
        sh = torch.zeros(SH_COEFFICIENT_COUNT, channels, device=device)
        sh[0] = values * math.sqrt(4 * math.pi)
        return Lighting(sh_coefficients=sh)

    @staticmethod
    def from_json(data: dict, device: torch.device | str = "cpu") -> Lighting:
        """The lighting of a lighting JSON record (the fitted light's light.json, data_synth's
        ground_truth/lighting.json or a dataset's lighting_relight.json): sh_coefficients
        [9][C], directional [{direction_to_light, irradiance}], points [{position, intensity,
        emitter_normal}] (optional), frame ('world' or 'camera'; default 'world'). Other keys (area lights, an environment map's file) are
        not part of recon's shading and are ignored."""

        def tensor(values) -> torch.Tensor:
            return torch.tensor(values, dtype=torch.float32, device=device)

        return Lighting(
            sh_coefficients=tensor(data["sh_coefficients"]),
            directional=[
                DirectionalLight(tensor(light["direction_to_light"]), tensor(light["irradiance"]))
                for light in data.get("directional", [])
            ],
            points=[
                PointLight(
                    tensor(light["position"]),
                    tensor(light["intensity"]),
                    None
                    if light.get("emitter_normal") is None
                    else tensor(light["emitter_normal"]),
                )
                for light in data.get("points", [])
            ],
            frame=data.get("frame", "world"),
        )

    def to(self, device: torch.device | str) -> Lighting:
        return self._map(lambda tensor: tensor.to(device))

    def detached(self) -> Lighting:
        """The same light without autograd history."""
        return self._map(torch.Tensor.detach)

    def _map(self, function) -> Lighting:
        """A copy with `function` applied to every tensor."""
        return replace(
            self,
            sh_coefficients=function(self.sh_coefficients),
            directional=[
                DirectionalLight(function(d.direction_to_light), function(d.irradiance))
                for d in self.directional
            ],
            points=[
                PointLight(
                    function(p.position),
                    function(p.intensity),
                    None if p.emitter_normal is None else function(p.emitter_normal),
                )
                for p in self.points
            ],
        )


def lambertian(
    albedo: torch.Tensor,
    normals: torch.Tensor,
    lighting: Lighting,
    positions: torch.Tensor | None = None,
) -> torch.Tensor:
    """Outgoing linear radiance rho / pi * E(n) (no shadows).

    albedo [..., C], unit normals [..., 3], positions [..., 3] world points (needed only for
    point lights: irradiance I cos / d^2).
    """
    irradiance = sh_irradiance(normals, lighting.sh_coefficients)
    for light in lighting.directional:
        direction = torch.nn.functional.normalize(light.direction_to_light, dim=-1)
        cosine = (normals * direction).sum(-1, keepdim=True).clamp_min(0)
        irradiance = irradiance + cosine * light.irradiance
    if lighting.points and positions is None:
        raise ReconError("lambertian: point lights need the shaded positions")
    for light in lighting.points:
        to_light = light.position - positions
        distance_squared = (to_light * to_light).sum(-1, keepdim=True).clamp_min(1e-12)
        direction = to_light / distance_squared.sqrt()
        cosine = (normals * direction).sum(-1, keepdim=True).clamp_min(0)
        emitted = light.intensity
        if light.emitter_normal is not None:
            facing = -(direction * light.emitter_normal).sum(-1, keepdim=True)
            emitted = emitted * facing.clamp_min(0)
        irradiance = irradiance + cosine * emitted / distance_squared
    return albedo * irradiance / math.pi
