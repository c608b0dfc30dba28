"""``eval-sequences``' results in the layout of thesis Table 5.2 (method, training set, scale
factor, supervision, occlusion module, metrics), the thesis' Table 5.2 / 5.3 numbers beside the
rows that match, and the files: results.md, results.csv, results.json."""

from __future__ import annotations

import json
import time
from pathlib import Path

import torch

from stillbox_gen.formats import atomic_write_text

from ..core import metrics, registry, runfolder, thesis
from ..core.runfolder import RESULTS_CSV, RESULTS_JSON, RESULTS_MD
from .sequence_eval import (
    PAIR_TARGET_DEPTH,
    POSE_COSINE,
    POSE_COSINE_GOOD,
    POSE_COSINE_SHARE,
    SEQUENCE_LENGTH,
    UPRIGHT,
    UPSIDE_DOWN,
    check_size,
    constant_plane,
    evaluate,
    load_model,
    test_scenes,
)

NONE = thesis.NONE  # the tables' "no supervision" mark
#: method names of the thesis' tables, per kind of registered method
METHOD_NAMES = {
    registry.DEPTH.name: "Supervised DepthNet",
    registry.UNSUPERVISED.name: "Unsupervised DepthNet",
    registry.SCALE_FREE.name: "SFMLearner",
    registry.CONSTANT.name: "Constant plane",
}


#: the thesis' numbers (Table 5.2: upright scores; Table 5.3: upside down)
THESIS_ROWS = thesis.TABLES_5_2_5_3
#: which thesis table sits beside the scores of each orientation
THESIS_TABLE = {UPRIGHT: "5.2", UPSIDE_DOWN: "5.3"}
HEADINGS = {
    UPRIGHT: "Upright (thesis Table 5.2 beside: StillBox, no pretraining)",
    UPSIDE_DOWN: "Upside down: rows of frames and depth flipped, sky down (thesis Table 5.3 "
    "beside: upside-down KITTI, networks trained on KITTI or StillBox → KITTI, so only "
    "indicative)",
}
#: the columns of Tables 5.2-5.3 (results.csv also has the field's metrics)
SHOWN = tuple(metrics.header(k) for k in metrics.THESIS_METRICS)
#: results.md's column of PoseNet's translation direction (results.csv: POSE_COSINE and
#: POSE_COSINE_SHARE)
POSE_HEADER = f"PoseNet cosine (share > {POSE_COSINE_GOOD:g})"


def method(row: dict) -> str:
    """The thesis' name of a result row's method."""
    return METHOD_NAMES[registry.MODELS[row["model"]].kind.name]


def supervision(row: dict) -> str:
    """Table 5.2's supervision of a result row: "D + O" (depth; frames stabilised by the known
    orientation), "O" (``--pose orientation``), "-" (no training) or ✗ (none)."""
    kind = registry.MODELS[row["model"]].kind
    if kind is registry.DEPTH:
        return "D + O"
    if kind is registry.CONSTANT:
        return "-"
    return "O" if row["pose"] == "orientation" else NONE


def thesis_row(row: dict) -> thesis.ThesisRow | None:
    """The thesis row beside a result row (its orientation's table): same method, scale and
    supervision, and occlusion module where the table has one."""
    key = (THESIS_TABLE[row["orientation"]], method(row), row["scale"], supervision(row))
    for t in THESIS_ROWS:
        if (t.table, t.method, t.scale, t.supervision) == key and t.occlusion in (
            None,
            bool(row["occlusion"]),
        ):
            return t
    return None


def _cells(values) -> str:
    return " | ".join(f"{v:.3f}" for v in values)


def occlusion(row: dict) -> str:
    """The occlusion-module column: ✓, ✗, or "-" for the constant plane."""
    if registry.MODELS[row["model"]].kind is registry.CONSTANT:
        return "-"
    return "✓" if row["occlusion"] else NONE


def pose_cell(row: dict) -> str:
    """The PoseNet column of a result row: the mean cosine and the share of sequences above
    POSE_COSINE_GOOD, e.g. "0.987 (92 %)"; empty without PoseNet (or in a row written before
    the column existed)."""
    cosine = row.get(POSE_COSINE)
    if cosine is None or cosine == "":
        return ""
    return f"{float(cosine):.3f} ({100 * float(row[POSE_COSINE_SHARE]):.0f} %)"


def markdown(rows: list[dict], info: dict) -> str:
    """One table per orientation, each of our rows followed by the matching thesis row."""
    scenes = f"{info['scenes']} scene{'s' if info['scenes'] != 1 else ''}"
    lines = [
        f"# Depth from {info['sequence_length']}-frame sequences (thesis §5.4.3-5.4.4) on "
        f"{info['data']}",
        "",
        f"{info['split']} split: {scenes}, {rows[0]['sequences']} sequences "
        f"({'rotating' if info['rotating'] else 'stabilised'} camera). Depth of each sequence's "
        f"last frame; DepthNet's pair: mean output closest to {info['pair_target_depth_m']:g} m, "
        "scaled by the measured displacement (P); P (fixed pair): the reference whose measured "
        "displacement is closest to the network's nominal one, the same scaling. "
        + info["averaging_rule"]
        + f" {POSE_HEADER}: networks with a PoseNet, the mean over sequences of the cosine "
        "between PoseNet's translation from the last frame to the row's reference (SFMLearner: "
        "the first frame) and the true one, and the share of sequences above "
        f"{POSE_COSINE_GOOD:g}.",
    ]
    head = "| method | model | training set | scale factor | supervision | occlusion | "
    for o in info["orientations"]:
        lines += ["", f"## {HEADINGS[o]}", ""]
        lines.append(
            head + " | ".join(SHOWN) + f" | {POSE_HEADER} | pair chosen (frames apart: count) |"
        )
        lines.append("|" + "---|" * (6 + len(SHOWN) + 2))
        for r in (r for r in rows if r["orientation"] == o):
            scores = _cells(r[k] for k in metrics.THESIS_METRICS)
            lines.append(
                f"| {method(r)} | {r['model']} | {r['training_set']} | {r['scale']} | "
                f"{supervision(r)} | {occlusion(r)} | {scores} | {pose_cell(r)} | "
                f"{r['shifts_used']} |"
            )
            t = thesis_row(r)
            if t is not None:
                occ = "" if t.occlusion is None else "✓" if t.occlusion else NONE
                lines.append(
                    f"| *thesis Table {t.table}* | | {t.training_set} | {t.scale} | "
                    f"{t.supervision} | {occ} | {_cells(t.values)} | | |"
                )
    return "\n".join(lines) + "\n"


def with_thesis(row: dict) -> dict:
    """A result row with its method, supervision and the thesis' numbers beside (``thesis_*``,
    None where no thesis row matches)."""
    t = thesis_row(row)
    first = ("orientation", "method", "model")
    out = {"orientation": row["orientation"], "method": method(row), "model": row["model"]}
    out.update((k, v) for k, v in row.items() if k not in first)
    out.update(supervision=supervision(row), thesis_table=t.table if t else None)
    for k, name in enumerate(metrics.THESIS_METRICS):
        out[f"thesis_{name}"] = t.values[k] if t else None
    return out


def write_results(out: Path, rows: list[dict], info: dict) -> str:
    """results.md, results.csv (one row per orientation, method and scale) and results.json
    (``info`` and the rows) into ``out``, each written atomically; returns the Markdown."""
    full = [with_thesis(r) for r in rows]
    md = markdown(rows, info)
    runfolder.make_folder(out)
    atomic_write_text(out / RESULTS_CSV, runfolder.csv_text(full))
    atomic_write_text(out / RESULTS_JSON, json.dumps({**info, "rows": full}, indent=2) + "\n")
    atomic_write_text(out / RESULTS_MD, md)
    return md


def run(
    checkpoints: list[Path],
    data: Path,
    out: Path,
    split: str = "test",
    upside: bool = False,
    device: torch.device | None = None,
    limit: int | None = None,
    progress: bool = True,
) -> tuple[list[dict], str]:
    """Load every checkpoint, check them and the data, score (sequence_eval.evaluate; the
    constant plane first) and write :func:`write_results` (``out`` is written only after every
    check and the scoring); returns the rows and the Markdown."""
    device = device or torch.device("cpu")
    t0 = time.perf_counter()
    models = [constant_plane(), *(load_model(p) for p in checkpoints)]
    scenes = test_scenes(data, split, limit)
    check_size(models, scenes, data)
    orientations = (UPRIGHT, UPSIDE_DOWN) if upside else (UPRIGHT,)
    rows = evaluate(models, scenes, device, orientations, progress)
    info = {
        "data": str(data), "split": split, "scenes": len(scenes),
        "sequence_length": SEQUENCE_LENGTH, "pair_target_depth_m": PAIR_TARGET_DEPTH,
        "rotating": any(not s.stabilised for s in scenes), "orientations": list(orientations),
        "device": str(device), "averaging_rule": metrics.AVERAGING_RULE,
        "seconds": round(time.perf_counter() - t0, 1),
    }  # fmt: skip
    return rows, write_results(out, rows, info)
