"""The author's DepthNet code as the reference for ours, at equal budget (docs/results/reference).

The user brings their own checkout of github.com/ClementPinard/DepthNet and a Python that can run
it (torch, numpy, imageio, path, tensorboardX, blessings, progressbar2); nothing of it is part
of this project. :func:`train_author` runs its ``train.py`` through
``reference_launcher.py`` on a stillbox-gen dataset written with ``--legacy --image-format jpg``
(so both codes read the same JPEG frames), on this dataset's own train split (validating on
:data:`AUTHOR_VAL_SCENES` of its val scenes), keeping the checkpoints of chosen epochs.
:func:`convert` turns such a checkpoint into one of this project's, so that ``stillbox-bench
eval`` scores both codes with the same metric code on the same test split.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import torch

from stillbox_gen import layout
from stillbox_gen.conventions import MAX_DEPTH, NOMINAL_SHIFT
from stillbox_gen.packed import PackedDataset

from ..core import runfolder
from ..core.data import camera_of, load_scenes, nominal_displacement, read_dataset
from ..core.errors import FieldError

LAUNCHER = Path(__file__).with_name("reference_launcher.py")
#: val scenes the author's code validates on after each epoch (its choice of "best" only; the
#: harness scores the kept epochs' last checkpoints on the test split)
AUTHOR_VAL_SCENES = 50
#: DataParallel's prefix on the author's state_dict keys
PARALLEL_PREFIX = "module."


def author_split(data: Path, val_scenes: int = AUTHOR_VAL_SCENES) -> dict:
    """The dataset's train scenes as the author's loader reads them (``imgs``, ``depth``,
    ``speed``, ``time_step``, ``subdir``: the chunk folder) and the validation pairs (i, i+3)
    of its first ``val_scenes`` val scenes as ``[[img1, img2], depth, displacement]`` paths
    relative to ``data``. FieldError on ``data`` unless the records hold the legacy ``.jpg`` and
    ``.npy`` files."""
    if isinstance(read_dataset(data), PackedDataset):  # its records name files it lacks
        raise FieldError(
            "data",
            "a pack (stillbox-gen pack) holds no --legacy copies, which the original DepthNet "
            "code reads; give the dataset folder",
            where=f" {data}",
        )
    out: dict = {"train": [], "val": []}
    for split in ("train", "val"):
        for scene in load_scenes(data, split):
            rec = scene.record
            if not (rec["imgs"][0].endswith(".jpg") and rec["depth"][0].endswith(".npy")):
                raise FieldError(
                    "data",
                    "needs the original DepthNet files (stillbox-gen --legacy --image-format jpg)",
                    where=f" {data}",
                )
            chunk = layout.chunk_name(scene.index)
            if split == "train":
                keys = ("imgs", "depth", "speed", "time_step")
                out["train"].append({**{k: rec[k] for k in keys}, "subdir": chunk})
            elif len(out["val"]) < val_scenes * (scene.frames - NOMINAL_SHIFT):
                disp = [v * NOMINAL_SHIFT * rec["time_step"] for v in rec["speed"]]
                for i in range(scene.frames - NOMINAL_SHIFT):
                    pair = [
                        f"{chunk}/{rec['imgs'][i]}",
                        f"{chunk}/{rec['imgs'][i + NOMINAL_SHIFT]}",
                    ]
                    out["val"].append([pair, f"{chunk}/{rec['depth'][i + NOMINAL_SHIFT]}", disp])
    return out


def train_author(
    code: Path,
    python: str,
    data: Path,
    out: Path,
    train_args: list[str],
    keep_epochs: list[int],
    threads: int,
) -> int:
    """Run the author's train.py in ``out`` (its ``Results/`` folder goes there; the kept
    epochs' checkpoints into ``out/epochs``); returns its exit code. ``train_args``: the
    author's own flags (``--epochs``, ``-b``, ``--seed``…); the dataset path is added."""
    code, data, out = Path(code).resolve(), Path(data).resolve(), Path(out).resolve()
    if not (code / "train.py").is_file() or not (code / "datasets" / "stillbox.py").is_file():
        raise FieldError("code", "is not a checkout of ClementPinard/DepthNet", where=f" {code}")
    split = author_split(data)
    out.mkdir(parents=True, exist_ok=True)
    split_json = out / "split.json"
    split_json.write_text(json.dumps(split))
    keep = ",".join(str(e) for e in keep_epochs)
    cmd = [python, str(LAUNCHER), str(code), str(split_json), str(out / "epochs"), keep, "--"]
    cmd += [*train_args, "--no-date", str(data)]
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
    (out / "command.txt").write_text(" ".join(cmd) + "\n")
    return subprocess.call(cmd, cwd=out, env=env)


def convert(author_ckpt: Path, data: Path, dest: Path) -> None:
    """The author's checkpoint (``--bn --activation-function elu``: the same layers as
    ``depthnet``) as a checkpoint of this project's ``depthnet`` for ``data``'s camera: its
    output is depth for NOMINAL_SHIFT frames of the training split's displacement, as ours."""
    ck = torch.load(author_ckpt, map_location="cpu", weights_only=True)
    if not ck.get("bn") or ck.get("activation_function") != "elu" or ck.get("clamp"):
        raise FieldError(
            "ckpt", "was not trained with --bn --activation-function elu", where=f" {author_ckpt}"
        )
    state = {k.removeprefix(PARALLEL_PREFIX): v for k, v in ck["state_dict"].items()}
    runfolder.save_checkpoint(
        Path(dest),
        {
            "model": state,
            "model_name": "depthnet",
            "nominal_displacement": nominal_displacement(load_scenes(data, "train"), NOMINAL_SHIFT),
            "shift": NOMINAL_SHIFT,
            "depth_range": [0.0, MAX_DEPTH],
            "camera": camera_of(data),
            "config": {"source": str(author_ckpt), "epoch": ck.get("epoch")},
        },
    )


def resolution_floor(data: Path, split: str = "test", shift: int = NOMINAL_SHIFT) -> dict:
    """The full-resolution error of a perfect 1/4-resolution depth network on ``split``'s eval
    pairs (the second frame's depth clipped to MAX_DEPTH, area-downsampled 4x as the training
    targets are, upsampled back as ``eval`` upsamples outputs): MAE (metres), MRE and MLE per
    image, then averaged. Not a strict lower bound: another 1/4-resolution map could score a
    little lower at full resolution; this one is the map DepthNet is trained towards."""
    import torch.nn.functional as F

    from ..core import metrics

    rows = []
    for scene in load_scenes(data, split):
        for f in range(shift, scene.frames):
            gt = torch.from_numpy(scene.load_depth(f)).clamp(max=MAX_DEPTH)[None, None]
            h, w = gt.shape[-2:]
            quarter = F.adaptive_avg_pool2d(gt, (h // 4, w // 4))
            up = metrics.upsample_to(quarter, h, w).reshape(1, h, w)
            rows.append(metrics.image_metrics(up, gt.reshape(1, h, w)))
    names = ("mae", "mre", "mle")
    return {"pairs": len(rows), **{k: float(torch.cat([r[k] for r in rows]).mean()) for k in names}}


def collect(evals: Path, epoch_size: int, batch_size: int) -> list[dict]:
    """One row per ``evals/<code>-s<seed>-e<epoch>/summary.json`` (``stillbox-bench eval``'s):
    code, seed, epoch, samples (epoch x epoch_size x batch_size), the test metrics and the MAE
    by distance to the focus of expansion (one column per band, pixels)."""
    rows = []
    for summary in sorted(Path(evals).glob("*-s*-e*/summary.json")):
        code, seed, epoch = summary.parent.name.rsplit("-", 2)
        s = json.loads(summary.read_text())
        m = s["metrics"]
        row = {"code": code, "seed": int(seed[1:]), "epoch": int(epoch[1:])}
        row["samples"] = row["epoch"] * epoch_size * batch_size
        row.update({k: m[k] for k in ("mae", "mre", "mle", "depth_error", "p1.25")})
        for band in s["error_by_foe_distance"]:
            to = "inf" if band["to_px"] is None else f"{band['to_px']:g}"  # the last band: open
            row[f"mae_foe_{band['from_px']:g}-{to}px"] = band["mae"]
        rows.append(row)
    return sorted(rows, key=lambda r: (r["code"], r["seed"], r["epoch"]))


def plot(rows: list[dict], path: Path, floor: float | None = None) -> None:
    """Test MAE against training samples (log axis), one line per code and seed, with the
    thesis' 4.72 m (Table 3.4) and the resolution floor of :func:`resolution_floor`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for code, seed in sorted({(r["code"], r["seed"]) for r in rows}):
        pts = [(r["samples"], r["mae"]) for r in rows if (r["code"], r["seed"]) == (code, seed)]
        style = "-o" if code == "ours" else "--s"
        ax.plot(*zip(*pts, strict=True), style, label=f"{code} (seed {seed})")
    ax.axhline(4.72, color="k", lw=0.8, ls=":", label="thesis Table 3.4 (4.72 m)")
    if floor is not None:
        ax.axhline(floor, color="grey", lw=0.8, label=f"perfect 1/4-res. output ({floor:.2f} m)")
    ax.set(xscale="log", xlabel="training samples", ylabel="test MAE (m)")
    ax.set_title("DepthNet 64 px: the author's code and ours, same data and recipe")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    """``python -m benchmark.supervised.reference train|convert ...`` (docs/results/reference)."""
    import argparse

    p = argparse.ArgumentParser(prog="python -m benchmark.supervised.reference")
    sub = p.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train", help="run the author's train.py on a stillbox-gen dataset")
    t.add_argument("--code", type=Path, required=True, help="checkout of ClementPinard/DepthNet")
    t.add_argument("--python", default=sys.executable, help="Python that runs the author's code")
    t.add_argument("--data", type=Path, required=True)
    t.add_argument("--out", type=Path, required=True)
    t.add_argument("--keep", default="", help="epochs whose checkpoints are kept, e.g. 6,18,55")
    t.add_argument("--threads", type=int, default=1)
    c = sub.add_parser("convert", help="author's checkpoint -> this project's")
    c.add_argument("ckpt", type=Path)
    c.add_argument("--data", type=Path, required=True)
    c.add_argument("--out", type=Path, required=True)
    f = sub.add_parser("floor", help="error of a perfect 1/4-resolution network on a split")
    f.add_argument("--data", type=Path, required=True)
    f.add_argument("--split", default="test")
    r = sub.add_parser("report", help="results.csv and mae_vs_samples.png from the evals")
    r.add_argument("evals", type=Path)
    r.add_argument("--out", type=Path, required=True)
    r.add_argument("--epoch-size", type=int, required=True)
    r.add_argument("--batch-size", type=int, required=True)
    r.add_argument("--floor", type=float, default=None)
    args, rest = p.parse_known_args(argv)
    if args.cmd == "report":
        import csv

        rows = collect(args.evals, args.epoch_size, args.batch_size)
        args.out.mkdir(parents=True, exist_ok=True)
        keys = list(dict.fromkeys(k for row in rows for k in row))
        with open(args.out / "results.csv", "w", newline="") as f:
            writer = csv.DictWriter(f, keys)
            writer.writeheader()
            writer.writerows(rows)
        plot(rows, args.out / "mae_vs_samples.png", args.floor)
        return
    if args.cmd == "floor":
        print(json.dumps(resolution_floor(args.data, args.split)))
        return
    if args.cmd == "train":
        keep = [int(e) for e in args.keep.split(",") if e]
        rest = [a for a in rest if a != "--"]
        raise SystemExit(
            train_author(args.code, args.python, args.data, args.out, rest, keep, args.threads)
        )
    if rest:
        p.error(f"unrecognised arguments: {' '.join(rest)}")
    convert(args.ckpt, args.data, args.out)


if __name__ == "__main__":
    main()
