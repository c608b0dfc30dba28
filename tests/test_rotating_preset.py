"""The rotating StillBox of thesis 5.3 (preset stillbox-rotating, camera.rotation_speed_range_deg):
a rotation speed drawn per scene, constant over its frames, recorded by its orientations; and the
presets without the field keep their scenes and fingerprints."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math

import numpy as np
import pytest
from conftest import run_cli

from stillbox_gen import config, formats
from stillbox_gen.scene import sample_scene
from stillbox_gen.validate import validate_dataset

PRESET = "stillbox-rotating"
N_SCENES = 100


@pytest.fixture(scope="module")
def cfg() -> config.DatasetConfig:
    return config.load_preset(PRESET)


@pytest.fixture(scope="module")
def scenes(cfg):
    return [sample_scene(cfg, k) for k in range(N_SCENES)]


def matrix_angle_deg(m: np.ndarray) -> float:
    """Rotation angle of a 3x3 rotation matrix, degrees: trace = 1 + 2 cos(angle) and the
    antisymmetric part's axial vector has length sin(angle) (atan2 of both, accurate near 0)."""
    sin = np.linalg.norm([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]]) / 2
    return math.degrees(math.atan2(sin, (np.trace(m) - 1) / 2))


def quat_angle_deg(q) -> float:
    """Rotation angle of a quaternion [w, x, y, z], degrees."""
    return math.degrees(2 * math.atan2(float(np.linalg.norm(q[1:])), q[0]))


def recorded_speed_deg(orientation: list) -> float:
    """A scene's rotation speed, degrees per frame, as a reader gets it from its record: the
    angle of orientation[1] (R_cam0<-cam1, docs/FORMAT.md)."""
    return quat_angle_deg(orientation[1])


def test_preset_is_stillbox_with_a_random_constant_rotation_and_20_frames(cfg):
    """Thesis 5.3: StillBox plus a random constant rotation, 1500 scenes = 30k frames; no noise."""
    c = cfg.camera
    assert 1500 * c.frames == 30_000 and 100 * c.frames == 2_000
    assert c.rotation_speed_range_deg == (0.0, 1.0)
    assert c.rotation_noise_deg == 0 and c.rotation_speed_deg == 0
    config.validate(cfg, config.preset_origin(PRESET))
    plain = dataclasses.replace(c, frames=10, rotation_speed_range_deg=None)
    assert dataclasses.replace(cfg, camera=plain, preset="stillbox") == config.DatasetConfig()


def test_relative_rotation_between_consecutive_frames_is_one_matrix(scenes):
    """R_i^T R_(i+1) (from cam2world) is the same matrix for every i, of the recorded speed."""
    for s in scenes:
        rots = np.array(s.camera.cam2world)[:, :3, :3]
        rel = np.einsum("fji,fjk->fik", rots[:-1], rots[1:])  # R_i^T R_(i+1)
        np.testing.assert_allclose(rel, [rel[0]] * len(rel), atol=1e-9, err_msg=f"{s.index}")
        speed = recorded_speed_deg(s.camera.orientation)
        assert matrix_angle_deg(rel[0]) == pytest.approx(speed, abs=1e-9)


def test_orientations_turn_by_the_speed_every_frame(scenes):
    """orientation[i] is a rotation by i times the speed about one axis (frame 0: identity)."""
    for s in scenes:
        q = np.array(s.camera.orientation)
        assert q.shape == (20, 4) and q[0].tolist() == [1.0, 0.0, 0.0, 0.0]
        speed = recorded_speed_deg(s.camera.orientation)
        angles = [quat_angle_deg(qi) for qi in q]
        np.testing.assert_allclose(angles, speed * np.arange(20), atol=1e-9)
        axes = q[1:, 1:] / np.linalg.norm(q[1:, 1:], axis=1, keepdims=True)
        np.testing.assert_allclose(axes, [axes[0]] * 19, atol=1e-9)


def test_speed_is_drawn_per_scene_uniformly_in_the_range(scenes, cfg):
    """Speeds lie in the range, differ between scenes and follow the uniform law (Kolmogorov
    distance below its 1 % critical value 1.63 / sqrt(n)); rotation axes differ too."""
    lo, hi = cfg.camera.rotation_speed_range_deg
    speeds = np.sort([recorded_speed_deg(s.camera.orientation) for s in scenes])
    assert lo <= speeds[0] and speeds[-1] <= hi
    assert len(np.unique(speeds)) == N_SCENES
    cdf = (speeds - lo) / (hi - lo)
    n = np.arange(1, N_SCENES + 1)
    ks = max(np.max(n / N_SCENES - cdf), np.max(cdf - (n - 1) / N_SCENES))
    assert ks < 1.63 / math.sqrt(N_SCENES)
    axes = np.array([s.camera.orientation[1][1:] for s in scenes])
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    assert np.linalg.norm(axes.mean(axis=0)) < 0.3  # not one shared axis


def test_speeds_depend_only_on_seed_and_index(cfg):
    """Scene k's speed is the same whatever was sampled before, and changes with the seed."""

    def speeds(c, ks):
        return [recorded_speed_deg(sample_scene(c, k).camera.orientation) for k in ks]

    first = speeds(cfg, [5, 6, 7])
    assert speeds(cfg, [7, 6, 5])[::-1] == first
    assert speeds(dataclasses.replace(cfg, seed=1), [5, 6, 7]) != first


# Computed at commit b3e75be, before camera.rotation_speed_range_deg existed: the fingerprint
# (dataset.json's; a resume into an older dataset compares it) and the SHA-256 of scene 0's
# description (canonical JSON), for the presets without the field.
UNCHANGED = {
    "stillbox": ("7789bfeeaef3f8a6", "381cf25899cad80d"),
    "stillbox-unstabilised": ("10772122403c1b7a", "836915c03df2984e"),
}


@pytest.mark.parametrize("name", sorted(UNCHANGED))
def test_presets_without_a_speed_range_keep_their_scenes(name):
    """The field is left out of their config (fingerprint) and draws nothing (same scenes).
    The fingerprints were recorded before render.light_tree existed: with the light tree on, as
    then, that key is left out too and the fingerprint is the recorded one."""
    cfg = config.load_preset(name)
    assert "rotation_speed_range_deg" not in cfg.to_dict()["camera"]
    scene = formats.canonical_json(sample_scene(cfg, 0).to_dict()).encode()
    before_light_tree = config.replace(cfg, render={"light_tree": True})
    got = (before_light_tree.fingerprint(), hashlib.sha256(scene).hexdigest()[:16])
    assert got == UNCHANGED[name]


@pytest.mark.render
def test_rendered_shards_record_the_sampled_speeds(tmp_path):
    """A tiny render, scene by scene in two shards: dataset.json keeps the range, each record
    the orientations sampled from (seed, k), of speeds in the range; the dataset validates."""
    out = tmp_path / "rotating"
    args = ("--preset", PRESET, "--res", 32, "--scenes", 3, "--seed", 7, "--quality", "fast")
    for shard in ("0/2", "1/2"):
        run_cli(*args, "--workers", 1, "--shard", shard, "--out", out, "--quiet")
    info = json.loads((out / "dataset.json").read_text())
    assert info["config"]["camera"]["rotation_speed_range_deg"] == [0.0, 1.0]
    cfg = config.from_dict(info["config"])
    assert cfg.fingerprint() == info["fingerprint"]
    records = json.loads((out / "0" / "metadata.json").read_text())["scenes"]
    assert [r["index"] for r in records] == [0, 1, 2]
    for r in records:
        cam = sample_scene(cfg, r["index"]).camera
        assert r["orientation"] == cam.orientation and r["cam2world"] == cam.cam2world
    speeds = [recorded_speed_deg(r["orientation"]) for r in records]
    assert all(0 <= v <= 1 for v in speeds) and len(set(speeds)) == 3
    problems, _ = validate_dataset(out)
    assert problems == []
