"""The author's chapter-5 code (github.com/ClementPinard/unsupervised-depthnet) against ours
(README.md in this folder). Runs with this project's Python; the author's code runs under its
own Python through ``launcher.py``. Nothing of the author's code is copied here: the user's
checkout is passed as CODE, and ``verify`` imports its ``models`` from there.

    harness.py prepare DATA OUT              the author's StillBox layout of DATA's train/val
    harness.py train CODE PYTHON LAYOUT OUT -- <train_img_pairs.py flags>
    harness.py convert DEPTHNET POSENET DATA DEST   author's checkpoints -> our depthnet-unsup
    harness.py verify CODE DEPTHNET POSENET DEST    both codes' networks on one input, to 1e-5
    harness.py curves OURS_STEPS AUTHOR_LOG OUT     loss curves (CSV and PNG)
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
#: DataParallel's prefix on the author's state_dict keys
PARALLEL = "module."
#: the author's frames are normalised (x - 0.5) / 0.5, ours (x - 0.5) / 0.2: an input of ours
#: times this is the author's input, so conv1's weights times it read ours
INPUT_RATIO = 0.2 / 0.5
#: the author's depth is ELU + 1.01, ours ELU + 1 (benchmark.core.models.depth_activation)
ACTIVATION_OFFSET = 0.01
#: PoseNet outputs per frame in the author's code (translation, then Euler angles)
AUTHOR_DOF = 6


def prepare(data: Path, out: Path) -> dict:
    """``OUT/train.txt``, ``OUT/val.txt`` and ``OUT/{train,val}/metadata.json``: the author's
    ``StillBox`` loader's layout (``datasets/shifted_sequence_folders.py``), one folder per split
    holding DATA's scenes of that split (so both codes train on the same scenes). Only JSON is
    written, and the val scenes' depth as ``.npy`` (the author's ``--with-gt`` validation reads
    those; its validation without ground truth does not run: ``validate`` calls
    ``validate_without_gt`` without its ``tb_writer`` argument). ``imgs`` are the absolute paths
    of DATA's frames, ``speed``, ``time_step`` and
    ``orientation`` DATA's records' (the original StillBox keys, docs/FORMAT.md); ``args`` has
    the ``fov`` and ``resolution`` the loader derives its intrinsics from."""
    from benchmark.core.data import camera_of, load_scenes

    cam = camera_of(data)
    out.mkdir(parents=True, exist_ok=True)
    counts = {}
    for split in ("train", "val"):
        scenes = load_scenes(data, split, rotations=True)
        folder = out / split
        folder.mkdir(exist_ok=True)
        records = []
        for s in scenes:
            depth = []
            if split == "val":  # --with-gt validation reads depth as .npy
                for f in range(s.frames):
                    depth.append(f"depth_{s.index:05d}_{f:02d}.npy")
                    np.save(folder / depth[-1], s.load_depth(f).astype(np.float32))
            records.append({
                "imgs": [str(p.resolve()) for p in s.rgb],
                "depth": depth,
                "speed": s.record["speed"],
                "time_step": s.record["time_step"],
                "orientation": s.record["orientation"],
                "length": s.frames,
                "index": s.index,
            })  # fmt: skip
        meta = {"args": {"fov": cam["fov_deg"], "resolution": [cam["width"], cam["height"]]},
                "scenes": records}  # fmt: skip
        (folder / "metadata.json").write_text(json.dumps(meta))
        (out / f"{split}.txt").write_text(f"{split}\n")
        counts[split] = len(records)
    return counts


def train(code: Path, python: str, layout: Path, out: Path, flags: list[str]) -> int:
    """The author's ``train_img_pairs.py`` on LAYOUT through launcher.py, in OUT (its
    ``checkpoints/`` go there, every epoch's also to ``OUT/epochs``), one torch thread."""
    code, layout, out = code.resolve(), layout.resolve(), out.resolve()
    if not (code / "train_img_pairs.py").is_file():
        raise SystemExit(f"CODE: {code} is not a checkout of ClementPinard/unsupervised-depthnet")
    out.mkdir(parents=True, exist_ok=True)
    cmd = [python, str(HERE / "launcher.py"), str(code), str(out / "epochs"), "--", str(layout)]
    cmd += flags
    (out / "command.txt").write_text(" ".join(cmd) + "\n")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    return subprocess.call(cmd, cwd=out, env=env)


def _author_state(path: Path) -> tuple[dict, dict]:
    ck = torch.load(path, map_location="cpu", weights_only=False)
    return {k.removeprefix(PARALLEL): v for k, v in ck["state_dict"].items()}, ck


def converted_state(depth_ckpt: Path, pose_ckpt: Path) -> tuple[dict, dict]:
    """Our ``depthnet-unsup`` state_dict (DepthPoseNet: ``depth.*``, ``pose.*``) from the
    author's two checkpoints (``--bn depth``: the same DepthNet layers and names as ours), and
    the author's DepthNet checkpoint's other entries. Three mappings:

    - input normalisation: conv1's (and PoseNet's first conv's) weights × INPUT_RATIO;
    - activation: the finest scale's prediction bias + ACTIVATION_OFFSET (ELU(x + 0.01) + 1 =
      x + 1.01 = the author's ELU(x) + 1.01 for x ≥ 0, i.e. depth ≥ 1.01 m; below, it differs by
      less than 0.01 m). Only the finest scale is scored; the coarser ones are left as they are
      because their raw values feed the next scale;
    - PoseNet: ``conv<i>.0`` -> ``encoder.<2(i-1)>``, ``pose_pred`` -> ``predict`` keeping the
      3 translation rows of each frame's 6 (our ``--pose orientation`` PoseNet; ``eval-sequences``
      stabilises with the known orientation and does not run it).
    """
    depth, meta = _author_state(depth_ckpt)
    if not meta.get("bn"):
        raise SystemExit(f"{depth_ckpt}: not trained with --bn depth (the layers of our DepthNet)")
    depth = dict(depth)
    depth["conv1.0.weight"] = depth["conv1.0.weight"] * INPUT_RATIO
    depth["predict_depth2.bias"] = depth["predict_depth2.bias"] + ACTIVATION_OFFSET
    pose_author, _ = _author_state(pose_ckpt)
    pose = {}
    for i in range(1, 8):
        w = pose_author[f"conv{i}.0.weight"]
        pose[f"encoder.{2 * (i - 1)}.weight"] = w * INPUT_RATIO if i == 1 else w
        pose[f"encoder.{2 * (i - 1)}.bias"] = pose_author[f"conv{i}.0.bias"]
    w, b = pose_author["pose_pred.weight"], pose_author["pose_pred.bias"]
    frames = w.shape[0] // AUTHOR_DOF
    rows = [f * AUTHOR_DOF + k for f in range(frames) for k in range(3)]
    pose["predict.weight"], pose["predict.bias"] = w[rows].clone(), b[rows].clone()
    state = {f"depth.{k}": v for k, v in depth.items()}
    state.update({f"pose.{k}": v for k, v in pose.items()})
    return state, meta


def convert(depth_ckpt: Path, pose_ckpt: Path, data: Path, dest: Path) -> None:
    """The author's checkpoints as one of our ``depthnet-unsup`` checkpoints for ``data``'s
    camera (``--pose orientation``), answering for the author's ``--nominal-displacement``."""
    from benchmark.core import runfolder
    from benchmark.core.data import camera_of
    from stillbox_gen.conventions import MAX_DEPTH, NOMINAL_SHIFT

    state, meta = converted_state(depth_ckpt, pose_ckpt)
    runfolder.save_checkpoint(
        Path(dest),
        {
            "model": state,
            "model_name": "depthnet-unsup",
            "nominal_displacement": float(meta["nominal_displacement"]),
            "shift": NOMINAL_SHIFT,
            "depth_range": [0.0, MAX_DEPTH],
            "camera": camera_of(data),
            "config": {
                "data": str(data),
                "pose": "orientation",
                "occlusion": False,
                "source": str(depth_ckpt),
                "epoch": meta.get("epoch"),
            },  # fmt: skip
        },
    )


def verify(code: Path, depth_ckpt: Path, pose_ckpt: Path, dest: Path, seed: int = 0) -> dict:
    """Both codes' networks on one random input (a batch of 2 pairs of 64 px frames and a
    5-frame sequence): the author's DepthNet (eval mode: its full-resolution ``depth0``) against
    our converted checkpoint's DepthNet (finest scale, upsampled as ``eval-sequences`` does),
    the translations of both PoseNets, and in training mode (batch statistics) the 1/4, 1/8 and
    1/16 scales. Returns the largest differences; raises unless the eval-mode depth (what
    ``eval-sequences`` scores) agrees to 1e-5 m where the activation's offset is exact
    (:func:`converted_state`: depth >= 1.01 m at 1/4) and the translations to 1e-5; the
    training-mode scales (the coarser ones minus the offset itself, 0.01 m) to 1e-4 m, as batch
    statistics over 2 samples amplify the float rounding of the folded input scale."""
    from benchmark.core import metrics, registry
    from benchmark.core.checkpoint import load_checkpoint, load_weights

    sys.path.insert(0, str(code.resolve()))
    import models as author_models  # the user's checkout

    g = torch.Generator().manual_seed(seed)
    x = torch.rand(2, 5, 3, 64, 64, generator=g)  # frames in [0, 1]
    a_seq, o_seq = (x - 0.5) / 0.5, (x - 0.5) / 0.2
    pair_a = torch.cat([a_seq[:, 1], a_seq[:, 4]], 1)
    pair_o = torch.cat([o_seq[:, 1], o_seq[:, 4]], 1)

    a_depth = author_models.DepthNet(depth_activation="elu", batch_norm=True)
    a_depth.load_state_dict(_author_state(depth_ckpt)[0])
    a_pose = author_models.PoseNet(seq_length=5, batch_norm=False)
    a_pose.load_state_dict(_author_state(pose_ckpt)[0])
    ck = load_checkpoint(dest)
    ours = registry.build_model(ck["model_name"])
    load_weights(ours, ck, "ckpt", dest, ck["model_name"])
    a_depth.eval(), a_pose.eval(), ours.eval()
    with torch.no_grad():
        theirs = a_depth(pair_a)[:, 0]  # (B, H, W): the author's eval output, full resolution
        quarter = ours(pair_o)[0]  # (B, 1, H/4, W/4)
        mine = metrics.upsample_to(quarter, 64, 64)
        # full-resolution pixels whose bilinear neighbours are all >= 1.01 m (exact there)
        exact = metrics.upsample_to((quarter >= 1.0 + ACTIVATION_OFFSET).float(), 64, 64) >= 1.0
        t_theirs = a_pose(a_seq)[..., :3]
        t_mine = ours.pose(o_seq.reshape(2, 15, 64, 64))
        a_depth.train(), ours.train()  # every scale, batch statistics in both
        scales_a, scales_o = a_depth(pair_a)[1:], ours(pair_o)[:3]
    diff = (theirs - mine).abs()
    coarse = [
        (a - ACTIVATION_OFFSET - o).abs().max()
        for a, o in zip(scales_a[1:], scales_o[1:], strict=False)
    ]
    fine = (scales_a[0] - scales_o[0]).abs()[scales_a[0] >= 1.0 + ACTIVATION_OFFSET]
    out = {
        "eval_depth_max_abs_diff_m": float(diff[exact].max()) if exact.any() else 0.0,
        "eval_pixels_compared": int(exact.sum()),
        "eval_pixels": int(diff.numel()),
        "eval_depth_max_abs_diff_all_pixels_m": float(diff.max()),
        "author_depth_range_m": [float(theirs.min()), float(theirs.max())],
        "train_scale_1/4_max_abs_diff_m": float(fine.max()) if fine.numel() else 0.0,
        "train_scales_1/8_1/16_max_abs_diff_m (author - 0.01)": float(max(coarse)),
        "translation_max_abs_diff": float((t_theirs - t_mine).abs().max()),
    }
    train = max(
        out["train_scale_1/4_max_abs_diff_m"],
        out["train_scales_1/8_1/16_max_abs_diff_m (author - 0.01)"],
    )
    evaluated = max(out["eval_depth_max_abs_diff_m"], out["translation_max_abs_diff"])
    if evaluated > 1e-5 or train > 1e-4:
        raise SystemExit(f"conversion does not reproduce the author's networks: {out}")
    return out


def _read_ours(path: Path) -> list[dict]:
    with open(path) as f:
        return [{"step": int(r["step"]), **{k: float(r.get(k) or "nan")
                 for k in ("loss", "photometric", "smooth")}}
                for r in csv.DictReader(f) if r.get("loss")]  # fmt: skip


def _read_author(path: Path) -> list[dict]:
    rows = []
    with open(path) as f:
        reader = csv.reader(f, delimiter="\t")
        next(reader)  # train_loss, photo_loss, explainability_loss, smooth_loss (3 columns written)
        for i, r in enumerate(reader, 1):
            rows.append({"step": i, "loss": float(r[0]), "photometric": float(r[1]),
                         "smooth": float(r[2])})  # fmt: skip
    return rows


def curves(ours_steps: Path, author_log: Path, out: Path, window: int = 50) -> None:
    """``loss_ours.csv``, ``loss_author.csv`` (step, loss, photometric, smooth: each code's own
    loss, not comparable in value) and ``loss_curves.png`` (each term relative to its mean over
    the first ``window`` logged steps, running mean over ``window`` steps)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    series = {"ours": _read_ours(ours_steps), "author": _read_author(author_log)}
    out.mkdir(parents=True, exist_ok=True)
    for who, rows in series.items():
        with open(out / f"loss_{who}.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=["step", "loss", "photometric", "smooth"])
            w.writeheader()
            w.writerows(rows)
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    for ax, term in zip(axes, ("loss", "photometric", "smooth"), strict=True):
        for who, rows in series.items():
            steps = [r["step"] for r in rows]
            vals = [r[term] for r in rows]
            k = max(1, min(window, len(vals)) // (10 if who == "ours" else 1))
            ref = sum(vals[:k]) / k or 1.0
            run = [sum(vals[max(0, i - k + 1): i + 1]) / len(vals[max(0, i - k + 1): i + 1])
                   for i in range(len(vals))]  # fmt: skip
            ax.plot(steps, [v / ref for v in run], label=who)
        ax.set_title(f"{term} / its start (running mean)")
        ax.set_xlabel("step (batch of 16)")
        ax.grid(alpha=0.3)
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(out / "loss_curves.png", dpi=110)


def main(argv: list[str]) -> None:
    cmd, *rest = argv
    if cmd == "prepare":
        print(json.dumps(prepare(Path(rest[0]), Path(rest[1]))))
    elif cmd == "train":
        sep = rest.index("--")
        code, python, layout, out = rest[:sep]
        raise SystemExit(train(Path(code), python, Path(layout), Path(out), rest[sep + 1 :]))
    elif cmd == "convert":
        convert(*(Path(a) for a in rest[:4]))
    elif cmd == "verify":
        print(json.dumps(verify(*(Path(a) for a in rest[:4])), indent=1))
    elif cmd == "curves":
        curves(*(Path(a) for a in rest[:3]))
    else:
        raise SystemExit(__doc__)


if __name__ == "__main__":
    main(sys.argv[1:])
