"""Beyond one process pool: shards in separate folders joined by `merge`, shards started at the
same instant into one new folder, and the Ray backend on a local Ray cluster started here.
Each must give the same files as the single local run of the `default_dataset` fixture."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
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
    run_cli,
)

pytestmark = pytest.mark.render

ARGS = ["--res", 64, "--seed", 3, "--quiet"]


def _scene_files(tree: dict[str, bytes]) -> list[str]:
    return [n for n in tree if "RGB_" in n or "depth_" in n or ".records" in n]


def test_shards_in_separate_folders_merge_into_a_single_run(default_dataset, tmp_path):
    a, b, merged = tmp_path / "a", tmp_path / "b", tmp_path / "merged"
    run_cli(*ARGS, "--scenes", 4, "--shard", "0/2", "--workers", 1, "--out", a)
    run_cli(*ARGS, "--scenes", 4, "--shard", "1/2", "--workers", 1, "--out", b)

    assert_user_error(invoke_cli("merge", merged, a), "lacks 2 of 4 scenes (1, 3)")
    assert not merged.exists()  # refused before anything is written
    other = tmp_path / "other"
    run_cli("--res", 64, "--seed", 4, "--quiet", "--scenes", 4, "--shard", "1/2", "--out", other)
    clash = invoke_cli("merge", tmp_path / "m2", a, other)
    assert_user_error(clash, f"'{other}' was made with other parameters")

    proc = run_cli("merge", merged, a, b)
    assert "merged 4 scenes from 2 folders; indexed 4 scenes, 40 frames" in proc.stdout
    ref, got = file_tree(default_dataset), file_tree(merged)
    assert sorted(ref) == sorted(got)
    assert [n for n in ref if ref[n] != got[n]] == []
    info = json.loads((merged / "dataset.json").read_text())
    assert info["complete"] is True and info["run"]["merged_from"] == [str(a), str(b)]
    assert run_cli("validate", merged).returncode == 0

    run_cli("merge", a, a, b)  # into one of the parts
    got = file_tree(a)
    assert sorted(ref) == sorted(got) and [n for n in ref if ref[n] != got[n]] == []


def test_shards_started_together_into_a_new_folder_equal_a_single_run(default_dataset, tmp_path):
    """Both shards create the folder and write dataset.json at once; neither may refuse it."""
    out = tmp_path / "together"
    cmd = [*CLI, *map(str, ARGS), "--scenes", "4", "--workers", "1", "--out", str(out)]
    procs = [
        subprocess.Popen([*cmd, "--shard", s], stderr=subprocess.PIPE, text=True)
        for s in ("0/2", "1/2")
    ]
    errors = [p.communicate(timeout=600)[1] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], errors
    if not (out / "manifest.parquet").exists():  # both finished at the same instant
        run_cli("index", out)
    ref, got = file_tree(default_dataset), file_tree(out)
    assert sorted(ref) == sorted(got)
    assert [n for n in ref if ref[n] != got[n]] == []


# ---------------------------------------------------------------- Ray

RAY_ENV = {
    "RAY_AUTH_MODE": "token",
    "RAY_AUTH_TOKEN": "0" * 32,
    "RAY_USAGE_STATS_ENABLED": "0",
    "RAY_GRACEFUL_SHUTDOWN_DRAIN_TIMEOUT_S": "0",  # stop at once on SIGTERM
}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class RayHead:
    address: str
    pid: int  # the `ray start --block` process; the node's processes are below it


@contextlib.contextmanager
def _ray_head():
    """A Ray head node of its own (2 CPUs, token authentication on, its own port and temp dir
    under /tmp: Ray's socket paths must stay below 108 bytes).

    `ray start --head --block` stops the processes it started when it gets SIGTERM; whatever
    of them outlives it (Ray workers run in their own process groups) is killed by pid. No
    `ray stop`: that stops every Ray instance on the machine, a user's own cluster included.
    """
    with tempfile.TemporaryDirectory(prefix="ray-", ignore_cleanup_errors=True) as tmp:
        yield from _run_ray_head(Path(tmp))


def _run_ray_head(temp_dir: Path):
    """_ray_head's body: start, yield a RayHead once it is up, stop what it started."""
    port = _free_port()
    cmd = [str(Path(sys.executable).parent / "ray"), "start", "--head", "--block",
           f"--port={port}", "--num-cpus=2", "--include-dashboard=false",
           "--disable-usage-stats", f"--temp-dir={temp_dir}"]  # fmt: skip
    log = temp_dir / "ray-start.log"
    with log.open("w") as out:
        head = subprocess.Popen(cmd, env={**os.environ, **RAY_ENV}, stdout=out, stderr=out)
    try:
        deadline = time.time() + 120
        while not (temp_dir / "ray_current_cluster").is_file():  # written once it is up
            if head.poll() is not None or time.time() > deadline:
                raise RuntimeError(f"ray start failed:\n{log.read_text()}")
            time.sleep(0.2)
        yield RayHead(f"127.0.0.1:{port}", head.pid)
    finally:
        procs = descendants(head.pid)
        head.terminate()
        try:
            head.wait(timeout=120)
        except subprocess.TimeoutExpired:
            head.kill()
            head.wait()
        deadline = time.time() + 30
        while alive_of(procs) and time.time() < deadline:
            time.sleep(0.2)
        for pid in alive_of(procs):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)


@pytest.fixture(scope="module")
def ray_cluster():
    """A local Ray head node started (and stopped) by these tests only."""
    pytest.importorskip("ray", reason="the [ray] extra is not installed")  # `make test` has it
    with _ray_head() as head:
        yield head


def test_stopping_the_test_cluster_leaves_other_ray_instances_alone():
    """Another Ray instance on the machine (standing for a user's own) outlives the test
    cluster, and nothing the test cluster started is left running."""
    pytest.importorskip("ray", reason="the [ray] extra is not installed")
    with _ray_head() as user:
        theirs = descendants(user.pid)
        with _ray_head() as ours:
            mine = descendants(ours.pid)
        assert mine and alive_of(mine) == []
        assert theirs and sorted(alive_of(theirs)) == sorted(theirs)


def _ray_cli(address: str, *args, check: bool = True) -> subprocess.CompletedProcess:
    env = {**os.environ, **RAY_ENV}
    cmd = [*CLI, *map(str, args), "--backend", "ray", "--ray-address", address]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    if check and proc.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} failed:\n{proc.stderr}")
    return proc


def test_ray_backend_on_a_ray_cluster_equals_a_local_run(default_dataset, ray_cluster, tmp_path):
    out = tmp_path / "ray"
    proc = _ray_cli(ray_cluster.address, *ARGS, "--scenes", 4, "--workers", 2, "--out", out)
    assert "(4 rendered now)" in proc.stderr
    ref, got = file_tree(default_dataset), file_tree(out)
    assert sorted(ref) == sorted(got)
    assert [n for n in ref if ref[n] != got[n]] == []
    run = json.loads((out / "dataset.json").read_text())["run"]
    assert run["backend"] == "ray" and run["peak_rss_mb_per_worker"] > 0
    assert run_cli("validate", out).returncode == 0


def test_ray_actor_killed_mid_run_is_replaced_and_its_scene_retried(
    default_dataset, ray_cluster, tmp_path
):
    out = tmp_path / "ray-crash"
    env = {**os.environ, **RAY_ENV}
    cmd = [*CLI, *map(str, ARGS), "--scenes", "8", "--out", str(out), "--backend", "ray",
           "--ray-address", ray_cluster.address]  # fmt: skip
    proc = subprocess.Popen(cmd, env=env, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 300
    while not list(out.glob("*/.records/*.json")) and time.time() < deadline:
        time.sleep(0.05)
    actors = {  # this cluster's render actors only, oldest first
        pid: start
        for pid, start in descendants(ray_cluster.pid).items()
        if cmdline(pid).startswith(b"ray::RenderActor")
    }
    assert actors, "no Ray actor process found"
    os.kill(min(actors, key=actors.get), signal.SIGKILL)
    _, stderr = proc.communicate(timeout=600)
    assert proc.returncode == 0, stderr
    assert "worker process died" in stderr and "failures    0" not in stderr, stderr
    ref, got = file_tree(default_dataset), file_tree(out)
    assert all(ref[n] == got[n] for n in _scene_files(ref))
    assert run_cli("validate", out).returncode == 0
