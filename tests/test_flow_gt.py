"""Optical-flow ground truth on disk (``stillbox-gen --flow``, stillbox_gen.flow): the stored flow
against an independent projection, a warp of the rendered frames with it, validation of its
files, the .flo format, KITTI's 16-bit PNG (``--flow-format kitti-png``) decoded here apart from
the package, and the flow files carried by ``stillbox-gen pack``."""

from __future__ import annotations

import json
import shutil
import struct
import tarfile
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from conftest import TINY_SHARES, assert_user_error, invoke_cli, invoke_main, run_cli

from stillbox_gen import formats, layout
from stillbox_gen.dataset import Dataset
from stillbox_gen.errors import ConfigError, DatasetError
from stillbox_gen.flow import OCCLUSION_TOLERANCE, write_scene_flow
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


# ---------------------------------------------------------------- KITTI's 16-bit PNG


@pytest.fixture(scope="module")
def kitti(stabilised, tmp_path_factory) -> Path:
    """The first 2 scenes of ``stabilised`` rendered again with ``--flow-format kitti-png`` alone
    (it implies --flow): the same seed, so the same frames and depth."""
    seed = json.loads((stabilised / layout.DATASET_JSON).read_text())["seed"]
    out = tmp_path_factory.mktemp("flow") / "kitti"
    run_cli("--res", 64, "--workers", 1, "--threads", 1, "--quiet", "--flow-format", "kitti-png",
            "--scenes", 2, "--seed", seed, "--split", ",".join(map(str, TINY_SHARES)),
            "--out", out)  # fmt: skip
    return out


def png_rgb16(path: Path) -> np.ndarray:
    """(H, W, 3) uint16 of a 16-bit RGB PNG in the file's channel order (R, G, B), decoded here
    with zlib and plain Python (no OpenCV, whose arrays are in B, G, R order): chunks, the
    scanline filters of the PNG specification, big-endian samples."""
    data = Path(path).read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, idat, head = 8, b"", None
    while pos < len(data):
        n, kind = struct.unpack(">I4s", data[pos : pos + 8])
        body = data[pos + 8 : pos + 8 + n]
        head = struct.unpack(">IIBBBBB", body) if kind == b"IHDR" else head
        idat += body if kind == b"IDAT" else b""
        pos += 12 + n
    w, h, depth, colour, _, _, interlace = head
    assert (depth, colour, interlace) == (16, 2, 0)  # 16 bits, truecolour RGB, not interlaced
    bpp, stride = 6, 6 * w
    raw = zlib.decompress(idat)
    prev, rows = [0] * stride, []
    for y in range(h):
        kind, line = raw[y * (stride + 1)], raw[y * (stride + 1) + 1 : (y + 1) * (stride + 1)]
        row = [0] * stride
        for i in range(stride):
            a, b = row[i - bpp] if i >= bpp else 0, prev[i]
            c = prev[i - bpp] if i >= bpp else 0
            if kind == 4:  # Paeth
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                pred = a if pa <= pb and pa <= pc else b if pb <= pc else c
            else:
                pred = (0, a, b, (a + b) // 2)[kind]
            row[i] = (line[i] + pred) % 256
        rows.append(row)
        prev = row
    pairs = np.array(rows, np.uint16).reshape(h, w, 3, 2)
    return pairs[..., 0] * np.uint16(256) + pairs[..., 1]


def kitti_decoded(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """KITTI's formula on :func:`png_rgb16`: ((H, W, 2) float64 (u, v) = (R, G) − 2**15) / 64,
    pixels), B as the valid flag (0 or 1)."""
    rgb = png_rgb16(path).astype(np.float64)
    return (rgb[..., :2] - 2**15) / 64, rgb[..., 2]


@pytest.mark.render
def test_kitti_png_flow_is_the_flo_flow_to_a_64th_of_a_pixel(stabilised, kitti):
    """--flow-format kitti-png: every pair's PNG, decoded here by KITTI's formula, holds the .flo
    dataset's flow to 1/128 px (rounded to 1/64 px steps) where valid, its valid channel is the
    .flo dataset's valid mask (at 64 px every valid flow fits KITTI's ±512 px), u = v = valid =
    0 elsewhere; the masks are the same files; the reader returns the decoded values; validate
    accepts the dataset. Prints the sizes of the flow files of both formats."""
    assert validate_dataset(kitti)[0] == []
    flo_ds, png_ds = Dataset(stabilised), Dataset(kitti)
    sizes, steps = np.zeros(2), set()
    for png_scene in png_ds.scenes():
        flo_scene = flo_ds.scene(png_scene.index)
        assert png_scene.depth[0].read_bytes() == flo_scene.depth[0].read_bytes()
        assert sorted(png_scene.flow_files) == sorted(flow_pairs(png_scene.frames))
        for (a, b), files in png_scene.flow_files.items():
            want = flo_scene.flow_files[a, b]
            assert files["flow"].name == layout.flow_name(layout.local_index(png_scene.index),
                                                          a, b, "kitti-png")  # fmt: skip
            assert files["flow"].suffix == ".png" and want["flow"].suffix == ".flo"
            for k in ("valid", "occluded"):
                assert files[k].read_bytes() == want[k].read_bytes(), (a, b, k)
            flo = formats.read_flo(want["flow"]).astype(np.float64)
            valid = formats.read_mask_png(want["valid"])
            uv, flag = kitti_decoded(files["flow"])
            assert np.array_equal(flag, valid.astype(np.float64))
            err = np.abs(uv - flo)[valid]
            assert err.max() <= 1 / 128, (a, b, err.max())
            assert np.all(uv[~valid] == -512)  # stored 0
            steps.update(np.unique(np.rint((uv[valid] - flo[valid]) * 1024)).tolist())
            flow, got_valid, _ = png_scene.load_flow(a, b)
            assert np.array_equal(got_valid, valid)
            assert np.array_equal(flow[valid], uv[valid].astype(np.float32))
            assert np.isnan(flow[~valid]).all()
            sizes += [files["flow"].stat().st_size, want["flow"].stat().st_size]
    assert len(steps) > 8  # rounding errors spread over (−1/128, 1/128): not a constant offset
    print(f"flow files of {len(png_ds.scenes())} scenes at 64 px: KITTI PNG {sizes[0]:,.0f} "
          f"bytes, .flo {sizes[1]:,.0f} bytes ({sizes[0] / sizes[1]:.2f})")  # fmt: skip


def test_kitti_png_out_of_range_and_undefined_flow_is_not_valid(tmp_path):
    """A valid flow beyond KITTI's 16 bits (about ±512 px) is stored as not valid, in both the
    PNG's valid channel and the valid mask (and not occluded), while the .flo file keeps it: a
    1100 px wide, 2 px high frame pair, the camera moving 6 m right past surfaces 1 m (row 0:
    flow −600 px) and 2 m away (row 1: −300 px). The encoder itself: KITTI's bounds, NaN."""
    w, f = 1100, 100.0
    depth = np.array([[1.0] * w, [2.0] * w], np.float32)
    moved = np.eye(4)
    moved[0, 3] = 6.0
    masks = {}
    for flow_format in ("flo", "kitti-png"):
        folder = tmp_path / flow_format
        folder.mkdir()
        record = {
            "depth_exr": ["d0.exr", "d1.exr"],
            "K": [[f, 0, (w - 1) / 2], [0, f, 0.5], [0, 0, 1]],
            "cam2world": [np.eye(4).tolist(), moved.tolist()],
            "flow": layout.flow_entries(0, 2, flow_format),
        }
        for name in record["depth_exr"]:
            formats.write_depth_exr(folder / name, depth)
        write_scene_flow(folder, record)
        entry = record["flow"][0]  # (0, 1)
        assert (entry["from"], entry["to"]) == (0, 1)
        masks[flow_format] = formats.read_mask_png(folder / entry["valid"])
        assert not formats.read_mask_png(folder / entry["occluded"]).any()
        if flow_format == "flo":
            flo = formats.read_flo(folder / entry["flow"])
            assert np.allclose(flo[0, 600:, 0], -600) and np.allclose(flo[1, 300:, 0], -300)
        else:
            uv, flag = kitti_decoded(folder / entry["flow"])
            assert np.array_equal(flag, masks[flow_format])
            assert np.abs(uv[1, 300:, 0] + 300).max() <= 1 / 128 and not uv[1, 300:, 1].any()
    inside = np.zeros((2, w), bool)
    inside[0, 600:], inside[1, 300:] = True, True
    assert np.array_equal(masks["flo"], inside)
    assert np.array_equal(masks["kitti-png"], inside & [[False], [True]])

    flow = np.array([[[511.984375, -512.0], [511.995, 0.0], [-512.01, 3.0], [np.nan, 0.0]]])
    valid = np.array([[True, False, False, False]])
    assert formats.kitti_representable(flow).tolist() == [[True, False, False, False]]
    path = tmp_path / "bounds.png"
    path.write_bytes(formats.kitti_flow_bytes(flow, valid))
    rgb = png_rgb16(path)
    assert rgb.tolist() == [[[65535, 0, 1], [0, 0, 0], [0, 0, 0], [0, 0, 0]]]
    with pytest.raises(ValueError, match="beyond KITTI's range"):
        formats.kitti_flow_bytes(flow, np.ones((1, 4), bool))


@pytest.mark.render
def test_validate_names_a_kitti_valid_channel_that_differs_from_its_mask(kitti, tmp_path):
    """A KITTI PNG whose valid channel no longer matches its valid mask is named by validate and
    refused by the reader."""
    copy = tmp_path / "ds"
    shutil.copytree(kitti, copy)
    scene = Dataset(copy).scene(0)
    path = scene.flow_files[0, 1]["flow"]
    bgr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    bgr[0, 0, 0] = 1 - bgr[0, 0, 0]  # OpenCV's channel 0 is the file's B: valid
    cv2.imwrite(str(path), bgr)
    problems = validate_dataset(copy)[0]
    assert any(path.name in p and "valid channel differs" in p for p in problems), problems
    with pytest.raises(DatasetError, match="valid channel differs"):
        scene.load_flow(0, 1)


def test_flow_format_implies_flow_and_a_preset_needs_render_flow(tmp_path):
    """--flow-format sets render.flow too; a preset with render.flow_format but no render.flow
    is refused naming the key; an unknown format is refused by the option."""
    from stillbox_gen import cli

    ctx = cli.generate.make_context("generate", ["--flow-format", "kitti-png"])
    cfg = cli.build_config(ctx.params)
    assert cfg.render.flow and cfg.render.flow_format == "kitti-png"
    assert "flow_format" in cfg.to_dict()["render"]
    plain = cli.build_config(cli.generate.make_context("generate", ["--flow"]).params)
    assert "flow_format" not in plain.to_dict()["render"]  # older fingerprints unchanged
    preset = tmp_path / "p.toml"
    preset.write_text('[render]\nflow_format = "kitti-png"\n')
    ctx = cli.generate.make_context("generate", ["--preset", str(preset)])
    with pytest.raises(ConfigError, match=r"render\.flow_format 'kitti-png' needs render\.flow"):
        cli.build_config(ctx.params)
    out = tmp_path / "never"
    assert_user_error(invoke_cli("--flow-format", "exr", "--out", out), "--flow-format")
    assert not out.exists()


# ---------------------------------------------------------------- packed shards carry the flow


@pytest.mark.render
@pytest.mark.parametrize("which", ["stabilised", "kitti"])
def test_pack_carries_the_flow_files_bit_for_bit(which, request, tmp_path):
    """``stillbox-gen pack``: every flow pair of every scene is in the shards under its
    documented member names, and PackedScene.load_flow returns the folder's flow and masks bit
    for bit (NaN included); the members are the folder's files byte for byte."""
    from stillbox_gen.packed import PackedDataset

    root = request.getfixturevalue(which)
    out = tmp_path / "P"
    result = invoke_cli("pack", root, "--format", "webdataset", "--out", out,
                        "--scenes-per-shard", 1)  # fmt: skip
    assert result.returncode == 0, result.stderr
    folder, pack = Dataset(root), PackedDataset(out)
    assert pack.index["pack_version"] == 2
    scenes = 0
    for s in pack.scenes():
        f = folder.scene(s.index)
        assert sorted(s.flow_files) == sorted(f.flow_files) == sorted(flow_pairs(f.frames))
        for a, b in f.flow_files:
            got, want = s.load_flow(a, b), f.load_flow(a, b)
            for x, y in zip(got, want, strict=True):
                assert x.dtype == y.dtype and x.tobytes() == y.tobytes(), (s.index, a, b)
        shard = next(sh for sh in pack.shards if s.index in sh.scenes)
        with tarfile.open(shard.path) as tar:
            for (a, b), files in f.flow_files.items():
                for k, path in files.items():
                    member = f"{s.index:07d}.{k}_{a:02d}_{b:02d}{path.suffix}"
                    assert tar.extractfile(member).read() == path.read_bytes()
        scenes += 1
    assert scenes == len(folder.indices())


@pytest.mark.render
def test_pack_refuses_a_changed_flow_file(stabilised, tmp_path):
    """A flow mask changed after generation fails its record's SHA-256 while packing: refused in
    one line naming the file, nothing left in --out."""
    copy = tmp_path / "ds"
    shutil.copytree(stabilised, copy)
    path = Dataset(copy).scene(0).flow_files[1, 0]["valid"]
    mask = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(path), 255 - mask)
    out = tmp_path / "P"
    result = invoke_cli("pack", copy, "--format", "webdataset", "--out", out)
    assert_user_error(result, path.name, "SHA-256")
    assert not out.exists() or not any(out.iterdir())
