"""benchmark.core.geometry: focus of expansion of a translating pinhole camera (OpenCV axes)."""

from __future__ import annotations

import numpy as np
import pytest

from benchmark.core.geometry import distance_to_foe, focus_of_expansion


def intrinsics(f: float = 32.0, cx: float = 31.5, cy: float = 31.5) -> np.ndarray:
    return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])


def project(K: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 3) camera-frame points -> (N, 2) pixel coordinates."""
    p = points @ K.T
    return p[:, :2] / p[:, 2:]


def test_forward_motion_foe_is_principal_point():
    K = intrinsics(cx=30.0, cy=20.0)
    assert focus_of_expansion(K, np.array([0.0, 0.0, 0.3])) == pytest.approx((30.0, 20.0))
    # backward motion: the same point (focus of contraction)
    assert focus_of_expansion(K, np.array([0.0, 0.0, -0.3])) == pytest.approx((30.0, 20.0))


def test_oblique_motion():
    # e = c + f·(Tx, Ty)/Tz = (31.5 + 32·1/1, 31.5 + 0) = (63.5, 31.5)
    assert focus_of_expansion(intrinsics(), np.array([1.0, 0.0, 1.0])) == pytest.approx(
        (63.5, 31.5)
    )
    # moving down-left and backward: (31.5 + 32·(−1)/(−2), 31.5 + 32·2/(−2)) = (47.5, −0.5)
    e = focus_of_expansion(intrinsics(), np.array([-1.0, 2.0, -2.0]))
    assert e == pytest.approx((47.5, -0.5))


def test_lateral_motion_has_no_foe():
    K = intrinsics()
    for t in ([1.0, 0.0, 0.0], [0.3, -0.2, 1e-12], [0.0, 0.0, 0.0]):
        assert focus_of_expansion(K, np.array(t)) is None
        d = distance_to_foe(K, np.array(t), 4, 6)
        assert d.shape == (4, 6) and d.dtype == np.float64 and np.all(np.isinf(d))


def test_distance_to_foe():
    K = intrinsics()
    # choose T so that the FOE is the pixel centre (x=40, y=20): Tx/Tz = 8.5/32, Ty/Tz = −11.5/32
    t = np.array([8.5, -11.5, 32.0])
    assert focus_of_expansion(K, t) == pytest.approx((40.0, 20.0))
    d = distance_to_foe(K, t, 64, 64)
    assert d.shape == (64, 64) and d.dtype == np.float64
    assert d[20, 40] == pytest.approx(0.0, abs=1e-12)
    assert d.argmin() == 20 * 64 + 40
    np.testing.assert_allclose(d[20, 41:45], [1, 2, 3, 4], atol=1e-12)  # along x
    np.testing.assert_allclose(d[16:20, 40], [4, 3, 2, 1], atol=1e-12)  # along y
    assert d[23, 44] == pytest.approx(5.0)  # 3-4-5 triangle
    ys, xs = np.mgrid[0:64, 0:64]
    np.testing.assert_allclose(d, np.hypot(xs - 40, ys - 20), atol=1e-12)


@pytest.mark.parametrize(
    "t", [[0.0, 0.0, 0.3], [0.1, -0.05, 0.2], [0.2, 0.1, -0.15], [-0.3, 0.2, 0.05]]
)
def test_foe_is_fixed_point_of_the_flow(t):
    """Each flow vector lies on the line through its pixel and the FOE (forward and backward)."""
    K = intrinsics(f=50.0, cx=40.0, cy=24.0)
    t = np.array(t)
    rng = np.random.default_rng(0)
    X = np.column_stack([rng.uniform(-5, 5, 20), rng.uniform(-5, 5, 20), rng.uniform(2, 30, 20)])
    p1 = project(K, X)  # seen from frame 1
    p2 = project(K, X - t)  # camera moved by t: the same point seen from frame 2
    e = np.array(focus_of_expansion(K, t))
    a, b = p1 - e, p2 - e
    cross = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    scale = np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1) + 1e-12
    np.testing.assert_allclose(cross / scale, 0.0, atol=1e-9)
    # forward motion pushes points away from the FOE, backward motion pulls them in
    grow = np.linalg.norm(b, axis=1) - np.linalg.norm(a, axis=1)
    moving = np.linalg.norm(a, axis=1) > 1e-6
    assert np.all(np.sign(grow[moving]) == np.sign(t[2]))
