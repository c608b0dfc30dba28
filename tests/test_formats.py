"""On-disk formats: depth EXR, sRGB conversion, JSON, the layout's records and the parquet
manifest."""

import json
import os
import re

import cv2
import jsonschema
import numpy as np
import pytest

from stillbox_gen import config, formats, layout, manifest, record, schema, writer
from stillbox_gen.errors import ConfigError
from stillbox_gen.scene import sample_scene

ORIGINAL_KEYS = ["imgs", "depth", "speed", "time_step", "length", "orientation"]


@pytest.fixture(scope="module")
def cfg():
    return config.load_preset("stillbox")


# ---------------------------------------------------------------- depth EXR


@pytest.fixture
def depth_map():
    d = np.random.default_rng(0).uniform(0.05, 200.0, size=(5, 7)).astype(np.float32)
    d[0, 0] = formats.NO_SURFACE_DEPTH
    d[4, 6] = np.float32(np.pi)
    d[2, 3] = np.nextafter(np.float32(1.0), np.float32(2.0))
    return d


def test_depth_exr_round_trip_is_bit_exact(tmp_path, depth_map):
    """write_depth_exr/read_depth_exr preserve float32 depth bit for bit, including 1e10."""
    path = tmp_path / "d.exr"
    formats.write_depth_exr(path, depth_map)
    back = formats.read_depth_exr(path)
    assert back.dtype == np.float32 and back.shape == depth_map.shape
    np.testing.assert_array_equal(back.view(np.uint32), depth_map.view(np.uint32))
    assert back[0, 0] == 1e10


def _opencv_has_openexr() -> bool:
    """Whether this OpenCV build has an EXR codec (the 4.x pip wheels do; 5.x's do not)."""
    build = cv2.getBuildInformation().splitlines()
    return any(line.split(":")[0].strip() == "OpenEXR" and "NO" not in line for line in build)


def test_depth_exr_is_readable_by_opencv(tmp_path, depth_map):
    """OpenCV reads the EXR as a single-channel float32 image equal to what was written."""
    if not _opencv_has_openexr():
        pytest.skip(f"OpenCV {cv2.__version__} is built without OpenEXR (no EXR codec to test)")
    path = tmp_path / "d.exr"
    formats.write_depth_exr(path, depth_map.astype(np.float64))  # converted to float32
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None
    assert img.dtype == np.float32 and img.shape == depth_map.shape
    np.testing.assert_array_equal(img, depth_map)


# ---------------------------------------------------------------- sRGB


def test_linear_to_srgb8_known_values():
    """0 -> 0, 1 -> 255, 0.5 linear -> 188 (sRGB curve), and values are clipped to [0, 1]."""
    out = formats.linear_to_srgb8(np.array([0.0, 1.0, 0.5, 2.0, -1.0, 0.0031308, 0.18]))
    assert out.dtype == np.uint8
    # 0.18 linear (mid grey) is 118 in sRGB; 0.0031308 ends the linear segment (x 12.92)
    assert out.tolist() == [0, 255, 188, 255, 0, 10, 118]


def test_linear_to_srgb8_is_monotonic():
    """The sRGB encoding never decreases and reaches every code at both ends."""
    out = formats.linear_to_srgb8(np.linspace(0.0, 1.0, 100001)).astype(int)
    assert np.all(np.diff(out) >= 0)
    assert out[0] == 0 and out[-1] == 255
    assert len(np.unique(out)) == 256


# ---------------------------------------------------------------- JSON


def test_atomic_write_json_leaves_only_the_file(tmp_path):
    """atomic_write_json writes the exact content and leaves no temporary file behind."""
    path = tmp_path / "meta.json"
    obj = {"b": [1, 2.5, None], "a": {"x": "y"}}
    formats.atomic_write_json(path, obj, indent=2)
    formats.atomic_write_json(path, {**obj, "c": 3})  # overwrite in place
    assert [p.name for p in tmp_path.iterdir()] == ["meta.json"]
    assert json.loads(path.read_text()) == {**obj, "c": 3}
    with pytest.raises(ValueError):
        formats.atomic_write_json(tmp_path / "nan.json", {"x": float("nan")})


def test_atomic_write_keeps_the_old_file_when_the_write_fails(tmp_path):
    """A write that fails half way leaves the old file and no temporary; the temporary is
    .<name>.tmp-<pid> beside the file (what every writer of both packages uses)."""
    path = tmp_path / "plot.png"
    path.write_bytes(b"old")
    assert formats.temp_path(path) == tmp_path / f".plot.png.tmp-{os.getpid()}"

    def half(f):
        f.write(b"ne")
        assert formats.temp_path(path).exists() and path.read_bytes() == b"old"
        raise RuntimeError("cut")

    with pytest.raises(RuntimeError, match="cut"):
        formats.atomic_write(path, half)
    assert [p.name for p in tmp_path.iterdir()] == ["plot.png"] and path.read_bytes() == b"old"
    formats.atomic_write(path, lambda f: f.write(b"new"), sync_folder=True)
    assert [p.name for p in tmp_path.iterdir()] == ["plot.png"] and path.read_bytes() == b"new"


def test_canonical_json_is_key_order_independent():
    """canonical_json gives the same text for equal dicts with different key orders."""
    a = {"a": 1, "b": {"c": [1, 2], "d": 0.1}}
    b = {"b": {"d": 0.1, "c": [1, 2]}, "a": 1}
    assert formats.canonical_json(a) == formats.canonical_json(b)
    assert formats.canonical_json(a) == '{"a":1,"b":{"c":[1,2],"d":0.1}}'
    assert formats.canonical_json({**a, "a": 2}) != formats.canonical_json(a)


# ---------------------------------------------------------------- scene records


@pytest.fixture(scope="module")
def spec(cfg):
    return sample_scene(cfg, 205).to_dict()  # chunk 1, scene 5 in the chunk


def test_scene_record_keeps_original_keys_and_names(spec):
    """Records start with the original StillBox keys and name files RGB_<ssss>_<ff>.png."""
    rec = record.scene_record(spec, "png", legacy=False)
    assert list(rec)[:6] == ORIGINAL_KEYS
    assert rec["length"] == 10 and rec["scene_in_chunk"] == 5 and rec["index"] == 205
    for names in (rec["imgs"], rec["rgb"], rec["depth"], rec["depth_exr"]):
        assert len(names) == 10
        assert all(n.count("_") == 2 for n in names)
    assert rec["imgs"] == rec["rgb"]
    assert all(re.fullmatch(r"RGB_0005_\d{2}\.png", n) for n in rec["rgb"])
    assert rec["rgb"][3] == "RGB_0005_03.png"
    assert rec["depth_exr"][9] == "depth_0005_09.exr"
    assert record.scene_record(spec, "jpg", legacy=False)["rgb"][0] == "RGB_0005_00.jpg"


def test_scene_record_geometry(spec):
    """world2cam inverts cam2world for every frame and the displacement is 0.1 m."""
    rec = record.scene_record(spec, "png", legacy=False)
    for c2w, w2c in zip(rec["cam2world"], rec["world2cam"], strict=True):
        np.testing.assert_allclose(np.array(w2c) @ np.array(c2w), np.eye(4), atol=1e-12)
    assert rec["displacement"] == pytest.approx(0.1, rel=1e-12)
    assert rec["speed"] == spec["camera"]["speed"]
    assert rec["resolution"] == [64, 64]


def test_scene_record_legacy_names(spec):
    """legacy=True names .jpg frames and .npy depth in imgs/depth but keeps png/exr files."""
    rec = record.scene_record(spec, "png", legacy=True)
    assert rec["imgs"][2] == "RGB_0005_02.jpg" and rec["depth"][2] == "depth_0005_02.npy"
    assert all(n.endswith(".png") for n in rec["rgb"])
    assert all(n.endswith(".exr") for n in rec["depth_exr"])


def test_spec_from_record_inverts_scene_record(spec):
    """record -> spec gives back the spec the record was written from (through JSON, as read
    from metadata.json), and keeps only the poses asked for; a record lacking a key is named."""
    rec = json.loads(json.dumps(record.scene_record(spec, "png", legacy=True)))
    assert record.spec_from_record(rec) == spec
    two = record.spec_from_record(rec, frames=[3, 0])
    assert two["camera"]["cam2world"] == [spec["camera"]["cam2world"][f] for f in (3, 0)]
    assert {k: v for k, v in two.items() if k != "camera"} == {
        k: v for k, v in spec.items() if k != "camera"
    }
    del rec["light"], rec["resolution"]
    with pytest.raises(ConfigError, match="scene 205's record lacks light, resolution"):
        record.spec_from_record(rec)


@pytest.mark.parametrize("legacy", [False, True])
def test_scene_record_matches_schema(spec, legacy):
    """The record is strict JSON and validates against schema.SCENE_RECORD."""
    rec = json.loads(json.dumps(record.scene_record(spec, "png", legacy), allow_nan=False))
    jsonschema.validate(rec, schema.SCENE_RECORD)
    rec["rgb"][0] = "RGB_0005.png"
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(rec, schema.SCENE_RECORD)


# ---------------------------------------------------------------- paths and checksums


def test_resolve_inside_refuses_paths_leaving_the_root(tmp_path):
    """Absolute paths, '..' components and symlinks out of the root are refused, naming the
    record; names inside the root (symlinks within it too) are returned unresolved."""
    root = tmp_path / "root"
    (root / "0").mkdir(parents=True)
    (tmp_path / "secret").write_text("x")
    (root / "0" / "in.png").write_text("x")
    os.symlink(tmp_path / "secret", root / "0" / "out.png")
    os.symlink("in.png", root / "0" / "link.png")
    os.symlink(tmp_path, root / "1")
    assert formats.resolve_inside(root, "0/in.png", "w") == root / "0" / "in.png"
    assert formats.resolve_inside(root, "0/link.png", "w") == root / "0" / "link.png"
    assert formats.resolve_inside(root, "in.png", "w", folder="0") == root / "0" / "in.png"
    with pytest.raises(formats.UnsafePathError, match="absolute path"):  # not root/0/<abs>
        formats.resolve_inside(root, str(tmp_path / "secret"), "w", folder="0")
    bad = {
        "../secret": "has '..'",
        "0/../0/in.png": "has '..'",
        str(tmp_path / "secret"): "absolute path",
        "0/out.png": "leads through a symlink",
        "1/secret": "leads through a symlink",
        "": "is not a file name",
    }
    for relpath, words in bad.items():
        with pytest.raises(formats.UnsafePathError, match="^0/metadata.json: scene 3: ") as e:
            formats.resolve_inside(root, relpath, "0/metadata.json: scene 3")
        assert words in str(e.value)


def test_scene_checksums_cover_every_scene_file(tmp_path, spec):
    """scene_checksums hashes every file a record names (legacy copies too), by SHA-256."""
    import hashlib

    rec = record.scene_record(spec, "png", legacy=True)
    names = layout.scene_files(rec)
    assert len(names) == 40 and names == sorted(
        set(rec["rgb"] + rec["imgs"] + rec["depth"] + rec["depth_exr"])
    )
    for i, name in enumerate(names):
        (tmp_path / name).write_bytes(bytes([i]))
    sums = writer.scene_checksums(tmp_path, rec)
    assert sums == {n: hashlib.sha256(bytes([i])).hexdigest() for i, n in enumerate(names)}


# ---------------------------------------------------------------- manifest


def test_split_of_is_deterministic_and_balanced():
    """split_of depends only on (seed, index) and follows the 0.8/0.1/0.1 shares."""
    shares = (0.8, 0.1, 0.1)
    splits = [manifest.split_of(0, i, shares) for i in range(2000)]
    assert [manifest.split_of(0, i, shares) for i in range(1999, -1, -1)] == splits[::-1]
    for name, share in zip(manifest.SPLITS, shares, strict=True):
        assert splits.count(name) / 2000 == pytest.approx(share, abs=0.03)
    assert [manifest.split_of(1, i, shares) for i in range(2000)] != splits
    assert {manifest.split_of(0, i, (0.0, 0.0, 1.0)) for i in range(100)} == {"test"}
    assert {manifest.split_of(0, i, (1.0, 0.0, 0.0)) for i in range(100)} == {"train"}


def test_manifest_round_trip(tmp_path, cfg):
    """write_manifest/read_manifest keep the schema and give one row per frame with right paths."""
    indices = [0, 1, 201]
    records = [
        record.scene_record(sample_scene(cfg, i).to_dict(), "png", legacy=False) for i in indices
    ]
    path = tmp_path / "manifest.parquet"
    manifest.write_manifest(path, records, seed=cfg.seed, shares=cfg.split)
    assert [p.name for p in tmp_path.iterdir()] == ["manifest.parquet"]
    table = manifest.read_manifest(path)
    # Parquet renames list children ("item" -> "element"), so compare types and docs separately
    assert table.schema.equals(manifest.MANIFEST_SCHEMA)
    assert table.schema.metadata == manifest.MANIFEST_SCHEMA.metadata
    assert [f.metadata for f in table.schema] == [f.metadata for f in manifest.MANIFEST_SCHEMA]
    rows = table.to_pylist()
    assert len(rows) == 10 * len(indices)
    for row in rows:
        rec = records[indices.index(row["scene"])]
        f = row["frame"]
        chunk = str(row["scene"] // 200)  # the documented chunk size, not layout.CHUNK_SIZE
        assert row["chunk"] == chunk
        assert row["rgb"] == f"{chunk}/{rec['rgb'][f]}"
        assert row["depth"] == f"{chunk}/{rec['depth_exr'][f]}"
        assert row["split"] == manifest.split_of(cfg.seed, row["scene"], cfg.split)
        expected = np.array(rec["speed"]) * rec["time_step"] * f
        np.testing.assert_allclose(row["position"], expected, atol=1e-12)
        pose0, pose = np.array(rec["cam2world"][0]), np.array(rec["cam2world"][f])
        in_cam0 = pose0[:3, :3].T @ (pose[:3, 3] - pose0[:3, 3])
        np.testing.assert_allclose(row["position"], in_cam0, atol=1e-12)
        np.testing.assert_allclose(np.reshape(row["cam2world"], (4, 4)), rec["cam2world"][f])
        assert row["orientation"] == [1.0, 0.0, 0.0, 0.0]
        assert [row["fx"], row["fy"], row["cx"], row["cy"]] == pytest.approx([32, 32, 31.5, 31.5])
    assert rows[25]["rgb"] == "1/RGB_0001_05.png" and rows[25]["scene_in_chunk"] == 1
