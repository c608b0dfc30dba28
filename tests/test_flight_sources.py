"""benchmark/flight/sources.py: the learned depth sources of the closed loop (a depth network
through the infer pipeline, a flow network through compare's geometry) against independent
maths, every source flying an empty room to its goal, and the depth error of what a source saw.

Networks are real registry networks saved as checkpoints; their finest prediction layer is set
by hand (a known output), so that what is tested is the pipeline around them: displacements
measured from the poses, the shift choice, the scaling, the flow-to-depth geometry.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from benchmark.core import registry
from benchmark.flight import raycast, simulate
from benchmark.flight.dynamics import camera_pose
from benchmark.flight.sources import UNSEEN, FlowDepth, NetworkDepth, Scored
from benchmark.flight.world import Obstacle, World

RES = 64
K = np.array([[32.0, 0, 31.5], [0, 32.0, 31.5], [0, 0, 1]])  # 90 deg at 64 px
ROOM = World((), np.zeros(3), np.array([30.0, 30.0, 30.0]))
START, GOAL = np.zeros(3), np.array([12.0, 0.0, 0.0])
D0 = 0.3  # m, the checkpoints' nominal displacement
CPU = torch.device("cpu")


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def checkpoint(path: Path, name: str, finest=None) -> Path:
    """A checkpoint as Trainer.checkpoint writes it; ``finest(state_dict)`` sets the finest
    prediction layer."""
    torch.manual_seed(0)
    state = registry.build_model(name).state_dict()
    if finest is not None:
        finest(state)
    ck = {
        "model": state,
        "model_name": name,
        "nominal_displacement": D0,
        "shift": 3,
        "camera": {"width": RES, "height": RES, "fov_deg": 90.0},
    }
    torch.save(ck, path)
    return path


def constant_output(metres: float):
    """DepthNet's finest output 1 + ELU(b) = metres everywhere (weights 0, bias b)."""

    def finest(state):
        state["predict_depth2.weight"].zero_()
        state["predict_depth2.bias"].fill_(metres - 1.0)

    return finest


def zero_flow(state):
    state["predict_flow2.weight"].zero_()


def render(world: World):
    def r(pose):
        d = raycast.render_depth(world, K, RES, RES, pose)
        return raycast.shade(d), d

    return r


def test_depth_network_scales_its_output_by_the_displacement_measured_from_the_poses(tmp_path):
    """Output c at the nominal displacement d0: depth c * d / d0, d = |p_t - p_{t-s}| of the
    shift s whose displacement is closest to d0 (the planner's first frame)."""
    src = NetworkDepth(checkpoint(tmp_path / "c.pt", "depthnet-tiny", constant_output(8.0)), CPU)
    frames = [np.zeros((RES, RES, 3), np.uint8)] * 4
    xs = [0.0, 0.1, 0.25, 0.45]  # steps 0.1, 0.15, 0.2 m: back from 0.45 m: 0.2, 0.35, 0.45
    poses = [camera_pose(np.array([x, 0.0, 1.0]), 0.0) for x in xs]
    truth = np.ones((RES, RES), np.float32)
    depth = src(frames, truth, poses)
    assert depth == pytest.approx(np.full((RES, RES), 8.0 * 0.35 / D0), rel=1e-5)  # shift 2
    assert (src(frames[:1], truth, poses[:1]) == UNSEEN).all()  # no earlier frame
    hover = [poses[0]] * 3
    assert (src(frames[:3], truth, hover) == UNSEEN).all()  # no motion: no depth


def exact_flow(depth: np.ndarray, pose_now: np.ndarray, pose_then: np.ndarray) -> np.ndarray:
    """Flow (2, H, W) px of the current frame's pixels to where they were in the earlier frame:
    back-projected to the world with the current pose, projected with the earlier one."""
    u, v = np.meshgrid(np.arange(RES, dtype=float), np.arange(RES, dtype=float))
    cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    world = (cam * depth[..., None]) @ pose_now[:3, :3].T + pose_now[:3, 3]
    then = (world - pose_then[:3, 3]) @ pose_then[:3, :3]
    uv = then[..., :2] / then[..., 2:] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    return np.stack([uv[..., 0] - u, uv[..., 1] - v])


class ExactFlowNetwork(torch.nn.Module):
    """Stands in for FlowNetS' forward pass: the exact flow at 1/4 resolution (as FlowNetS
    outputs it, in full-resolution pixels), so that FlowDepth's geometry is tested alone."""

    def __init__(self, flow: np.ndarray):
        super().__init__()
        self.flow = torch.from_numpy(flow).float()[None]

    def forward(self, x):
        return [torch.nn.functional.avg_pool2d(self.flow, 4)]


@pytest.mark.parametrize("yaw", [0.0, 2.0])
def test_flow_network_depth_uses_the_translation_in_the_current_camera_axes(tmp_path, yaw):
    """Exact flow of a camera moving forward and sideways (any heading): the depth back is the
    true depth away from the focus of expansion (1/4-resolution flow upsampled: smooth
    surfaces only)."""
    src = FlowDepth(checkpoint(tmp_path / "f.pt", "flownets-flow-tiny"), CPU, K)
    wall = World(
        (Obstacle("slab", np.array([0.3, 80.0, 80.0]), np.array([9.0, 0, 0]), np.eye(3)),),
        np.zeros(3),
        np.array([30.0, 30.0, 30.0]),
    )
    c, s = np.cos(yaw), np.sin(yaw)
    turn = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    world = World(
        tuple(Obstacle(o.kind, o.dimensions, turn @ o.location, turn) for o in wall.obstacles),
        wall.box_center,
        wall.box_half_extents,
    )
    positions = [turn @ np.array([0.0, 0.0, 0.0]), turn @ np.array([0.2, 0.15, 0.05])]
    poses = [camera_pose(p, yaw) for p in positions]
    truth = raycast.render_depth(world, K, RES, RES, poses[-1])
    src.method.model = ExactFlowNetwork(exact_flow(truth.astype(float), poses[1], poses[0]))
    frames = [np.zeros((RES, RES, 3), np.uint8)] * 2
    depth = src(frames, truth, poses)
    assert np.median(np.abs(depth - truth) / truth) < 0.02
    assert (src(frames[:1], truth, poses[:1]) == UNSEEN).all()


@pytest.fixture(scope="module")
def far_sources(tmp_path_factory):
    """Learned sources that see nothing near: a DepthNet whose output is 200 m at d0 and a
    FlowNetS of zero flow (depth_from_flow: MAX_DEPTH)."""
    d = tmp_path_factory.mktemp("sources")
    return {
        "depth network": NetworkDepth(
            checkpoint(d / "far.pt", "depthnet-tiny", constant_output(200.0)), CPU, shifts=2
        ),
        "flow network": FlowDepth(
            checkpoint(d / "zero.pt", "flownets-flow-tiny", zero_flow), CPU, K
        ),
    }


@pytest.mark.parametrize("name", ["oracle", "constant", "depth network", "flow network"])
def test_no_obstacle_reaches_the_goal_with_every_source(far_sources, name):
    source = {"oracle": simulate.oracle, "constant": simulate.constant(100.0)}.get(name)
    scored = Scored(source or far_sources[name])
    scored.reset()
    r = simulate.fly(ROOM, START, GOAL, K, render(ROOM), scored)
    assert r.outcome == "reached" and r.path_ratio == pytest.approx(1.0, abs=0.02)
    e = scored.errors()
    assert e["depth_frames"] >= r.steps - (0 if name in ("oracle", "constant") else 1)
    if name == "oracle":
        assert e["depth_mae_m"] == 0 and e["depth_mre"] == 0


def test_scored_errors_against_hand_values():
    """MAE and MRE per frame (core.metrics), then the mean over the frames with depth."""
    truth = np.full((4, 4), 10.0, np.float32)
    answers = iter([np.full((4, 4), 12.0), np.full((4, 4), UNSEEN), np.full((4, 4), 9.0)])
    scored = Scored(lambda rgbs, true_depth, poses: next(answers))
    scored.reset()
    for _ in range(3):
        scored([], truth, [])
    e = scored.errors()
    assert e == {
        "depth_frames": 2,
        "depth_mae_m": pytest.approx(1.5),
        "depth_mre": pytest.approx(0.15),
        "near_mae_m": pytest.approx(1.5),  # every pixel is within the 15 m range
        "missed_near": 0.0,
        "phantom_near": None,  # no pixel is truly beyond it
    }
    scored.reset()
    assert scored.errors() == dict.fromkeys(e) | {"depth_frames": 0}


def test_scored_near_range_errors_against_hand_values():
    """Within the sensing range: an obstacle estimated beyond it is missed, a far wall estimated
    within it is a phantom; the near MAE ignores the far pixels."""
    truth = np.array([[4.0, 8.0, 30.0, 40.0]], np.float32)  # two near pixels, two far
    answers = iter([np.array([[5.0, 20.0, 10.0, 40.0]]), np.array([[4.0, 8.0, 30.0, 40.0]])])
    scored = Scored(lambda rgbs, true_depth, poses: next(answers), near_range=15.0)
    scored([], truth, [])
    e = scored.errors()
    assert e["near_mae_m"] == pytest.approx((1 + 12) / 2)
    assert e["missed_near"] == pytest.approx(0.5) and e["phantom_near"] == pytest.approx(0.5)
    scored([], truth, [])  # exact: the means over both frames halve
    e = scored.errors()
    assert e["near_mae_m"] == pytest.approx(13 / 4)
    assert e["missed_near"] == pytest.approx(0.25) and e["phantom_near"] == pytest.approx(0.25)
