"""Run a generation: prepare the output folder, render pending scenes in worker processes, commit
each scene atomically, then write metadata.json per chunk, manifest.parquet and dataset.json.

A scene is complete exactly when ``<chunk>/.records/<s>.json`` exists; it is written (atomically)
after the scene's files have been moved into the chunk folder. Re-running the same command skips
complete scenes and redoes the rest, so a killed run resumes where it stopped.
"""

from __future__ import annotations

import dataclasses
import json
import multiprocessing
import os
import time
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from importlib import metadata as importlib_metadata
from pathlib import Path

from tqdm import tqdm

from . import config, formats, manifest, photos
from .config import ConfigError, DatasetConfig, denoise_quality
from .scene import sample_scene

DATASET_JSON = "dataset.json"
MANIFEST = "manifest.parquet"


@dataclass
class RunOptions:
    out: Path
    scenes: int
    workers: int = 1
    threads: int = 0  # Cycles threads per worker; 0 = all cores
    recycle_after: int = 200  # scenes per worker process before it is replaced
    progress: bool = True
    shard: tuple[int, int] = (0, 1)  # (I, N): render only scene indices k with k % N == I
    scene_timeout: float = 600.0  # seconds without any finished scene before workers are replaced
    retries: int = 2  # extra attempts per scene after a crash, hang or render error
    backend: str = "local"  # "local" (process pool) or "ray" (actors on a Ray cluster)
    ray_address: str | None = None  # Ray cluster to join; None starts a local instance


@dataclass
class Summary:
    scenes: int = 0
    frames: int = 0
    rendered_now: int = 0
    rejected: int = 0
    seconds: float = 0.0
    bytes: int = 0
    peak_rss_mb: float = 0.0
    split_counts: dict = field(default_factory=dict)
    failures: list = field(default_factory=list)  # "scene k: why", one per failed attempt

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


def versions() -> dict:
    def v(name: str) -> str:
        try:
            return importlib_metadata.version(name)
        except importlib_metadata.PackageNotFoundError:
            return "unknown"

    return {"stillbox-gen": v("stillbox-gen"), "blender (bpy)": v("bpy"), "numpy": v("numpy")}


def generator_name() -> str:
    return f"stillbox-gen {versions()['stillbox-gen']}"


# ---------------------------------------------------------------- output folder


def prepare_output(out: Path, cfg: DatasetConfig, scenes: int) -> None:
    """Check --out, mark the dataset incomplete; ConfigError (nothing written) on conflicts."""
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out: '{out}' exists and is a file, not a folder")
    existing = out / DATASET_JSON
    if existing.is_file():
        try:
            old = json.loads(existing.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise ConfigError(f"--out: cannot read '{existing}' ({e})") from None
        if old.get("fingerprint") != cfg.fingerprint():
            raise ConfigError(
                f"--out: '{out}' holds a dataset made with other parameters "
                f"(preset {old.get('preset')!r}, seed {old.get('seed')}); "
                "use the same parameters to resume or extend it, or another --out"
            )
        if old.get("scenes", 0) > scenes:
            raise ConfigError(
                f"--scenes: {scenes} is fewer than the {old['scenes']} scenes already in '{out}'"
            )
    elif out.is_dir() and any(not _is_own_temporary(p) for p in out.iterdir()):
        if existing.is_file():  # another shard's dataset.json appeared meanwhile: check it
            return prepare_output(out, cfg, scenes)
        raise ConfigError(
            f"--out: '{out}' is a non-empty folder that is not a stillbox-gen dataset"
        )
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"--out: cannot create '{out}' ({e.strerror})") from None
    if not os.access(out, os.W_OK):
        raise ConfigError(f"--out: '{out}' is not writable")
    state = dataset_info(cfg, scenes, complete=False)
    formats.atomic_write_json(existing, state, indent=2)
    (out / MANIFEST).unlink(missing_ok=True)


def _is_own_temporary(path: Path) -> bool:
    """A dataset.json being written by another shard that started into the same new folder."""
    return path.name.startswith(f".{DATASET_JSON}.tmp-")


def dataset_info(cfg: DatasetConfig, scenes: int, complete: bool, **extra) -> dict:
    r, w, h = cfg.render, cfg.camera.width, cfg.camera.height
    return {
        "format_version": formats.FORMAT_VERSION,
        "complete": complete,
        "versions": versions(),
        "preset": cfg.preset,
        "seed": cfg.seed,
        "fingerprint": cfg.fingerprint(),
        "scenes": scenes,
        "frames_per_scene": cfg.camera.frames,
        "chunk_size": formats.CHUNK_SIZE,
        "render": {
            "engine": "CYCLES",
            "device": "CPU",
            "shading": r.shading,
            "samples": r.samples,
            "denoiser": (
                f"OPENIMAGEDENOISE ({denoise_quality(r.denoise_quality, w, h)})"
                if r.denoise
                else None
            ),
            "max_bounces": r.max_bounces,
            "view_transform": "Standard",
            "rgb": f"8-bit sRGB {r.image_format}",
            "depth": formats.DEPTH_CONVENTION,
            "pixel_filter": "box, 1 pixel wide (samples integrate the pixel's area)",
            "noise_seed": (
                "per frame, derived from the scene seed"
                if r.shading == "path"
                else "one per scene (the scene seed): fixed sample placement in every frame"
            ),
            "photos": photo_source(cfg),
        },
        "config": cfg.to_dict(),
        **extra,
    }


def photo_source(cfg: DatasetConfig) -> str | None:
    """Where the photo textures come from, for dataset.json."""
    m = cfg.materials
    if m.texture_files:
        return f"--textures ({len(m.texture_files)} images of config.materials.textures_dir)"
    return photos.BUNDLED_SOURCE if m.photos == "bundled" else None


def pending_indices(out: Path, scenes: int, shard: tuple[int, int] = (0, 1)) -> list[int]:
    """Scene indices of this shard without a record (round-robin: k % N == I)."""
    i, n = shard
    return [k for k in range(i, scenes, n) if not formats.record_path(out, k).is_file()]


# ---------------------------------------------------------------- workers (bpy-free trampolines)


def _worker_init(render: dict, width: int, height: int, threads: int, textures: str | None):
    from .blender.render import init_worker

    init_worker(render, width, height, threads, textures)


def _worker_render(spec: dict, tmp_dir: str, image_format: str, legacy: bool) -> dict:
    from .blender.render import render_scene

    return render_scene(spec, tmp_dir, image_format, legacy)


def _tmp_dir(out: Path, index: int) -> Path:
    return out / formats.chunk_name(index) / f".tmp-{formats.local_index(index):04d}"


def commit_scene(out: Path, spec: dict, cfg: DatasetConfig) -> dict:
    """Move a rendered scene into its chunk folder, then write its record (the completion mark)
    with the SHA-256 of every file of the scene."""
    tmp = _tmp_dir(out, spec["index"])
    chunk_dir = tmp.parent
    record = formats.scene_record(spec, cfg.render.image_format, cfg.render.legacy)
    record["sha256"] = formats.scene_checksums(tmp, record)
    for f in sorted(tmp.iterdir()):
        os.replace(f, chunk_dir / f.name)
    rec_path = formats.record_path(out, spec["index"])
    rec_path.parent.mkdir(exist_ok=True)
    formats.atomic_write_json(rec_path, record)
    formats.remove_tree(tmp)
    return record


class LocalPool:
    """Blender worker processes on this machine (spawned, each replaced after
    ``opts.recycle_after`` scenes); workers write a scene's files into its temporary folder."""

    died_errors: tuple[type[BaseException], ...] = (BrokenProcessPool,)

    def __init__(self, cfg: DatasetConfig, opts: RunOptions) -> None:
        self._pool = ProcessPoolExecutor(
            max_workers=opts.workers,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=_worker_init,
            initargs=worker_init_args(cfg, opts),
            max_tasks_per_child=opts.recycle_after,
        )

    def submit(self, spec: dict, tmp_dir: Path, image_format: str, legacy: bool) -> Future:
        return self._pool.submit(_worker_render, spec, str(tmp_dir), image_format, legacy)

    def kill(self) -> None:
        """Stop workers that crashed or hang (kills the processes, waits for nothing)."""
        for proc in list((getattr(self._pool, "_processes", None) or {}).values()):
            if proc.is_alive():
                proc.kill()
        self._pool.shutdown(wait=False, cancel_futures=True)

    def shutdown(self) -> None:
        self._pool.shutdown(wait=True)


def worker_init_args(cfg: DatasetConfig, opts: RunOptions) -> tuple:
    """Arguments of blender.render.init_worker for this dataset."""
    c, mat = cfg.camera, cfg.materials
    return (cfg.to_dict()["render"], c.width, c.height, opts.threads, mat.textures_dir)


def new_pool(cfg: DatasetConfig, opts: RunOptions):
    """The worker pool of ``opts.backend``: LocalPool, or ray_pool.RayPool."""
    if opts.backend == "ray":
        from .ray_pool import RayPool

        return RayPool(cfg, opts)
    return LocalPool(cfg, opts)


def _write_returned_files(tmp: Path, result: dict) -> None:
    """Remote workers return a scene's files as {name: bytes}; write them where a local
    worker would have."""
    for name, data in sorted(result.pop("files", {}).items()):
        (tmp / name).write_bytes(data)


def render_pending(cfg: DatasetConfig, opts: RunOptions, todo: list[int], summary: Summary):
    """Render ``todo`` in a pool; a crashed or hung worker (no scene finished for
    ``opts.scene_timeout`` s) gets the pool replaced and its scenes retried, up to
    ``opts.retries`` times per scene. Failures are counted in ``summary.failures``."""
    if not todo:
        return
    c = cfg.camera
    shard_total = len(range(opts.shard[0], opts.scenes, opts.shard[1]))
    bar = tqdm(
        total=shard_total,
        initial=shard_total - len(todo),
        unit="scene",
        disable=not opts.progress,
        dynamic_ncols=True,
    )
    t0 = time.perf_counter()
    queue = list(reversed(todo))  # pop() from the end gives ascending order
    attempts: dict[int, int] = {}
    pool = new_pool(cfg, opts)
    running: dict = {}
    broken: list[int] = []  # set when submit() finds the pool broken

    def submit_next() -> None:
        if not queue:
            return
        index = queue.pop()
        spec = sample_scene(cfg, index).to_dict()
        tmp = _tmp_dir(opts.out, index)
        formats.remove_tree(tmp)
        tmp.mkdir(parents=True)
        try:
            fut = pool.submit(spec, tmp, cfg.render.image_format, cfg.render.legacy)
        except pool.died_errors:  # a worker died since the last check: replaced below
            queue.append(index)
            broken.append(index)
            return
        running[fut] = spec

    def retry(specs: list[dict], why: str) -> None:
        for spec in specs:
            k = spec["index"]
            attempts[k] = attempts.get(k, 0) + 1
            summary.failures.append(f"scene {k}: {why}")
            if attempts[k] > opts.retries:
                raise RuntimeError(
                    f"scene {k} failed {attempts[k]} times (last: {why}); finished scenes are "
                    "kept, re-run the same command to resume"
                )
            queue.append(k)

    try:
        for _ in range(2 * opts.workers):
            submit_next()
        restarts = 0
        while running or queue:
            if not running:  # submit() found the pool broken with nothing in flight
                restarts += 1
                if restarts > opts.retries + 3:
                    raise RuntimeError("worker processes keep dying before they take a scene")
                pool.kill()
                pool = new_pool(cfg, opts)
                broken.clear()
                for _ in range(2 * opts.workers):
                    submit_next()
                continue
            done, _ = wait(running, timeout=opts.scene_timeout, return_when=FIRST_COMPLETED)
            if not done:  # watchdog: nothing finished in time, assume a hung worker
                stuck = list(running.values())
                running.clear()
                pool.kill()
                retry(stuck, f"no scene finished within {opts.scene_timeout:g} s (hung worker)")
                pool = new_pool(cfg, opts)
                for _ in range(2 * opts.workers):
                    submit_next()
                continue
            crashed = []
            for fut in done:
                spec = running.pop(fut)
                try:
                    stats = fut.result()
                except pool.died_errors:
                    crashed.append(spec)
                    continue
                except Exception as e:  # a scene that cannot render: retried, then fatal
                    retry([spec], f"{type(e).__name__}: {e}")
                    submit_next()
                    continue
                _write_returned_files(_tmp_dir(opts.out, spec["index"]), stats)
                commit_scene(opts.out, spec, cfg)
                summary.rendered_now += 1
                summary.peak_rss_mb = max(summary.peak_rss_mb, stats["peak_rss_mb"])
                bar.update(1)
                elapsed = time.perf_counter() - t0
                bar.set_postfix(fps=f"{summary.rendered_now * c.frames / elapsed:.1f}")
                submit_next()
            if crashed or broken:  # a broken pool fails every future: replace, retry
                crashed += list(running.values())
                running.clear()
                broken.clear()
                pool.kill()
                retry(crashed, "worker process died")
                pool = new_pool(cfg, opts)
                for _ in range(2 * opts.workers):
                    submit_next()
    except BaseException:
        pool.kill()
        raise
    finally:
        bar.close()
    pool.shutdown()


def finalize(out: Path, cfg: DatasetConfig, scenes: int, run_info: dict) -> Summary:
    """Write every chunk's metadata.json, the manifest and a complete dataset.json."""
    records = [json.loads(formats.record_path(out, k).read_text()) for k in range(scenes)]
    args = formats.chunk_args(cfg.to_dict(), generator_name())
    for start in range(0, scenes, formats.CHUNK_SIZE):
        chunk = records[start : start + formats.CHUNK_SIZE]
        meta = {"args": args, "scenes": chunk}
        formats.atomic_write_json(out / formats.chunk_name(start) / "metadata.json", meta)
    table = manifest.write_manifest(out / MANIFEST, records, cfg.seed, cfg.split)
    splits = table.column("split").to_pylist()
    frames = cfg.camera.frames
    split_counts = {s: splits.count(s) // frames for s in manifest.SPLITS}
    summary = Summary(
        scenes=scenes,
        frames=scenes * frames,
        rejected=sum(r["rejected"] for r in records),
        split_counts=split_counts,
    )
    info = dataset_info(
        cfg,
        scenes,
        complete=True,
        frames=summary.frames,
        rejected_scenes=summary.rejected,
        split_scenes=split_counts,
        run=run_info,
    )
    formats.atomic_write_json(out / DATASET_JSON, info, indent=2)
    return summary


def folder_size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def generate(cfg: DatasetConfig, opts: RunOptions, announce=lambda: None) -> Summary:
    """Render and index a dataset; ``announce`` runs once the output folder is accepted.

    With ``opts.shard`` = (I, N), only scenes k % N == I are rendered; the folder is indexed
    (metadata, manifest, dataset.json complete) by whichever shard finds every scene present,
    or later by :func:`index_dataset`. The result equals an unsharded run with the same seed.
    """
    prepare_output(opts.out, cfg, opts.scenes)
    announce()
    todo = pending_indices(opts.out, opts.scenes, opts.shard)
    summary = Summary()
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
    if pending_indices(opts.out, opts.scenes):  # other shards still have work
        return dataclasses.replace(summary, seconds=seconds, scenes=opts.scenes)
    final = finalize(opts.out, cfg, opts.scenes, run_info)
    final.rendered_now, final.seconds, final.peak_rss_mb = (
        summary.rendered_now,
        seconds,
        summary.peak_rss_mb,
    )
    final.failures = summary.failures
    final.bytes = folder_size(opts.out)
    return final


def index_dataset(out: Path, run_info: dict | None = None) -> Summary:
    """Write metadata, manifest and a complete dataset.json for a folder filled by shards;
    ``run_info`` replaces dataset.json's ``run`` block when given."""
    info_path = out / DATASET_JSON
    if not info_path.is_file():
        raise ConfigError(f"DATASET: '{out}' has no {DATASET_JSON} (not a stillbox-gen dataset)")
    info = json.loads(info_path.read_text())
    cfg = config.from_dict(info["config"])
    if cfg.fingerprint() != info["fingerprint"]:
        raise ConfigError(f"DATASET: '{info_path}' config does not match its fingerprint")
    missing = pending_indices(out, info["scenes"])
    if missing:
        shown = ", ".join(map(str, missing[:10])) + (" ..." if len(missing) > 10 else "")
        raise ConfigError(
            f"DATASET: '{out}' lacks {len(missing)} of {info['scenes']} scenes ({shown}); "
            "run the missing shards first"
        )
    run_info = run_info or info.get("run", {"indexed_from": "shards"})
    return finalize(out, cfg, info["scenes"], run_info)
