"""``--device``: Cycles' render device, found by Blender (stillbox_gen.workers.choose_device).

This machine has no GPU, so what runs here is the CPU side: auto picks the CPU and says so, an
explicit GPU backend is a one-line error that writes nothing, and dataset.json records the device
(also across a resume on another device). Tests that need a GPU-less machine are skipped where
the kernel shows a GPU device node; the GPU path itself is not tested.
"""

from __future__ import annotations

import csv
import glob
import json
import subprocess
import sys

import pytest
from conftest import assert_user_error, invoke_cli, run_cli

from stillbox_gen import bench, config, workers, writer

NO_GPU = not any(glob.glob(p) for p in ("/dev/nvidia*", "/dev/kfd", "/dev/dri"))
cpu_only = pytest.mark.skipif(not NO_GPU, reason="this machine has a GPU device node")
TINY = ["--res", 16, "--scenes", 1, "--frames", 2, "--workers", 1, "--quiet"]


@cpu_only
@pytest.mark.blender
def test_blender_finds_no_gpu_backend_here():
    assert workers.find_gpus() == {}
    assert workers.choose_device("auto") == (
        "CPU",
        "render device: CPU (no GPU backend found by Cycles)",
    )
    assert workers.choose_device("cpu") == ("CPU", "render device: CPU")


@cpu_only
@pytest.mark.blender
@pytest.mark.parametrize("device", ["cuda", "optix", "hip"])
def test_gpu_backend_without_device_is_a_one_line_error_and_writes_nothing(tmp_path, device):
    out = tmp_path / "out"
    result = invoke_cli(*TINY, "--device", device, "--out", out)
    assert_user_error(
        result, f"--device {device}: no {device.upper()} device found by Cycles (found: CPU only)"
    )
    assert not out.exists()


@cpu_only
@pytest.mark.blender
def test_gpu_error_end_to_end_keeps_blender_warnings_off_stderr(tmp_path):
    """Cycles prints CUEW/HIPEW warnings while it looks: they stay in the detection subprocess."""
    out = tmp_path / "out"
    proc = run_cli(*TINY, "--device", "cuda", "--out", out, check=False)
    assert proc.stderr == (
        "stillbox-gen: error: --device cuda: no CUDA device found by Cycles (found: CPU only)\n"
    )
    assert not out.exists()


@cpu_only
@pytest.mark.blender  # generate/bench check Blender before the folder
def test_bench_refuses_a_missing_gpu_before_measuring():
    assert_user_error(invoke_cli("bench", "--device", "optix"), "--device optix: no OPTIX device")


@pytest.mark.parametrize("args", [["--device", "gpu"], ["bench", "--device", "CUDA0"]])
def test_unknown_device_is_refused_by_click(tmp_path, args):
    out = tmp_path / "out"
    result = invoke_cli(*args, *(["--out", out] if args[0] != "bench" else []))
    assert_user_error(result, "--device", args[-1])
    assert "'auto', 'cpu', 'optix', 'cuda', 'hip'" in result.stderr
    assert not out.exists()


def test_gpu_backends_are_refused_with_ray_before_looking(tmp_path):
    pytest.importorskip("ray")
    out = tmp_path / "out"
    result = invoke_cli("--backend", "ray", "--device", "cuda", "--out", out)
    assert_user_error(result, "--device cuda: --backend ray renders on CPUs")
    assert workers.choose_device("auto", "ray")[0] == "CPU"
    assert not out.exists()


@cpu_only
@pytest.mark.render
def test_auto_renders_on_the_cpu_says_so_and_records_it(tmp_path):
    out = tmp_path / "out"
    proc = run_cli(*TINY, "--device", "auto", "--out", out)
    assert "render device: CPU (no GPU backend found by Cycles)" in proc.stderr.splitlines()
    assert json.loads((out / "dataset.json").read_text())["render"]["device"] == "CPU"
    # extending it with an explicit --device: accepted (the device is not a parameter)
    proc = run_cli(*TINY[:2], "--scenes", 2, *TINY[4:], "--device", "cpu", "--out", out)
    assert "render device: CPU" in proc.stderr.splitlines()
    assert "(1 rendered now)" in proc.stderr
    info = json.loads((out / "dataset.json").read_text())
    assert info["complete"] and info["scenes"] == 2 and info["render"]["device"] == "CPU"


def test_a_resume_on_another_device_is_accepted_and_recorded(tmp_path):
    """Same parameters, another device: same fingerprint, so the run resumes; render.device
    then names both devices, in order of use (stands in for a GPU run: nothing renders)."""
    cfg = config.replace(config.DatasetConfig(), camera={"width": 16, "height": 16})
    out = tmp_path / "ds"
    assert writer.prepare_output(out, cfg, 2, "CUDA") == "CUDA"
    assert writer.prepare_output(out, cfg, 2, "CPU") == "CUDA + CPU"
    assert writer.prepare_output(out, cfg, 3, "CUDA") == "CUDA + CPU"
    info = json.loads((out / "dataset.json").read_text())
    assert info["render"]["device"] == "CUDA + CPU" and info["fingerprint"] == cfg.fingerprint()
    assert writer.join_devices(None) == "CPU" and writer.join_devices("CPU", "CPU") == "CPU"


@pytest.mark.blender
def test_worker_set_up_uses_the_cpu_and_refuses_a_missing_gpu():
    """The workers' own check (blender.devices.use_device), behind the driver's."""
    code = (
        "import bpy\n"
        "from stillbox_gen.blender.devices import use_device\n"
        "print('=', use_device('CPU'), bpy.context.scene.cycles.device)\n"
        "try:\n"
        "    use_device('CUDA')\n"
        "except RuntimeError as e:\n"
        "    print('=', e)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    lines = [line for line in proc.stdout.splitlines() if line.startswith("= ")]  # no warnings
    assert lines[0] == "= ['CPU'] CPU"
    if NO_GPU:
        assert lines[1] == "= Cycles finds no CUDA device in this worker process"


def test_bench_table_and_csv_name_the_device(tmp_path):
    row = bench.BenchRow(64, "fast", "CPU", "direct", 1, False, 2, 1.0, 20.0, 30.0)
    table = bench.markdown_table([row]).splitlines()
    assert table[0].startswith("| px | config | device |") and "| 64 | fast | CPU |" in table[2]
    bench.write_csv([row], tmp_path / "b.csv")
    assert [r["device"] for r in csv.DictReader((tmp_path / "b.csv").open())] == ["CPU"]
