"""benchmark/flight/detour.py: segment distances, via-points and the cost-to-go by hand."""

from __future__ import annotations

import numpy as np
import pytest

from benchmark.flight.detour import (
    BLOCKED,
    LATERAL_OFFSETS,
    cost_to_go,
    segment_distances,
    via_points,
)

GOAL = np.array([20.0, 0.0, 0.0])


def test_segment_distances_by_hand():
    a = np.array([[0.0, 0, 0], [0.0, 0, 0]])
    b = np.array([[10.0, 0, 0], [0.0, 10.0, 0]])
    pts = np.array([[5.0, 3.0, 0.0], [-4.0, 0.0, 3.0]])
    # segment 1: (5, 3, 0) is 3 m off its middle; segment 2: (5, 3, 0) is 5 m from (0, 3, 0),
    # (-4, 0, 3) is 5 m from its end (0, 0, 0)
    assert segment_distances(a, b, pts) == pytest.approx([3.0, 5.0])
    assert np.isinf(segment_distances(a, b, np.empty((0, 3)))).all()
    many = np.repeat(a, 100, axis=0), np.repeat(b, 100, axis=0)  # across several chunks
    assert segment_distances(*many, pts) == pytest.approx(np.repeat([3.0, 5.0], 100))


def test_via_points_beside_the_nearest_blocker():
    pts = np.array([[8.0, 0.5, 0.0], [12.0, 0.0, 0.0], [5.0, 4.0, 0.0]])  # the third is aside
    v = via_points(np.zeros(3), GOAL, pts, corridor=1.5)
    assert np.allclose(v[:, 0], 8.0)  # at the nearest blocker's distance along the line
    lateral = sorted(np.round(np.abs(v[:, 1]), 6))
    assert set(lateral) >= set(LATERAL_OFFSETS)  # sideways: world Y across a line along X
    assert np.abs(v[:, 2]).max() > 0  # and some above and below
    assert len(via_points(np.zeros(3), GOAL, pts[2:], corridor=1.5)) == 0  # nothing across


def test_cost_to_go_straight_via_and_blocked():
    xs = np.array([[0.0, 0, 0], [0.0, 5.0, 0]])
    assert cost_to_go(xs, GOAL, np.empty((0, 3)), np.empty((0, 3)), 1.5) == pytest.approx(
        np.linalg.norm(xs - GOAL, axis=1)
    )
    # a 4 m wide wall of points across the line at x = 10 (y in [-2, 2])
    wall = np.stack([np.full(41, 10.0), np.linspace(-2, 2, 41), np.zeros(41)], axis=1)
    via = np.array([[10.0, 5.0, 0.0]])  # 3 m beside the wall's edge: both legs clear
    c = cost_to_go(xs, GOAL, via, wall, 1.5)
    # from (0, 0, 0): the straight way is blocked; via (10, 5, 0): sqrt(125) + sqrt(125)
    assert c[0] == pytest.approx(2 * np.sqrt(125))
    # from (0, 5, 0): the straight way to the goal passes (10, 2.5, 0), 0.5 m from the edge:
    # blocked; via: 10 + sqrt(125)
    assert c[1] == pytest.approx(10 + np.sqrt(125))
    # no clear via-point: the straight length plus BLOCKED
    bad = np.array([[10.0, 0.0, 0.0]])
    assert cost_to_go(xs, GOAL, bad, wall, 1.5) == pytest.approx(
        np.linalg.norm(xs - GOAL, axis=1) + BLOCKED
    )
