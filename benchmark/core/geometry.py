"""Focus of expansion (FOE) of a purely translating pinhole camera (thesis 3.1.5).

Conventions: OpenCV camera axes (x right, y down, z forward); pixel coordinates (x, y) in pixels
with the centre of the top-left pixel at (0, 0); ``K`` is the 3×3 intrinsic matrix
``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``; the translation ``T = (Tx, Ty, Tz)`` (any length unit)
is the camera displacement from frame 1 to frame 2, expressed in frame 1's camera axes.

The FOE is the image of the direction of motion, ``e = Π(K·T)``, i.e. ``e = c + f·(Tx, Ty)/Tz``
without skew. Every optical-flow vector lies on the line through its pixel and the FOE. For
backward motion (``Tz < 0``) the same point is the focus of contraction.
"""

from __future__ import annotations

import numpy as np


def focus_of_expansion(K: np.ndarray, translation: np.ndarray) -> tuple[float, float] | None:
    """Pixel position ``(x, y)`` of the focus of expansion.

    Args:
        K: ``(3, 3)`` camera intrinsics, pixels.
        translation: ``(3,)`` camera translation between the two frames, in frame 1's camera
            axes (OpenCV: x right, y down, z forward).

    Returns:
        ``(x, y)`` in pixels (pixel-centre convention; may lie outside the image), or ``None``
        when the FOE is at infinity: lateral motion ``|Tz| < 1e-9·|T|``, or no motion at all.
    """
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    t = np.asarray(translation, dtype=np.float64).reshape(3)
    norm = float(np.linalg.norm(t))
    if norm == 0.0 or abs(t[2]) < 1e-9 * norm:
        return None
    p = K @ t
    return float(p[0] / p[2]), float(p[1] / p[2])


def distance_to_foe(K: np.ndarray, translation: np.ndarray, height: int, width: int) -> np.ndarray:
    """Distance in pixels from each pixel centre to the focus of expansion.

    Args:
        K: ``(3, 3)`` camera intrinsics, pixels.
        translation: ``(3,)`` camera translation between the frames, frame 1's camera axes.
        height, width: image size in pixels.

    Returns:
        ``(height, width)`` float64 array; pixel ``[y, x]`` holds ``|(x, y) − e|``. All ``np.inf``
        when the FOE is at infinity (see :func:`focus_of_expansion`).
    """
    foe = focus_of_expansion(K, translation)
    if foe is None:
        return np.full((height, width), np.inf, dtype=np.float64)
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    return np.hypot(xs - foe[0], ys - foe[1])
