"""Camera maths: intrinsics, rotations and the OpenCV <-> Blender conventions.

Conventions used everywhere in this project:

* Camera axes are OpenCV's: x right, y down, z forward (optical axis). Units are metres.
* Pixel coordinates are OpenCV's pixel-centre convention: the centre of the top-left pixel is
  (0, 0), so a centred principal point is ((W - 1) / 2, (H - 1) / 2).
* ``K = [[f, 0, cx], [0, f, cy], [0, 0, 1]]`` with square pixels (fx = fy = f).
* Quaternions are [w, x, y, z], unit norm, w >= 0.
* ``cam2world`` maps camera (OpenCV) coordinates to world coordinates; ``world2cam`` is its inverse.

Everything that feeds a scene description or a record (rotations, poses, their inverses, focal
lengths) uses :mod:`portable` arithmetic, so it has the same bits on every machine.

Blender's camera looks down its local -Z with +Y up, so
``cam2world_opencv = matrix_world_blender @ diag(1, -1, -1, 1)``.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from . import portable

#: Sensor width (mm) given to Blender; only the ratio lens / sensor width matters.
BLENDER_SENSOR_WIDTH_MM = 36.0


def focal_from_fov(fov_deg: float, width: int) -> float:
    """Focal length in pixels for a horizontal field of view in degrees: f = W / (2 tan(fov/2))."""
    return width / (2.0 * portable.tan(math.radians(fov_deg) / 2.0))


def fov_from_focal(focal_px: float, width: int) -> float:
    """Horizontal field of view in degrees for a focal length in pixels."""
    return math.degrees(2.0 * portable.atan(width / (2.0 * focal_px)))


def centred_principal_point(width: int, height: int) -> tuple[float, float]:
    """Principal point at the image centre, in the pixel-centre convention."""
    return (width - 1) / 2.0, (height - 1) / 2.0


def intrinsics_matrix(focal_px: float, cx: float, cy: float) -> np.ndarray:
    """3x3 pinhole matrix K (pixels) with square pixels."""
    return np.array([[focal_px, 0.0, cx], [0.0, focal_px, cy], [0.0, 0.0, 1.0]])


def blender_camera_settings(K: np.ndarray, width: int, height: int) -> dict[str, float | str]:
    """Blender camera data settings that reproduce K at resolution width x height.

    With ``sensor_fit = 'HORIZONTAL'`` Blender measures both lens shifts in units of the image
    width and places the optical axis at continuous coordinate (W/2, H/2), i.e. at pixel-centre
    coordinate (W/2 - 1/2, H/2 - 1/2). Shifting right (+shift_x) moves the principal point left;
    shifting up (+shift_y) moves it down (y grows downwards).
    """
    f, cx, cy = float(K[0, 0]), float(K[0, 2]), float(K[1, 2])
    if not math.isclose(K[0, 0], K[1, 1], rel_tol=1e-9):
        raise ValueError("Blender cameras have square pixels: K[0,0] must equal K[1,1]")
    return {
        "sensor_fit": "HORIZONTAL",
        "sensor_width": BLENDER_SENSOR_WIDTH_MM,
        "lens": f * BLENDER_SENSOR_WIDTH_MM / width,
        "shift_x": (width / 2.0 - 0.5 - cx) / width,
        "shift_y": (cy - height / 2.0 + 0.5) / width,
    }


def intrinsics_from_blender(settings: dict, width: int, height: int) -> np.ndarray:
    """Inverse of :func:`blender_camera_settings` (for sensor_fit 'HORIZONTAL')."""
    f = settings["lens"] * width / settings["sensor_width"]
    cx = width / 2.0 - 0.5 - settings["shift_x"] * width
    cy = height / 2.0 - 0.5 + settings["shift_y"] * width
    return intrinsics_matrix(f, cx, cy)


def opencv_to_blender_cam2world(cam2world_cv: np.ndarray) -> np.ndarray:
    """Blender object ``matrix_world`` (4x4) for an OpenCV camera-to-world matrix."""
    out = np.array(cam2world_cv, dtype=float).copy()
    out[:3, 1:3] = -out[:3, 1:3]  # R @ diag(1, -1, -1), exactly: flip y and z
    return out


def pose_matrix(rotation: ArrayLike, translation: ArrayLike) -> np.ndarray:
    """4x4 homogeneous matrix from a 3x3 rotation and a 3-vector translation."""
    m = np.eye(4)
    m[:3, :3] = rotation
    m[:3, 3] = translation
    return m


def invert_pose(m: ArrayLike) -> np.ndarray:
    """Inverse of a rigid 4x4 transform: [R^T, -R^T t] (portable arithmetic)."""
    m = np.asarray(m, dtype=float)
    rt = portable.transpose(m[:3, :3])
    return pose_matrix(rt, [-x for x in portable.matvec(rt, m[:3, 3])])


def quat_to_matrix(q: ArrayLike) -> np.ndarray:
    """3x3 rotation matrix of a quaternion [w, x, y, z] (normalised first)."""
    w, x, y, z = portable.normalise(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat(m: ArrayLike) -> np.ndarray:
    """Unit quaternion [w, x, y, z] (w >= 0) of a 3x3 rotation matrix."""
    m = [[float(v) for v in row] for row in np.asarray(m, dtype=float)]
    tr = m[0][0] + m[1][1] + m[2][2]
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [0.25 * s, (m[2][1] - m[1][2]) / s, (m[0][2] - m[2][0]) / s, (m[1][0] - m[0][1]) / s]
    elif m[0][0] > m[1][1] and m[0][0] > m[2][2]:
        s = 2.0 * math.sqrt(1.0 + m[0][0] - m[1][1] - m[2][2])
        q = [(m[2][1] - m[1][2]) / s, 0.25 * s, (m[0][1] + m[1][0]) / s, (m[0][2] + m[2][0]) / s]
    elif m[1][1] > m[2][2]:
        s = 2.0 * math.sqrt(1.0 + m[1][1] - m[0][0] - m[2][2])
        q = [(m[0][2] - m[2][0]) / s, (m[0][1] + m[1][0]) / s, 0.25 * s, (m[1][2] + m[2][1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2][2] - m[0][0] - m[1][1])
        q = [(m[1][0] - m[0][1]) / s, (m[0][2] + m[2][0]) / s, (m[1][2] + m[2][1]) / s, 0.25 * s]
    q = portable.normalise(q)
    return np.array([-v for v in q] if q[0] < 0 else q)


def rotation_vector_to_matrix(v: ArrayLike) -> np.ndarray:
    """Rodrigues: rotation of angle |v| (radians) about axis v / |v|."""
    angle = portable.norm(v)
    if angle < 1e-15:
        return np.eye(3)
    ax, ay, az = (float(c) / angle for c in v)
    k = [[0.0, -az, ay], [az, 0.0, -ax], [-ay, ax, 0.0]]
    k2 = portable.matmul(k, k)
    s, c = portable.sin(angle), 1.0 - portable.cos(angle)
    return np.array(
        [[(i == j) + s * k[i][j] + c * k2[i][j] for j in range(3)] for i in range(3)], dtype=float
    )


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Rotation matrix drawn uniformly from SO(3) (normalised Gaussian quaternion)."""
    return quat_to_matrix(rng.normal(size=4).tolist())


def random_unit_vector(rng: np.random.Generator) -> np.ndarray:
    """Direction drawn uniformly on the unit sphere."""
    return np.array(portable.normalise(rng.normal(size=3).tolist()))


def pixel_ray(K: ArrayLike, u: float, v: float) -> list[float]:
    """K^-1 [u, v, 1] (camera frame, z = 1) by back-substitution on the upper-triangular K."""
    (f, skew, cx), (_, fy, cy) = K[0], K[1]
    y = (v - float(cy)) / float(fy)
    return [(u - float(skew) * y - float(cx)) / float(f), y, 1.0]


def pixel_grid(width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre coordinates ``(u, v)``, each (H, W) float64: u the column (x, right), v the
    row (y, down), integers at pixel centres (OpenCV convention)."""
    return np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))


def pixel_rays(K: ArrayLike, width: int, height: int) -> np.ndarray:
    """Camera-frame ray directions (H, W, 3) ``K^-1 [u, v, 1]`` of every pixel centre (z = 1):
    :func:`pixel_ray` for whole images, in numpy (not portable bits: for measurements only)."""
    u, v = pixel_grid(width, height)
    pix = np.stack([u, v, np.ones_like(u)], axis=-1)
    return pix @ np.linalg.inv(np.asarray(K, dtype=np.float64)).T


def project(points_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixel coordinates (..., 2) of camera-frame points (..., 3) with z > 0."""
    p = points_cam @ K.T
    return p[..., :2] / p[..., 2:3]


def backproject(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame points (H, W, 3), metres, of a planar depth map (H, W) in metres."""
    h, w = depth.shape
    return pixel_rays(K, w, h) * np.asarray(depth, dtype=np.float64)[..., None]
