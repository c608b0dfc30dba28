"""Beyond one process pool: shards in separate folders joined by `merge`, shards started at the
same instant into one new folder, and the Ray backend on a local Ray cluster started here.
Each must give the same files as the single local run of the `default_dataset` fixture."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import CLI, file_tree, run_cli

pytestmark = pytest.mark.render

ARGS = ["--res", 64, "--seed", 3, "--quiet"]


def _scene_files(tree: dict[str, bytes]) -> list[str]:
    return [n for n in tree if "RGB_" in n or "depth_" in n or ".records" in n]


def test_shards_in_separate_folders_merge_into_a_single_run(default_dataset, tmp_path):
    a, b, merged = tmp_path / "a", tmp_path / "b", tmp_path / "merged"
    run_cli(*ARGS, "--scenes", 4, "--shard", "0/2", "--workers", 1, "--out", a)
    run_cli(*ARGS, "--scenes", 4, "--shard", "1/2", "--workers", 1, "--out", b)

    missing = run_cli("merge", merged, a, check=False)
    assert missing.returncode == 2 and "lacks 2 of 4 scenes (1, 3)" in missing.stderr
    other = tmp_path / "other"
    run_cli("--res", 64, "--seed", 4, "--quiet", "--scenes", 4, "--shard", "1/2", "--out", other)
    clash = run_cli("merge", tmp_path / "m2", a, other, check=False)
    assert clash.returncode == 2 and f"'{other}' was made with other parameters" in clash.stderr

    proc = run_cli("merge", merged, a, b)
    assert "merged 2 scenes from 2 folders; indexed 4 scenes, 40 frames" in proc.stdout
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

RAY_ENV = {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": "0" * 32, "RAY_USAGE_STATS_ENABLED": "0"}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def ray_cluster(tmp_path_factory):
    """A local Ray head node (2 CPUs, token authentication on); yields its address."""
    pytest.importorskip("ray", reason="the [ray] extra is not installed")  # `make test` has it
    ray_bin = str(Path(sys.executable).parent / "ray")
    env = {**os.environ, **RAY_ENV}
    port = _free_port()
    start = [ray_bin, "start", "--head", f"--port={port}", "--num-cpus=2",
             "--include-dashboard=false", "--disable-usage-stats",
             f"--temp-dir={tmp_path_factory.mktemp('ray')}"]  # fmt: skip
    subprocess.run(start, env=env, check=True, capture_output=True, timeout=120)
    try:
        yield f"127.0.0.1:{port}"
    finally:
        subprocess.run([ray_bin, "stop", "--force"], env=env, capture_output=True, timeout=120)


def _ray_cli(address: str, *args, check: bool = True) -> subprocess.CompletedProcess:
    env = {**os.environ, **RAY_ENV}
    cmd = [*CLI, *map(str, args), "--backend", "ray", "--ray-address", address]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    if check and proc.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} failed:\n{proc.stderr}")
    return proc


def test_ray_backend_on_a_ray_cluster_equals_a_local_run(default_dataset, ray_cluster, tmp_path):
    out = tmp_path / "ray"
    proc = _ray_cli(ray_cluster, *ARGS, "--scenes", 4, "--workers", 2, "--out", out)
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
           "--ray-address", ray_cluster]  # fmt: skip
    proc = subprocess.Popen(cmd, env=env, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 300
    while not list(out.glob("*/.records/*.json")) and time.time() < deadline:
        time.sleep(0.05)
    killed = subprocess.run(["pkill", "-9", "-o", "-f", "ray::RenderActor"], check=False)
    _, stderr = proc.communicate(timeout=600)
    assert killed.returncode == 0, "no Ray actor process found"
    assert proc.returncode == 0, stderr
    assert "worker process died" in stderr and "failures    0" not in stderr, stderr
    ref, got = file_tree(default_dataset), file_tree(out)
    assert all(ref[n] == got[n] for n in _scene_files(ref))
    assert run_cli("validate", out).returncode == 0


def test_ray_backend_errors_name_the_flag(tmp_path):
    proc = run_cli(
        *ARGS, "--scenes", 2, "--out", tmp_path / "x", "--ray-address", "h:1", check=False
    )
    assert proc.returncode == 2 and "--ray-address: only with --backend ray" in proc.stderr
    assert not (tmp_path / "x").exists()
