"""The interface every model-side effect module implements.

A model effect is a small differentiable ``torch.nn.Module`` whose parameters are all zero at
the identity: a freshly built effect changes nothing, so it can be switched on in a fitted
forward model without moving it, and the gradient of the loss at zero scores it (see the
diagnosis brief). Each acts at one stage of the forward model:

- 'camera': on the cameras before rendering (pose_error): ``apply_to_cameras``.
- 'shading': on the shaded radiance, from the render's buffers (specular, shadows,
  interreflection): ``forward(render_output, context) -> RenderOutput``.
- 'image': on the rendered image (the rest):
  ``forward(color, alpha, cameras, view_indices) -> (color, alpha)``.

Per-view effects hold one set of parameters per training view and are told which training view
each batch entry is (``view_indices`` [B]); a pinned view stays at the identity to fix a gauge
(exposure x light, white balance x light colour, pose x world frame). ``view_indices=None``
(a view the fit did not train on) uses the typical view: the mean of the per-view parameters for
photometric and blur effects, the identity for pose corrections.

The world side (data_synth.effects) implements every effect differently on purpose; the
modules here are deliberately simple.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar, Literal

import torch

from recon.effects.facts import DiagnosisFacts
from recon.errors import ReconError

Stage = Literal["camera", "shading", "image"]
STAGES: tuple[Stage, ...] = ("camera", "shading", "image")


class ModelEffect(torch.nn.Module):
    """Base class: name, stage, per-view bookkeeping, learning rate and lock fraction.

    Subclasses set the class attributes and create their parameters (all zero = identity).

    view_count: number of training views (needed by per-view effects, ignored otherwise).
    learning_rate: Adam step size for this effect (None = default_learning_rate).
    lock_fraction: share of a fit, from its start, during which the effect stays frozen so the
        scene settles first (None = default_lock_fraction), as ADOP does for its camera model.
    pinned_view: per-view effects with a gauge keep this view at the identity (None = no pin).
    """

    name: ClassVar[str]
    stage: ClassVar[Stage]
    per_view: ClassVar[bool] = False
    # What the gap diagnosis needs to know about the effect (recon.effects.facts).
    diagnosis: ClassVar[DiagnosisFacts]
    default_learning_rate: ClassVar[float] = 0.01
    default_lock_fraction: ClassVar[float] = 0.2
    # Whether a per-view effect pins a view by default (a gauge against albedo x light or the
    # world frame); effects without a gauge (motion blur) leave every view free.
    pins_a_view: ClassVar[bool] = False
    # Per-parameter multipliers of the learning rate, for parameters of different scales.
    learning_rate_scales: ClassVar[dict[str, float]] = {}
    # An image effect that maps each pixel's colour and alpha by its view's parameters alone (no
    # neighbours, no image position): it may be applied to any subset of a view's pixels, which
    # the diagnosis' probes use to render only the pixels their fit counts.
    pixelwise: ClassVar[bool] = False

    def __init__(
        self,
        view_count: int | None = None,
        learning_rate: float | None = None,
        lock_fraction: float | None = None,
        pinned_view: int | None | Literal["default"] = "default",
    ) -> None:
        super().__init__()
        if self.per_view:
            if view_count is None or int(view_count) < 1:
                raise ReconError(
                    f"effect {self.name}: a per-view effect needs view_count >= 1 (the number of "
                    f"training views), got {view_count}"
                )
            self.view_count = int(view_count)
        else:
            self.view_count = None if view_count is None else int(view_count)
        self.learning_rate = float(
            self.default_learning_rate if learning_rate is None else learning_rate
        )
        if not self.learning_rate > 0:
            raise ReconError(
                f"effect {self.name}: learning_rate must be positive, got {self.learning_rate}"
            )
        self.lock_fraction = float(
            self.default_lock_fraction if lock_fraction is None else lock_fraction
        )
        if not 0.0 <= self.lock_fraction <= 1.0:
            raise ReconError(
                f"effect {self.name}: lock_fraction must lie in [0, 1], got {self.lock_fraction}"
            )
        if pinned_view == "default":
            pinned_view = 0 if (self.per_view and self.pins_a_view) else None
        if pinned_view is not None:
            if not self.per_view:
                raise ReconError(f"effect {self.name}: pinned_view needs a per-view effect")
            if not 0 <= int(pinned_view) < self.view_count:
                raise ReconError(
                    f"effect {self.name}: pinned_view {pinned_view} out of range for "
                    f"{self.view_count} views"
                )
            pinned_view = int(pinned_view)
        self.pinned_view = pinned_view
        if self.per_view:
            # 1 for free views, 0 for the pinned one: multiplying the raw parameters by it keeps
            # the pinned view exactly at the identity and its gradient exactly zero.
            free = torch.ones(self.view_count)
            if pinned_view is not None:
                free[pinned_view] = 0.0
            self.register_buffer("free_views", free, persistent=False)

    # ---------------------------------------------------------------------------------------
    # optimisation helpers

    def reset_parameters(self) -> None:
        """Set every parameter to zero: the identity."""
        with torch.no_grad():
            for parameter in self.parameters():
                parameter.zero_()

    def is_identity(self) -> bool:
        """True when every parameter is exactly zero."""
        return all(bool((parameter == 0).all()) for parameter in self.parameters())

    def is_locked(self, progress: float) -> bool:
        """Whether the effect stays frozen at fit progress in [0, 1]."""
        return progress < self.lock_fraction

    def parameter_groups(self) -> list[dict]:
        """Optimizer parameter groups with this effect's learning rate (scaled per parameter)."""
        groups = []
        for name, parameter in self.named_parameters():
            scale = self.learning_rate_scales.get(name, 1.0)
            groups.append(
                {
                    "params": [parameter],
                    "lr": self.learning_rate * scale,
                    "name": f"{self.name}.{name}",
                }
            )
        return groups

    def parameters_summary(self) -> dict:
        """The recovered parameters in interpretable units (JSON-ready)."""
        raise NotImplementedError

    # ---------------------------------------------------------------------------------------
    # per-view helpers

    def masked(self, per_view_parameter: torch.Tensor) -> torch.Tensor:
        """per_view_parameter [V, ...] with the pinned view zeroed (the identity)."""
        shape = (self.view_count,) + (1,) * (per_view_parameter.ndim - 1)
        return per_view_parameter * self.free_views.to(per_view_parameter).view(shape)

    def select_views(
        self, per_view_values: torch.Tensor, view_indices: torch.Tensor | None, batch: int
    ) -> torch.Tensor:
        """Rows of per_view_values [V, ...] for each batch entry -> [batch, ...].

        view_indices: [batch] training view of each entry, or None for the typical view (the
        mean over views, repeated).
        """
        if view_indices is None:
            typical = per_view_values.mean(dim=0, keepdim=True)
            return typical.expand(batch, *per_view_values.shape[1:])
        indices = check_view_indices(view_indices, self.view_count, batch, self.name)
        return per_view_values.index_select(0, indices.to(per_view_values.device))

    def extra_repr(self) -> str:
        parts = [f"stage={self.stage}", f"lr={self.learning_rate:g}"]
        parts.append(f"lock_fraction={self.lock_fraction:g}")
        if self.per_view:
            parts.append(f"views={self.view_count}, pinned_view={self.pinned_view}")
        return ", ".join(parts)


def check_view_indices(
    view_indices: torch.Tensor | Sequence[int], view_count: int, batch: int, name: str
) -> torch.Tensor:
    """view_indices as an int64 tensor [batch]; ReconError on a bad shape or range."""
    indices = torch.as_tensor(view_indices)
    if indices.ndim != 1 or indices.shape[0] != batch:
        raise ReconError(
            f"effect {name}: view_indices must have shape [{batch}] (one training view per "
            f"batch entry), got {tuple(indices.shape)}"
        )
    if indices.dtype.is_floating_point or indices.dtype == torch.bool:
        raise ReconError(f"effect {name}: view_indices must be integers, got {indices.dtype}")
    indices = indices.to(torch.int64)
    if indices.numel() and (int(indices.min()) < 0 or int(indices.max()) >= view_count):
        raise ReconError(
            f"effect {name}: view_indices must lie in [0, {view_count - 1}], got range "
            f"[{int(indices.min())}, {int(indices.max())}]"
        )
    return indices


def check_image(color: torch.Tensor, alpha: torch.Tensor, name: str) -> tuple[int, int, int]:
    """(B, H, W) of color [B, H, W, C] and alpha [B, H, W, 1]; ReconError otherwise."""
    if color.ndim != 4:
        raise ReconError(
            f"effect {name}: color must have shape [B, H, W, C], got {tuple(color.shape)}"
        )
    if alpha.ndim != 4 or alpha.shape[:3] != color.shape[:3] or alpha.shape[-1] != 1:
        raise ReconError(
            f"effect {name}: alpha must have shape {tuple(color.shape[:3]) + (1,)}, got "
            f"{tuple(alpha.shape)}"
        )
    return color.shape[0], color.shape[1], color.shape[2]


def to_list(values: torch.Tensor, digits: int = 6) -> list:
    """A tensor as nested Python floats rounded to digits significant decimals."""
    return _round_nested(values.detach().double().cpu().tolist(), digits)


def to_float(value: torch.Tensor | float, digits: int = 6) -> float:
    return _round_nested(float(value), digits)


def _round_nested(values, digits: int):
    if isinstance(values, list):
        return [_round_nested(value, digits) for value in values]
    return float(f"{values:.{digits}g}")
