"""A sampling-based model predictive controller (thesis 6.5.1): follow the straight line to the
goal, drift around (or stop before) the obstacle points seen in the depth maps.

At each control step, from the drone's state (world frame, +Z up) it predicts with the point-mass
model of dynamics.py one trajectory per candidate: a constant target velocity, tracked for
``horizon`` steps, followed by a full brake to rest (so a chosen plan always ends in a safe stop).
Candidates: the direction to the goal turned by ``yaw_offsets`` (about world Z) and
``pitch_offsets`` (elevation), at most 44 deg from it by default: the camera faces the goal's
heading (simulate.py), so the drone flies into the space its 90 deg view has seen; each at
``speed_fractions`` of the desired speed min(max_speed, sqrt(2 a d)) (d: distance to the goal);
plus "stop" (target velocity 0). A candidate is feasible when none of its predicted
positions (braking tail included) comes within ``safety_radius`` of an obstacle point. Among the
feasible ones it takes the least cost

    w_goal togo(p_*) + w_line mean_k dist(p_k, line) + w_near mean_k max(0, s + m - d_k)^2
    + w_change |target - v|^2

(p_k: predicted positions of the plan, k = 1 .. horizon; p_* the one nearest the goal, so that
near the goal the drone flies through it rather than stopping short; togo: the length of a
short clear way from there to the goal around the seen points, detour.py, a cost-to-go that
makes the drone turn early, towards the shorter side, rather than stop in front of an obstacle
beyond the horizon; d_k: their distance to the nearest point, s the safety radius, m
``near_margin``). With no feasible candidate it takes the one
whose trajectory keeps farthest from the points. It returns the first acceleration of the chosen
plan.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .detour import cost_to_go, via_points
from .dynamics import DroneState, DynamicsConfig, accel_towards, rollout
from .obstacles import voxel_filter

DEFAULT_YAW_OFFSETS = tuple(math.radians(d) for d in (-40, -30, -20, -10, 0, 10, 20, 30, 40))
DEFAULT_PITCH_OFFSETS = tuple(math.radians(d) for d in (-20, 0, 20))


@dataclass(frozen=True)
class ControllerConfig:
    """Horizon in steps, distances in metres, angles in radians, dimensionless weights."""

    horizon: int = 20
    safety_radius: float = 1.0
    near_margin: float = 1.0
    yaw_offsets: tuple[float, ...] = DEFAULT_YAW_OFFSETS
    pitch_offsets: tuple[float, ...] = DEFAULT_PITCH_OFFSETS
    speed_fractions: tuple[float, ...] = (1.0, 0.5)
    w_goal: float = 1.0
    w_line: float = 0.3
    w_near: float = 5.0
    w_change: float = 0.05
    coarse_voxel: float = 0.5  # m, points thinned to one per cube of this side for the ways


@dataclass(frozen=True)
class Plan:
    """The chosen command: ``accel`` (m/s^2, world) for this step, ``target`` velocity (m/s),
    ``feasible`` (False: no candidate kept the safety radius), ``trajectory`` (T, 3) predicted
    positions (braking tail included) and its least distance ``clearance`` (m) to the points."""

    accel: np.ndarray
    target: np.ndarray
    feasible: bool
    trajectory: np.ndarray
    clearance: float


def candidate_velocities(
    position: np.ndarray, goal: np.ndarray, dyn: DynamicsConfig, cfg: ControllerConfig
) -> np.ndarray:
    """Target velocities (C, 3), m/s: turned directions to the goal at fractions of the
    desired speed; the last row is "stop" (zero)."""
    d = goal - position
    dist = float(np.linalg.norm(d))
    azimuth = math.atan2(d[1], d[0])
    elevation = math.asin(max(-1.0, min(1.0, d[2] / max(dist, 1e-9))))
    speed = min(dyn.max_speed, math.sqrt(2 * dyn.max_accel * dist))
    rows = []
    for da in cfg.yaw_offsets:
        for de in cfg.pitch_offsets:
            az, el = azimuth + da, elevation + de
            u = [math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)]
            rows += [[c * speed * f for c in u] for f in cfg.speed_fractions]
    return np.array([*rows, [0.0, 0.0, 0.0]])


def nearest_distances(trajectory: np.ndarray, points: np.ndarray, chunk: int = 4096) -> np.ndarray:
    """Distance (m) from each position (..., 3) to the nearest of points (P, 3); inf if P = 0."""
    flat = trajectory.reshape(-1, 3)
    best = np.full(len(flat), np.inf)
    for i in range(0, len(points), chunk):
        p = points[i : i + chunk]
        d2 = (flat**2).sum(1)[:, None] + (p**2).sum(1)[None, :] - 2 * flat @ p.T
        best = np.minimum(best, np.sqrt(np.maximum(d2.min(axis=1), 0.0)))
    return best.reshape(trajectory.shape[:-1])


def line_distances(x: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance (m) from positions (..., 3) to the segment a-b (a, b (3,) or broadcastable)."""
    ab = b - a
    t = np.clip(((x - a) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-12), 0.0, 1.0)
    return np.linalg.norm(x - (a + t[..., None] * ab), axis=-1)


def predict(state: DroneState, targets: np.ndarray, dyn: DynamicsConfig, cfg: ControllerConfig):
    """Predicted positions (C, horizon + brake steps, 3): the plan, then a full brake."""
    plan_p, plan_v = rollout(state.position, state.velocity, targets, cfg.horizon, dyn)
    brake = int(math.ceil(dyn.max_speed / (dyn.max_accel * dyn.dt))) + 1
    tail_p, _ = rollout(plan_p[:, -1], plan_v[:, -1], np.zeros_like(targets), brake, dyn)
    return np.concatenate([plan_p, tail_p], axis=1)


def plan(
    state: DroneState,
    start: np.ndarray,
    goal: np.ndarray,
    points: np.ndarray,
    dyn: DynamicsConfig,
    cfg: ControllerConfig,
) -> Plan:
    """The command for this step given obstacle ``points`` (world, (P, 3))."""
    targets = candidate_velocities(state.position, goal, dyn, cfg)
    traj = predict(state, targets, dyn, cfg)
    reach = np.linalg.norm(traj - state.position, axis=-1).max() + cfg.safety_radius + 1.0
    near_pts = points[np.linalg.norm(points - state.position, axis=1) <= reach]
    dist = nearest_distances(traj, near_pts)
    plan_part = slice(0, cfg.horizon)
    coarse = voxel_filter(points, cfg.coarse_voxel)
    # the ways keep the safety radius, so they start clear from every feasible plan
    vias = via_points(state.position, goal, coarse, cfg.safety_radius)
    nearest = np.linalg.norm(traj[:, plan_part] - goal, axis=-1).argmin(axis=1)
    ends = traj[np.arange(len(traj)), nearest]
    togo = cost_to_go(ends, goal, vias, coarse, cfg.safety_radius)
    least = dist.min(axis=1)
    cost = (
        cfg.w_goal * togo
        + cfg.w_line * line_distances(traj[:, plan_part], start, goal).mean(axis=1)
        + cfg.w_near
        * (np.maximum(0.0, cfg.safety_radius + cfg.near_margin - dist[:, plan_part]) ** 2).mean(1)
        + cfg.w_change * ((targets - state.velocity) ** 2).sum(axis=1)
    )
    feasible = least > cfg.safety_radius
    best = (
        int(np.argmin(np.where(feasible, cost, np.inf))) if feasible.any() else int(least.argmax())
    )
    accel = accel_towards(state.velocity, targets[best], dyn)
    return Plan(accel, targets[best], bool(feasible.any()), traj[best], float(least[best]))
