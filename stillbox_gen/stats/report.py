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


def table(stats: dict) -> str:
    """The report as a plain-text table: our figure beside StillBox's ('-' when it has none)."""
    ref = stats["stillbox_reference"]
    d, wo, fl, rs = stats["depth"], stats["walls_objects"], stats["flow"], stats["residual"]
    rows: list[tuple[str, str, str]] = [
        ("median pixel depth", _fmt(d["median_m"], "m"), _fmt(ref["median_depth_m"], "m")),
        ("pixels below 25 m", _fmt(d["share_below_25m"], "%"), _fmt(ref["share_below_25m"], "%")),
        ("pixels in 5-25 m", _fmt(d["share_5_25m"], "%"), _fmt(ref["share_5_25m"], "%")),
    ]
    for k in BAND_LABELS:
        rows.append(
            (f"  depth {k} m", _fmt(d["band_shares"][k], "%"), _fmt(ref["band_shares"][k], "%"))
        )
    rows += [
        ("wall pixels", _fmt(wo["wall_share"], "%"), "-"),
        ("object pixels", _fmt(wo["object_share"], "%"), "-"),
        ("median wall depth", _fmt(wo["median_wall_depth_m"], "m"), "-"),
        ("median object depth", _fmt(wo["median_object_depth_m"], "m"), "-"),
    ]
    s = stats["shift"]
    for p in PARTS:
        f = fl[p]
        spread = f"{_fmt(f['median_px'], 'px')} ({_fmt(f['p10_px'], '')}-{_fmt(f['p90_px'], '')})"
        rows.append((f"flow at shift {s}, {p}: median (p10-p90)", spread, "-"))
    for key, label in (("unwarped", "no warp"), ("warped", "after true-flow warp")):
        for p in PARTS:
            rows.append((f"residual {label}, {p} (grey levels)", _fmt(rs[key][p], ""), "-"))
    for p in PARTS:
        rows.append((f"  pixels kept for the warp, {p}", _fmt(rs["valid_share"][p], "%"), "-"))
    fk = stats.get("flicker")
    if fk:
        for key, label in (("same_pose", "same-pose flicker"), ("other_seed", "other seed")):
            for p in PARTS:
                rows.append((f"{label}, {p} (grey levels)", _fmt(fk[key][p], ""), "-"))
    head = ("", "ours", "StillBox")
    widths = [max(len(r[c]) for r in [head, *rows]) for c in range(3)]
    lines = [
        f"{stats['dataset']}: {stats['n_scenes']} scenes, {stats['frames']} frames, "
        f"{stats['pairs']} pairs (i, i+{s}), {stats['resolution'][0]}x{stats['resolution'][1]} px",
        "  ".join(
            h.ljust(wd) if i == 0 else h.rjust(wd)
            for i, (h, wd) in enumerate(zip(head, widths, strict=True))
        ),
    ]
    for r in rows:
        lines.append(
            "  ".join(
                v.ljust(wd) if i == 0 else v.rjust(wd)
                for i, (v, wd) in enumerate(zip(r, widths, strict=True))
            )
        )
    return "\n".join(lines)


def plot(stats: dict, path: Path) -> None:
    """stats.png: depth bands ours vs StillBox, depth histogram to --max-depth (walls, objects),
    flow-magnitude histogram (walls, objects) on a log x-axis. Written via a temporary name."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d, fl = stats["depth"], stats["flow"]
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.2))
    x = np.arange(len(BAND_LABELS))
    ax = axes[0]
    ours = [100 * d["band_shares"][k] for k in BAND_LABELS]
    ref = [100 * stats["stillbox_reference"]["band_shares"][k] for k in BAND_LABELS]
    ax.bar(x - 0.2, ours, 0.4, label=f"ours ({stats['n_scenes']} scenes)")
    ax.bar(x + 0.2, ref, 0.4, label="StillBox (published samples)")
    ax.set_xticks(x, BAND_LABELS, rotation=45)
    ax.set_xlabel("pixel depth band (m)")
    ax.set_ylabel("share of pixels (%)")
    ax.set_title("pixel depth")
    ax.legend(fontsize=8)

    ax = axes[1]
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

    ax = axes[2]
    edges = np.asarray(fl["histogram"]["edges_px"])
    for p in PARTS:
        v = 100 * np.asarray(fl["histogram"][p]["shares"])
        ax.stairs(v, edges, label=f"{p} (median {_fmt(fl[p]['median_px'], 'px')})")
    ax.set_xscale("log")
    ax.set_xlabel(f"true flow magnitude (px), frames i to i+{stats['shift']}")
    ax.set_ylabel("share of the part's pixels (%)")
    ax.set_title("flow magnitude")
    ax.legend(fontsize=8)
    fig.tight_layout()
    try:
        atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=100))
    finally:
        plt.close(fig)
