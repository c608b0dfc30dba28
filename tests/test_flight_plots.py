"""benchmark/flight/plots.py: the footprints of the top-down figure against hand geometry."""

from __future__ import annotations

import numpy as np

from benchmark.flight.plots import episode_figure, footprints
from benchmark.flight.world import Obstacle, World


def test_footprints_of_a_sphere_in_and_near_the_flight_plane():
    """A ball of radius 2 centred 1.5 m above the plane: the plane cuts a disc of radius
    sqrt(4 - 1.5^2); the column within 2 m of the plane holds its whole radius-2 disc."""
    ball = Obstacle("sphere", np.full(3, 4.0), np.array([0.0, 0.0, 1.5]), np.eye(3))
    world = World((ball,), np.zeros(3), np.full(3, 30.0))
    xs, ys, plane, column = footprints(world, 0.0, (-5, 5, -5, 5), band=2.0, grid=201)
    r = np.hypot(*np.meshgrid(xs, ys))
    cut = np.sqrt(4 - 1.5**2)
    assert ((plane < 0) == (r < cut))[np.abs(r - cut) > 0.06].all()
    assert ((column < 0) == (r < 2.0))[np.abs(r - 2.0) > 0.06].all()


def test_episode_figure_marks_the_collision():
    world = World((), np.zeros(3), np.full(3, 30.0))
    path = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]])
    fig = episode_figure(world, path[0], np.array([10.0, 0, 0]), path, "collided", "t", 0.25, 1.0)
    labels = fig.axes[0].get_legend_handles_labels()[1]
    assert "collision" in labels and "goal" in labels
    fig = episode_figure(world, path[0], np.array([10.0, 0, 0]), path, "reached", "t", 0.25, 1.0)
    assert "collision" not in fig.axes[0].get_legend_handles_labels()[1]
