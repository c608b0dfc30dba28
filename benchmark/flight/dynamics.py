"""Point-mass dynamics with speed and acceleration limits, and the stabilised camera's pose.

World frame (+Z up, metres, seconds). The drone is a point with position p and velocity v; each
control step of ``dt`` seconds applies a constant acceleration a with |a| <= max_accel:
v' = v + a dt, p' = p + (v + v') dt / 2 (exact for a constant acceleration), then |v'| is capped
at max_speed. The camera is stabilised: no roll, no pitch, its optical axis horizontal along the
yaw (angle from world +X towards +Y), which turns towards a target at most max_yaw_rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class DynamicsConfig:
    """``dt`` (s) per control step; limits in m/s, m/s^2 and rad/s. At the default 2 m/s and
    0.1 s a step moves the camera 0.2 m (StillBox frames: 0.1 m)."""

    dt: float = 0.1
    max_speed: float = 2.0
    max_accel: float = 2.0
    max_yaw_rate: float = math.radians(90.0)


@dataclass(frozen=True)
class DroneState:
    """Position and velocity (world, m and m/s) and yaw (rad) of the camera's optical axis."""

    position: np.ndarray
    velocity: np.ndarray
    yaw: float


def clip_norm(x: np.ndarray, most: float) -> np.ndarray:
    """Vectors x (..., 3) scaled down, where longer, to length ``most``."""
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    return x * np.minimum(1.0, most / np.maximum(n, 1e-12))


def accel_towards(v: np.ndarray, target: np.ndarray, cfg: DynamicsConfig) -> np.ndarray:
    """Acceleration (..., 3) that brings velocity v to ``target`` in one step, within the limit."""
    return clip_norm((target - v) / cfg.dt, cfg.max_accel)


def integrate(p: np.ndarray, v: np.ndarray, a: np.ndarray, cfg: DynamicsConfig):
    """(p', v') after one step of acceleration a (clipped to max_accel); arrays (..., 3)."""
    a = clip_norm(a, cfg.max_accel)
    v_next = clip_norm(v + a * cfg.dt, cfg.max_speed)
    return p + (v + v_next) * (cfg.dt / 2), v_next


def turn(yaw: float, target: float, cfg: DynamicsConfig) -> float:
    """Yaw (rad) after one step towards ``target`` at most max_yaw_rate, the short way round."""
    diff = (target - yaw + math.pi) % (2 * math.pi) - math.pi
    most = cfg.max_yaw_rate * cfg.dt
    return yaw + max(-most, min(most, diff))


def step(state: DroneState, accel: np.ndarray, yaw_target: float, cfg: DynamicsConfig):
    """The state one control step later."""
    p, v = integrate(state.position, state.velocity, np.asarray(accel, float), cfg)
    return DroneState(p, v, turn(state.yaw, yaw_target, cfg))


def rollout(p: np.ndarray, v: np.ndarray, targets: np.ndarray, steps: int, cfg: DynamicsConfig):
    """Positions and velocities (C, steps, 3) of C constant velocity ``targets`` (C, 3) tracked
    from (p, v) with accel_towards for ``steps`` steps (the controller's prediction)."""
    pos = np.broadcast_to(p, targets.shape).copy()
    vel = np.broadcast_to(v, targets.shape).copy()
    ps, vs = np.empty((len(targets), steps, 3)), np.empty((len(targets), steps, 3))
    for k in range(steps):
        pos, vel = integrate(pos, vel, accel_towards(vel, targets, cfg), cfg)
        ps[:, k], vs[:, k] = pos, vel
    return ps, vs


def camera_pose(position: np.ndarray, yaw: float) -> np.ndarray:
    """OpenCV camera-to-world 4x4 of the stabilised camera: z (forward) horizontal along the
    yaw, y (down) = world -Z, x (right) = y cross z."""
    c, s = math.cos(yaw), math.sin(yaw)
    m = np.eye(4)
    m[:3, 0] = [s, -c, 0.0]
    m[:3, 1] = [0.0, 0.0, -1.0]
    m[:3, 2] = [c, s, 0.0]
    m[:3, 3] = position
    return m


def heading(frm: np.ndarray, to: np.ndarray, default: float) -> float:
    """Yaw (rad) of the horizontal direction from ``frm`` to ``to``; ``default`` when above."""
    d = np.asarray(to, float) - np.asarray(frm, float)
    if math.hypot(d[0], d[1]) < 1e-9:
        return default
    return math.atan2(d[1], d[0])
