"""Wall and CPU seconds per iteration of one loss's full default toy batch (70 maps of 200x200)
with 1 and with 2 kernel threads, interleaved in one process (README.md here, "Time").

Usage: ``python time_threads.py DATA LOSS M ROUNDS``: ``DATA`` the folder of ``toy-flower`` and
``toy-horizon``, ``LOSS`` a smooth loss (``photometric`` for none); one warm-up step with each
thread count, then ``ROUNDS`` rounds of ``M`` steps with 1 thread / ``M`` steps with 2.
"""

import sys
import time

import torch

from benchmark.unsupervised import toy, toy_kernels

DATA, LOSS = sys.argv[1], sys.argv[2]
M, ROUNDS = (int(a) for a in sys.argv[3:5])
torch.set_num_threads(1)
scenes = [toy.load_scene(f"{DATA}/toy-{n}", n) for n in ("horizon", "flower")]
problem = toy.Problem(scenes, *toy.grid(toy.StudyConfig()))
start = toy._np(torch.full_like(problem.truth, toy.START_DEPTH)[:, 0])
smooth = None if LOSS == "photometric" else LOSS
states = {n: toy._Kernels(problem, smooth, start.copy()) for n in (1, 2)}
wall, cpu = {1: [], 2: []}, {1: 0.0, 2: 0.0}
for n, s in states.items():
    toy_kernels.set_threads(n)
    s.step(1, toy.LEARNING_RATE)
step = 2
for _ in range(ROUNDS):
    for n, s in states.items():
        toy_kernels.set_threads(n)
        t, c = time.perf_counter(), time.process_time()
        for i in range(M):
            s.step(step + i, toy.LEARNING_RATE)
        wall[n].append((time.perf_counter() - t) / M)
        cpu[n] += time.process_time() - c
    step += M
for n in states:
    w = sorted(wall[n])
    rounds = " ".join(f"{x:.3f}" for x in wall[n])
    print(f"{n} thread(s): wall s/it median {w[len(w) // 2]:.4f} min {w[0]:.4f} "
          f"(rounds {rounds}), CPU s/it {cpu[n] / (M * ROUNDS):.4f}")  # fmt: skip
