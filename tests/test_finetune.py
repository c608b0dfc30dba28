"""``stillbox-bench finetune`` (issue 24 part 4, thesis §5.4.5) on a tiny real network and a tiny
generated footage (test_infer's panning texture, 64×64, 8 frames): the run folder, its best.pt
loading in ``infer``, the pose warm-up freezing the DepthNet, exact resume, one-line errors with
nothing written, and the footage's sequences (stride, moving stretches, intrinsics) on numbers."""

from __future__ import annotations

import csv
import json
import math
import signal
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import invoke_main
from test_bench_hardening import assert_bench_error
from test_infer import SIZE, _checkpoint, _frames, _write_folder

from benchmark import cli
from benchmark.core import registry
from benchmark.core.checkpoint import load_checkpoint, load_weights
from benchmark.core.footage import Crop
from benchmark.core.posenet import DepthPoseNet
from benchmark.engine.loop import NonFiniteLoss
from benchmark.engine.network import depth_network
from benchmark.unsupervised.finetune import FinetuneOptions, Finetuner
from benchmark.unsupervised.footage_sequences import frame_stride, moving_stretches, prepared_K

#: the footage moves 0.3 m a frame (3 m/s at 10 frames/s); the checkpoint's d0 is 0.3 m for a
#: shift of 3 frames: 0.1 m a training frame, so every frame is kept (stride 1): 4 sequences
MOTION = ("--speed", 3, "--fps", 10)
TINY = ("--batch-size", 2, "--threads", 1, "--quiet")


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("finetune")
    (d / "notes.txt").write_text("not a checkpoint")
    return {
        "ckpt": _checkpoint(d / "tiny.pt", "depthnet-tiny"),
        "flow_ckpt": _checkpoint(d / "flow.pt", "flownets-flow-tiny"),
        "folder": _write_folder(d / "pngs", _frames()),
        "short": _write_folder(d / "short", _frames()[:4]),
        "text": d / "notes.txt",
    }


def finetune(files: dict, out: Path, *args: object, ok: bool = True):
    proc = invoke_main(
        cli.main, "finetune", "--ckpt", files["ckpt"], "--input", files["folder"], "--out", out,
        *MOTION, *TINY, *args,
    )  # fmt: skip
    if ok:
        assert proc.returncode == 0, proc.stderr
    return proc


def _steps(out: Path) -> list[dict]:
    return list(csv.DictReader((out / "steps.csv").open()))


def _weights(path: Path) -> dict[str, torch.Tensor]:
    return torch.load(path, weights_only=True)["model"]


def test_finetune_writes_a_depth_checkpoint_that_infer_loads(files, tmp_path):
    out = tmp_path / "ft"
    proc = finetune(files, out, "--steps", 3, "--pose-warmup", 1, "--log-every", 1)
    assert "Fine-tuned 3 steps" in proc.stdout
    assert str(out / "checkpoints" / "best.pt") in proc.stdout
    rows = _steps(out)
    assert [int(r["step"]) for r in rows] == [1, 2, 3]
    assert [r["phase"] for r in rows] == ["pose-warmup", "joint", "joint"]
    assert all(np.isfinite(float(r["loss"])) for r in rows)
    # the default λ is 0 (finetune.SMOOTH_WEIGHT): the loss is the photometric term alone
    assert json.loads((out / "config.json").read_text())["smooth_weight"] == 0.0
    assert all(float(r["smooth"]) == 0 and r["loss"] == r["photometric"] for r in rows)
    best = torch.load(out / "checkpoints" / "best.pt", weights_only=True)
    assert best["model_name"] == "depthnet-tiny" and "optimizer" not in best and "pose" not in best
    assert best["nominal_displacement"] == 0.3 and best["shift"] == 3
    assert best["camera"] == {"width": SIZE, "height": SIZE, "fov_deg": 90.0}
    last = torch.load(out / "checkpoints" / "last.pt", weights_only=True)
    assert {"optimizer", "pose", "state"} <= set(last) and last["state"]["global_step"] == 3
    source = _weights(files["ckpt"])
    changed = [k for k in source if not torch.equal(source[k], best["model"][k])]
    assert changed  # the joint steps moved the DepthNet
    ck = load_checkpoint(out / "checkpoints" / "best.pt", "ckpt")  # eval's loading
    load_weights(registry.build_model(ck["model_name"]), ck, "ckpt", "best.pt", ck["model_name"])
    model, scale, info = depth_network(out / "checkpoints" / "best.pt")  # infer's loader
    assert scale.d0 == 0.3 and info["model_name"] == "depthnet-tiny"
    depth = tmp_path / "depth"
    proc = invoke_main(
        cli.main, "infer", "--ckpt", out / "checkpoints" / "best.pt", "--input", files["folder"],
        "--out", depth, *MOTION, "--quiet",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert len(list((depth / "depth").glob("*.npy"))) == 7  # every frame but the first


def test_pose_warmup_freezes_the_depthnet_then_trains_it(files, tmp_path):
    """During the warm-up the DepthNet's weights and BatchNorm statistics stay the checkpoint's
    while PoseNet learns; the first joint step changes the weights, never the statistics (the
    network trained is the one eval and infer run)."""
    o = FinetuneOptions(
        out=tmp_path / "ft", ckpt=files["ckpt"], input=files["folder"], speed=3.0, fps=10.0,
        steps=3, pose_warmup=2, batch_size=2, ckpt_every=0, log_every=1000, quiet=True,
    )  # fmt: skip
    tuner = Finetuner(o)
    tuner.setup()
    assert isinstance(tuner.net, DepthPoseNet)
    copy = lambda m: {k: v.clone() for k, v in m.state_dict().items()}  # noqa: E731
    depth0, pose0 = copy(tuner.net.depth), copy(tuner.net.pose)
    assert all(torch.equal(depth0[k], v) for k, v in _weights(files["ckpt"]).items())
    batch = tuner.data.batch([0, 1], 0)

    def one_step() -> str:  # as the engine's loop makes it: the step, then the step count
        tuner.train_step(batch)
        tuner.state["global_step"] += 1
        return tuner.train_step.phase

    for _ in range(2):
        assert one_step() == "pose-warmup"
        assert all(torch.equal(depth0[k], v) for k, v in tuner.net.depth.state_dict().items())
    assert not any(p.requires_grad for p in tuner.net.depth.parameters())
    assert any(not torch.equal(pose0[k], v) for k, v in tuner.net.pose.state_dict().items())
    assert one_step() == "joint"
    depth = tuner.net.depth.state_dict()
    moved = [k for k in depth if not torch.equal(depth0[k], depth[k])]
    assert moved and all(p.requires_grad for p in tuner.net.depth.parameters())
    stats = [k for k in depth if "running" in k or "num_batches" in k]
    assert stats and not any(k in moved for k in stats), moved


def test_resume_continues_as_one_run_and_keeps_its_options(files, tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    finetune(files, a, "--steps", 3, "--pose-warmup", 2, "--log-every", 1)
    finetune(files, a, "--resume", "--steps", 5, "--log-every", 1)
    finetune(files, b, "--steps", 5, "--pose-warmup", 2, "--log-every", 1)
    assert [int(r["step"]) for r in _steps(a)] == [1, 2, 3, 4, 5]
    assert [r["loss"] for r in _steps(a)] == [r["loss"] for r in _steps(b)]
    wa, wb = _weights(a / "checkpoints" / "best.pt"), _weights(b / "checkpoints" / "best.pt")
    assert all(torch.equal(wa[k], wb[k]) for k in wa)
    proc = finetune(files, a, "--resume", "--steps", 6, "--lr", 1e-3, ok=False)
    assert_bench_error(proc, "--lr", "0.0002")
    assert_bench_error(finetune(files, b, "--steps", 6, ok=False), "--out", "--resume")
    assert_bench_error(finetune(files, tmp_path / "none", "--resume", ok=False), "--resume")


def _tuner(files: dict, out: Path, **changes) -> Finetuner:
    o = FinetuneOptions(
        out=out, ckpt=files["ckpt"], input=files["folder"], speed=3.0, fps=10.0, steps=4,
        pose_warmup=1, batch_size=2, ckpt_every=1, log_every=1, quiet=True,
    )  # fmt: skip
    tuner = Finetuner(replace(o, **changes))
    tuner.setup()
    return tuner


def _calls_then(tuner: Finetuner, at: int, then) -> list:
    """Make ``tuner``'s step call ``then(loss)`` on its ``at``-th call; returns the calls."""
    step, calls = tuner.train_step.step.update, []

    def update(batch):
        calls.append(1)
        terms = step(batch)
        return {**terms, "loss": then(terms["loss"])} if len(calls) == at else terms

    tuner.train_step.step.update = update
    return calls


def test_a_nan_loss_stops_fine_tuning_keeping_the_last_good_checkpoints(files, tmp_path):
    """The engine's loop (engine.loop) runs fine-tuning: a loss that turns NaN at step 3 stops
    it in one line naming that step, and both checkpoints are step 2's, with finite weights."""
    tuner = _tuner(files, tmp_path / "ft")
    _calls_then(tuner, 3, lambda loss: loss * math.nan)
    with pytest.raises(NonFiniteLoss, match=r"^fine-tuning stopped: the loss is nan at step 3 "):
        tuner.fit()
    for name in ("last", "best"):
        ck = torch.load(tmp_path / "ft" / "checkpoints" / f"{name}.pt", weights_only=True)
        assert ck["state"]["global_step"] == 2
        assert all(torch.isfinite(v).all() for v in ck["model"].values() if v.is_floating_point())
    assert [int(r["step"]) for r in _steps(tmp_path / "ft")] == [1, 2]


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_an_interrupted_fine_tuning_resumes_as_one_run(files, tmp_path, sig):
    """Ctrl-C (or SIGTERM) during step 1 of 4 (2 a pass over the footage's 4 sequences): the
    step ends, both checkpoints are saved, then KeyboardInterrupt; --resume then gives the
    steps.csv and weights of an uninterrupted run."""
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    _tuner(files, whole, ckpt_every=0).fit()  # 0: saves at the end and when stopped only

    def interrupt(loss):
        signal.raise_signal(sig)
        return loss

    tuner = _tuner(files, cut, ckpt_every=0)
    _calls_then(tuner, 1, interrupt)
    with pytest.raises(KeyboardInterrupt):
        tuner.fit()
    assert torch.load(cut / "checkpoints" / "last.pt", weights_only=True)["state"] == {
        "epoch": 0, "step_in_epoch": 1, "global_step": 1,
    }  # fmt: skip
    finetune(files, cut, "--resume")
    assert _steps(cut) == _steps(whole)
    for name in ("last", "best"):
        a, b = (
            _weights(whole / "checkpoints" / f"{name}.pt"),
            _weights(cut / "checkpoints" / f"{name}.pt"),
        )
        assert all(torch.equal(a[k], b[k]) for k in a)


def test_resume_keeps_steps_and_intervals_unless_given_again(files, tmp_path):
    """--steps, --log-every and --ckpt-every left out of --resume are the run's, not the
    defaults (which would log every 10th step and train to 1,000 steps)."""
    out = tmp_path / "ft"
    finetune(files, out, "--steps", 2, "--pose-warmup", 1, "--log-every", 1, "--ckpt-every", 1)
    finetune(files, out, "--resume", "--steps", 4)
    assert [int(r["step"]) for r in _steps(out)] == [1, 2, 3, 4]
    config = json.loads((out / "config.json").read_text())
    assert (config["steps"], config["log_every"], config["ckpt_every"]) == (4, 1, 1)
    proc = finetune(files, out, "--resume")  # the run's 4 steps: nothing left to do
    assert "Fine-tuned 4 steps" in proc.stdout and len(_steps(out)) == 4


@pytest.mark.parametrize(
    ("change", "flag"),
    [
        ({"--ckpt": "missing.pt"}, "--ckpt"),
        ({"--ckpt": "text"}, "--ckpt"),
        ({"--ckpt": "flow_ckpt"}, "--ckpt"),
        ({"--input": "missing"}, "--input"),
        ({"--input": "short"}, "--input"),
        ({"--speed": -1}, "--speed"),
        ({"--fps": 0}, "--fps"),
        ({"--batch-size": 10}, "--batch-size"),
        ({"--pose-warmup": -1}, "--pose-warmup"),
        ({"--steps": 0}, "--steps"),
        ({"--smooth-weight": -1}, "--smooth-weight"),
    ],
)
def test_bad_input_is_one_line_and_writes_nothing(files, tmp_path, change, flag):
    args = {"--ckpt": files["ckpt"], "--input": files["folder"], "--speed": 3, "--fps": 10,
            "--batch-size": 2, "--steps": 2}  # fmt: skip
    for k, v in change.items():
        args[k] = files.get(v, tmp_path / str(v)) if isinstance(v, str) else v
    out = tmp_path / "ft"
    flat = [x for kv in args.items() for x in kv]
    proc = invoke_main(cli.main, "finetune", *flat, "--out", out, *TINY[2:])
    assert_bench_error(proc, flag)
    assert not out.exists()


def test_no_checkpoint_given_is_one_line(files, tmp_path):
    proc = invoke_main(cli.main, "finetune", "--input", files["folder"], "--out", tmp_path / "o",
                       *MOTION, *TINY)  # fmt: skip
    assert_bench_error(proc, "--ckpt")


def test_footage_sequences_on_numbers():
    """Stride: 0.1 m per training frame over 0.025 m per footage frame -> every 4th frame;
    stretches cut where the camera stands still; K of a crop of a 200 px focal video."""
    positions = np.zeros((40, 3))
    positions[:, 2] = 0.025 * np.arange(40)
    assert frame_stride(positions, 0.3, 3) == 4
    assert frame_stride(np.zeros((5, 3)), 0.3, 3) == 1  # no motion at all
    still = positions.copy()
    still[10:20] = still[10]  # hovering from frame 10 to 19
    kept = list(range(0, 40, 2))
    assert moving_stretches(still, kept, 5) == [
        [0, 2, 4, 6, 8, 10],
        [18, 20, 22, 24, 26, 28, 30, 32, 34, 36, 38],
    ]
    K = prepared_K((64, 32), Crop(x=10, y=5, width=128, height=64, factor=1.0), 200.0)
    np.testing.assert_allclose(K, [[100.0, 0, 31.5], [0, 100.0, 15.5], [0, 0, 1]])


def test_poses_give_the_pose_cosine_column(files, tmp_path):
    """With --poses (camera axes) steps.csv has the cosine between PoseNet's reference
    translation and the known one; with --speed it is empty (the direction is unknown)."""
    poses = tmp_path / "poses.csv"
    poses.write_text("x,y,z\n" + "".join(f"{0.3 * k},0,0\n" for k in range(8)))
    out = tmp_path / "ft"
    proc = invoke_main(
        cli.main, "finetune", "--ckpt", files["ckpt"], "--input", files["folder"], "--out", out,
        "--poses", poses, "--fps", 10, *TINY, "--steps", 2, "--log-every", 1,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    cosines = [float(r["pose_cosine"]) for r in _steps(out)]
    assert len(cosines) == 2 and all(-1 <= c <= 1 for c in cosines)
    finetune(files, tmp_path / "speed", "--steps", 1, "--log-every", 1)
    assert [r["pose_cosine"] for r in _steps(tmp_path / "speed")] == [""]


def test_known_motion_warps_with_the_poses_and_needs_them(files, tmp_path):
    """--known-motion: the warps use --poses' motion (steps.csv's cosine against it is 1), there
    is no warm-up (every step trains the DepthNet), and without --poses it is refused in one
    line naming the flag."""
    poses = tmp_path / "poses.csv"
    poses.write_text("x,y,z\n" + "".join(f"{0.3 * k},{0.1 * k},0\n" for k in range(8)))
    out = tmp_path / "ft"
    proc = invoke_main(
        cli.main, "finetune", "--ckpt", files["ckpt"], "--input", files["folder"], "--out", out,
        "--poses", poses, "--fps", 10, *TINY, "--steps", 2, "--log-every", 1, "--known-motion",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    rows = _steps(out)
    assert [r["phase"] for r in rows] == ["joint", "joint"]
    assert all(abs(float(r["pose_cosine"]) - 1) < 1e-5 for r in rows)
    before, after = _weights(files["ckpt"]), _weights(out / "checkpoints" / "best.pt")
    assert any(not torch.equal(before[k], after[k]) for k in before)
    proc = finetune(files, tmp_path / "speed", "--known-motion", ok=False)
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1
    assert "--known-motion" in proc.stderr and "--poses" in proc.stderr
    assert not (tmp_path / "speed").exists()


def test_a_depthnet_unsup_checkpoint_keeps_its_posenet(files, tmp_path):
    ckpt = _checkpoint(tmp_path / "unsup.pt", "depthnet-unsup-tiny")
    out = tmp_path / "ft"
    proc = invoke_main(
        cli.main, "finetune", "--ckpt", ckpt, "--input", files["folder"], "--out", out,
        *MOTION, *TINY, "--steps", 1, "--pose-warmup", 1,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    best = torch.load(out / "checkpoints" / "best.pt", weights_only=True)
    assert best["model_name"] == "depthnet-unsup-tiny" and "pose" not in best
    source = _weights(ckpt)
    pose = [k for k in source if k.startswith("pose.")]
    assert pose and any(not torch.equal(source[k], best["model"][k]) for k in pose)
    assert all(torch.equal(source[k], best["model"][k]) for k in source if k.startswith("depth."))


def test_finetunes_training_knobs_are_the_training_configs_declarations():
    """finetune restates no training knob: each of its options named like a TrainConfig flag is
    made from that field's declaration (its help and rule), and every field declared for
    finetune is an option of it; a declared rule refuses a bad value in finetune's terms."""
    from benchmark.cli.unsupervised import finetune_cmd
    from benchmark.core.config import FLAGGED
    from benchmark.core.errors import FieldError
    from benchmark.unsupervised.finetune import TRAINING_KNOBS, check_numbers

    declared = {f.metadata["flag"].name: f for f in FLAGGED}
    options = {p.opts[0]: p for p in finetune_cmd.params if p.opts[0].startswith("--")}
    offered = {n for n, f in declared.items() if "finetune" in f.metadata["flag"].help}
    assert offered <= set(options)
    assert {declared[n].name for n in offered} == set(TRAINING_KNOBS)
    for name in offered:
        text = declared[name].metadata["flag"].help["finetune"].split("  [default")[0]
        assert options[name].help.startswith(text.split("{")[0]), name
    for knob, bad in (("lr", 0.0), ("batch_size", 0), ("seed", -1), ("log_every", 0)):
        with pytest.raises(FieldError) as e:
            check_numbers(FinetuneOptions(out=Path("x"), **{knob: bad}))
        assert e.value.field == knob
