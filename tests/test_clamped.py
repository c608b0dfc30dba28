"""The clamped DepthNet of thesis 6.4: its recipe, clipped targets, clamped outputs, a smoke run."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from test_bench import bench

from benchmark.core import registry
from benchmark.core.data import STILL_TARGET, FrameStore, PairDataset, load_scenes
from benchmark.core.models import DepthNet, count_parameters
from benchmark.engine import evaluate
from stillbox_gen.conventions import MAX_DEPTH, NOMINAL_SHIFT


def test_clamped_networks_are_registered_with_the_thesis_recipe():
    for name in ("depthnet-clamped", "depthnet-clamped-thin", "depthnet-clamped-tiny"):
        recipe = registry.MODELS[name].recipe
        assert (recipe.shift, recipe.depth_range) == (5, (10.0, 60.0)), name
        # everything else is DepthNet's recipe
        assert recipe.lr == registry.DEPTH_RECIPE.lr and recipe.epochs == 55
    assert registry.DEPTH_RECIPE.shift == NOMINAL_SHIFT
    full = count_parameters(registry.build_model("depthnet-clamped"))
    thin = registry.build_model("depthnet-clamped-thin")
    assert thin.conv1[0].out_channels == 16 and thin.conv6_1[0].out_channels == 256
    assert 0.2 < count_parameters(thin) / full < 0.3  # half the maps: about a quarter the weights


def test_output_clamp_only_for_a_narrower_range():
    assert registry.output_clamp((0.0, MAX_DEPTH)) is None
    assert registry.output_clamp([10, 60]) == (10.0, 60.0)


@pytest.fixture(scope="module")
def store(tiny_dataset) -> FrameStore:
    return FrameStore(load_scenes(tiny_dataset, "train"), progress=False)


def test_training_targets_are_clipped_to_the_depth_range(store):
    plain = PairDataset(store, "train", shift=5, seed=1)
    clamped = PairDataset(store, "train", shift=5, seed=1, depth_range=(10.0, 60.0))
    seen_still = False
    for i in range(len(plain)):
        a, b = plain[i], clamped[i]
        assert torch.equal(a["input"], b["input"])  # same pair, same flips
        expected = np.clip(a["target"].numpy(), 10.0, 60.0)  # plain: already within [0, 100]
        np.testing.assert_array_equal(b["target"].numpy(), expected)
        if a["frames"][0] == a["frames"][1]:
            seen_still = True
            assert float(a["target"].max()) == STILL_TARGET and float(b["target"].max()) == 60.0
    assert seen_still  # the sampling draws identical frames now and then (shift 0)
    t = torch.cat([clamped[i]["target"].flatten() for i in range(len(clamped))])
    assert float(t.min()) == 10.0 and float(t.max()) == 60.0


def test_scoring_clamps_the_network_output_before_the_displacement_scale():
    torch.manual_seed(0)
    model = DepthNet(width=0.125).eval()
    with torch.no_grad():
        model.predict_depth2.bias.fill_(200.0)  # finest output far above the range
    batch = {
        "input": torch.randn(2, 6, 64, 64),
        "target": torch.full((2, 64, 64), 30.0),
        "translation": torch.tensor([[0.0, 0.0, 0.5], [0.0, 0.0, 1.0]]),
    }
    dev = torch.device("cpu")
    with torch.no_grad():
        raw = evaluate.predict(evaluate.Method(registry.DEPTH, model, 0.5), batch, dev)["depth_q"]
        clamped = evaluate.Method(registry.DEPTH, model, 0.5, depth_range=(10, 60))
        out = evaluate.predict(clamped, batch, dev)
    assert float(raw.min()) > 60
    q = out["depth_q"]
    assert torch.allclose(q[0], torch.full_like(q[0], 60.0))  # clamped at 60, displacement 0.5
    assert torch.allclose(q[1], torch.full_like(q[1], 120.0))  # then scaled by 1.0 / 0.5


def test_clamped_smoke_run_records_its_range_shift_and_camera(tiny_dataset, tmp_path):
    out = tmp_path / "clamped"
    args = ["run", "depthnet-clamped-tiny", "--data", tiny_dataset, "--out", out]
    bench(*args, "--batch-size", 4, "--max-steps", 2, "--quiet")
    ck = torch.load(out / "checkpoints" / "best.pt", weights_only=True)
    assert ck["shift"] == 5 and ck["depth_range"] == [10.0, 60.0]
    assert ck["camera"] == {"width": 64, "height": 64, "fov_deg": 90.0}
    assert ck["nominal_displacement"] == pytest.approx(0.5)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["shift"] == 5 and summary["depth_range"] == [10.0, 60.0]
    config = json.loads((out / "config.json").read_text())
    assert config["depth_range"] == [10.0, 60.0] and config["shift"] == 5
    # the flags override the registered recipe: plain DepthNet clamped as the example
    out2 = tmp_path / "flags"
    bench(
        "run", "depthnet-tiny", "--data", tiny_dataset, "--out", out2, "--clamp", "10,60",
        "--shift", 4, "--batch-size", 4, "--max-steps", 1, "--quiet",
    )  # fmt: skip
    ck = torch.load(out2 / "checkpoints" / "best.pt", weights_only=True)
    assert ck["shift"] == 4 and ck["depth_range"] == [10.0, 60.0]


@pytest.mark.parametrize(
    ("flags", "words"),
    [
        (["--clamp", "60,10"], ["--clamp", "LO < HI"]),
        (["--clamp", "ten,60"], ["--clamp", "LO,HI"]),
        (["--clamp", "10,200"], ["--clamp", "100"]),
        (["--shift", "0"], ["--shift", "at least 1"]),
        (["--shift", "10"], ["--shift", "10 frames"]),
    ],
)
def test_bad_clamp_or_shift_is_one_line_and_leaves_no_run(tiny_dataset, tmp_path, flags, words):
    out = tmp_path / "run"
    proc = bench(
        "run", "depthnet-clamped-tiny", "--data", tiny_dataset, "--out", out, *flags,
        "--max-steps", 1, "--quiet", check=False,
    )  # fmt: skip
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert all(w in lines[0] for w in words), lines[0]
    assert not out.exists()
