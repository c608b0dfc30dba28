"""Camera maths checked against independent formulas (no Blender)."""

import math

import numpy as np
import pytest

from stillbox_gen import camera


def test_focal_fov_known_values_and_round_trip():
    """A 90 degree horizontal FOV gives f = W/2, and fov_from_focal inverts focal_from_fov."""
    assert camera.focal_from_fov(90.0, 64) == pytest.approx(32.0, abs=1e-12)
    assert camera.focal_from_fov(90.0, 512) == pytest.approx(256.0, abs=1e-12)
    for fov, width in [(30.0, 64), (60.0, 640), (90.0, 512), (120.0, 100), (170.0, 7)]:
        f = camera.focal_from_fov(fov, width)
        assert f == pytest.approx(width / 2 / math.tan(math.radians(fov) / 2), rel=1e-12)
        assert camera.fov_from_focal(f, width) == pytest.approx(fov, abs=1e-9)


def test_centred_principal_point_uses_pixel_centre_convention():
    """The centred principal point is ((W-1)/2, (H-1)/2), not (W/2, H/2)."""
    assert camera.centred_principal_point(64, 64) == (31.5, 31.5)
    assert camera.centred_principal_point(640, 480) == (319.5, 239.5)
    assert camera.centred_principal_point(5, 3) == (2.0, 1.0)


@pytest.mark.parametrize(
    "width,height,f,cx,cy",
    [
        (64, 64, 32.0, 31.5, 31.5),
        (64, 64, 40.0, 20.25, 45.0),
        (640, 480, 500.0, 300.2, 250.7),
        (480, 640, 321.0, 250.0, 300.0),
    ],
)
def test_blender_settings_round_trip(width, height, f, cx, cy):
    """blender_camera_settings and intrinsics_from_blender are inverses, including off-centre."""
    K = camera.intrinsics_matrix(f, cx, cy)
    s = camera.blender_camera_settings(K, width, height)
    assert s["sensor_fit"] == "HORIZONTAL"
    np.testing.assert_allclose(camera.intrinsics_from_blender(s, width, height), K, atol=1e-9)
    # independent statement of the render-verified convention
    assert cx == pytest.approx(width / 2 - s["shift_x"] * width - 0.5, abs=1e-9)
    assert cy == pytest.approx(height / 2 + s["shift_y"] * width - 0.5, abs=1e-9)
    assert s["lens"] / s["sensor_width"] == pytest.approx(f / width, rel=1e-12)


@pytest.mark.parametrize("width,height", [(64, 64), (640, 480), (480, 640)])
def test_centred_principal_point_needs_no_shift(width, height):
    """A centred principal point maps to zero Blender lens shift on both axes."""
    K = camera.intrinsics_matrix(100.0, *camera.centred_principal_point(width, height))
    s = camera.blender_camera_settings(K, width, height)
    assert s["shift_x"] == pytest.approx(0.0, abs=1e-15)
    assert s["shift_y"] == pytest.approx(0.0, abs=1e-15)


def test_shift_signs():
    """A principal point left of centre gives shift_x > 0; a larger cy gives shift_y > 0."""
    w, h = 640, 480
    cx0, cy0 = camera.centred_principal_point(w, h)
    left = camera.blender_camera_settings(camera.intrinsics_matrix(500.0, cx0 - 10, cy0), w, h)
    assert left["shift_x"] > 0 and left["shift_y"] == pytest.approx(0.0, abs=1e-15)
    down = camera.blender_camera_settings(camera.intrinsics_matrix(500.0, cx0, cy0 + 10), w, h)
    assert down["shift_y"] > 0 and down["shift_x"] == pytest.approx(0.0, abs=1e-15)
    # shifts are in units of the image width on both axes
    assert left["shift_x"] == pytest.approx(10 / w) and down["shift_y"] == pytest.approx(10 / w)


def test_blender_settings_reject_non_square_pixels():
    """K with fx != fy cannot be reproduced by a Blender camera and raises ValueError."""
    K = np.array([[100.0, 0, 31.5], [0, 110.0, 31.5], [0, 0, 1]])
    with pytest.raises(ValueError, match="square pixels"):
        camera.blender_camera_settings(K, 64, 64)


def test_opencv_to_blender_axes():
    """Blender's viewing direction (-Z local) is OpenCV forward (+z) and Blender up (+Y) is -y."""
    m = camera.opencv_to_blender_cam2world(np.eye(4))
    np.testing.assert_allclose(m[:3, :3] @ [0, 0, -1], [0, 0, 1], atol=1e-15)
    np.testing.assert_allclose(m[:3, :3] @ [0, 1, 0], [0, -1, 0], atol=1e-15)
    np.testing.assert_allclose(m[:3, :3] @ [1, 0, 0], [1, 0, 0], atol=1e-15)
    # a general pose keeps its translation and maps -Z to its OpenCV optical axis
    rot = camera.random_rotation(np.random.default_rng(3))
    pose = camera.pose_matrix(rot, [1.0, 2.0, 3.0])
    before = pose.copy()
    mb = camera.opencv_to_blender_cam2world(pose)
    np.testing.assert_array_equal(pose, before)  # the input is not modified
    np.testing.assert_allclose(mb[:3, 3], [1, 2, 3])
    np.testing.assert_allclose(mb[:3, :3] @ [0, 0, -1], rot[:, 2], atol=1e-12)
    np.testing.assert_allclose(mb[:3, :3] @ [0, 1, 0], -rot[:, 1], atol=1e-12)


def test_quaternion_round_trip_on_random_rotations():
    """matrix_to_quat inverts quat_to_matrix (w >= 0) and the matrices are proper rotations."""
    rng = np.random.default_rng(0)
    qs = rng.normal(size=(500, 4))
    qs /= np.linalg.norm(qs, axis=1, keepdims=True)
    qs[qs[:, 0] < 0] *= -1
    # include the branches where the trace is not the largest term
    qs = np.vstack([qs, [[0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [0, 0.6, 0.8, 0]]])
    for q in qs:
        m = camera.quat_to_matrix(q)
        np.testing.assert_allclose(m @ m.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(m) == pytest.approx(1.0, abs=1e-12)
        back = camera.matrix_to_quat(m)
        assert back[0] >= 0
        # q and -q are the same rotation; with w == 0 either sign is acceptable
        assert min(np.abs(back - q).max(), np.abs(back + q).max()) < 1e-9
        if q[0] > 1e-6:
            np.testing.assert_allclose(back, q, atol=1e-9)


def test_quat_to_matrix_matches_rodrigues():
    """The quaternion of angle a about axis k is [cos(a/2), sin(a/2) k], same as Rodrigues."""
    rng = np.random.default_rng(1)
    for _ in range(50):
        axis = camera.random_unit_vector(rng)
        angle = rng.uniform(0, np.pi)
        q = np.r_[np.cos(angle / 2), np.sin(angle / 2) * axis]
        np.testing.assert_allclose(
            camera.quat_to_matrix(q), camera.rotation_vector_to_matrix(axis * angle), atol=1e-12
        )


def test_rotation_vector_quarter_turn_about_z():
    """A rotation of pi/2 about z maps x to y and y to -x; a zero vector gives the identity."""
    r = camera.rotation_vector_to_matrix([0, 0, np.pi / 2])
    np.testing.assert_allclose(r @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(r @ [0, 1, 0], [-1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(r @ [0, 0, 1], [0, 0, 1], atol=1e-15)
    np.testing.assert_array_equal(camera.rotation_vector_to_matrix([0, 0, 0]), np.eye(3))


def test_random_rotation_is_deterministic_per_generator_seed():
    """Equal seeds give equal rotations, different seeds different ones, all proper rotations."""
    a = camera.random_rotation(np.random.default_rng(42))
    b = camera.random_rotation(np.random.default_rng(42))
    c = camera.random_rotation(np.random.default_rng(43))
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    np.testing.assert_allclose(a @ a.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(a) == pytest.approx(1.0)


def test_invert_pose():
    """invert_pose gives the matrix inverse of a rigid transform."""
    pose = camera.pose_matrix(camera.random_rotation(np.random.default_rng(5)), [1.0, -2.0, 0.5])
    np.testing.assert_allclose(camera.invert_pose(pose) @ pose, np.eye(4), atol=1e-12)


def test_project_backproject_returns_pixel_grid():
    """Projecting the back-projected points of a depth map gives back every pixel centre."""
    h, w = 6, 9
    K = camera.intrinsics_matrix(7.0, 3.3, 2.1)
    depth = np.random.default_rng(0).uniform(0.5, 50.0, size=(h, w))
    pts = camera.backproject(depth, K)
    assert pts.shape == (h, w, 3)
    np.testing.assert_array_equal(pts[..., 2], depth)
    uv = camera.project(pts.reshape(-1, 3), K).reshape(h, w, 2)
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    np.testing.assert_allclose(uv[..., 0], u, atol=1e-9)
    np.testing.assert_allclose(uv[..., 1], v, atol=1e-9)
    # the principal point's ray is the optical axis
    p = camera.project(np.array([[0.0, 0.0, 3.0]]), K)
    np.testing.assert_allclose(p, [[3.3, 2.1]])
