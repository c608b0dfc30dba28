"""Optical-flow ground truth on disk (``stillbox-gen --flow``, stillbox_gen.flow): the stored flow
against an independent projection, a warp of the rendered frames with it, validation of its
files, and the .flo format."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from conftest import TINY_SHARES, invoke_main, run_cli

from stillbox_gen import formats, layout
from stillbox_gen.dataset import Dataset
from stillbox_gen.errors import DatasetError
from stillbox_gen.flow import OCCLUSION_TOLERANCE
from stillbox_gen.layout import FLOW_SHIFTS, flow_pairs
from stillbox_gen.validate import validate_dataset

RUN = ("--res", 64, "--workers", 1, "--threads", 1, "--flow", "--quiet")


@pytest.fixture(scope="module")
def stabilised(tmp_path_factory) -> Path:
    """Default preset (stabilised camera), 3 scenes of 10 frames, one per split, with --flow."""
    from stillbox_gen.manifest import split_of

    splits = {"train", "val", "test"}
    seed = next(s for s in range(100) if {split_of(s, k, TINY_SHARES) for k in range(3)} == splits)
    out = tmp_path_factory.mktemp("flow") / "stabilised"
    run_cli(*RUN, "--scenes", 3, "--seed", seed, "--split", ",".join(map(str, TINY_SHARES)),
            "--out", out)  # fmt: skip
    return out


@pytest.fixture(scope="module")
def rotating(tmp_path_factory) -> Path:
    """Preset stillbox-rotating (rotation and translation), 3 scenes of 6 frames, with --flow."""
    out = tmp_path_factory.mktemp("flow") / "rotating"
    run_cli(*RUN, "--preset", "stillbox-rotating", "--frames", 6, "--scenes", 3, "--seed", 4,
            "--out", out)  # fmt: skip
    return out


def projected(rec: dict, depth: np.ndarray, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
    """Where frame a's pixel centres land in frame b, and their depth there, written apart from
    stillbox_gen.flow: each pixel solved through K, to world by frame a's cam2world, back by frame
    b's recorded world2cam, divided by its z. Returns ((H, W, 2) pixels, (H, W) metres)."""
    K = np.array(rec["K"])
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    rays = np.linalg.solve(K, np.stack([u.ravel(), v.ravel(), np.ones(h * w)]))  # (3, N)
    cam = np.vstack([rays * depth.ravel().astype(np.float64), np.ones(h * w)])
    world = np.array(rec["cam2world"][a]) @ cam
    in_b = (np.array(rec["world2cam"][b]) @ world)[:3]
    z = in_b[2]
    xy = np.stack([K[0, 0] * in_b[0] / z + K[0, 2], K[1, 1] * in_b[1] / z + K[1, 2]], axis=-1)
    return xy.reshape(h, w, 2), z.reshape(h, w)


def landing_masks(xy: np.ndarray, z: np.ndarray, depth_b: np.ndarray):
    """(inside frame b and in front of it, hidden at the nearest pixel) of :func:`projected`."""
    h, w = z.shape
    x, y = xy[..., 0], xy[..., 1]
    inside = (z > 0) & (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    col = np.clip(np.rint(np.nan_to_num(x)), 0, w - 1).astype(int)
    row = np.clip(np.rint(np.nan_to_num(y)), 0, h - 1).astype(int)
    hidden = inside & (z > (1 + OCCLUSION_TOLERANCE) * depth_b[row, col])
    return inside, hidden


@pytest.mark.render
@pytest.mark.parametrize("which", ["stabilised", "rotating"])
def test_stored_flow_is_the_projection_of_depth_through_the_poses(which, request):
    """Every pair of flow_pairs is stored; its flow equals an independent projection to 1e-3 px
    on the valid pixels, its valid mask equals "lands inside frame b, in front of it", and every
    occluded pixel is hidden at the pixel it lands in."""
    ds = Dataset(request.getfixturevalue(which))
    for scene in ds.scenes():
        assert sorted(scene.flow_files) == sorted(flow_pairs(scene.frames))
        for a, b in scene.flow_files:
            flow, valid, occluded = scene.load_flow(a, b)
            xy, z = projected(scene.record, scene.load_depth(a), a, b)
            inside, hidden = landing_masks(xy, z, scene.load_depth(b))
            grid = np.stack(np.meshgrid(np.arange(xy.shape[1]), np.arange(xy.shape[0])), -1)
            err = np.abs(flow - (xy - grid))[valid]
            assert err.max() < 1e-3, (which, scene.index, a, b, err.max())
            assert np.array_equal(valid, inside)
            assert not np.any(occluded & ~hidden)  # hidden at the landing pixel
            assert occluded.mean() < 0.1


@pytest.mark.render
def test_stabilised_flow_equals_the_benchmarks_translation_only_flow(stabilised):
    """On a stabilised camera the stored flow is benchmark.core.flow's translation-only formula."""
    from benchmark.core.flow import flow_from_depth

    for scene in Dataset(stabilised).scenes():
        for a, b in ((0, 1), (4, 1)):
            flow, valid, _ = scene.load_flow(a, b)
            t = torch.from_numpy(scene.translation(a, b))
            depth = torch.from_numpy(scene.load_depth(a).astype(np.float64))
            ref = flow_from_depth(depth, torch.from_numpy(scene.K), t).numpy()
            assert np.abs(flow - ref.transpose(1, 2, 0))[valid].max() < 1e-3


@pytest.mark.render
def test_rotating_flow_holds_the_rotation(rotating):
    """The rotating preset's stored flow differs from the translation-only flow by the rotation:
    the full poses are used."""
    from benchmark.core.flow import flow_from_depth

    gaps = []
    for scene in Dataset(rotating).scenes():
        flow, valid, _ = scene.load_flow(3, 0)
        c2w_0, c2w_3 = scene.cam2world[0], scene.cam2world[3]
        t = torch.from_numpy(c2w_3[:3, :3].T @ (c2w_0[:3, 3] - c2w_3[:3, 3]))  # in 3's axes
        depth = torch.from_numpy(scene.load_depth(3).astype(np.float64))
        ref = flow_from_depth(depth, torch.from_numpy(scene.K), t).numpy().transpose(1, 2, 0)
        gaps.append(float(np.median(np.linalg.norm(flow - ref, axis=-1)[valid])))
    assert max(gaps) > 0.2, gaps


def photometric_residuals(scene, a: int, b: int) -> tuple[np.ndarray, int]:
    """Summed |frame a − frame b resampled| (grey levels, mean over colour channels) on the
    pixels valid, not occluded and moving by more than a pixel, with frame b resampled
    (bilinearly) at a's pixels moved by the stored flow, by the test's own depth projection, and
    not moved; and the number of those pixels."""
    img_a, img_b = (scene.load_rgb(f).astype(np.float32) for f in (a, b))
    flow, valid, occluded = scene.load_flow(a, b)
    xy, _ = projected(scene.record, scene.load_depth(a), a, b)
    h, w = valid.shape
    grid = np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).astype(np.float32)
    use = valid & ~occluded & (np.linalg.norm(np.nan_to_num(flow), axis=-1) > 1.0)

    def residual(where: np.ndarray) -> float:
        m = where.astype(np.float32)
        warped = cv2.remap(img_b, m[..., 0], m[..., 1], cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_REPLICATE)  # fmt: skip
        return float(np.abs(warped - img_a).mean(-1)[use].sum())

    sums = [residual(grid + np.nan_to_num(flow)), residual(xy), residual(grid)]
    return np.array(sums), int(use.sum())


@pytest.mark.render
@pytest.mark.parametrize("which", ["stabilised", "rotating"])
def test_warping_with_the_stored_flow_reproduces_the_frame(which, request):
    """Frame b warped to frame a with the stored flow, over the pairs (0, s) and (s, 0) of every
    scene (s = 1 and 3): on valid, non-occluded pixels moving by more than a pixel, the mean
    residual is the depth-based warp's (within 1 %) and under 0.6 times the residual without a
    warp (at 64 px, resampling aliased textures leaves 2-7 grey levels)."""
    ds = Dataset(request.getfixturevalue(which))
    total, pixels = np.zeros(3), 0
    for scene in ds.scenes():
        for s in FLOW_SHIFTS:
            for a, b in ((0, s), (s, 0)):
                sums, used = photometric_residuals(scene, a, b)
                assert sums[0] <= 1.01 * sums[1] + 0.01 * used, (scene.index, a, b, sums / used)
                total, pixels = total + sums, pixels + used
    stored, depth, none = total / pixels
    print(f"{which}: {pixels} px, residual (grey levels) stored flow {stored:.3f}, "
          f"depth warp {depth:.3f}, no warp {none:.3f}")  # fmt: skip
    assert pixels > 1000
    assert stored <= 1.01 * depth and stored < 0.6 * none


@pytest.mark.render
def test_validate_names_a_missing_or_changed_flow_file(stabilised, tmp_path):
    """validate: a deleted .flo, a changed mask and a record without its flow list each named."""
    assert validate_dataset(stabilised)[0] == []
    copy = tmp_path / "ds"
    shutil.copytree(stabilised, copy)
    chunk = copy / "0"
    rec = json.loads((chunk / layout.METADATA_JSON).read_text())["scenes"][0]
    gone, changed = rec["flow"][0]["flow"], rec["flow"][1]["occluded"]
    (chunk / gone).unlink()
    mask = cv2.imread(str(chunk / changed), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(chunk / changed), 255 - mask)
    problems = validate_dataset(copy)[0]
    assert any(gone in p and "missing" in p for p in problems), problems
    assert any(changed in p and "SHA-256" in p for p in problems), problems
    assert any(changed in p and "occluded pixels outside the valid mask" in p for p in problems)


def test_flo_round_trip_and_bad_magic(tmp_path):
    """A .flo file reads back bit for bit (with OpenCV too); another magic number is refused in
    one line naming the file."""
    flow = np.random.default_rng(0).normal(size=(5, 7, 2)).astype(np.float32) * 30
    path = tmp_path / "a.flo"
    formats.write_flo(path, flow)
    assert np.array_equal(formats.read_flo(path), flow)
    assert np.array_equal(cv2.readOpticalFlow(str(path)), flow)
    bad = tmp_path / "bad.flo"
    bad.write_bytes(np.float32(1.0).tobytes() + path.read_bytes()[4:])
    with pytest.raises(DatasetError, match=r"bad\.flo.*magic number") as e:
        formats.read_flo(bad)
    assert "\n" not in str(e.value)


def test_flow_pairs_are_consecutive_and_nominal_both_ways():
    assert flow_pairs(5) == [(0, 1), (1, 0), (1, 2), (2, 1), (2, 3), (3, 2), (3, 4), (4, 3),
                             (0, 3), (3, 0), (1, 4), (4, 1)]  # fmt: skip
    assert flow_pairs(2) == [(0, 1), (1, 0)]


# ---------------------------------------------------------------- the benchmark scores flow on it


def bench(*args) -> str:
    """``stillbox-bench ARGS`` in this process; its stdout (the test fails on an error)."""
    from benchmark import cli

    result = invoke_main(cli.main, *args)
    assert result.returncode == 0, result.stderr
    return result.stdout


@pytest.mark.render
def test_flow_network_is_scored_against_the_stored_flow_and_saves_flo(stabilised, tmp_path):
    """A FlowNetS run on a dataset with stored flow: its EPE and Fl-all are those of its saved
    .flo predictions against the stored flow on the valid pixels (recomputed here in numpy), and
    the report says which ground truth it used."""
    out = tmp_path / "flownets"
    bench("run", "flownets-flow-tiny", "--data", stabilised, "--batch-size", 4, "--max-steps",
          2, "--quiet", "--save-predictions", "--out", out)  # fmt: skip
    summary = json.loads((out / "summary.json").read_text())
    assert summary["flow_ground_truth"].startswith("the dataset's stored flow")
    assert "stored flow" in (out / "summary.md").read_text()
    ds = Dataset(stabilised)
    epe, fl = [], []
    for row in csv_rows(out / "per_sample.csv"):
        k, i1, i2 = int(row["scene"]), int(row["frame1"]), int(row["frame2"])
        pred = formats.read_flo(out / "predictions" / layout.chunk_name(k)
                                / layout.flow_name(layout.local_index(k), i2, i1))  # fmt: skip
        truth, valid, _ = ds.scene(k).load_flow(i2, i1)
        err = np.linalg.norm(pred.astype(np.float64) - truth, axis=-1)[valid]
        size = np.linalg.norm(truth, axis=-1)[valid]
        epe.append(err.mean())
        fl.append(np.mean((err > 3) & (err > 0.05 * size)))
        assert float(row["epe"]) == pytest.approx(epe[-1], rel=1e-5)
    assert summary["metrics"]["epe"] == pytest.approx(np.mean(epe), rel=1e-5)
    assert summary["metrics"]["fl_all"] == pytest.approx(np.mean(fl), abs=1e-9)
    given = tmp_path / "given"  # the saved folder, flow files beside the depth, reads back
    bench("eval", "--predictions", out / "predictions", "--data", stabilised,
          "--out", given)  # fmt: skip
    again = json.loads((given / "summary.json").read_text())["metrics"]
    assert again["mae"] == pytest.approx(summary["metrics"]["mae"], rel=1e-5)


@pytest.mark.render
def test_oracle_flow_matches_the_stored_flow_on_a_stabilised_camera(stabilised, tmp_path):
    """oracle-flow's exact flow (translation only, the second frame's depth) scored against the
    stored flow: the two computations agree to float32 rounding."""
    out = tmp_path / "oracle"
    bench("run", "oracle-flow", "--data", stabilised, "--quiet", "--out", out)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["flow_ground_truth"].startswith("the dataset's stored flow")
    assert summary["metrics"]["epe"] < 1e-4 and summary["metrics"]["fl_all"] == 0


def csv_rows(path: Path) -> list[dict]:
    import csv

    return list(csv.DictReader(path.open()))
