"""The run loop of ``stillbox-gen generate``: prepare the output folder, render the pending
scenes in a pool of Blender workers (local processes, or Ray actors with ``--backend ray``),
commit each scene as it finishes, then index the dataset. The run's phases (stillbox_gen.phases)
are timed on the way, the driver's here and the workers' from each scene's statistics, into
``Summary.profile``.

A scene is complete exactly when its record exists (stillbox_gen.writer.commit_scene), so a
killed run resumes where it stopped. A worker that dies, or a pool in which no scene finishes
for ``scene_timeout`` seconds, gets the whole pool replaced and the scenes in flight retried.
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, wait
from dataclasses import dataclass, field
from pathlib import Path

from tqdm import tqdm

from . import formats, layout, writer
from .config import CPU_DEVICE, DatasetConfig
from .lock import folder_lock
from .phases import RunProfile
from .scene import sample_scene
from .workers import LocalPool


@dataclass
class RunOptions:
    """How to run a generation (what to render is the DatasetConfig)."""

    out: Path
    scenes: int
    workers: int = 2  # Blender worker processes (or Ray actors)
    threads: int = 0  # Cycles threads per worker; 0 = all cores
    recycle_after: int = 200  # scenes per worker process before it is replaced
    progress: bool = True
    shard: tuple[int, int] = (0, 1)  # (I, N): render only scene indices k with k % N == I
    scene_timeout: float = 600.0  # seconds without any finished scene before workers are replaced
    retries: int = 2  # extra attempts per scene after a crash, hang or render error
    backend: str = "local"  # "local" (process pool) or "ray" (actors on a Ray cluster)
    ray_address: str | None = None  # Ray cluster to join; None starts a local instance
    # Cycles device of local workers: CPU_DEVICE or a GPU backend (workers.choose_device gives
    # it for --device); it changes no scene. Ray actors render on CPUs.
    device: str = CPU_DEVICE
    # time Cycles' sync, sampling and result apart in local workers (WorkerSetup.profile);
    # every other phase is timed in every run
    profile: bool = False


@dataclass
class Summary:
    """What a run did (printed at its end; ``run`` block of dataset.json)."""

    scenes: int = 0
    frames: int = 0
    rendered_now: int = 0
    rejected: int = 0
    seconds: float = 0.0
    bytes: int = 0
    peak_rss_mb: float = 0.0
    split_counts: dict = field(default_factory=dict)
    failures: list = field(default_factory=list)  # "scene k: why", one per failed attempt
    profile: RunProfile = field(default_factory=RunProfile)  # where the time went

    def lines(self) -> list[str]:
        fps = self.rendered_frames_per_second
        return [
            f"scenes      {self.scenes} ({self.rendered_now} rendered now)",
            f"frames      {self.frames}",
            f"rejected    {self.rejected} sampled scenes (camera path hit an object)",
            f"splits      {', '.join(f'{k} {v}' for k, v in self.split_counts.items())}",
            f"time        {self.seconds:.1f} s ({fps:.1f} frames/s rendered)",
            f"size        {self.bytes / 1e6:.1f} MB",
            f"peak RSS    {self.peak_rss_mb:.0f} MB per worker",
            f"failures    {len(self.failures)} (retried)"
            + "".join(f"\n              {f}" for f in self.failures[:10]),
        ]

    @property
    def rendered_frames_per_second(self) -> float:
        frames = self.rendered_now * (self.frames // max(self.scenes, 1))
        return frames / self.seconds if self.seconds > 0 else 0.0


def new_pool(cfg: DatasetConfig, opts: RunOptions):
    """The worker pool of ``opts.backend``: workers.LocalPool, or ray_pool.RayPool."""
    args = (cfg, opts.workers, opts.threads, opts.recycle_after)
    if opts.backend == "ray":
        from .ray_pool import RayPool

        return RayPool(*args)
    return LocalPool(*args, opts.device, opts.profile)


class _Scheduler:
    """Keeps ``2 * workers`` scenes in flight in a pool until ``todo`` is rendered; commits
    each finished scene (``on_done(stats)`` after it). A dead worker or a hang replaces the pool
    (:meth:`_replace`) and retries its scenes, at most ``opts.retries`` times each."""

    def __init__(
        self,
        cfg: DatasetConfig,
        opts: RunOptions,
        todo: list[int],
        summary: Summary,
        on_done: Callable[[dict], None],
    ):
        self.cfg, self.opts, self.summary, self.on_done = cfg, opts, summary, on_done
        self.queue = list(reversed(todo))  # pop() from the end gives ascending order
        self.attempts: dict[int, int] = {}
        self.running: dict[Future, dict] = {}
        self.broken = False  # set when submit() found the pool broken
        self.times = summary.profile
        with self.times.measure("pool_start"):
            self.pool = new_pool(cfg, opts)

    def run(self) -> None:
        try:
            self._fill()
            restarts = 0
            while self.running or self.queue:
                if not self.running:  # submit() found the pool broken with nothing in flight
                    restarts += 1
                    if restarts > self.opts.retries + 3:
                        raise RuntimeError("worker processes keep dying before they take a scene")
                    self._replace([], "")
                    continue
                timeout = self.opts.scene_timeout
                with self.times.measure("wait"):
                    done, _ = wait(self.running, timeout=timeout, return_when=FIRST_COMPLETED)
                if not done:  # watchdog: nothing finished in time, assume a hung worker
                    stuck = list(self.running.values())
                    self._replace(stuck, f"no scene finished within {timeout:g} s (hung worker)")
                    continue
                crashed = [spec for spec in map(self._finish, done) if spec is not None]
                if crashed or self.broken:  # a broken pool fails every future: replace, retry
                    self._replace(crashed + list(self.running.values()), "worker process died")
        except BaseException:
            self.pool.kill()
            raise
        with self.times.measure("pool_stop"):
            self.pool.shutdown()

    def _submit_next(self) -> None:
        if not self.queue:
            return
        index = self.queue.pop()
        with self.times.measure("sample"):
            spec = sample_scene(self.cfg, index).to_dict()
            tmp = self.opts.out / layout.scene_tmp_name(index)
            formats.remove_tree(tmp)
            tmp.mkdir(parents=True)
        r = self.cfg.render
        try:
            with self.times.measure("submit"):
                fut = self.pool.submit(spec, tmp, r.image_format, r.legacy)
        except self.pool.died_errors:  # a worker died since the last check: replaced soon
            self.queue.append(index)
            self.broken = True
            return
        self.running[fut] = spec

    def _fill(self) -> None:
        for _ in range(2 * self.opts.workers):
            self._submit_next()

    def _finish(self, fut: Future) -> dict | None:
        """Commit a finished scene, or retry it after a render error; returns its spec when its
        worker died instead (the caller then replaces the pool)."""
        spec = self.running.pop(fut)
        try:
            stats = fut.result()
        except self.pool.died_errors:
            return spec
        except Exception as e:  # a scene that cannot render: retried, then fatal
            if formats.is_disk_full(e):  # no retry can help: stop (cli.main says it in a line)
                raise
            self._retry([spec], f"{type(e).__name__}: {e}")
            self._submit_next()
            return None
        with self.times.measure("commit"):
            _write_returned_files(self.opts.out / layout.scene_tmp_name(spec["index"]), stats)
        writer.commit_scene(self.opts.out, spec, self.cfg, self.times.times)
        self.on_done(stats)
        self._submit_next()
        return None

    def _replace(self, failed: list[dict], why: str) -> None:
        """Kill the pool, count ``failed`` scenes as attempts (``why``), start a new pool and
        submit again: the one way out of a crash, a hang or a broken pool."""
        self.running.clear()
        self.broken = False
        self.pool.kill()
        self._retry(failed, why)
        with self.times.measure("pool_start"):
            self.pool = new_pool(self.cfg, self.opts)
        self._fill()

    def _retry(self, specs: list[dict], why: str) -> None:
        for spec in specs:
            k = spec["index"]
            self.attempts[k] = self.attempts.get(k, 0) + 1
            self.summary.failures.append(f"scene {k}: {why}")
            if self.attempts[k] > self.opts.retries:
                raise RuntimeError(
                    f"scene {k} failed {self.attempts[k]} times (last: {why}); finished scenes "
                    "are kept, re-run the same command to resume"
                )
            self.queue.append(k)


def _write_returned_files(tmp: Path, result: dict) -> None:
    """Remote workers return a scene's files as {name: bytes}; write them where a local
    worker would have."""
    for name, data in sorted(result.pop("files", {}).items()):
        (tmp / name).write_bytes(data)


def render_pending(cfg: DatasetConfig, opts: RunOptions, todo: list[int], summary: Summary):
    """Render and commit the scenes ``todo`` (indices) with a progress bar; failures are
    counted in ``summary.failures``, scenes rendered and peak memory in ``summary``."""
    if not todo:
        return
    shard_total = len(range(opts.shard[0], opts.scenes, opts.shard[1]))
    bar = tqdm(
        total=shard_total,
        initial=shard_total - len(todo),
        unit="scene",
        disable=not opts.progress,
        dynamic_ncols=True,
    )
    t0 = time.perf_counter()

    def done(stats: dict) -> None:
        summary.rendered_now += 1
        summary.peak_rss_mb = max(summary.peak_rss_mb, stats["peak_rss_mb"])
        summary.profile.add_scene(stats)
        bar.update(1)
        elapsed = time.perf_counter() - t0
        bar.set_postfix(fps=f"{summary.rendered_now * cfg.camera.frames / elapsed:.1f}")

    try:
        _Scheduler(cfg, opts, todo, summary, done).run()
    finally:
        bar.close()


def folder_size(path: Path) -> int:
    """Bytes of every file under ``path`` (a file another shard renames meanwhile is skipped)."""
    total = 0
    for f in path.rglob("*"):
        with contextlib.suppress(FileNotFoundError):
            total += f.stat().st_size if f.is_file() else 0
    return total


def generate(cfg: DatasetConfig, opts: RunOptions, announce=lambda: None) -> Summary:
    """Render and index a dataset; ``announce`` runs once the output folder is accepted.

    With ``opts.shard`` = (I, N), only scenes k % N == I are rendered; the folder is indexed
    (metadata, manifest, dataset.json complete) by whichever shard finds every scene present,
    or later by :func:`writer.index_dataset`. The result equals an unsharded run with the same
    seed. A second run on the same ``opts.out`` (the same shard, or any shard beside an
    unsharded run) is refused with a FolderInUse error while this one runs (stillbox_gen.lock).
    """
    with folder_lock(opts.out, "--out", opts.shard):  # refuses a second run on --out
        return _generate(cfg, opts, announce)


def _generate(cfg: DatasetConfig, opts: RunOptions, announce) -> Summary:
    """:func:`generate` once the folder's lock is held."""
    device = CPU_DEVICE if opts.backend == "ray" else opts.device
    summary = Summary()
    with summary.profile.measure("prepare"):
        devices = writer.prepare_output(opts.out, cfg, opts.scenes, device)
    announce()
    with summary.profile.measure("prepare"):
        todo = writer.pending_indices(opts.out, opts.scenes, opts.shard)
    t0 = time.perf_counter()
    if opts.backend == "ray" and todo:
        from .ray_pool import ray_session

        with ray_session(opts.ray_address):
            render_pending(cfg, opts, todo, summary)
    else:
        render_pending(cfg, opts, todo, summary)
    seconds = time.perf_counter() - t0
    run_info = {
        "seconds": round(seconds, 3),
        "scenes_rendered": summary.rendered_now,
        "backend": opts.backend,
        "workers": opts.workers,
        "threads_per_worker": opts.threads,
        "peak_rss_mb_per_worker": round(summary.peak_rss_mb, 1),
        "failures": summary.failures,
    }
    with summary.profile.measure("finalize"):
        pending = writer.pending_indices(opts.out, opts.scenes)
    if pending:  # other shards still have work
        return dataclasses.replace(summary, seconds=seconds, scenes=opts.scenes)
    with summary.profile.measure("finalize"):
        totals = writer.finalize(opts.out, cfg, opts.scenes, run_info, devices)
    with summary.profile.measure("size"):
        size = folder_size(opts.out)
    return dataclasses.replace(
        summary,
        scenes=totals.scenes,
        frames=totals.frames,
        rejected=totals.rejected,
        split_counts=totals.split_counts,
        seconds=seconds,
        bytes=size,
    )
