"""What a fit optimises: geometry, albedo (per vertex or UV texture) and lighting, plus the
training data pyramid and the losses. Shared by the geometry and texture stages."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from recon.camera import Cameras
from recon.io.datasets import CaptureSet
from recon.io.images import linear_to_srgb
from recon.render.shading import SH_COEFFICIENT_COUNT, DirectionalLight, Lighting


class FitEffects:
    """The optional effect modules of a fit's forward model (config fit.effects; none by
    default), with their own optimizer, learning rates and lock fractions."""

    def __init__(self, names: list[str], view_count: int, device: torch.device) -> None:
        from recon.effects.registry import make_effect

        self.modules = [make_effect(name, view_count=view_count).to(device) for name in names]
        groups = [group for module in self.modules for group in module.parameter_groups()]
        self.optimizer = torch.optim.Adam(groups) if groups else None

    def zero_grad(self) -> None:
        if self.optimizer is not None:
            self.optimizer.zero_grad()

    def step(self, progress: float) -> None:
        """One optimizer step; effects still inside their lock fraction keep their values."""
        if self.optimizer is None:
            return
        for module in self.modules:
            if module.is_locked(progress):
                for parameter in module.parameters():
                    parameter.grad = None
        self.optimizer.step()

    def state_dict(self) -> dict:
        return {
            "modules": [module.state_dict() for module in self.modules],
            "optimizer": None if self.optimizer is None else self.optimizer.state_dict(),
        }

    def to_json(self) -> dict:
        """The fitted effects for the run folder (effects.json): name, view count and each
        parameter's values, enough for from_json to rebuild them for rendering."""
        return {
            "effects": [
                {
                    "name": module.name,
                    "view_count": module.view_count,
                    "parameters": {
                        key: value.detach().cpu().tolist()
                        for key, value in module.state_dict().items()
                    },
                    "summary": module.parameters_summary(),
                }
                for module in self.modules
            ]
        }

    @staticmethod
    def modules_from_json(data: dict, device: torch.device) -> list:
        """The effect modules [ModelEffect] of a to_json record, on device, for rendering."""
        from recon.effects.registry import make_effect

        modules = []
        for record in data.get("effects", []):
            module = make_effect(record["name"], view_count=record.get("view_count"))
            state = {
                key: torch.as_tensor(value, dtype=torch.float32)
                for key, value in record["parameters"].items()
            }
            module.load_state_dict(state)
            modules.append(module.to(device))
        return modules

    def load_state_dict(self, state: dict) -> None:
        for module, module_state in zip(self.modules, state["modules"], strict=True):
            module.load_state_dict(module_state)
        if self.optimizer is not None and state["optimizer"] is not None:
            self.optimizer.load_state_dict(state["optimizer"])


class LightModel(torch.nn.Module):
    """SH environment [9, 3] plus an optional sun (direction, log irradiance)."""

    def __init__(self, ambient: float = 1.0, with_sun: bool = True, frame: str = "world") -> None:
        """frame: 'world', or 'camera' for a light fixed to the camera (config fit.light)."""
        super().__init__()
        self.frame = frame
        sh = torch.zeros(SH_COEFFICIENT_COUNT, 3)
        sh[0] = ambient * math.sqrt(4 * math.pi)
        self.sh = torch.nn.Parameter(sh)
        self.with_sun = with_sun
        self.sun_direction = torch.nn.Parameter(torch.tensor([0.3, 0.8, 0.4]))
        self.sun_log_irradiance = torch.nn.Parameter(torch.full((3,), math.log(0.3)))

    @classmethod
    def from_lighting(cls, lighting: Lighting) -> LightModel:
        """A trainable model holding `lighting` (SH plus at most one sun), on its device."""
        light = cls(with_sun=bool(lighting.directional), frame=lighting.frame)
        with torch.no_grad():
            light.sh.copy_(lighting.sh_coefficients)
            if lighting.directional:
                sun = lighting.directional[0]
                light.sun_direction.copy_(sun.direction_to_light)
                light.sun_log_irradiance.copy_(sun.irradiance.clamp_min(1e-6).log())
        return light.to(lighting.sh_coefficients.device)

    def lighting(self) -> Lighting:
        directional = []
        if self.with_sun:
            directional.append(
                DirectionalLight(
                    torch.nn.functional.normalize(self.sun_direction, dim=0),
                    self.sun_log_irradiance.exp(),
                )
            )
        return Lighting(sh_coefficients=self.sh, directional=directional, frame=self.frame)

    def to_json(self) -> dict:
        lighting = self.lighting()
        return {
            "sh_coefficients": lighting.sh_coefficients.detach().cpu().tolist(),
            "directional": [
                {
                    "direction_to_light": light.direction_to_light.detach().cpu().tolist(),
                    "irradiance": light.irradiance.detach().cpu().tolist(),
                }
                for light in lighting.directional
            ],
            "frame": self.frame,
        }


@dataclass
class TrainingPyramid:
    """The training captures at each resolution of a coarse-to-fine schedule.

    levels[i] = (cameras at that size, images [B, h, w, 3] premultiplied linear, masks).
    """

    levels: list[tuple[Cameras, torch.Tensor, torch.Tensor]]
    resolutions: list[int]

    @staticmethod
    def build(
        captures: CaptureSet, resolutions: list[int], device: torch.device
    ) -> TrainingPyramid:
        height, width = captures.cameras.image_size
        levels = []
        used = []
        for resolution in resolutions:
            scale = min(1.0, resolution / max(height, width))
            size = (max(1, round(height * scale)), max(1, round(width * scale)))
            if used and size == levels[-1][0].image_size:
                continue
            images = captures.images.permute(0, 3, 1, 2)
            masks = captures.masks.permute(0, 3, 1, 2)
            if size != (height, width):
                # Area averaging keeps the images what a coarser camera would integrate.
                images = torch.nn.functional.interpolate(images, size=size, mode="area")
                masks = torch.nn.functional.interpolate(masks, size=size, mode="area")
            levels.append(
                (
                    captures.cameras.with_image_size(size).to(device),
                    images.permute(0, 2, 3, 1).contiguous().to(device),
                    masks.permute(0, 2, 3, 1).contiguous().to(device),
                )
            )
            used.append(resolution)
        return TrainingPyramid(levels, used)

    def level_for(self, progress: float) -> int:
        """Equal shares of the steps per level."""
        return min(len(self.levels) - 1, int(progress * len(self.levels)))


def texture_total_variation(texture: torch.Tensor) -> torch.Tensor:
    """Mean absolute difference of neighbouring texels [h, w, C] (keeps texels that few views
    see from speckling). A side of one texel adds 0 (not the NaN of an empty mean)."""
    total = texture.new_zeros(())
    if texture.shape[0] > 1:
        total = total + (texture[1:] - texture[:-1]).abs().mean()
    if texture.shape[1] > 1:
        total = total + (texture[:, 1:] - texture[:, :-1]).abs().mean()
    return total


def image_loss(prediction: torch.Tensor, target: torch.Tensor, kind: str = "l1") -> torch.Tensor:
    """L1 in linear radiance, or in log-sRGB (more weight on dark regions)."""
    if kind == "log_srgb_l1":
        prediction = torch.log1p(linear_to_srgb(prediction.clamp_min(0)))
        target = torch.log1p(linear_to_srgb(target.clamp_min(0)))
    return (prediction - target).abs().mean()


def step_record(
    stage: str,
    step: int,
    losses: dict[str, torch.Tensor],
    prediction: torch.Tensor,
    target: torch.Tensor,
    resolution: tuple[int, int],
    faces: int,
    seconds: float,
) -> dict:
    """One history.jsonl record: the losses, training PSNR (linear), resolution, face count."""
    mse = float(((prediction.detach() - target) ** 2).mean())
    record = {"stage": stage, "step": step}
    record.update({name: float(value.detach()) for name, value in losses.items()})
    record.update(
        {
            "psnr_linear": psnr_from_mse(mse),
            "resolution": list(resolution),
            "faces": faces,
            "seconds": round(seconds, 3),
        }
    )
    return record


def psnr_from_mse(mse: float) -> float:
    return 10 * math.log10(1.0 / max(mse, 1e-12))


def sample_views(count: int, per_step: int, generator: torch.Generator) -> torch.Tensor:
    return torch.randperm(count, generator=generator)[: min(per_step, count)]
