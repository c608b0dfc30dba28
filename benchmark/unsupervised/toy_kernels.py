"""Fused CPU kernels of the toy study's optimiser (numba): loss gradients, Adam and the ODM.

In the toy problems (:mod:`benchmark.unsupervised.toy`) the depth values are the parameters and
the frames are fixed, so every term has a gradient that can be written per pixel:

- the L1 photometric loss is separable: pixel ``p``'s error depends only on ``θ(p)`` through
  the inverse warp ``θ·a(p) + c`` (:func:`benchmark.unsupervised.reprojection.warp_rays`), so one
  pass computes each pixel's error, its derivative through the bilinear weights, and the
  masked means of both references (:func:`photometric`);
- the smooth losses are stencils on ``ξ = 1/θ`` whose gradients are derived by hand, the robust
  ones' 10 inner descent steps included (:func:`smooth`);
- Adam is element-wise (:func:`adam_step`), and the ODM's z-buffer (Algorithm 1) is a loop over
  source pixels (:func:`occlusions`).

They compute exactly the forms of :mod:`~benchmark.unsupervised.reprojection` (the reference
implementation, torch and autograd, kept for chapter 5's networks); tests/test_toy_kernels.py
checks losses and gradients against it. Arrays are float32 ``(B, H, W)`` depth maps (one
problem per sample ``b``), the frames and constants of each scene indexed by ``scene[b]``;
intermediate sums are float64, in a fixed order. Every kernel runs its samples with ``prange``:
a sample is computed by one thread, start to end (the photometric kernel: a row of a scene, all
its grid points, the rows' partial sums added in row order), so results do not depend on the
number of threads (``numba.set_num_threads``). No fastmath (so no reassociation: vectorised
loops compute exactly what their scalar form does).
"""

from __future__ import annotations

import math
import os

import numba
import numpy as np
from numba import config, njit, prange

#: numba's own thread pool, not OpenMP: with its "omp" layer next to torch's OpenMP runtime the
#: study's command ran 3-4x slower (CPU time, torch and numba at 1 thread each). It must be set
#: before numba's first parallel launch (or :func:`numba.set_num_threads`): use
#: :func:`set_threads`. An explicit NUMBA_THREADING_LAYER still wins.
if "NUMBA_THREADING_LAYER" not in os.environ:
    config.THREADING_LAYER = "workqueue"


def set_threads(threads: int) -> None:
    """Threads of the kernels (at most numba's pool, NUMBA_NUM_THREADS: the number of cores)."""
    numba.set_num_threads(max(1, min(threads, config.NUMBA_NUM_THREADS)))


#: Codes of the smooth losses in :func:`smooth` (the names of reprojection.SMOOTH_LOSSES).
SMOOTH_CODES = {
    "tv": 0,
    "tvv": 1,
    "diffusion": 2,
    "gradient_diffusion": 3,
    "robust_diffusion": 4,
    "robust_gradient_diffusion": 5,
}
#: Channels of the frames (RGB; :func:`photometric` needs exactly this many).
CHANNELS = 3
#: As reprojection._RayProjection: the projected depth is clamped to this before dividing.
_MIN_Z = 1e-6


# ---------------------------------------------------------------- photometric


def bilinear_coefficients(image: np.ndarray) -> np.ndarray:
    """Per pixel ``(y0, x0)`` of a ``(C, H, W)`` image, the coefficients ``(A, B, C, D)`` of the
    bilinear interpolation ``A + B·e + C·f + D·e·f`` over the cell ``[x0, x0+1] × [y0, y0+1]``
    (``e``, ``f`` the fractional parts), channel-last: ``(H, W, 4, C)`` float64. Corners outside
    the image count as 0, as in grid_sample (which matters only to the derivative on the last
    row and column)."""
    c, h, w = image.shape
    pad = np.zeros((h + 1, w + 1, c))
    pad[:h, :w] = image.transpose(1, 2, 0)
    nw, ne, sw, se = pad[:h, :w], pad[:h, 1:], pad[1:, :w], pad[1:, 1:]
    return np.ascontiguousarray(np.stack([nw, ne - nw, sw - nw, nw - ne - sw + se], 2))


@njit(parallel=True, cache=True)
def kept_weights(occluded, points, use_occ, out):  # noqa: ANN001, ANN201
    """:func:`photometric`'s ``kept`` ``(S, H, W, R, G)`` float32 from the ODM's ``occluded``
    ``(B, R, H, W)`` bool (``B = S·G``, sample ``s·G + g``): 0 where occluded, else 1; all 1 if
    not ``use_occ``. Computed once per ODM call, not per iteration."""
    b, refs, h, w = occluded.shape
    n = b // points
    for job in prange(n * h):
        s, i = job // h, job % h
        for j in range(w):
            for r in range(refs):
                for g in range(points):
                    occ = use_occ and occluded[s * points + g, r, i, j]
                    out[s, i, j, r, g] = 0.0 if occ else 1.0


def photometric_work(samples: int, points: int, refs: int, h: int, w: int) -> tuple:
    """Scratch arrays of :func:`photometric` for ``samples`` maps of ``points`` grid points."""
    n = samples // points
    return (
        np.empty((n, h, w, points), dtype=np.float32),  # depth, grid point innermost
        np.empty((n, h, w, refs, points)),  # per-pixel derivative before the means
        np.empty((n, h, refs, points)),  # per row: sum of the kept pixels' errors
        np.empty((n, h, refs, points)),  # per row: number of kept pixels
    )


@njit(parallel=True, cache=True)
def photometric(depth, points, target, coef, rays, offsets, kept, grad, dt, tmp, accs, cnts):  # noqa: ANN001, ANN201, E501
    """L1 photometric loss per sample ``(B,)`` float64, its gradient in θ written to ``grad``.

    ``depth`` ``(B, H, W)`` metres, ``B = S·G``: scene ``s`` at grid point ``g`` is sample
    ``s·G + g`` (``points`` = G); ``target`` ``(S, H, W, C)`` (channel-last); ``coef``
    ``(S, R, H, W, 4, C)`` the references' :func:`bilinear_coefficients`; ``rays``
    ``(S, R, 3, H, W)`` and ``offsets`` ``(S, R, 3)``
    (:func:`~benchmark.unsupervised.reprojection.warp_rays`); ``kept`` ``(S, H, W, R, G)``
    float32, 0 for the pixels the ODM drops (:func:`kept_weights`); ``dt``, ``tmp``, ``accs``,
    ``cnts``: scratch, :func:`photometric_work`. ``grad`` ``(B, H, W)`` float32 is overwritten.

    As :meth:`benchmark.unsupervised.toy.Problem.photometric`: a pixel is kept where its point
    is in front of the reference and projects within the pixel centres (``inverse_warp_rays``'
    valid mask) and is not occluded; its error is ``mean_c |Ĩ − I_t|``, with ``Ĩ`` sampled
    bilinearly (grid_sample's, align_corners), and its derivative goes through the bilinear
    weights, ``∂x/∂θ = (a_x − a_z·x)/z``; the loss is the sum over references of the mean
    error over the kept pixels.

    Layout: the G grid points of a scene share its frames and rays, so each row ``(s, i)`` is
    one job, with the grid points innermost (contiguous, branch-free: the compiler vectorises
    that loop, gathering the bilinear coefficients). Each row's partial sums are kept apart and
    added in row order, so the results do not depend on the number of threads.
    """
    b, h, w = depth.shape
    n = b // points
    refs = coef.shape[1]
    wm = w - 1.0
    hm = h - 1.0
    for job in prange(n * h):
        s, i = job // h, job % h
        for g in range(points):
            for j in range(w):
                dt[s, i, j, g] = depth[s * points + g, i, j]
    for job in prange(n * h):
        s, i = job // h, job % h
        for r in range(refs):
            for g in range(points):
                accs[s, i, r, g] = 0.0
                cnts[s, i, r, g] = 0.0
        for j in range(w):
            i0 = target[s, i, j, 0]
            i1 = target[s, i, j, 1]
            i2 = target[s, i, j, 2]
            for r in range(refs):
                rx = rays[s, r, 0, i, j]
                ry = rays[s, r, 1, i, j]
                rz = rays[s, r, 2, i, j]
                ox = offsets[s, r, 0]
                oy = offsets[s, r, 1]
                oz = offsets[s, r, 2]
                for g in range(points):  # no branch, no call: vectorised
                    t = np.float64(dt[s, i, j, g])
                    z = oz + t * rz
                    inv = 1.0 / (z if z > _MIN_Z else _MIN_Z)
                    x = (ox + t * rx) * inv
                    y = (oy + t * ry) * inv
                    ok = (x >= 0) & (x <= wm) & (y >= 0) & (y <= hm) & (z > 0) & (t > 0)
                    keep = kept[s, i, j, r, g] * (1.0 if ok else 0.0)
                    # the cell read where not kept is any valid one: its terms are multiplied by 0
                    x0 = int((x if x < wm else wm) if x > 0.0 else 0.0)
                    y0 = int((y if y < hm else hm) if y > 0.0 else 0.0)
                    e = x - x0
                    f = y - y0
                    a0 = coef[s, r, y0, x0, 0, 0]
                    b0 = coef[s, r, y0, x0, 1, 0]
                    c0 = coef[s, r, y0, x0, 2, 0]
                    d0 = coef[s, r, y0, x0, 3, 0]
                    a1 = coef[s, r, y0, x0, 0, 1]
                    b1 = coef[s, r, y0, x0, 1, 1]
                    c1 = coef[s, r, y0, x0, 2, 1]
                    d1 = coef[s, r, y0, x0, 3, 1]
                    a2 = coef[s, r, y0, x0, 0, 2]
                    b2 = coef[s, r, y0, x0, 1, 2]
                    c2 = coef[s, r, y0, x0, 2, 2]
                    d2 = coef[s, r, y0, x0, 3, 2]
                    diff0 = a0 + b0 * e + (c0 + d0 * e) * f - i0
                    diff1 = a1 + b1 * e + (c1 + d1 * e) * f - i1
                    diff2 = a2 + b2 * e + (c2 + d2 * e) * f - i2
                    s0 = 1.0 if diff0 > 0 else (-1.0 if diff0 < 0 else 0.0)
                    s1 = 1.0 if diff1 > 0 else (-1.0 if diff1 < 0 else 0.0)
                    s2 = 1.0 if diff2 > 0 else (-1.0 if diff2 < 0 else 0.0)
                    err = abs(diff0) + abs(diff1) + abs(diff2)
                    gx = s0 * (b0 + d0 * f) + s1 * (b1 + d1 * f) + s2 * (b2 + d2 * f)
                    gy = s0 * (c0 + d0 * e) + s1 * (c1 + d1 * e) + s2 * (c2 + d2 * e)
                    accs[s, i, r, g] += keep * (err / CHANNELS)
                    cnts[s, i, r, g] += keep
                    ax = rx - rz * x
                    ay = ry - rz * y
                    tmp[s, i, j, r, g] = keep * ((ax * gx + ay * gy) * inv / CHANNELS)
    out = np.zeros(b)
    counts = np.empty((b, refs))
    for k in prange(b):
        s, g = k // points, k % points
        total = 0.0
        for r in range(refs):
            acc = 0.0
            count = 0.0
            for i in range(h):
                acc += accs[s, i, r, g]
                count += cnts[s, i, r, g]
            if count > 0:
                total += acc / count
            counts[k, r] = max(count, 1.0)
        out[k] = total
    for job in prange(n * h):
        s, i = job // h, job % h
        for g in range(points):
            for j in range(w):
                v = 0.0
                for r in range(refs):
                    v += tmp[s, i, j, r, g] / counts[s * points + g, r]
                grad[s * points + g, i, j] = v
    return out


# ---------------------------------------------------------------- smooth losses


@njit(cache=True)
def _sign(v):  # noqa: ANN001, ANN202
    return 1.0 if v > 0 else (-1.0 if v < 0 else 0.0)


@njit(cache=True)
def _gradient_loss(xi, wf, robust_power, g):  # noqa: ANN001, ANN202
    """TV (power 1) or diffusion (power 2) on the (H−1, W−1) forward-difference grid."""
    h, w = xi.shape
    n = (h - 1) * (w - 1)
    total = 0.0
    for i in range(h - 1):
        for j in range(w - 1):
            gx = xi[i, j + 1] - xi[i, j]
            gy = xi[i + 1, j] - xi[i, j]
            if robust_power == 2:
                total += wf[i, j] * (gx * gx + gy * gy)
                cx = 2 * wf[i, j] * gx / n
                cy = 2 * wf[i, j] * gy / n
            else:
                norm = math.sqrt(gx * gx + gy * gy)
                total += wf[i, j] * norm
                if norm > 0:
                    cx = wf[i, j] * gx / norm / n
                    cy = wf[i, j] * gy / norm / n
                else:
                    cx = 0.0
                    cy = 0.0
            g[i, j + 1] += cx
            g[i, j] -= cx + cy
            g[i + 1, j] += cy
    return total / n


@njit(cache=True)
def _laplacian(xi, i, j):  # noqa: ANN001, ANN202
    """The 5-point Laplacian at interior pixel (i, j), as reprojection._divergence sums it."""
    return (
        (xi[i, j + 1] - xi[i, j])
        - (xi[i, j] - xi[i, j - 1])
        + ((xi[i + 1, j] - xi[i, j]) - (xi[i, j] - xi[i - 1, j]))
    )


@njit(cache=True)
def _laplacian_loss(xi, wl, power, g):  # noqa: ANN001, ANN202
    """TVV (power 1) or gradient diffusion (power 2) at the interior pixels; ``wl`` (H−2, W−2)."""
    h, w = xi.shape
    n = (h - 2) * (w - 2)
    total = 0.0
    for i in range(1, h - 1):
        for j in range(1, w - 1):
            lap = _laplacian(xi, i, j)
            wt = wl[i - 1, j - 1]
            if power == 2:
                total += wt * lap * lap
                c = 2 * wt * lap / n
            else:
                total += wt * abs(lap)
                c = wt * _sign(lap) / n
            g[i, j + 1] += c
            g[i, j - 1] += c
            g[i + 1, j] += c
            g[i - 1, j] += c
            g[i, j] -= 4 * c
    return total / n


@njit(cache=True)
def _robust_diffusion(xi, wf, steps, step, g):  # noqa: ANN001, ANN202
    """MSE between ξ and a copy diffused by ``steps`` descent steps on ``Σ w·‖∇ξ‖²``, whose
    gradient is ``−div(2w·∇s)`` (the fluxes ``cx``, ``cy`` are 0 on the last column / row)."""
    h, w = xi.shape
    s = xi.copy()
    cx = np.zeros((h, w))
    cy = np.zeros((h, w))
    for _ in range(steps):
        for i in range(h - 1):
            for j in range(w - 1):
                cx[i, j] = 2 * wf[i, j] * (s[i, j + 1] - s[i, j])
                cy[i, j] = 2 * wf[i, j] * (s[i + 1, j] - s[i, j])
        for i in range(h):
            for j in range(w):
                d = -cx[i, j] - cy[i, j]
                if j > 0:
                    d += cx[i, j - 1]
                if i > 0:
                    d += cy[i - 1, j]
                s[i, j] -= step * d
    n = h * w
    total = 0.0
    for i in range(h):
        for j in range(w):
            e = xi[i, j] - s[i, j]
            total += e * e
            g[i, j] += 2 * e / n
    return total / n


@njit(cache=True)
def _robust_gradient_diffusion(xi, wl, steps, step, g):  # noqa: ANN001, ANN202
    """MSE between ∇ξ and a copy ``A`` of it diffused by ``steps`` descent steps on
    ``Σ w·(div A)²``, whose gradient is ``−∇(2w·div A)`` (``c = 2w·div A``, 0 off the interior)."""
    h, w = xi.shape
    ax = np.empty((h, w - 1))
    ay = np.empty((h - 1, w))
    for i in range(h):
        for j in range(w - 1):
            ax[i, j] = xi[i, j + 1] - xi[i, j]
    for i in range(h - 1):
        for j in range(w):
            ay[i, j] = xi[i + 1, j] - xi[i, j]
    sx = ax.copy()
    sy = ay.copy()
    c = np.zeros((h, w))
    for _ in range(steps):
        for i in range(1, h - 1):
            for j in range(1, w - 1):
                div = (sx[i, j] - sx[i, j - 1]) + (sy[i, j] - sy[i - 1, j])
                c[i, j] = 2 * wl[i - 1, j - 1] * div
        for i in range(h):
            for j in range(w - 1):
                sx[i, j] -= step * (c[i, j] - c[i, j + 1])
        for i in range(h - 1):
            for j in range(w):
                sy[i, j] -= step * (c[i, j] - c[i + 1, j])
    n = h * (w - 1) + (h - 1) * w
    total = 0.0
    for i in range(h):
        for j in range(w - 1):
            e = ax[i, j] - sx[i, j]
            total += e * e
            d = 2 * e / n
            g[i, j + 1] += d
            g[i, j] -= d
    for i in range(h - 1):
        for j in range(w):
            e = ay[i, j] - sy[i, j]
            total += e * e
            d = 2 * e / n
            g[i + 1, j] += d
            g[i, j] -= d
    return total / n


@njit(cache=True)
def _smooth_one(code, xi, wf, wl, steps, step, g):  # noqa: ANN001, ANN202
    if code == 0:
        return _gradient_loss(xi, wf, 1, g)
    if code == 1:
        return _laplacian_loss(xi, wl, 1, g)
    if code == 2:
        return _gradient_loss(xi, wf, 2, g)
    if code == 3:
        return _laplacian_loss(xi, wl, 2, g)
    if code == 4:
        return _robust_diffusion(xi, wf, steps, step, g)
    return _robust_gradient_diffusion(xi, wl, steps, step, g)


@njit(parallel=True, cache=True)
def smooth(code, depth, weight_fwd, weight_lap, lam, steps, step, grad):  # noqa: ANN001, ANN201
    """Smooth loss ``code`` (:data:`SMOOTH_CODES`) of ``ξ = 1/θ`` per sample ``(B,)`` float64,
    and ``λ·∂L_s/∂θ`` *added* to ``grad`` ``(B, H, W)``.

    ``weight_fwd`` ``(B, H−1, W−1)`` and ``weight_lap`` ``(B, H−2, W−2)``: each sample's edge
    weights (reprojection._gradient_terms / _laplacian_terms' ``w``, exponent as the loss
    needs); ``lam`` ``(B,)``; ``steps``, ``step``: the robust losses' inner descent.
    """
    b, h, w = depth.shape
    out = np.zeros(b)
    for k in prange(b):
        xi = np.empty((h, w))
        for i in range(h):
            for j in range(w):
                xi[i, j] = 1.0 / depth[k, i, j]
        g = np.zeros((h, w))
        out[k] = _smooth_one(code, xi, weight_fwd[k], weight_lap[k], steps, step, g)
        for i in range(h):
            for j in range(w):
                grad[k, i, j] += lam[k] * g[i, j] * (-xi[i, j] * xi[i, j])
    return out


# ---------------------------------------------------------------- Adam


@njit(parallel=True, cache=True)
def adam_step(param, grad, m, v, t, lr, beta1, beta2, eps, low, high):  # noqa: ANN001, ANN201
    """One Adam step (torch.optim.Adam's update, step number ``t`` ≥ 1) on ``param`` in place,
    then ``param`` clamped to ``[low, high]``; all ``(B, H, W)``."""
    b, h, w = param.shape
    bc1 = 1 - beta1**t
    bc2 = math.sqrt(1 - beta2**t)
    size = lr / bc1
    for k in prange(b):
        for i in range(h):
            for j in range(w):
                gr = grad[k, i, j]
                m[k, i, j] = m[k, i, j] + (gr - m[k, i, j]) * (1 - beta1)
                v[k, i, j] = v[k, i, j] * beta2 + (1 - beta2) * gr * gr
                p = param[k, i, j] - size * m[k, i, j] / (math.sqrt(v[k, i, j]) / bc2 + eps)
                param[k, i, j] = min(max(p, low), high)


# ---------------------------------------------------------------- occlusion detection


@njit(cache=True)
def _direct_warp(depth, rays, offset, max_square, zbuf):  # noqa: ANN001, ANN202
    """reprojection.direct_warp's z-buffer for one sample: ``zbuf`` ``(H, W)`` filled with the
    nearest reference depth painted there (inf where none); squares in float32 as torch."""
    h, w = depth.shape
    zbuf[:] = np.inf
    for i in range(h):
        for j in range(w):
            t = depth[i, j]
            z = np.float32(offset[2] + t * rays[2, i, j])
            inv = np.float32(1.0) / max(z, np.float32(_MIN_Z))
            u = np.float32(np.float32(offset[0] + t * rays[0, i, j]) * inv)
            v = np.float32(np.float32(offset[1] + t * rays[1, i, j]) * inv)
            d = min(np.float32(t / z), np.float32(max_square))
            u0 = np.float32(u - d / np.float32(2))
            v0 = np.float32(v - d / np.float32(2))
            if not (np.isfinite(u0) and np.isfinite(v0) and np.isfinite(z) and t > 0 and z > 0):
                continue
            uend = np.float32(u0 + d)
            vend = np.float32(v0 + d)
            yy = math.ceil(v0)
            while yy < vend:
                if 0 <= yy <= h - 1:
                    xx = math.ceil(u0)
                    while xx < uend:
                        if 0 <= xx <= w - 1 and z < zbuf[yy, xx]:
                            zbuf[yy, xx] = z
                        xx += 1
                yy += 1


@njit(parallel=True, cache=True)
def occlusions(
    depth, scene, rays, offsets, back_rays, back_offsets, ratio, dilation, max_square, out
):  # noqa: ANN001, ANN201, E501
    """The ODM's "warp back" mask (reprojection.occlusion_mask) of every sample and reference,
    written to ``out`` ``(B, R, H, W)`` bool: the depth painted into the reference by the direct
    warp, painted back with the inverse pose, occluded where not within ``[θ/ratio, θ·ratio]``,
    then dilated by ``dilation`` pixels. ``rays``/``offsets`` as :func:`photometric`,
    ``back_*`` those of the inverse poses."""
    b, h, w = depth.shape
    refs = rays.shape[1]
    for job in prange(b * refs):
        k, r = job // refs, job % refs
        s = scene[k]
        fwd = np.empty((h, w), dtype=np.float32)
        back = np.empty((h, w), dtype=np.float32)
        _direct_warp(depth[k], rays[s, r], offsets[s, r], max_square, fwd)
        _direct_warp(fwd, back_rays[s, r], back_offsets[s, r], max_square, back)
        occ = np.empty((h, w), dtype=np.bool_)
        for i in range(h):
            for j in range(w):
                t = depth[k, i, j]
                occ[i, j] = not (back[i, j] >= t / ratio and back[i, j] <= t * ratio)
        _dilate(occ, dilation, out[k, r])


@njit(cache=True)
def _dilate(occ, dilation, out):  # noqa: ANN001, ANN202
    """``out`` = ``occ`` dilated by a square of side ``2·dilation + 1`` (max_pool2d's, the
    image border not padded with True), separably: rows, then columns."""
    h, w = occ.shape
    rows = np.empty((h, w), dtype=np.bool_)
    for i in range(h):
        for j in range(w):
            hit = False
            for c in range(max(0, j - dilation), min(w, j + dilation + 1)):
                hit = hit or occ[i, c]
            rows[i, j] = hit
    for i in range(h):
        for j in range(w):
            hit = False
            for a in range(max(0, i - dilation), min(h, i + dilation + 1)):
                hit = hit or rows[a, j]
            out[i, j] = hit
