"""The toy-problem study of thesis §4.6 (Table 4.1, Figs. 4.13-4.18): depth maps optimised
directly by reprojection, with each smooth loss over a log grid of (λ, κ), ODM off and on.

Each toy scene (``stillbox-gen --preset toy-flower`` / ``toy-horizon``) has three frames; the
centre frame's depth map θ is the parameter (one value per pixel, metres), started at the
background depth (10 m, Fig. 4.11) and optimised from frames t-1 and t+1 with

    L(θ) = L_p(θ) + λ·L_s(ξ = 1/θ, κ)                                   (§4.6.2)

where ``L_p`` is the plain L1 photometric loss (α = 0, §4.7.3: "for our toy examples, we only
used the simple photometric loss"), summed over the two references, each over its valid pixels
(minus the pixels the occlusion detection module finds occluded when the ODM is on), and ``L_s``
one of the six smooth losses of :data:`benchmark.reprojection.SMOOTH_LOSSES`.

Batching: every grid point of one smooth loss and both scenes are optimised together, as one
batch of ``scenes × grid points`` independent depth maps (:class:`Problem`). Losses are per
sample and summed, and Adam is element-wise, so each sample follows exactly the trajectory it
would follow alone (a test checks it).

Computation: :func:`optimise` runs on the fused CPU kernels of :mod:`toy_kernels` (numba; the
photometric loss's gradient per pixel, the smooth losses' hand-derived gradients, Adam, the
ODM), ~9x faster than torch autograd on the losses of :mod:`reprojection`, which stay the
reference (``Problem.photometric`` / ``Problem.loss`` / ``Problem.occlusions``; the kernels are
tested against them). The work is split between threads by depth map (the photometric loss: by
row of a scene, its grid points together), each part's sums added in a fixed order, so the
results do not depend on the number of threads.

Choices the thesis leaves open (all in constants below):

- Optimiser: Adam (β = 0.9, 0.999), learning rate 0.15. §4.6 gives only the learning rate; Adam
  is what the thesis uses for its unsupervised trainings (§5.3.1), and a step of 0.15 on a loss
  that is a mean over 40,000 pixels is only meaningful for a scale-free optimiser (plain SGD
  would move each depth by ~1e-5 m per step).
- The parameters are depths (§4.6.2: "the training parameters are depth values"), projected
  back into [MIN_DEPTH, MAX_DEPTH] = [0.1, 100] m after every step (the benchmark's depth range,
  thesis §3.6.2), so that ξ stays finite.
- LE: the mean logarithmic error ``mean |log θ − log θ̃|`` over the pixels whose true depth is
  within MAX_DEPTH (Fig. 4.13's "mean logarithmic error"; the sky of Horizon, and the ground
  beyond 100 m, have no usable true depth and are left out).
- The ODM mask (``occlusion_mask``, "warp back", dilation 2) is recomputed from the current
  depth every :data:`ODM_EVERY` iterations (a call costs about one optimiser iteration); the
  thesis does not say how often it ran it.
- ΔM (the thesis' "robustness index", undefined there): see :func:`robustness`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np
import torch

from stillbox_gen.conventions import MAX_DEPTH
from stillbox_gen.dataset import Dataset

from ..core import thesis
from ..core.metrics import MIN_DEPTH
from .reprojection import (
    MAX_SQUARE,
    ODM_DEPTH_RATIO,
    ODM_DILATION,
    ROBUST_STEP,
    ROBUST_STEPS,
    SMOOTH_LOSSES,
    edge_weights,
    inverse_warp,
    inverse_warp_rays,
    invert_pose,
    l1_map,
    masked_mean,
    occlusion_mask,
    warp_rays,
)

#: The two toy scenes in Table 4.1's order of columns, and the preset that renders each.
SCENES = ("horizon", "flower")
PRESETS = {"horizon": "toy-horizon", "flower": "toy-flower"}
#: Frame whose depth is optimised, and its two references (t-1, t+1).
CENTRE = 1
REFERENCES = (0, 2)
#: Start depth, metres: the background depth of both scenes (Fig. 4.11 caption).
START_DEPTH = 10.0
LEARNING_RATE = 0.15
ITERATIONS = 10_000
#: Iterations between two computations of the ODM mask (see the module doc).
ODM_EVERY = 10
#: LE is recorded every ITERATIONS // HISTORY_POINTS iterations (for the LE-vs-time curves).
HISTORY_POINTS = 100
#: The log grids (half a decade apart), wide enough to hold every optimum of Table 4.1 and,
#: on the toy scenes, every optimum of ours inside the λ grid: measured at 10^4 iterations
#: (κ = 1, λ 100-3000), M peaks at λ = 100 (diffusion, robust diffusion), 300 (gradient
#: diffusion; robust gradient diffusion ODM on) or 1000 (robust gradient diffusion ODM off,
#: 0.647 against 0.607 at 3000) (docs/results/toy/README.md, "The λ grid").
LAMBDAS = (0.1, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0, 300.0, 1000.0, 3000.0)
KAPPAS = (0.03, 0.1, 0.3, 1.0, 3.0)
#: --quick: a 2x2 grid and a few iterations, for CI.
QUICK_LAMBDAS = (1.0, 30.0)
QUICK_KAPPAS = (0.3, 1.0)
QUICK_ITERATIONS = 20
QUICK_ODM_EVERY = 5
#: ODM masks are computed for this many samples at once (the direct warp's memory grows with
#: the square of the largest projected square, up to 16² copies of the batch).
ODM_CHUNK = 8

THESIS_KEYS = thesis.TABLE_4_1_KEYS  # κ, λ, M, ΔM, LE Horizon, LE Flower
THESIS_TABLE_4_1 = thesis.TABLE_4_1


def thesis_value(loss: str, odm: bool, key: str) -> float | None:
    """Table 4.1's value of ``key`` (one of THESIS_KEYS) for ``loss`` with the ODM off / on."""
    row = THESIS_TABLE_4_1.get(loss)
    return None if row is None else row[int(odm)][THESIS_KEYS.index(key)]


# ---------------------------------------------------------------- data


@dataclass
class ToyScene:
    """One toy scene, ready to optimise: frames ``(3, 3, H, W)`` RGB in [0, 1], the centre
    frame's true depth ``(1, 1, H, W)`` metres (unclipped), the pixels LE is scored on
    ``(1, 1, H, W)`` bool, ``K`` ``(3, 3)`` pixels, and the centre → reference pose ``(R, t)``
    of each of :data:`REFERENCES` (benchmark.reprojection's convention)."""

    name: str
    frames: torch.Tensor
    depth: torch.Tensor
    valid: torch.Tensor
    K: torch.Tensor
    poses: list[tuple[torch.Tensor, torch.Tensor]]

    @property
    def target(self) -> torch.Tensor:
        return self.frames[CENTRE : CENTRE + 1]

    def reference(self, i: int) -> torch.Tensor:
        return self.frames[REFERENCES[i] : REFERENCES[i] + 1]

    def to(self, device: torch.device | str) -> ToyScene:
        """A copy with every tensor on ``device``."""
        return ToyScene(
            self.name,
            self.frames.to(device),
            self.depth.to(device),
            self.valid.to(device),
            self.K.to(device),
            [(r.to(device), t.to(device)) for r, t in self.poses],
        )


class ToyDataError(ValueError):
    """A toy dataset that is missing or not a 3-frame scene (the message names the folder)."""


def load_scene(root: str | Path, name: str) -> ToyScene:
    """Scene 0 of the dataset at ``root`` as a :class:`ToyScene` named ``name`` (float32)."""
    from stillbox_gen.errors import DatasetError

    try:
        scene = Dataset(root).scene(0)
        if scene.frames != 3:
            raise ToyDataError(f"'{root}' has {scene.frames} frames per scene, not 3")
        rgb = np.stack([scene.load_rgb(i) for i in range(3)]).astype(np.float32) / 255
        depth = scene.load_depth(CENTRE).astype(np.float32)
    except DatasetError as e:
        raise ToyDataError(str(e)) from None
    poses = []
    for ref in REFERENCES:
        pose = torch.from_numpy(scene.relative_pose(CENTRE, ref)).float()
        poses.append((pose[:3, :3], pose[:3, 3]))
    d = torch.from_numpy(depth)[None, None]
    return ToyScene(
        name=name,
        frames=torch.from_numpy(rgb).permute(0, 3, 1, 2).contiguous(),
        depth=d,
        valid=torch.isfinite(d) & (d > 0) & (d <= MAX_DEPTH),
        K=torch.from_numpy(scene.K).float(),
        poses=poses,
    )


@torch.no_grad()
def scene_warps(
    scene: ToyScene, depth: torch.Tensor, occluded: list[torch.Tensor] | None = None
) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Each reference warped to the centre frame with ``depth`` ``(1, 1, H, W)``: ``(warped
    (1, 3, H, W), kept (1, 1, H, W) bool)``, kept = valid and (when given) not occluded."""
    out = []
    for i, (r, t) in enumerate(scene.poses):
        warped, valid = inverse_warp(scene.reference(i), depth, r, t, scene.K)
        out.append((warped, valid if occluded is None else valid & ~occluded[i]))
    return out


# ---------------------------------------------------------------- metrics


def log_error(depth: torch.Tensor, truth: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """LE: ``mean |log θ − log θ̃|`` over ``valid`` pixels, per sample ``(B,)``.

    ``depth`` ``(B, 1, H, W)`` estimates, ``truth`` and ``valid`` ``(1 or B, 1, H, W)``."""
    err = (depth.log() - truth.clamp(min=MIN_DEPTH).log()).abs()
    valid = valid.expand_as(err)
    return torch.where(valid, err, 0).flatten(1).sum(1) / valid.flatten(1).sum(1).clamp(min=1)


def scene_quality(le: float | np.ndarray, le0: float) -> float | np.ndarray:
    """M_S = max(0, 1 − LE / LE_0) (§4.6 "Metrics"): 1 for the true depth, 0 when no better
    than the start."""
    return np.maximum(0.0, 1.0 - np.asarray(le) / le0)


def quality(per_scene: Sequence[float | np.ndarray]) -> float | np.ndarray:
    """M, the geometric mean of the scenes' M_S (§4.6 "Metrics")."""
    stacked = np.stack([np.asarray(m, dtype=np.float64) for m in per_scene])
    return np.prod(stacked, axis=0) ** (1.0 / len(per_scene))


def robustness(
    m: np.ndarray, best: tuple[int, int], lambdas: Sequence[float], kappas: Sequence[float]
) -> float:
    """ΔM, the robustness index of Table 4.1: how fast M falls around its optimum.

    The thesis names it ("robustness index", to minimise) without defining it; it reads it off
    the heat maps (an optimum "more evenly distributed, without a strong peak" is more robust)
    and its values reach 1.05, so it is not a drop of M itself (M ≤ 1). Ours: the mean, over the
    grid neighbours of the optimum along λ and along κ (up to 4), of ``(M* − M_neighbour)``
    divided by their distance in decades (``|log10(v_neighbour / v*)|``): the mean slope of M
    away from the optimum, per decade. 0 for a flat optimum. ``m``: ``(len(λ), len(κ))``;
    ``best``: the optimum's index.
    """
    i, j = best
    slopes = []
    for a, b in ((i - 1, j), (i + 1, j), (i, j - 1), (i, j + 1)):
        if 0 <= a < m.shape[0] and 0 <= b < m.shape[1]:
            decades = abs(math.log10(lambdas[a] / lambdas[i])) + abs(
                math.log10(kappas[b] / kappas[j])
            )
            slopes.append((m[i, j] - m[a, b]) / decades)
    return float(np.mean(slopes)) if slopes else 0.0


# ---------------------------------------------------------------- batched optimisation


@dataclass
class Problem:
    """``len(scenes) × G`` independent depth maps in one batch (scene-major: sample
    ``s·G + g`` is scene ``s`` at grid point ``g``), with each sample's λ and κ."""

    scenes: list[ToyScene]
    lambdas: torch.Tensor  # (G,)
    kappas: torch.Tensor  # (G,)
    target: torch.Tensor = field(init=False)
    references: list[torch.Tensor] = field(init=False)
    poses: list[tuple[torch.Tensor, torch.Tensor]] = field(init=False)
    _arrays: KernelArrays | None = field(init=False, default=None, repr=False)

    def __post_init__(self) -> None:
        g = self.points

        def rep(x: torch.Tensor) -> torch.Tensor:
            return x.repeat_interleave(g, 0)

        self.target = rep(torch.cat([s.target for s in self.scenes]))
        self.references = [
            rep(torch.cat([s.reference(i) for s in self.scenes])) for i in range(len(REFERENCES))
        ]
        self.poses = [
            (
                rep(torch.stack([s.poses[i][0] for s in self.scenes])),
                rep(torch.stack([s.poses[i][1] for s in self.scenes])),
            )
            for i in range(len(REFERENCES))
        ]
        h, w = self.target.shape[2:]
        rays = [warp_rays(r, t, self.K, h, w) for r, t in self.poses]
        # both references in one batch: reference i of sample s is sample i·B + s
        self.stacked_references = torch.cat(self.references)
        self.stacked_target = self.target.repeat(len(self.references), 1, 1, 1)
        self.rays = torch.cat([a for a, _ in rays])
        self.offsets = torch.cat([c for _, c in rays])
        self.truth = rep(torch.cat([s.depth for s in self.scenes]))
        self.valid = rep(torch.cat([s.valid for s in self.scenes]))
        self.lam = self.lambdas.repeat(len(self.scenes))
        self.kap = self.kappas.repeat(len(self.scenes))

    def arrays(self) -> KernelArrays:
        """The problem's constants as the arrays of :mod:`toy_kernels` (computed once)."""
        if self._arrays is None:
            self._arrays = KernelArrays.of(self)
        return self._arrays

    @property
    def points(self) -> int:
        return len(self.lambdas)

    @property
    def K(self) -> torch.Tensor:
        return self.scenes[0].K

    def warps(self, depth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """:func:`inverse_warp` of both references for ``depth`` ``(B, 1, H, W)``, as one batch
        with the constants precomputed: ``(2B, 3, H, W)`` warped frames and ``(2B, 1, H, W)``
        valid masks, reference ``i`` of sample ``s`` at ``i·B + s``."""
        n = len(self.references)
        return inverse_warp_rays(
            self.stacked_references, depth.repeat(n, 1, 1, 1), self.rays, self.offsets
        )

    @torch.no_grad()
    def occlusions(self, depth: torch.Tensor) -> list[torch.Tensor]:
        """The ODM's occluded mask ``(B, 1, H, W)`` of each reference, computed by chunks."""
        out, n = [], ODM_CHUNK
        for r, t in self.poses:
            parts = [
                occlusion_mask(depth[i : i + n], r[i : i + n], t[i : i + n], self.K)
                for i in range(0, depth.shape[0], n)
            ]
            out.append(torch.cat(parts))
        return out

    def photometric(
        self, depth: torch.Tensor, occluded: list[torch.Tensor] | None = None
    ) -> torch.Tensor:
        """L1 photometric loss per sample ``(B,)`` (α = 0), occluded pixels dropped if given.

        :func:`photometric_loss` (α = 0, no minimum: the sum over references of each one's
        masked mean) computed on both references as one batch."""
        warped, kept = self.warps(depth)
        if occluded is not None:
            kept = kept & ~torch.cat(occluded)
        per_reference = masked_mean(l1_map(self.stacked_target, warped), kept)
        return per_reference.reshape(len(self.references), -1).sum(0)

    def loss(
        self, depth: torch.Tensor, smooth: str | None, occluded: list[torch.Tensor] | None
    ) -> torch.Tensor:
        """``L_p + λ·L_s(1/θ, κ)`` per sample ``(B,)``."""
        total = self.photometric(depth, occluded)
        if smooth is None:
            return total
        g, xi = self.points, 1 / depth
        parts = [  # per scene, so that its image's gradients are computed once, not G times
            SMOOTH_LOSSES[smooth](xi[i * g : (i + 1) * g], s.target, self.kappas)
            for i, s in enumerate(self.scenes)
        ]
        return total + self.lam * torch.cat(parts)


#: Losses whose edge weight is ``exp(−‖∇I‖/κ)`` (the others: ``exp(−(‖∇I‖/κ)²)``).
_UNSQUARED = ("tv", "tvv")
#: Adam's constants (torch.optim.Adam's defaults).
ADAM_BETAS = (0.9, 0.999)
ADAM_EPS = 1e-8


NUMBA_MISSING = "the toy study needs numba: pip install 'stillbox-gen[toy]'"


def kernels():  # noqa: ANN201
    """:mod:`toy_kernels`, imported when first needed (numba adds ~0.3 s to every command's
    start otherwise); without numba, a ModuleNotFoundError whose message names the extra."""
    try:
        from . import toy_kernels
    except ModuleNotFoundError as e:
        if e.name != "numba":
            raise
        raise ModuleNotFoundError(NUMBA_MISSING, name="numba") from None
    return toy_kernels


def _np(x: torch.Tensor, dtype: type = np.float32) -> np.ndarray:
    return np.ascontiguousarray(x.detach().cpu().numpy().astype(dtype))


@dataclass
class KernelArrays:
    """A :class:`Problem`'s constants for :mod:`toy_kernels` (CPU numpy): per scene ``S`` the
    target ``(S, H, W, C)`` and the references' bilinear coefficients ``(S, R, H, W, 4, C)``
    (float64, :func:`toy_kernels.bilinear_coefficients`), the warp constants (float32) of
    each reference's pose and of its inverse (``rays`` ``(S, R, 3, H, W)``, ``offsets``
    ``(S, R, 3)``), and per sample ``B`` its scene ``(B,)`` and λ ``(B,)`` (float64)."""

    scene: np.ndarray
    lam: np.ndarray
    target: np.ndarray
    coef: np.ndarray
    rays: np.ndarray
    offsets: np.ndarray
    back_rays: np.ndarray
    back_offsets: np.ndarray
    weights: dict[bool, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    @classmethod
    def of(cls, problem: Problem) -> KernelArrays:
        scenes = [s.to("cpu") for s in problem.scenes]
        h, w = scenes[0].frames.shape[2:]
        rays, offsets, back_rays, back_offsets = [], [], [], []
        for s in scenes:
            for r, t in s.poses:
                a, c = warp_rays(r, t, s.K, h, w)
                rays.append(a[0])
                offsets.append(c.reshape(3))
                a, c = warp_rays(*invert_pose(r, t), s.K, h, w)
                back_rays.append(a[0])
                back_offsets.append(c.reshape(3))
        n, refs = len(scenes), len(REFERENCES)
        if scenes[0].frames.shape[1] != kernels().CHANNELS:
            raise ValueError(f"toy frames must have {kernels().CHANNELS} channels (RGB)")

        def stack(xs: list[torch.Tensor], dtype: type = np.float32) -> np.ndarray:
            t = torch.stack(xs)
            return _np(t.reshape(n, refs, *t.shape[1:]), dtype)

        return cls(
            scene=np.repeat(np.arange(n), problem.points),
            lam=_np(problem.lam, np.float64),
            target=_np(torch.cat([s.target for s in scenes]).permute(0, 2, 3, 1), np.float64),
            coef=np.stack(
                [
                    np.stack(
                        [
                            kernels().bilinear_coefficients(_np(s.reference(i)[0]))
                            for i in range(refs)
                        ]
                    )
                    for s in scenes
                ]
            ),
            rays=stack(rays, np.float64),  # float32 values, stored wide: no conversions
            offsets=stack(offsets, np.float64),
            back_rays=stack(back_rays),
            back_offsets=stack(back_offsets),
        )

    def edge_weights(self, problem: Problem, smooth: str) -> tuple[np.ndarray, np.ndarray]:
        """Each sample's edge weights ``(B, H−1, W−1)`` and ``(B, H−2, W−2)`` for ``smooth``."""
        squared = smooth not in _UNSQUARED
        if squared not in self.weights:
            kap = problem.kappas.cpu()
            parts = [edge_weights(s.target.cpu(), kap, squared) for s in problem.scenes]
            self.weights[squared] = (
                _np(torch.cat([f for f, _ in parts])[:, 0]),
                _np(torch.cat([lap for _, lap in parts])[:, 0]),
            )
        return self.weights[squared]


class _Kernels:
    """One optimisation's state on the CPU kernels: ``depth``, Adam's moments, the gradient
    buffer and the ODM masks ``(B, R, H, W)``, all numpy."""

    def __init__(self, problem: Problem, smooth: str | None, depth: np.ndarray) -> None:
        self.problem, self.a, self.smooth = problem, problem.arrays(), smooth
        self.depth = depth
        self.m, self.v = np.zeros_like(depth), np.zeros_like(depth)
        self.grad = np.zeros_like(depth)
        b, h, w = depth.shape
        refs = len(REFERENCES)
        self.occluded = np.zeros((b, refs, h, w), dtype=np.bool_)
        self.use_occ = False
        self.work = kernels().photometric_work(b, problem.points, refs, h, w)
        self.kept = np.empty((b // problem.points, h, w, refs, problem.points), np.float32)
        self.set_occluded(None)
        if smooth is not None:
            self.code = kernels().SMOOTH_CODES[smooth]
            self.wf, self.wl = self.a.edge_weights(problem, smooth)

    def occlusions(self) -> None:
        a = self.a
        kernels().occlusions(self.depth, a.scene, a.rays, a.offsets, a.back_rays,
                               a.back_offsets, ODM_DEPTH_RATIO, ODM_DILATION, MAX_SQUARE,
                               self.occluded)  # fmt: skip
        self.set_occluded(self.occluded)

    def set_occluded(self, occluded: np.ndarray | None) -> None:
        """Drop the pixels of ``occluded`` ``(B, R, H, W)`` bool from the photometric loss
        (None: keep them all)."""
        self.use_occ = occluded is not None
        if occluded is not None and occluded is not self.occluded:
            self.occluded[:] = occluded
        kernels().kept_weights(self.occluded, self.problem.points, self.use_occ, self.kept)

    def photometric(self) -> np.ndarray:
        """Photometric loss ``(B,)``; its gradient in ``self.grad`` (overwritten)."""
        a = self.a
        return kernels().photometric(self.depth, self.problem.points, a.target, a.coef, a.rays,
                                       a.offsets, self.kept, self.grad, *self.work)  # fmt: skip

    def step(self, t: int, lr: float) -> None:
        """Adam step ``t`` (from 1) on the gradient of the photometric + smooth loss."""
        self.photometric()
        if self.smooth is not None:
            kernels().smooth(self.code, self.depth, self.wf, self.wl, self.a.lam,
                               ROBUST_STEPS, ROBUST_STEP, self.grad)  # fmt: skip
        kernels().adam_step(self.depth, self.grad, self.m, self.v, t, lr, *ADAM_BETAS,
                              ADAM_EPS, MIN_DEPTH, MAX_DEPTH)  # fmt: skip

    def masks(self, device: torch.device) -> list[torch.Tensor]:
        """The ODM masks as :meth:`Problem.occlusions` gives them."""
        occ = torch.from_numpy(self.occluded.copy()).to(device)
        return [occ[:, i : i + 1] for i in range(occ.shape[1])]


@dataclass
class RunResult:
    """One batched optimisation: final depth ``(B, 1, H, W)``, final LE ``(B,)``, the LE
    history ``(T, B)`` at ``history_iterations``, the last ODM masks (or None), the final
    photometric loss ``(B,)``, the wall time and the process CPU time (both threads; a fairer
    measure than wall time on a shared machine), seconds."""

    depth: torch.Tensor
    le: np.ndarray
    history: np.ndarray
    history_iterations: list[int]
    occluded: list[torch.Tensor] | None
    photometric: np.ndarray
    seconds: float
    cpu_seconds: float


def optimise(
    problem: Problem,
    smooth: str | None,
    iterations: int,
    odm_every: int = 0,
    start: torch.Tensor | None = None,
    lr: float = LEARNING_RATE,
    on_step: Callable[[], None] | None = None,
) -> RunResult:
    """Adam on the depths of every sample of ``problem`` for ``iterations`` steps.

    ``smooth``: a name of SMOOTH_LOSSES, or None for the photometric loss alone. ``odm_every``:
    0 for no ODM, else the ODM masks are recomputed from the current depth every this many
    iterations (first at iteration 0). ``start``: ``(B, 1, H, W)`` start depth (default
    :data:`START_DEPTH` everywhere). ``on_step`` is called after every step (progress bars).
    """
    b = problem.target.shape[0]
    h, w = problem.target.shape[2:]
    device = problem.target.device
    if start is None:
        start = torch.full((b, 1, h, w), START_DEPTH)
    depth = _np(start.clamp(MIN_DEPTH, MAX_DEPTH)[:, 0])
    state = _Kernels(problem, smooth, depth)
    truth, valid = problem.truth.cpu(), problem.valid.cpu()
    every = max(1, iterations // HISTORY_POINTS)
    history, steps = [], []
    t0, c0 = time.perf_counter(), time.process_time()
    for it in range(iterations):
        if odm_every and it % odm_every == 0:
            state.occlusions()
        if it % every == 0:
            history.append(log_error(torch.from_numpy(depth)[:, None], truth, valid).numpy())
            steps.append(it)
        state.step(it + 1, lr)
        if on_step is not None:
            on_step()
    final = torch.from_numpy(depth.copy())[:, None]
    le = log_error(final, truth, valid).numpy()
    photo = state.photometric()
    history.append(le)
    steps.append(iterations)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    occluded = state.masks(device) if state.use_occ else None
    return RunResult(final.to(device), le, np.stack(history), steps, occluded, photo, wall, cpu)


def initial_log_errors(scenes: Sequence[ToyScene]) -> dict[str, float]:
    """LE_0 of each scene: the LE of the start depth (START_DEPTH everywhere)."""
    out = {}
    for s in scenes:
        start = torch.full_like(s.depth, START_DEPTH)
        out[s.name] = float(log_error(start, s.depth, s.valid)[0])
    return out


# ---------------------------------------------------------------- the study


@dataclass
class StudyConfig:
    """What one study runs: grids, iterations, ODM period, and which losses."""

    iterations: int = ITERATIONS
    lambdas: tuple[float, ...] = LAMBDAS
    kappas: tuple[float, ...] = KAPPAS
    odm_every: int = ODM_EVERY
    losses: tuple[str, ...] = tuple(SMOOTH_LOSSES)
    odm: tuple[bool, ...] = (False, True)

    @classmethod
    def quick(cls, iterations: int | None = None) -> StudyConfig:
        return cls(
            iterations=iterations or QUICK_ITERATIONS,
            lambdas=QUICK_LAMBDAS,
            kappas=QUICK_KAPPAS,
            odm_every=QUICK_ODM_EVERY,
        )

    @property
    def runs(self) -> int:
        """Batched optimisations: photometric alone (ODM off), then each loss × ODM setting."""
        return 1 + len(self.losses) * len(self.odm)


def grid(cfg: StudyConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """(λ, κ) of every grid point, ``(G,)`` each, λ-major: point ``i·len(κ) + j``."""
    lam = torch.tensor(cfg.lambdas).repeat_interleave(len(cfg.kappas))
    kap = torch.tensor(cfg.kappas).repeat(len(cfg.lambdas))
    return lam, kap


def summarise(
    run: RunResult, scenes: Sequence[ToyScene], le0: dict[str, float], cfg: StudyConfig | None
) -> dict:
    """results.json's block for one run: LE per scene and M over the grid (``(len(λ), len(κ))``
    lists) and the best grid point (κ, λ, M, ΔM, LE per scene); ``cfg`` None for the
    photometric-only run (one point)."""
    g = len(run.le) // len(scenes)
    le = {s.name: run.le[i * g : (i + 1) * g] for i, s in enumerate(scenes)}
    ms = {n: scene_quality(v, le0[n]) for n, v in le.items()}
    m = quality(list(ms.values()))
    photo = {s.name: run.photometric[i * g : (i + 1) * g] for i, s in enumerate(scenes)}
    shape = (1, 1) if cfg is None else (len(cfg.lambdas), len(cfg.kappas))
    best = int(np.argmax(m))
    bi, bj = divmod(best, shape[1])
    out = {
        "seconds": round(run.seconds, 2),
        "cpu_seconds": round(run.cpu_seconds, 2),
        "seconds_per_iteration": round(run.seconds / max(1, run.history_iterations[-1]), 4),
        "le": {n: v.reshape(shape).round(4).tolist() for n, v in le.items()},
        "m": m.reshape(shape).round(4).tolist(),
        "best": {
            "index": best,
            "m": round(float(m[best]), 4),
            "delta_m": 0.0
            if cfg is None
            else round(robustness(m.reshape(shape), (bi, bj), cfg.lambdas, cfg.kappas), 4),
            "le": {n: round(float(v[best]), 4) for n, v in le.items()},
            "m_s": {n: round(float(v[best]), 4) for n, v in ms.items()},
            "photometric": {n: round(float(v[best]), 5) for n, v in photo.items()},
        },
    }
    if cfg is not None:
        out["best"]["lambda"] = cfg.lambdas[bi]
        out["best"]["kappa"] = cfg.kappas[bj]
    return out


def best_samples(run: RunResult, n_scenes: int, best: int) -> list[int]:
    """Batch indices of grid point ``best`` in each scene."""
    g = len(run.le) // n_scenes
    return [s * g + best for s in range(n_scenes)]


@dataclass
class BestRun:
    """What the figures need of a run's best grid point: per scene, its final depth
    ``(1, 1, H, W)``, the last ODM masks (or None) and the LE history."""

    label: str
    depth: dict[str, torch.Tensor]
    occluded: dict[str, list[torch.Tensor] | None]
    history: dict[str, np.ndarray]
    history_iterations: list[int]


def _best_run(label: str, run: RunResult, scenes: Sequence[ToyScene], best: int) -> BestRun:
    idx = best_samples(run, len(scenes), best)
    return BestRun(
        label=label,
        depth={s.name: run.depth[i : i + 1].cpu() for s, i in zip(scenes, idx, strict=True)},
        occluded={
            s.name: None if run.occluded is None else [o[i : i + 1].cpu() for o in run.occluded]
            for s, i in zip(scenes, idx, strict=True)
        },
        history={s.name: run.history[:, i] for s, i in zip(scenes, idx, strict=True)},
        history_iterations=run.history_iterations,
    )


def run_key(loss: str, odm: bool) -> str:
    """results.json's key of a run: ``"<loss>/odm-off"`` or ``"<loss>/odm-on"``."""
    return f"{loss}/odm-{'on' if odm else 'off'}"


#: A finished run: its results.json block and its BestRun.
Finished = tuple[dict, BestRun]


def _photometric_run(
    scenes: list[ToyScene], le0: dict[str, float], cfg: StudyConfig, on_step
) -> Finished:
    device = scenes[0].frames.device
    alone = Problem(scenes, torch.zeros(1, device=device), torch.zeros(1, device=device))
    run = optimise(alone, None, cfg.iterations, on_step=on_step)
    return summarise(run, scenes, le0, None), _best_run("photometric", run, scenes, 0)


def _grid_run(
    problem: Problem, loss: str, odm: bool, le0: dict[str, float], cfg: StudyConfig, on_step
) -> Finished:
    every = cfg.odm_every if odm else 0
    run = optimise(problem, loss, cfg.iterations, every, on_step=on_step)
    block = summarise(run, problem.scenes, le0, cfg)
    return block, _best_run(run_key(loss, odm), run, problem.scenes, block["best"]["index"])


def run_keys(cfg: StudyConfig) -> list[str]:
    """Keys of the study's runs, in the order :func:`run_study` runs them."""
    return ["photometric"] + [run_key(loss, odm) for loss in cfg.losses for odm in cfg.odm]


def compute_run(scenes: Sequence[ToyScene], cfg: StudyConfig, key: str, on_step=None) -> Finished:
    """Run ``key`` of the study alone (as :func:`run_study` computes it: the same results, bit
    for bit), e.g. in a worker process of ``stillbox-bench toy --jobs``."""
    scenes = list(scenes)
    le0 = initial_log_errors(scenes)
    if key == "photometric":
        return _photometric_run(scenes, le0, cfg, on_step)
    loss, _, setting = key.partition("/odm-")
    lam, kap = grid(cfg)
    device = scenes[0].frames.device
    problem = Problem(scenes, lam.to(device), kap.to(device))
    return _grid_run(problem, loss, setting == "on", le0, cfg, on_step)


def run_study(
    scenes: Sequence[ToyScene],
    cfg: StudyConfig,
    on_run: Callable[[str], None] | None = None,
    on_step: Callable[[], None] | None = None,
    done: dict[str, Finished] | None = None,
    on_done: Callable[[str, dict, BestRun], None] | None = None,
) -> tuple[dict, dict[str, BestRun]]:
    """The study: photometric loss alone, then every loss of ``cfg`` × ODM setting over the
    (λ, κ) grid, each one batch. Returns results.json's dict and each run's :class:`BestRun`
    (key ``"photometric"`` or :func:`run_key`). ``on_run(key)`` is called before each run
    computed here, ``on_done(key, block, best)`` after it (to save it: :mod:`toy_runs`);
    ``done`` holds runs finished earlier by key, taken as they are instead of run again."""
    scenes = list(scenes)
    done = done or {}
    le0 = initial_log_errors(scenes)
    results: dict = {
        "scenes": [s.name for s in scenes],
        "iterations": cfg.iterations,
        "learning_rate": LEARNING_RATE,
        "optimizer": "Adam (betas 0.9, 0.999)",
        "start_depth_m": START_DEPTH,
        "depth_range_m": [MIN_DEPTH, MAX_DEPTH],
        "odm_every": cfg.odm_every,
        "lambdas": list(cfg.lambdas),
        "kappas": list(cfg.kappas),
        "le0": {n: round(v, 4) for n, v in le0.items()},
        "runs": {},
    }
    best: dict[str, BestRun] = {}

    def one(key: str, run: Callable[[], Finished]) -> Finished:
        if key in done:
            return done[key]
        if on_run is not None:
            on_run(key)
        block, b = run()
        if on_done is not None:
            on_done(key, block, b)
        return block, b

    results["photometric"], best["photometric"] = one(
        "photometric", partial(_photometric_run, scenes, le0, cfg, on_step)
    )
    lam, kap = grid(cfg)
    device = scenes[0].frames.device
    problem = Problem(scenes, lam.to(device), kap.to(device))
    for loss in cfg.losses:
        for odm in cfg.odm:
            key = run_key(loss, odm)
            run = partial(_grid_run, problem, loss, odm, le0, cfg, on_step)
            results["runs"][key], best[key] = one(key, run)
    return results, best


def table_markdown(results: dict) -> str:
    """Table 4.1's layout, ours beside the thesis': per loss, rows κ, λ, M, ΔM, LE (Horizon),
    LE (Flower), columns ODM off / on, each "ours (thesis)"."""
    rows = [("κ", "kappa"), ("λ", "lambda"), ("M", "m"), ("ΔM", "delta_m")]
    rows += [(f"LE ({n.capitalize()})", n) for n in SCENES]
    lines = []
    for loss in dict.fromkeys(k.split("/")[0] for k in results["runs"]):
        lines += [
            f"| {loss} | ODM off: ours (thesis) | ODM on: ours (thesis) |",
            "|---|---|---|",
        ]
        for label, key in rows:
            cells = []
            for odm in (False, True):
                block = results["runs"].get(run_key(loss, odm))
                thesis = thesis_value(loss, odm, key)
                ref = "–" if thesis is None else f"{thesis:g}"
                if block is None:
                    cells.append(f"not run ({ref})")
                    continue
                b = block["best"]
                ours = b["le"][key] if key in SCENES else b[key]
                cells.append(
                    f"{ours:.3g} ({ref})" if key not in ("kappa", "lambda") else f"{ours:g} ({ref})"
                )
            lines.append(f"| {label} | {cells[0]} | {cells[1]} |")
        lines.append("")
    photo = results["photometric"]["best"]
    le0 = results["le0"]
    head = [
        f"Toy problems (thesis Table 4.1): {results['iterations']} iterations, Adam lr "
        f"{results['learning_rate']}, grid λ ∈ {results['lambdas']}, κ ∈ {results['kappas']}, "
        f"ODM mask recomputed every {results['odm_every']} iterations.",
        "",
        "LE_0 (start at 10 m): "
        + ", ".join(f"{n} {v:.3f}" for n, v in le0.items())
        + "; photometric loss alone: LE "
        + ", ".join(f"{n} {v:.3f}" for n, v in photo["le"].items())
        + f", M {photo['m']:.3f}.",
        "",
        "ΔM (undefined in the thesis): mean slope of M from the optimum to its grid neighbours "
        "along λ and κ, per decade (benchmark/toy.py, `robustness`).",
        "",
    ]
    return "\n".join(head + lines)


def measure(
    scenes: Sequence[ToyScene], cfg: StudyConfig, iterations: int = 3
) -> dict[str, dict[str, float]]:
    """Seconds per iteration (one optimiser step, without the LE history recorded every
    ``iterations // HISTORY_POINTS``) of each loss's full batch (``len(scenes)`` × grid
    points), wall and process CPU time, after one warm-up step; ``"photometric"`` alone; and
    one ODM call on the whole batch (``"odm"``, both references). With the ODM every k
    iterations an iteration costs ``loss + odm / k``."""
    lam, kap = grid(cfg)
    problem = Problem(list(scenes), lam, kap)
    start = _np(torch.full_like(problem.truth, START_DEPTH)[:, 0])
    out = {}
    for loss in (None, *cfg.losses):
        state = _Kernels(problem, loss, start.copy())
        state.step(1, LEARNING_RATE)  # compiles the kernels (numba caches them on disk)
        t0, c0 = time.perf_counter(), time.process_time()
        for t in range(2, iterations + 2):
            state.step(t, LEARNING_RATE)
        out[loss or "photometric"] = {
            "wall": (time.perf_counter() - t0) / iterations,
            "cpu": (time.process_time() - c0) / iterations,
        }
    state = _Kernels(problem, None, start)
    state.occlusions()
    t0, c0 = time.perf_counter(), time.process_time()
    state.occlusions()
    out["odm"] = {"wall": time.perf_counter() - t0, "cpu": time.process_time() - c0}
    return out


def extrapolate(per_iteration: dict[str, dict[str, float]], cfg: StudyConfig, key: str) -> float:
    """Seconds of the whole study of ``cfg`` from :func:`measure`'s ``key`` ("wall" or "cpu")
    times, the photometric-only run counted as one loss run (it is 1 grid point, not G)."""
    odm = per_iteration["odm"][key] / cfg.odm_every
    total = 0.0
    for loss in cfg.losses:
        for on in cfg.odm:
            total += per_iteration[loss][key] + (odm if on else 0.0)
    points = len(cfg.lambdas) * len(cfg.kappas)
    total += per_iteration["photometric"][key] / points
    return total * cfg.iterations
