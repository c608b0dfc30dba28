"""DepthNet and FlowNetS architectures, their checkpoint layout, the registry and the losses."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import model_fixture
import pytest
import torch

from benchmark.core.models import DepthNet, FlowNetS, count_parameters, macs
from benchmark.core.registry import (
    FLOW,
    KINDS,
    MODELS,
    UNSUPERVISED,
    ModelSpec,
    Target,
    build_model,
    list_models,
)

# Parameter count of the thesis 3.5 architecture (= the public DepthNet code with batch norm):
# encoder convs without bias + BN, deconv blocks (transposed conv with bias, 3×3 conv, BN),
# 5 predict_depth convs with bias, 4 bias-free 1→1 up-convs. Computed by hand and by
# count_parameters; the public code is "about 10.3 M".
DEPTHNET_PARAMETERS = 10_290_473


@pytest.fixture(scope="module")
def depthnet() -> DepthNet:
    torch.manual_seed(0)
    return DepthNet().eval()


@pytest.fixture(scope="module")
def tiny() -> torch.nn.Module:
    torch.manual_seed(0)
    return build_model("depthnet-tiny")


def expected_shapes(b: int, h: int, w: int) -> list[tuple[int, ...]]:
    return [(b, 1, h // s, w // s) for s in (4, 8, 16, 32, 64)]


def test_parameter_count(depthnet):
    """The exact count of the thesis 3.5 architecture, within 0.5 % of 10.29 M."""
    n = count_parameters(depthnet)
    assert n == DEPTHNET_PARAMETERS
    assert abs(n - 10.29e6) / 10.29e6 < 0.005


@pytest.mark.parametrize("h,w", [(64, 64), (128, 192)])
def test_output_shapes_and_positive(depthnet, h, w):
    with torch.no_grad():
        outs = depthnet(torch.randn(2, 6, h, w))
    assert [tuple(o.shape) for o in outs] == expected_shapes(2, h, w)
    assert all(bool((o > 0).all()) for o in outs)


def test_train_mode_returns_all_scales(tiny):
    tiny.train()
    outs = tiny(torch.randn(2, 6, 64, 128))
    assert [tuple(o.shape) for o in outs] == expected_shapes(2, 64, 128)


@pytest.mark.parametrize("shape", [(1, 6, 64, 96), (1, 6, 100, 64), (1, 3, 64, 64), (6, 64, 64)])
def test_bad_input_raises(tiny, shape):
    with pytest.raises(ValueError, match="DepthNet"):
        tiny(torch.randn(*shape))


def test_tiny_variant(tiny):
    assert count_parameters(tiny) < DEPTHNET_PARAMETERS / 20
    tiny.eval()
    with torch.no_grad():
        outs = tiny(torch.randn(1, 6, 128, 192))
    assert [tuple(o.shape) for o in outs] == expected_shapes(1, 128, 192)
    assert all(bool((o > 0).all()) for o in outs)


def test_macs(depthnet):
    m64 = macs(depthnet, 64, 64)
    assert abs(m64 - 0.072e9) / 0.072e9 < 0.10
    # every layer's spatial size doubles with the input, so MACs scale exactly ×4
    assert macs(depthnet, 128, 128) == 4 * m64
    assert macs(depthnet, 256, 256) == 16 * m64
    assert not depthnet.training  # mode restored


def test_macs_restores_training_mode(tiny):
    tiny.train()
    macs(tiny, 64, 64)
    assert tiny.training


def test_registry():
    assert {"depthnet", "depthnet-tiny"} <= set(list_models())
    assert {"flownets-depth", "flownets-flow", "oracle-flow", "constant"} <= set(list_models())
    assert list_models() == sorted(MODELS)
    for spec in MODELS.values():
        assert spec.kind in KINDS
        assert spec.trainable == (spec.kind.target is not None) == (spec.build is not None)
        if not spec.trainable:
            with pytest.raises(ValueError, match="no network"):
                build_model(spec.name)
            continue
        r = spec.recipe  # depth networks are trained like DepthNet (thesis Table 3.5),
        # flow networks with the public FlowNetS optimiser (Adam, lr 1e-4), same batch and epochs
        if spec.kind.target is Target.VIDEO:  # thesis 5.4.2: Adam, lr 2e-4; eq. 5.5's 1/2^s
            assert (r.optimizer, r.lr, r.momentum, r.beta2) == ("adam", 2e-4, 0.9, 0.999)
            scales = 5 if spec.kind is UNSUPERVISED else 4  # DepthNet's, DispNet's (sfmlearner)
            assert r.loss_weights == (1, 0.5, 0.25, 0.125, 0.0625)[:scales]
            assert r.sequence_length == 5
            continue
        lr = 1e-4 if spec.kind is FLOW else 1e-2
        assert r.lr == lr and r.batch_size == 256 and r.epochs == 55
        assert [round(f * r.epochs) for f in r.milestones] == [19, 30, 44, 53]
        assert r.loss_weights == (0.32, 0.08, 0.02, 0.01, 0.005)
        assert r.loss_scale == (1 / 20 if spec.kind is FLOW else 1.0)
        if spec.name.endswith("-tiny"):  # full widths: the fixture test builds them
            channels = 2 if spec.kind.target is Target.FLOW else 1
            with torch.no_grad():
                out = spec.build().eval()(torch.zeros(1, 6, 64, 64))
            assert out[0].shape == (1, channels, 16, 16)
    with pytest.raises(ValueError, match="depthnet-tiny"):
        build_model("nope")


def test_kinds_say_how_a_method_trains_and_is_scored():
    """The registry's kinds: which train, on what target, and which metric picks best.pt."""
    kinds = {spec.name: spec.kind for spec in MODELS.values()}
    assert {k.name for k in KINDS} == {
        *("depth", "flow", "unsupervised-depth", "scale-free-depth", "oracle-flow", "constant"),
        "given-depth",  # eval --predictions: another method's files, no network
    }
    assert kinds["depthnet-unsup"].target is Target.VIDEO and kinds["depthnet-unsup"].trains
    assert kinds["depthnet-unsup"].scored_as is kinds["depthnet"].scored_as
    assert kinds["depthnet"].target is Target.DEPTH and kinds["depthnet"].best_by == "mae"
    assert kinds["flownets-flow"].target is Target.FLOW and kinds["flownets-flow"].best_by == "epe"
    assert not kinds["oracle-flow"].trains and not kinds["constant"].trains
    assert kinds["depthnet-clamped"].scored_as is kinds["flownets-depth"].scored_as
    with pytest.raises(ValueError, match="go together"):  # a network needs a training kind
        ModelSpec("bad", "a network of a kind that does not train", MODELS["depthnet"].build,
                  kind=MODELS["constant"].kind)  # fmt: skip


def test_init_statistics(depthnet):
    """Weights ~ N(0, 2 / (k·k·C_out)), biases 0, BN weight 1 / bias 0 (the public code)."""
    w = depthnet.conv6_1[0].weight  # 512·512·9 samples
    assert abs(w.std().item() / (2 / (9 * 512)) ** 0.5 - 1) < 0.01
    t = depthnet.deconv5[0].weight  # transposed conv: fan-out uses out_channels = 256
    assert abs(t.std().item() / (2 / (16 * 256)) ** 0.5 - 1) < 0.01
    assert torch.count_nonzero(depthnet.deconv5[0].bias) == 0
    assert torch.count_nonzero(depthnet.predict_depth2.bias) == 0
    assert torch.all(depthnet.conv1[1].weight == 1) and torch.all(depthnet.conv1[1].bias == 0)


def test_multiscale_l1_by_hand():
    """Each output against the target area-averaged to its size, weighted (thesis 3.6)."""
    from benchmark.engine.pair_step import multiscale_loss

    target = torch.tensor([[1.0, 1, 3, 3], [1, 1, 3, 3], [5, 5, 7, 7], [5, 5, 7, 7]])[None]
    outputs = [torch.full((1, 1, 2, 2), 3.0), torch.full((1, 1, 1, 1), 5.0)]
    # 2x2 target [[1, 3], [5, 7]]: mean |3 - t| = (2 + 0 + 2 + 4) / 4 = 2; 1x1 target 4: |5 - 4| = 1
    loss = multiscale_loss(outputs, target, (0.5, 0.25))
    assert loss.item() == pytest.approx(0.5 * 2 + 0.25 * 1)


def test_multiscale_epe_averages_valid_pixels_only():
    """Flow targets: each output pixel against the mean of the *valid* target pixels under it;
    output pixels over no valid pixel are left out."""
    from benchmark.engine.pair_step import multiscale_loss

    target = torch.empty(1, 2, 4, 4)
    target[:, 0], target[:, 1] = 3.0, 4.0  # EPE 5 against zero flow
    target[:, :, :2, :2] = float("nan")
    target[:, :, 0, 0] = torch.tensor([6.0, 8.0])  # the only valid pixel of its 2x2 cell
    outputs = [torch.zeros(1, 2, 2, 2), torch.zeros(1, 2, 1, 1)]
    # 2x2: cells (6, 8), (3, 4) x 3 -> (10 + 3 * 5) / 4
    # 1x1: 12 pixels (3, 4) and one (6, 8) -> mean (42, 56) / 13, norm 70 / 13
    loss = multiscale_loss(outputs, target, (1.0, 0.5))
    assert loss.item() == pytest.approx(25 / 4 + 0.5 * 70 / 13)
    target[:, :, 2:, :] = float("nan")  # the 2x2 output's bottom cells cover no valid pixel
    loss = multiscale_loss(outputs[:1], target, (1.0,))
    assert loss.item() == pytest.approx((10 + 5) / 2)


# FlowNetS (Dosovitskiy 2015): encoder convs 6→64 (7×7), 64→128 (5×5), 128→256 (5×5), then 3×3
# 256→256, 256→512, 512→512, 512→512, 512→512, 512→1024, 1024→1024, with biases: 24,050,752;
# bias-free 4×4 deconvs 1024→512, 1026→256, 770→128, 386→64: 14,563,328; bias-free 3×3
# predict_flow convs from 1024, 1026, 770, 386, 194 channels to 2: 61,200; four bias-free 4×4
# 2→2 up-convs: 256. Total 38,675,536 ≈ 38.7 M.
FLOWNETS_PARAMETERS = 38_675_536


def test_flownets_parameter_count():
    n = count_parameters(FlowNetS("flow"))
    assert n == FLOWNETS_PARAMETERS
    assert n == 24_050_752 + 14_563_328 + 61_200 + 256
    assert abs(n - 38.7e6) / 38.7e6 < 0.001
    # batch norm (the registry's trained variants): conv biases replaced by BN weight + bias
    encoder_channels = 64 + 128 + 256 + 256 + 512 + 512 + 512 + 512 + 1024 + 1024
    assert count_parameters(FlowNetS("flow", batch_norm=True)) == n + encoder_channels
    # depth head: 1 output channel instead of 2, so one channel less in each concatenation:
    # predict convs 9·(2·c − (c − 1)) fewer for c = 1026, 770, 386, 194 and 9·1024 for the
    # coarsest, up-convs 4·(64 − 16), deconvs fed by a concatenation 16·(256 + 128 + 64)
    depth = count_parameters(FlowNetS("depth"))
    fewer = 9 * (1024 + 1027 + 771 + 387 + 195) + 4 * 48 + 16 * (256 + 128 + 64)
    assert depth == n - fewer == 38_637_540
    assert count_parameters(MODELS["flownets-flow"].build()) == n + encoder_channels
    assert count_parameters(DepthNet()) * 3.7 < n  # thesis: DepthNet has ~4-5x fewer


def test_flownets_macs_and_outputs():
    model = FlowNetS("flow").eval()
    assert abs(macs(model, 512, 512) - 21e9) / 21e9 < 0.01  # about 21 GMAC at 512 px
    tiny = build_model("flownets-flow-tiny").eval()
    with torch.no_grad():
        outs = tiny(torch.randn(2, 6, 64, 128))
        depth = build_model("flownets-depth-tiny").eval()(torch.randn(2, 6, 64, 128))
    assert [tuple(o.shape) for o in outs] == [(2, 2, 64 // s, 128 // s) for s in (4, 8, 16, 32, 64)]
    assert [tuple(o.shape) for o in depth] == expected_shapes(2, 64, 128)
    assert all(bool((o > 0).all()) for o in depth)
    assert count_parameters(tiny) < FLOWNETS_PARAMETERS / 50
    with pytest.raises(ValueError, match="FlowNetS"):
        tiny(torch.randn(1, 6, 64, 96))


def test_untrained_flow_head_predicts_zero_flow_and_depth_head_does_not():
    x = torch.randn(2, 6, 64, 64)
    with torch.no_grad():
        flows = build_model("flownets-flow").eval()(x)
        depths = build_model("flownets-depth-tiny").eval()(x)
    assert all(bool((f == 0).all()) for f in flows)
    assert depths[0].std().item() > 0.01


def test_flow_recipe_is_the_public_flownets_adam():
    from benchmark.engine.runner import train_config

    cfg = train_config("flownets-flow", Path("d"), Path("o"))
    assert (cfg.optimizer, cfg.lr, cfg.momentum, cfg.beta2) == ("adam", 1e-4, 0.9, 0.999)
    assert (cfg.weight_decay, cfg.loss_scale, cfg.batch_size) == (4e-4, 1 / 20, 256)
    depth = train_config("depthnet", Path("d"), Path("o"), lr=0.02)
    assert (depth.optimizer, depth.lr, depth.dampening) == ("sgd", 0.02, 0.9)


def test_train_config_defaults_are_the_depthnet_recipe():
    """TrainConfig repeats no number of the registry: its recipe fields default to DepthNet's."""
    from dataclasses import asdict

    from benchmark.core.config import TrainConfig
    from benchmark.core.registry import DEPTH_RECIPE

    cfg = asdict(TrainConfig("depthnet", "d", "o"))
    assert {k: cfg[k] for k in asdict(DEPTH_RECIPE)} == asdict(DEPTH_RECIPE)


def test_flownets_trains_on_flow():
    """Steps of the recipe's optimizer (Adam) lower the multi-scale EPE of the tiny flow variant
    from its zero-flow start, towards a flow field with structure (a zero-mean random field
    would already be best matched by zero flow)."""
    from benchmark.engine.pair_step import multiscale_loss

    torch.manual_seed(0)
    model = build_model("flownets-flow-tiny").train()
    r = MODELS["flownets-flow-tiny"].recipe
    x = torch.randn(4, 6, 64, 64)
    target = torch.tensor([3.0, -2.0]).view(1, 2, 1, 1) + 0.3 * torch.randn(4, 2, 64, 64)
    target[0, :, :8] = float("nan")  # invalid pixels are ignored

    def loss() -> torch.Tensor:
        return multiscale_loss(model(x), target, r.loss_weights) * r.loss_scale

    opt = torch.optim.Adam(model.parameters(), lr=r.lr, betas=(r.momentum, r.beta2))
    before = loss()
    assert torch.isfinite(before)
    for _ in range(3):
        opt.zero_grad()
        loss().backward()
        opt.step()
    with torch.no_grad():
        assert loss().item() < before.item()


# --------------------------------------------------------------------------- checkpoint layout

FIXTURE = model_fixture.load()

# Outputs move with the CPU kernels oneDNN and ATen pick (instruction set, AMX, thread count), so
# they are compared by their sums: |sum - recorded| and |sum |x| - recorded| at most
# OUTPUT_TOL * recorded sum |x| per output scale. Measured on one Xeon (AVX-512, AMX) against
# the fixture, worst over the six networks and both modes, run in subprocesses:
# default 3.0e-8; ONEDNN_MAX_CPU_ISA=AVX2 4.1e-6 (the sum itself 7.4e-5 relative, what an AMD
# EPYC gave); ONEDNN_MAX_CPU_ISA=SSE41 6.0e-6; ATEN_CPU_CAPABILITY=default 1.7e-6; both at their
# lowest with OPENBLAS_CORETYPE=Sandybridge 5.5e-6. OUTPUT_TOL is the worst, rounded up.
OUTPUT_TOL = 1e-5
# Environments under which the tiny networks are run again in a subprocess.
KERNEL_VARIANTS = {
    "onednn-avx2": {"ONEDNN_MAX_CPU_ISA": "AVX2"},
    "onednn-sse41-aten-default": {"ONEDNN_MAX_CPU_ISA": "SSE41", "ATEN_CPU_CAPABILITY": "default"},
}


def assert_outputs_match(got: dict, want: dict) -> None:
    for mode, out in want.items():
        for scale, ((s, a), (ws, wa)) in enumerate(
            zip(got[mode]["sums"], out["sums"], strict=True)
        ):
            deviation = max(abs(s - ws), abs(a - wa)) / wa
            assert deviation <= OUTPUT_TOL, (mode, scale, deviation)


@pytest.mark.parametrize("name", sorted(FIXTURE["models"]))
def test_state_dict_layout_and_outputs_are_those_of_the_fixture(name):
    """Names, shapes and order of every state_dict entry and parameter as recorded before
    DepthNet and FlowNetS shared their code (checkpoints load with strict=True, optimiser states
    keep their order); a checkpoint built from those names alone loads strictly and gives the
    recorded outputs; seed 0 gives the recorded initial weights where torch fills them with the
    same kernels (same version and ATen CPU capability: its vectorised normal_ differs between
    "default" and AVX2/AVX-512)."""
    want = FIXTURE["models"][name]
    got = model_fixture.describe(name)
    assert list(got["state_dict"].items()) == list(want["state_dict"].items())
    assert got["parameters"] == want["parameters"]
    assert_outputs_match(got["outputs"], want["outputs"])
    if model_fixture.environment() == FIXTURE["environment"]:
        assert got["init_sha256"] == want["init_sha256"]


@pytest.mark.parametrize("variant", sorted(KERNEL_VARIANTS))
def test_fixture_outputs_hold_under_other_cpu_kernels(variant):
    """The tiny networks, run with other oneDNN / ATen kernels, stay within OUTPUT_TOL."""
    env = {**os.environ, **KERNEL_VARIANTS[variant]}
    names = [n for n in FIXTURE["models"] if n.endswith("-tiny")]
    script = Path(model_fixture.__file__)
    proc = subprocess.run(
        [sys.executable, str(script), "--describe", *names],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    got = json.loads(proc.stdout)
    for name in names:
        assert_outputs_match(got[name]["outputs"], FIXTURE["models"][name]["outputs"])
