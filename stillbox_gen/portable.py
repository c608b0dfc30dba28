"""Floating-point maths that gives the same bits on every machine (scene sampling and records).

Why: numpy routes small matrix products and norms through OpenBLAS, whose kernels are chosen per
CPU (Haswell, SkylakeX, Zen...) and sum in different orders; numpy's own sin/cos/exp/log/power
use SIMD code chosen per CPU (AVX-512 gets SVML); glibc's libm picks FMA or non-FMA variants of
sin/cos/exp/log/pow at load time. Each can move the last bits of a result, so a scene sampled on
one machine differed from the same scene sampled on another (measured: every camera pose and
most primitive locations under ``OPENBLAS_CORETYPE=Haswell``; material colours and scales under
``GLIBC_TUNABLES=glibc.cpu.hwcaps=-AVX2,-FMA``).

What is portable, and used here:

* Python float arithmetic: each ``+ - * /`` is one IEEE-754 double operation rounded to nearest,
  evaluated in the written order (CPython never fuses a multiply and an add), and ``math.sqrt``
  is correctly rounded by IEEE-754. So sums are written out in a fixed order, never ``np.dot``,
  ``@``, ``np.linalg`` or a reduction.
* Element-wise numpy ``+ - * /``, ``sqrt``, ``abs``, ``minimum``/``maximum`` on arrays: one
  correctly rounded operation per element whatever the SIMD width (used by vectorised geometry).
* Transcendental functions from mpmath, which computes them with integer arithmetic at 53 bits
  (plus its own guard bits) and rounds to nearest: the same result on any CPU and OS.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from mpmath import libmp

_PREC = 53  # bits of an IEEE double
_NEAREST = libmp.round_nearest

Vector = Sequence[float]
Matrix = Sequence[Sequence[float]]


def _unary(fn, x: float) -> float:
    return libmp.to_float(fn(libmp.from_float(float(x)), _PREC, _NEAREST))


def sin(x: float) -> float:
    """sin(x), x in radians."""
    return _unary(libmp.mpf_sin, x)


def cos(x: float) -> float:
    """cos(x), x in radians."""
    return _unary(libmp.mpf_cos, x)


def tan(x: float) -> float:
    """tan(x), x in radians."""
    return _unary(libmp.mpf_tan, x)


def atan(x: float) -> float:
    """arctan(x), radians."""
    return _unary(libmp.mpf_atan, x)


def exp(x: float) -> float:
    return _unary(libmp.mpf_exp, x)


def log(x: float) -> float:
    """Natural logarithm of x > 0."""
    if not x > 0:
        raise ValueError(f"log of {x}")
    return _unary(libmp.mpf_log, x)


def cbrt(x: float) -> float:
    """Real cube root (negative for negative x)."""
    return -_unary(libmp.mpf_cbrt, -x) if x < 0 else _unary(libmp.mpf_cbrt, x)


def power(x: float, y: float) -> float:
    """x ** y for x >= 0."""
    if x < 0:
        raise ValueError(f"power of negative base {x}")
    s, t = libmp.from_float(float(x)), libmp.from_float(float(y))
    return libmp.to_float(libmp.mpf_pow(s, t, _PREC, _NEAREST))


def dot(a: Vector, b: Vector) -> float:
    """Sum of a[i] * b[i], added left to right."""
    total = 0.0
    for x, y in zip(a, b, strict=True):
        total += float(x) * float(y)
    return total


def norm(v: Vector) -> float:
    """Euclidean length."""
    return math.sqrt(dot(v, v))


def normalise(v: Vector) -> list[float]:
    """v / |v|."""
    n = norm(v)
    return [float(x) / n for x in v]


def matvec(m: Matrix, v: Vector) -> list[float]:
    """m @ v for a matrix given as rows."""
    return [dot(row, v) for row in m]


def matmul(a: Matrix, b: Matrix) -> list[list[float]]:
    """a @ b for matrices given as rows."""
    columns = list(zip(*b, strict=True))
    return [[dot(row, col) for col in columns] for row in a]


def transpose(m: Matrix) -> list[list[float]]:
    return [[float(x) for x in col] for col in zip(*m, strict=True)]


def transform_rows(m: Matrix, points: np.ndarray) -> np.ndarray:
    """Each row p of ``points`` (N, k) mapped to m @ p, as (N, len(m)): element-wise products
    summed in a fixed order (numpy's ``points @ m.T`` goes through BLAS)."""
    points = np.asarray(points, dtype=float)
    out = np.empty((len(points), len(m)))
    for i, row in enumerate(m):
        acc = points[:, 0] * float(row[0])
        for j in range(1, len(row)):
            acc = acc + points[:, j] * float(row[j])
        out[:, i] = acc
    return out


def row_norms(points: np.ndarray) -> np.ndarray:
    """Euclidean length of each row of ``points`` (N, k), summed in a fixed order."""
    points = np.asarray(points, dtype=float)
    acc = points[:, 0] * points[:, 0]
    for j in range(1, points.shape[1]):
        acc = acc + points[:, j] * points[:, j]
    return np.sqrt(acc)


class Generator(np.random.Generator):
    """numpy's Generator whose ``uniform`` is computed here, in Python floats, from
    ``random()``: ``low + (high - low) * random()``, numpy's own formula and stream (so the
    same values as ``np.random.Generator.uniform``), without relying on how the C library
    was compiled (a fused multiply-add would move the last bit)."""

    def uniform(self, low: float = 0.0, high: float = 1.0, size=None):
        low, high = float(low), float(high)
        span = high - low
        if size is None:
            return low + span * self.random()
        return np.array([low + span * u for u in self.random(size).ravel().tolist()]).reshape(size)
