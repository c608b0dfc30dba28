"""The toy study's runs spread over worker processes: ``stillbox-bench toy --jobs N``.

The study's runs are independent (:func:`toy.compute_run`), so N single-threaded processes run
them side by side, the costliest first (longest-processing-time order, :data:`RELATIVE_COST`),
each handing its run back to the parent, which saves it as it arrives (toy_runs: an interrupted
study resumes) and then assembles the study as :func:`toy.run_study` does. The workers report
their iterations through a queue as they go (every :data:`PROGRESS_EVERY`), so the parent's
progress bar moves during a run, not only at its end. The results are the
same, bit for bit, whatever N: every run is computed by the same code from the same inputs, and
the kernels' results do not depend on their thread count.

Why processes and not the kernels' threads (``--threads``): numba splits each iteration's rows
statically between its threads, which wait for each other every iteration, so on a machine
where anything else runs the slowest thread sets the pace (measured: 17.4 iterations/s with 2
threads on a quiet machine, 2.6-3 once other jobs ran beside it, even at the lowest priority);
a single-threaded process keeps its pace on its core (docs/results/toy/README.md).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from multiprocessing import get_context
from queue import Empty

from .toy import BestRun, Finished, StudyConfig, ToyScene, compute_run, run_keys

#: CPU time per iteration of a run relative to a plain smooth loss's (measured: the robust
#: losses' 10 inner diffusion steps cost about 1.3x; the photometric run has no grid)
RELATIVE_COST = {"photometric": 0.1, "robust_diffusion": 1.3, "robust_gradient_diffusion": 1.3}
#: Iterations between two progress reports of a worker (a report is one small queue message)
PROGRESS_EVERY = 50
#: Seconds the parent waits for a run to end before it reads the workers' reports again
POLL_SECONDS = 1.0


def cost(key: str) -> float:
    """Relative CPU time of run ``key`` (``"photometric"`` or ``"<loss>/odm-<on|off>"``)."""
    return RELATIVE_COST.get(key.split("/")[0], 1.0)


def schedule(keys: Sequence[str]) -> list[str]:
    """``keys`` costliest first (ties in their given order): the order runs are handed to the
    workers, which balances N workers within one run's time."""
    return sorted(keys, key=cost, reverse=True)


#: the worker's end of the progress queue (set by :func:`_start_worker`)
_progress = None


def _start_worker(progress) -> None:  # noqa: ANN001 (a multiprocessing queue)
    global _progress
    import torch

    from . import toy_kernels

    torch.set_num_threads(1)
    toy_kernels.set_threads(1)
    _progress = progress


def _run(scenes: list[ToyScene], cfg: StudyConfig, key: str) -> tuple[str, dict, BestRun]:
    """Run ``key`` in a worker, putting its iterations on the progress queue as they are done
    (every PROGRESS_EVERY and the remainder at the end)."""
    unreported = 0

    def step() -> None:
        nonlocal unreported
        unreported += 1
        if unreported == PROGRESS_EVERY:
            _progress.put(unreported)
            unreported = 0

    block, best = compute_run(scenes, cfg, key, on_step=step if _progress is not None else None)
    if _progress is not None and unreported:
        _progress.put(unreported)
    return key, block, best


def _drain(progress, on_progress: Callable[[int], None] | None) -> None:  # noqa: ANN001
    """Hand every iteration count waiting in ``progress`` to ``on_progress``."""
    while True:
        try:
            n = progress.get_nowait()
        except Empty:
            return
        if on_progress is not None:
            on_progress(n)


def run_parallel(
    scenes: Sequence[ToyScene],
    cfg: StudyConfig,
    jobs: int,
    done: dict[str, Finished],
    on_done: Callable[[str, dict, BestRun], None],
    on_progress: Callable[[int], None] | None = None,
) -> dict[str, Finished]:
    """The study's runs not in ``done``, computed by ``jobs`` worker processes (spawned, one
    thread each); ``on_done(key, block, best)`` is called in this process as each one ends,
    ``on_progress(n)`` as the workers report ``n`` more iterations done (each run's
    ``cfg.iterations`` in all, by the time this returns). Returns the runs by key. A
    failure or Ctrl-C cancels the runs not started, waits for the workers and raises (the runs
    already handed to ``on_done`` are kept)."""
    pending = schedule([k for k in run_keys(cfg) if k not in done])
    finished: dict[str, Finished] = {}
    scenes = [s.to("cpu") for s in scenes]
    context = get_context("spawn")
    progress = context.Queue()
    pool = ProcessPoolExecutor(
        jobs, mp_context=context, initializer=_start_worker, initargs=(progress,)
    )
    try:
        running = {pool.submit(_run, scenes, cfg, key) for key in pending}
        while running:
            ended, running = wait(running, timeout=POLL_SECONDS, return_when=FIRST_COMPLETED)
            _drain(progress, on_progress)
            for future in ended:
                key, block, best = future.result()
                on_done(key, block, best)
                finished[key] = (block, best)
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    _drain(progress, on_progress)  # what the workers sent as their last runs ended
    progress.close()
    return finished
