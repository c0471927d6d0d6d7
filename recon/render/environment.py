"""Environment light for the split-sum approximation: a lat-long radiance map, its GGX
pre-filtered chain over roughness and its diffuse irradiance (Karis 2013).

Lat-long convention (the same as data_synth's environment maps and the fitted light's EXR):
image [h, w, C] linear radiance; row i is the polar angle theta = pi (i + 0.5) / h from +y (row 0
looks up), column j the azimuth phi = 2 pi (j + 0.5) / w, direction = (sin theta cos phi,
cos theta, sin theta sin phi).

Pre-filtering follows Karis' assumption n = v = r: the level of roughness r holds, for every
output direction r, the average of L(l) weighted by D(h) (n.l) over the hemisphere around r,
h = normalize(r + l), normalised by the sum of the weights. It is computed by brute force over
every texel (weights times solid angle), which is exact for the discrete map and cheap at the
small resolutions a fit uses; the weight matrices depend only on the sizes and are cached, so
pre-filtering is one matrix product per level and the map receives gradients. Level 0
(roughness 0) is the map itself. The diffuse term is the order-2 SH projection of the map
convolved with the clamped cosine (shading.sh_irradiance).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from recon.errors import ReconError
from recon.render.brdf import ggx_distribution, roughness_to_alpha
from recon.render.shading import DirectionalLight, sh_basis, sh_irradiance

_WEIGHT_CACHE: dict[tuple, torch.Tensor] = {}
_WEIGHT_CACHE_SIZE = 64


def latlong_directions(
    height: int, width: int, device: torch.device | str = "cpu", dtype=torch.float32
) -> tuple[torch.Tensor, torch.Tensor]:
    """Directions [h, w, 3] of texel centres and their exact solid angles [h, w] (sum 4 pi)."""
    theta = (torch.arange(height, dtype=torch.float64) + 0.5) * math.pi / height
    phi = (torch.arange(width, dtype=torch.float64) + 0.5) * 2 * math.pi / width
    theta, phi = torch.meshgrid(theta, phi, indexing="ij")
    directions = torch.stack(
        [torch.sin(theta) * torch.cos(phi), torch.cos(theta), torch.sin(theta) * torch.sin(phi)],
        dim=-1,
    )
    edges = torch.arange(height + 1, dtype=torch.float64) * math.pi / height
    band = (torch.cos(edges[:-1]) - torch.cos(edges[1:])) * (2 * math.pi / width)
    solid_angle = band[:, None].expand(height, width)
    return directions.to(device, dtype), solid_angle.to(device, dtype)


def sample_latlong(environment: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """Bilinear lookup of a lat-long map [h, w, C] at unit directions [..., 3] -> [..., C]:
    wraps in azimuth, clamps at the poles. Differentiable in the map and the directions."""
    return sample_latlong_at(environment, direction_angles(directions))


def direction_angles(directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Polar angle theta from +y and azimuth phi in [0, 2 pi) [...] of unit directions
    [..., 3] (the lat-long convention of this module)."""
    x, y, z = directions.unbind(-1)
    theta = torch.acos(y.clamp(-1 + 1e-6, 1 - 1e-6))
    phi = torch.atan2(z, x) % (2 * math.pi)
    return theta, phi


def sample_latlong_at(
    environment: torch.Tensor, angles: tuple[torch.Tensor, torch.Tensor]
) -> torch.Tensor:
    """sample_latlong at directions given by their direction_angles (theta, phi) [...], so
    that several maps are looked up along the same directions without recomputing them."""
    height, width, channels = environment.shape
    theta, phi = angles
    leading = theta.shape
    theta, phi = theta.reshape(-1), phi.reshape(-1)
    # One wrapped column on each side makes the azimuth seam bilinear too.
    padded = torch.cat([environment[:, -1:], environment, environment[:, :1]], dim=1)
    column = phi / (2 * math.pi) * width + 0.5  # texel-centre coordinates in the padded map
    row = theta / math.pi * height - 0.5
    grid = torch.stack([(column + 0.5) / (width + 2) * 2 - 1, (row + 0.5) / height * 2 - 1], dim=-1)
    sampled = F.grid_sample(
        padded.permute(2, 0, 1)[None],
        grid[None, None],
        mode="bilinear",
        padding_mode="border",
        align_corners=False,
    )  # [1, C, 1, N]
    return sampled[0, :, 0].transpose(0, 1).reshape(*leading, channels)


def add_suns(environment: torch.Tensor, suns: list[DirectionalLight]) -> torch.Tensor:
    """The environment [h, w, C] with each sun (direction_to_light [3], irradiance [C]) added as
    a bilinear splat of radiance over the four texels around its direction: the splat's integral
    over solid angle is the sun's irradiance, so a renderer that reads only the map (the exported
    EXR) receives the same light as the fit's separate, shadowed suns. Not differentiable."""
    height, width, _ = environment.shape
    combined = environment.detach().clone()
    _, solid_angle = latlong_directions(height, width, environment.device, environment.dtype)
    for sun in suns:
        direction = F.normalize(sun.direction_to_light.detach().to(environment), dim=0)
        theta, phi = direction_angles(direction)
        row = float(theta) / math.pi * height - 0.5
        column = float(phi) / (2 * math.pi) * width - 0.5
        row_low, column_low = math.floor(row), math.floor(column)
        row_share, column_share = row - row_low, column - column_low
        for row_step, row_weight in ((0, 1 - row_share), (1, row_share)):
            # Beyond the first or last row's centre the sun stays on that row (the pole cap).
            target_row = min(max(row_low + row_step, 0), height - 1)
            for column_step, column_weight in ((0, 1 - column_share), (1, column_share)):
                target_column = (column_low + column_step) % width
                weight = row_weight * column_weight
                radiance = sun.irradiance.detach().to(environment) * weight
                combined[target_row, target_column] += (
                    radiance / solid_angle[target_row, target_column]
                )
    return combined


def prefilter_weights(
    input_size: tuple[int, int],
    output_size: tuple[int, int],
    roughness: float,
    device: torch.device | str = "cpu",
    dtype=torch.float32,
) -> torch.Tensor:
    """Row-normalised weights [h_out * w_out, h_in * w_in]: D(h) max(0, r.l) dOmega(l) with
    h = normalize(r + l), n = v = r (Karis 2013), for one roughness level. Cached."""
    key = (input_size, output_size, float(roughness), str(torch.device(device)), dtype)
    weights = _WEIGHT_CACHE.get(key)
    if weights is not None:
        return weights
    inputs, solid_angle = latlong_directions(*input_size, dtype=torch.float64)
    outputs, _ = latlong_directions(*output_size, dtype=torch.float64)
    inputs, solid_angle, outputs = (
        inputs.reshape(-1, 3),
        solid_angle.reshape(-1),
        outputs.reshape(-1, 3),
    )
    alpha = roughness_to_alpha(torch.tensor(float(roughness), dtype=torch.float64))
    cosine = outputs @ inputs.T  # r.l: [O, I]
    # n.h with h = (r + l) / |r + l| and |r + l| = sqrt(2 + 2 r.l).
    n_dot_h = (1 + cosine) / torch.sqrt((2 + 2 * cosine).clamp_min(1e-12))
    weights = ggx_distribution(n_dot_h, alpha) * cosine.clamp_min(0) * solid_angle
    totals = weights.sum(-1, keepdim=True)
    # A lobe narrower than a texel can miss every centre: fall back to the nearest texel.
    nearest = torch.nn.functional.one_hot(cosine.argmax(-1), inputs.shape[0]).double()
    weights = torch.where(totals > 1e-12, weights / totals.clamp_min(1e-300), nearest)
    weights = weights.to(device, dtype)
    if len(_WEIGHT_CACHE) >= _WEIGHT_CACHE_SIZE:
        _WEIGHT_CACHE.pop(next(iter(_WEIGHT_CACHE)))
    _WEIGHT_CACHE[key] = weights
    return weights


def level_size(input_size: tuple[int, int], roughness: float) -> tuple[int, int]:
    """Output resolution of a pre-filtered level: a texel (pi / h radians) no wider than half
    the reflected lobe's half width (about 1.3 alpha), at most the input's, at least 8 x 16
    (bilinear lookups of coarser levels err by several percent even on smooth light)."""
    alpha = float(roughness_to_alpha(torch.tensor(float(roughness))))
    height = min(input_size[0], max(8, math.ceil(math.pi / (0.65 * alpha))))
    return height, max(2 * height, round(height * input_size[1] / input_size[0]))


@dataclass
class PrefilteredEnvironment:
    """A lat-long environment ready for split-sum shading.

    levels: K maps [h_k, w_k, C], level k pre-filtered for roughness roughness[k] (level 0 is
    the map itself, roughness 0). roughness: [K] increasing, from 0 to 1.
    sh_coefficients: [9, C] order-2 SH of the radiance, for the diffuse irradiance.
    """

    levels: list[torch.Tensor]
    roughness: torch.Tensor
    sh_coefficients: torch.Tensor

    def specular(self, directions: torch.Tensor, roughness: torch.Tensor) -> torch.Tensor:
        """Pre-filtered radiance [..., C] along reflection directions [..., 3] at roughness
        [..., 1]: bilinear in each level, linear between the two levels around the roughness."""
        knots = self.roughness.to(roughness.dtype)
        clamped = roughness.clamp(0, 1)
        # Hat-function weights in roughness: only the two neighbouring levels are non-zero.
        spacing_left = torch.cat([knots[1:2] - knots[0:1], knots[1:] - knots[:-1]])
        spacing_right = torch.cat([knots[1:] - knots[:-1], knots[-1:] - knots[-2:-1]])
        offset = clamped - knots  # [..., K]
        weights = torch.where(
            offset < 0, 1 + offset / spacing_left, 1 - offset / spacing_right
        ).clamp_min(0)
        leading = directions.shape[:-1]
        theta, phi = direction_angles(directions.reshape(-1, 3))
        weights = weights.reshape(theta.shape[0], -1)
        result = directions.new_zeros(theta.shape[0], self.levels[0].shape[-1])
        for index, level in enumerate(self.levels):
            weight = weights[:, index : index + 1]
            used = weight[:, 0] > 0
            if bool(used.all()):
                result = result + weight * sample_latlong_at(level, (theta, phi))
            elif bool(used.any()):
                # Only the look-ups between this level and a neighbour (most of them skip it).
                rows = used.nonzero()[:, 0]
                sampled = sample_latlong_at(level, (theta[rows], phi[rows])) * weight[rows]
                result = result.index_add(0, rows, sampled)
        return result.reshape(*leading, -1)

    def irradiance(self, normals: torch.Tensor) -> torch.Tensor:
        """Diffuse irradiance E(n) [..., C] at unit normals [..., 3]."""
        return sh_irradiance(normals, self.sh_coefficients)


def project_to_sh(environment: torch.Tensor) -> torch.Tensor:
    """Order-2 SH coefficients [9, C] of a lat-long radiance map [h, w, C] (differentiable)."""
    height, width, channels = environment.shape
    directions, solid_angle = latlong_directions(
        height, width, environment.device, environment.dtype
    )
    basis = sh_basis(directions.reshape(-1, 3)) * solid_angle.reshape(-1, 1)
    return basis.T @ environment.reshape(-1, channels)


def prefilter_environment(
    environment: torch.Tensor, level_count: int = 8
) -> PrefilteredEnvironment:
    """Pre-filter a lat-long map [h, w, C] into level_count + 1 levels at roughness
    linspace(0, 1, level_count + 1), plus its SH projection. Differentiable in the map."""
    if environment.ndim != 3 or environment.shape[0] < 2 or environment.shape[1] < 2:
        raise ReconError(
            f"environment: expected a lat-long map [h, w, C] with h, w >= 2, got "
            f"{tuple(environment.shape)}"
        )
    if level_count < 1:
        raise ReconError(f"environment: level_count must be >= 1, got {level_count}")
    height, width, channels = environment.shape
    roughness = torch.linspace(0, 1, level_count + 1)
    levels = [environment]
    flat = environment.reshape(-1, channels)
    for value in roughness[1:].tolist():
        size = level_size((height, width), value)
        weights = prefilter_weights(
            (height, width), size, value, environment.device, environment.dtype
        )
        levels.append((weights @ flat).reshape(*size, channels))
    return PrefilteredEnvironment(
        levels, roughness.to(environment.device), project_to_sh(environment)
    )
