"""The cost of one unsupervised training step, against a supervised one, measured in one run.

``python -m benchmark.unsupervised.step_speed --res 128 --batch 8 --steps 6`` times, step by
step in turn so that all see the same load on a shared machine (median of the timed steps,
after one untimed warm-up):

- ``supervised``: DepthNet's supervised step (benchmark.engine.pair_step.TrainStep, training
  defaults) on a random pair and target;
- ``unsupervised``: ``depthnet-unsup``'s step (PhotometricStep: DepthNet + PoseNet, eq. 5.5 over
  every reference and scale), as trained (``levers`` on);
- ``unsupervised, levers off``: the same step with the photometric terms as first written
  (every target repeated for its warps, kornia's SSIM with its depthwise convolutions).

Inputs are random frames (``(B, 5, 3, H, W)``, a focal of half the width, rotations of a few
degrees with ``--pose orientation``): the cost does not depend on the content. Before timing,
the two unsupervised variants' losses and parameter gradients on the same batch and weights are
compared; the largest differences are printed (the levers change no value beyond float
rounding). One CSV row per variant with ``--out``.
"""

from __future__ import annotations

import argparse
import copy
import csv
import statistics
import time
from pathlib import Path

import torch

from ..core import registry
from ..engine.pair_step import TrainStep
from ..engine.train import make_optimizer
from .training import PhotometricStep, smooth_settings

UNSUPERVISED = "depthnet-unsup"
FRAMES = registry.UNSUPERVISED_RECIPE.sequence_length


def _rotation(angles: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``(…, 3, 3)`` of axis-angle vectors ``(…, 3)`` (radians)."""
    zero = torch.zeros_like(angles[..., 0])
    x, y, z = angles.unbind(-1)
    skew = torch.stack((zero, -z, y, z, zero, -x, -y, x, zero), -1)
    return torch.linalg.matrix_exp(skew.view(*angles.shape[:-1], 3, 3))


def random_batch(batch: int, size: int, seed: int = 0) -> dict:
    """A SequenceDataset-like batch of random frames (see benchmark.unsupervised.sequences)."""
    g = torch.Generator().manual_seed(seed)
    frames = torch.rand(batch, FRAMES, 3, size, size, generator=g)
    sequence = (frames - 0.5) / 0.2
    tgt = torch.randint(0, FRAMES, (batch,), generator=g)
    ref = (tgt + 1 + torch.randint(0, FRAMES - 1, (batch,), generator=g)) % FRAMES
    rows = torch.arange(batch)
    rotation = _rotation(torch.randn(batch, FRAMES, 3, generator=g) * 0.05)
    rotation[rows, tgt] = torch.eye(3)
    f = size / 2
    K = torch.tensor([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1.0]])
    return {
        "frames": frames,
        "sequence": sequence.reshape(batch, 3 * FRAMES, size, size),
        "input": torch.cat([sequence[rows, ref], sequence[rows, tgt]], 1),
        "target_index": tgt,
        "reference_index": ref,
        "K": K.expand(batch, 3, 3).contiguous(),
        "rotation": rotation,
    }


def _unsupervised(levers: bool, pose: str, occlusion: bool, state=None) -> PhotometricStep:
    torch.manual_seed(0)
    net = registry.build_model(UNSUPERVISED)
    if state is not None:
        net.load_state_dict(state)
    recipe = registry.MODELS[UNSUPERVISED].recipe
    opt = make_optimizer(net.parameters(), recipe, fused=True)
    lam, kappa = smooth_settings(None, None, occlusion)
    d0 = 0.3  # metres; any positive value costs the same
    return PhotometricStep(net, opt, torch.device("cpu"), recipe.loss_weights, d0, lam, kappa,
                           occlusion, None, pose, levers=levers)  # fmt: skip


def _supervised() -> TrainStep:
    torch.manual_seed(0)
    spec = registry.MODELS["depthnet"]
    net = spec.build()
    opt = make_optimizer(net.parameters(), spec.recipe, fused=True)
    return TrainStep(
        net, opt, torch.device("cpu"), spec.recipe.loss_weights, spec.recipe.loss_scale
    )


def agreement(on: PhotometricStep, off: PhotometricStep, batch: dict) -> dict[str, float]:
    """Largest absolute differences between the two variants' loss terms and parameter
    gradients on ``batch`` (the same weights in both)."""
    out = {}
    grads = []
    for step in (on, off):
        step.net.zero_grad(set_to_none=True)
        terms = step.losses(batch)
        terms["loss"].backward()
        grads.append([p.grad.clone() for p in step.net.parameters() if p.grad is not None])
        out.setdefault("terms", []).append(
            torch.stack([terms[k].detach() for k in ("loss", "photometric", "smooth")])
        )
    return {
        "max_loss_diff": float((out["terms"][0] - out["terms"][1]).abs().max()),
        "max_grad_diff": max(float((a - b).abs().max()) for a, b in zip(*grads, strict=True)),
        "max_grad": max(float(a.abs().max()) for a in grads[0]),
    }


def measure(size: int, batch: int, steps: int, pose: str = "orientation",
            occlusion: bool = False) -> tuple[list[dict], dict]:  # fmt: skip
    """Rows ``variant, ms_per_step, ms_per_sample, vs_supervised`` and the agreement check."""
    data = random_batch(batch, size)
    on = _unsupervised(True, pose, occlusion)
    off = _unsupervised(False, pose, occlusion, copy.deepcopy(on.net.state_dict()))
    check = agreement(on, off, data)
    g = torch.Generator().manual_seed(1)
    sup_batch = {"input": data["input"], "target": torch.rand(batch, size, size, generator=g) * 100}
    variants = {
        "supervised": (_supervised(), sup_batch),
        "unsupervised": (on, data),
        "unsupervised, levers off": (off, data),
    }
    times: dict[str, list[float]] = {k: [] for k in variants}
    for i in range(steps + 1):
        for name, (step, b) in variants.items():
            t0 = time.perf_counter()
            step(b).item()
            if i:  # the first round warms up
                times[name].append(time.perf_counter() - t0)
            print(f"step {i}/{steps} {name}: {time.perf_counter() - t0:.2f} s", flush=True)
    sup = statistics.median(times["supervised"])
    rows = []
    for name, t in times.items():
        med = statistics.median(t)
        rows.append({
            "variant": name, "px": size, "batch": batch, "pose": pose, "occlusion": occlusion,
            "ms_per_step": round(med * 1e3, 1), "ms_per_sample": round(med * 1e3 / batch, 1),
            "vs_supervised": round(med / sup, 2), "steps": steps,
            "threads": torch.get_num_threads(), "torch": torch.__version__,
        })  # fmt: skip
    return rows, check


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--res", type=int, default=128, help="square frame size, pixels (× 64)")
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--steps", type=int, default=6, help="timed steps per variant")
    p.add_argument("--pose", default="orientation", choices=("orientation", "translation"))
    p.add_argument("--occlusion", action="store_true")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", type=Path, help="CSV file to write")
    a = p.parse_args(argv)
    # DepthNet's batch norm needs two samples at its 1-pixel scale; 64 px its smallest input
    if not (
        64 <= a.res <= 1024 and a.res % 64 == 0 and 2 <= a.batch <= 256 and 1 <= a.steps <= 1000
    ):
        p.error("--res a multiple of 64 in 64-1024, --batch 2-256, --steps 1-1000")
    torch.set_num_threads(a.threads)
    rows, check = measure(a.res, a.batch, a.steps, a.pose, a.occlusion)
    print("levers on vs off, same weights and batch: " + ", ".join(
        f"{k} {v:.3g}" for k, v in check.items()))  # fmt: skip
    base = next(r for r in rows if r["variant"] == "unsupervised, levers off")["ms_per_step"]
    for r in rows:
        r["vs_levers_off"] = round(base / r["ms_per_step"], 2)
        print(", ".join(f"{k} {v}" for k, v in r.items()))
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        with a.out.open("w", newline="") as f:
            w = csv.DictWriter(f, [*rows[0], "max_loss_diff", "max_grad_diff"])
            w.writeheader()
            for r in rows:
                w.writerow(
                    {**r, **{k: f"{check[k]:.3g}" for k in ("max_loss_diff", "max_grad_diff")}}
                )


if __name__ == "__main__":
    main()
