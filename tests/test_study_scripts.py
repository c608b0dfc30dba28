"""The study scripts under docs/results/ that import the library, run as their READMEs run them
(``python docs/results/.../script.py ARGS`` from the repository root, this venv's Python, a
subprocess) on the suite's tiny datasets and checkpoints, with their smallest arguments: each
exits 0 and prints or writes what its README quotes (a table's header and rows, a file's columns
or keys), never a measured number, so that a change of the library that breaks one fails here.

- finetune/: ``footage_from_dataset.py`` (2 training scenes of tiny_dataset), ``pose_overfit.py``
  (a depthnet-tiny checkpoint, 0 steps: one update), ``photometric_landscape.py`` (gap 1),
  ``smooth_scale.py`` (1 scene), ``loss_floor.py`` (tiny_dataset's training sequences, one
  checkpoint);
- reference/unsupervised/: ``harness.py prepare`` (the author's layout of rotating_dataset),
  ``convert`` (author-style checkpoints built here from our depthnet-unsup's state_dict: the
  ``module.`` prefix, ``conv<i>.0`` and the six outputs per frame of the author's PoseNet),
  ``curves`` (our steps.csv of a 2-step run, an author log written here) and ``train``, which runs
  ``launcher.py`` under this Python on a stub of the author's checkout (its ``logger``,
  ``utils`` and ``train_img_pairs.py`` reduced to the calls the launcher substitutes);
- flight/``failure_frames.py``: a 5-step ``fly`` run (analytic renderer, constant depth)
  replayed through Blender with a depthnet-tiny checkpoint;
- toy/``time_threads.py`` and ``time_old_new.py`` (the "old tree" a copy of this one's
  ``benchmark``), generator-speed/``levers.py``: one step or scene per timing, 64 or 16 px;
- unsup-128/``loss_at_candidates.py``: a 1-step depthnet-unsup-tiny run on tiny_dataset
  (``--known-motion``) and on rotating_dataset (``--pose orientation``), 8 windows;
  ``pretrained_start.py``: the untrained depthnet-tiny checkpoint on tiny_dataset, 4 windows;
  ``rotating_pose_control.py``: rotating_dataset's training scene, 2 steps;
  ``pose_generalisation.py``: its training and test scenes, 2 steps, frames as they are and
  stabilised; ``curve.py`` reads only committed CSV files: its table must equal the committed
  ``learning_curve.md``, and its trend is checked on an exact geometric series.

Not covered: the author's own code (github.com/ClementPinard/unsupervised-depthnet) is not on
this machine (offline), so ``harness.py verify`` (it imports the author's ``models``) is not run,
and ``train``/``launcher.py`` run only against the stub: whether the substitutions still fit the
author's current ``train_img_pairs.py`` is not checked. ``generator-speed/interleave.sh`` is a
shell script comparing two trees, not a Python script of the library.

Tests that render (or use a rendering fixture) carry ``render``; ``launcher`` needs neither
Blender nor a dataset.
"""

from __future__ import annotations

import csv
import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from test_bench_hardening import write_checkpoint

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path("docs/results")
NUMBER = r"-?[\d.]+"


def run_script(script: str, *args: object, timeout: float = 300) -> str:
    """``python docs/results/SCRIPT ARGS`` from the repository root; its stdout (exit 0)."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    proc = subprocess.run(
        [sys.executable, str(RESULTS / script), *map(str, args)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    assert proc.returncode == 0, f"{script} {args}:\n{proc.stdout}\n{proc.stderr}"
    return proc.stdout


def run_bench(*args: object) -> None:
    """``stillbox-bench ARGS`` in a subprocess (exit 0)."""
    proc = subprocess.run(
        [sys.executable, "-m", "benchmark.cli", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr


def lines_of(out: str) -> list[str]:
    return [line for line in out.splitlines() if line.strip()]


@pytest.fixture(scope="module")
def tiny_ckpt(tmp_path_factory) -> Path:
    """An untrained depthnet-tiny checkpoint for 64 px frames (fly's and eval's camera check)."""
    camera = {"width": 64, "height": 64, "fov_deg": 90.0}
    return write_checkpoint(tmp_path_factory.mktemp("ck") / "tiny.pt", camera=camera)


# ---------------------------------------------------------------- finetune/


def test_footage_from_dataset(tiny_dataset, tmp_path):
    """OUT/frames/NNNNNN.png in order and OUT/poses.csv (t,x,y,z), one row per frame; the first
    frame of the second scene repeats the last position (the camera hovers between scenes)."""
    from stillbox_gen.dataset import Dataset

    out = tmp_path / "footage"
    printed = run_script("finetune/footage_from_dataset.py", tiny_dataset, "train", out, 2)
    scenes = Dataset(tiny_dataset).scenes("train")[:2]
    n = sum(s.frames for s in scenes)
    frames = out / "frames"
    assert printed.strip() == f"{n} frames of 2 scenes in {frames}, poses in {out / 'poses.csv'}"
    assert sorted(p.name for p in frames.iterdir()) == [f"{i:06d}.png" for i in range(n)]
    rows = list(csv.reader((out / "poses.csv").read_text().splitlines()))
    assert rows[0] == ["t", "x", "y", "z"] and len(rows) == n + 1
    values = np.array(rows[1:], float)
    assert (values[0] == 0).all() and (np.diff(values[:, 0]) > 0).all()
    first = scenes[0].frames
    np.testing.assert_array_equal(values[first, 1:], values[first - 1, 1:])


def test_pose_overfit(tiny_ckpt, tiny_dataset):
    """One update (STEPS 0): the line printed every 25 steps. tiny_dataset's few training
    windows give the batch of 8 windows closer than one in 20."""
    out = run_script("finetune/pose_overfit.py", tiny_ckpt, tiny_dataset, "1e-3", 0)
    assert re.fullmatch(rf"step +0  photometric {NUMBER}  cosine {NUMBER}", out.strip()), out


def test_photometric_landscape(tiny_dataset):
    """The table of candidates against the truth, one gap (MAX_GAP 1): header, separator, the
    truth first at +0 and the candidates the README's table quotes."""
    from stillbox_gen.dataset import Dataset

    out = lines_of(run_script("finetune/photometric_landscape.py", tiny_dataset, 1))
    pairs = 2 * len(Dataset(tiny_dataset).scenes())  # frames 3 and 5 of each scene
    assert out[0] == f"{tiny_dataset}: {pairs} (target, reference) pairs, 64x64 px, target frame 4"
    assert out[1] == "| depth | MAE m | gap 1: loss (vs truth) |"
    assert out[2] == "|---|---|---|"
    rows = [
        re.fullmatch(rf"\| (.+) \| ({NUMBER}) \| {NUMBER} \(([+-][\d.]+)\) \|", r) for r in out[3:]
    ]
    assert all(rows), out[3:]
    names = [m[1] for m in rows]
    assert names[0] == "truth" and float(rows[0][2]) == 0 and float(rows[0][3]) == 0
    quoted = ["truth x1.1", "beyond 20 m: x1.5", "beyond 20 m: x3", "beyond 20 m: 100 m"]
    quoted += ["below 10 m: x1.3", "blur 3x3", "median constant", "truth at 1/4 resolution"]
    assert set(quoted) <= set(names), names


def test_smooth_scale(tiny_dataset):
    out = lines_of(run_script("finetune/smooth_scale.py", tiny_dataset, 1))
    assert out[0] == f"{tiny_dataset}: 1 scenes, frame 4, 64 px"
    assert out[1].split() == ["candidate", "raw", "normalised"]
    names = []
    for line in out[2:5]:
        m = re.fullmatch(rf"(.+?) +({NUMBER}) +({NUMBER})", line)
        assert m, line
        names.append(m[1])
    assert names == ["truth", "truth x 2", "beyond 20 m -> 100 m"]
    assert re.fullmatch(rf"truth raw / normalised: {NUMBER}", out[5]) and len(out) == 6


def test_loss_floor(tiny_dataset, tiny_ckpt):
    """The truth's (× 1, 2, 0.5) and a checkpoint's photometric and smooth terms."""
    out = lines_of(run_script("finetune/loss_floor.py", tiny_dataset, tiny_ckpt))
    assert re.fullmatch(
        rf"{re.escape(str(tiny_dataset))}: \d+ training sequences; photometric, smooth "
        rf"\(λ = {NUMBER}\)",
        out[0],
    ), out[0]
    for line, name in zip(out[1:4], ("truth", "truth x 2", "truth x 0.5"), strict=True):
        assert re.fullmatch(rf"{re.escape(name)} +{NUMBER} {NUMBER}", line), line
    assert re.fullmatch(
        rf"{re.escape(str(tiny_ckpt))} +{NUMBER} {NUMBER}  median depth / truth {NUMBER}",
        out[4],
    ), out[4]
    assert len(out) == 5


# ---------------------------------------------------------------- reference/unsupervised/

HARNESS = "reference/unsupervised/harness.py"


def test_harness_prepare_writes_the_authors_layout(rotating_dataset, tmp_path):
    """train.txt/val.txt naming a folder each, whose metadata.json holds the camera (fov,
    resolution) and one record per scene of that split with the original StillBox keys; the
    frames are DATA's own files, the val scenes' depth .npy files beside the metadata."""
    from stillbox_gen.dataset import Dataset

    layout = tmp_path / "author-layout"
    counts = json.loads(run_script(HARNESS, "prepare", rotating_dataset, layout))
    ds = Dataset(rotating_dataset)
    assert counts == {split: len(ds.scenes(split)) for split in ("train", "val")}
    for split in ("train", "val"):
        assert (layout / f"{split}.txt").read_text() == f"{split}\n"
        meta = json.loads((layout / split / "metadata.json").read_text())
        assert set(meta["args"]) == {"fov", "resolution"}
        assert meta["args"]["resolution"] == [64, 64]
        assert len(meta["scenes"]) == counts[split]
        for record in meta["scenes"]:
            keys = {"imgs", "depth", "speed", "time_step", "orientation", "length", "index"}
            assert set(record) == keys
            scene = ds.scene(record["index"])
            assert record["imgs"] == [str(p.resolve()) for p in scene.rgb]
            assert record["length"] == scene.frames == len(record["orientation"])
            assert len(record["depth"]) == (scene.frames if split == "val" else 0)
            for name in record["depth"]:
                assert np.load(layout / split / name).shape == (64, 64)


def _author_checkpoints(tmp_path: Path, bn: bool = True) -> tuple[Path, Path, dict]:
    """The author's two checkpoints (DataParallel's ``module.`` keys; PoseNet's ``conv<i>.0``
    and 6 outputs per frame, translation first) holding the weights of a seeded depthnet-unsup
    of ours, and that network's state_dict."""
    from benchmark.core import registry

    torch.manual_seed(0)
    ours = registry.build_model("depthnet-unsup").state_dict()
    depth = {f"module.{k.removeprefix('depth.')}": v for k, v in ours.items() if k[:6] == "depth."}
    pose = {}
    for i in range(1, 8):
        for p in ("weight", "bias"):
            pose[f"module.conv{i}.0.{p}"] = ours[f"pose.encoder.{2 * (i - 1)}.{p}"]
    w, b = ours["pose.predict.weight"], ours["pose.predict.bias"]
    frames = w.shape[0] // 3
    rotation_w = torch.randn(frames, 3, *w.shape[1:])
    pose["module.pose_pred.weight"] = torch.cat([w.view(frames, 3, *w.shape[1:]), rotation_w], 1)
    pose["module.pose_pred.weight"] = pose["module.pose_pred.weight"].flatten(0, 1)
    pose["module.pose_pred.bias"] = torch.cat([b.view(frames, 3), torch.randn(frames, 3)], 1)
    pose["module.pose_pred.bias"] = pose["module.pose_pred.bias"].flatten()
    tmp_path.mkdir(exist_ok=True)
    d_path, p_path = tmp_path / "epoch1_depthnet.pth.tar", tmp_path / "epoch1_posenet.pth.tar"
    meta = {"epoch": 1, "nominal_displacement": 0.3}
    torch.save({"state_dict": depth, "bn": bn, **meta}, d_path)
    torch.save({"state_dict": pose, **meta}, p_path)
    return d_path, p_path, ours


def test_harness_convert_maps_the_authors_checkpoints_to_ours(rotating_dataset, tmp_path):
    """The converted checkpoint loads into depthnet-unsup for DATA's camera, with the README's
    mappings: conv1 × 0.4 (DepthNet's and PoseNet's), the finest prediction's bias + 0.01, the
    translation rows of the author's PoseNet. A DepthNet trained without --bn depth is refused."""
    from benchmark.core import registry
    from benchmark.core.checkpoint import load_checkpoint, load_weights
    from benchmark.core.data import camera_of

    d_path, p_path, ours = _author_checkpoints(tmp_path)
    dest = tmp_path / "author.pt"
    assert run_script(HARNESS, "convert", d_path, p_path, rotating_dataset, dest) == ""
    ck = load_checkpoint(dest)
    load_weights(registry.build_model(ck["model_name"]), ck, "ckpt", dest, ck["model_name"])
    assert ck["model_name"] == "depthnet-unsup" and ck["nominal_displacement"] == 0.3
    assert ck["camera"] == camera_of(rotating_dataset) and ck["config"]["pose"] == "orientation"
    got = ck["model"]
    assert set(got) == set(ours)
    for key in ("depth.conv1.0.weight", "pose.encoder.0.weight"):
        torch.testing.assert_close(got[key], ours[key] * 0.4)
    bias = "depth.predict_depth2.bias"
    torch.testing.assert_close(got[bias], ours[bias] + 0.01)
    for key in ("depth.conv2.0.weight", "pose.encoder.2.weight", "pose.predict.bias"):
        torch.testing.assert_close(got[key], ours[key], rtol=0, atol=0)
    torch.testing.assert_close(
        got["pose.predict.weight"], ours["pose.predict.weight"], rtol=0, atol=0
    )

    d_nobn, _, _ = _author_checkpoints(tmp_path / "nobn", bn=False)
    proc = subprocess.run(
        [sys.executable, str(RESULTS / HARNESS), "convert", d_nobn, p_path, rotating_dataset,
         tmp_path / "refused.pt"],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 1 and "not trained with --bn depth" in proc.stderr, proc.stderr
    assert not (tmp_path / "refused.pt").exists()


def test_harness_curves(rotating_dataset, tmp_path):
    """loss_ours.csv and loss_author.csv (step, loss, photometric, smooth) and loss_curves.png
    from our run's steps.csv (a 2-step depthnet-unsup run, every step logged as run.sh does)
    and an author's progress_log_full.csv (tab-separated, a header, 3 columns)."""
    ours = tmp_path / "ours"
    run_bench(
        *("run", "depthnet-unsup-tiny", "--pose", "orientation", "--data", rotating_dataset),
        *("--batch-size", 2, "--max-steps", 2, "--threads", 1, "--log-every", 1, "--quiet"),
        *("--out", ours),
    )
    log = tmp_path / "progress_log_full.csv"
    rows = [f"{1 / (i + 1)}\t{0.8 / (i + 1)}\t{0.1 / (i + 1)}" for i in range(20)]
    log.write_text("train_loss\tphoto_loss\texplainability_loss\tsmooth_loss\n" + "\n".join(rows))
    out = tmp_path / "curves"
    run_script(HARNESS, "curves", ours / "steps.csv", log, out)
    expected = {"ours": 2, "author": 20}
    for who, n in expected.items():
        with open(out / f"loss_{who}.csv") as f:
            read = list(csv.DictReader(f))
        assert list(read[0]) == ["step", "loss", "photometric", "smooth"]
        assert [int(r["step"]) for r in read] == list(range(1, n + 1))
        assert all(np.isfinite(float(r["loss"])) for r in read)
    assert (out / "loss_curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


#: A stub of the author's checkout: the three names launcher.py substitutes, used as the
#: author's train_img_pairs.py uses them (utils calls matplotlib.cm.get_cmap on import).
STUB = {
    "logger.py": """
class TermLogger:
    def __init__(self, n_epochs, train_size, valid_size):
        raise RuntimeError("TermLogger needs a terminal")
""",
    "utils.py": """
import json
from pathlib import Path

import matplotlib.cm

COLORMAP = matplotlib.cm.get_cmap("magma")


def save_checkpoint(save_path, depthnet_state, posenet_state, is_best,
                    filename="checkpoint.pth.tar"):
    for prefix, state in (("depthnet", depthnet_state), ("posenet", posenet_state)):
        (Path(save_path) / f"{prefix}_{filename}").write_text(json.dumps(state))
""",
    "train_img_pairs.py": """
import json
import sys
from pathlib import Path

import logger
import utils

log = logger.TermLogger(n_epochs=2, train_size=3, valid_size=1)
log.epoch_bar.start()
log.reset_train_bar()
log.train_bar.update(1)
log.train_writer.write("Train: loss 1.0\\r")
log.valid_writer.write("Valid: error 2.0\\n")
save = Path("checkpoints")
save.mkdir()
for epoch in (1, 2):
    utils.save_checkpoint(save, {"epoch": epoch, "net": "depth"}, {"epoch": epoch, "net": "pose"},
                          epoch == 1)
print("argv " + json.dumps(sys.argv[1:]))
""",
}


def test_harness_train_runs_the_launcher_on_a_checkout(tmp_path):
    """``harness.py train CODE PYTHON LAYOUT OUT -- FLAGS`` runs launcher.py (here under this
    Python, on STUB): the author's script gets LAYOUT and FLAGS, its logger writes plain lines,
    ``cm.get_cmap`` resolves, every epoch's checkpoints are kept in OUT/epochs; the command is
    recorded in OUT/command.txt. A folder without train_img_pairs.py is refused."""
    code = tmp_path / "unsupervised-depthnet"
    code.mkdir()
    for name, text in STUB.items():
        (code / name).write_text(text.lstrip())
    layout, out = tmp_path / "layout", tmp_path / "author"
    layout.mkdir()
    flags = ["--dataset-format", "StillBox", "-b", "16"]
    printed = run_script(HARNESS, "train", code, sys.executable, layout, out, "--", *flags)
    assert lines_of(printed) == [
        "Train: loss 1.0",
        "Valid: error 2.0",
        "argv " + json.dumps([str(layout.resolve()), *flags]),
    ]
    assert (out / "command.txt").read_text().split() == [
        sys.executable, str(ROOT / RESULTS / "reference/unsupervised/launcher.py"),
        str(code), str(out / "epochs"), "--", str(layout), *flags,
    ]  # fmt: skip
    for epoch in (1, 2):
        for net, prefix in (("depth", "depthnet"), ("pose", "posenet")):
            kept = json.loads((out / "epochs" / f"epoch{epoch}_{prefix}.pth.tar").read_text())
            assert kept == {"epoch": epoch, "net": net}
    assert (out / "checkpoints" / "depthnet_checkpoint.pth.tar").is_file()

    proc = subprocess.run(
        [sys.executable, str(RESULTS / HARNESS), "train", layout, sys.executable, layout,
         tmp_path / "x", "--"],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 1 and "not a checkout of" in proc.stderr, proc.stderr


# ---------------------------------------------------------------- flight/


@pytest.mark.render
def test_failure_frames(tiny_ckpt, tmp_path):
    """A 5-step episode flown without Blender (analytic renderer, constant depth), replayed
    through Blender with the checkpoint to its last frame (SECONDS 0): the figure and its line."""
    run = tmp_path / "fly"
    run_bench(
        *("fly", "--depth", "constant", "--constant-depth", 10, "--renderer", "analytic"),
        *("--episodes", 1, "--max-steps", 5, "--quiet", "--out", run),
    )
    record = json.loads((run / "episodes" / "000000.json").read_text())
    png = tmp_path / "episode_0.png"
    out = run_script("flight/failure_frames.py", run, 0, tiny_ckpt, png, 0)
    shown = len(record["positions"]) - 2  # the last pose rendered
    assert out.strip() == f"{png}: frame {shown} of episode 0 ({record['outcome']})"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# ---------------------------------------------------------------- toy/ and generator-speed/


def test_time_threads(toy_data):
    """One round of one step with 1 and with 2 kernel threads: a line per thread count."""
    data = toy_data["flower"].parent
    out = lines_of(run_script("toy/time_threads.py", data, "diffusion", 1, 1))
    for line, n in zip(out, (1, 2), strict=True):
        assert re.fullmatch(
            rf"{n} thread\(s\): wall s/it median {NUMBER} min {NUMBER} \(rounds {NUMBER}\), "
            rf"CPU s/it {NUMBER}",
            line,
        ), line


def test_time_old_new(toy_data, tmp_path):
    """The README's "Time" table rows (photometric alone, each smooth loss, one ODM call; old
    and new CPU s / it, their ratio, ms per map) and the extrapolated study of both trees, the
    old tree a copy of this one's ``benchmark`` (its numba caches kept: no compilation)."""
    from benchmark.unsupervised import toy

    old = tmp_path / "old"
    shutil.copytree(ROOT / "benchmark", old / "benchmark_old")
    data = toy_data["flower"].parent
    out = lines_of(run_script("toy/time_old_new.py", old, data, 1, 1))
    labels = ["photometric alone", *toy.StudyConfig().losses, "one ODM call (both references)"]
    cells = rf" \| {NUMBER}" * 5
    for line, label in zip(out, labels, strict=False):
        assert re.fullmatch(rf"\| {re.escape(label)}{cells} \|", line), line
    assert len(out) == len(labels) + 2
    for line, tree in zip(out[-2:], ("old", "new"), strict=True):
        assert re.fullmatch(
            rf"{tree}: extrapolated full study {NUMBER} CPU-hours, {NUMBER} h on 2 cores", line
        ), line


@pytest.mark.render
def test_levers():
    """One 16 px scene per lever and its 256-sample reference: the header and a line per lever
    with its phases, bytes and PSNRs."""
    out = lines_of(
        run_script(
            "generator-speed/levers.py",
            *("--res", 16, "--scenes", 1, "--threads", 1),
            *("--levers", "base,samples_1", "--reference-scenes", 1),
        )
    )
    assert out[0] == "16 px, 1 scenes, 1 Cycles threads; ms per frame:"
    assert len(out) == 3
    for line, (lever, same) in zip(out[1:], (("base", "1/1"), ("samples_1", r"\d/1")), strict=True):
        n = rf" +{NUMBER}"
        assert re.fullmatch(
            rf"{lever} +total{n}  build{n}  sync{n}  sampling{n}  result{n}  same bytes as base "
            rf"{same}  PSNR vs base +({NUMBER}|inf) dB  PSNR vs 256 samples{n} dB",
            line,
        ), line


# ---------------------------------------------------------------- unsup-128/


def _photometric_terms(out: str) -> dict[tuple[str, str], float]:
    """loss_at_candidates.py's rows: (depth, translations) -> photometric term."""
    rows = {}
    for line in lines_of(out)[3:]:
        depth, motion, photo, smooth, loss = (c.strip() for c in line.strip("|").split("|"))
        assert all(re.fullmatch(NUMBER, v) for v in (photo, smooth, loss)), line
        assert float(loss) == pytest.approx(float(photo) + float(smooth), abs=2e-4), line
        rows[(depth, motion)] = float(photo)
    return rows


@pytest.mark.render
@pytest.mark.parametrize("rotating", [False, True])
def test_loss_at_candidates(tiny_dataset, rotating_dataset, tmp_path, rotating):
    """A 1-step depthnet-unsup-tiny run (--known-motion on stabilised data, --pose orientation
    on rotating data), then the table of eq. 5.5 at the candidates: every (depth, translations)
    row, and the true depth's photometric term lower with the true motion than with PoseNet's
    and than the constants' with the true motion (a wrong pose convention in the script would
    lose that; the smooth term can tip the total on these 2-window sets)."""
    data = rotating_dataset if rotating else tiny_dataset
    mode = ("--pose", "orientation") if rotating else ("--known-motion",)
    run_bench(
        *("run", "depthnet-unsup-tiny", *mode, "--data", data, "--batch-size", 2),
        *("--max-steps", 1, "--threads", 1, "--quiet", "--out", tmp_path / "run"),
    )
    ckpt = tmp_path / "run" / "checkpoints" / "last.pt"
    out = run_script("unsup-128/loss_at_candidates.py", data, ckpt, 4, 8)
    head = lines_of(out)[:3]
    pose = "orientation" if rotating else "translation"
    assert re.fullmatch(rf"{re.escape(str(data))}: \d+ windows, .*last\.pt \({pose}\)", head[0])
    assert head[1] == "| depth | translations | photometric | λ·smooth | loss |"
    rows = _photometric_terms(out)
    depths = ["the checkpoint's depth", "truth", "truth × 1.5", "truth / 1.5"]
    depths += ["truth, beyond 20 m set to 100 m", "median constant"]
    depths += ["flat 10 m (DepthNet at step 0)", "flat 100 m"]
    assert list(rows) == [(d, m) for m in ("true", "PoseNet's") for d in depths]
    truth = rows[("truth", "true")]
    assert truth < rows[("truth", "PoseNet's")]
    assert truth < rows[("median constant", "true")] and truth < rows[("flat 100 m", "true")]


@pytest.mark.render
def test_pretrained_start(tiny_dataset, tiny_ckpt):
    """A supervised checkpoint's maps and eq. 5.5's terms at step 0, in both BatchNorm modes."""
    out = lines_of(run_script("unsup-128/pretrained_start.py", tiny_dataset, tiny_ckpt, 2, 4))
    assert re.fullmatch(
        rf"{re.escape(str(tiny_dataset))}: \d+ windows, .* \(depthnet-tiny\)", out[0]
    )
    assert len(out) == 5
    for mode, maps, terms in ((("train", *out[1:3])), ("eval", *out[3:5])):
        scale = rf"1/\d+: median {NUMBER} m, {NUMBER}% below 0.1 m"
        assert re.fullmatch(rf"{mode} mode: {scale}(; {scale})*", maps), maps
        assert re.fullmatch(
            rf"{mode} mode: photometric {NUMBER}, λ·smooth {NUMBER} \(every scale\); "
            rf"photometric {NUMBER} \(finest map alone\)",
            terms,
        ), terms


@pytest.mark.render
@pytest.mark.parametrize("with_ckpt", [False, True])
def test_rotating_pose_control(rotating_dataset, tiny_ckpt, with_ckpt):
    """PoseNet against the true depth of rotating windows, or a frozen checkpoint's: a header
    and the cosine lines."""
    ckpt = [tiny_ckpt] if with_ckpt else []
    script = "unsup-128/rotating_pose_control.py"
    out = lines_of(run_script(script, rotating_dataset, 2, 1, *ckpt))
    source = f"depth of {tiny_ckpt}" if with_ckpt else "true depth"
    assert re.fullmatch(
        rf"{re.escape(str(rotating_dataset))}: \d+ windows of 1 scenes, --pose orientation, "
        + re.escape(source)
        + ", PoseNet width 0.25, Adam 0.001",
        out[0],
    ), out[0]
    assert [line.split(":")[0] for line in out[1:]] == ["after 0 steps", "after 2 steps"]
    for line in out[1:]:
        assert re.fullmatch(rf"after \d steps: loss {NUMBER}, pose cosine {NUMBER}", line), line


@pytest.mark.render
@pytest.mark.parametrize("stabilised", [False, True])
def test_pose_generalisation(rotating_dataset, stabilised):
    """PoseNet over a training split against the true depth, scored on test windows: a header,
    the cosine before training and after each step."""
    how = ["stabilised"] if stabilised else []
    out = lines_of(
        run_script("unsup-128/pose_generalisation.py", rotating_dataset, 2, 1e-3, 1, *how)
    )
    reads = "frames stabilised to the last one" if stabilised else "the rotating frames"
    assert re.fullmatch(
        rf"{re.escape(str(rotating_dataset))}: \d+ training windows of 1 scenes, \d+ test "
        rf"windows of 1 scenes; PoseNet width 1 reading {reads}, Adam 0.001, true depth",
        out[0],
    ), out[0]
    assert re.fullmatch(rf"after 0 steps: test cosine {NUMBER}", out[1]), out[1]
    assert len(out) == 4
    for k, line in enumerate(out[2:], 1):
        pattern = rf"after {k} steps: training cosine {NUMBER}, test cosine {NUMBER} \(\d+ s\)"
        assert re.fullmatch(pattern, line), line


def test_learning_curve_is_the_committed_one(tmp_path):
    """curve.py on the committed results.csv files writes the committed learning_curve.md (the
    page's numbers come from those files) and its figure."""
    out = run_script("unsup-128/curve.py", tmp_path)
    assert "learning_curve.md" in out
    committed = (ROOT / RESULTS / "unsup-128" / "learning_curve.md").read_text()
    assert (tmp_path / "learning_curve.md").read_text() == committed
    assert (tmp_path / "learning_curve.png").stat().st_size > 10_000


def test_learning_curve_trend_against_a_stepped_geometric_series():
    """curve.py's trend on an exact geometric approach to 10 m (MAE = 10 + 60·0.9^i every 100
    steps): ratio 0.9, asymptote 10 m, and the steps to the constant (30 m) and to −25 % of it
    (22.5 m) counted by stepping the series on; a target below the asymptote is never reached,
    and a series that got worse has no trend."""
    spec = importlib.util.spec_from_file_location("curve", ROOT / RESULTS / "unsup-128/curve.py")
    curve = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(curve)

    def series(constant: float) -> list[dict]:
        return [
            {"steps": 100 * i, "mae": 10 + 60 * 0.9**i, "constant": constant} for i in range(1, 8)
        ]

    def stepped(target: float) -> int:
        i = 7
        while 10 + 60 * 0.9**i > target:
            i += 1
        return 100 * (i - 7)

    t = curve.trend(series(30.0))
    assert t["ratio"] == pytest.approx(0.9) and t["asymptote"] == pytest.approx(10.0)
    assert t["steps"] == 700 and t["mae"] == pytest.approx(10 + 60 * 0.9**7)
    assert t["to_constant"] == stepped(30.0) > 0
    assert t["to_goal"] == stepped(22.5) > t["to_constant"]
    assert curve.trend(series(12.0))["to_goal"] is None  # 9 m: below the asymptote
    worse = series(30.0)
    worse[-1]["mae"] = worse[-2]["mae"] + 1
    assert curve.trend(worse) is None


@pytest.mark.parametrize("run", ["orientation-recipe", "orientation-pose-lr"])
def test_collect_gives_back_the_committed_outputs_of_a_run(tmp_path, run):
    """collect.py on a run.sh folder rebuilt from a committed run (each scored epoch's
    eval-sequences rows with the constant plane, as eval-sequences writes them) gives back the
    committed results.csv, results-epoch_K.md and logs byte for byte: the merge is the one the
    page's numbers went through."""
    committed = ROOT / RESULTS / "unsup-128" / run
    runs = tmp_path / "orientation"
    (runs / "O").mkdir(parents=True)
    for name in ("config.json", "metrics.csv", "steps.csv"):
        shutil.copyfile(committed / name, runs / "O" / name)
    with open(committed / "results.csv", newline="") as f:  # csv's line ends: CR LF
        header, *rows = f.read().splitlines(keepends=True)
    model = header.split(",").index("model")
    constant = [r for r in rows if r.split(",")[model] == "constant"]
    epochs = sorted(int(p.stem.split("_")[1]) for p in committed.glob("results-epoch_*.md"))
    for k in epochs:
        own = [r for r in rows if f"/kept/epoch_{k}.pt," in r]
        assert own, k
        folder = runs / f"eval-epoch_{k}"
        folder.mkdir()
        with open(folder / "results.csv", "w", newline="") as f:
            f.writelines([header, *constant, *own])
        shutil.copyfile(committed / f"results-epoch_{k}.md", folder / "results.md")
    out = tmp_path / "out"
    said = run_script("unsup-128/collect.py", runs, out)
    assert said.strip() == f"{out}: epochs {', '.join(map(str, epochs))}"
    for path in committed.iterdir():
        assert (out / path.name).read_bytes() == path.read_bytes(), path.name
    assert len(list(out.iterdir())) == len(list(committed.iterdir()))


def test_collect_refuses_a_folder_that_is_not_a_run_in_one_line(tmp_path):
    proc = subprocess.run(
        [sys.executable, str(RESULTS / "unsup-128/collect.py"), str(tmp_path), str(tmp_path / "o")],
        cwd=ROOT, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert proc.returncode == 1 and proc.stdout == ""
    assert (
        proc.stderr.strip()
        == f"collect.py: {tmp_path / 'O'}: no metrics.csv (not a run.sh run folder)"
    )
    assert not (tmp_path / "o").exists()
