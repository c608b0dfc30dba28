"""benchmark/flight/raycast.py and simulate.py: the analytic renderer against hand geometry, and
the closed loop flown without Blender (oracle and constant depth)."""

from __future__ import annotations

import numpy as np
import pytest

from benchmark.flight import raycast, simulate
from benchmark.flight.dynamics import camera_pose
from benchmark.flight.episodes import flight_scene_config, make_episode
from benchmark.flight.obstacles import camera_points, to_world
from benchmark.flight.world import Obstacle, World

RES = 32
K = np.array([[16.0, 0, 15.5], [0, 16.0, 15.5], [0, 0, 1]])  # 90 deg at 32 px
ROOM = (np.zeros(3), np.array([30.0, 30.0, 30.0]))
START, GOAL = np.zeros(3), np.array([15.0, 0.0, 0.0])


def world_of(*obstacles: Obstacle, box=ROOM) -> World:
    return World(tuple(obstacles), *box)


def renderer(world: World, seen: list | None = None):
    def render(pose: np.ndarray):
        if seen is not None:
            seen.append(pose)
        depth = raycast.render_depth(world, K, RES, RES, pose)
        return raycast.shade(depth), depth

    return render


def sphere_planar_depth(centre: np.ndarray, radius: float) -> np.ndarray:
    """Camera-frame sphere: nearest root s of |s d - c| = r with d = K^-1 (u, v, 1) (z = 1, so
    s is the planar depth); NaN where the ray misses."""
    u, v = np.meshgrid(np.arange(RES, dtype=float), np.arange(RES, dtype=float))
    d = np.stack([(u - 15.5) / 16, (v - 15.5) / 16, np.ones_like(u)], -1)
    a, b = (d * d).sum(-1), -2 * (d @ centre)
    disc = b * b - 4 * a * (centre @ centre - radius**2)
    return np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.nan)


def test_raycast_walls_cube_and_sphere_against_hand_geometry():
    pose = camera_pose(np.zeros(3), 0.0)  # looking along world +X
    # the front wall at x = 20 fills the 90 deg view (+-20 m < 30 m): constant depth 20
    walls = world_of(box=(np.zeros(3), np.array([20.0, 30.0, 30.0])))
    assert raycast.render_depth(walls, K, RES, RES, pose) == pytest.approx(np.full((RES, RES), 20))
    # a 2 x 4 x 4 m box at x = 10: its face at x = 9 where |lateral| < 2 m, i.e. |u - c| < 16 * 2/9
    cube = Obstacle("cube", np.array([2.0, 4.0, 4.0]), np.array([10.0, 0, 0]), np.eye(3))
    d = raycast.render_depth(world_of(cube), K, RES, RES, pose)
    off = np.abs(np.arange(RES) - 15.5)
    inside = (off[:, None] < 16 * 2 / 9) & (off[None, :] < 16 * 2 / 9)
    assert d[inside] == pytest.approx(9.0, abs=2e-3)
    assert d[~inside] == pytest.approx(30.0)  # beside it, the wall at x = 30
    # a sphere of radius 3 at (12, 2, 1) world = camera (right -2, down -1, forward 12)
    ball = Obstacle("sphere", np.full(3, 6.0), np.array([12.0, 2.0, 1.0]), np.eye(3))
    d = raycast.render_depth(world_of(ball), K, RES, RES, pose)
    truth = sphere_planar_depth(np.array([-2.0, -1.0, 12.0]), 3.0)
    hit = np.isfinite(truth)
    assert hit.sum() > 40  # about pi (16 * 3 / 12)^2 = 50 pixels
    # exact to the tolerance but where rays graze the silhouette: sphere tracing stops within
    # HIT_TOLERANCE of the surface, up to sqrt(2 r tol) = 8 cm early there (nearer, never farther)
    err = d[hit] - truth[hit]
    assert err.max() < 2e-3 and err.min() > -0.08
    assert np.mean(np.abs(err) < 2e-3) > 0.8
    assert d[~hit] == pytest.approx(30.0)


def test_raycast_points_of_a_generated_scene_lie_on_its_surfaces():
    """Every kind of primitive: the back-projected depth (obstacles.py) lands on a surface."""
    e = make_episode(0, 1)
    pose = camera_pose(e.start, 0.3)
    depth = raycast.render_depth(e.world, K, RES, RES, pose)
    pts = to_world(camera_points(depth, K, 1, 1e9), pose)
    assert len(pts) == RES * RES  # inside the box every ray meets something
    assert np.abs(e.world.clearance(pts)).max() < 2e-3


def test_raycast_beyond_the_far_clip_is_a_miss():
    pose = camera_pose(np.zeros(3), 0.0)
    d = raycast.render_depth(world_of(), K, RES, RES, pose, max_distance=10.0)
    assert (d == raycast.MISS_DEPTH).all()


@pytest.mark.parametrize("source", ["oracle", "constant"])
def test_no_obstacle_reaches_the_goal_with_every_source(source):
    depth = simulate.oracle if source == "oracle" else simulate.constant(100.0)
    seen: list = []
    r = simulate.fly(world_of(), START, GOAL, K, renderer(world_of(), seen), depth)
    assert r.outcome == "reached"
    assert r.min_clearance > 10
    assert r.path_ratio == pytest.approx(1.0, abs=0.02)
    assert len(seen) == r.steps  # one render per control step, at the drone's pose
    assert all(np.allclose(p[:3, 2], [1, 0, 0]) for p in seen)  # facing the goal, level
    again = simulate.fly(world_of(), START, GOAL, K, renderer(world_of()), depth)
    assert np.array_equal(again.positions, r.positions)  # deterministic


def wall_across(x: float = 8.0) -> Obstacle:
    return Obstacle("slab", np.array([0.3, 80.0, 80.0]), np.array([x, 0, 0]), np.eye(3))


def test_a_wall_across_the_path_stops_oracle_flight_and_constant_depth_crashes():
    w = world_of(wall_across())
    cfg = simulate.FlightConfig(max_steps=90)  # at rest before the wall by then
    r = simulate.fly(w, START, GOAL, K, renderer(w), simulate.oracle, cfg)
    assert r.outcome == "timeout"
    margin = cfg.controller.safety_radius - cfg.drone_radius
    assert r.min_clearance > margin - 0.05  # the safety radius held (wall sampled every 2 px)
    assert r.positions[:, 0].max() < 8.0
    c = simulate.fly(w, START, GOAL, K, renderer(w), simulate.constant(100.0), cfg)
    assert c.outcome == "collided" and c.min_clearance < 0
    assert c.positions[-1, 0] == pytest.approx(8.0 - 0.15 - cfg.drone_radius, abs=0.06)


def test_a_post_on_the_line_is_flown_around_with_oracle_depth():
    post = Obstacle("cylinder", np.array([1.5, 1.5, 60.0]), np.array([7.0, 0.3, 0]), np.eye(3))
    w = world_of(post)
    r = simulate.fly(w, START, GOAL, K, renderer(w), simulate.oracle)
    assert r.outcome == "reached" and r.min_clearance > 0.3
    assert r.path_ratio > 1.01  # it went round
    c = simulate.fly(w, START, GOAL, K, renderer(w), simulate.constant(100.0))
    assert c.outcome == "collided"


def test_yaw_modes_face_the_goal_or_keep_the_line():
    """Round a post: "line" keeps one orientation (pure translation between frames); "goal"
    turns the camera towards the goal as the drone drifts, within the yaw-rate limit."""
    post = Obstacle("cylinder", np.array([1.5, 1.5, 60.0]), np.array([7.0, 0.3, 0]), np.eye(3))
    w = world_of(post)
    rotations = {}
    for mode in simulate.YAW_MODES:
        seen: list = []
        cfg = simulate.FlightConfig(yaw=mode)
        r = simulate.fly(w, START, GOAL, K, renderer(w, seen), simulate.oracle, cfg)
        assert r.outcome == "reached"
        rotations[mode] = np.array([p[:3, :3] for p in seen])
    assert np.abs(rotations["line"] - rotations["line"][0]).max() == 0
    yaws = np.arctan2(rotations["goal"][:, 1, 2], rotations["goal"][:, 0, 2])
    assert np.abs(yaws).max() > 0.05  # it turned
    limit = simulate.FlightConfig().dynamics.max_yaw_rate * simulate.FlightConfig().dynamics.dt
    assert np.abs(np.diff(yaws)).max() <= limit + 1e-9
    with pytest.raises(ValueError, match="yaw"):
        simulate.fly(
            w, START, GOAL, K, renderer(w), simulate.oracle, simulate.FlightConfig(yaw="x")
        )


def test_a_generated_episode_end_to_end():
    """Episodes block the straight line: constant depth crashes, oracle depth gets through."""
    e = make_episode(0, 0, scene_cfg=flight_scene_config(width=RES, height=RES))
    assert np.allclose(e.K, K)
    r = simulate.fly(e.world, e.start, e.goal, e.K, renderer(e.world), simulate.oracle)
    assert r.outcome == "reached" and r.min_clearance > 0
    c = simulate.fly(e.world, e.start, e.goal, e.K, renderer(e.world), simulate.constant(100.0))
    assert c.outcome == "collided"
    assert r.render_s > 0 and r.control_s > 0 and r.depth_s >= 0
