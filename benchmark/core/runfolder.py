"""The run folder of ``stillbox-bench``: its layout and every write into it (docs/RUNS.md).

Layout of a run folder::

    config.json          the resolved TrainConfig (networks) or the scoring options (no network)
    environment.json     versions, device, threads (and the frame cache of a training)
    steps.csv            training loss every ``log_every`` optimiser steps
    metrics.csv          one row per validation (epoch ends and the last step)
    tb/                  TensorBoard events (with the tensorboard package: the `tb` extra)
    checkpoints/         last.pt (training state) and best.pt (best validation score)
    summary.json         scores, formulas, averaging and scale rules, error by FOE distance
    summary.md           the same as a thesis-style table
    per_sample.csv       metrics per scored pair
    pixels.npz           a pixel subsample of the scored pairs (for the figures)
    plots/               PNG figures (:data:`PLOTS`)
    predictions/         depth of every scored pair's second frame (``--save-predictions``;
                         :func:`prediction_name`)
    .stillbox.lock       while a run writes the folder (stillbox_gen.lock, via runner.run_method)

A comparison (``compare --out DIR``, ``report --out OUT``) writes ``OUT.md``, ``OUT.csv`` and
``OUT-error_vs_foe_distance.png`` (``compare``: OUT = DIR/comparison, beside one run folder per
method).

A fly run (``stillbox-bench fly``) writes ``config.json``, ``episodes/NNNNNN.json`` (one per
finished episode, as it ends), ``plots/episode_NNNNNN.png``, ``episodes.csv`` and, last,
``summary.json`` (docs/FLIGHT.md).

Writes: JSON, Markdown and CSV reports by :func:`stillbox_gen.formats.atomic_write_text` (a
temporary name, fsynced, renamed); checkpoints, figures and ``pixels.npz`` by
:func:`atomic_write_binary`; ``steps.csv`` and ``metrics.csv`` grow a row at a time and are cut
back to the checkpoint's step on resume (:func:`start_logs`), and so are the TensorBoard event
files (:func:`cut_events`). Only this module writes into a run
folder (evaluate's per-pair predictions go through :func:`save_prediction`).
"""

from __future__ import annotations

import csv
import importlib.util
import io
import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

import numpy as np
import torch

from stillbox_gen import layout
from stillbox_gen.formats import TEMP_INFIX, atomic_write, atomic_write_text, flo_bytes

from .checkpoint import first_line
from .errors import FieldError

CONFIG_JSON = "config.json"
ENVIRONMENT_JSON = "environment.json"
STEPS_CSV = "steps.csv"
METRICS_CSV = "metrics.csv"
TB_DIR = "tb"
CHECKPOINTS_DIR = "checkpoints"
SUMMARY_JSON = "summary.json"
SUMMARY_MD = "summary.md"
PER_SAMPLE_CSV = "per_sample.csv"
PIXELS_NPZ = "pixels.npz"
PLOTS_DIR = "plots"
PREDICTIONS_DIR = "predictions"
#: figures of a run, ``plots/<name>.png``
PLOTS = ("error_vs_depth", "error_vs_foe_distance", "error_vs_estimate", "samples")
PLOTS += ("learning_curve",)
#: the tables of a results folder (eval-multishift, eval-sequences)
RESULTS_CSV, RESULTS_MD, RESULTS_JSON = "results.csv", "results.md", "results.json"
COMPARISON = "comparison"  # compare --out DIR writes DIR/comparison.{md,csv} and the figure


# ---------------------------------------------------------------- paths


def checkpoint_path(run: Path, name: str) -> Path:
    """``checkpoints/<name>.pt`` (name: "last" or "best")."""
    return Path(run) / CHECKPOINTS_DIR / f"{name}.pt"


def plot_path(run: Path, name: str) -> Path:
    """``plots/<name>.png`` for a name of :data:`PLOTS`."""
    if name not in PLOTS:
        raise ValueError(f"unknown plot {name!r} (one of {', '.join(PLOTS)})")
    return Path(run) / PLOTS_DIR / f"{name}.png"


def predictions_dir(run: Path) -> Path:
    return Path(run) / PREDICTIONS_DIR


def tb_dir(run: Path) -> Path:
    return Path(run) / TB_DIR


def comparison_paths(out: Path) -> dict[str, Path]:
    """The files of a comparison named ``out``: ``md``, ``csv`` and ``figure``."""
    out = Path(out)
    return {
        "md": out.with_name(f"{out.name}.md"),
        "csv": out.with_name(f"{out.name}.csv"),
        "figure": out.with_name(f"{out.name}-error_vs_foe_distance.png"),
    }


# ---------------------------------------------------------------- reads


def has_summary(run: Path) -> bool:
    """True when the run was scored (its summary.json exists)."""
    return (Path(run) / SUMMARY_JSON).is_file()


def read_summary(run: Path) -> dict:
    """summary.json: a dict with a ``model`` name and a ``metrics`` dict; anything else (not
    JSON, not UTF-8, another shape) is a one-line ValueError naming the file."""
    path = Path(run) / SUMMARY_JSON
    try:
        summary = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: not a readable {SUMMARY_JSON} ({first_line(e)})") from None
    if not (
        isinstance(summary, dict)
        and isinstance(summary.get("model"), str)
        and isinstance(summary.get("metrics"), dict)
    ):
        raise ValueError(f"{path}: not a stillbox-bench {SUMMARY_JSON} (no 'model' and 'metrics')")
    return summary


def read_pixels(run: Path) -> dict[str, np.ndarray] | None:
    """The numeric arrays of pixels.npz, or None when the run has none. Read without pickle (an
    array of objects is refused, never unpickled); a file that is not such an archive is a
    one-line ValueError naming it."""
    path = Path(run) / PIXELS_NPZ
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as px:
            arrays = {k: px[k] for k in px.files}
    except Exception as e:  # noqa: BLE001 - any reader failure (zip, header, pickle) is the file's
        raise ValueError(f"{path}: not a readable {PIXELS_NPZ} ({first_line(e)})") from None
    odd = [k for k, a in arrays.items() if a.dtype.kind not in "biuf"]
    if odd:
        raise ValueError(f"{path}: array '{odd[0]}' is not numeric ({arrays[odd[0]].dtype})")
    return arrays


def read_rows(run: Path, name: str) -> list[dict]:
    """Rows of steps.csv or metrics.csv as dicts of strings ([] when the file is missing)."""
    path = Path(run) / name
    if not path.exists():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


# ---------------------------------------------------------------- folders and atomic writes


def make_folder(folder: Path, field: str = "out") -> Path:
    """``mkdir -p folder``; a folder that cannot be made (e.g. under /proc, read-only, a file
    in the way) is a one-line FieldError naming ``field`` (the run folder's) and the folder."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise FieldError(field, f"cannot create '{folder}' ({e.strerror or e})") from None
    return folder


def atomic_write_binary(
    path: Path, write: Callable[[BinaryIO], None], sync_folder: bool = False
) -> None:
    """``formats.atomic_write`` into a run folder, making its folder first (FieldError naming
    ``out`` when it cannot)."""
    path = Path(path)
    make_folder(path.parent)
    atomic_write(path, write, sync_folder)


def save_figure(fig, path: str | os.PathLike, dpi: int = 100) -> None:
    """Render the matplotlib Figure ``fig`` to PNG at ``path`` atomically (folders created),
    then release it."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    try:
        FigureCanvasAgg(fig)
        atomic_write_binary(path, lambda f: fig.savefig(f, format="png", dpi=dpi))
    finally:
        fig.clear()


def _write_json(path: Path, obj) -> None:
    """Indented JSON; NaN and infinities are written as NaN / Infinity (Python's reading)."""
    atomic_write_text(path, json.dumps(obj, indent=2) + "\n")


def csv_text(rows: list[dict]) -> str:
    """CSV with a header from the first row's keys (excel dialect, CRLF line ends)."""
    buf = io.StringIO(newline="")
    if rows:
        w = csv.DictWriter(buf, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return buf.getvalue()


# ---------------------------------------------------------------- configuration


def write_config(run: Path, config: dict) -> None:
    _write_json(Path(run) / CONFIG_JSON, config)


def write_environment(run: Path, env: dict) -> None:
    _write_json(Path(run) / ENVIRONMENT_JSON, env)


# ---------------------------------------------------------------- training logs and checkpoints


def save_checkpoint(path: Path, payload: dict) -> None:
    """``torch.save(payload)`` atomically, the folder fsynced after the rename."""
    atomic_write_binary(path, lambda f: torch.save(payload, f), sync_folder=True)


def remove_stale_temps(folder: Path) -> list[Path]:
    """Delete the temporary files of checkpoint writes cut short by a kill; return them."""
    folder = Path(folder)
    stale = sorted(folder.glob(f".*.pt{TEMP_INFIX}*")) if folder.is_dir() else []
    for p in stale:
        p.unlink(missing_ok=True)
    return stale


def start_logs(run: Path, resume: bool, last_step: int) -> list[Path]:
    """Make the folder ready for training; return the checkpoint temporaries it removed.

    Resuming: drop log rows and TensorBoard events written after the checkpoint's
    ``last_step``. Not resuming (no
    checkpoint to continue, e.g. a run killed before its first one): start steps.csv,
    metrics.csv, tb/ and best.pt afresh. Either way delete checkpoint temporaries left by a kill.
    """
    run = Path(run)
    make_folder(make_folder(run) / CHECKPOINTS_DIR)
    stale = remove_stale_temps(run / CHECKPOINTS_DIR)
    if resume:
        for name in (STEPS_CSV, METRICS_CSV):
            rows = read_rows(run, name)
            (run / name).unlink(missing_ok=True)
            for row in rows:
                if float(row["step"]) <= last_step:
                    append_row(run, name, row)
        cut_events(tb_dir(run), last_step)
        return stale
    for path in (run / STEPS_CSV, run / METRICS_CSV, checkpoint_path(run, "best")):
        path.unlink(missing_ok=True)
    shutil.rmtree(tb_dir(run), ignore_errors=True)
    return stale


#: what a training logs once when it writes no TensorBoard events
TENSORBOARD_MISSING = (
    "TensorBoard logs off: the tensorboard package is not installed (pip install "
    "'stillbox-gen[tb]'); steps.csv and metrics.csv hold the same values"
)


def has_tensorboard() -> bool:
    """Whether the tensorboard package (the `tb` extra) is installed."""
    return importlib.util.find_spec("tensorboard") is not None


class NoTensorBoard:
    """Stands in for torch's SummaryWriter without the tensorboard package: logs nothing."""

    def add_scalar(self, *args: object, **kwargs: object) -> None:
        pass

    def close(self) -> None:
        pass


def tensorboard_writer(run: Path):  # noqa: ANN201 (torch's SummaryWriter, imported lazily)
    """A SummaryWriter into ``run/tb``, or :class:`NoTensorBoard` when the package is missing
    (torch.utils.tensorboard needs it)."""
    if not has_tensorboard():
        return NoTensorBoard()
    from torch.utils.tensorboard import SummaryWriter

    return SummaryWriter(str(tb_dir(run)))


def cut_events(folder: Path, last_step: int) -> None:
    """Drop the TensorBoard events of steps after ``last_step`` from every event file of
    ``folder`` (rewritten atomically; a record cut short by a kill is dropped too), so a resumed
    run logs each step once, whatever reads the files (TensorBoard's purge of orphaned data is
    done by some readers only). Without the tensorboard package the files cannot be read and are
    left as they are (a resumed run then writes no events to them)."""
    if not has_tensorboard():
        return
    from tensorboard.backend.event_processing.event_file_loader import RawEventFileLoader
    from tensorboard.compat.proto.event_pb2 import Event
    from tensorboard.summary.writer.record_writer import RecordWriter

    for path in sorted(Path(folder).glob("events.out.tfevents.*")) if Path(folder).is_dir() else []:
        records = list(RawEventFileLoader(str(path)).Load())
        kept = [r for r in records if Event.FromString(r).step <= last_step]
        if len(kept) == len(records) and path.stat().st_size == sum(len(r) + 16 for r in kept):
            continue  # nothing after the checkpoint, no truncated record

        def write(f: BinaryIO, kept: list[bytes] = kept) -> None:
            writer = RecordWriter(f)
            for record in kept:
                writer.write(record)

        atomic_write_binary(path, write)


def append_row(run: Path, name: str, row: dict) -> None:
    """Append ``row`` to steps.csv or metrics.csv (header first when the file is new)."""
    path = Path(run) / name
    new = not path.exists()
    with open(path, "a", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(row))
        if new:
            w.writeheader()
        w.writerow(row)


# ---------------------------------------------------------------- scores


def prediction_name(scene: int, frame: int, ext: str = "npy") -> str:
    """``<chunk>/depth_<s>_<f>.<ext>``: the prediction of frame ``frame`` of scene ``scene``
    (global index) in a predictions folder, the dataset's own chunk and depth-file names
    (stillbox_gen.layout), so that ``eval --predictions`` reads what ``--save-predictions``
    writes."""
    return f"{layout.chunk_name(scene)}/{layout.depth_name(layout.local_index(scene), frame, ext)}"


def save_prediction(folder: Path, scene: int, frame: int, depth: np.ndarray) -> None:
    """:func:`prediction_name` under ``folder``: float32 depth (H, W) in metres of frame
    ``frame`` (a scored pair's second frame) at full resolution, written atomically."""
    array = depth.astype(np.float32)
    atomic_write_binary(Path(folder) / prediction_name(scene, frame), lambda f: np.save(f, array))


def flow_prediction_name(scene: int, a: int, b: int) -> str:
    """``<chunk>/flow_<s>_<a>_<b>.flo``: a predicted flow from frame ``a`` to frame ``b`` of scene
    ``scene`` (global index), the name the dataset gives its stored flow (stillbox_gen.layout)."""
    return f"{layout.chunk_name(scene)}/{layout.flow_name(layout.local_index(scene), a, b)}"


def save_flow_prediction(folder: Path, scene: int, a: int, b: int, flow: np.ndarray) -> None:
    """:func:`flow_prediction_name` under ``folder``: a (2, H, W) flow in pixels on frame ``a``'s
    grid towards frame ``b`` (channel 0 x right, 1 y down), as Middlebury .flo, atomically."""
    data = flo_bytes(np.asarray(flow).transpose(1, 2, 0))
    atomic_write_binary(Path(folder) / flow_prediction_name(scene, a, b), lambda f: f.write(data))


def write_report(
    run: Path,
    summary: dict,
    markdown: str,
    per_sample: list[dict],
    pixels: dict[str, np.ndarray],
) -> None:
    """per_sample.csv, pixels.npz (when there are pixels), summary.json and summary.md."""
    run = make_folder(run)
    atomic_write_text(run / PER_SAMPLE_CSV, csv_text(per_sample))
    if pixels:
        atomic_write_binary(run / PIXELS_NPZ, lambda f: np.savez_compressed(f, **pixels))
    _write_json(run / SUMMARY_JSON, summary)
    atomic_write_text(run / SUMMARY_MD, markdown)


def write_comparison(out: Path, markdown: str, csv_text: str) -> None:
    """``OUT.md`` and ``OUT.csv`` of a comparison (:func:`comparison_paths`)."""
    paths = comparison_paths(out)
    make_folder(paths["md"].parent)
    atomic_write_text(paths["md"], markdown)
    atomic_write_text(paths["csv"], csv_text)


# ---------------------------------------------------------------- closed-loop flight (fly)

FLIGHT_KIND = "fly"  # summary.json's "kind" of a fly run
EPISODES_CSV = "episodes.csv"
EPISODES_DIR = "episodes"  # one NNNNNN.json per finished episode: what a resumed run skips


def episode_path(run: Path, index: int) -> Path:
    """``episodes/<index:06d>.json``: one finished episode of a fly run."""
    return Path(run) / EPISODES_DIR / f"{index:06d}.json"


def episode_plot_path(run: Path, index: int) -> Path:
    """``plots/episode_<index:06d>.png``: the top-down figure of one episode."""
    return Path(run) / PLOTS_DIR / f"episode_{index:06d}.png"


def read_config(run: Path) -> dict | None:
    """config.json, or None when the folder has none (a one-line ValueError when unreadable)."""
    path = Path(run) / CONFIG_JSON
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: not a readable {CONFIG_JSON} ({first_line(e)})") from None


def write_episode(run: Path, index: int, record: dict) -> None:
    """One finished episode (atomic): written as soon as it is flown."""
    path = episode_path(run, index)
    make_folder(path.parent)
    _write_json(path, record)


def read_episodes(run: Path) -> dict[int, dict]:
    """The finished episodes of a fly run by index ({} for none); a file that is not readable
    JSON (never the case for atomic writes) is left out, so that episode is flown again."""
    found = {}
    folder = Path(run) / EPISODES_DIR
    for path in sorted(folder.glob("[0-9]*.json")) if folder.is_dir() else []:
        try:
            found[int(path.stem)] = json.loads(path.read_text())
        except (ValueError, OSError):
            continue
    return found


def write_flight_report(run: Path, summary: dict, rows: list[dict]) -> None:
    """episodes.csv (one row per episode) and summary.json, the last file a fly run writes."""
    atomic_write_text(Path(run) / EPISODES_CSV, csv_text(rows))
    _write_json(Path(run) / SUMMARY_JSON, summary)


def read_flight_summary(run: Path) -> dict:
    """summary.json of a finished fly run; anything else is a one-line ValueError naming it."""
    path = Path(run) / SUMMARY_JSON
    try:
        summary = json.loads(path.read_text())
    except FileNotFoundError:
        raise ValueError(f"{path}: no {SUMMARY_JSON} (not a finished fly run)") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: not a readable {SUMMARY_JSON} ({first_line(e)})") from None
    if not isinstance(summary, dict) or summary.get("kind") != FLIGHT_KIND:
        raise ValueError(f"{path}: not the {SUMMARY_JSON} of a 'stillbox-bench fly' run")
    return summary
