"""``stillbox-gen bench``: whole-process generation speed and image quality, side by side.

For each resolution and render configuration it times a complete ``generate`` run (worker start-up,
rendering, writing, indexing) into a temporary folder, then re-renders a few of those frames with
``REFERENCE_SAMPLES`` samples (same shading, no denoiser) and reports the PSNR of the generated
8-bit sRGB frames against them. Speed ratios are taken against the ``plain`` configuration, which
is measured in the same invocation. A fixed CPU workload (:func:`reference_loop`) is timed before
and after the whole benchmark, so that tables measured in different machine states (a VM's
drifting speed, other jobs) can be compared. With ``profile``, each timed run is followed by the
table of where its time went (stillbox_gen.phases.profile_table), Cycles' time split into sync,
sampling and result.
"""

from __future__ import annotations

import csv
import io
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import config, formats, generate, layout, phases
from .dataset import Dataset
from .errors import ConfigError
from .scene import sample_scene
from .worker_setup import worker_setup
from .workers import process_pool, render_scene

REFERENCE_SAMPLES = 256
# The baseline: path-traced Principled BSDF, 8 samples, 1 bounce, no denoiser, and each
# frame rendered as an independent still (no persistent scene data).
PLAIN = {"shading": "path", "samples": 8, "denoise": False, "max_bounces": 1, "persistent": False}
#: The reference loop (:func:`reference_loop`): pure-Python steps of a linear congruential
#: generator, then sorts of numpy integers; timed as the best of REFERENCE_REPEATS runs.
REFERENCE_PYTHON_STEPS = 3_000_000
REFERENCE_ARRAY_SIZE = 1 << 20
REFERENCE_SORTS = 4
REFERENCE_REPEATS = 3
#: The generator's multiplier, increment and modulus mask (the ANSI C rand's, modulus 2^31).
LCG = (1103515245, 12345, 0x7FFFFFFF)


def configurations(names: list[str]) -> dict[str, dict]:
    """Render-section overrides by name: the quality levels plus ``plain``."""
    table = {**{q: dict(v) for q, v in config.QUALITY.items()}, "plain": dict(PLAIN)}
    unknown = [n for n in names if n not in table]
    if unknown:
        raise ConfigError(
            f"--configs: unknown {', '.join(unknown)} (choose from {', '.join(table)})"
        )
    return {n: table[n] for n in names}


@dataclass
class BenchRow:
    res: int
    config: str
    device: str  # Cycles device (config.CPU_DEVICE or a GPU backend)
    shading: str
    samples: int
    denoise: bool
    scenes: int
    seconds: float
    fps: float
    psnr_db: float
    speedup: float = float("nan")  # frames/s relative to "plain" at the same resolution
    reference_before_s: float = float("nan")  # reference_seconds() before the whole benchmark
    reference_after_s: float = float("nan")  # and after it (the same in every row)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB of two uint8 images (peak 255); inf when identical."""
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float("inf") if mse == 0 else float(10 * np.log10(255.0**2 / mse))


def reference_loop(
    steps: int = REFERENCE_PYTHON_STEPS,
    size: int = REFERENCE_ARRAY_SIZE,
    sorts: int = REFERENCE_SORTS,
) -> int:
    """A fixed CPU workload, single-threaded, exact integer arithmetic (the same result on every
    machine): ``steps`` steps of the :data:`LCG` x -> (a·x + c) mod 2^31 from x = 1 in pure
    Python, summing x >> 16 (the interpreter's speed); then ``sorts`` times, every element of
    ``size`` int64 values (numpy's PCG64 from seed 0, in [0, 2^31)) through one LCG step and
    the array sorted (numpy's vectorised arithmetic and sort). Returns the Python sum plus the
    sum of the final array (a checksum)."""
    a, c, mask = LCG
    x, total = 1, 0
    for _ in range(steps):
        x = (a * x + c) & mask
        total += x >> 16
    values = np.random.default_rng(0).integers(0, mask + 1, size, dtype=np.int64)
    for _ in range(sorts):
        values = np.sort((values * a + c) & mask)
    return total + int(values.sum())


def reference_seconds(repeats: int = REFERENCE_REPEATS) -> float:
    """Wall time of :func:`reference_loop`, seconds, the best of ``repeats`` runs
    (time.perf_counter)."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        reference_loop()
        times.append(time.perf_counter() - t0)
    return min(times)


def reference_line(rows: list[BenchRow]) -> str:
    """The line printed below the table: the reference loop's times of ``rows``."""
    r = rows[0]
    return (
        f"reference loop: {r.reference_before_s:.2f} s before, {r.reference_after_s:.2f} s "
        f"after (best of {REFERENCE_REPEATS}; stillbox_gen.bench.reference_loop)"
    )


def reference_psnr(
    cfg: config.DatasetConfig,
    root: Path,
    scenes: int,
    frames: list[int],
    workers: int,
    device: str = config.CPU_DEVICE,
    threads: int = 0,
) -> float:
    """Mean PSNR of the dataset's frames against REFERENCE_SAMPLES-sample renders of them
    (on the same Cycles ``device``, ``threads`` Cycles threads per worker, 0 = all cores)."""
    reference = config.replace(cfg, render={"samples": REFERENCE_SAMPLES, "denoise": False})
    values = []
    ds = Dataset(root)
    with (
        tempfile.TemporaryDirectory() as tmp,
        process_pool(workers, worker_setup(reference, threads, device)) as pool,
    ):
        jobs = []
        for k in range(scenes):
            spec = sample_scene(cfg, k).to_dict()
            spec["camera"]["cam2world"] = [spec["camera"]["cam2world"][f] for f in frames]
            out = Path(tmp) / str(k)
            jobs.append((k, out, pool.submit(render_scene, spec, str(out), "png", False)))
        for k, out, job in jobs:
            job.result()
            scene, local = ds.scene(k), layout.local_index(k)
            for i, f in enumerate(frames):
                ref = formats.read_rgb(out / layout.rgb_name(local, i))
                values.append(psnr(scene.load_rgb(f), ref))
    return float(np.mean(values))


def run_bench(
    resolutions: list[tuple[int, int]],
    names: list[str],
    workers: int,
    psnr_scenes: int,
    workdir: Path,
    log=print,
    device: str = config.CPU_DEVICE,
    profile: bool = False,
    threads: int = 0,
) -> list[BenchRow]:
    """Measure every (resolution, configuration) on the Cycles ``device`` (workers.choose_device)
    with ``threads`` Cycles threads per worker (0 = all cores); ``resolutions`` holds (pixels,
    scenes) pairs. Every row also holds the reference loop's time before and after the whole
    measurement (:func:`reference_seconds`). With ``profile``, ``log`` also gets each timed
    run's profile table (phases.profile_table)."""
    before = reference_seconds()
    rows = []
    for res, scenes in resolutions:
        for name, render in configurations(names).items():
            cfg = config.load_preset("stillbox")
            cfg = config.replace(cfg, camera={"width": res, "height": res}, render=render)
            out = workdir / f"{res}-{name}"
            formats.remove_tree(out)
            opts = generate.RunOptions(
                out=out,
                scenes=scenes,
                workers=workers,
                progress=False,
                threads=threads,
                device=device,
                profile=profile,
            )
            t0, c0 = phases.clocks()
            summary = generate.generate(cfg, opts)
            t1, c1 = phases.clocks()
            seconds = t1 - t0
            frames = [0, cfg.camera.frames - 1]
            quality = reference_psnr(
                cfg, out, min(psnr_scenes, scenes), frames, workers, device, threads
            )
            r = cfg.render
            row = BenchRow(
                res=res,
                config=name,
                device=device,
                shading=r.shading,
                samples=r.samples,
                denoise=r.denoise,
                scenes=scenes,
                seconds=seconds,
                fps=scenes * cfg.camera.frames / seconds,
                psnr_db=quality,
            )
            rows.append(row)
            log(f"{res:>4} px  {name:<8} {row.fps:6.1f} frames/s  PSNR {quality:5.1f} dB")
            if profile:
                frames_rendered = summary.rendered_now * cfg.camera.frames
                table = phases.profile_table(
                    summary.profile, frames_rendered, seconds, workers, c1 - c0
                )
                log(f"profile of {res} px {name} (whole generate call, {workers} workers):")
                log(table)
            formats.remove_tree(out)
        base = next((r.fps for r in rows if r.res == res and r.config == "plain"), None)
        for r in rows:
            if r.res == res and base:
                r.speedup = r.fps / base
    after = reference_seconds()
    for r in rows:
        r.reference_before_s, r.reference_after_s = round(before, 3), round(after, 3)
    return rows


def markdown_table(rows: list[BenchRow]) -> str:
    lines = [
        "| px | config | device | shading | samples | denoiser | frames/s | vs plain | PSNR (dB) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r.res} | {r.config} | {r.device} | {r.shading} | {r.samples} "
            f"| {'OIDN' if r.denoise else '-'} "
            f"| {r.fps:.1f} | {'-' if r.speedup != r.speedup else f'{r.speedup:.2f}x'} "
            f"| {r.psnr_db:.1f} |"
        )
    return "\n".join(lines)


def write_csv(rows: list[BenchRow], path: Path) -> None:
    """The rows as CSV (one column per BenchRow field), written atomically."""
    fields = list(BenchRow.__dataclass_fields__)
    text = io.StringIO(newline="")
    w = csv.DictWriter(text, fieldnames=fields)
    w.writeheader()
    for r in rows:
        w.writerow({k: getattr(r, k) for k in fields})
    formats.atomic_write_text(path, text.getvalue())
