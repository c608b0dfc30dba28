"""``stillbox-bench fly``: fly the episodes of a seed with one depth source into a run folder.

Episode k of the run is episodes.make_episode(seed, k) at the run's frame size: the same for
every depth source. Each finished episode is written at once (runfolder.write_episode), so a run
cut short continues where it stopped (``--resume``: the episodes already flown are read back,
not flown again); episodes.csv, the figures and summary.json come at the end, summary.json
last. Every file goes through benchmark.core.runfolder (atomic writes).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..core import runfolder
from .episodes import Episode, flight_scene_config, make_episode
from .plots import episode_figure
from .render import open_renderer
from .simulate import EpisodeResult, FlightConfig, fly
from .sources import Scored
from .summary import ERROR_KEYS, OUTCOMES, episode_row, source_summary

RESULT_FIELDS = [f.name for f in dataclasses.fields(EpisodeResult)]


def record_of(index: int, e: Episode, r: EpisodeResult, errors: dict) -> dict:
    """One finished episode as plain JSON: its result (positions (steps + 1, 3) m as lists),
    start and goal (m) and the depth source's errors."""
    rec = {name: getattr(r, name) for name in RESULT_FIELDS}
    rec["positions"] = np.asarray(r.positions).tolist()
    return {"episode": index, "start": e.start.tolist(), "goal": e.goal.tolist(), **rec, **errors}


def result_of(record: dict) -> EpisodeResult:
    """The EpisodeResult of a record written by :func:`record_of`."""
    values = {name: record[name] for name in RESULT_FIELDS}
    values["positions"] = np.asarray(values["positions"], float)
    return EpisodeResult(**values)


def row_of(record: dict, dt: float) -> dict:
    """episodes.csv's row of a record: summary.episode_row, the flight time (s; ``dt`` seconds
    per control step), start, goal and the depth errors."""
    row = episode_row(record["episode"], result_of(record))
    row["flight_time_s"] = record["steps"] * dt
    xyz = ("x", "y", "z")
    row |= {f"start_{a}_m": v for a, v in zip(xyz, record["start"], strict=True)}
    row |= {f"goal_{a}_m": v for a, v in zip(xyz, record["goal"], strict=True)}
    return row | {k: record.get(k) for k in ("depth_frames", *ERROR_KEYS)}


def fly_run(
    out: Path,
    config: dict,
    source: Scored,
    flight: FlightConfig,
    render_device: str = "cpu",
    progress: bool = True,
    on_episode: Callable[[int, dict], None] | None = None,
) -> dict:
    """Fly episodes 0 .. config["episodes"] - 1 of config["seed"] at config["res"] (W, H) with
    config["renderer"] into ``out`` (config.json already there), skipping those already written;
    returns summary.json's content. ``on_episode(index, record)`` after each flown episode."""
    width, height = config["res"]
    scene_cfg = flight_scene_config(config["seed"], width, height)
    done = runfolder.read_episodes(out)
    records: dict[int, dict] = {k: v for k, v in done.items() if k < config["episodes"]}
    todo = [k for k in range(config["episodes"]) if k not in records]
    bar = tqdm(total=config["episodes"], initial=len(records), unit="episode", disable=not progress)
    start = time.perf_counter()
    episodes = {}
    with bar, open_renderer(config["renderer"], scene_cfg, render_device) as renderer:
        for k in todo:
            e = episodes[k] = make_episode(config["seed"], k, scene_cfg=scene_cfg)
            source.reset()
            r = fly(e.world, e.start, e.goal, e.K, renderer(e), source, flight)
            records[k] = record_of(k, e, r, source.errors())
            runfolder.write_episode(out, k, records[k])
            if on_episode is not None:
                on_episode(k, records[k])
            bar.update()
            counts = [sum(v["outcome"] == o for v in records.values()) for o in OUTCOMES]
            bar.set_postfix(dict(zip(OUTCOMES, counts, strict=True)))
    seconds = time.perf_counter() - start
    ordered = [records[k] for k in sorted(records)]
    for rec in ordered:
        k = rec["episode"]
        e = episodes.get(k) or make_episode(config["seed"], k, scene_cfg=scene_cfg)
        title = f"episode {k}: {rec['outcome']}, least clearance {rec['min_clearance']:.2f} m"
        fig = episode_figure(
            e.world, e.start, e.goal, np.asarray(rec["positions"]), rec["outcome"],
            f"{config['depth']}: {title}", flight.drone_radius, flight.reach_radius,
        )  # fmt: skip
        runfolder.save_figure(fig, runfolder.episode_plot_path(out, k))
    summary = {
        "kind": runfolder.FLIGHT_KIND,
        "depth": config["depth"],
        **source_summary([result_of(r) for r in ordered], ordered),
        "seconds_this_session": seconds,
        "episodes_flown_this_session": len(todo),
        "config": config,
    }
    runfolder.write_flight_report(out, summary, [row_of(r, flight.dynamics.dt) for r in ordered])
    return summary


def describe(summary: dict, out: Path) -> str:
    """The one-paragraph summary printed at the end."""
    s = summary
    low, high = s["success_rate_ci95"]
    mae = "-" if s["depth_mae_m"] is None else f"{s['depth_mae_m']:.3f} m"
    mre = "-" if s["depth_mre"] is None else f"{s['depth_mre']:.3f}"
    ratio = s["mean_path_ratio_reached"]
    ms = {k: 1000 * (s[f"{k}_s_per_step"] or 0.0) for k in ("render", "depth", "control")}
    return (
        f"fly {s['depth']}: {s['reached']}/{s['episodes']} episodes reached the goal "
        f"(success {s['success_rate']:.0%}, 95 % CI {low:.0%}-{high:.0%}), {s['collided']} "
        f"collided, {s['timeout']} timed out; mean least clearance "
        f"{s['mean_min_clearance_m']:.2f} m, path ratio "
        f"{'-' if ratio is None else f'{ratio:.3f}'}; depth error MAE {mae}, MRE {mre} over "
        f"{s['depth_frames']} frames; per step {ms['render']:.1f} ms render, {ms['depth']:.1f} "
        f"ms depth, {ms['control']:.1f} ms control; {s['episodes_flown_this_session']} episodes "
        f"flown in {s['seconds_this_session']:.0f} s; results in {out}"
    )
