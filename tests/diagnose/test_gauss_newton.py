"""The probes' Gauss-Newton solver: it recovers per-view and global effect parameters together,
its score test predicts the reduction of a near-linear problem, and the Jacobian it builds one
column at a time matches autograd."""

from __future__ import annotations

import math

import torch

from recon.camera import orbit_cameras
from recon.diagnose.gauss_newton import GaussNewtonProblem
from recon.effects import make_effect

VIEWS, SIZE = 4, 24


def base_images() -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(0)
    image = 0.3 + 0.4 * torch.rand(VIEWS, SIZE, SIZE, 3, generator=generator)
    return image, torch.ones(VIEWS, SIZE, SIZE, 1)


CAMERAS = orbit_cameras(VIEWS, (SIZE, SIZE), distance=2.0, fov_x_deg=45)


def render_with(effects, image, alpha):
    color = image
    for effect in effects:
        color, alpha = effect(color, alpha, CAMERAS, torch.arange(VIEWS))
    return color


def test_recovers_per_view_exposure_and_global_vignetting_together():
    image, alpha = base_images()
    truth_exposure = make_effect("exposure", view_count=VIEWS, pinned_view=None)
    truth_vignetting = make_effect("vignetting")
    with torch.no_grad():
        truth_exposure.log_gain.copy_(torch.tensor([0.2, -0.1, 0.05, -0.25]))
        truth_vignetting.coefficients.copy_(torch.tensor([-0.3, 0.1]))
        observed = render_with([truth_vignetting, truth_exposure], image, alpha)
    exposure = make_effect("exposure", view_count=VIEWS, pinned_view=None)
    vignetting = make_effect("vignetting")
    problem = GaussNewtonProblem(
        [exposure, vignetting],
        lambda: render_with([vignetting, exposure], image, alpha),
        observed,
        alpha,
    )
    assert problem.unknowns == VIEWS * 1 + 2
    result = problem.fit(iterations=8)
    assert result["final_loss"] < 1e-6 * result["initial_loss"]
    assert torch.allclose(exposure.log_gain, truth_exposure.log_gain, atol=1e-3)
    assert torch.allclose(vignetting.coefficients, truth_vignetting.coefficients, atol=1e-2)


def test_score_predicts_the_reduction_of_a_nearly_linear_problem():
    image, alpha = base_images()
    exposure = make_effect("exposure", view_count=VIEWS, pinned_view=None)
    gains = torch.tensor([1.01, 0.99, 1.0, 1.02])
    noise = 0.001 * torch.randn(image.shape, generator=torch.Generator().manual_seed(1))
    observed = image * gains[:, None, None, None] + noise
    problem = GaussNewtonProblem(
        [exposure], lambda: render_with([exposure], image, alpha), observed, alpha
    )
    result = problem.fit(iterations=4)
    achieved = 1 - result["final_loss"] / result["initial_loss"]
    assert 0.5 < achieved < 1.0
    assert math.isclose(result["score"], achieved, rel_tol=0.02)


def test_the_columnwise_jacobian_matches_autograd():
    image, alpha = base_images()
    white_balance = make_effect("white_balance", view_count=VIEWS, pinned_view=None)
    with torch.no_grad():
        white_balance.log_red_blue.copy_(0.1 * torch.randn(VIEWS, 2))
    problem = GaussNewtonProblem(
        [white_balance], lambda: render_with([white_balance], image, alpha), image, alpha
    )
    with torch.no_grad():
        base = problem.render()
    jacobian = problem.jacobian(base)  # [2 columns, N counted pixels, 3]
    for column in range(2):
        # A per-view column moves its parameter in every view at once.
        selector = torch.zeros(VIEWS, 2)
        selector[:, column] = 1.0
        _, tangent = torch.func.jvp(
            lambda parameters: render_with_parameters(white_balance, parameters, image, alpha),
            (white_balance.log_red_blue.detach(),),
            (selector,),
        )
        assert torch.allclose(jacobian[column], problem.counted(tangent), atol=5e-3 * 3)


def test_the_normal_equations_over_counted_pixels_match_the_dense_sums():
    """Summing over the pixels with weight > 0 only gives the dense weighted sums: the per-view
    blocks, the global block, their cross terms and the right-hand side."""
    generator = torch.Generator().manual_seed(3)
    image, alpha = base_images()
    exposure = make_effect("exposure", view_count=VIEWS, pinned_view=None)
    vignetting = make_effect("vignetting")
    weight = alpha * torch.rand(alpha.shape, generator=generator)
    weight[:, ::2] = 0.0  # rows that do not count, as a probe's other half of the blocks
    observed = image * 1.05 + 0.01
    problem = GaussNewtonProblem(
        [exposure, vignetting],
        lambda: render_with([exposure, vignetting], image, alpha),
        observed,
        weight,
    )
    dense = torch.randn(len(problem.columns), *image.shape, generator=generator)
    residual = torch.randn(image.shape, generator=generator)
    matrix, vector = problem.normal_equations(
        torch.stack([problem.counted(column) for column in dense]), problem.counted(residual)
    )
    weighted = dense * weight
    products = torch.einsum("cbhwk,dbhwk->cdb", weighted, dense).double()
    right = torch.einsum("cbhwk,bhwk->cb", weighted, residual).double()
    # Unknowns: the exposure of each view, then vignetting's global parameters.
    is_per_view = torch.tensor([column.per_view for column in problem.columns])
    local = torch.nonzero(is_per_view).flatten()
    shared = torch.nonzero(~is_per_view).flatten()
    assert local.numel() == 1 and shared.numel() >= 1
    for view in range(VIEWS):
        assert torch.isclose(matrix[view, view], products[local[0], local[0], view], rtol=1e-4)
        assert torch.isclose(vector[view], right[local[0], view], rtol=1e-4, atol=1e-3)
        cross = products[local[0], shared, view]
        assert torch.allclose(matrix[view, VIEWS:], cross, rtol=1e-4, atol=1e-3)
        assert torch.allclose(matrix[VIEWS:, view], cross, rtol=1e-4, atol=1e-3)
    expected_global = products[shared][:, shared].sum(-1)
    assert torch.allclose(matrix[VIEWS:, VIEWS:], expected_global, rtol=1e-4, atol=1e-3)
    assert torch.allclose(vector[VIEWS:], right[shared].sum(-1), rtol=1e-4, atol=1e-3)
    assert torch.all(matrix[:VIEWS, :VIEWS] == torch.diag(matrix.diagonal()[:VIEWS]))
    assert math.isclose(
        problem.loss(image), float(((image - observed) ** 2 * weight).sum()), rel_tol=1e-5
    )


def render_with_parameters(effect, parameters, image, alpha):
    return torch.func.functional_call(
        effect, {"log_red_blue": parameters}, (image, alpha, CAMERAS, torch.arange(VIEWS))
    )[0]


def test_a_step_that_raises_the_loss_is_undone():
    image, alpha = base_images()
    exposure = make_effect("exposure", view_count=VIEWS, pinned_view=None)
    observed = image * 1.1
    calls = {"count": 0}

    def adversarial_render():
        # Honest at the start and for the one Jacobian column, then every render looks worse.
        calls["count"] += 1
        color = render_with([exposure], image, alpha)
        return color if calls["count"] <= 2 else color + 1.0

    problem = GaussNewtonProblem([exposure], adversarial_render, observed, alpha)
    problem.fit(iterations=3)
    assert torch.all(exposure.log_gain == 0)


def test_a_counted_render_gives_the_same_fit():
    """render_counted (the render at the counted pixels alone) leaves the solver's steps as
    they are: the same parameters and losses as rendering whole images."""
    image, alpha = base_images()
    weight = alpha.clone()
    weight[:, ::2] = 0.0
    observed = image * torch.tensor([1.1, 0.9, 1.0, 1.05])[:, None, None, None]
    results = []
    for counted in (False, True):
        exposure = make_effect("exposure", view_count=VIEWS, pinned_view=None)
        problem = GaussNewtonProblem(
            [exposure], lambda e=exposure: render_with([e], image, alpha), observed, weight
        )
        if counted:
            problem = GaussNewtonProblem(
                [exposure],
                lambda e=exposure: render_with([e], image, alpha),
                observed,
                weight,
                render_counted=lambda e=exposure, p=problem: p.counted(
                    render_with([e], image, alpha)
                ),
            )
        results.append((problem.fit(iterations=3), exposure.log_gain.detach().clone()))
    (plain, plain_gains), (counted, counted_gains) = results
    assert torch.equal(plain_gains, counted_gains)
    assert plain["final_loss"] == counted["final_loss"] < 0.01 * plain["initial_loss"]
