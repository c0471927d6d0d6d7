"""Laplacian-preconditioned vertex updates (the "Large Steps" parameterisation, own code).

Vertices v are optimised through a latent u = (I + lambda L) v with L the uniform Laplacian.
Gradient steps on u move v by (I + lambda L)^-1 applied to the step: a smoothed, low-frequency
update that lets meshes move far without tangling. The system matrix is sparse symmetric
positive definite; it is factorised once per topology (scipy's SuperLU) and refactorised after
each remesh. Backward through v = M^-1 u is another solve with M (symmetric).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch

from recon.errors import ReconError
from recon.mesh.laplacian import uniform_laplacian


class LaplacianPreconditioner:
    """M = I + lambda L for one topology, factorised once.

    faces: [F, 3] int64; vertex_count: V; smoothing: lambda (Large Steps uses about 19-49).
    """

    def __init__(self, faces: torch.Tensor, vertex_count: int, smoothing: float) -> None:
        if smoothing < 0:
            raise ReconError(f"large steps lambda: expected >= 0, got {smoothing}")
        laplacian = uniform_laplacian(faces, vertex_count)
        identity = scipy.sparse.identity(vertex_count, format="csr")
        self.matrix = (identity + smoothing * laplacian).tocsc()
        self._solve = scipy.sparse.linalg.factorized(self.matrix)
        self.vertex_count = vertex_count

    def to_latent(self, verts: torch.Tensor) -> torch.Tensor:
        """u = M v for verts [V, 3] (no gradient)."""
        result = self.matrix @ verts.detach().cpu().double().numpy()
        return torch.as_tensor(result, dtype=verts.dtype).to(verts.device)

    def solve(self, values: torch.Tensor) -> torch.Tensor:
        """M^-1 values for values [V, K], no autograd."""
        array = values.detach().cpu().double().numpy()
        result = np.stack([self._solve(array[:, k]) for k in range(array.shape[1])], axis=1)
        return torch.as_tensor(result, dtype=values.dtype).to(values.device)

    def from_latent(self, latent: torch.Tensor) -> torch.Tensor:
        """v = M^-1 u, differentiable (the backward is a solve with the symmetric M)."""
        return _LatentSolve.apply(latent, self)


class _LatentSolve(torch.autograd.Function):
    @staticmethod
    def forward(context, latent: torch.Tensor, preconditioner: LaplacianPreconditioner):
        context.preconditioner = preconditioner
        return preconditioner.solve(latent)

    @staticmethod
    def backward(context, gradient: torch.Tensor):
        return context.preconditioner.solve(gradient), None


class UniformAdam(torch.optim.Optimizer):
    """Adam whose step is normalised by the largest second-moment entry instead of per entry.

    Per-entry normalisation would undo the preconditioning (every vertex would move by about the
    learning rate); a single scale keeps the smooth step's shape (Nicolet et al. 2021).
    """

    def __init__(
        self, params, lr: float = 1e-2, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8
    ):
        super().__init__(params, {"lr": lr, "betas": betas, "eps": eps})

    @torch.no_grad()
    def step(self, closure=None):  # noqa: D102
        for group in self.param_groups:
            beta1, beta2 = group["betas"]
            for parameter in group["params"]:
                if parameter.grad is None:
                    continue
                state = self.state[parameter]
                if not state:
                    state["step"] = 0
                    state["exp_avg"] = torch.zeros_like(parameter)
                    state["exp_avg_sq"] = torch.zeros_like(parameter)
                state["step"] += 1
                state["exp_avg"].mul_(beta1).add_(parameter.grad, alpha=1 - beta1)
                state["exp_avg_sq"].mul_(beta2).addcmul_(
                    parameter.grad, parameter.grad, value=1 - beta2
                )
                bias1 = 1 - beta1 ** state["step"]
                bias2 = 1 - beta2 ** state["step"]
                denominator = (state["exp_avg_sq"].max() / bias2).sqrt() + group["eps"]
                parameter.add_(state["exp_avg"] / bias1 / denominator, alpha=-group["lr"])
