"""`stillbox-gen stats`: geometry against hand-computed values, histograms, and one real run."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import assert_user_error, invoke_cli, run_cli

from stillbox_gen import conventions
from stillbox_gen.camera import intrinsics_matrix, pose_matrix, random_rotation
from stillbox_gen.stats import geometry, histograms, measure

# 5x5 pixels, f = 2 px, principal point at the centre pixel: pixel (u, v) has the camera ray
# ((u - 2) / 2, (v - 2) / 2, 1).
K5 = intrinsics_matrix(2.0, 2.0, 2.0)


# ---------------------------------------------------------------- bands and histograms


def test_band_shares_of_a_hand_made_depth_array():
    # two pixels in each band, at both ends of the half-open interval; a miss counts as > 100
    d = np.array(
        [0, 4.99, 5, 9.9, 10, 14.9, 15, 19, 20, 24.9, 25, 29, 30, 49, 50, 74, 75, 99.9, 100, 1e10]
    ).reshape(4, 5)
    shares = histograms.band_shares(d)
    assert list(shares) == list(histograms.BAND_LABELS)
    assert histograms.BAND_LABELS[0] == "0-5" and histograms.BAND_LABELS[-1] == ">100"
    assert all(v == pytest.approx(0.1) for v in shares.values())
    one = histograms.band_shares(np.array([[7.0, 7.0, 7.0, 120.0]]))
    assert one["5-10"] == 0.75 and one[">100"] == 0.25 and sum(one.values()) == 1.0
    assert sum(histograms.band_shares(np.array([np.nan, 3.0])).values()) == 1.0
    assert set(histograms.band_shares(np.array([])).values()) == {0.0}


def test_stillbox_reference_bands_sum_to_one():
    ref = measure.STILLBOX_REFERENCE
    assert list(ref["band_shares"]) == list(histograms.BAND_LABELS)
    assert sum(ref["band_shares"].values()) == pytest.approx(1.0)
    bands = ref["band_shares"]
    assert ref["share_5_25m"] == pytest.approx(sum(bands[k] for k in histograms.BAND_LABELS[1:5]))


def test_histogram_quantiles_match_numpy():
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 120.0, size=20_000)
    h = histograms.depth_histogram()
    h.add(depth)
    for q in (0.1, 0.5, 0.9):
        assert h.quantile(q) == pytest.approx(np.quantile(depth, q), abs=0.03)  # 3 bins
    flow = np.exp(rng.normal(0.0, 2.0, size=20_000))
    f = histograms.flow_histogram()
    f.add(flow)
    for q in (0.1, 0.5, 0.9):
        assert f.quantile(q) == pytest.approx(np.quantile(flow, q), rel=0.005)
    assert histograms.depth_histogram().quantile(0.5) is None


# ---------------------------------------------------------------- walls


def test_box_depth_of_an_axis_aligned_camera_by_hand():
    # camera at the origin looking along world +z; box x in [-10, 10], y in [-20, 20], z in
    # [-30, 30]: planar depth = the ray's exit t, ray (x, y, 1) -> min(10/|x|, 20/|y|, 30).
    d = geometry.box_depth(K5, np.eye(4), [0, 0, 0], [10, 20, 30], 5, 5)
    assert d[2, 2] == pytest.approx(30.0)  # optical axis: the far wall
    assert d[2, 4] == pytest.approx(10.0)  # ray (1, 0, 1): the x = 10 wall
    assert d[2, 3] == pytest.approx(20.0)  # ray (0.5, 0, 1): x = 10 at t = 20
    assert d[4, 2] == pytest.approx(20.0)  # ray (0, 1, 1): the y = 20 wall
    assert d[0, 0] == pytest.approx(10.0)  # ray (-1, -1, 1): x = -10 first


def test_box_depth_of_a_turned_and_moved_camera_by_hand():
    # camera at (2, -1, 0.5) looking along world +x, image x along world +y, image y along
    # world +z; box centred at (1, 0, 0), half extents (10, 4, 10): x in [-9, 11], y in [-4, 4].
    r = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # columns x_c, y_c, z_c
    assert np.linalg.det(r) == pytest.approx(1.0)
    pose = pose_matrix(r, [2.0, -1.0, 0.5])
    d = geometry.box_depth(K5, pose, [1, 0, 0], [10, 4, 10], 5, 5)
    assert d[2, 2] == pytest.approx(9.0)  # world (1, 0, 0): x = 11 at t = 9
    assert d[2, 4] == pytest.approx(5.0)  # world (1, 1, 0): y = 4 at t = 5
    assert d[2, 0] == pytest.approx(3.0)  # world (1, -1, 0): y = -4 at t = 3
    assert d[4, 2] == pytest.approx(9.0)  # world (1, 0, 1): x = 11 (t = 9) before z = 10 (9.5)


def test_box_depth_exit_points_lie_on_the_box_surface():
    rng = np.random.default_rng(1)
    K = intrinsics_matrix(20.0, 15.5, 11.5)
    center, half = np.array([3.0, -2.0, 1.0]), np.array([40.0, 55.0, 35.0])
    pose = pose_matrix(random_rotation(rng), center + rng.uniform(-20, 20, 3))
    d = geometry.box_depth(K, pose, center, half, 32, 24)
    u, v = np.meshgrid(np.arange(32.0), np.arange(24.0))
    rays = np.stack([(u - 15.5) / 20, (v - 11.5) / 20, np.ones_like(u)], -1)
    pts = (rays * d[..., None]) @ pose[:3, :3].T + pose[:3, 3]  # planar depth * ray, to world
    rel = np.abs(pts - center) / half
    assert np.allclose(rel.max(axis=-1), 1.0)  # on a face, inside the others
    assert np.all(d > 0)


def test_wall_mask_tolerance():
    wall = np.full((2, 3), 50.0)
    depth = np.array([[50.0, 50.0 * (1 + 5e-4), 50.0 + 0.07], [49.0, 10.0, 50.0 - 0.05]])
    np.testing.assert_array_equal(
        geometry.wall_mask(depth, wall), [[True, True, False], [False, False, True]]
    )  # tolerance at 50 m: 1e-3 * 50 + 1e-3 = 0.051 m


# ---------------------------------------------------------------- flow and residuals


def test_flow_toward_a_fronto_parallel_wall():
    # depth Z everywhere is a plane facing the camera; moving forward by T scales the image about
    # the principal point c: p' = c + (p - c) Z / (Z - T), so |flow| = |p - c| T / (Z - T).
    w, h, Z, T = 64, 48, 10.0, 0.3
    K = intrinsics_matrix(32.0, 31.5, 23.5)
    rng = np.random.default_rng(2)
    r = random_rotation(rng)  # any orientation of the camera in the world
    pose_i = pose_matrix(r, [5.0, -3.0, 2.0])
    pose_j = pose_matrix(r, pose_i[:3, 3] + r @ [0.0, 0.0, T])  # forward along its own axis
    flow, z_j = geometry.true_flow(np.full((h, w), Z), K, pose_i, pose_j)
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    radial = np.stack([u - 31.5, v - 23.5], axis=-1)
    np.testing.assert_allclose(flow, radial * T / (Z - T), atol=1e-9)
    np.testing.assert_allclose(
        np.hypot(flow[..., 0], flow[..., 1]), np.hypot(*radial.transpose(2, 0, 1)) * T / (Z - T)
    )
    np.testing.assert_allclose(z_j, Z - T)


def test_flow_of_a_lateral_move_and_of_a_point_behind_the_camera():
    K = intrinsics_matrix(32.0, 15.5, 15.5)
    pose_j = pose_matrix(np.eye(3), [1.0, 0.0, 0.0])  # 1 m to the right
    flow, _ = geometry.true_flow(np.full((32, 32), 16.0), K, np.eye(4), pose_j)
    np.testing.assert_allclose(flow[..., 0], -32.0 * 1.0 / 16.0)  # -f Tx / Z = -2 px
    np.testing.assert_allclose(flow[..., 1], 0.0, atol=1e-12)
    back = pose_matrix(np.eye(3), [0.0, 0.0, 5.0])  # moves past a wall 2 m ahead
    flow, z_j = geometry.true_flow(np.full((4, 4), 2.0), K, np.eye(4), back)
    assert np.all(z_j < 0) and np.all(np.isnan(flow))


def test_warp_with_the_true_flow_undoes_a_lateral_move():
    # flow is (-2, 0) px everywhere: frame j is frame i moved 2 px to the left
    rng = np.random.default_rng(3)
    img_i = rng.integers(0, 256, size=(20, 24, 3), dtype=np.uint8)
    img_j = np.roll(img_i, -2, axis=1)
    depth = np.full((20, 24), 16.0)
    K = intrinsics_matrix(32.0, 11.5, 9.5)
    flow, z_j = geometry.true_flow(depth, K, np.eye(4), pose_matrix(np.eye(3), [1.0, 0.0, 0.0]))
    depth_j = depth.copy()
    depth_j[:5, :] = 8.0  # something nearer in frame j hides the top rows
    unwarped, warped, valid = geometry.warp_residuals(img_i, img_j, depth_j, flow, z_j)
    expected_valid = np.zeros((20, 24), bool)
    expected_valid[5:, 2:] = True  # columns 0-1 leave the frame; rows 0-4 are occluded
    np.testing.assert_array_equal(valid, expected_valid)
    assert np.all(warped[valid] < 1e-3)
    direct = np.abs(img_j.astype(float) - img_i.astype(float)).mean(axis=-1)
    np.testing.assert_allclose(unwarped, direct, atol=1e-4)
    assert unwarped[valid].mean() > 20


# ---------------------------------------------------------------- command line


def test_stats_of_a_folder_that_is_not_a_dataset_is_a_one_line_error(tmp_path):
    (tmp_path / "notes.txt").write_text("hello")
    assert_user_error(invoke_cli("stats", tmp_path), "dataset.json")
    assert_user_error(invoke_cli("stats", tmp_path / "missing"), "not a folder")
    assert not (tmp_path / "stats.json").exists()


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("stats") / "tiny"
    run_cli("--res", 32, "--scenes", 2, "--seed", 7, "--workers", 1, "--out", out, "--quiet")
    return out


@pytest.mark.render
def test_stats_command_on_a_tiny_real_dataset(tiny_dataset, tmp_path):
    report = tmp_path / "report"
    proc = run_cli("stats", tiny_dataset, "--flicker", 1, "--out", report)
    assert "median pixel depth" in proc.stdout and "StillBox" in proc.stdout
    assert (report / "stats.png").stat().st_size > 0
    s = json.loads((report / "stats.json").read_text())
    assert s["scenes_used"] == [0, 1] and s["shift"] == conventions.NOMINAL_SHIFT
    assert s["frames"] == 20 and s["pairs"] == 2 * (10 - conventions.NOMINAL_SHIFT)
    assert sum(s["depth"]["band_shares"].values()) == pytest.approx(1.0)
    wo = s["walls_objects"]
    assert wo["wall_share"] + wo["object_share"] == pytest.approx(1.0)
    assert wo["wall_share"] > 0.2 and wo["beyond_box_share"] == 0.0  # the box is seen, and sound
    assert wo["median_wall_depth_m"] > 15 and wo["median_object_depth_m"] < 30
    hist = s["depth"]["histogram"]
    total = sum(sum(hist[p]["shares"]) + hist[p]["share_above"] for p in ("walls", "objects"))
    assert total == pytest.approx(1.0)
    assert 0 < s["flow"]["walls"]["median_px"] < s["flow"]["objects"]["median_px"]
    assert s["residual"]["warped"]["walls"] < s["residual"]["unwarped_on_valid"]["walls"] + 1
    f = s["flicker"]
    assert f["frames"] == [[0, 0]] and f["depth_max_abs_diff_m"] < 1e-3  # same pose re-rendered
    assert f["same_pose"]["walls"] < 0.3 and f["same_pose"]["objects"] < 0.3  # issue target
    assert f["other_seed"]["walls"] is not None


@pytest.mark.render
def test_stats_python_api_and_bad_numbers(tiny_dataset, tmp_path):
    s = measure.dataset_stats(tiny_dataset, scenes=1, shift=9)
    assert s["scenes_used"] == [0] and s["pairs"] == 1
    assert s["depth"]["share_below_25m"] == pytest.approx(
        sum(s["depth"]["band_shares"][k] for k in histograms.BAND_LABELS[:5])
    )
    for args, word in (
        (["--shift", 10], "--shift"),
        (["--shift", 0], "--shift"),
        (["--scenes", 0], "--scenes"),
        (["--max-depth", -1], "--max-depth"),
        (["--flicker", 3], "--flicker"),
    ):
        assert_user_error(invoke_cli("stats", tiny_dataset, *args, "--out", tmp_path / "x"), word)
    assert not (tmp_path / "x").exists()


def test_stats_module_does_not_import_bpy():
    import subprocess
    import sys

    code = "import sys, stillbox_gen.stats, stillbox_gen.cli; print('bpy' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
