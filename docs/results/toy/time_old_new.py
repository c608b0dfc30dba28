"""CPU seconds per iteration of each loss's full default toy batch (70 maps of 200x200), old and
new code interleaved in one process (the "Time" table of README.md here).

Usage: ``python time_old_new.py OLD_ROOT DATA N M ROUNDS`` with ``OLD_ROOT`` a folder holding
the old tree's ``benchmark`` package renamed ``benchmark_old`` (``git archive``), ``DATA`` the
folder of ``toy-flower`` and ``toy-horizon``; per loss one warm-up iteration each, then
``ROUNDS`` rounds of old ``N`` iterations (``toy.optimise``) / new ``M`` iterations (the step
``optimise`` runs); one ODM call each after a warm-up call; then ``toy.extrapolate``. 1 thread.
"""

import importlib
import sys
import time

import torch

from benchmark.unsupervised import toy_kernels

OLD_ROOT, DATA = sys.argv[1], sys.argv[2]
N, M, ROUNDS = (int(a) for a in sys.argv[3:6])
sys.path.insert(0, OLD_ROOT)
torch.set_num_threads(1)
toy_kernels.set_threads(1)  # after choosing numba's threading layer
old = importlib.import_module("benchmark_old.unsupervised.toy")
new = importlib.import_module("benchmark.unsupervised.toy")


def problem(toy):  # noqa: ANN001, ANN201
    names = ("horizon", "flower")
    scenes = [toy.load_scene(f"{DATA}/toy-{n}", n) for n in names]
    return toy.Problem(scenes, *toy.grid(toy.StudyConfig()))


probs = {"old": problem(old), "new": problem(new)}
cfg = new.StudyConfig()
maps = probs["new"].target.shape[0]
start = new._np(torch.full_like(probs["new"].truth, new.START_DEPTH)[:, 0])
per: dict = {"old": {}, "new": {}}


def row(label: str, key: str) -> None:
    o, n = per["old"][key]["cpu"], per["new"][key]["cpu"]
    print(f"| {label} | {o:.3f} | {n:.4f} | {o / n:.1f} | {1e3 * o / maps:.1f} | "
          f"{1e3 * n / maps:.2f} |", flush=True)  # fmt: skip


for loss in (None, *cfg.losses):
    old.optimise(probs["old"], loss, 1)
    state = new._Kernels(probs["new"], loss, start.copy())
    state.step(1, new.LEARNING_RATE)
    step, acc = 2, {"old": 0.0, "new": 0.0}
    for _ in range(ROUNDS):
        acc["old"] += old.optimise(probs["old"], loss, N).cpu_seconds
        c = time.process_time()
        for _ in range(M):
            state.step(step, new.LEARNING_RATE)
            step += 1
        acc["new"] += time.process_time() - c
    key = loss or "photometric"
    per["old"][key] = {"cpu": acc["old"] / (N * ROUNDS)}
    per["new"][key] = {"cpu": acc["new"] / (M * ROUNDS)}
    row(loss or "photometric alone", key)
depth = torch.full_like(probs["old"].truth, new.START_DEPTH)
probs["old"].occlusions(depth)
c = time.process_time()
probs["old"].occlusions(depth)
per["old"]["odm"] = {"cpu": time.process_time() - c}
state = new._Kernels(probs["new"], None, start.copy())
state.occlusions()
c = time.process_time()
state.occlusions()
per["new"]["odm"] = {"cpu": time.process_time() - c}
row("one ODM call (both references)", "odm")
for name in ("old", "new"):
    hours = new.extrapolate(per[name], cfg, "cpu") / 3600
    print(f"{name}: extrapolated full study {hours:.2f} CPU-hours, {hours / 2:.2f} h on 2 cores")
