"""The closed loop: render, estimate depth, sense, plan, move; scored against the truth.

Each control step renders the stabilised camera at the drone's pose (``render(cam2world) ->
(rgb, true_depth)``, OpenCV pose, RGB (H, W, 3) uint8, planar depth (H, W) m), asks the depth
source under test for a depth map, adds its points to the controller's memory, plans, and moves
the drone one step. The move is checked against the World (never against the estimated depth):
a swept sphere of ``drone_radius`` touching a surface ends the episode as "collided"; coming
within ``reach_radius`` of the goal as "reached"; else "timeout" after ``max_steps``.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from .choices import MAX_STEPS, YAW_MODES
from .controller import ControllerConfig, plan
from .dynamics import DroneState, DynamicsConfig, camera_pose, heading, step
from .obstacles import PointMemory, SensingConfig
from .world import World

Render = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
#: depth_source(rgb_history, true_depth, poses) -> depth (H, W) m: frames and OpenCV poses so
#: far (oldest first, the current one last, at most HISTORY), the current frame's true depth.
DepthSource = Callable[[Sequence[np.ndarray], np.ndarray, Sequence[np.ndarray]], np.ndarray]
HISTORY = 8


def oracle(
    rgb_history: Sequence[np.ndarray], true_depth: np.ndarray, poses: Sequence[np.ndarray]
) -> np.ndarray:
    """The rendered depth itself."""
    return true_depth


def constant(value: float) -> DepthSource:
    """A source that sees every pixel at ``value`` metres (the baseline that sees nothing when
    ``value`` exceeds the sensing range)."""
    return lambda rgb_history, true_depth, poses: np.full(true_depth.shape, value, np.float32)


@dataclass(frozen=True)
class FlightConfig:
    """``drone_radius`` (m): the collision sphere; ``reach_radius`` (m) around the goal;
    ``max_steps``: control steps before "timeout"; ``yaw``: the camera faces the goal from
    where the drone is ("goal", turning at most max_yaw_rate), or keeps the heading of the
    straight line start-goal ("line": frames differ by a pure translation, as StillBox's)."""

    dynamics: DynamicsConfig = field(default_factory=DynamicsConfig)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    sensing: SensingConfig = field(default_factory=SensingConfig)
    drone_radius: float = 0.25
    reach_radius: float = 1.0
    max_steps: int = MAX_STEPS
    yaw: str = "goal"


@dataclass
class EpisodeResult:
    """``outcome`` "reached" | "collided" | "timeout"; ``min_clearance`` (m) of the drone's
    sphere to any surface along the flown path (< 0: collided); ``straight_length`` (m) from
    the start to the goal's reach sphere, ``path_ratio`` = flown length / it (1: straight);
    seconds per step (render, depth, control); ``positions`` (steps + 1, 3) world."""

    outcome: str
    steps: int
    min_clearance: float
    path_length: float
    straight_length: float
    render_s: float
    depth_s: float
    control_s: float
    positions: np.ndarray = field(repr=False)

    @property
    def path_ratio(self) -> float:
        return self.path_length / self.straight_length


def fly(
    world: World,
    start: np.ndarray,
    goal: np.ndarray,
    K: np.ndarray,
    render: Render,
    depth_source: DepthSource,
    cfg: FlightConfig = FlightConfig(),  # noqa: B008 (frozen)
) -> EpisodeResult:
    """One episode from ``start`` at rest, camera facing the goal."""
    if cfg.yaw not in YAW_MODES:
        raise ValueError(f"yaw must be one of {YAW_MODES}, got {cfg.yaw!r}")
    start, goal = np.asarray(start, float), np.asarray(goal, float)
    line_yaw = heading(start, goal, 0.0)
    state = DroneState(start, np.zeros(3), line_yaw)
    memory = PointMemory(cfg.sensing)
    rgbs: deque = deque(maxlen=HISTORY)
    poses: deque = deque(maxlen=HISTORY)
    timing = np.zeros(3)
    positions = [start]
    min_clear = float(world.clearance(start[None], cfg.drone_radius)[0])
    outcome = "timeout"
    for _ in range(cfg.max_steps):
        t0 = time.perf_counter()
        pose = camera_pose(state.position, state.yaw)
        rgb, true_depth = render(pose)
        t1 = time.perf_counter()
        rgbs.append(rgb)
        poses.append(pose)
        depth = depth_source(list(rgbs), true_depth, list(poses))
        t2 = time.perf_counter()
        memory.add(depth, K, pose)
        command = plan(state, start, goal, memory.points(), cfg.dynamics, cfg.controller)
        yaw_target = line_yaw if cfg.yaw == "line" else heading(state.position, goal, state.yaw)
        nxt = step(state, command.accel, yaw_target, cfg.dynamics)
        timing += [t1 - t0, t2 - t1, time.perf_counter() - t2]
        swept = world.swept(state.position, nxt.position, cfg.drone_radius)
        min_clear = min(min_clear, swept.min_clearance)
        if swept.collided:
            hit = state.position + swept.first_hit * (nxt.position - state.position)
            positions.append(hit)
            outcome = "collided"
            break
        state = nxt
        positions.append(state.position)
        if np.linalg.norm(state.position - goal) <= cfg.reach_radius:
            outcome = "reached"
            break
    path = np.array(positions)
    steps = len(path) - 1
    per_step = timing / max(steps, 1)
    return EpisodeResult(
        outcome,
        steps,
        min_clear,
        float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum()),
        float(np.linalg.norm(goal - start)) - cfg.reach_radius,
        *(float(x) for x in per_step),
        positions=path,
    )
