"""benchmark/flight/controller.py: the sampling MPC on obstacle points given directly (no
rendering), flown in closed loop with the point-mass dynamics."""

from __future__ import annotations

import numpy as np
import pytest

from benchmark.flight.controller import (
    ControllerConfig,
    line_distances,
    nearest_distances,
    plan,
)
from benchmark.flight.dynamics import DroneState, DynamicsConfig, step

DYN = DynamicsConfig()
CTRL = ControllerConfig()
START, GOAL = np.zeros(3), np.array([15.0, 0.0, 0.0])


def fly_points(points: np.ndarray, steps: int = 200, goal=GOAL):
    """Closed loop with fixed world points; positions (T, 3) and the plans."""
    s = DroneState(START.copy(), np.zeros(3), 0.0)
    path, plans = [s.position], []
    for _ in range(steps):
        p = plan(s, START, goal, points, DYN, CTRL)
        s = step(s, p.accel, 0.0, DYN)
        path.append(s.position)
        plans.append(p)
        if np.linalg.norm(s.position - goal) < 0.5:
            break
    return np.array(path), plans


def brute_force_clearance(path: np.ndarray, points: np.ndarray) -> float:
    return min(float(np.linalg.norm(points - x, axis=1).min()) for x in path)


def test_helpers_against_hand_distances():
    pts = np.array([[0.0, 0, 0], [10.0, 0, 0]])
    traj = np.array([[[3.0, 4.0, 0.0], [9.0, 0.0, 0.0]]])
    assert nearest_distances(traj, pts) == pytest.approx(np.array([[5.0, 1.0]]))
    assert np.isinf(nearest_distances(traj, np.empty((0, 3)))).all()
    x = np.array([[5.0, 2.0, 0.0], [-3.0, 4.0, 0.0], [20.0, 0.0, 0.0]])
    assert line_distances(x, START, GOAL) == pytest.approx([2.0, 5.0, 5.0])


def test_no_obstacle_flies_straight_to_the_goal():
    path, plans = fly_points(np.empty((0, 3)))
    assert np.linalg.norm(path[-1] - GOAL) < 0.5
    assert np.abs(path[:, 1:]).max() < 1e-9  # on the line
    first = plans[0].accel
    assert first == pytest.approx([DYN.max_accel, 0, 0])  # full acceleration towards the goal
    speeds = np.linalg.norm(np.diff(path, axis=0), axis=1) / DYN.dt
    assert speeds.max() <= DYN.max_speed + 1e-9
    assert speeds.max() == pytest.approx(DYN.max_speed)  # it cruises at the limit
    # time: accelerate 1 s (1 m), cruise; within 2 s of the 15 m / 2 m/s + 1 s ideal
    assert len(path) - 1 <= (15.0 / DYN.max_speed + 1.0 + 2.0) / DYN.dt


def wall_points(x: float, half_width: float, spacing: float = 0.2) -> np.ndarray:
    g = np.arange(-half_width, half_width + 1e-9, spacing)
    y, z = np.meshgrid(g, g)
    return np.stack([np.full(y.size, x), y.ravel(), z.ravel()], axis=1)


def test_a_wall_across_the_path_stops_the_drone_outside_the_safety_radius():
    wall = wall_points(8.0, 8.0, spacing=0.4)
    path, plans = fly_points(wall, steps=100)
    assert brute_force_clearance(path, wall) > CTRL.safety_radius
    assert path[:, 0].max() < 8.0 - CTRL.safety_radius
    assert np.linalg.norm(path[-1] - path[-2]) / DYN.dt < 0.05  # at rest, not through
    assert all(p.feasible for p in plans)


def test_a_post_on_the_line_is_flown_around_to_the_goal():
    """A 1 m thick vertical post of points across the line: the drone drifts around it."""
    g = np.arange(-0.5, 0.51, 0.25)
    h = np.arange(-10.0, 10.01, 0.25)
    y, z = np.meshgrid(g, h)
    post = np.concatenate(
        [np.stack([7.0 + y.ravel() * 0 + dx, y.ravel(), z.ravel()], 1) for dx in g]
    )
    path, _ = fly_points(post)
    assert np.linalg.norm(path[-1] - GOAL) < 0.5
    assert brute_force_clearance(path, post) > CTRL.safety_radius
    assert np.abs(path[:, 1]).max() > CTRL.safety_radius  # it drifted sideways


def test_limits_hold_for_random_states_and_points():
    rng = np.random.default_rng(1)
    for _ in range(30):
        v = rng.normal(size=3)
        v *= rng.uniform(0, DYN.max_speed) / np.linalg.norm(v)
        s = DroneState(rng.normal(size=3), v, 0.0)
        pts = rng.uniform(-10, 10, size=(200, 3))
        p = plan(s, START, GOAL, pts, DYN, CTRL)
        assert np.linalg.norm(p.accel) <= DYN.max_accel + 1e-9
        assert np.linalg.norm(p.target) <= DYN.max_speed + 1e-9
        if p.feasible:
            assert nearest_distances(p.trajectory, pts).min() > CTRL.safety_radius


def test_inside_the_safety_radius_it_does_not_move_closer():
    """A point 0.5 m ahead: no candidate is feasible; the chosen one keeps the most distance,
    which from rest is staying put (every candidate goes forward or stops)."""
    pts = np.array([[0.5, 0.0, 0.0]])
    p = plan(DroneState(np.zeros(3), np.zeros(3), 0.0), START, GOAL, pts, DYN, CTRL)
    assert not p.feasible
    assert p.clearance == pytest.approx(0.5)
    assert np.linalg.norm(p.accel) == pytest.approx(0.0)


def test_a_wide_obstacle_beyond_the_horizon_is_turned_around_early():
    """A 6 m wide post 12 m ahead: without the cost-to-go the drone would close in until the
    straight plan fails, too near for any turn within the view; with it, it turns while far."""
    g = np.arange(-3.0, 3.01, 0.4)
    h = np.arange(-10.0, 10.01, 0.4)
    y, z = np.meshgrid(g, h)
    post = np.concatenate(
        [np.stack([np.full(y.size, 12.0 + dx), y.ravel(), z.ravel()], 1) for dx in (-0.5, 0.5)]
    )
    path, _ = fly_points(post, goal=np.array([20.0, 0.0, 0.0]), steps=250)
    assert np.linalg.norm(path[-1] - [20.0, 0, 0]) < 0.5
    assert brute_force_clearance(path, post) > CTRL.safety_radius
    turned = np.flatnonzero(np.abs(path[:, 1]) > 0.1)[0]
    assert path[turned, 0] < 12.0 - 3.0 - 2 * CTRL.safety_radius  # turned well before it
