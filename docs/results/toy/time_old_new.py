"""CPU seconds per iteration of each loss's full default toy batch (70 maps of 200x200), old and
new code interleaved in one process (the "Time" table of README.md here).

Usage: ``python time_old_new.py OLD_ROOT DATA M ROUNDS`` with ``OLD_ROOT`` a folder holding
the old tree's ``benchmark`` package renamed ``benchmark_old`` (``git archive``), ``DATA`` the
folder of ``toy-flower`` and ``toy-horizon``. Both trees' optimiser state (``toy._Kernels``:
the step ``optimise`` runs, without the LE history it records every 100 iterations) on the same
problem; per loss one warm-up step each, then ``ROUNDS`` rounds of old ``M`` steps / new ``M``
steps; then ``ROUNDS`` rounds of one ODM call each after a warm-up call; then
``toy.extrapolate`` for both. 1 thread.
"""

import importlib
import sys
import time

import torch

from benchmark.unsupervised import toy_kernels

OLD_ROOT, DATA = sys.argv[1], sys.argv[2]
M, ROUNDS = (int(a) for a in sys.argv[3:5])
sys.path.insert(0, OLD_ROOT)
torch.set_num_threads(1)
toy_kernels.set_threads(1)  # after choosing numba's threading layer
old = importlib.import_module("benchmark_old.unsupervised.toy")
new = importlib.import_module("benchmark.unsupervised.toy")
importlib.import_module("benchmark_old.unsupervised.toy_kernels").set_threads(1)
trees = {"old": old, "new": new}


def problem(toy):  # noqa: ANN001, ANN201
    names = ("horizon", "flower")
    scenes = [toy.load_scene(f"{DATA}/toy-{n}", n) for n in names]
    return toy.Problem(scenes, *toy.grid(toy.StudyConfig()))


probs = {k: problem(t) for k, t in trees.items()}
cfg = new.StudyConfig()
maps = probs["new"].target.shape[0]
start = new._np(torch.full_like(probs["new"].truth, new.START_DEPTH)[:, 0])
per: dict = {"old": {}, "new": {}}


def row(label: str, key: str) -> None:
    o, n = per["old"][key]["cpu"], per["new"][key]["cpu"]
    print(f"| {label} | {o:.4f} | {n:.4f} | {o / n:.2f} | {1e3 * o / maps:.2f} | "
          f"{1e3 * n / maps:.2f} |", flush=True)  # fmt: skip


for loss in (None, *cfg.losses):
    states = {k: t._Kernels(probs[k], loss, start.copy()) for k, t in trees.items()}
    for s in states.values():
        s.step(1, new.LEARNING_RATE)
    step, acc = 2, {"old": 0.0, "new": 0.0}
    for _ in range(ROUNDS):
        for k, s in states.items():
            c = time.process_time()
            for i in range(M):
                s.step(step + i, new.LEARNING_RATE)
            acc[k] += time.process_time() - c
        step += M
    key = loss or "photometric"
    for k in trees:
        per[k][key] = {"cpu": acc[k] / (M * ROUNDS)}
    row(loss or "photometric alone", key)
states = {k: t._Kernels(probs[k], None, start.copy()) for k, t in trees.items()}
acc = {"old": 0.0, "new": 0.0}
for s in states.values():
    s.occlusions()
for _ in range(ROUNDS):
    for k, s in states.items():
        c = time.process_time()
        s.occlusions()
        acc[k] += time.process_time() - c
for k in trees:
    per[k]["odm"] = {"cpu": acc[k] / ROUNDS}
row("one ODM call (both references)", "odm")
for name in trees:
    hours = new.extrapolate(per[name], cfg, "cpu") / 3600
    print(f"{name}: extrapolated full study {hours:.2f} CPU-hours, {hours / 2:.2f} h on 2 cores")
