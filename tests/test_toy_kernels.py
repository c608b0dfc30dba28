"""The toy optimiser's fused kernels (benchmark.unsupervised.toy_kernels) against the reference
implementation (benchmark.unsupervised.reprojection, torch and autograd): loss values and
gradients on random problems, the ODM's masks, Adam's step, independence from the number of
threads, and a short optimisation against torch's Adam on reprojection's losses.

Tolerances: the kernels sum in float64, torch in float32, so losses agree to ~1e-7 relative and
gradients to ~1e-6 of their largest value (asserted with 10x margin); a trajectory of 30 Adam
steps from a random start agrees to 1e-3 in LE (Adam's normalised steps amplify rounding where
a gradient is near 0, and the bilinear sampling has kinks at integer coordinates)."""

from __future__ import annotations

import numba
import numpy as np
import pytest
import torch
from test_toy_study import _random_scene

from benchmark.unsupervised import toy, toy_kernels
from benchmark.unsupervised.reprojection import SMOOTH_LOSSES


@pytest.fixture(scope="module")
def problem() -> toy.Problem:
    scenes = [_random_scene("horizon", 0, 32), _random_scene("flower", 1, 32)]
    return toy.Problem(scenes, torch.tensor([0.3, 3.0, 30.0]), torch.tensor([0.3, 1.0, 0.1]))


def _depth(problem: toy.Problem, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return 2 + 8 * torch.rand(problem.truth.shape, generator=gen)


def _state(problem: toy.Problem, depth: torch.Tensor, smooth: str | None = None) -> toy._Kernels:
    return toy._Kernels(problem, smooth, toy._np(depth[:, 0]))


def _assert_gradient(got: np.ndarray, expected: torch.Tensor) -> None:
    scale = expected.abs().max().item()
    assert scale > 0
    np.testing.assert_allclose(got / scale, expected[:, 0].numpy() / scale, rtol=0, atol=2e-5)


@pytest.mark.parametrize("occluded", [False, True])
def test_photometric_loss_and_gradient_equal_the_reference(problem, occluded):
    depth = _depth(problem, 2)
    gen = torch.Generator().manual_seed(3)
    occ = [torch.rand(problem.truth.shape, generator=gen) < 0.2 for _ in toy.REFERENCES]
    occ = occ if occluded else None
    d = depth.clone().requires_grad_(True)
    expected = problem.photometric(d, occ)
    expected.sum().backward()
    state = _state(problem, depth)
    if occ is not None:
        state.set_occluded(torch.cat(occ, 1).numpy())
    got = state.photometric()
    np.testing.assert_allclose(got, expected.detach().numpy(), rtol=1e-6, atol=0)
    _assert_gradient(state.grad, d.grad)


def test_photometric_kernel_gives_each_sample_what_it_gives_it_alone():
    """The default grid's 50 points in one batch: the kernel's loop over grid points then runs
    vectorised (several points at a time) and a scalar remainder, where one point alone runs
    only the scalar form; losses and gradients must be equal bit for bit, ODM masks included."""
    scenes = [_random_scene("horizon", 8, 24), _random_scene("flower", 9, 24)]
    lam, kap = toy.grid(toy.StudyConfig())
    wide = toy.Problem(scenes, lam, kap)
    depth = _depth(wide, 10)
    gen = torch.Generator().manual_seed(11)
    occ = (torch.rand((depth.shape[0], len(toy.REFERENCES), 24, 24), generator=gen) < 0.2).numpy()
    state = _state(wide, depth)
    state.set_occluded(occ)
    loss = state.photometric()
    points = wide.points
    for g in range(points):
        rows = [g, points + g]  # grid point g of each scene
        alone = _state(toy.Problem(scenes, lam[g : g + 1], kap[g : g + 1]), depth[rows])
        alone.set_occluded(occ[rows])
        assert np.array_equal(alone.photometric(), loss[rows])
        assert np.array_equal(alone.grad, state.grad[rows])


@pytest.mark.parametrize("smooth", list(SMOOTH_LOSSES))
def test_smooth_loss_and_gradient_equal_autograd(problem, smooth):
    """λ·L_s(1/θ) and its gradient in θ, the robust losses' 10 inner steps included."""
    depth = _depth(problem, 4)
    d = depth.clone().requires_grad_(True)
    g, xi = problem.points, 1 / d
    parts = [
        SMOOTH_LOSSES[smooth](xi[i * g : (i + 1) * g], s.target, problem.kappas)
        for i, s in enumerate(problem.scenes)
    ]
    expected = problem.lam * torch.cat(parts)
    expected.sum().backward()
    state = _state(problem, depth, smooth)
    state.grad[:] = 0
    a = state.a
    got = toy_kernels.smooth(state.code, state.depth, state.wf, state.wl, a.lam,
                             toy.ROBUST_STEPS, toy.ROBUST_STEP, state.grad)  # fmt: skip
    np.testing.assert_allclose(got * a.lam, expected.detach().numpy(), rtol=1e-5, atol=0)
    _assert_gradient(state.grad, d.grad)


def test_odm_masks_equal_the_reference():
    """A background plane with a nearer rectangle: the occluded bands beside it, both
    references, pixel for pixel. The depths are generic: at round ones (8 m here) the squares of
    the direct warp tile the plane with edges exactly on pixel centres, where float rounding
    (float64 here, float32 matrix products in torch) decides which of two neighbours paints a
    pixel; the masks then differ by one-pixel seams (dilated to 5), equally valid both ways."""
    scenes = [_random_scene("horizon", 5, 48), _random_scene("flower", 6, 48)]
    problem = toy.Problem(scenes, torch.tensor([1.0]), torch.tensor([1.0]))
    depth = torch.full(problem.truth.shape, 8.37)
    depth[0, :, 14:30, 16:34] = 2.13
    depth[1, :, 20:40, 10:24] = 3.29
    expected = problem.occlusions(depth)
    state = _state(problem, depth)
    state.occlusions()
    for got, ref in zip(state.masks(torch.device("cpu")), expected, strict=True):
        assert 0.02 < ref.float().mean() < 0.9
        assert torch.equal(got, ref)


def test_adam_step_is_torch_adam_with_the_clamp():
    gen = torch.Generator().manual_seed(7)
    p = 5 + torch.rand(2, 6, 5, generator=gen)
    param = p.clone().requires_grad_(True)
    opt = torch.optim.Adam([param], lr=0.15)
    mine = p.numpy().copy()
    m, v = np.zeros_like(mine), np.zeros_like(mine)
    for t in range(1, 6):
        grad = torch.randn(p.shape, generator=gen) * 10.0 ** (t - 3)
        param.grad = grad.clone()
        opt.step()
        with torch.no_grad():
            param.clamp_(0.1, 100)
        toy_kernels.adam_step(mine, grad.numpy().copy(), m, v, t, 0.15, 0.9, 0.999, 1e-8, 0.1, 100)
        np.testing.assert_allclose(mine, param.detach().numpy(), rtol=1e-6, atol=0)


def _reference_optimise(problem, smooth, iterations, odm_every) -> np.ndarray:
    """The toy optimiser on reprojection's torch losses and torch.optim.Adam: final LE (B,)."""
    depth = torch.full(problem.truth.shape, toy.START_DEPTH).requires_grad_(True)
    opt = torch.optim.Adam([depth], lr=toy.LEARNING_RATE)
    occluded = None
    for it in range(iterations):
        if odm_every and it % odm_every == 0:
            occluded = problem.occlusions(depth.detach())
        opt.zero_grad()
        problem.loss(depth, smooth, occluded).sum().backward()
        opt.step()
        with torch.no_grad():
            depth.clamp_(0.1, 100)
    return toy.log_error(depth.detach(), problem.truth, problem.valid).numpy()


@pytest.mark.parametrize(
    ("smooth", "odm_every"), [("diffusion", 0), ("robust_gradient_diffusion", 4)]
)
def test_short_optimisation_matches_the_torch_path(problem, smooth, odm_every):
    expected = _reference_optimise(problem, smooth, 30, odm_every)
    got = toy.optimise(problem, smooth, 30, odm_every).le
    le0 = toy.log_error(torch.full_like(problem.truth, 10.0), problem.truth, problem.valid)
    assert np.abs(got - le0.numpy()).max() > 0.05  # the depths moved
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-3)


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="needs 2 numba threads")
def test_results_do_not_depend_on_the_number_of_threads(problem):
    runs = []
    try:
        for threads in (1, 2):
            toy_kernels.set_threads(threads)
            runs.append(toy.optimise(problem, "robust_diffusion", 6, odm_every=3))
    finally:
        toy_kernels.set_threads(numba.config.NUMBA_NUM_THREADS)
    assert torch.equal(runs[0].depth, runs[1].depth)
    assert np.array_equal(runs[0].le, runs[1].le)
