"""The outputs of the scoring commands (issue 40): one writer per --out folder (eval,
eval-multishift, eval-sequences, speed and stillbox-gen stats take its lock, as run, finetune and
fly do), frames of another size than the checkpoint's refused before --out is written, a full disk
in one line, and the bounds of run's --clamp and eval-multishift's --shifts.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

import pytest
from conftest import TINY_SHARES, invoke_cli, run_cli
from test_bench import bench
from test_bench_hardening import assert_bench_error, write_checkpoint
from test_reliability import hold_lock, kill_9

from stillbox_gen.layout import LOCK_FILE

pytestmark = pytest.mark.usefixtures("one_torch_thread")

CAMERA_64 = {"width": 64, "height": 64, "fov_deg": 90.0}  # what 'run' records on tiny_dataset
SPEED = ["speed", "--models", "depthnet-tiny", "--resolutions", "64", "--time-res", "64"]


def _render(root: Path, res: str) -> Path:
    """tiny_dataset's six scenes (one split each at least) at ``res`` pixels."""
    out = root / f"tiny-{res}"
    split = ",".join(map(str, TINY_SHARES))
    run_cli("--res", res, "--scenes", 6, "--seed", 0, "--split", split, "--out", out, "--quiet")
    return out


@pytest.fixture(scope="module")
def other_sizes(tmp_path_factory) -> dict[str, Path]:
    """tiny_dataset at 32 px (frames DepthNet cannot read) and 128 px (frames it reads, at
    another scale than a 64 px checkpoint's)."""
    root = tmp_path_factory.mktemp("sizes")
    return {res: _render(root, res) for res in ("32", "128")}


# ---------------------------------------------------------------- one writer per --out


def _lock_cases(data: Path, ckpt: Path) -> dict[str, list]:
    """Each command that writes a folder, with arguments that get it as far as its --out."""
    return {
        "eval": ["eval", "--ckpt", ckpt, "--data", data],
        "eval-multishift": ["eval-multishift", "--ckpt", ckpt, "--data", data, "--quiet"],
        "eval-sequences": ["eval-sequences", "--ckpt", ckpt, "--data", data, "--quiet"],
        "speed": [*SPEED, "--warmup", 0, "--repeats", 1],
        "speed --train": [*SPEED, "--train", "--batches", 2, "--warmup", 1, "--repeats", 1],
        "stats": ["stats", data],
    }


@pytest.mark.render
@pytest.mark.parametrize("command", list(_lock_cases(Path(), Path())))
@pytest.mark.parametrize("folder", ["new", "existing"])
def test_second_writer_of_an_out_folder_is_refused(tiny_dataset, tmp_path, command, folder):
    """Another process holds --out: one line naming --out and the holder, exit code 2 (as run,
    finetune and fly), nothing written beside the holder's lock file."""
    ckpt = write_checkpoint(tmp_path / "c.pt", camera=CAMERA_64)
    out = tmp_path / "out"
    if folder == "existing":
        out.mkdir()
    holder = hold_lock(out)
    try:
        args = [*_lock_cases(tiny_dataset, ckpt)[command], "--out", out]
        proc = invoke_cli(*args) if command == "stats" else bench(*args, check=False)
        line = f"--out: '{out}' is in use by another run (process {holder.pid} holds"
        if command == "stats":
            assert proc.returncode == 2 and proc.stderr.strip().splitlines() == [
                f"stillbox-gen: error: {line} '{out / LOCK_FILE}'); wait for it to end, or use "
                "another folder"
            ], proc.stderr
        else:
            assert_bench_error(proc, line)
        assert [p.name for p in out.iterdir()] == [LOCK_FILE]
    finally:
        kill_9(holder)


@pytest.mark.render
@pytest.mark.parametrize("command", ["report", "compare", "toy"])
def test_report_compare_and_toy_refuse_a_second_writer(tiny_dataset, toy_data, tmp_path, command):
    """report (into the folder of OUT.md), compare and toy hold --out's lock as the other
    commands do: while another process holds it, one line naming --out and the holder, and
    nothing written beside the lock file; once it is free, the same command runs and leaves
    no lock file."""
    run, out = tmp_path / "run", tmp_path / "out"
    bench("run", "constant", "--data", tiny_dataset, "--out", run)
    args = {
        "report": ["report", run, "--out", out / "table"],
        "compare": ["compare", "--data", tiny_dataset, "--models", "constant", "--out", out],
        "toy": [
            *("toy", "--flower", toy_data["flower"], "--horizon", toy_data["horizon"]),
            *("--iterations", 1, "--losses", "tv", "--lambdas", 1, "--kappas", 1, "--quiet"),
            *("--out", out),
        ],
    }[command]
    holder = hold_lock(out)
    try:
        proc = bench(*args, check=False)
        assert_bench_error(proc, f"--out: '{out}' is in use by another run (process {holder.pid}")
        assert [p.name for p in out.iterdir()] == [LOCK_FILE]
    finally:
        kill_9(holder)
    bench(*args)
    assert not (out / LOCK_FILE).exists() and len(list(out.iterdir())) > 0


@pytest.mark.render
def test_the_lock_is_released_and_its_file_removed(tiny_dataset, tmp_path):
    """A finished command leaves its outputs and no lock file; the next one into the folder runs."""
    out = tmp_path / "speed"
    for _ in range(2):
        bench(*SPEED, "--warmup", 0, "--repeats", 1, "--out", out)
        assert [p.suffix for p in out.iterdir()] == [".csv"]
    ckpt = write_checkpoint(tmp_path / "c.pt", camera=CAMERA_64)
    bench("eval", "--ckpt", ckpt, "--data", tiny_dataset, "--out", tmp_path / "eval")
    assert not (tmp_path / "eval" / LOCK_FILE).exists()
    assert (tmp_path / "eval" / "summary.json").is_file()


# ---------------------------------------------------------------- frames of another size


#: the commands that score a checkpoint on a dataset's frames (one size check for all:
#: engine.runner.check_frame_size), with what they need besides --ckpt, --data and --out
SCORING = {
    "eval": [],
    "eval-sequences": ["--quiet"],
    "eval-multishift": ["--max-shift", "3", "--quiet"],
}


@pytest.mark.render
@pytest.mark.parametrize("command", sorted(SCORING))
@pytest.mark.parametrize("res", ["32", "128"])
@pytest.mark.parametrize("folder", ["new", "existing"])
def test_eval_on_frames_of_another_size_names_data_and_both_sizes(
    other_sizes, tmp_path, command, res, folder
):
    """A checkpoint trained on 64x64 px frames scored on 32 px frames (which it cannot read) or
    128 px ones (which it reads at twice its pixels' scale): one line naming --data, the frames'
    size and the checkpoint's, before --out is written (a new one is not made, an empty one
    stays empty)."""
    data = other_sizes[res]
    ckpt = write_checkpoint(tmp_path / "c.pt", camera=CAMERA_64)
    out = tmp_path / "out"
    if folder == "existing":
        out.mkdir()
    args = ["--ckpt", ckpt, "--data", data, "--out", out, *SCORING[command]]
    proc = bench(command, *args, check=False)
    assert_bench_error(proc, f"--data {data}", f"{res}x{res} px", "64x64 px", str(ckpt))
    assert (list(out.iterdir()) == []) if folder == "existing" else not out.exists()


@pytest.mark.render
def test_eval_of_a_checkpoint_without_camera_names_the_size_the_network_needs(
    other_sizes, tmp_path
):
    """A checkpoint that records no training camera: frames the network cannot read (not
    multiples of 64 px) are refused in one line naming --data and both sizes, --out not made."""
    data, out = other_sizes["32"], tmp_path / "out"
    ckpt = write_checkpoint(tmp_path / "c.pt")
    proc = bench("eval", "--ckpt", ckpt, "--data", data, "--out", out, check=False)
    assert_bench_error(proc, f"--data {data}", "32x32 px", "multiples of 64 px")
    assert not out.exists()


# ---------------------------------------------------------------- a full disk


def _fsync_fails(code: int):
    """os.fsync raising ``code`` (a full disk shows at the write or at the fsync after it)."""

    def fsync(fd: int) -> None:
        raise OSError(code, os.strerror(code))

    return fsync


@pytest.mark.render
@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EDQUOT], ids=["ENOSPC", "EDQUOT"])
@pytest.mark.parametrize("command", ["eval", "speed"])
def test_full_disk_is_one_line_naming_the_file(tiny_dataset, tmp_path, monkeypatch, code, command):
    """A write that fails for lack of space: one line ``stillbox-bench: failed: disk full
    writing '<file>' (<reason>); ...``, exit code 1 (as stillbox-gen), no traceback, no
    temporary file left."""
    ckpt = write_checkpoint(tmp_path / "c.pt", camera=CAMERA_64)
    out = tmp_path / "out"
    args = {
        "eval": ["eval", "--ckpt", ckpt, "--data", tiny_dataset, "--out", out],
        "speed": [*SPEED, "--warmup", 0, "--repeats", 1, "--out", out],
    }[command]
    monkeypatch.setattr(os, "fsync", _fsync_fails(code))
    proc = bench(*args, check=False)
    last = proc.stderr.strip().rsplit("\r", 1)[-1]  # after eval's progress bar, which \r clears
    assert proc.returncode == 1, proc.stderr
    assert "Traceback" not in proc.stderr and len(last.splitlines()) == 1, proc.stderr
    assert last.startswith(f"stillbox-bench: failed: disk full writing '{out}/"), last
    assert f"({os.strerror(code)}); " in last and "re-run the same command" in last
    assert not [p for p in out.rglob("*") if ".tmp-" in p.name or p.name == LOCK_FILE]


def test_other_os_errors_are_not_called_a_full_disk(tmp_path, monkeypatch):
    """Only ENOSPC and EDQUOT become the one line; another OSError is not hidden."""
    monkeypatch.setattr(os, "fsync", _fsync_fails(errno.EIO))
    with pytest.raises(OSError, match="Input/output error"):
        bench(*SPEED, "--warmup", 0, "--repeats", 1, "--out", tmp_path / "out", check=False)


# ---------------------------------------------------------------- --clamp and --shifts

CLAMPS = ["5,1", "-1,100", "0,inf", "nan,3", "1e30,1e31", "0,1e400", "3,3", "0,101", "1,2,3"]


@pytest.mark.render
@pytest.mark.parametrize("clamp", CLAMPS)
def test_clamp_out_of_bounds_is_one_line_before_anything(tiny_dataset, tmp_path, clamp):
    """run --clamp LO,HI: metres with 0 <= LO < HI <= 100 (core.config's rule, the one source
    of the range); anything else is one line naming --clamp, before --out is made."""
    out = tmp_path / "out"
    proc = bench("run", "depthnet-tiny", "--data", tiny_dataset, "--out", out,
                 f"--clamp={clamp}", "--max-steps", 1, check=False)  # fmt: skip
    assert_bench_error(proc, "--clamp", clamp.split(",")[0].replace("1e30", "1e+30"))
    assert not out.exists()


@pytest.mark.parametrize("shifts", ["0", "-1", str(10**9), "1,5", "nan", "1,,2", ""])
def test_shifts_out_of_bounds_is_refused_while_parsing(tmp_path, shifts):
    """eval-multishift --shifts: each n within its row of limits.LIMITS, refused by click before
    anything is read (a missing --ckpt and --data are not reached), in one line naming it."""
    out = tmp_path / "out"
    proc = bench("eval-multishift", "--ckpt", tmp_path / "none.pt", "--data", tmp_path / "none",
                 "--out", out, f"--shifts={shifts}", check=False)  # fmt: skip
    assert_bench_error(proc, "--shifts")
    assert not out.exists()
