"""Concurrency, signals and a full disk: one writer at a time per output folder
(stillbox_gen.lock), no worker left behind by a terminated or killed run, a full disk said in one
line without retries, and each time the resumed run's dataset equal to an undisturbed one."""

from __future__ import annotations

import contextlib
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import (
    CLI,
    alive_of,
    assert_user_error,
    cmdline,
    descendants,
    file_tree,
    invoke_cli,
    invoke_main,
    run_cli,
)
from test_bench_hardening import assert_bench_error

from stillbox_gen.layout import LOCK_FILE
from stillbox_gen.lock import FolderInUse, folder_lock

HOLD = """\
import sys, time
from stillbox_gen.lock import folder_lock
i, n = map(int, sys.argv[2].split("/"))
with folder_lock(sys.argv[1], "--out", (i, n)):
    print("held", flush=True)
    time.sleep(600)
"""


def hold_lock(folder: Path, shard: str = "0/1") -> subprocess.Popen:
    """Another process holding the lock of ``folder`` (as shard I/N) until it is killed."""
    proc = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(folder), shard], stdout=subprocess.PIPE, text=True
    )
    assert proc.stdout.readline() == "held\n"
    return proc


def kill_9(proc: subprocess.Popen) -> None:
    proc.send_signal(signal.SIGKILL)
    proc.communicate(timeout=60)


def tree_with_info(root: Path) -> dict[str, bytes]:
    """Every file under ``root``, dataset.json and the lock file included."""
    return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*") if p.is_file()}


@pytest.mark.blender  # generate/bench check Blender before the folder
def test_shards_of_one_split_share_a_folder_but_no_shard_runs_twice(tmp_path):
    """Shard 0/2 holds a new folder: shard 1/2 may write beside it; shard 0/2 again, or an
    unsharded run, is refused in one line naming the folder and the holder, writing nothing. Once
    the holder is killed (kill -9), its lock blocks nothing."""
    out = tmp_path / "new"
    holder = hold_lock(out, "0/2")
    try:
        with folder_lock(out, "--out", (1, 2)):
            pass
        assert (out / LOCK_FILE).is_file()  # still held by shard 0/2: not deleted
        for shard in ((0, 2), (0, 1)):
            with (
                pytest.raises(FolderInUse, match=f"process {holder.pid} holds"),
                folder_lock(out, "--out", shard),
            ):
                pass
        args = ["--res", 64, "--scenes", 2, "--device", "cpu", "--quiet", "--out", out]
        for shard in ("0/2", "0/1"):
            proc = invoke_cli(*args, "--shard", shard)
            assert_user_error(proc, f"--out: '{out}' is in use", f"process {holder.pid}")
        assert [p.name for p in out.iterdir()] == [LOCK_FILE]  # nothing written
    finally:
        kill_9(holder)
    with folder_lock(out, "--out"):
        pass
    assert list(out.iterdir()) == []  # the stale lock file taken over, then deleted


@pytest.mark.parametrize("held, wanted", [("0/2", (1, 4)), ("3/4", (0, 2)), ("1/3", (2, 5))])
def test_shards_of_two_different_splits_are_refused(tmp_path, held, wanted):
    """A shard of a split into N beside a shard of another split (their scenes overlap): one
    line naming the folder and the holder, nothing written; a shard of the held split is still
    admitted beside it."""
    out = tmp_path / "new"
    holder = hold_lock(out, held)
    try:
        with (
            pytest.raises(FolderInUse, match=f"another split \\(process {holder.pid} holds"),
            folder_lock(out, "--out", wanted),
        ):
            pass
        assert [p.name for p in out.iterdir()] == [LOCK_FILE]
        n = int(held.split("/")[1])
        with folder_lock(out, "--out", ((int(held.split("/")[0]) + 1) % n, n)):
            pass
    finally:
        kill_9(holder)


def test_shard_bytes_stay_below_the_split_bytes():
    """The exclusive byte of every shard up to MAX_SHARDS lies below the split bytes, and the
    command line refuses a larger N in one line."""
    from stillbox_gen import lock

    top = lock.MAX_SHARDS
    assert lock._shard_byte((top - 1, top)) < lock._split_byte(1)
    proc = invoke_cli("--res", 64, "--scenes", 2, "--shard", f"0/{top + 1}", "--out", "x")
    assert_user_error(proc, "--shard: need 1 <= N <= 1,000,000")


def test_second_writer_of_a_dataset_is_refused_and_a_killed_holder_blocks_nothing(
    default_dataset, tmp_path
):
    """generate (extending), index and merge into a dataset another process holds: one line
    each, exit 2, no file changed. After kill -9 of the holder its lock file stays; validate
    accepts it, and the extending run succeeds (and removes it)."""
    ds = tmp_path / "ds"
    shutil.copytree(default_dataset, ds)
    holder = hold_lock(ds)
    try:
        before = tree_with_info(ds)
        extend = ["--res", 64, "--scenes", 5, "--seed", 3, "--device", "cpu", "--out", ds]
        for args, flag in (
            (extend, "--out"),
            (["index", ds], "DATASET"),
            (["merge", ds, ds], "OUT"),
        ):
            proc = invoke_cli(*args, "--quiet") if flag == "--out" else invoke_cli(*args)
            assert_user_error(proc, f"{flag}: '{ds}' is in use", f"process {holder.pid}")
        assert tree_with_info(ds) == before
    finally:
        kill_9(holder)
    assert (ds / LOCK_FILE).is_file()
    assert run_cli("validate", ds).returncode == 0
    proc = run_cli(*extend, "--quiet")
    assert "(1 rendered now)" in proc.stderr
    assert not (ds / LOCK_FILE).exists()
    assert run_cli("validate", ds).returncode == 0


def test_second_benchmark_run_into_one_folder_is_refused(tiny_dataset, tmp_path):
    """Two `stillbox-bench run`s into one --out would interleave steps.csv: the second is refused
    in one line naming the holder, writing nothing; a killed holder blocks nothing."""
    from benchmark.cli import main

    out = tmp_path / "run"
    args = ["run", "constant", "--data", tiny_dataset, "--out", out, "--quiet"]
    holder = hold_lock(out)
    try:
        proc = invoke_main(main, *args)
        assert_bench_error(proc, f"--out: '{out}' is in use", f"process {holder.pid}")
        assert [p.name for p in out.iterdir()] == [LOCK_FILE]
    finally:
        kill_9(holder)
    assert invoke_main(main, *args).returncode == 0
    assert (out / "summary.json").is_file() and not (out / LOCK_FILE).exists()


def _workers(root: int, timeout: float = 300) -> dict[int, int]:
    """Every process below ``root`` once a Blender worker (a spawned child) exists."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        procs = descendants(root)
        if any(
            b"spawn_main" in cmdline(p) and b"resource_tracker" not in cmdline(p) for p in procs
        ):
            return procs
        time.sleep(0.05)
    raise AssertionError("no worker process started")


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL], ids=["SIGTERM", "SIGKILL"])
def test_terminated_or_killed_run_leaves_no_process_and_resumes(default_dataset, tmp_path, sig):
    """SIGTERM (timeout, job schedulers) or kill -9 of `generate` once a worker runs: within
    seconds no process of the run is left (Blender workers, resource tracker); SIGTERM exits as
    Ctrl-C does (one line, code 143). While it runs, a second run on its --out is refused. A
    re-run resumes to the files of an undisturbed run. (The run is stopped by SIGSTOP while
    the second run is tried, so that it cannot end before the signal.)"""
    out = tmp_path / "ds"
    args = ["--res", 64, "--scenes", 4, "--seed", 3, "--device", "cpu", "--quiet", "--out", out]
    proc = subprocess.Popen([*CLI, *map(str, args)], stderr=subprocess.PIPE, text=True)
    procs = _workers(proc.pid)
    assert any(b"resource_tracker" in cmdline(p) for p in procs)  # it must end too
    proc.send_signal(signal.SIGSTOP)  # it cannot finish meanwhile; the signal waits for SIGCONT
    assert_user_error(invoke_cli(*args), f"'{out}' is in use", f"process {proc.pid}")
    proc.send_signal(sig)
    proc.send_signal(signal.SIGCONT)
    _, stderr = proc.communicate(timeout=120)
    if sig == signal.SIGTERM:
        assert proc.returncode == 128 + signal.SIGTERM, stderr
        assert stderr.strip().splitlines()[-1] == (
            "stillbox-gen: interrupted; re-run the same command to resume"
        )
        assert "Traceback" not in stderr
    else:
        assert proc.returncode == -signal.SIGKILL
    deadline = time.time() + 20
    while alive_of(procs) and time.time() < deadline:
        time.sleep(0.1)
    assert alive_of(procs) == [], [cmdline(p) for p in alive_of(procs)]
    run_cli(*args)
    ref, got = file_tree(default_dataset), file_tree(out)
    assert sorted(ref) == sorted(got) and [n for n in ref if ref[n] != got[n]] == []
    assert run_cli("validate", out).returncode == 0


# ---------------------------------------------------------------- a full disk


@pytest.fixture
def small_disk(tmp_path) -> Path:
    """A 400 KiB tmpfs (mounting needs root; skipped otherwise), unmounted afterwards."""
    disk = tmp_path / "disk"
    disk.mkdir()
    proc = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=400k", "tmpfs", str(disk)], capture_output=True
    )
    if proc.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {proc.stderr.decode().strip()}")
    try:
        yield disk
    finally:
        subprocess.run(["umount", "-l", str(disk)], check=True)


def grow(disk: Path) -> None:
    """Give the tmpfs room (8 MiB; files kept)."""
    subprocess.run(["mount", "-o", "remount,size=8m", str(disk)], check=True)


def test_full_disk_stops_generation_in_one_line_and_the_rerun_resumes(default_dataset, small_disk):
    """Frames that do not fit on the disk: the run stops at the first failure with one line
    naming the disk-full error and the folder (no retries, no traceback), exit 1; with room
    again, the same command resumes to the files of an undisturbed run."""
    out = small_disk / "ds"
    args = ["--res", 64, "--scenes", 4, "--seed", 3, "--device", "cpu", "--quiet", "--out", out]
    proc = run_cli(*args, check=False)
    last = proc.stderr.strip().splitlines()[-1]
    assert proc.returncode == 1, proc.stderr
    assert last.startswith(f"stillbox-gen: failed: disk full writing '{out}/"), last
    assert "(No space left on device)" in last and "re-run the same command" in last
    for word in ("Traceback", "StopIteration", "failed 3 times", "retried"):
        assert word not in proc.stderr
    grow(small_disk)
    run_cli(*args)
    ref, got = file_tree(default_dataset), file_tree(out)
    assert sorted(ref) == sorted(got) and [n for n in ref if ref[n] != got[n]] == []
    assert run_cli("validate", out).returncode == 0


def test_full_disk_while_indexing_is_one_line_and_leaves_no_partial_file(
    default_dataset, small_disk
):
    """The driver's own writes (here `index` writing metadata.json) on a full disk: one line
    naming the file, exit 1, no temporary file left; with room again, index succeeds."""
    ds = small_disk / "ds"
    grow(small_disk)
    shutil.copytree(default_dataset, ds)
    (ds / "0" / "metadata.json").unlink()
    (ds / "manifest.parquet").unlink()
    with contextlib.suppress(OSError), open(small_disk / "filler", "wb") as f:
        while True:  # fill the disk
            f.write(bytes(4096))
            f.flush()
    proc = invoke_cli("index", ds)
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr.strip().splitlines() == [
        f"stillbox-gen: failed: disk full writing '{ds}/0/metadata.json' (No space left on "
        "device); finished scenes are kept: free space, then re-run the same command to resume"
    ]
    assert not list((ds / "0").glob(".metadata.json.tmp-*"))
    (small_disk / "filler").unlink()
    assert invoke_cli("index", ds).returncode == 0
    assert run_cli("validate", ds).returncode == 0
