"""benchmark/flight/dynamics.py: limits, exact integration, the stabilised camera's pose."""

from __future__ import annotations

import math

import numpy as np
import pytest

from benchmark.flight.dynamics import (
    DroneState,
    DynamicsConfig,
    camera_pose,
    rollout,
    step,
    turn,
)
from stillbox_gen.camera import project

CFG = DynamicsConfig()


def test_constant_acceleration_is_integrated_exactly():
    """From rest, a = 1 m/s^2 along x for 10 steps of 0.1 s: x = a t^2 / 2 = 0.5 m, v = 1."""
    s = DroneState(np.zeros(3), np.zeros(3), 0.0)
    for _ in range(10):
        s = step(s, np.array([1.0, 0, 0]), 0.0, CFG)
    assert s.position == pytest.approx([0.5, 0, 0])
    assert s.velocity == pytest.approx([1.0, 0, 0])


def test_speed_and_acceleration_limits_hold_under_any_command():
    rng = np.random.default_rng(0)
    s = DroneState(np.zeros(3), np.zeros(3), 0.0)
    for _ in range(500):
        v0 = s.velocity
        s = step(s, rng.normal(scale=20.0, size=3), rng.uniform(-4, 4), CFG)
        assert np.linalg.norm(s.velocity) <= CFG.max_speed + 1e-9
        assert np.linalg.norm(s.velocity - v0) <= CFG.max_accel * CFG.dt + 1e-9


def test_a_long_push_saturates_at_the_speed_limit():
    s = DroneState(np.zeros(3), np.zeros(3), 0.0)
    for _ in range(50):
        s = step(s, np.array([0.0, 100.0, 0.0]), 0.0, CFG)
    assert s.velocity == pytest.approx([0, CFG.max_speed, 0])


def test_yaw_turns_the_short_way_at_the_rate_limit():
    most = CFG.max_yaw_rate * CFG.dt
    assert turn(0.0, 1.0, CFG) == pytest.approx(most)
    assert turn(0.0, -1.0, CFG) == pytest.approx(-most)
    assert turn(3.0, -3.0, CFG) == pytest.approx(3.0 + most)  # through pi, not through 0
    assert turn(0.0, 0.01, CFG) == pytest.approx(0.01)


def test_rollout_reaches_a_target_velocity_within_the_limits():
    targets = np.array([[2.0, 0, 0], [0, 0, 0], [0, -1.0, 1.0]])
    p, v = rollout(np.zeros(3), np.array([0.0, 1.0, 0]), targets, 20, CFG)
    assert p.shape == v.shape == (3, 20, 3)
    assert v[:, -1] == pytest.approx(targets)
    dv = np.diff(np.concatenate([np.broadcast_to([0.0, 1.0, 0], (3, 1, 3)), v], 1), axis=1)
    assert np.linalg.norm(dv, axis=-1).max() <= CFG.max_accel * CFG.dt + 1e-9


@pytest.mark.parametrize("yaw", [0.0, 0.7, -2.0, math.pi])
def test_camera_pose_is_level_and_looks_along_the_yaw(yaw):
    pose = camera_pose(np.array([1.0, 2.0, 3.0]), yaw)
    r = pose[:3, :3]
    assert r.T @ r == pytest.approx(np.eye(3))
    assert np.linalg.det(r) == pytest.approx(1.0)
    assert r[:, 2] == pytest.approx([math.cos(yaw), math.sin(yaw), 0])  # forward, level
    assert r[:, 1] == pytest.approx([0, 0, -1])  # image down = world down
    K = np.array([[32.0, 0, 31.5], [0, 32.0, 31.5], [0, 0, 1]])
    world2cam = np.linalg.inv(pose)

    def pixel(p_world):
        return project((world2cam @ [*p_world, 1.0])[None, :3], K)[0]

    ahead = pose[:3, 3] + 10 * np.array([math.cos(yaw), math.sin(yaw), 0])
    left = np.array([-math.sin(yaw), math.cos(yaw), 0])  # +90 deg from the heading, Z up
    assert pixel(ahead) == pytest.approx([31.5, 31.5])
    assert pixel(ahead - 2 * left)[0] > 31.5  # right of the heading: right in the image
    assert pixel(ahead + [0, 0, 2])[1] < 31.5  # above: higher in the image
