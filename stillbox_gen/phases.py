"""Where a generation run's time goes: the phases timed in the Blender workers
(stillbox_gen.blender.render) and in the driver (stillbox_gen.generate, stillbox_gen.writer),
named once here (:data:`PHASES`), accumulated per run (:class:`RunProfile`) and printed by
``stillbox-gen bench --profile`` (:func:`profile_table`).

Two clocks, both in seconds: *wall* is ``time.perf_counter``; *CPU* is ``time.process_time``,
the CPU time of the whole process (all its threads: a worker's Cycles render threads included).
Worker phases are summed over the worker processes, which run in parallel; driver phases are
one process's timeline. Nothing here imports bpy or changes what is rendered or written.

Every run measures its phases (a few clock reads per frame); the split of Cycles' own time into
sync, sampling and result (``detail``) needs a handler on Blender's render status messages and
is on only when asked for (:class:`stillbox_gen.worker_setup.WorkerSetup` ``profile``).
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

WORKER = "worker"
DRIVER = "driver"


@dataclass(frozen=True)
class Phase:
    """One timed phase: its key in the statistics, the process it runs in, what it covers."""

    name: str
    process: str  # WORKER or DRIVER
    label: str  # what is timed (the profile table's first column)
    derived: bool = False  # not timed itself: the remainder of a total (see profile_table)
    detail: bool = False  # a part of "cycles", timed only with WorkerSetup.profile


PHASES: tuple[Phase, ...] = (
    # ------------------------------------------------------------ in each worker process
    Phase("startup", WORKER, "process start, imports (bpy), Cycles set-up; once per process"),
    Phase("build", WORKER, "scene build: clear the last one, meshes, materials, photos"),
    Phase("render_setup", WORKER, "animation render start, up to frame 0 (depsgraph)"),
    Phase("frame_step", WORKER, "frame change, pose handler, between frames"),
    Phase("cycles", WORKER, "Cycles: sync + BVH, sampling, result + temporary EXR"),
    Phase("cycles_sync", WORKER, "of which sync and scene update (BVH, shaders)", detail=True),
    Phase("cycles_sampling", WORKER, "of which sampling (and denoising if on)", detail=True),
    Phase("cycles_result", WORKER, "of which result to Blender, temporary EXR", detail=True),
    Phase("render_finish", WORKER, "animation render end, after the last frame"),
    Phase("exr_read", WORKER, "temporary EXR read back and deleted"),
    Phase("to_srgb", WORKER, "linear to 8-bit sRGB"),
    Phase("rgb_write", WORKER, "PNG/JPG encoding and write (legacy JPG too)"),
    Phase("depth_write", WORKER, "depth EXR encoding and write (legacy .npy too)"),
    Phase("worker_python", WORKER, "rest of the scene calls (Python, untimed)", derived=True),
    Phase(
        "worker_outside",
        WORKER,
        "outside scene calls: idle, results sent, before start, after end",
        derived=True,
    ),
    # ------------------------------------------------------------ in the driver process
    Phase("prepare", DRIVER, "output folder checked, dataset.json marked incomplete"),
    Phase("pool_start", DRIVER, "worker pool created"),
    Phase("sample", DRIVER, "scene sampling (layouts, poses), temporary folder"),
    Phase("submit", DRIVER, "scene sent to a worker (spawns workers when needed)"),
    Phase("wait", DRIVER, "waiting for a worker to finish a scene"),
    Phase("flow", DRIVER, "optical flow and masks from depth and poses (--flow)"),
    Phase("hash", DRIVER, "SHA-256 of the scene's files"),
    Phase("commit", DRIVER, "record built, files moved, record written"),
    Phase("pool_stop", DRIVER, "worker pool shut down"),
    Phase("finalize", DRIVER, "index: metadata.json, manifest, dataset.json"),
    Phase("size", DRIVER, "dataset size summed"),
    Phase("driver_python", DRIVER, "rest of the run (Python, untimed)", derived=True),
)
BY_NAME: dict[str, Phase] = {p.name: p for p in PHASES}
#: The parts of "cycles" timed with WorkerSetup.profile, in order; they sum to "cycles".
CYCLES_PARTS: tuple[str, ...] = tuple(p.name for p in PHASES if p.detail)


def clocks() -> tuple[float, float]:
    """(wall, CPU) now, seconds: time.perf_counter and time.process_time."""
    return time.perf_counter(), time.process_time()


@dataclass
class PhaseTimes:
    """Wall and CPU seconds per phase name (keys of :data:`PHASES`), summed."""

    wall: dict[str, float] = field(default_factory=dict)
    cpu: dict[str, float] = field(default_factory=dict)

    def add(self, name: str, wall: float, cpu: float) -> None:
        """Add ``wall`` and ``cpu`` seconds to phase ``name`` (a KeyError if not in PHASES)."""
        BY_NAME[name]  # noqa: B018  (a misspelt name fails here, not as a missing table row)
        self.wall[name] = self.wall.get(name, 0.0) + wall
        self.cpu[name] = self.cpu.get(name, 0.0) + cpu

    @contextlib.contextmanager
    def measure(self, name: str) -> Iterator[None]:
        """Time the block as phase ``name`` (also when it raises)."""
        w0, c0 = clocks()
        try:
            yield
        finally:
            w1, c1 = clocks()
            self.add(name, w1 - w0, c1 - c0)

    def to_dict(self) -> dict[str, list[float]]:
        """{name: [wall s, CPU s]}: picklable and JSON-friendly (a worker's statistics)."""
        return {k: [self.wall[k], self.cpu[k]] for k in self.wall}

    def add_dict(self, phases: dict[str, list[float]]) -> None:
        """Add a :meth:`to_dict` of another PhaseTimes."""
        for name, (wall, cpu) in phases.items():
            self.add(name, wall, cpu)


def measure(times: PhaseTimes | None, name: str) -> contextlib.AbstractContextManager:
    """``times.measure(name)``, or nothing when ``times`` is None."""
    return contextlib.nullcontext() if times is None else times.measure(name)


_IMPORTED = time.perf_counter()  # process_age's fallback


def process_age() -> float:
    """Wall seconds since this process started: on Linux /proc/self/stat's start time against
    CLOCK_BOOTTIME (10 ms resolution); elsewhere since this module was imported (in a worker:
    when the pool's initializer was unpickled, before bpy's import)."""
    try:
        stat = Path("/proc/self/stat").read_text()
        start_ticks = int(stat.rsplit(")", 1)[1].split()[19])  # field 22, starttime
        return time.clock_gettime(time.CLOCK_BOOTTIME) - start_ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, AttributeError):
        return time.perf_counter() - _IMPORTED


@dataclass
class RunProfile:
    """A run's phases: the driver's, timed in the driver (:meth:`PhaseTimes.measure`), and the
    workers', summed from each scene's statistics (:meth:`add_scene`)."""

    times: PhaseTimes = field(default_factory=PhaseTimes)
    scenes: int = 0  # scenes whose statistics were added
    scene_wall: float = 0.0  # wall s of the workers' scene calls, summed
    scene_cpu: float = 0.0  # CPU s of the workers' scene calls, summed
    worker_cpu: dict[int, float] = field(default_factory=dict)  # pid: its CPU s so far

    def measure(self, name: str) -> contextlib.AbstractContextManager:
        """Time a driver block as phase ``name``."""
        return self.times.measure(name)

    def add_scene(self, stats: dict) -> None:
        """Add a worker's statistics of one scene (stillbox_gen.blender.render.render_scene):
        ``phases`` ({name: [wall, CPU]}), ``seconds``, ``cpu_seconds``, and the worker's
        ``pid`` with its ``process_cpu_seconds``. Statistics without ``phases`` (another
        renderer's) are counted in no phase."""
        if "phases" not in stats:
            return
        self.scenes += 1
        self.times.add_dict(stats["phases"])
        self.scene_wall += stats["seconds"]
        self.scene_cpu += stats["cpu_seconds"]
        pid = stats["pid"]
        self.worker_cpu[pid] = max(self.worker_cpu.get(pid, 0.0), stats["process_cpu_seconds"])


@dataclass
class ProfileRow:
    """A line of the profile table: wall and CPU milliseconds per frame and their shares."""

    phase: Phase
    wall_ms: float  # wall ms per frame (summed over workers for a worker phase)
    wall_share: float  # of the workers' wall (workers x run wall) or of the driver's (run wall)
    cpu_ms: float  # CPU ms per frame
    cpu_share: float  # of the CPU all processes of the run used


def profile_rows(
    profile: RunProfile, frames: int, wall: float, workers: int, driver_cpu: float
) -> list[ProfileRow]:
    """The rows of :func:`profile_table` for a run of ``frames`` frames rendered in ``wall``
    seconds by ``workers`` worker processes, its driver using ``driver_cpu`` CPU seconds.

    Derived phases: ``worker_python`` is the workers' scene calls minus their timed phases;
    ``worker_outside`` is the workers' time outside scene calls (wall: ``workers * wall``
    minus start-up and scene calls; CPU: the workers' process CPU minus both);
    ``driver_python`` is ``wall`` (``driver_cpu``) minus the driver's timed phases.
    """
    t, n = profile.times, max(frames, 1)
    wall_of = dict(t.wall)
    cpu_of = dict(t.cpu)
    worker_timed = [p.name for p in PHASES if p.process == WORKER and not (p.derived or p.detail)]
    in_scenes = [k for k in worker_timed if k != "startup"]
    wall_of["worker_python"] = profile.scene_wall - sum(wall_of.get(k, 0.0) for k in in_scenes)
    cpu_of["worker_python"] = profile.scene_cpu - sum(cpu_of.get(k, 0.0) for k in in_scenes)
    start_wall, start_cpu = wall_of.get("startup", 0.0), cpu_of.get("startup", 0.0)
    wall_of["worker_outside"] = workers * wall - start_wall - profile.scene_wall
    workers_cpu = sum(profile.worker_cpu.values())
    cpu_of["worker_outside"] = workers_cpu - start_cpu - profile.scene_cpu
    driver_timed = [p.name for p in PHASES if p.process == DRIVER and not p.derived]
    wall_of["driver_python"] = wall - sum(wall_of.get(k, 0.0) for k in driver_timed)
    cpu_of["driver_python"] = driver_cpu - sum(cpu_of.get(k, 0.0) for k in driver_timed)
    total_cpu = workers_cpu + driver_cpu
    rows = []
    for p in PHASES:
        if p.detail and p.name not in t.wall:
            continue
        slots = workers * wall if p.process == WORKER else wall
        w, c = wall_of.get(p.name, 0.0), cpu_of.get(p.name, 0.0)
        rows.append(
            ProfileRow(
                phase=p,
                wall_ms=1000 * w / n,
                wall_share=w / slots if slots > 0 else float("nan"),
                cpu_ms=1000 * c / n,
                cpu_share=c / total_cpu if total_cpu > 0 else float("nan"),
            )
        )
    return rows


def profile_table(
    profile: RunProfile,
    frames: int,
    wall: float,
    workers: int,
    driver_cpu: float,
    cores: int | None = None,
) -> str:
    """A markdown table of where a run's time went, per rendered frame, and two lines of totals.

    ``frames`` frames rendered in ``wall`` seconds (the whole ``generate`` call) by ``workers``
    worker processes on ``cores`` CPUs (os.sched_getaffinity when None); ``driver_cpu``: the
    driver's CPU seconds during the run. Wall shares of worker rows are of ``workers * wall``
    (each worker's timeline, summed); those of driver rows of ``wall``; each group adds up to
    100 % with its derived rows. CPU shares are of the CPU the run used in all its processes,
    and all rows add up to 100 %. "of which" rows (the parts of ``cycles``) are not added.
    """
    if cores is None:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    cores = cores or 1
    rows = profile_rows(profile, frames, wall, workers, driver_cpu)
    n = max(frames, 1)
    lines = [
        "| phase | process | what | wall ms/frame | wall share | CPU ms/frame | CPU share |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        p = r.phase
        lines.append(
            f"| {p.name} | {p.process} | {p.label} | {r.wall_ms:.2f} | {100 * r.wall_share:.1f} % "
            f"| {r.cpu_ms:.2f} | {100 * r.cpu_share:.1f} % |"
        )
    workers_cpu = sum(profile.worker_cpu.values())
    used = workers_cpu + driver_cpu
    available = cores * wall
    per_frame = 1000 * wall / n
    lines.append(
        f"wall: {frames} frames in {wall:.2f} s ({frames / wall if wall > 0 else 0.0:.1f} "
        f"frames/s), {per_frame:.2f} ms/frame; worker rows share {workers} workers x {wall:.2f} s "
        f"= {workers * per_frame:.2f} ms/frame, driver rows {per_frame:.2f} ms/frame"
    )
    lines.append(
        f"CPU: {1000 * used / n:.2f} ms/frame used (workers {1000 * workers_cpu / n:.2f}, "
        f"driver {1000 * driver_cpu / n:.2f}) of {1000 * available / n:.2f} on {cores} CPUs "
        f"({100 * used / available if available > 0 else 0.0:.1f} % of the CPUs' time)"
    )
    return "\n".join(lines)
