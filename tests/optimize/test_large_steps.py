"""Large Steps parameterisation: round trip, gradient, smoothing of updates."""

from __future__ import annotations

import torch
import trimesh

from recon.optimize.large_steps import LaplacianPreconditioner, UniformAdam


def _sphere():
    mesh = trimesh.creation.icosphere(subdivisions=2)
    return torch.tensor(mesh.vertices, dtype=torch.float32), torch.tensor(mesh.faces)


def test_latent_round_trip_and_gradient_matches_finite_differences():
    verts, faces = _sphere()
    preconditioner = LaplacianPreconditioner(faces, verts.shape[0], smoothing=10.0)
    latent = preconditioner.to_latent(verts)
    torch.testing.assert_close(preconditioner.from_latent(latent), verts, atol=1e-4, rtol=1e-4)
    # d/du of sum(w * v(u)) = M^-1 w (M symmetric); check against finite differences.
    latent = latent.double().requires_grad_(True)
    weights = torch.randn(verts.shape[0], 3, dtype=torch.float64)
    (preconditioner.from_latent(latent) * weights).sum().backward()
    step = 1e-4
    for index in [(0, 0), (5, 1), (40, 2)]:
        plus, minus = latent.detach().clone(), latent.detach().clone()
        plus[index] += step
        minus[index] -= step
        numeric = (
            (preconditioner.from_latent(plus) * weights).sum()
            - (preconditioner.from_latent(minus) * weights).sum()
        ) / (2 * step)
        assert abs(float(latent.grad[index]) - float(numeric)) < 1e-6


def test_preconditioned_step_is_smoother_than_the_raw_gradient():
    verts, faces = _sphere()
    preconditioner = LaplacianPreconditioner(faces, verts.shape[0], smoothing=20.0)
    spike = torch.zeros_like(verts)
    spike[0] = 1.0
    smoothed = preconditioner.solve(spike)
    # The response spreads to neighbours and decays: a spike becomes a bump.
    assert float(smoothed[0].norm()) < 1.0
    neighbours = torch.tensor(faces[(faces == 0).any(1)].unique())
    assert float(smoothed[neighbours[neighbours != 0]].norm(dim=-1).min()) > 0


def test_uniform_adam_moves_every_entry_by_one_shared_scale():
    parameter = torch.zeros(4, requires_grad=True)
    optimizer = UniformAdam([parameter], lr=0.1)
    parameter.grad = torch.tensor([1.0, 0.5, 0.0, -2.0])
    optimizer.step()
    # Relative sizes of the step follow the gradient (Adam would give +-0.1 for all non-zero).
    step = -parameter.detach()
    torch.testing.assert_close(step / step.abs().max(), torch.tensor([0.5, 0.25, 0.0, -1.0]))
