"""``stillbox-bench fly`` and ``fly-compare`` end to end with the analytic renderer: the run
folder's files and summary fields, a run cut short and resumed per episode, one-line errors
before anything is written, and the comparison table."""

from __future__ import annotations

import csv
import importlib.util
import json

import numpy as np
import pytest
import torch
from conftest import invoke_main
from test_bench_hardening import assert_bench_error, write_checkpoint
from test_reliability import hold_lock, kill_9

from benchmark import cli
from benchmark.core import registry, runfolder
from benchmark.flight import run as flight_run
from benchmark.flight.simulate import FlightConfig, oracle
from benchmark.flight.sources import Scored
from stillbox_gen.layout import LOCK_FILE
from stillbox_gen.live import WorkerDied, WorkerHung

FAST = ("--renderer", "analytic", "--res", "32", "--quiet")
SUMMARY_KEYS = {
    "kind", "depth", "episodes", "reached", "collided", "timeout", "success_rate",
    "success_rate_ci95", "mean_min_clearance_m", "min_min_clearance_m", "mean_path_ratio_reached",
    "render_s_per_step", "depth_s_per_step", "control_s_per_step", "depth_frames", "depth_mae_m",
    "depth_mre", "config",
}  # fmt: skip


def fly(*args):
    return invoke_main(cli.main, "fly", *args)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Two finished runs of the same two episodes: oracle and constant 100 m."""
    d = tmp_path_factory.mktemp("fly")
    constant = ("--depth", "constant", "--constant-depth", "100")
    for name, depth in (("oracle", ("--depth", "oracle")), ("constant", constant)):
        proc = fly(*depth, "--episodes", "2", "--out", d / name, *FAST)
        assert proc.returncode == 0, proc.stderr
        assert f"results in {d / name}" in proc.stdout
    return d


def test_fly_writes_the_run_folder(runs):
    out = runs / "oracle"
    s = json.loads((out / "summary.json").read_text())
    assert set(s) >= SUMMARY_KEYS
    assert s["kind"] == "fly" and s["depth"] == "oracle" and s["episodes"] == 2
    assert s["reached"] + s["collided"] + s["timeout"] == 2
    assert s["success_rate"] == s["reached"] / 2
    low, high = s["success_rate_ci95"]
    assert 0 <= low <= s["success_rate"] <= high <= 1
    assert s["depth_mae_m"] == 0 and s["depth_frames"] > 0  # the oracle is the truth
    assert s["render_s_per_step"] > 0 and s["control_s_per_step"] > 0
    with open(out / "episodes.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["episode"]) for r in rows] == [0, 1]
    assert {"outcome", "min_clearance_m", "path_ratio", "depth_mae_m", "start_x_m"} <= set(rows[0])
    assert float(rows[0]["min_clearance_m"]) >= s["min_min_clearance_m"]
    assert float(rows[0]["flight_time_s"]) == pytest.approx(0.1 * int(rows[0]["steps"]))
    for k in range(2):
        assert runfolder.episode_plot_path(out, k).stat().st_size > 1000
    config = json.loads((out / "config.json").read_text())
    assert config["res"] == [32, 32] and config["renderer"] == "analytic"
    c = json.loads((runs / "constant" / "summary.json").read_text())
    assert c["collided"] == 2 and c["depth_mae_m"] > 1  # sees nothing: flies into the obstacle


def test_fly_compare_prints_and_writes_one_row_per_run(runs, tmp_path):
    out = tmp_path / "table"
    proc = invoke_main(cli.main, "fly-compare", runs / "oracle", runs / "constant", "--out", out)
    assert proc.returncode == 0, proc.stderr
    md = (tmp_path / "table.md").read_text()
    assert md in proc.stdout
    lines = md.strip().splitlines()
    assert len(lines) == 4 and "success" in lines[0] and "depth MAE (m)" in lines[0]
    with open(tmp_path / "table.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["depth"] for r in rows] == ["oracle", "constant"]
    assert float(rows[1]["collided"]) == 2 and float(rows[0]["depth_mae_m"]) == 0
    bad = invoke_main(cli.main, "fly-compare", runs / "oracle", tmp_path)
    assert_bench_error(bad, "RUN", "summary.json")


def test_fly_compare_refuses_a_second_writer_of_its_folder(runs, tmp_path):
    """fly-compare holds the lock of the folder of OUT.md and OUT.csv, as report does: while
    another process holds it, one line naming --out and the holder, nothing written; once it is
    free, the same command writes both files and leaves no lock file."""
    out = tmp_path / "tables"
    out.mkdir()
    args = ("fly-compare", runs / "oracle", runs / "constant", "--out", out / "table")
    holder = hold_lock(out)
    try:
        proc = invoke_main(cli.main, *args)
        assert_bench_error(proc, f"--out: '{out}' is in use by another run (process {holder.pid}")
        assert [p.name for p in out.iterdir()] == [LOCK_FILE]
    finally:
        kill_9(holder)
    assert invoke_main(cli.main, *args).returncode == 0
    assert sorted(p.name for p in out.iterdir()) == ["table.csv", "table.md"]


@pytest.mark.parametrize("error", [WorkerDied, WorkerHung])
def test_a_dead_or_hung_blender_worker_is_one_line(tmp_path, monkeypatch, error):
    """The live Blender worker gone mid-flight (died, or hung and stopped by LiveRenderer's
    timeout): one line naming it and how to continue, exit code 1, no traceback."""

    def fly_run(*args, **kwargs):
        raise error("the live Blender worker (pid 1) gave no answer")

    monkeypatch.setattr(flight_run, "fly_run", fly_run)
    proc = fly("--depth", "oracle", "--episodes", "1", "--out", tmp_path / "run", *FAST)
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr.splitlines() == [
        "stillbox-bench: failed: the live Blender worker (pid 1) gave no answer; "
        "continue with --resume --out <run>"
    ]


def test_a_run_cut_short_resumes_per_episode(runs, tmp_path):
    """Killed after its first episode: the folder needs --resume, which flies only the rest and
    ends as an uninterrupted run."""
    out = tmp_path / "cut"
    assert fly("--depth", "oracle", "--episodes", "1", "--out", out, *FAST).returncode == 0
    (out / "summary.json").unlink()  # as if killed before the end: episode 0 is written
    first = runfolder.episode_path(out, 0).read_bytes()
    assert_bench_error(fly("--depth", "oracle", "--episodes", "2", "--out", out, *FAST), "--out")
    assert_bench_error(
        fly("--depth", "constant", "--constant-depth", "5", "--out", out, "--resume", *FAST),
        "--resume",
        "depth",
    )
    line = assert_bench_error(
        fly("--depth", "oracle", "--max-steps", "299", "--out", out, "--resume", *FAST),
        "--resume",
    )
    assert "--max-steps (flight.max_steps) 300, not 299" in line  # the flag, not the settings
    proc = fly("--depth", "oracle", "--episodes", "2", "--out", out, "--resume", *FAST)
    assert proc.returncode == 0, proc.stderr
    assert runfolder.episode_path(out, 0).read_bytes() == first  # not flown again
    s = json.loads((out / "summary.json").read_text())
    assert s["episodes_flown_this_session"] == 1
    whole = json.loads((runs / "oracle" / "summary.json").read_text())
    for key in ("reached", "collided", "mean_min_clearance_m", "mean_path_ratio_reached"):
        assert s[key] == whole[key]
    assert_bench_error(fly("--depth", "oracle", "--out", out, *FAST), "--out", "finished")


def test_an_interruption_inside_the_loop_keeps_the_finished_episodes(tmp_path):
    out = tmp_path / "stop"
    config = {"depth": "oracle", "episodes": 2, "seed": 0, "res": [32, 32], "renderer": "analytic"}
    runfolder.write_config(runfolder.make_folder(out), config)

    def stop(index, record):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        flight_run.fly_run(
            out, config, Scored(oracle), FlightConfig(), progress=False, on_episode=stop
        )
    assert sorted(runfolder.read_episodes(out)) == [0]
    assert not (out / "summary.json").exists()


@pytest.fixture(scope="module")
def depth_ckpt(tmp_path_factory):
    camera = {"width": 64, "height": 64, "fov_deg": 90.0}
    return write_checkpoint(tmp_path_factory.mktemp("ck") / "tiny.pt", camera=camera)


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (("--depth", "lidar"), ("--depth", "lidar")),
        (("--depth", "oracle", "--episodes", "0"), ("--episodes",)),
        (("--depth", "oracle", "--max-steps", "0"), ("--max-steps",)),
        (("--depth", "oracle", "--res", "big"), ("--res",)),
        (("--depth", "oracle", "--shifts", "2"), ("--shifts",)),
        (("--depth", "{ckpt}", "--shifts", "5"), ("--shifts",)),
        (("--depth", "oracle", "--constant-depth", "3"), ("--constant-depth",)),
        (("--depth", "constant", "--constant-depth", "-3"), ("--constant-depth",)),
        (("--depth", "constant", "--data", "{missing}"), ("--data",)),
        (("--depth", "oracle", "--threads", "-1"), ("--threads",)),
        (("--depth", "oracle", "--device", "tpu"), ("--device",)),
        (("--depth", "{ckpt}"), ("--renderer analytic",)),
        # the checkpoint is read after the check for bpy (the gen extra's error comes first)
        pytest.param(
            ("--depth", "{text}", "--renderer", "blender"), ("--depth",), marks=pytest.mark.blender
        ),
    ],
)
def test_bad_input_is_one_line_before_anything_is_written(tmp_path, depth_ckpt, args, words):
    (tmp_path / "notes.txt").write_text("not a checkpoint")
    paths = {"ckpt": depth_ckpt, "missing": tmp_path / "nothing", "text": tmp_path / "notes.txt"}
    argv = [str(a).format(**paths) for a in args]
    out = tmp_path / "run"
    renderer = () if "--renderer" in argv else ("--renderer", "analytic")
    assert_bench_error(fly(*argv, "--out", out, "--quiet", *renderer), *words)
    assert not out.exists()


def test_out_is_checked_first(tmp_path):
    (tmp_path / "file").write_text("x")
    assert_bench_error(fly("--depth", "lidar", "--out", tmp_path / "file"), "--out")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    assert_bench_error(fly("--depth", "oracle", "--out", tmp_path / "full", *FAST), "--out")
    assert_bench_error(
        fly("--depth", "oracle", "--out", tmp_path / "new", "--resume", *FAST), "--resume"
    )


def test_blender_renderer_without_bpy_names_the_gen_extra(tmp_path, monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "bpy" else real(name, *a)
    )
    out = tmp_path / "run"
    assert_bench_error(fly("--depth", "oracle", "--out", out, "--renderer", "blender"), "[gen]")
    assert not out.exists()


def test_record_round_trip():
    """episodes/NNNNNN.json holds everything the summary and the figure need."""
    from benchmark.flight.episodes import flight_scene_config, make_episode
    from benchmark.flight.simulate import EpisodeResult

    e = make_episode(0, 0, scene_cfg=flight_scene_config(width=32, height=32))
    r = EpisodeResult("timeout", 2, 0.5, 1.0, 19.0, 0.1, 0.2, 0.3, np.zeros((3, 3)))
    errors = {"depth_frames": 2, "depth_mae_m": 0.5, "depth_mre": 0.1}
    back = flight_run.result_of(json.loads(json.dumps(flight_run.record_of(0, e, r, errors))))
    assert back.outcome == r.outcome and back.path_ratio == r.path_ratio
    assert np.array_equal(back.positions, r.positions)


def test_a_failure_before_the_first_episode_leaves_nothing(tmp_path, monkeypatch):
    def broken(*args, **kwargs):
        raise RuntimeError("no scene")

    monkeypatch.setattr(flight_run, "make_episode", broken)
    out = tmp_path / "run"
    with pytest.raises(RuntimeError, match="no scene"):
        fly("--depth", "oracle", "--out", out, *FAST)
    assert not out.exists()


def test_checkpoint_sources_for_the_blender_renderer(tmp_path, depth_ckpt):
    """What --depth PATH becomes (the Blender renderer's end-to-end test comes with it): a depth
    network (infer's pipeline) or a flow network, its camera and frame size checked."""
    from benchmark.cli.flight import _source
    from benchmark.cli.options import UserError
    from benchmark.flight.sources import FlowDepth, NetworkDepth

    flow = tmp_path / "flow.pt"
    ck = {
        "model": registry.build_model("flownets-flow-tiny").state_dict(),
        "model_name": "flownets-flow-tiny",
        "nominal_displacement": 0.3,
    }
    torch.save(ck, flow)
    o = {"renderer": "blender", "shifts": 2, "constant_depth": None, "data": tmp_path}
    cpu = torch.device("cpu")
    src, info = _source({**o, "depth": str(depth_ckpt)}, (64, 64), cpu)
    assert isinstance(src, NetworkDepth) and src.shifts == 2
    assert info["depth_kind"] == "depth network" and info["nominal_displacement_m"] == 0.3
    src, info = _source({**o, "depth": str(flow)}, (48, 48), cpu)
    assert isinstance(src, FlowDepth) and info["model_name"] == "flownets-flow-tiny"
    with pytest.raises(UserError, match="--res"):
        _source({**o, "depth": str(depth_ckpt)}, (48, 48), cpu)
    ck = torch.load(depth_ckpt, weights_only=True)
    ck["camera"]["fov_deg"] = 60.0
    torch.save(ck, tmp_path / "narrow.pt")
    with pytest.raises(UserError, match="60 deg"):
        _source({**o, "depth": str(tmp_path / "narrow.pt")}, (64, 64), cpu)
