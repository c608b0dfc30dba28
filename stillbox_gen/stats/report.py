"""The report of ``stillbox-gen stats``: a plain-text table beside StillBox's figures, and
stats.png."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..formats import atomic_write
from .common import PARTS
from .histograms import BAND_LABELS


def _fmt(v: float | None, kind: str) -> str:
    if v is None:
        return "-"
    if kind == "%":
        return f"{100 * v:.1f} %"
    if kind == "m":
        return f"{v:.1f} m"
    if kind == "px":
        return f"{v:.2f} px"
    return f"{v:.2f}"


Row = tuple[str, str, str]  # label, our figure, StillBox's ('-' when it has none)


def _depth_rows(stats: dict) -> list[Row]:
    ref, d, wo = stats["stillbox_reference"], stats["depth"], stats["walls_objects"]
    rows = [
        ("median pixel depth", _fmt(d["median_m"], "m"), _fmt(ref["median_depth_m"], "m")),
        ("pixels below 25 m", _fmt(d["share_below_25m"], "%"), _fmt(ref["share_below_25m"], "%")),
        ("pixels in 5-25 m", _fmt(d["share_5_25m"], "%"), _fmt(ref["share_5_25m"], "%")),
    ]
    for k in BAND_LABELS:
        rows.append(
            (f"  depth {k} m", _fmt(d["band_shares"][k], "%"), _fmt(ref["band_shares"][k], "%"))
        )
    return rows + [
        ("wall pixels", _fmt(wo["wall_share"], "%"), "-"),
        ("object pixels", _fmt(wo["object_share"], "%"), "-"),
        ("median wall depth", _fmt(wo["median_wall_depth_m"], "m"), "-"),
        ("median object depth", _fmt(wo["median_object_depth_m"], "m"), "-"),
    ]


def _motion_rows(stats: dict) -> list[Row]:
    fl, rs, s = stats["flow"], stats["residual"], stats["shift"]
    rows = []
    for p in PARTS:
        f = fl[p]
        spread = f"{_fmt(f['median_px'], 'px')} ({_fmt(f['p10_px'], '')}-{_fmt(f['p90_px'], '')})"
        rows.append((f"flow at shift {s}, {p}: median (p10-p90)", spread, "-"))
    for key, label in (("unwarped", "no warp"), ("warped", "after true-flow warp")):
        for p in PARTS:
            rows.append((f"residual {label}, {p} (grey levels)", _fmt(rs[key][p], ""), "-"))
    for p in PARTS:
        rows.append((f"  pixels kept for the warp, {p}", _fmt(rs["valid_share"][p], "%"), "-"))
    return rows + _flicker_rows(stats.get("flicker"))


def _flicker_rows(fk: dict | None) -> list[Row]:
    if not fk:
        return []
    labels = (("same_pose", "same-pose flicker"), ("other_seed", "other seed"))
    return [
        (f"{label}, {p} (grey levels)", _fmt(fk[key][p], ""), "-")
        for key, label in labels
        for p in PARTS
    ]


def _aligned(rows: list[Row]) -> list[str]:
    """Rows as text columns: the label left-aligned, the figures right-aligned."""
    widths = [max(len(r[c]) for r in rows) for c in range(3)]
    return [
        "  ".join(
            v.ljust(wd) if i == 0 else v.rjust(wd)
            for i, (v, wd) in enumerate(zip(r, widths, strict=True))
        )
        for r in rows
    ]


def table(stats: dict) -> str:
    """The report as a plain-text table: our figure beside StillBox's ('-' when it has none)."""
    (w, h), s = stats["resolution"], stats["shift"]
    title = (
        f"{stats['dataset']}: {stats['n_scenes']} scenes, {stats['frames']} frames, "
        f"{stats['pairs']} pairs (i, i+{s}), {w}x{h} px"
    )
    head: Row = ("", "ours", "StillBox")
    return "\n".join([title, *_aligned([head, *_depth_rows(stats), *_motion_rows(stats)])])


def _plot_bands(ax, stats: dict) -> None:
    """Pixel-depth bands, ours beside StillBox's."""
    d, x = stats["depth"], np.arange(len(BAND_LABELS))
    ours = [100 * d["band_shares"][k] for k in BAND_LABELS]
    ref = [100 * stats["stillbox_reference"]["band_shares"][k] for k in BAND_LABELS]
    ax.bar(x - 0.2, ours, 0.4, label=f"ours ({stats['n_scenes']} scenes)")
    ax.bar(x + 0.2, ref, 0.4, label="StillBox (published samples)")
    ax.set_xticks(x, BAND_LABELS, rotation=45)
    ax.set_xlabel("pixel depth band (m)")
    ax.set_ylabel("share of pixels (%)")
    ax.set_title("pixel depth")
    ax.legend(fontsize=8)


def _plot_depth(ax, stats: dict) -> None:
    """The depth histogram up to --max-depth, walls and objects stacked."""
    d = stats["depth"]
    edges = np.asarray(d["histogram"]["edges_m"])
    bottom = np.zeros(len(edges) - 1)
    for p in PARTS:
        v = 100 * np.asarray(d["histogram"][p]["shares"])
        ax.bar(edges[:-1], v, np.diff(edges), bottom=bottom, align="edge", label=p)
        bottom += v
    ax.set_xlabel(f"pixel depth (m), up to --max-depth {stats['max_depth_m']:g}")
    ax.set_ylabel("share of pixels (%)")
    ax.set_title("pixel depth, walls and objects")
    ax.legend(fontsize=8)


def _plot_flow(ax, stats: dict) -> None:
    """The flow-magnitude histogram of walls and of objects, log x-axis."""
    fl = stats["flow"]
    edges = np.asarray(fl["histogram"]["edges_px"])
    for p in PARTS:
        v = 100 * np.asarray(fl["histogram"][p]["shares"])
        ax.stairs(v, edges, label=f"{p} (median {_fmt(fl[p]['median_px'], 'px')})")
    ax.set_xscale("log")
    ax.set_xlabel(f"true flow magnitude (px), frames i to i+{stats['shift']}")
    ax.set_ylabel("share of the part's pixels (%)")
    ax.set_title("flow magnitude")
    ax.legend(fontsize=8)


def plot(stats: dict, path: Path) -> None:
    """stats.png: depth bands ours vs StillBox, depth histogram to --max-depth (walls, objects),
    flow-magnitude histogram (walls, objects) on a log x-axis. Written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(16, 4.2))
    for draw, ax in zip((_plot_bands, _plot_depth, _plot_flow), axes, strict=True):
        draw(ax, stats)
    fig.tight_layout()
    try:
        atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=100))
    finally:
        plt.close(fig)
