"""Scene specs and records have the same bits on every CPU (stillbox_gen/portable.py).

The sampler runs in subprocesses under the dispatch settings that pick other kernels on this
machine: OpenBLAS core types, numpy with its SIMD extensions turned off, glibc's libm without
its FMA/AVX2 variants. A canary (a BLAS product, numpy's sin, libm's pow) shows that each setting
really changes floating-point results here; the records must not change at all.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from stillbox_gen import camera, portable, shapes

# Sampled in every variant: the default preset, the two rotating ones (unstabilised: spin and
# noise; rotating: a speed drawn per scene), and a config with every camera feature (noise, spin,
# custom intrinsics, non-square frames), as the golden dataset.
SCRIPT = """
import hashlib, json, math, sys
import numpy as np
from stillbox_gen import config, formats, record, shapes, writer
from stillbox_gen.scene import sample_scene

def canary():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(64, 64)), rng.normal(size=(64, 64))
    x = np.linspace(0.1, 50, 4001)
    libm = [math.pow(v, 2.2) for v in x.tolist()] + [math.exp(v / 7) for v in x.tolist()]
    parts = [(a @ b).tobytes(), np.sin(x).tobytes(), np.power(x, 2.2).tobytes(), repr(libm)]
    return hashlib.sha256("".join(map(str, parts)).encode()).hexdigest()[:16]

custom = config.replace(
    config.load_preset("stillbox"),
    camera={"width": 80, "height": 48, "focal_px": 50.0, "principal_point": (30.0, 20.0),
            "rotation_noise_deg": 0.3, "rotation_speed_deg": 0.5},
)
records = []
presets = ("stillbox", "stillbox-unstabilised", "stillbox-rotating")
for cfg in (*(config.load_preset(p) for p in presets), custom):
    records.append(writer.chunk_args(cfg.to_dict(), "stillbox-gen"))  # metadata.json's args
    for k in range(int(sys.argv[1])):
        spec = sample_scene(cfg, k).to_dict()
        records.append([spec, record.scene_record(spec, "png", False)])
meshes = [shapes.mesh(kind, [2.0, 1.7, 1.3])[0].tobytes().hex() for kind in config.PRIMITIVE_KINDS]
digest = hashlib.sha256((formats.canonical_json(records) + "".join(meshes)).encode())
print(json.dumps({"records": digest.hexdigest()[:16], "canary": canary()}))
"""
SCENES = 12  # per config: 48 scenes


def _cpu_flags() -> set[str]:
    text = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").is_file() else ""
    line = next((ln for ln in text.splitlines() if ln.startswith(("flags", "Features"))), "")
    return set(line.split(":", 1)[-1].split())


def dispatch_variants() -> dict[str, dict[str, str]]:
    """Environment settings that change the kernels picked on this CPU (only those it can run:
    forcing an OpenBLAS core type the CPU lacks would crash)."""
    flags = _cpu_flags()
    out: dict[str, dict[str, str]] = {"default": {}}
    if "sse3" in flags or "pni" in flags:
        out["openblas-prescott"] = {"OPENBLAS_CORETYPE": "Prescott"}
    if "avx" in flags:
        out["openblas-sandybridge"] = {"OPENBLAS_CORETYPE": "Sandybridge"}
    if {"avx2", "fma"} <= flags:
        out["openblas-haswell"] = {"OPENBLAS_CORETYPE": "Haswell"}
    if "avx512f" in flags:
        out["openblas-skylakex"] = {"OPENBLAS_CORETYPE": "SkylakeX"}
    # numpy._core: numpy 2's name (numpy.core warns there); numpy 1.26 has it too
    from numpy._core._multiarray_umath import __cpu_baseline__, __cpu_features__

    found = [f for f, on in __cpu_features__.items() if on and f not in __cpu_baseline__]
    if found:
        out["numpy-baseline-simd"] = {"NPY_DISABLE_CPU_FEATURES": " ".join(found)}
    if {"avx2", "fma"} <= flags:
        out["libm-no-fma"] = {"GLIBC_TUNABLES": "glibc.cpu.hwcaps=-AVX2,-FMA,-AVX512F"}
    return out


def _sample_in(env: dict[str, str]) -> dict[str, str]:
    import json

    full = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_CORETYPE",)}
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(SCENES)],
        env={**full, **env},
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_records_are_bit_identical_under_every_dispatch_variant():
    variants = dispatch_variants()
    results = {name: _sample_in(env) for name, env in variants.items()}
    base = results["default"]
    moved = [n for n, r in results.items() if r["records"] != base["records"]]
    assert not moved, f"records moved under {moved}: {results}"
    canaries_moved = [n for n, r in results.items() if r["canary"] != base["canary"]]
    if len(variants) > 2:  # an x86-64 CPU with AVX: the settings must really change kernels
        assert canaries_moved, (
            f"no setting changed the canary here; the test proves nothing {results}"
        )


# ---------------------------------------------------------------- the functions themselves


def _ulps(a: float, b: float) -> float:
    return abs(a - b) / math.ulp(max(abs(a), abs(b)))


@pytest.mark.parametrize(
    ("fn", "ref", "xs"),
    [
        (portable.sin, math.sin, np.linspace(-7, 7, 301)),
        (portable.cos, math.cos, np.linspace(-7, 7, 301)),
        (portable.tan, math.tan, np.linspace(-1.5, 1.5, 301)),
        (portable.atan, math.atan, np.linspace(-50, 50, 301)),
        (portable.exp, math.exp, np.linspace(-20, 20, 301)),
        (portable.log, math.log, np.geomspace(1e-6, 1e6, 301)),
        (portable.cbrt, lambda x: math.copysign(abs(x) ** (1 / 3), x), np.linspace(-900, 900, 301)),
        (lambda x: portable.power(x, 2.2), lambda x: x**2.2, np.linspace(0, 1, 301)),
    ],
)
def test_functions_agree_with_libm_within_one_ulp(fn, ref, xs):
    worst = max(_ulps(fn(float(x)), ref(float(x))) for x in xs if ref(float(x)) != 0)
    assert worst <= 1.0, worst


def test_exact_values():
    assert portable.sin(0.0) == 0.0 and portable.cos(0.0) == 1.0
    assert portable.cbrt(27.0) == 3.0 and portable.cbrt(-8.0) == -2.0
    assert portable.power(4.0, 0.5) == 2.0 and portable.exp(0.0) == 1.0
    assert portable.norm([3.0, 4.0]) == 5.0
    assert portable.matmul([[1.0, 2.0], [3.0, 4.0]], [[5.0, 6.0], [7.0, 8.0]]) == [
        [19.0, 22.0],
        [43.0, 50.0],
    ]
    with pytest.raises(ValueError):
        portable.log(0.0)


def test_products_match_numpy_to_rounding():
    rng = np.random.default_rng(3)
    a, b, v = rng.normal(size=(3, 3)), rng.normal(size=(3, 3)), rng.normal(size=3)
    np.testing.assert_allclose(portable.matmul(a, b), a @ b, rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(portable.matvec(a, v), a @ v, rtol=1e-14, atol=1e-15)
    pts = rng.normal(size=(50, 3))
    np.testing.assert_allclose(portable.transform_rows(a, pts), pts @ a.T, rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(portable.row_norms(pts), np.linalg.norm(pts, axis=1), rtol=1e-15)


def test_uniform_draws_are_numpys():
    """Same stream and values as numpy's own uniform (so portable.Generator changes no scene)."""
    ours = portable.Generator(np.random.PCG64(np.random.SeedSequence([5, 7])))
    theirs = np.random.default_rng(np.random.SeedSequence([5, 7]))
    for lo, hi, size in [(0.0, 1.0, None), (-100, 100, 3), (4.0, 30.0, (2, 2)), (0.5, 1.0, None)]:
        a, b = ours.uniform(lo, hi, size=size), theirs.uniform(lo, hi, size=size)
        assert np.array_equal(a, b) and np.shape(a) == np.shape(b)
    assert ours.normal() == theirs.normal() and ours.integers(9) == theirs.integers(9)


def test_rotations_and_inverse_pose_are_rigid():
    rng = np.random.default_rng(1)
    for _ in range(20):
        r = camera.random_rotation(rng)
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-14)
        assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-14)
        np.testing.assert_allclose(camera.quat_to_matrix(camera.matrix_to_quat(r)), r, atol=1e-14)
        m = camera.pose_matrix(r, rng.normal(size=3) * 10)
        np.testing.assert_allclose(camera.invert_pose(m) @ m, np.eye(4), atol=1e-13)
    axis_angle = np.array([0.0, 0.0, math.pi / 2])  # +90 deg about z: x -> y
    np.testing.assert_allclose(
        camera.rotation_vector_to_matrix(axis_angle) @ [1, 0, 0], [0, 1, 0], atol=1e-15
    )


def test_mesh_circle_is_exact_at_the_quarter_turns():
    ring = shapes._unit_circle(32)
    assert ring[0].tolist() == [1.0, 0.0] and ring[16].tolist() == [-1.0, portable.sin(math.pi)]
    np.testing.assert_allclose(np.hypot(ring[:, 0], ring[:, 1]), 1.0, rtol=1e-15)
