"""benchmark/flight/world.py: clearance and swept collisions against distances computed by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from benchmark.flight.episodes import flight_scene_config
from benchmark.flight.world import Obstacle, World
from stillbox_gen import shapes
from stillbox_gen.camera import quat_to_matrix
from stillbox_gen.scene import sample_scene

BIG_BOX = (np.zeros(3), np.full(3, 100.0))


def world_of(*obstacles: Obstacle, box=BIG_BOX) -> World:
    return World(tuple(obstacles), *box)


def sphere(centre, radius) -> Obstacle:
    return Obstacle("sphere", np.full(3, 2.0 * radius), np.asarray(centre, float), np.eye(3))


def about_z(angle: float) -> np.ndarray:
    """Quaternion [w, x, y, z] of a turn of ``angle`` radians about +Z."""
    return np.array([math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)])


def test_clearance_to_hand_placed_spheres():
    w = world_of(sphere([5, 0, 0], 1.0), sphere([0, -10, 0], 2.0))
    pts = np.array([[0, 0, 0], [5, 0, 3], [5, 0, 0.5], [0, -6, 0]], float)
    # |p - c| - r, nearest sphere: 5 - 1; 3 - 1; 0.5 - 1 (inside); 4 - 2
    assert w.clearance(pts) == pytest.approx([4.0, 2.0, -0.5, 2.0])
    # a sphere of radius 0.5 around the point: 0.5 m less
    assert w.clearance(pts, radius=0.5) == pytest.approx([3.5, 1.5, -1.0, 1.5])


def test_clearance_to_a_turned_cube():
    """A 2 m cube at (0, 5, 0) turned 45 deg about Z points an edge at the origin: its nearest
    point is the edge at 5 - sqrt(2) m; along X, a face at 1 m from the centre... turned, the
    point (sqrt(2) + 1, 5, 0) is 1 m beyond the right edge."""
    cube = Obstacle(
        "cube", np.full(3, 2.0), np.array([0.0, 5.0, 0.0]), quat_to_matrix(about_z(math.pi / 4))
    )
    w = world_of(cube)
    pts = np.array([[0, 0, 0], [math.sqrt(2) + 1, 5, 0], [0, 5, 0]])
    assert w.clearance(pts) == pytest.approx([5 - math.sqrt(2), 1.0, -1.0])


def test_rotation_is_local_to_world_as_blender_applies_the_quaternion():
    """A bar 4 m long along its local X, turned 90 deg about Z, lies along world Y."""
    bar = Obstacle(
        "cube", np.array([4.0, 1.0, 1.0]), np.zeros(3), quat_to_matrix(about_z(math.pi / 2))
    )
    c = world_of(bar).clearance(np.array([[0.0, 1.9, 0.0], [1.9, 0.0, 0.0]]))
    assert c[0] < 0 and c[1] == pytest.approx(1.9 - 0.5)


def test_walls_are_the_inside_of_the_box():
    w = world_of(box=(np.array([1.0, 0.0, 0.0]), np.array([10.0, 20.0, 30.0])))
    pts = np.array([[1, 0, 0], [10, 0, 0], [1, -19.5, 0], [12, 0, 0]], float)
    assert w.clearance(pts) == pytest.approx([10.0, 1.0, 0.5, -1.0])


def test_swept_segment_through_a_sphere_collides_and_beside_it_does_not():
    w = world_of(sphere([5, 0, 0], 1.0))
    through = w.swept(np.zeros(3), np.array([10.0, 0, 0]), radius=0.25)
    assert through.collided and through.min_clearance < 0
    # the sphere's surface is at x = 4, the drone's at x = 3.75: the first hit near 37.5 %
    assert through.first_hit == pytest.approx(0.375, abs=0.01)
    beside = w.swept(np.array([0.0, 2.0, 0]), np.array([10.0, 2.0, 0]), radius=0.25)
    # nearest approach: centre (5, 2, 0), 2 - 1 - 0.25 from the surface
    assert not beside.collided and beside.first_hit is None
    assert beside.min_clearance == pytest.approx(0.75, abs=1e-6)


def test_one_long_step_does_not_tunnel_through_a_thin_slab():
    """A 1 mm slab across the path, crossed in one 10 m step, both ends far from it."""
    slab = Obstacle("slab", np.array([0.001, 4.0, 4.0]), np.array([5.0123, 0, 0]), np.eye(3))
    w = world_of(slab)
    a, b = np.zeros(3), np.array([10.0, 0, 0])
    assert w.clearance(np.stack([a, b]), 0.1).min() > 4
    assert w.swept(a, b, radius=0.1).collided
    assert w.swept(a, b, radius=0.01).collided
    assert not w.swept(a + [0, 3, 0], b + [0, 3, 0], radius=0.1).collided


def test_world_of_a_sampled_scene_matches_its_primitives():
    """Each primitive's centre is inside it (its own signed distance, independently, is < 0),
    the world's clearance there is at most that, and the rendered mesh's vertices (placed as
    Blender places them: R v + t) lie on or inside the analytic surface."""
    scene = sample_scene(flight_scene_config(seed=3), 2)
    w = World.from_scene(scene)
    assert len(w.obstacles) == len(scene.primitives)
    for p in scene.primitives:
        r = quat_to_matrix(p.rotation)
        own = shapes.signed_distance(p.kind, np.array(p.dimensions), np.zeros((1, 3)))[0]
        centre = np.array(p.location)[None]
        assert w.clearance(centre)[0] <= own + 1e-12
        verts, _ = shapes.mesh(p.kind, p.dimensions)
        assert w.clearance(verts @ r.T + p.location).max() <= 1e-9
    centre = np.array(scene.box.center)
    half = np.array(scene.box.half_extents)
    corner_in = centre + half - 0.5
    assert w.wall_clearance(corner_in[None])[0] == pytest.approx(0.5)
