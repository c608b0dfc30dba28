"""benchmark.unsupervised.reprojection: warps, photometric and smooth losses, occlusion detection.

Expected values are computed by hand from the geometry (an analytic scene of textured planes,
ray-cast here), not by re-running the module's formulas.
"""

from __future__ import annotations

import math

import kornia
import numpy as np
import pytest
import torch

from benchmark.core.flow import pixel_grid, warp
from benchmark.unsupervised import reprojection as rp
from stillbox_gen.camera import rotation_vector_to_matrix

DT = torch.float64
SIZE = 64
FOCAL = SIZE / 2  # 90° horizontal field of view
CENTRE = (SIZE - 1) / 2
K = torch.tensor([[FOCAL, 0, CENTRE], [0, FOCAL, CENTRE], [0, 0, 1]], dtype=DT)


# ---------------------------------------------------------------- an analytic scene


BACK_Z, FRONT_Z, FRONT_HALF = 10.0, 4.0, 1.0  # world planes z = const; the square |x|, |y| ≤ 1


def _background(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Smooth texture of the background plane (wavelengths ≥ 17 px at 10 m), RGB in [0, 1]."""
    return np.stack(
        (
            0.5 + 0.3 * np.sin(2 * np.pi * x / 6.2) * np.cos(2 * np.pi * y / 5.4),
            0.5 + 0.3 * np.cos(2 * np.pi * (x + y) / 8.6),
            0.4 + 0.2 * np.sin(2 * np.pi * y / 7.4),
        )
    )


def _foreground(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Texture of the foreground square: dark red, clearly unlike the background."""
    return np.stack(
        (
            0.9 + 0.05 * np.sin(2 * np.pi * x / 1.3),
            0.1 + 0.05 * np.cos(2 * np.pi * y / 1.1),
            np.full_like(x, 0.1),
        )
    )


def render(cam2world: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """Image ``(1, 3, H, W)`` and planar depth ``(1, 1, H, W)`` of the scene seen by an OpenCV
    camera with pose ``cam2world`` (4x4) and intrinsics K, by casting a ray through each pixel
    centre: the square at z = FRONT_Z in front of the textured plane z = BACK_Z."""
    ys, xs = np.mgrid[0:SIZE, 0:SIZE].astype(float)
    ray_cam = np.stack(((xs - CENTRE) / FOCAL, (ys - CENTRE) / FOCAL, np.ones_like(xs)))
    ray = np.einsum("ij,jhw->ihw", cam2world[:3, :3], ray_cam)  # world direction, camera z = 1
    c = cam2world[:3, 3]

    def hit(plane_z):  # ray parameter s is the planar depth (the camera-frame ray has z = 1)
        s = (plane_z - c[2]) / ray[2]
        return s, c[0] + s * ray[0], c[1] + s * ray[1]

    s_back, xb, yb = hit(BACK_Z)
    s_front, xf, yf = hit(FRONT_Z)
    front = (s_front > 0) & (np.abs(xf) <= FRONT_HALF) & (np.abs(yf) <= FRONT_HALF)
    image = np.where(front, _foreground(xf, yf), _background(xb, yb))
    depth = np.where(front, s_front, s_back)
    return torch.from_numpy(image)[None], torch.from_numpy(depth)[None, None]


def relative(cam2world_target: np.ndarray, cam2world_ref: np.ndarray):
    """(R, t) mapping target camera coordinates to the reference's."""
    rel = np.linalg.inv(cam2world_ref) @ cam2world_target
    return torch.from_numpy(rel[:3, :3]), torch.from_numpy(rel[:3, 3])


def pose(rotvec=(0.0, 0.0, 0.0), centre=(0.0, 0.0, 0.0)) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = rotation_vector_to_matrix(list(rotvec))
    m[:3, 3] = centre
    return m


# ---------------------------------------------------------------- inverse warp


@pytest.fixture(scope="module")
def scene_pair():
    """Target at the origin; reference moved (0.3, −0.2, 0.4) m and turned 0.02 rad."""
    tgt, ref = pose(), pose((0.01, -0.02, 0.005), (0.3, -0.2, 0.4))
    image_t, depth_t = render(tgt)
    image_r, _ = render(ref)
    return image_t, depth_t, image_r, relative(tgt, ref)


def test_inverse_warp_with_true_depth_and_pose_rebuilds_the_target(scene_pair):
    """Up to interpolation (smooth textures: a few hundredths at most, mostly at the square's
    silhouette) and the occlusions the ODM finds, where the foreground's ghost appears."""
    image_t, depth_t, image_r, (r, t) = scene_pair
    warped, valid = rp.inverse_warp(image_r, depth_t, r, t, K)
    occluded = rp.occlusion_mask(depth_t, r, t, K, dilation=0)
    err = (warped - image_t).abs().amax(1, keepdim=True)
    kept = valid & ~occluded
    assert kept.float().mean() > 0.8
    assert err[kept].mean() < 0.005
    assert torch.quantile(err[kept], 0.99) < 0.02
    ghost = valid & occluded & (depth_t > 9)  # background hidden by the square in the reference
    assert ghost.sum() > 20 and err[ghost].mean() > 0.2  # there the warp copies the red square
    assert not (warped - image_t).abs()[~valid.expand_as(warped)].eq(0).all()  # a real mask
    # without moving the reference, nothing is rebuilt: the warp is doing the work
    assert (image_r - image_t).abs().amax(1, keepdim=True)[kept].mean() > 10 * err[kept].mean()


def test_inverse_warp_valid_mask_is_the_view_of_the_reference():
    """Camera moved 1 m right: a plane at 10 m moves f·1/10 = 3.2 px left, so target pixel x
    samples the reference at x − 3.2; columns 0-3 would sample left of the first pixel centre."""
    depth = torch.full((1, 1, SIZE, SIZE), 10.0, dtype=DT)
    image = torch.rand(1, 3, SIZE, SIZE, dtype=DT)
    warped, valid = rp.inverse_warp(image, depth, None, torch.tensor([-1.0, 0, 0], dtype=DT), K)
    assert valid[0, 0, :, 4:].all() and not valid[0, 0, :, :4].any()
    # bilinear between columns x − 4 (weight 0.2) and x − 3 (weight 0.8)
    expected = 0.2 * image[..., :, :-4] + 0.8 * image[..., :, 1:-3]
    torch.testing.assert_close(warped[..., :, 4:], expected)
    behind = rp.inverse_warp(image, depth, None, torch.tensor([0, 0, -11.0], dtype=DT), K)[1]
    assert not behind.any()  # every point behind the reference camera


def test_inverse_warp_agrees_with_kornia(scene_pair):
    """kornia.geometry.depth.warp_frame_depth has our conventions (pixel centres, X_ref = R X + t)
    wherever the sample is inside the reference (it pads with zeros, we with the border)."""
    image_t, depth_t, image_r, (r, t) = scene_pair
    ours, valid = rp.inverse_warp(image_r, depth_t, r, t, K)
    m = torch.eye(4, dtype=DT)
    m[:3, :3], m[:3, 3] = r, t
    theirs = kornia.geometry.depth.warp_frame_depth(image_r, depth_t, m[None], K[None])
    v = valid.expand_as(ours)
    torch.testing.assert_close(ours[v], theirs[v])


def test_gradients_flow_to_depth_and_pose(scene_pair):
    image_t, depth_t, image_r, (r, t) = scene_pair
    depth = (depth_t * 1.1).requires_grad_(True)
    t = t.clone().requires_grad_(True)
    warped, valid = rp.inverse_warp(image_r, depth, r, t, K)
    loss = rp.photometric_loss(image_t, [warped], [valid]).sum()
    xi_loss = sum(f(1 / depth, image_t, 1.0).sum() for f in rp.SMOOTH_LOSSES.values())
    (loss + xi_loss).backward()
    assert torch.isfinite(depth.grad).all() and torch.isfinite(t.grad).all()
    assert depth.grad[valid].abs().gt(0).float().mean() > 0.9
    assert t.grad.abs().sum() > 0


def test_precomputed_rays_warp_as_the_back_projection(scene_pair):
    """inverse_warp_rays (precomputed rays, hand-written ∂/∂θ) gives the warp, mask and depth
    gradient of the back-projection it replaces (reference_points + project, sampled by
    core.flow.warp) and of its autograd path (taken when the pose needs a gradient)."""
    _, depth_t, image_r, (r, t) = scene_pair
    gen = torch.Generator().manual_seed(0)
    depth = depth_t * (1 + 0.05 * torch.rand(depth_t.shape, generator=gen, dtype=DT))
    weights = torch.rand(image_r.shape, generator=gen, dtype=DT)  # a loss with every gradient
    rays, offset = rp.warp_rays(r, t, K, SIZE, SIZE)

    def run(fn):
        d = depth.clone().requires_grad_(True)
        warped, valid = fn(d)
        (warped * weights).sum().backward()
        return warped.detach(), valid, d.grad

    def back_projection(d):
        coords, z = rp.project(rp.reference_points(d, r, t, K), K)
        xs, ys = pixel_grid(SIZE, SIZE, d)
        warped, inside = warp(image_r, coords - torch.stack((xs, ys)))
        return warped, inside.unsqueeze(1) & (z > 0) & (d > 0)

    expected = run(back_projection)
    fast = run(lambda d: rp.inverse_warp_rays(image_r, d, rays, offset))
    slow = run(lambda d: rp.inverse_warp_rays(image_r, d, rays.requires_grad_(True), offset))
    assert expected[1].float().mean() > 0.8
    for got in (fast, slow):
        torch.testing.assert_close(got[0], expected[0], rtol=0, atol=1e-6)
        assert torch.equal(got[1], expected[1])
        scale = expected[2].abs().max()
        torch.testing.assert_close(got[2] / scale, expected[2] / scale, rtol=0, atol=1e-6)


# ---------------------------------------------------------------- photometric losses


def test_l1_map_gradients_are_autograds():
    """l1_map's hand-written derivative equals autograd's on |I_t − Ĩ|, with ties (zero
    difference) and a target broadcast over the batch."""
    gen = torch.Generator().manual_seed(0)
    target = torch.rand(1, 3, 5, 6, generator=gen, dtype=DT)
    warped = torch.rand(2, 3, 5, 6, generator=gen, dtype=DT)
    warped[0, :, 0] = target[0, :, 0]  # ties: zero subgradient
    weights = torch.rand(2, 1, 5, 6, generator=gen, dtype=DT)
    grads = []
    for fn in (rp.l1_map, lambda t, w: (t - w).abs().mean(1, keepdim=True)):
        t, w = target.clone().requires_grad_(True), warped.clone().requires_grad_(True)
        out = fn(t, w)
        (out * weights).sum().backward()
        grads.append((out.detach(), t.grad, w.grad))
    for ours, autograd in zip(grads[0], grads[1], strict=True):
        torch.testing.assert_close(ours, autograd, rtol=1e-12, atol=0)
    assert grads[0][2][0, :, 0].eq(0).all() and grads[0][2].ne(0).float().mean() > 0.8


def test_l1_and_dssim_maps_by_hand():
    a = torch.zeros(1, 3, 5, 5, dtype=DT)
    b = a + torch.tensor([0.1, 0.2, 0.6], dtype=DT).view(1, 3, 1, 1)
    torch.testing.assert_close(rp.l1_map(a, b), torch.full((1, 1, 5, 5), 0.3, dtype=DT))
    x = torch.rand(2, 3, 9, 9, dtype=DT)
    assert rp.dssim_map(x, x).abs().max() < 1e-6  # identical images: SSIM 1
    # mixed with α = 0.15 (eq. 5.3)
    mix = rp.photometric_map(a, b)
    torch.testing.assert_close(mix, 0.85 * rp.l1_map(a, b) + 0.15 * rp.dssim_map(a, b))


def test_kornia_ssim_is_the_textbook_ssim_with_a_3x3_gaussian_window():
    """At an interior pixel: Gaussian weights exp(−d²/(2·1.5²)) normalised over the 3x3 window,
    C1 = 0.01², C2 = 0.03² (images in [0, 1]); the border pixels use reflect padding."""
    g = torch.Generator().manual_seed(0)
    x, y = (
        torch.rand(1, 1, 6, 6, generator=g, dtype=DT),
        torch.rand(1, 1, 6, 6, generator=g, dtype=DT),
    )
    w1 = np.exp(-np.array([1.0, 0.0, 1.0]) / (2 * 1.5**2))
    w = np.outer(w1, w1) / np.outer(w1, w1).sum()

    def at(xw, yw):
        mx, my = (w * xw).sum(), (w * yw).sum()
        vx, vy = (w * xw**2).sum() - mx**2, (w * yw**2).sum() - my**2
        cxy = (w * xw * yw).sum() - mx * my
        c1, c2 = 0.01**2, 0.03**2
        return (2 * mx * my + c1) * (2 * cxy + c2) / ((mx**2 + my**2 + c1) * (vx + vy + c2))

    xn, yn = x[0, 0].numpy(), y[0, 0].numpy()
    dssim = rp.dssim_map(x, y)
    assert dssim[0, 0, 2, 3].item() == pytest.approx((1 - at(xn[1:4, 2:5], yn[1:4, 2:5])) / 2)
    xr, yr = np.pad(xn, 1, mode="reflect"), np.pad(yn, 1, mode="reflect")
    assert dssim[0, 0, 0, 0].item() == pytest.approx((1 - at(xr[0:3, 0:3], yr[0:3, 0:3])) / 2)


def test_photometric_loss_masks_sums_and_minimum_sampling():
    target = torch.zeros(1, 1, 1, 4, dtype=DT)
    w1 = torch.tensor([[[[0.1, 0.5, 0.3, 0.9]]]], dtype=DT)
    w2 = torch.tensor([[[[0.2, 0.4, 0.7, 0.8]]]], dtype=DT)
    m1 = torch.tensor([[[[True, True, False, False]]]])
    m2 = torch.tensor([[[[True, True, True, False]]]])
    l1 = dict(alpha=0.0)
    # eq. 4.23: each reference's mean over its kept pixels, summed
    total = rp.photometric_loss(target, [w1, w2], [m1, m2], **l1)
    assert total.item() == pytest.approx((0.1 + 0.5) / 2 + (0.2 + 0.4 + 0.7) / 3)
    # §4.7.2: per-pixel minimum over the references keeping it; the last pixel has none
    best = rp.photometric_loss(target, [w1, w2], [m1, m2], minimum=True, **l1)
    assert best.item() == pytest.approx((0.1 + 0.4 + 0.7) / 3)
    assert rp.photometric_loss(target, [w1], [None], **l1).item() == pytest.approx(0.45)
    nothing = torch.zeros_like(m1)
    assert rp.photometric_loss(target, [w1], [nothing], **l1).item() == 0  # not NaN


# ---------------------------------------------------------------- smooth losses

N = 12  # map side for the smooth-loss cases


def _flat_image(batch: int = 1) -> torch.Tensor:
    return torch.full((batch, 3, N, N), 0.5, dtype=DT)


def _ramp(a: float, b: float) -> torch.Tensor:
    ys, xs = torch.meshgrid(torch.arange(N, dtype=DT), torch.arange(N, dtype=DT), indexing="ij")
    return (1.0 + a * xs + b * ys)[None, None]


@pytest.mark.parametrize("name", sorted(rp.SMOOTH_LOSSES))
def test_a_constant_inverse_depth_has_zero_smooth_loss(name):
    image = torch.rand(2, 3, N, N, dtype=DT)
    xi = torch.full((2, 1, N, N), 0.1, dtype=DT, requires_grad=True)
    loss = rp.SMOOTH_LOSSES[name](xi, image, 0.5)
    assert loss.shape == (2,) and loss.abs().max() == 0
    loss.sum().backward()
    assert torch.isfinite(xi.grad).all()


def test_a_ramp_has_zero_gradient_diffusion_loss_but_not_zero_diffusion_loss():
    """ξ = 1 + 0.375·x + 0.5·y (exact in binary) on a flat image (weight 1): ‖∇ξ‖ = 0.625
    everywhere, Δξ = 0."""
    xi, image = _ramp(0.375, 0.5), _flat_image()
    for name in ("gradient_diffusion", "tvv", "robust_gradient_diffusion"):
        assert rp.SMOOTH_LOSSES[name](xi, image, 1.0).item() == 0, name
    assert rp.diffusion_loss(xi, image, 1.0).item() == 0.625**2
    assert rp.tv_loss(xi, image, 1.0).item() == 0.625
    # the ramp is not stable under diffusion: its borders flatten (thesis §4.4.6)
    assert rp.robust_diffusion_loss(xi, image, 1.0).item() > 1e-8


def test_laplacian_losses_of_a_parabola():
    """ξ = x²/2 (per pixel): Δξ = 1 at every interior pixel."""
    xs = torch.arange(N, dtype=DT)
    xi = (xs**2 / 2).expand(1, 1, N, N)
    assert rp.tvv_loss(xi, _flat_image(), 1.0).item() == pytest.approx(1.0)
    assert rp.gradient_diffusion_loss(xi, _flat_image(), 1.0).item() == pytest.approx(1.0)


def test_edge_aware_weights_by_hand():
    """A step of 1 in every channel between columns 5 and 6 of the image, and a step s of ξ at
    the same place: only the 11 forward differences of column 5 (rows 0-10) are non-zero, with
    ‖∇I‖ = 1 there, out of 11 x 11."""
    s = 0.2
    image = _flat_image()
    image[..., 6:] += 1
    xi = torch.ones(1, 1, N, N, dtype=DT)
    xi[..., 6:] += s
    for kappa in (0.5, 1.0, 3.0):
        expected = 11 * math.exp(-((1 / kappa) ** 2)) * s**2 / 121
        assert rp.diffusion_loss(xi, image, kappa).item() == pytest.approx(expected)
        expected = 11 * math.exp(-1 / kappa) * s / 121
        assert rp.tv_loss(xi, image, kappa).item() == pytest.approx(expected)
    # Laplacian losses: central differences put ‖∇I‖ = 1/2 on columns 5 and 6, where Δξ = ±s
    expected = 2 * 10 * math.exp(-((0.5 / 0.7) ** 2)) * s**2 / 100
    assert rp.gradient_diffusion_loss(xi, image, 0.7).item() == pytest.approx(expected)
    # κ = 0: no smoothing at all; κ = inf: the plain loss
    assert rp.diffusion_loss(xi, image, 0.0).item() == 0
    assert rp.diffusion_loss(xi, image, math.inf).item() == pytest.approx(11 * s**2 / 121)


def test_kappa_per_sample_solves_independent_problems_in_one_batch():
    g = torch.Generator().manual_seed(1)
    xi = torch.rand(3, 1, N, N, generator=g, dtype=DT)
    image = torch.rand(3, 3, N, N, generator=g, dtype=DT)
    kappas = torch.tensor([0.1, 1.0, 10.0], dtype=DT)
    for name, loss in rp.SMOOTH_LOSSES.items():
        together = loss(xi, image, kappas)
        alone = torch.cat([loss(xi[i : i + 1], image[i : i + 1], kappas[i]) for i in range(3)])
        torch.testing.assert_close(together, alone, msg=name)
        one_image = loss(xi, image[:1], kappas)  # broadcast against the batch of ξ
        torch.testing.assert_close(one_image, loss(xi, image[:1].expand(3, -1, -1, -1), kappas))


def test_robust_diffusion_one_step_by_hand():
    """A spike s at an interior pixel, flat image: the diffusion energy Σ‖∇ξ‖² has gradient 8s
    at the spike and −2s at its 4 neighbours; one step γ = 0.1 moves them by −0.8s and +0.2s,
    so the MSE is (0.64 + 4·0.04)·s² / N²."""
    s = 0.5
    xi = torch.zeros(1, 1, N, N, dtype=DT)
    xi[0, 0, 5, 5] = s
    loss = rp.robust_diffusion_loss(xi, _flat_image(), 1.0, steps=1)
    assert loss.item() == pytest.approx(0.8 * s**2 / N**2)


def test_robust_gradient_diffusion_one_step_by_hand():
    """ξ = x²/2: ∂x ξ = x + 1/2, div = 1 at the interior pixels. The energy Σ(div A)² moves,
    in one step γ = 0.1, only the differences at the ends of each interior row/column by 0.2:
    2·(N−2) horizontal and 2·(N−2) vertical ones, among N(N−1) of each."""
    xs = torch.arange(N, dtype=DT)
    xi = (xs**2 / 2).expand(1, 1, N, N).contiguous()
    loss = rp.robust_gradient_diffusion_loss(xi, _flat_image(), 1.0, steps=1)
    assert loss.item() == pytest.approx(0.2**2 * 4 * (N - 2) / (2 * N * (N - 1)))
    # ten steps (the default) are stable: the clone does not blow up
    assert rp.robust_gradient_diffusion_loss(xi, _flat_image(), 1.0).item() < 1.0


def test_image_gradient_norm_by_hand_and_as_kornia_computes_it():
    """I = 3x² in channel 0, 4y in channel 1, 0 in channel 2: forward differences at (y, x) are
    (3(2x + 1), 4), central ones at interior pixels (6x, 4); the norm is averaged over the 3
    channels. The central ones are kornia's spatial_gradient(mode='diff') inside the border."""
    ys, xs = torch.meshgrid(torch.arange(5, dtype=DT), torch.arange(6, dtype=DT), indexing="ij")
    image = torch.stack((3 * xs**2, 4 * ys, 0 * xs))[None]
    forward, central = rp.image_gradient_norm(image)
    fx = 3 * (2 * xs[:-1, :-1] + 1)
    torch.testing.assert_close(forward[0, 0], (fx + 4) / 3)
    torch.testing.assert_close(central[0, 0], (6 * xs[1:-1, 1:-1] + 4) / 3)
    k = kornia.filters.spatial_gradient(image, mode="diff")[..., 1:-1, 1:-1]
    torch.testing.assert_close(central, k.norm(dim=2).mean(1, keepdim=True))


# ---------------------------------------------------------------- direct warp and the ODM


def test_direct_warp_with_identity_pose_paints_every_pixel_on_itself():
    depth = 1 + 9 * torch.rand(2, 1, 16, 20, dtype=DT)
    k = torch.tensor([[15.0, 0, 9.5], [0, 15, 7.5], [0, 0, 1]], dtype=DT)
    warped, index = rp.direct_warp(depth, None, torch.zeros(3), k)
    torch.testing.assert_close(warped, depth)
    assert (index == torch.arange(16 * 20).reshape(1, 1, 16, 20)).all()


def test_direct_warp_of_a_plane_under_forward_motion_leaves_no_hole():
    """Plane at 10 m, camera 1 m forward: every reference pixel is painted, at depth 9 m, and the
    ODM finds only the target's border leaving the view: pixel x is seen when its square,
    centre cx + (x − cx)·10/9, half-width 5/9 px, covers a pixel centre ≥ 0: x ≥ 3 (by hand:
    cx + (x + ½ − cx)·10/9 > 0 for x > 2.65), and symmetrically x ≤ 60."""
    depth = torch.full((1, 1, SIZE, SIZE), 10.0, dtype=DT)
    t = torch.tensor([0, 0, -1.0], dtype=DT)
    warped, index = rp.direct_warp(depth, None, t, K)
    assert torch.isfinite(warped).all() and (index >= 0).all()
    torch.testing.assert_close(warped, torch.full_like(warped, 9.0))
    border = torch.ones(SIZE, SIZE, dtype=torch.bool)
    border[3:61, 3:61] = False
    for method in ("index", "warp_back"):
        occluded = rp.occlusion_mask(depth, None, t, K, method=method, dilation=0)
        assert (occluded[0, 0] == border).all(), method


def test_odm_finds_the_occluded_band_beside_a_foreground_square():
    """Background at 8 m, a square at 2 m (rows and columns 20-39), camera moved (0.25, 0.25, 0)
    m (right and down). Flow −f·T/Z: the background moves 1 px up-left, the square 4 px: it hides
    the background pixels whose image 3 px (= f·T·(1/2 − 1/8)) further right and down is in the
    square: rows and columns 17-36 minus the square; plus row 0 and column 0, which leave
    the view."""
    depth = torch.full((1, 1, SIZE, SIZE), 8.0, dtype=DT)
    depth[..., 20:40, 20:40] = 2.0
    t = torch.tensor([-0.25, -0.25, 0.0], dtype=DT)
    expected = torch.zeros(SIZE, SIZE, dtype=torch.bool)
    expected[17:37, 17:37] = True
    expected[20:40, 20:40] = False
    expected[0, :] = expected[:, 0] = True
    for method in ("index", "warp_back"):
        occluded = rp.occlusion_mask(depth, None, t, K, method=method, dilation=0)
        assert (occluded[0, 0] == expected).all(), method
    # the default dilation widens every occluded region by 2 pixels
    dilated = rp.occlusion_mask(depth, None, t, K)
    assert dilated[0, 0, 18, 15] and not dilated[0, 0, 18, 14] and dilated[0, 0, 2, 30]
    assert not dilated[0, 0, 3, 30] and not dilated[0, 0, 30, 30]


def painted_pixel_by_pixel(depth, rotations, translations, k, max_square):
    """Algorithm 1 one target pixel at a time (numpy, float64): pixel (x, y) at depth θ moves to
    X = R·θ·K⁻¹(x, y, 1) + t; in front of the reference (Z > 0) its square of side
    d = min(θ/Z, max_square), from its projection minus d/2, paints the pixel centres it covers
    (half-open); the nearest Z wins, then the smallest source index. ``(zbuf, index)``."""
    b, h, w = depth.shape
    zbuf, index = np.full((b, h, w), np.inf), np.full((b, h, w), -1)
    kinv = np.linalg.inv(k)
    for s in range(b):
        for y in range(h):
            for x in range(w):
                point = rotations[s] @ (depth[s, y, x] * kinv @ [x, y, 1.0]) + translations[s]
                if point[2] <= 0:
                    continue
                u, v = (k @ point)[:2] / point[2]
                side = min(depth[s, y, x] / point[2], max_square)
                for yy in range(max(math.ceil(v - side / 2), 0), h):
                    for xx in range(max(math.ceil(u - side / 2), 0), w):
                        inside = xx < u + side / 2 and yy < v + side / 2
                        nearer = point[2] < zbuf[s, yy, xx] or (
                            point[2] == zbuf[s, yy, xx] and y * w + x < index[s, yy, xx]
                        )
                        if inside and nearer:
                            zbuf[s, yy, xx], index[s, yy, xx] = point[2], y * w + x
    return zbuf, index


@pytest.mark.parametrize("max_square", [rp.MAX_SQUARE, 2.0])
def test_direct_warp_matches_a_pixel_by_pixel_painter(max_square):
    """Near points moving closer make squares of several pixels that overlap (clipped to 2 px in
    the second case); the second sample moves backward (squares under a pixel: holes)."""
    rng = np.random.default_rng(3)
    depth = 4 + 8 * rng.random((2, 10, 12))
    depth[:, 3:6, 4:8] = 0.4 + 0.1 * rng.random((2, 1, 1))
    k = np.array([[9.0, 0, 5.5], [0, 9, 4.5], [0, 0, 1]])
    rotations = np.stack(
        [rotation_vector_to_matrix(r) for r in ([0.02, -0.03, 0.01], [0, 0.02, 0])]
    )
    translations = np.array([[0.1, -0.05, -0.35], [-0.2, 0.1, 0.3]])
    expected_z, expected_index = painted_pixel_by_pixel(
        depth, rotations, translations, k, max_square
    )
    warped, index = rp.direct_warp(
        torch.from_numpy(depth)[:, None], torch.from_numpy(rotations),
        torch.from_numpy(translations), torch.from_numpy(k), max_square,
    )  # fmt: skip
    painted_by_one = np.bincount(expected_index[0][expected_index[0] >= 0])
    assert painted_by_one.max() == (16 if max_square > 3 else 4)  # 4x4 squares, or 2x2 clipped
    assert (expected_index[1] < 0).any()
    assert (index[:, 0].numpy() == expected_index).all()
    torch.testing.assert_close(warped[:, 0], torch.from_numpy(expected_z))


def test_direct_warp_is_per_sample_in_a_batch():
    d1 = torch.full((1, 1, 16, 16), 5.0, dtype=DT)
    d2 = d1.clone()
    d2[..., 4:9, 4:9] = 1.0
    t = torch.tensor([[-0.3, 0.1, 0.2], [0.2, -0.1, -0.3]], dtype=DT)
    k = torch.tensor([[8.0, 0, 7.5], [0, 8, 7.5], [0, 0, 1]], dtype=DT)
    both = rp.direct_warp(torch.cat((d1, d2)), None, t, k)
    for i, d in enumerate((d1, d2)):
        alone = rp.direct_warp(d, None, t[i], k)
        assert torch.equal(both[0][i], alone[0][0]) and torch.equal(both[1][i], alone[1][0])


def test_occlusion_method_is_checked():
    with pytest.raises(ValueError, match="occlusion method"):
        rp.occlusion_mask(torch.ones(1, 1, 4, 4), None, torch.zeros(3), K, method="nope")


def test_invert_pose_round_trip():
    r = torch.from_numpy(rotation_vector_to_matrix([0.1, -0.2, 0.3]))
    t = torch.tensor([0.5, -1.0, 2.0], dtype=DT)
    ri, ti = rp.invert_pose(r, t)
    torch.testing.assert_close(ri @ r, torch.eye(3, dtype=DT))
    torch.testing.assert_close(ri @ t + ti, torch.zeros(3, dtype=DT))


# ---------------------------------------------------------------- a rendered pair


def test_a_rendered_pair_warped_with_its_true_depth_and_pose(tiny_dataset):
    """A real Cycles pair of the tiny dataset, frames 9 → 0 of a scene (0.9 m apart): the
    reference warped with the target's true depth and the recorded poses matches the target,
    away from occlusions and the view's edge, far better than the unwarped reference or a warp
    with the inverse pose do (what is left is render noise and 64 px aliasing)."""
    from stillbox_gen.dataset import Dataset

    scene = Dataset(tiny_dataset).scenes()[0]
    target, reference = 9, 0

    def image(frame: int) -> torch.Tensor:
        return torch.from_numpy(scene.load_rgb(frame)).permute(2, 0, 1)[None].double() / 255

    image_t, image_r = image(target), image(reference)
    depth = torch.from_numpy(scene.load_depth(target).astype(np.float64))[None, None]
    k = torch.from_numpy(scene.K)

    def error(rel: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        r, t = torch.from_numpy(rel[:3, :3]), torch.from_numpy(rel[:3, 3])
        warped, valid = rp.inverse_warp(image_r, depth, r, t, k)
        kept = valid & ~rp.occlusion_mask(depth, r, t, k)
        assert kept.float().mean() > 0.3
        before = (image_r - image_t).abs().mean(1, keepdim=True)[kept].mean()
        return (warped - image_t).abs().mean(1, keepdim=True)[kept].mean(), before

    err, before = error(scene.relative_pose(target, reference))
    wrong, _ = error(scene.relative_pose(reference, target))
    assert err < 0.6 * before and err < 0.5 * wrong and err < 0.04, (err, before, wrong)


# ---------------------------------------------------------------- the fast SSIM


@pytest.mark.parametrize("shape", [(2, 3, 7, 9), (3, 2, 4, 3, 6, 5)])
def test_gaussian_blur_is_reflect_padding_and_a_separable_convolution(shape):
    """Against torch's reflect padding and a 2-D convolution with the outer product of the taps
    (an independent route), and its hand-written backward against autograd's numerical check."""
    g = torch.Generator().manual_seed(0)
    x = torch.rand(shape, generator=g, dtype=DT)
    for taps in (rp.ssim_taps(x), torch.tensor([0.1, 0.2, 0.4, 0.2, 0.1], dtype=DT)):
        half = len(taps) // 2
        flat = x.reshape(-1, 1, *shape[-2:])
        padded = torch.nn.functional.pad(flat, (half,) * 4, mode="reflect")
        theirs = torch.nn.functional.conv2d(padded, torch.outer(taps, taps)[None, None])
        torch.testing.assert_close(rp.gaussian_blur(x, taps), theirs.view(shape))
        leaf = x.clone().requires_grad_()
        assert torch.autograd.gradcheck(lambda v, t=taps: rp.gaussian_blur(v, t), (leaf,))


def test_dssim_map_is_kornias_with_one_target_for_many_references():
    """The broadcast target (its statistics computed once) gives kornia's map and gradients,
    which repeat the target for every reference; float32 within 1e-5 (the order of the sums
    differs: rounding reaches 1.3e-6 on these random images)."""
    g = torch.Generator().manual_seed(1)
    target = torch.rand(1, 2, 1, 3, 12, 10, generator=g)
    warped = torch.rand(5, 2, 4, 3, 12, 10, generator=g).requires_grad_()
    weights = torch.rand(5, 2, 4, 1, 12, 10, generator=g)
    ours = rp.dssim_map(target, warped)
    (ours * weights).sum().backward()
    ours_grad, warped.grad = warped.grad, None
    flat = warped.reshape(-1, 3, 12, 10)
    theirs = rp.kornia_dssim_map(target.expand_as(warped).reshape(-1, 3, 12, 10), flat)
    (theirs.view_as(ours) * weights).sum().backward()
    torch.testing.assert_close(ours, theirs.view_as(ours), rtol=0, atol=1e-5)
    torch.testing.assert_close(ours_grad, warped.grad, rtol=0, atol=1e-5)


def test_dssim_hand_backward_matches_autograd_in_double():
    g = torch.Generator().manual_seed(2)
    target = torch.rand(1, 3, 7, 8, generator=g, dtype=DT)
    warped = torch.rand(4, 3, 7, 8, generator=g, dtype=DT).requires_grad_()
    assert torch.autograd.gradcheck(lambda w: rp.dssim_map(target, w), (warped,))
    # a target that needs a gradient goes through autograd, the same values
    t = target.clone().requires_grad_()
    torch.testing.assert_close(rp.dssim_map(t, warped), rp.dssim_map(target, warped))
