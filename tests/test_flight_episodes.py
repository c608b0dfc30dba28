"""benchmark/flight/episodes.py: reproducible episodes with an obstacle between start and goal."""

from __future__ import annotations

import math

import numpy as np
import pytest

from benchmark.flight.episodes import EpisodeConfig, flight_scene_config, make_episode
from stillbox_gen import shapes
from stillbox_gen.camera import quat_to_matrix

CFG = EpisodeConfig()


def independent_clearance(scene, points: np.ndarray) -> np.ndarray:
    """Distance to the nearest surface, from shapes.py directly (not through World)."""
    best = np.full(len(points), np.inf)
    for p in scene.primitives:
        local = (points - p.location) @ quat_to_matrix(p.rotation)
        best = np.minimum(best, shapes.signed_distance(p.kind, np.array(p.dimensions), local))
    half, centre = np.array(scene.box.half_extents), np.array(scene.box.center)
    walls = (half - np.abs(points - centre)).min(axis=1)
    return np.minimum(best, walls)


def test_same_seed_and_index_give_the_same_episode():
    a, b = make_episode(7, 3), make_episode(7, 3)
    assert a.scene.to_dict() == b.scene.to_dict()
    assert np.array_equal(a.start, b.start) and np.array_equal(a.goal, b.goal)
    c, d = make_episode(7, 4), make_episode(8, 3)
    assert not np.array_equal(a.start, c.start) and not np.array_equal(a.start, d.start)
    assert a.scene.to_dict() != c.scene.to_dict()


@pytest.mark.parametrize("index", range(6))
def test_start_and_goal_are_clear_apart_level_and_blocked(index):
    e = make_episode(0, index)
    assert np.linalg.norm(e.goal - e.start) == pytest.approx(CFG.distance)
    assert e.goal[2] == e.start[2]  # level: the stabilised camera sees the goal ahead
    ends = independent_clearance(e.scene, np.stack([e.start, e.goal]))
    assert ends.min() >= CFG.clearance
    t = np.linspace(0, 1, 4001)[:, None]  # every 5 mm
    line = independent_clearance(e.scene, e.start + t * (e.goal - e.start))
    assert line.min() <= CFG.near + 0.01  # an obstacle on (or near) the straight line
    # the blocking object is a primitive, not a wall
    walls = (
        np.array(e.scene.box.half_extents)
        - np.abs(e.start + t * (e.goal - e.start) - e.scene.box.center)
    ).min(1)
    assert walls.min() > CFG.near


def test_frame_size_follows_the_scene_config():
    e = make_episode(0, 0, scene_cfg=flight_scene_config(width=32, height=32))
    assert e.scene.camera.width == 32
    assert e.K[0, 0] == pytest.approx(16.0 / math.tan(math.radians(45)))
    assert e.K[0, 2] == pytest.approx(15.5)
