"""Reprojection: warps, photometric and smooth losses, occlusion detection (thesis chapter 4).

The pieces that learn depth from video without ground truth: a depth map of a *target* frame and
the relative pose of a *reference* frame reproject the reference onto the target (inverse warp,
eq. 4.2); the photometric loss compares the two (eq. 5.3, §4.7.2); smooth losses regularise the
inverse depth (eqs. 4.18-4.21, §4.4.5); the occlusion detection module (ODM, §4.5.6, Algorithm 1)
finds the target pixels hidden in the reference, to drop from the photometric loss.

Conventions (the dataset's, docs/FORMAT.md; the same as :mod:`benchmark.core.flow`):

- Every image, depth map, loss map and mask is batched ``(B, C, H, W)``, ``C = 1`` for depth,
  inverse depth ``ξ = 1/θ``, masks and per-pixel losses. Images are RGB in ``[0, 1]``.
- OpenCV camera axes: x right, y down, z forward. Pixel coordinates ``(x, y)``, the centre of the
  top-left pixel at ``(0, 0)``; ``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``, ``(B, 3, 3)`` or
  ``(3, 3)``, pixels.
- Depth ``θ`` is planar depth along the optical axis, metres.
- Pose: ``rotation`` ``R`` and ``translation`` ``t`` map *target* camera coordinates to *reference*
  camera coordinates, ``X_ref = R·X_tgt + t`` (metres; ``(B, 3, 3)`` / ``(B, 3)`` or unbatched).
  For two frames of a dataset scene, ``scene.relative_pose(target, reference)`` is ``[R | t]``.
  For a stabilised camera (``R = I``) that moves by ``T`` from target to reference (in target
  axes), ``t = −T``: the opposite sign of :mod:`benchmark.core.flow`'s displacement.
- Smooth losses take the inverse depth ``ξ = 1/θ`` ``(B, 1, H, W)`` (1/m), the frame ``I`` it
  belongs to (``(B, C, H, W)``, or batch 1 for all), and κ (a number, or one per sample ``(B,)``).
- Losses are returned per sample, ``(B,)``, so that a batch may hold independent problems (e.g.
  a grid of hyper-parameters); ``.mean()`` or ``.sum()`` them. Means over pixels replace the
  thesis' integrals ``∬_Ω dS``.

Choices the thesis leaves open, and where this differs from the author's later code
(ClementPinard/unsupervised-depthnet, ``loss_functions.py``, ``inverse_warp.py``; the thesis is
followed where they differ):

- Discretisation: ``∇ξ`` by forward differences (central ones cannot see a checkerboard), ``Δξ``
  the 5-point Laplacian at interior pixels only (so a ramp has exactly zero Laplacian losses; the
  thesis discusses the boundary terms in §4.4.6). ``‖∇I‖`` is the mean over channels of each
  channel's gradient norm, as §4.4.9 says; the author's ``grad_diffusion_loss`` instead weighs
  ``∂xx ξ`` and ``∂yy ξ`` separately (``(∂xx ξ)² + (∂yy ξ)²``, not the thesis' ``(Δξ)²``) by the
  per-axis central difference of the channel-summed image.
- Robust losses: the inner descent uses the integral (sum) form of the loss, so that γ = 0.1 is
  a real diffusion step (on a mean, 10 steps of 0.1 would barely move a 200 px map). Robust
  gradient diffusion diffuses ``∇ξ`` (see :func:`robust_gradient_diffusion_loss`).
- SSIM pads with reflection (kornia); the author's pads with zeros (on images shifted by +1).
- The inverse warp masks points behind the reference camera; the author's clamps their depth to
  1e-3 m and keeps them.
- The direct warp paints half-open squares (:func:`direct_warp`); Algorithm 1 rounds.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import kornia
import torch
import torch.nn.functional as F

from ..core.flow import pixel_grid

#: Weight α of DSSIM against L1 in the photometric loss (eq. 5.3).
SSIM_WEIGHT = 0.15
#: Side of SSIM's Gaussian window, pixels (σ = 1.5, kornia's); the author's code uses 3 too.
SSIM_WINDOW = 3
#: Robust smooth losses (§4.6.2): gradient-descent steps on the detached clone, and their step γ.
ROBUST_STEPS = 10
ROBUST_STEP = 0.1
#: ODM "warp back": a target pixel is seen in the reference when its depth warped there and back
#: is within this ratio of its own depth (the thesis' α > 1; it gives no value: our choice).
ODM_DEPTH_RATIO = 1.1
#: ODM: occluded pixels are dilated by this many pixels (Fig. 4.10: "erosion of valid pixels by 2").
ODM_DILATION = 2
#: Direct warp: largest side of a projected square, pixels (squares of points very close to the
#: reference camera are clipped to it, which bounds the work).
MAX_SQUARE = 16.0


# ---------------------------------------------------------------- geometry


def _pose(
    rotation: torch.Tensor | None, translation: torch.Tensor, batch: int, like: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(R (B, 3, 3), t (B, 3, 1))`` in ``like``'s dtype and device; ``None`` is the identity."""
    t = torch.as_tensor(translation).to(like).reshape(-1, 3, 1).expand(batch, 3, 1)
    if rotation is None:
        rotation = torch.eye(3)
    r = torch.as_tensor(rotation).to(like).reshape(-1, 3, 3).expand(batch, 3, 3)
    return r, t


def _intrinsics(K: torch.Tensor, batch: int, like: torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(K).to(like).reshape(-1, 3, 3).expand(batch, 3, 3)


def invert_pose(
    rotation: torch.Tensor | None, translation: torch.Tensor
) -> tuple[torch.Tensor | None, torch.Tensor]:
    """The reference → target pose of a target → reference one: ``(Rᵀ, −Rᵀ·t)``."""
    if rotation is None:
        return None, -torch.as_tensor(translation)
    rt = torch.as_tensor(rotation).transpose(-1, -2)
    return rt, -(rt @ torch.as_tensor(translation).unsqueeze(-1)).squeeze(-1)


def reference_points(
    depth: torch.Tensor, rotation: torch.Tensor | None, translation: torch.Tensor, K: torch.Tensor
) -> torch.Tensor:
    """The target's pixels back-projected with ``depth`` and moved to reference camera coordinates.

    ``depth``: ``(B, 1, H, W)`` metres. Returns ``(B, 3, H, W)`` points ``R·θ·K⁻¹(x, y, 1) + t``,
    metres, in the reference camera's OpenCV axes.
    """
    b, _, h, w = depth.shape
    r, t = _pose(rotation, translation, b, depth)
    rays = torch.linalg.inv(_intrinsics(K, b, depth)) @ _pixels(h, w, depth)
    return (r @ (rays * depth.reshape(b, 1, h * w)) + t).reshape(b, 3, h, w)


def _pixels(height: int, width: int, like: torch.Tensor) -> torch.Tensor:
    """Homogeneous pixel-centre coordinates ``(x, y, 1)``, ``(1, 3, H·W)``."""
    xs, ys = pixel_grid(height, width, like)
    return torch.stack((xs, ys, torch.ones_like(xs))).reshape(1, 3, height * width)


def warp_rays(
    rotation: torch.Tensor | None,
    translation: torch.Tensor,
    K: torch.Tensor,
    height: int,
    width: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The per-pixel constants of :func:`inverse_warp` for a fixed pose and camera.

    A target pixel ``p`` at depth ``θ`` lands in the reference at the homogeneous pixel
    ``K·(R·θ·K⁻¹p + t) = θ·a(p) + c`` with ``a(p) = K·R·K⁻¹·p`` and ``c = K·t``: linear in
    ``θ``, so that a depth map optimised against fixed frames (the toy study) pays per
    iteration only for this affine map and the sampling, not for the back-projection.

    Returns ``a`` ``(B, 3, H, W)`` (homogeneous pixels) and ``c`` ``(B, 3, 1, 1)`` (homogeneous
    pixels × metres), in the dtype and device of ``translation`` (float32 if it is an integer
    tensor; B = the batch of the pose or K, 1 if unbatched). Use them with
    :func:`inverse_warp_rays`.
    """
    like = torch.as_tensor(translation)
    if not like.is_floating_point():
        like = like.float()
    batch = max(
        like.reshape(-1, 3).shape[0],
        torch.as_tensor(K).reshape(-1, 9).shape[0],
        1 if rotation is None else torch.as_tensor(rotation).reshape(-1, 9).shape[0],
    )
    r, t = _pose(rotation, translation, batch, like)
    k = _intrinsics(K, batch, like)
    rays = k @ (r @ (torch.linalg.inv(k) @ _pixels(height, width, like)))
    return rays.reshape(batch, 3, height, width), (k @ t).reshape(batch, 3, 1, 1)


def project(points: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel coordinates ``(B, 2, H, W)`` and depth ``z`` ``(B, 1, H, W)`` of camera-frame points.

    Division by ``z`` is guarded (``z`` clamped to 1e-6 m) so that points behind the camera give
    finite coordinates and gradients; mask them with ``z > 0``.
    """
    b, _, h, w = points.shape
    hom = (_intrinsics(K, b, points) @ points.reshape(b, 3, h * w)).reshape(b, 3, h, w)
    z = hom[:, 2:]
    return hom[:, :2] / z.clamp(min=1e-6), z


def inverse_warp(
    reference: torch.Tensor,
    depth: torch.Tensor,
    rotation: torch.Tensor | None,
    translation: torch.Tensor,
    K: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The reference frame resampled on the target's grid with the target's depth (eq. 4.2).

    ``out(p) = I_ref(Π(K·(R·θ(p)·K⁻¹p + t)))``, bilinear at pixel-centre coordinates (by
    :func:`inverse_warp_rays`, after :func:`warp_rays`), differentiable with respect to
    ``reference``, ``depth`` and the pose.

    Args:
        reference: ``(B, C, H, W)`` reference frame.
        depth: ``(B, 1, H, W)`` target depth, metres.
        rotation, translation: target → reference pose (module doc); ``rotation`` may be None.
        K: intrinsics, pixels (the same camera for both frames).

    Returns:
        The warped frame ``(B, C, H, W)`` and a ``(B, 1, H, W)`` bool mask of the pixels whose
        point is in front of the reference camera and projects inside it (within the pixel
        centres ``[0, W − 1] × [0, H − 1]``, so all four bilinear neighbours exist).
    """
    h, w = depth.shape[2:]
    t = torch.as_tensor(translation).to(depth)
    return inverse_warp_rays(reference, depth, *warp_rays(rotation, t, K, h, w))


def rotate_frame(
    reference: torch.Tensor, rotation: torch.Tensor, K: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The reference frame seen with the target's orientation (eq. 5.1, thesis §5.2.2).

    ``out(p) = I_ref(Π(K·R·K⁻¹p))``: :func:`inverse_warp` with a zero translation, where the
    depth drops out (any positive depth gives the same pixels). ``rotation`` ``(B, 3, 3)`` is
    the target → reference rotation (module doc), ``K`` pixels. Returns the warped frame
    ``(B, C, H, W)`` and the mask of pixels seen by the reference (outside it, the frame's
    border pixels, as :func:`inverse_warp`)."""
    b, _, h, w = reference.shape
    ones = reference.new_ones(b, 1, h, w)
    return inverse_warp(reference, ones, rotation, reference.new_zeros(b, 3), K)


def inverse_warp_rays(
    reference: torch.Tensor, depth: torch.Tensor, rays: torch.Tensor, offset: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`inverse_warp` from the precomputed constants of :func:`warp_rays`.

    ``reference`` ``(B, C, H, W)``, ``depth`` ``(B, 1, H, W)`` metres, ``rays`` ``(B or 1, 3,
    H, W)``, ``offset`` ``(B or 1, 3, 1, 1)``. The reference pixel of ``p`` is
    ``(θ·a + c)_xy / (θ·a + c)_z`` (the depth clamped to 1e-6 m as in :func:`project`), sampled
    bilinearly at pixel-centre coordinates (``grid_sample``, ``align_corners=True``, the
    sampling of :func:`benchmark.core.flow.warp`). Differentiable with respect to ``reference``
    and ``depth``. Returns the warped frame and the valid mask, as :func:`inverse_warp`.
    """
    h, w = depth.shape[2:]
    if rays.requires_grad or offset.requires_grad:  # a pose to optimise: autograd throughout
        grid, x, y, z = _project_rays(depth, rays, offset)
    else:
        grid, x, y, z = _RayProjection.apply(depth, rays, offset)
    with torch.no_grad():  # NaN fails every comparison: no isfinite needed
        inside = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    grid = torch.nan_to_num(grid, nan=-2.0).to(reference.dtype)
    out = F.grid_sample(reference, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out, inside.unsqueeze(1) & (z > 0) & (depth > 0)


def _project_rays(
    depth: torch.Tensor, rays: torch.Tensor, offset: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """:class:`_RayProjection`'s forward by autograd (differentiable in the rays and offset)."""
    h, w = depth.shape[2:]
    hom = depth * rays + offset
    z = hom[:, 2:]
    xy = hom[:, :2] / z.clamp(min=1e-6)
    x, y = xy[:, 0], xy[:, 1]
    grid = torch.stack((x * (2 / max(w - 1, 1)) - 1, y * (2 / max(h - 1, 1)) - 1), dim=-1)
    return grid, x.detach(), y.detach(), z.detach()


class _RayProjection(torch.autograd.Function):
    """``θ ↦`` grid_sample's grid of :func:`inverse_warp_rays`, with its derivative by hand.

    Forward: ``z = θ·a_z + c_z``, ``x = (θ·a_x + c_x) / ẑ``, ``y`` alike (``ẑ = max(z, 1e-6)``),
    and the grid ``(2x / (W − 1) − 1, 2y / (H − 1) − 1)`` ``(B, H, W, 2)``. Backward (to ``θ``
    only; the rays and the offset are constants): ``∂x/∂θ = (a_x − a_z·x) / ẑ``, ``y`` alike (the
    clamp's zero derivative is dropped: such points are masked out). Saves autograd's
    three-channel intermediate tensors, the cost of the toy study's iterations.
    Returns ``(grid, x (B, H, W), y (B, H, W), z (B, 1, H, W))``; only ``grid`` has a gradient.
    """

    @staticmethod
    def forward(ctx, depth, rays, offset):  # noqa: ANN001, ANN205 (autograd's signature)
        h, w = depth.shape[2:]
        sx, sy = 2 / max(w - 1, 1), 2 / max(h - 1, 1)
        z = torch.addcmul(offset[:, 2:], depth, rays[:, 2:])
        inv = 1 / z.clamp(min=1e-6)
        x = (torch.addcmul(offset[:, 0:1], depth, rays[:, 0:1]) * inv)[:, 0]
        y = (torch.addcmul(offset[:, 1:2], depth, rays[:, 1:2]) * inv)[:, 0]
        grid = torch.stack((x * sx - 1, y * sy - 1), dim=-1)
        ctx.save_for_backward(rays, x, y, inv)
        ctx.scale, ctx.depth_shape = (sx, sy), depth.shape
        ctx.mark_non_differentiable(x, y, z)
        return grid, x, y, z

    @staticmethod
    def backward(ctx, grad_grid, *_):  # noqa: ANN001, ANN205
        rays, x, y, inv = ctx.saved_tensors
        sx, sy = ctx.scale
        dx = (rays[:, 0] - rays[:, 2] * x) * grad_grid[..., 0]
        dy = (rays[:, 1] - rays[:, 2] * y) * grad_grid[..., 1]
        grad = (dx * sx + dy * sy).unsqueeze(1) * inv
        if grad.shape != ctx.depth_shape:  # a depth broadcast over a batch of rays
            grad = grad.sum(0, keepdim=True)
        return grad, None, None


# ---------------------------------------------------------------- photometric losses


def l1_map(target: torch.Tensor, warped: torch.Tensor) -> torch.Tensor:
    """``|I_t − Ĩ|`` averaged over channels (dim −3), ``(…, 1, H, W)``; ``target`` broadcasts
    against ``warped`` (e.g. one target for several references)."""
    return _L1Map.apply(target, warped)


class _L1Map(torch.autograd.Function):
    """:func:`l1_map` with its derivative by hand, ``±sign(Ĩ − I_t)·g / C`` (autograd's values,
    0 where equal), from one saved sign tensor instead of autograd's several passes over the
    frames (the photometric loss's main cost in the toy study)."""

    @staticmethod
    def forward(ctx, target, warped):  # noqa: ANN001, ANN205 (autograd's signature)
        diff = warped - target
        ctx.save_for_backward(diff.sign())
        ctx.target_shape, ctx.warped_shape = target.shape, warped.shape
        return diff.abs().mean(-3, keepdim=True)

    @staticmethod
    def backward(ctx, grad):  # noqa: ANN001, ANN205
        (sign,) = ctx.saved_tensors
        grad_warped = sign * (grad / sign.shape[-3])
        grad_target = None
        if ctx.needs_input_grad[0]:
            grad_target = (-grad_warped).sum_to_size(ctx.target_shape)
        if ctx.needs_input_grad[1]:
            return grad_target, grad_warped.sum_to_size(ctx.warped_shape)
        return grad_target, None


def gaussian_blur(x: torch.Tensor, taps: torch.Tensor) -> torch.Tensor:
    """``x`` filtered by the separable window ``taps`` (odd length, symmetric, a constant) along
    its last two dimensions, with reflect padding (``F.pad(mode="reflect")``'s: the border pixel
    is not repeated), any leading dimensions. Shifted slices instead of a depthwise convolution,
    with the backward pass by hand (:class:`_Blur`): on a CPU the convolution's backward pass
    was most of an unsupervised step's time."""
    return _Blur.apply(_Blur.apply(x, taps, -2), taps, -1)


def _correlate(padded: torch.Tensor, taps: torch.Tensor, dim: int, n: int) -> torch.Tensor:
    """``Σ_k taps[k]·padded[k : k + n]`` along ``dim`` (symmetric taps: pairs added first)."""
    half = len(taps) // 2
    out = taps[half] * padded.narrow(dim, half, n)
    for k in range(half):
        out = out + taps[k] * (padded.narrow(dim, k, n) + padded.narrow(dim, 2 * half - k, n))
    return out


class _Blur(torch.autograd.Function):
    """One axis of :func:`gaussian_blur`: reflect padding by ``half`` then the correlation.
    Backward: the same correlation of the gradient zero-padded by twice ``half`` (the
    transpose of a symmetric window), then each padding pixel's share added back to the pixel
    it mirrors (the transpose of reflect padding), without autograd's zero-filled slices."""

    @staticmethod
    def forward(ctx, x, taps, dim):  # noqa: ANN001, ANN205 (autograd's signature)
        half, n = len(taps) // 2, x.shape[dim]
        left, right = x.narrow(dim, 1, half).flip(dim), x.narrow(dim, n - 1 - half, half).flip(dim)
        ctx.save_for_backward(taps)
        ctx.dim = dim
        return _correlate(torch.cat((left, x, right), dim), taps, dim, n)

    @staticmethod
    def backward(ctx, grad):  # noqa: ANN001, ANN205
        (taps,) = ctx.saved_tensors
        return _Blur.backward_of(grad, taps, ctx.dim), None, None

    @staticmethod
    def backward_of(grad: torch.Tensor, taps: torch.Tensor, dim: int) -> torch.Tensor:
        """The transpose of one axis of the blur applied to ``grad``."""
        half, n = len(taps) // 2, grad.shape[dim]
        axis = dim % grad.dim()
        zeros = grad.new_zeros(grad.shape[:axis] + (2 * half,) + grad.shape[axis + 1 :])
        # the gradient of each padded pixel, x's (centre) and the mirrored ones (both ends)
        padded = _correlate(torch.cat((zeros, grad, zeros), dim), taps, dim, n + 2 * half)
        out = padded.narrow(dim, half, n).clone()
        # the padding pixel j (left) mirrors x[half − j]; the right one j mirrors x[n − 2 − j]
        out.narrow(dim, 1, half).add_(padded.narrow(dim, 0, half).flip(dim))
        out.narrow(dim, n - 1 - half, half).add_(padded.narrow(dim, n + half, half).flip(dim))
        return out


def ssim_taps(like: torch.Tensor) -> torch.Tensor:
    """SSIM's window: kornia's 1-D Gaussian of :data:`SSIM_WINDOW` taps, σ = 1.5, sum 1."""
    return kornia.filters.get_gaussian_kernel1d(
        SSIM_WINDOW, 1.5, device=like.device, dtype=like.dtype
    ).reshape(-1)


def dssim_map(target: torch.Tensor, warped: torch.Tensor) -> torch.Tensor:
    """``(1 − SSIM) / 2`` clipped to ``[0, 1]``, averaged over channels (dim −3), ``(…, 1, H, W)``.

    SSIM is kornia's (:func:`kornia.metrics.ssim`, same values to float rounding): Gaussian window
    of :data:`SSIM_WINDOW` pixels, σ = 1.5, ``C1 = 0.01²``, ``C2 = 0.03²`` for images in ``[0, 1]``,
    ε = 1e-12 in the denominator, reflect padding at the border (the author's code pads with
    zeros). ``target`` broadcasts against ``warped``: its local mean and variance are computed
    once for all the references it is compared with. A pixel's window may reach pixels that a
    mask drops (as in the author's code). Differentiable in ``warped`` by hand
    (:class:`_DSSIM`) when ``target`` needs no gradient (the training's frames), else by autograd.
    """
    taps = ssim_taps(warped)
    if target.requires_grad:
        return _dssim(target, warped, taps)
    return _DSSIM.apply(target, warped, taps)


#: SSIM's constants for images in [0, 1] (kornia's: (0.01·L)², (0.03·L)², ε)
SSIM_C1, SSIM_C2, SSIM_EPS = 0.01**2, 0.03**2, 1e-12


def _ssim_terms(target, warped, taps):  # noqa: ANN001, ANN202
    """SSIM's factors ``(a, b, c, d)``: SSIM = a·b / (c·d + ε), and the local means."""
    mu_t, mu_w = gaussian_blur(target, taps), gaussian_blur(warped, taps)
    var_t = gaussian_blur(target * target, taps) - mu_t * mu_t
    var_w = gaussian_blur(warped * warped, taps) - mu_w * mu_w
    cov = gaussian_blur(target * warped, taps) - mu_t * mu_w
    a, b = 2.0 * mu_t * mu_w + SSIM_C1, 2.0 * cov + SSIM_C2
    c, d = mu_t * mu_t + mu_w * mu_w + SSIM_C1, var_t + var_w + SSIM_C2
    return a, b, c, d, mu_t, mu_w


def _dssim(target, warped, taps):  # noqa: ANN001, ANN202
    a, b, c, d, _, _ = _ssim_terms(target, warped, taps)
    ssim = a * b / (c * d + SSIM_EPS)
    return ((1 - ssim) / 2).clamp(0, 1).mean(-3, keepdim=True)


class _DSSIM(torch.autograd.Function):
    """:func:`dssim_map` with its derivative to ``warped`` by hand (the target is a constant).

    With SSIM = a·b/q, q = c·d + ε, and ``a = 2·μ_t·μ_w + C1``, ``b = 2·(E[t·w] − μ_t·μ_w) + C2``,
    ``c = μ_t² + μ_w² + C1``, ``d = σ_t² + E[w²] − μ_w² + C2`` (E the Gaussian window's mean):
    ``∂S/∂μ_w = 2·μ_t·(b − a)/q + 2·μ_w·S·(c − d)/q``, ``∂S/∂E[t·w] = 2·a/q``,
    ``∂S/∂E[w²] = −S·c/q``; each goes back through the window's transpose (:class:`_Blur`), and
    ``E[w²]``, ``E[t·w]`` to ``w`` by ``2·w``, ``t``. The clamp passes the gradient where
    ``0 ≤ (1 − S)/2 ≤ 1`` (torch's). Saves autograd's dozen full-size intermediates."""

    @staticmethod
    def forward(ctx, target, warped, taps):  # noqa: ANN001, ANN205 (autograd's signature)
        a, b, c, d, mu_t, mu_w = _ssim_terms(target, warped, taps)
        q = c * d + SSIM_EPS
        ssim = a * b / q
        half = (1 - ssim) / 2
        ctx.save_for_backward(target, warped, taps, a, b, c, d, q, ssim, mu_t, mu_w)
        return half.clamp(0, 1).mean(-3, keepdim=True)

    @staticmethod
    def backward(ctx, grad):  # noqa: ANN001, ANN205
        target, warped, taps, a, b, c, d, q, ssim, mu_t, mu_w = ctx.saved_tensors
        half = (1 - ssim) / 2
        g = grad * (-0.5 / warped.shape[-3]) * ((half >= 0) & (half <= 1))  # dL/dS
        g_q = g / q
        g_mu = 2 * g_q * (mu_t * (b - a) + mu_w * ssim * (c - d))
        g_tw, g_ww = 2 * g_q * a, -g_q * ssim * c

        def back(x: torch.Tensor) -> torch.Tensor:  # the window's transpose, both axes
            return _Blur.backward_of(_Blur.backward_of(x, taps, -1), taps, -2)

        grad_w = back(g_mu) + 2 * warped * back(g_ww) + target * back(g_tw)
        return None, grad_w.sum_to_size(warped.shape), None


def kornia_dssim_map(target: torch.Tensor, warped: torch.Tensor) -> torch.Tensor:
    """:func:`dssim_map` by :func:`kornia.metrics.ssim` (``(B, C, H, W)`` both, no broadcasting):
    the independent implementation it is tested against, and the speed baseline."""
    ssim = kornia.metrics.ssim(target, warped, SSIM_WINDOW, max_val=1.0)
    return ((1 - ssim) / 2).clamp(0, 1).mean(1, keepdim=True)


def photometric_map(
    target: torch.Tensor, warped: torch.Tensor, alpha: float = SSIM_WEIGHT
) -> torch.Tensor:
    """Per-pixel photometric error ``(1 − α)·|I_t − Ĩ| + α·(1 − SSIM)/2`` (eq. 5.3),
    ``(…, 1, H, W)``; ``target`` broadcasts against ``warped``.

    ``alpha = 0`` is the plain L1 distance of the thesis' toy problems (§4.7.3).
    """
    out = l1_map(target, warped)
    if alpha:
        out = (1 - alpha) * out + alpha * dssim_map(target, warped)
    return out


def masked_mean(values: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean of ``(B, 1, H, W)`` values over the pixels where ``mask`` is True, per sample ``(B,)``.

    A sample without any kept pixel gives 0 (and no gradient), not NaN.
    """
    if mask is None:
        return values.flatten(1).mean(1)
    mask = mask.expand_as(values)
    total = torch.where(mask, values, torch.zeros_like(values)).flatten(1).sum(1)
    return total / mask.flatten(1).sum(1).clamp(min=1)


def photometric_loss(
    target: torch.Tensor,
    warped: Sequence[torch.Tensor],
    masks: Sequence[torch.Tensor | None],
    alpha: float = SSIM_WEIGHT,
    minimum: bool = False,
) -> torch.Tensor:
    """Photometric loss of a target against its warped references, per sample ``(B,)``.

    Args:
        target: ``(B, C, H, W)`` target frame ``I_t``.
        warped: the references warped to the target, each ``(B, C, H, W)``.
        masks: for each reference, a ``(B, 1, H, W)`` bool mask of the pixels to keep (the
            inverse warp's valid mask, minus the ODM's occluded pixels), or None for all.
        alpha: DSSIM weight (eq. 5.3).
        minimum: False: eq. 5.3 / 4.23, the sum over references of each one's mean error over its
            kept pixels. True: minimal loss sampling (§4.7.2), the mean over pixels of the
            smallest error among the references that keep the pixel; a pixel no reference keeps
            is left out.
    """
    if len(warped) != len(masks) or not warped:
        raise ValueError("photometric_loss needs one mask (or None) per warped reference")
    maps = [photometric_map(target, w, alpha) for w in warped]
    full = [
        torch.ones_like(m, dtype=torch.bool) if k is None else k
        for m, k in zip(maps, masks, strict=True)
    ]
    if not minimum:
        return sum(masked_mean(m, k) for m, k in zip(maps, full, strict=True))
    inf = torch.tensor(float("inf"), dtype=maps[0].dtype, device=maps[0].device)
    stacked = torch.cat([torch.where(k, m, inf) for m, k in zip(maps, full, strict=True)], 1)
    best = stacked.min(1, keepdim=True).values
    kept = torch.isfinite(best)
    return masked_mean(torch.where(kept, best, torch.zeros_like(best)), kept)


# ---------------------------------------------------------------- smooth losses


def _forward_gradient(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Forward differences ``(x[:, :, i, j+1] − x[i, j], x[i+1, j] − x[i, j])``, ``(B, C, H, W−1)``
    and ``(B, C, H−1, W)``, per pixel (units of ``x`` per pixel)."""
    return x[..., :, 1:] - x[..., :, :-1], x[..., 1:, :] - x[..., :-1, :]


def _divergence(ax: torch.Tensor, ay: torch.Tensor) -> torch.Tensor:
    """Backward-difference divergence of a field of :func:`_forward_gradient`'s shapes, at the
    interior pixels ``(B, C, H−2, W−2)``; ``div(grad ξ)`` is the 5-point Laplacian there."""
    return (ax[..., 1:-1, 1:] - ax[..., 1:-1, :-1]) + (ay[..., 1:, 1:-1] - ay[..., :-1, 1:-1])


def _norm(gx: torch.Tensor, gy: torch.Tensor) -> torch.Tensor:
    """``sqrt(gx² + gy²)`` with a zero subgradient at 0 (not NaN)."""
    sq = gx**2 + gy**2
    nonzero = sq > 0
    return torch.where(nonzero, sq, torch.ones_like(sq)).sqrt() * nonzero


def _edge_weight(
    grad_norm: torch.Tensor, kappa: float | torch.Tensor, squared: bool
) -> torch.Tensor:
    """``exp(−(‖∇I‖/κ)²)`` (``squared``) or ``exp(−‖∇I‖/κ)``; κ a number or one per sample ``(B,)``.

    ``κ = 0`` gives weight 0 (no smoothing, as the thesis notes), ``κ = inf`` weight 1 (plain loss).
    """
    k = torch.as_tensor(kappa, dtype=grad_norm.dtype, device=grad_norm.device).reshape(-1, 1, 1, 1)
    ratio = grad_norm / k
    w = torch.exp(-(ratio**2 if squared else ratio))
    return torch.where(k > 0, w, torch.zeros_like(w))


def image_gradient_norm(image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``‖∇I‖`` of a ``(B, C, H, W)`` image, the mean over channels of each channel's gradient norm
    (§4.4.9), at two sets of points (per pixel, images in ``[0, 1]``):

    - ``(B, 1, H−1, W−1)`` from forward differences: where :func:`tv_loss` and
      :func:`diffusion_loss` take ``∇ξ``;
    - ``(B, 1, H−2, W−2)`` at the interior pixels from central differences
      ``(I[x+1] − I[x−1]) / 2``: where the Laplacian losses take ``Δξ``, so that an edge between
      two pixels weighs the Laplacian of both. (kornia's ``spatial_gradient(mode='diff')`` gives
      the same values, 15 times slower on 200 px frames.)
    """
    gx, gy = _forward_gradient(image)
    forward = _norm(gx[..., :-1, :], gy[..., :, :-1]).mean(1, keepdim=True)
    cx = (image[..., 1:-1, 2:] - image[..., 1:-1, :-2]) / 2
    cy = (image[..., 2:, 1:-1] - image[..., :-2, 1:-1]) / 2
    return forward, _norm(cx, cy).mean(1, keepdim=True)


def edge_weights(
    image: torch.Tensor, kappa: float | torch.Tensor, squared: bool
) -> tuple[torch.Tensor, torch.Tensor]:
    """The edge weights of the smooth losses: ``(B, 1, H−1, W−1)`` on the forward-difference grid
    (TV, diffusion) and ``(B, 1, H−2, W−2)`` at the interior pixels (TVV, gradient diffusion),
    ``exp(−(‖∇I‖/κ)²)`` (``squared``) or ``exp(−‖∇I‖/κ)``, κ a number or one per sample."""
    fwd, lap = image_gradient_norm(image)
    return _edge_weight(fwd, kappa, squared), _edge_weight(lap, kappa, squared)


def _gradient_terms(
    xi: torch.Tensor, image: torch.Tensor, kappa: float | torch.Tensor, squared: bool
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(weight, ∂x ξ, ∂y ξ) on the ``(H−1, W−1)`` grid of forward differences."""
    gx, gy = _forward_gradient(xi)
    w = _edge_weight(image_gradient_norm(image)[0], kappa, squared)
    return w, gx[..., :-1, :], gy[..., :, :-1]


def _laplacian_terms(
    xi: torch.Tensor, image: torch.Tensor, kappa: float | torch.Tensor, squared: bool
) -> tuple[torch.Tensor, torch.Tensor]:
    """(weight, Δξ) at the interior pixels."""
    lap = _divergence(*_forward_gradient(xi))
    return _edge_weight(image_gradient_norm(image)[1], kappa, squared), lap


def diffusion_loss(
    xi: torch.Tensor, image: torch.Tensor, kappa: float | torch.Tensor
) -> torch.Tensor:
    """Eq. 4.18: mean of ``exp(−(‖∇I‖/κ)²)·‖∇ξ‖²`` (``ξ`` per pixel, forward differences)."""
    w, gx, gy = _gradient_terms(xi, image, kappa, squared=True)
    return (w * (gx**2 + gy**2)).flatten(1).mean(1)


def tv_loss(xi: torch.Tensor, image: torch.Tensor, kappa: float | torch.Tensor) -> torch.Tensor:
    """Eq. 4.19: mean of ``exp(−‖∇I‖/κ)·‖∇ξ‖`` (isotropic total variation)."""
    w, gx, gy = _gradient_terms(xi, image, kappa, squared=False)
    return (w * _norm(gx, gy)).flatten(1).mean(1)


def gradient_diffusion_loss(
    xi: torch.Tensor, image: torch.Tensor, kappa: float | torch.Tensor
) -> torch.Tensor:
    """Eq. 4.20: mean over interior pixels of ``exp(−(‖∇I‖/κ)²)·(Δξ)²`` (5-point Laplacian)."""
    w, lap = _laplacian_terms(xi, image, kappa, squared=True)
    return (w * lap**2).flatten(1).mean(1)


def tvv_loss(xi: torch.Tensor, image: torch.Tensor, kappa: float | torch.Tensor) -> torch.Tensor:
    """Eq. 4.21: mean over interior pixels of ``exp(−‖∇I‖/κ)·|Δξ|``."""
    w, lap = _laplacian_terms(xi, image, kappa, squared=False)
    return (w * lap.abs()).flatten(1).mean(1)


def _descend(
    energy: Callable[..., torch.Tensor], xs: tuple[torch.Tensor, ...], steps: int, step: float
) -> tuple[torch.Tensor, ...]:
    """``steps`` gradient-descent steps ``x ← x − γ·∇E(x)`` on detached copies of ``xs``."""
    xs = tuple(x.detach() for x in xs)
    with torch.enable_grad():
        for _ in range(steps):
            xs = tuple(x.requires_grad_(True) for x in xs)
            grads = torch.autograd.grad(energy(*xs), xs)
            xs = tuple((x - step * g).detach() for x, g in zip(xs, grads, strict=True))
    return xs


def robust_diffusion_loss(
    xi: torch.Tensor,
    image: torch.Tensor,
    kappa: float | torch.Tensor,
    steps: int = ROBUST_STEPS,
    step: float = ROBUST_STEP,
) -> torch.Tensor:
    """Robust diffusion (§4.4.5, §4.6.2): MSE between ``ξ`` and a detached clone of it diffused
    by ``steps`` gradient steps ``γ`` on eq. 4.18 in its integral (sum) form, whose gradient is
    the explicit anisotropic diffusion ``ξ ← ξ + 2γ·div(g∇ξ)`` (stable for γ ≤ 1/8)."""
    w = _gradient_terms(xi, image, kappa, squared=True)[0].detach()

    def energy(x: torch.Tensor) -> torch.Tensor:
        gx, gy = _forward_gradient(x)
        return (w * (gx[..., :-1, :] ** 2 + gy[..., :, :-1] ** 2)).sum()

    (smooth,) = _descend(energy, (xi,), steps, step)
    return ((xi - smooth) ** 2).flatten(1).mean(1)


def robust_gradient_diffusion_loss(
    xi: torch.Tensor,
    image: torch.Tensor,
    kappa: float | torch.Tensor,
    steps: int = ROBUST_STEPS,
    step: float = ROBUST_STEP,
) -> torch.Tensor:
    """Robust gradient diffusion: MSE between ``∇ξ`` and a detached clone of it diffused by
    ``steps`` gradient steps ``γ`` on eq. 4.20 as a function of the field ``A = ∇ξ``,
    ``Σ g·(div A)²`` (the thesis writes it ``L_gdiff(∇ξ)``; its gradient is ``−2∇(g·div A)``,
    a diffusion of ``A``, eq. 4.16, stable for γ ≤ 1/8; the same descent on ``ξ`` would be
    biharmonic, unstable at γ = 0.1). The MSE is over every forward difference of both
    components."""
    w = _laplacian_terms(xi, image, kappa, squared=True)[0].detach()

    def energy(ax: torch.Tensor, ay: torch.Tensor) -> torch.Tensor:
        return (w * _divergence(ax, ay) ** 2).sum()

    gx, gy = _forward_gradient(xi)
    sx, sy = _descend(energy, (gx, gy), steps, step)
    err = torch.cat((((gx - sx) ** 2).flatten(1), ((gy - sy) ** 2).flatten(1)), 1)
    return err.mean(1)


#: The six smooth losses of Table 4.1, ``name: loss(ξ, image, κ) -> (B,)``.
SMOOTH_LOSSES: dict[str, Callable[..., torch.Tensor]] = {
    "tv": tv_loss,
    "tvv": tvv_loss,
    "diffusion": diffusion_loss,
    "gradient_diffusion": gradient_diffusion_loss,
    "robust_diffusion": robust_diffusion_loss,
    "robust_gradient_diffusion": robust_gradient_diffusion_loss,
}


# ---------------------------------------------------------------- direct warp and occlusions


@torch.no_grad()
def direct_warp(
    depth: torch.Tensor,
    rotation: torch.Tensor | None,
    translation: torch.Tensor,
    K: torch.Tensor,
    max_square: float = MAX_SQUARE,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Depth of the target painted into the reference frame as a square cloud (§4.5.6, Alg. 1).

    Each target pixel ``p`` is a square facing the reference camera, one target pixel wide: at
    reference depth ``Z`` it covers ``[u₀, u₀ + d) × [v₀, v₀ + d)`` with ``d = θ(p)/Z`` and
    ``(u₀, v₀)`` its projected centre minus ``d/2``. It paints the reference pixels whose centres
    it covers (half-open squares, so the squares of a fronto-parallel plane tile the image with
    neither hole nor overlap; Algorithm 1 starts from ``round(u₀)`` and may paint one more
    column); a z-buffer keeps the nearest. Vectorised: a loop over the ``⌈max d⌉²`` offsets
    inside a square, none over pixels. Not differentiable.

    ``d`` assumes square pixels (``fx = fy``, as stillbox-gen writes) and is clipped to
    ``max_square``. Pixels with a non-finite or non-positive depth, or behind the reference
    camera, paint nothing.

    Returns:
        ``(B, 1, H, W)`` reference depth, metres, ``inf`` where nothing was painted, and the
        ``(B, 1, H, W)`` int64 index map ``Id``: the flat index ``y·W + x`` of the target pixel
        painted there (the smallest on ties), −1 where none.
    """
    b, _, h, w = depth.shape
    coords, z = project(reference_points(depth, rotation, translation, K), K)
    u, v, z = coords[:, 0], coords[:, 1], z[:, 0]
    d = (depth[:, 0] / z).clamp(max=max_square)
    u0, v0 = u - d / 2, v - d / 2
    ok = torch.isfinite(u0) & torch.isfinite(v0) & torch.isfinite(z) & (depth[:, 0] > 0) & (z > 0)
    first_u, first_v = torch.ceil(u0), torch.ceil(v0)
    n = int(torch.ceil(torch.where(ok, d, 0).max()).item())  # [u₀, u₀ + d) holds ≤ ⌈d⌉ integers
    dump = b * h * w  # an extra z-buffer cell for what is not painted (no boolean indexing)
    offset = (torch.arange(b, device=depth.device) * h * w).reshape(b, 1, 1)

    def painted(i: int, j: int) -> torch.Tensor:
        """The z-buffer cell each target pixel paints at offset (j, i) of its square, or dump."""
        uu, vv = first_u + j, first_v + i
        paint = ok & (uu < u0 + d) & (vv < v0 + d)
        paint &= (uu >= 0) & (uu <= w - 1) & (vv >= 0) & (vv <= h - 1)
        target = offset + vv.clamp(0, h - 1).long() * w + uu.clamp(0, w - 1).long()
        return torch.where(paint, target, dump).reshape(-1)

    # One offset at a time, twice (the nearest depth, then the smallest source at it): memory of
    # one map per offset instead of ⌈d⌉² of them (10 GB for 64 maps of 128 px at MAX_SQUARE).
    offsets = [(i, j) for i in range(n) for j in range(n)]
    zs = torch.where(ok, z, float("inf")).reshape(-1)
    zbuf = torch.full((dump + 1,), float("inf"), dtype=depth.dtype, device=depth.device)
    for i, j in offsets:
        zbuf.scatter_reduce_(0, painted(i, j), zs, "amin")
    source = torch.arange(h * w, device=depth.device).repeat(b)
    index = torch.full((dump + 1,), h * w, dtype=torch.int64, device=depth.device)
    for i, j in offsets:
        flat = painted(i, j)
        nearest = torch.where(zs == zbuf[flat], flat, dump)  # on ties, the smallest source wins
        index.scatter_reduce_(0, nearest, source, "amin")
    index = torch.where(index[:dump] == h * w, -1, index[:dump])
    return zbuf[:dump].reshape(b, 1, h, w), index.reshape(b, 1, h, w)


@torch.no_grad()
def occlusion_mask(
    depth: torch.Tensor,
    rotation: torch.Tensor | None,
    translation: torch.Tensor,
    K: torch.Tensor,
    method: str = "warp_back",
    ratio: float = ODM_DEPTH_RATIO,
    dilation: int | None = None,
) -> torch.Tensor:
    """Occlusion detection module (§4.5.6): target pixels not seen in the reference, to drop from
    the photometric loss. ``(B, 1, H, W)`` bool, True = occluded (or out of the reference view).

    ``method``:
        ``"index"``: "index back" (eq. 4.26), occluded where no reference pixel's index map
        :func:`direct_warp` points back to the pixel. Sparse false positives where squares
        overlap (oblique surfaces, backward motion).
        ``"warp_back"``: the reference depth of :func:`direct_warp` warped back to the target the
        same way; occluded where the result is not within ``[θ/ratio, θ·ratio]``.
    ``dilation``: the occluded mask is dilated by this many pixels (a square of side
    ``2·dilation + 1``), which also removes the sparse false negatives of a noisy depth; by
    default :data:`ODM_DILATION` for ``"warp_back"`` (Fig. 4.10) and 0 for ``"index"`` (whose
    sparse false positives a dilation would spread).
    """
    b, _, h, w = depth.shape
    warped, index = direct_warp(depth, rotation, translation, K)
    if method == "index":
        offset = (torch.arange(b, device=depth.device) * h * w).reshape(b, 1, 1, 1)
        painted = torch.where(index >= 0, index + offset, b * h * w).reshape(-1)
        seen = torch.zeros(b * h * w + 1, dtype=torch.bool, device=depth.device)
        seen[painted] = True
        occluded = ~seen[:-1].reshape(b, 1, h, w)
    elif method == "warp_back":
        back, _ = direct_warp(warped, *invert_pose(rotation, translation), K)
        occluded = ~((back >= depth / ratio) & (back <= depth * ratio))
    else:
        raise ValueError(f"unknown occlusion method {method!r}: 'index' or 'warp_back'")
    if dilation is None:
        dilation = ODM_DILATION if method == "warp_back" else 0
    if dilation > 0:
        size = 2 * dilation + 1
        occluded = F.max_pool2d(occluded.float(), size, stride=1, padding=dilation) > 0
    return occluded
