"""Levenberg-Marquardt on an effect module's few parameters, with the scene frozen.

Every effect module has a handful of parameters: a few global ones (vignetting, response curve,
blur, distortion, specular) or a few per view (exposure, white balance, motion blur, pose).
For so few unknowns a Gauss-Newton step is cheaper and surer than many first-order steps: the
Jacobian of the rendered image takes one extra render per parameter *column*, because a per-view
column moves its parameter in every view at once and each view's image depends on its own
parameters only. The normal matrix is then block-diagonal over views plus a dense global part,
and a handful of damped steps converge where Adam needed 60 forward+backward renders.

The same Jacobian at zero gives the score test of the diagnosis brief: the loss reduction a full
Gauss-Newton step predicts, g^T (J^T J)^-1 g, before any parameter has moved.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass

import torch

from recon.effects.base import ModelEffect

# Damping of the first step (relative to the normal matrix's diagonal) and its change on a
# rejected / accepted step.
INITIAL_DAMPING = 1.0
DAMPING_UP = 10.0
DAMPING_DOWN = 0.3
# A relative ridge that keeps gauge directions (response LUT offsets) solvable.
RIDGE = 1e-9


@dataclass
class _Column:
    """One Jacobian column: a parameter element (global) or one element of every view's row
    (per view)."""

    parameter: torch.nn.Parameter
    index: tuple
    per_view: bool
    step: float


def _columns(effects: list[ModelEffect], view_count: int) -> list[_Column]:
    columns = []
    for effect in effects:
        for name, parameter in effect.named_parameters():
            if not parameter.requires_grad:
                continue
            # One learning-rate step is the module's own notion of a small change.
            step = effect.learning_rate * effect.learning_rate_scales.get(name, 1.0)
            per_view = effect.per_view and parameter.ndim >= 1 and parameter.shape[0] == view_count
            if per_view:
                for rest in itertools.product(*[range(size) for size in parameter.shape[1:]]):
                    columns.append(_Column(parameter, (slice(None), *rest), True, step))
            else:
                for index in itertools.product(*[range(size) for size in parameter.shape]):
                    columns.append(_Column(parameter, index, False, step))
    return columns


def counted_pixels(weight: torch.Tensor, shape: torch.Size) -> torch.Tensor:
    """[N] flat indices over B * H * W (ascending) of the pixels with weight [B, H, W, 1] > 0
    in images of shape [B, H, W, C]: the pixels a GaussNewtonProblem counts."""
    flat_weight = weight.expand(*shape[:-1], 1).reshape(-1)
    return torch.nonzero(flat_weight > 0).squeeze(1)


class GaussNewtonProblem:
    """Weighted least squares sum(weight * (render() - observed)^2) over the parameters of
    `effects` (the ones to fit; render may apply others too), each view's per-view parameters
    seeing only that view.

    render: () -> [B, H, W, C] image of the frozen scene with the effects' current parameters.
    observed: [B, H, W, C]; weight: [B, H, W, 1] (0 outside the pixels that count).
    render_counted: () -> [N, C] the same image at the counted pixels only (counted(render()),
        in that order), where the caller can render those alone for less (pixelwise effects);
        every render of the solver then goes through it.
    """

    def __init__(
        self,
        effects: list[ModelEffect],
        render: Callable[[], torch.Tensor],
        observed: torch.Tensor,
        weight: torch.Tensor,
        render_counted: Callable[[], torch.Tensor] | None = None,
    ) -> None:
        self.render = render
        self.view_count = observed.shape[0]
        self.columns = _columns(effects, self.view_count)
        self.per_view_columns = [c for c in self.columns if c.per_view]
        self.global_columns = [c for c in self.columns if not c.per_view]
        self.unknowns = self.view_count * len(self.per_view_columns) + len(self.global_columns)
        # Only the pixels with weight > 0 enter the sums (a probe's half of the pixel blocks
        # inside the object's region, about a sixth of the image): the Jacobian, the residual
        # and the loss are kept at those pixels alone, view after view.
        self.channels = observed.shape[-1]
        flat_weight = weight.expand(*observed.shape[:-1], 1).reshape(-1)
        self._counted = counted_pixels(weight, observed.shape)  # [N] over B * H * W
        self._counted_weight = flat_weight[self._counted][:, None]  # [N, 1]
        pixels_per_view = observed[0, ..., 0].numel()
        self._view_counts = torch.bincount(
            torch.div(self._counted, pixels_per_view, rounding_mode="floor"),
            minlength=self.view_count,
        ).tolist()
        self.observed = self.counted(observed)
        self._render_counted = render_counted

    @property
    def counted_index(self) -> torch.Tensor:
        """[N] flat indices over B * H * W of the counted pixels (ascending)."""
        return self._counted

    def render_at_counted(self) -> torch.Tensor:
        """render() at the counted pixels [N, C] (through render_counted where given)."""
        with torch.no_grad():
            if self._render_counted is not None:
                return self._render_counted()
            return self.counted(self.render())

    def counted(self, image: torch.Tensor) -> torch.Tensor:
        """The counted pixels [N, C] of an image [B, H, W, C] (views in order)."""
        return image.reshape(-1, self.channels).index_select(0, self._counted)

    # -- parameter vector ----------------------------------------------------------------
    def _add(self, delta: torch.Tensor) -> None:
        """Add an update [unknowns] (per-view block first, view-major; then the global ones)."""
        views, per_view = self.view_count, len(self.per_view_columns)
        with torch.no_grad():
            blocks = delta[: views * per_view].view(views, per_view) if per_view else None
            for position, column in enumerate(self.per_view_columns):
                column.parameter[column.index] += blocks[:, position].to(column.parameter)
            for position, column in enumerate(self.global_columns):
                column.parameter[column.index] += delta[views * per_view + position].to(
                    column.parameter
                )

    def _move_column(self, column: _Column, amount: float) -> None:
        with torch.no_grad():
            column.parameter[column.index] += amount

    # -- pieces ----------------------------------------------------------------------------
    def loss(self, image: torch.Tensor | None = None) -> float:
        """The weighted squared error of an image [B, H, W, C] (default: render())."""
        values = self.render_at_counted() if image is None else self.counted(image)
        return self._loss(values)

    def _loss(self, values: torch.Tensor) -> float:
        """The weighted squared error of the counted pixels' values [N, C]."""
        with torch.no_grad():
            return float(((values - self.observed) ** 2 * self._counted_weight).sum())

    def jacobian(self, base: torch.Tensor) -> torch.Tensor:
        """[columns, N, C] forward differences of the image at the counted pixels, one column at
        a time; base: render() [B, H, W, C] at the current parameters."""
        return self._jacobian(self.counted(base))

    def _jacobian(self, base: torch.Tensor) -> torch.Tensor:
        """jacobian from the counted pixels' values [N, C] at the current parameters."""
        changes = []
        with torch.no_grad():
            for column in self.columns:
                self._move_column(column, column.step)
                changes.append((self.render_at_counted() - base) / column.step)
                self._move_column(column, -column.step)
        return torch.stack(changes)

    def normal_equations(
        self, jacobian: torch.Tensor, residual: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(J^T W J [unknowns, unknowns], J^T W r [unknowns]) in float64, from the Jacobian
        [columns, N, C] and r = observed - image [N, C] at the counted pixels."""
        weighted = jacobian * self._counted_weight
        # Per view: column x column products and column x residual products (one matrix
        # product each over the view's counted pixels).
        products = jacobian.new_zeros(len(self.columns), len(self.columns), self.view_count)
        right = jacobian.new_zeros(len(self.columns), self.view_count)
        start = 0
        for view, count in enumerate(self._view_counts):
            rows = weighted[:, start : start + count].reshape(len(self.columns), -1)
            products[:, :, view] = (
                rows @ jacobian[:, start : start + count].reshape(len(self.columns), -1).T
            )
            right[:, view] = rows @ residual[start : start + count].reshape(-1)
            start += count
        products, right = products.double(), right.double()
        views = self.view_count
        per_view = len(self.per_view_columns)
        is_per_view = torch.tensor([c.per_view for c in self.columns])
        local = torch.nonzero(is_per_view).flatten()
        shared = torch.nonzero(~is_per_view).flatten()
        # Unknowns: each view's per-view block (view-major), then the global ones.
        local_block = products[local][:, local].permute(2, 0, 1)  # [B, Kp, Kp]
        cross = products[local][:, shared].permute(2, 0, 1).reshape(views * per_view, len(shared))
        matrix = torch.block_diag(*local_block, products[shared][:, shared].sum(-1))
        offset = views * per_view
        matrix[:offset, offset:] = cross
        matrix[offset:, :offset] = cross.T
        vector = torch.cat([right[local].T.reshape(-1), right[shared].sum(-1)])
        return matrix, vector

    @staticmethod
    def solve(matrix: torch.Tensor, vector: torch.Tensor, damping: float) -> torch.Tensor:
        diagonal = matrix.diagonal().clamp_min(RIDGE * float(matrix.diagonal().max().clamp_min(1)))
        damped = matrix + torch.diag(diagonal * (damping + RIDGE))
        return torch.linalg.lstsq(damped, vector[:, None]).solution[:, 0]

    def _predicted(self, matrix: torch.Tensor, vector: torch.Tensor, loss: float) -> float:
        return float(vector @ self.solve(matrix, vector, 0.0)) / max(loss, 1e-20)

    def score(self, start_image: torch.Tensor | None = None) -> float:
        """The score test at the current parameters: the relative loss reduction a full
        Gauss-Newton step predicts, g^T (J^T J)^-1 g / loss with g = J^T r (nothing moves)."""
        if not self.columns:
            return 0.0
        start = self._start_values(start_image)
        matrix, vector = self.normal_equations(self._jacobian(start), self.observed - start)
        return self._predicted(matrix, vector, self._loss(start))

    def _start_values(self, start_image: torch.Tensor | None) -> torch.Tensor:
        """The counted pixels [N, C] of start_image, else of a render at the current
        parameters."""
        return self.render_at_counted() if start_image is None else self.counted(start_image)

    # -- the solver --------------------------------------------------------------------------
    def fit(self, iterations: int, start_image: torch.Tensor | None = None) -> dict:
        """Damped Gauss-Newton from the current parameters, the Jacobian recomputed after every
        accepted step; returns {'score': the score test at the start (see score), 'initial_loss',
        'final_loss'}. start_image: render() at the current parameters when the caller has it.
        """
        if not self.columns or iterations <= 0:
            loss = self.loss()
            return {"score": 0.0, "initial_loss": loss, "final_loss": loss}
        # Everything below works on the counted pixels' values [N, C] alone.
        base = self._start_values(start_image)
        loss = self._loss(base)
        initial_loss = loss
        jacobian = self._jacobian(base)
        matrix, vector = self.normal_equations(jacobian, self.observed - base)
        score = self._predicted(matrix, vector, initial_loss)
        damping = INITIAL_DAMPING
        for iteration in range(iterations):
            delta = self.solve(matrix, vector, damping)
            self._add(delta)
            candidate = self.render_at_counted()
            candidate_loss = self._loss(candidate)
            if candidate_loss < loss:
                loss, base = candidate_loss, candidate
                damping *= DAMPING_DOWN
                if iteration + 1 < iterations:
                    jacobian = self._jacobian(base)
                    matrix, vector = self.normal_equations(jacobian, self.observed - base)
            else:
                self._add(-delta)
                damping *= DAMPING_UP
        return {"score": score, "initial_loss": initial_loss, "final_loss": loss}
