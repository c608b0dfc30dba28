"""``stillbox-bench export``: ONNX (run by onnxruntime), TorchScript and safetensors files of a
depth network give the PyTorch network's depth, carry their metadata, and `infer` runs the ONNX
file as it runs the checkpoint; bad outputs are refused in one line with nothing written."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import invoke_main
from model_fixture import synthetic_state_dict
from test_bench_hardening import assert_bench_error
from test_infer import _checkpoint, _frames, _write_folder

from benchmark import cli
from benchmark.engine import export
from benchmark.engine.network import depth_network

pytest.importorskip("onnxruntime")
pytest.importorskip("safetensors")
pytestmark = pytest.mark.usefixtures("one_torch_thread")

#: largest |ONNX - PyTorch| depth accepted, metres, for depths of tens of metres (float32
#: kernels of two runtimes; 2e-5 m measured on the 64 px DepthNet)
ONNX_TOLERANCE_M = 1e-3


def _weighted_checkpoint(path: Path, name: str, **changes) -> Path:
    """A checkpoint whose every weight and BatchNorm statistic is non-trivial (a freshly built
    network's depth barely depends on its input); ``changes`` as test_infer's."""
    ck = torch.load(_checkpoint(path, name, **changes))
    shapes = {k: list(v.shape) for k, v in ck["model"].items()}
    ck["model"] = synthetic_state_dict(shapes)
    torch.save(ck, path)
    return path


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("export")
    return {
        "ckpt": _weighted_checkpoint(d / "tiny.pt", "depthnet-tiny"),
        "clamped": _weighted_checkpoint(
            d / "clamped.pt", "depthnet-clamped-tiny", depth_range=[0.8, 1.3]
        ),
        "flow": _checkpoint(d / "flow.pt", "flownets-flow-tiny"),
        "video": _write_folder(d / "pngs", _frames()),
        "dir": d,
    }


def _export(ckpt: Path, fmt: str, out: Path):
    return invoke_main(cli.main, "export", "--ckpt", ckpt, "--format", fmt, "--out", out)


def _reference(ckpt: Path, frames: torch.Tensor) -> torch.Tensor:
    network, _, info = depth_network(ckpt)
    with torch.no_grad():
        return export.DeployedDepth(network, info["clamp"]).eval()(frames)


def _frames_batch(batch: int) -> torch.Tensor:
    return torch.randn(batch, 6, 64, 64, generator=torch.Generator().manual_seed(3))


@pytest.mark.parametrize("name", ["ckpt", "clamped"])
def test_onnx_matches_pytorch_at_any_batch_and_records_its_metadata(files, tmp_path, name):
    out = tmp_path / "net.onnx"
    proc = _export(files[name], "onnx", out)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""  # exporter notes silenced
    network, scale, info = export.onnx_depth_network(out)
    for batch in (1, 3):
        frames = _frames_batch(batch)
        (depth,) = network(frames)
        reference = _reference(files[name], frames)
        assert depth.shape == reference.shape == (batch, 1, 64, 64)
        assert (depth - reference).abs().max() < ONNX_TOLERANCE_M
        assert reference.std() > 0.01  # the comparison sees a depth that varies
    meta = export.read_onnx_metadata(out)
    _, ref_scale, ref_info = depth_network(files[name])
    assert scale == ref_scale and info["clamp"] == ref_info["clamp"]
    assert meta["input"]["shape"] == ["B", 6, 64, 64] and meta["output"]["unit"] == "m"
    assert meta["nominal_displacement_m"] == 0.3
    if name == "clamped":  # clamped inside the file: no depth beyond the training range
        lo, hi = meta["depth_range_m"]
        assert (lo, hi) == (0.8, 1.3)  # around the synthetic weights' 0.45-1.8 m
        depth = network(_frames_batch(4) * 5)[0]
        assert lo - 1e-6 <= depth.min() and depth.max() <= hi + 1e-6  # float32 bounds
        assert (depth < lo + 1e-6).any() and (depth > hi - 1e-6).any()  # both bounds bite


@pytest.mark.filterwarnings("ignore:`torch.jit.load` is deprecated")
def test_torchscript_and_safetensors_give_the_same_depth(files, tmp_path):
    from safetensors import safe_open
    from safetensors.torch import load_file

    from benchmark.core import registry

    frames = _frames_batch(2)
    reference = _reference(files["ckpt"], frames)
    script = tmp_path / "net.pt"
    assert _export(files["ckpt"], "torchscript", script).returncode == 0
    extra = {"stillbox.json": ""}
    loaded = torch.jit.load(str(script), _extra_files=extra)
    assert torch.equal(loaded(frames), reference)
    assert json.loads(extra["stillbox.json"])["model_name"] == "depthnet-tiny"
    weights = tmp_path / "net.safetensors"
    assert _export(files["ckpt"], "safetensors", weights).returncode == 0
    model = registry.build_model("depthnet-tiny")
    model.load_state_dict(load_file(str(weights)))
    with torch.no_grad():
        assert torch.equal(export.DeployedDepth(model.eval(), None)(frames), reference)
    with safe_open(str(weights), "pt") as f:
        assert json.loads(f.metadata()["stillbox"])["camera"]["fov_deg"] == 90.0


def test_infer_runs_the_onnx_file_as_the_checkpoint(files, tmp_path):
    onnx_file = tmp_path / "net.onnx"
    assert _export(files["ckpt"], "onnx", onnx_file).returncode == 0
    depths = {}
    for label, ckpt in (("torch", files["ckpt"]), ("onnx", onnx_file)):
        out = tmp_path / label
        proc = invoke_main(
            cli.main, "infer", "--ckpt", ckpt, "--input", files["video"], "--speed", 3,
            "--fps", 10, "--out", out, "--quiet",
        )  # fmt: skip
        assert proc.returncode == 0, proc.stderr
        depths[label] = np.stack([np.load(p) for p in sorted((out / "depth").glob("*.npy"))])
    assert depths["onnx"].shape == depths["torch"].shape == (7, 64, 64)
    assert np.abs(depths["onnx"] - depths["torch"]).max() < ONNX_TOLERANCE_M
    proc = invoke_main(
        cli.main, "infer", "--ckpt", onnx_file, "--input", files["video"], "--speed", 3,
        "--fps", 10, "--res", "128x64", "--out", tmp_path / "other", "--quiet",
    )  # fmt: skip
    assert_bench_error(proc, "--res", "64x64")
    assert not (tmp_path / "other").exists()


def test_bad_outputs_and_inputs_are_refused_with_nothing_written(files, tmp_path):
    dataset = tmp_path / "dataset"
    dataset.mkdir()
    (dataset / "dataset.json").write_text("{}")
    (tmp_path / "taken.onnx").write_bytes(b"keep")
    cases = [
        (files["ckpt"], "onnx", tmp_path / "net.pt", ("--out", ".onnx")),
        (files["ckpt"], "onnx", tmp_path / "taken.onnx", ("--out", "exists")),
        (files["ckpt"], "onnx", tmp_path / "missing" / "net.onnx", ("--out", "no such folder")),
        (files["ckpt"], "onnx", dataset / "net.onnx", ("--out", "inside the dataset")),
        (files["ckpt"], "onnx", Path("/proc/net.onnx"), ("--out", "cannot write into '/proc'")),
        (files["flow"], "onnx", tmp_path / "flow.onnx", ("--ckpt", "not depth")),
        (tmp_path / "none.pt", "torchscript", tmp_path / "none2.pt", ("--ckpt",)),
    ]
    before = sorted(p.name for p in tmp_path.iterdir())
    for ckpt, fmt, out, words in cases:
        assert_bench_error(_export(ckpt, fmt, out), *words)
    assert sorted(p.name for p in tmp_path.iterdir()) == before
    assert (tmp_path / "taken.onnx").read_bytes() == b"keep"
    assert sorted(p.name for p in dataset.iterdir()) == ["dataset.json"]


def test_an_onnx_file_without_metadata_is_refused_by_infer(files, tmp_path):
    import onnx

    plain = tmp_path / "plain.onnx"
    model = onnx.load(str(_export_to(files["ckpt"], tmp_path / "net.onnx")))
    del model.metadata_props[:]
    onnx.save(model, str(plain))
    proc = invoke_main(
        cli.main, "infer", "--ckpt", plain, "--input", files["video"], "--speed", 3,
        "--fps", 10, "--out", tmp_path / "out", "--quiet",
    )  # fmt: skip
    assert_bench_error(proc, "--ckpt", "without stillbox metadata")
    assert not (tmp_path / "out").exists()


def _export_to(ckpt: Path, out: Path) -> Path:
    assert _export(ckpt, "onnx", out).returncode == 0
    return out
