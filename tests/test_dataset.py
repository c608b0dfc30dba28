"""stillbox_gen.writer (commit, finalize) and stillbox_gen.dataset (the one reader), on a
dataset written without Blender (synthetic frames) and on a rendered one, and the README's
Python API example run as written."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from stillbox_gen import config, layout, manifest, writer
from stillbox_gen.dataset import Dataset
from stillbox_gen.errors import DatasetError
from stillbox_gen.formats import write_depth_exr
from stillbox_gen.record import scene_record
from stillbox_gen.scene import sample_scene
from stillbox_gen.validate import validate_dataset

README = Path(__file__).resolve().parents[1] / "README.md"
W, H, FRAMES, SCENES = 8, 6, 4, 5


def _fake_frames(folder: Path, record: dict, k: int) -> None:
    """Write the scene's RGB frames (a known pattern per scene and frame) and depth maps."""
    for f, (rgb, exr) in enumerate(zip(record["rgb"], record["depth_exr"], strict=True)):
        cv2.imwrite(str(folder / rgb), _pattern(k, f)[..., ::-1])  # OpenCV writes BGR
        write_depth_exr(folder / exr, np.full((H, W), 10.0 + k + f / 10, np.float32))


def _pattern(k: int, f: int) -> np.ndarray:
    """(H, W, 3) uint8 RGB, different in each channel, scene and frame."""
    img = np.zeros((H, W, 3), np.uint8)
    img[..., 0], img[..., 1], img[..., 2] = 10 * k, 20 * f, np.arange(W) * 30
    return img


@pytest.fixture(scope="module")
def fake(tmp_path_factory) -> tuple[Path, config.DatasetConfig]:
    """A 5-scene dataset through the real lifecycle (prepare, commit, finalize), frames drawn
    here instead of rendered."""
    out = tmp_path_factory.mktemp("fake") / "ds"
    camera = {"width": W, "height": H, "frames": FRAMES}
    cfg = config.replace(config.load_preset("stillbox"), camera=camera)
    writer.prepare_output(out, cfg, SCENES)
    for k in writer.pending_indices(out, SCENES):
        spec = sample_scene(cfg, k).to_dict()
        tmp = out / layout.scene_tmp_name(k)
        tmp.mkdir(parents=True)
        record = scene_record(spec, cfg.render.image_format, cfg.render.legacy)
        _fake_frames(tmp, record, k)
        writer.commit_scene(out, spec, cfg)
    totals = writer.finalize(out, cfg, SCENES, {"by": "test_dataset"})
    assert totals.scenes == SCENES and totals.frames == SCENES * FRAMES
    return out, cfg


def test_a_finalized_dataset_validates(fake):
    """What the lifecycle writes is the documented format (no Blender needed to check that)."""
    out, _ = fake
    problems, stats = validate_dataset(out)
    assert problems == [] and stats["scenes"] == SCENES


def test_reader_gives_splits_files_camera_and_pixels(fake):
    out, cfg = fake
    ds = Dataset(out)
    assert ds.info["complete"] is True and ds.info["run"] == {"by": "test_dataset"}
    assert ds.indices() == list(range(SCENES))
    for k in range(SCENES):
        assert ds.splits[k] == manifest.split_of(cfg.seed, k, cfg.split)
    for split in manifest.SPLITS:
        assert [s.index for s in ds.scenes(split)] == ds.indices(split)
    assert [s.index for s in ds.scenes(limit=2)] == [0, 1]
    scene = ds.scene(3)
    spec = sample_scene(cfg, 3).to_dict()
    assert scene.frames == FRAMES and scene.split == ds.splits[3]
    assert scene.rgb[2] == out / "0" / "RGB_0003_02.png"
    assert scene.depth[2] == out / "0" / "depth_0003_02.exr"
    np.testing.assert_array_equal(scene.K, spec["camera"]["K"])
    assert scene.cam2world.shape == (FRAMES, 4, 4)
    np.testing.assert_array_equal(scene.cam2world, spec["camera"]["cam2world"])
    np.testing.assert_array_equal(scene.load_rgb(2), _pattern(3, 2))  # RGB order
    assert scene.load_depth(2).dtype == np.float32
    assert np.all(scene.load_depth(2) == np.float32(13.2))  # 10 + scene + frame / 10
    assert scene.displacement == pytest.approx(cfg.camera.displacement)
    assert scene.record["index"] == 3 and scene.stabilised


def test_relative_pose_and_translation_agree_with_the_poses(fake):
    """Stabilised camera: frame i to frame j is a pure translation, minus the camera's
    displacement in its own axes."""
    scene = Dataset(fake[0]).scene(1)
    pose = scene.relative_pose(0, 3)
    np.testing.assert_allclose(pose[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(pose[:3, 3], -scene.translation(0, 3), atol=1e-12)
    assert np.linalg.norm(scene.translation(0, 3)) == pytest.approx(3 * scene.displacement)


def test_reader_errors_name_the_file(fake, tmp_path):
    out, _ = fake
    with pytest.raises(DatasetError, match="is not a folder"):
        Dataset(tmp_path / "missing")
    empty = Dataset(tmp_path)
    with pytest.raises(DatasetError, match="has no dataset.json"):
        _ = empty.info
    with pytest.raises(DatasetError, match="has no manifest.parquet"):
        empty.scenes()
    with pytest.raises(DatasetError, match="manifest.parquet: no scene 99"):
        Dataset(out).scene(99)


def test_reader_reads_each_file_once(fake, monkeypatch):
    """One read of the manifest and of each chunk's metadata.json, however many calls."""
    out, _ = fake
    reads: list[str] = []
    real = manifest.read_manifest
    monkeypatch.setattr(manifest, "read_manifest", lambda *a, **k: reads.append(a) or real(*a, **k))
    ds = Dataset(out)
    ds.scenes("train"), ds.scenes(), ds.indices("val"), ds.scene(0)
    assert len(reads) == 1 and len(ds._metadata) == 1


# ---------------------------------------------------------------- the README's example


def readme_example() -> str:
    """The Python code block of the README's "Python API" section."""
    section = README.read_text().split("## Python API", 1)[1].split("\n## ", 1)[0]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_readme_example_loads_pairs(default_dataset):
    """Runs the README's example as written (DataLoader with 2 worker processes) on the
    session's rendered 4-scene dataset, and checks a batch against the files."""
    code = readme_example()
    assert '"data/stillbox-64"' in code
    namespace: dict = {}
    exec(code.replace('"data/stillbox-64"', repr(str(default_dataset))), namespace)
    pairs, loader = namespace["loader"].dataset, namespace["loader"]
    train = Dataset(default_dataset).scenes("train")
    assert len(pairs) == sum(s.frames - 3 for s in train) > 0
    batch = next(iter(loader))
    n = len(batch["images"])
    assert batch["images"].shape == (n, 6, 64, 64) and batch["depth"].shape == (n, 64, 64)
    assert batch["K"].shape == (n, 3, 3) and batch["pose"].shape == (n, 4, 4)
    assert float(batch["images"].min()) >= 0 and float(batch["images"].max()) <= 1
    assert float(batch["depth"].min()) > 0 and float(batch["depth"].max()) <= 100.0

    item, (k, i) = pairs[0], pairs.items[0]
    scene = pairs.scenes[k]
    frames = np.concatenate([scene.load_rgb(i), scene.load_rgb(i + 3)], axis=-1)
    np.testing.assert_allclose(item["images"].numpy(), frames.transpose(2, 0, 1) / 255, atol=1e-7)
    np.testing.assert_array_equal(item["depth"].numpy(), np.clip(scene.load_depth(i + 3), 0, 100))
    np.testing.assert_allclose(item["pose"][:3, 3].numpy(), -scene.translation(i, i + 3), atol=1e-6)
