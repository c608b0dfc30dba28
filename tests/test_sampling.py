"""Scene sampling, primitive shapes and configuration (pure Python, no Blender)."""

import dataclasses
import json
import math
import tomllib
from importlib import resources

import cv2
import numpy as np
import pytest

from stillbox_gen import camera, config, shapes
from stillbox_gen.errors import ConfigError
from stillbox_gen.record import SceneSpec
from stillbox_gen.scene import path_hits, sample_scene

N_SCENES = 500


@pytest.fixture(scope="module")
def cfg():
    return config.load_preset("stillbox")


@pytest.fixture(scope="module")
def scenes(cfg):
    return [sample_scene(cfg, k) for k in range(N_SCENES)]


def _positions(spec: SceneSpec) -> np.ndarray:
    return np.array(spec.camera.cam2world)[:, :3, 3]


# ---------------------------------------------------------------- determinism


def test_sampling_is_deterministic_per_seed_and_index(cfg):
    """Scene k depends only on (seed, k): repeatable, order-independent, and seed-sensitive."""
    a = sample_scene(cfg, 7).to_dict()
    for k in range(3):
        sample_scene(cfg, k)  # sampling other scenes first must not matter
    assert sample_scene(cfg, 7).to_dict() == a
    assert sample_scene(cfg, 8).to_dict() != a
    reseeded = dataclasses.replace(cfg, seed=1)
    assert sample_scene(reseeded, 7).to_dict() != a
    assert sample_scene(reseeded, 7).to_dict()["camera"] != a["camera"]


def test_scene_dict_round_trip_and_strict_json(cfg):
    """SceneSpec.from_dict inverts to_dict, and the dict is strict JSON that round-trips exactly."""
    d = sample_scene(cfg, 3).to_dict()
    assert SceneSpec.from_dict(d).to_dict() == d
    text = json.dumps(d, allow_nan=False)
    assert json.loads(text) == d


# ---------------------------------------------------------------- parameter ranges


def test_primitive_kinds_sizes_and_distances(cfg, scenes):
    """Every scene has objects.count primitives of configured kinds, sizes and distances."""
    o = cfg.objects
    seen = set()
    for s in scenes[:200]:
        assert len(s.primitives) == o.count == 20
        p0 = _positions(s)[0]
        for p in s.primitives:
            seen.add(p.kind)
            assert p.kind in o.kinds
            assert o.size_range[0] - 1e-9 <= max(p.dimensions) <= o.size_range[1] + 1e-9
            assert min(p.dimensions) > 0
            dist = np.linalg.norm(np.array(p.location) - p0)
            assert o.distance_range[0] - 1e-9 <= dist <= o.distance_range[1] + 1e-9
            assert np.linalg.norm(p.rotation) == pytest.approx(1.0) and p.rotation[0] >= 0
    assert seen == set(o.kinds)


def test_most_objects_are_in_front_of_the_first_camera(scenes):
    """With behind_fraction 0.15 about 92% of objects have positive depth in the first frame."""
    in_front = []
    for s in scenes[:200]:
        w2c = np.linalg.inv(np.array(s.camera.cam2world[0]))
        for p in s.primitives:
            in_front.append((w2c @ np.r_[p.location, 1.0])[2] > 0)
    assert 0.85 < np.mean(in_front) < 0.98


def test_camera_moves_in_a_straight_line_at_constant_speed(cfg, scenes):
    """Consecutive frames are 0.1 m apart and frame i sits at i*speed*time_step in frame-0 axes."""
    for s in scenes[:200]:
        c = s.camera
        pos = _positions(s)
        assert len(pos) == cfg.camera.frames == 10
        np.testing.assert_allclose(np.linalg.norm(np.diff(pos, axis=0), axis=1), 0.1, rtol=1e-9)
        pose0 = np.array(c.cam2world[0])
        for i, p in enumerate(pos):
            in_cam0 = pose0[:3, :3].T @ (p - pose0[:3, 3])
            np.testing.assert_allclose(in_cam0, np.array(c.speed) * c.time_step * i, atol=1e-12)
        # no rotation in the default preset: every frame has the frame-0 orientation
        np.testing.assert_allclose(np.array(c.cam2world)[:, :3, :3], [pose0[:3, :3]] * 10)
        assert c.orientation == []
        assert c.time_step == pytest.approx(1 / 30)
        assert np.linalg.norm(c.speed) == pytest.approx(3.0)


def test_intrinsics_match_90_degree_fov(scenes):
    """The default 64x64 camera has f = 32 px (90 degree FOV) and a centred principal point."""
    for s in scenes[:20]:
        assert (s.camera.width, s.camera.height) == (64, 64)
        np.testing.assert_allclose(s.camera.K, [[32, 0, 31.5], [0, 32, 31.5], [0, 0, 1]])


def test_unstabilised_preset_has_one_unit_quaternion_per_frame():
    """The unstabilised preset records one unit quaternion (w >= 0) per frame and rotates."""
    cfg = config.load_preset("stillbox-unstabilised")
    s = sample_scene(cfg, 0)
    q = np.array(s.camera.orientation)
    assert q.shape == (cfg.camera.frames, 4)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, rtol=1e-12)
    assert np.all(q[:, 0] >= 0)
    rots = np.array(s.camera.cam2world)[:, :3, :3]
    assert not np.allclose(rots[0], rots[-1], atol=1e-4)


def test_unstabilised_orientation_is_relative_to_frame_zero():
    """orientation[i] is R_cam0<-cam_i and speed is in frame-0 camera axes, with rotation noise."""
    s = sample_scene(config.load_preset("stillbox-unstabilised"), 0)
    c = s.camera
    poses = np.array(c.cam2world)
    r0 = poses[0, :3, :3]
    assert c.orientation[0] == [1.0, 0.0, 0.0, 0.0]
    for i, q in enumerate(c.orientation):
        np.testing.assert_allclose(
            r0.T @ poses[i, :3, :3], quat_to_matrix_ref(q), atol=1e-9, err_msg=f"frame {i}"
        )
        in_cam0 = r0.T @ (poses[i, :3, 3] - poses[0, :3, 3])
        np.testing.assert_allclose(in_cam0, np.array(c.speed) * c.time_step * i, atol=1e-9)


def quat_to_matrix_ref(q) -> np.ndarray:
    """Independent quaternion -> matrix (via Rodrigues on the axis-angle)."""
    w, v = q[0], np.array(q[1:])
    s = np.linalg.norm(v)
    if s < 1e-15:
        return np.eye(3)
    k, angle = v / s, 2 * math.atan2(s, w)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * kx + (1 - math.cos(angle)) * kx @ kx


def test_motion_direction_is_roughly_uniform(scenes):
    """Unit speed vectors of accepted scenes have mean near 0 and second moments near 1/3."""
    v = np.array([s.camera.speed for s in scenes])
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    assert np.linalg.norm(v.mean(axis=0)) < 0.15
    np.testing.assert_allclose((v**2).mean(axis=0), 1 / 3, atol=0.06)


# ---------------------------------------------------------------- rejection


def test_accepted_scenes_keep_the_camera_path_clear(cfg, scenes):
    """No primitive of an accepted scene comes within path_clearance of the camera path."""
    clearance = cfg.objects.path_clearance
    for s in scenes[:200]:
        assert not any(path_hits(p, s.camera, clearance) for p in s.primitives)
    assert any(s.rejected > 0 for s in scenes[:200])


def test_crowded_scenes_are_rejected_deterministically(cfg):
    """Big objects close to the camera force resampling, with the same counts on every run."""
    crowded = config.replace(
        cfg, objects={"count": 10, "distance_range": (0.0, 3.0), "size_range": (1.0, 2.0)}
    )
    first = [sample_scene(crowded, k) for k in range(4)]
    counts = [s.rejected for s in first]
    assert sum(counts) > 0
    assert [sample_scene(crowded, k).rejected for k in range(4)] == counts
    for s in first:
        clearance = crowded.objects.path_clearance
        assert not any(path_hits(p, s.camera, clearance) for p in s.primitives)


def _frame_with_z(axis: np.ndarray) -> list[float]:
    """Quaternion of a rotation whose local z axis points along ``axis`` (world)."""
    z = axis / np.linalg.norm(axis)
    x = np.cross(z, [0.3, 0.5, 0.8])
    x /= np.linalg.norm(x)
    return camera.matrix_to_quat(np.column_stack([x, np.cross(z, x), z])).tolist()


def test_path_hits_follows_the_whole_path_and_the_rotation(cfg):
    """path_hits tests every point of the segment from the first to the last camera centre."""
    s = sample_scene(cfg, 0)
    prim, pos = s.primitives[0], _positions(s)
    motion = (pos[-1] - pos[0]) / np.linalg.norm(pos[-1] - pos[0])
    side = np.cross(motion, [0.0, 0.0, 1.0])
    side /= np.linalg.norm(side)
    prim.kind, prim.dimensions, prim.rotation = "sphere", [0.04] * 3, [1.0, 0, 0, 0]
    for t in (0.0, 0.3, 0.5, 0.95, 1.0):  # 0.03 m from the path anywhere along it
        prim.location = (pos[0] + t * (pos[-1] - pos[0]) + 0.05 * side).tolist()
        assert path_hits(prim, s.camera, 0.1), t
        assert not path_hits(prim, s.camera, 0.02), t
    prim.dimensions = [0.2] * 3  # 0.2 m beyond the end of the path
    prim.location = (pos[-1] + 0.3 * motion).tolist()
    assert not path_hits(prim, s.camera, 0.1) and path_hits(prim, s.camera, 0.25)
    # a thin rod 0.5 m aside: it crosses the path when its axis points sideways
    prim.kind, prim.dimensions = "cylinder", [0.02, 0.02, 3.0]
    prim.location = (pos.mean(axis=0) + 0.5 * side).tolist()
    prim.rotation = _frame_with_z(side)
    assert path_hits(prim, s.camera, 0.1)
    prim.rotation = _frame_with_z(motion)
    assert not path_hits(prim, s.camera, 0.1)


# ---------------------------------------------------------------- shapes


@pytest.mark.parametrize(
    "kind,dims,point,expected",
    [
        ("cube", [2, 4, 6], [0, 0, 0], -1.0),
        ("cube", [2, 4, 6], [3, 0, 0], 2.0),
        ("cube", [2, 4, 6], [0, 0, -4], 1.0),
        ("cube", [2, 4, 6], [2, 3, 4], math.sqrt(3)),
        ("slab", [2, 2, 0.2], [0, 0, 0], -0.1),
        ("slab", [2, 2, 0.2], [0.5, 0.5, 1.1], 1.0),
        ("sphere", [2, 2, 2], [0, 0, 0], -1.0),
        ("sphere", [2, 2, 2], [0, 3, 0], 2.0),
        ("sphere", [2, 2, 2], [1, 1, 1], math.sqrt(3) - 1),
        ("cylinder", [2, 2, 4], [0, 0, 0], -1.0),
        ("cylinder", [2, 2, 4], [3, 0, 0], 2.0),
        ("cylinder", [2, 2, 4], [0, 0.5, 5], 3.0),
        ("cylinder", [2, 2, 4], [0, 4, 6], 5.0),
        ("cone", [2, 2, 2], [0, 0, 0], -1 / math.sqrt(5)),
        ("cone", [2, 2, 2], [0.05, 0, 0], -0.9 / math.sqrt(5)),
        ("cone", [2, 2, 2], [0.3, 0, -0.8], -0.2),
        ("cone", [2, 2, 2], [0, 0, -3], 2.0),
        ("cone", [2, 2, 2], [0, 0, 4], 3.0),
        ("cone", [2, 2, 2], [0.5 + 2 / math.sqrt(5), 0, 1 / math.sqrt(5)], 1.0),
        ("torus", [4, 4, 1], [1.5, 0, 0], -0.5),
        ("torus", [4, 4, 1], [0, 0, 0], 1.0),
        ("torus", [4, 4, 1], [0, 3, 0], 1.0),
        ("torus", [4, 4, 1], [-1.5, 0, 2], 1.5),
    ],
)
def test_signed_distance_on_hand_computed_points(kind, dims, point, expected):
    """signed_distance is negative inside and equals the hand-computed distance outside."""
    d = shapes.signed_distance(kind, np.array(dims, float), np.array([point], float))
    assert d.shape == (1,)
    assert d[0] == pytest.approx(expected, abs=1e-12)


def _signed_volume(v: np.ndarray, faces) -> float:
    vol = 0.0
    for f in faces:
        for i in range(1, len(f) - 1):
            vol += np.linalg.det(np.array([v[f[0]], v[f[i]], v[f[i + 1]]])) / 6
    return vol


def _analytic_volume(kind: str, d) -> float:
    dx, dy, dz = d
    if kind in ("cube", "slab"):
        return dx * dy * dz
    if kind == "sphere":
        return 4 / 3 * math.pi * (dx / 2) ** 3
    if kind == "cylinder":
        return math.pi * (dx / 2) ** 2 * dz
    if kind == "cone":
        return math.pi * (dx / 2) ** 2 * dz / 3
    major, minor = (dx - dz) / 2, dz / 2
    return 2 * math.pi**2 * major * minor**2


@pytest.mark.parametrize(
    "kind,dims",
    [
        ("cube", [1.0, 0.7, 0.4]),
        ("slab", [2.0, 1.5, 0.1]),
        ("sphere", [1.2, 1.2, 1.2]),
        ("cylinder", [1.0, 1.0, 1.7]),
        ("cone", [0.8, 0.8, 1.5]),
        ("torus", [2.0, 2.0, 0.6]),
    ],
)
def test_mesh_is_closed_outward_and_inscribed(kind, dims):
    """Each mesh is a closed, outward-oriented polyhedron inscribed in its analytic shape."""
    v, faces = shapes.mesh(kind, dims, segments=32)
    # closed and consistently oriented: every directed edge is matched by its reverse once
    edges = [(f[i], f[(i + 1) % len(f)]) for f in faces for i in range(len(f))]
    assert len(set(edges)) == len(edges)
    assert set(edges) == {(b, a) for a, b in edges}
    assert all(len(set(f)) == len(f) >= 3 for f in faces)
    vol, exact = _signed_volume(v, faces), _analytic_volume(kind, dims)
    assert vol > 0
    if kind in ("cube", "slab"):
        assert vol == pytest.approx(exact, rel=1e-12)
    else:
        assert 0.95 * exact <= vol <= exact
    assert np.all(shapes.signed_distance(kind, np.array(dims), v) <= 1e-9)
    np.testing.assert_allclose(v.max(axis=0) - v.min(axis=0), dims, rtol=0.02)


def test_unknown_kind_raises():
    """An unknown primitive kind is an error, not a silent default."""
    with pytest.raises(ValueError):
        shapes.signed_distance("pyramid", np.ones(3), np.zeros((1, 3)))
    with pytest.raises(ValueError):
        shapes.mesh("pyramid", [1, 1, 1])


# ---------------------------------------------------------------- config


def test_unknown_preset_lists_available_ones():
    """load_preset of an unknown name raises ConfigError naming the available presets."""
    with pytest.raises(ConfigError) as e:
        config.load_preset("nope")
    assert "'nope'" in str(e.value)
    assert "stillbox" in str(e.value) and "stillbox-unstabilised" in str(e.value)


def test_preset_file_with_unknown_key(tmp_path):
    """A TOML preset with a misspelt key raises ConfigError naming the key and the file."""
    path = tmp_path / "mine.toml"
    path.write_text("[camera]\nwidht = 128\n")
    with pytest.raises(ConfigError) as e:
        config.load_preset(str(path))
    assert "camera.widht" in str(e.value) and str(path) in str(e.value)
    path.write_text("[camera]\nwidth = 128\n")
    assert config.load_preset(str(path)).camera.width == 128


def test_preset_file_with_unknown_section(tmp_path):
    """An unknown top-level section is rejected too, naming it."""
    path = tmp_path / "bad.toml"
    path.write_text("[lights]\nsun_strength_range = [1, 2]\n")
    with pytest.raises(ConfigError, match="lights"):
        config.load_preset(str(path))


@pytest.mark.parametrize(
    "section,change,flag",
    [
        ("camera", {"width": -64}, "--res"),
        ("camera", {"height": 0}, "--res"),
        ("camera", {"fov_deg": 0.0}, "--fov"),
        ("camera", {"fov_deg": 180.0}, "--fov"),
        ("camera", {"frames": 1}, "--frames"),
        ("camera", {"displacement": 0.0}, "--displacement"),
        ("camera", {"principal_point": (64.0, 10.0)}, "--principal-point"),
        ("camera", {"principal_point": (10.0, -0.6)}, "--principal-point"),
    ],
)
def test_validate_names_the_bad_flag(cfg, section, change, flag):
    """validate() rejects inconsistent parameters with a ConfigError naming the flag."""
    config.validate(cfg)  # the preset itself is valid
    with pytest.raises(ConfigError) as e:
        config.validate(config.replace(cfg, **{section: change}))
    assert str(e.value).startswith(flag)


def test_validate_accepts_edge_principal_point(cfg):
    """A principal point on the outer edge of the image (-0.5 or W-0.5) is still valid."""
    config.validate(config.replace(cfg, camera={"principal_point": (-0.5, 63.5)}))


def test_texture_folder_errors(tmp_path):
    """An empty folder or a file path given as --textures raises ConfigError naming the flag."""
    with pytest.raises(ConfigError, match="--textures"):
        config.list_texture_files(str(tmp_path))
    f = tmp_path / "x.png"
    f.write_bytes(b"")
    with pytest.raises(ConfigError, match="--textures"):
        config.list_texture_files(str(f))


def test_texture_folder_lists_real_images(tmp_path):
    """A PNG written by OpenCV is listed by name; non-image files are ignored."""
    assert cv2.imwrite(str(tmp_path / "wood.png"), np.full((4, 4, 3), 128, np.uint8))
    (tmp_path / "notes.txt").write_text("hello")
    assert config.list_texture_files(str(tmp_path)) == ("wood.png",)


@pytest.mark.parametrize("name", config.available_presets())
def test_presets_set_only_what_differs_from_the_dataclasses(name):
    """The dataclasses are the one source of defaults: a bundled preset that repeated one would
    silently split from the others when the default changes."""
    data = tomllib.loads((resources.files("scene_presets") / f"{name}.toml").read_text())
    data.pop("description", None)
    for section, values in data.items():
        defaults = config.SECTIONS[section]()
        for key, value in values.items():
            value = tuple(value) if isinstance(value, list) else value
            assert value != getattr(defaults, key), f"{name}.toml repeats {section}.{key}"


def test_stillbox_preset_is_the_dataclass_defaults():
    assert config.load_preset("stillbox") == config.DatasetConfig()


def test_fingerprint_tracks_parameters(cfg):
    """The fingerprint is stable for equal configs and changes with any content parameter."""
    fp = cfg.fingerprint()
    assert config.load_preset("stillbox").fingerprint() == fp
    assert config.replace(cfg, camera={"width": 128}).fingerprint() != fp
    assert config.replace(cfg, objects={"count": 21}).fingerprint() != fp
    assert config.replace(cfg, render={"samples": 8}).fingerprint() != fp


# ---------------------------------------------------------------- calibrated placement, photos


def test_volume_law_distances_follow_the_cube_law(cfg, scenes):
    """distance_law "volume": P(d < r) = (r^3 - lo^3) / (hi^3 - lo^3) (Kolmogorov distance)."""
    o = cfg.objects
    assert o.distance_law == "volume"
    d = np.sort(
        [
            np.linalg.norm(np.array(p.location) - _positions(s)[0])
            for s in scenes[:200]
            for p in s.primitives
        ]
    )
    lo, hi = o.distance_range
    expected = (d**3 - lo**3) / (hi**3 - lo**3)
    empirical = np.arange(1, len(d) + 1) / len(d)
    assert np.abs(empirical - expected).max() < 0.03  # 4,000 draws: KS 1 % level is 0.026
    uniform = (d - lo) / (hi - lo)
    assert np.abs(empirical - uniform).max() > 0.1  # and clearly not uniform in distance


def test_bundled_photos_are_used_without_a_textures_folder(cfg, scenes):
    """About texture_ratio of surfaces (objects and walls) get one of the bundled photos."""
    from stillbox_gen import photos

    mats = [p.material for s in scenes[:200] for p in s.primitives]
    walls = [s.box.material for s in scenes[:200]]
    for group in (mats, walls):
        share = np.mean([m.kind == "image" for m in group])
        assert abs(share - cfg.materials.texture_ratio) < 0.1, share
    used = {m.image for m in mats + walls if m.kind == "image"}
    assert used == set(photos.BUNDLED_PHOTOS)
    off = config.replace(cfg, materials={"photos": "none"})
    assert not any(p.material.kind == "image" for p in sample_scene(off, 0).primitives)
    with pytest.raises(ConfigError, match="--photos"):
        config.validate(config.replace(cfg, materials={"photos": "web"}))


@pytest.mark.blender  # the photos ship inside the bpy wheel
def test_bundled_photos_load_as_tone_mapped_reflectance():
    """Each of the 8 panoramas ships with bpy and maps to [0, 1] around the chosen middle grey."""
    from stillbox_gen import photos

    assert sorted(p.name for p in photos.bundled_folder().glob("*.exr")) == sorted(
        photos.BUNDLED_PHOTOS
    )
    img = photos.load_bundled("forest.exr")
    assert img.shape == (512, 1024, 3) and img.dtype == np.float32
    assert img.min() >= 0.0 and img.max() <= 1.0
    lum = img @ np.array([0.2126, 0.7152, 0.0722])
    assert 0.1 < np.median(lum) < 0.5 and lum.std() > 0.05  # a photo, not a flat colour


def test_tone_map_puts_the_log_average_at_middle_grey():
    """Exposure-independent: scaling the HDR input by any factor gives the same result."""
    from stillbox_gen import photos

    rng = np.random.default_rng(0)
    hdr = np.exp(rng.normal(0.0, 2.0, size=(32, 32, 3)))
    a, b = photos.tone_map(hdr), photos.tone_map(hdr * 1000.0)
    np.testing.assert_allclose(a, b, atol=1e-3)  # up to the 1e-4 guard inside the log
    grey = np.full((4, 4, 3), 7.0)  # a uniform image is its own log-average
    np.testing.assert_allclose(photos.tone_map(grey), photos.MIDDLE_GREY, atol=1e-3)


def test_photo_prefilter_level_gives_about_two_texels_per_pixel():
    """The level halves the width while at least TEXELS_PER_PIXEL texels stay per pixel."""
    from stillbox_gen import photos

    # a 10 m photo 20 m away at f = 32 px: 16 pixels across it, so 32 texels wanted
    assert photos.prefiltered_width(1024, 10.0, 20.0, 32.0) == 32
    assert photos.prefiltered_width(1024, 10.0, 20.0, 128.0) == 128  # 4x the focal, 4x texels
    assert photos.prefiltered_width(1024, 10.0, 1.0, 128.0) == 1024  # never above full size
    assert photos.prefiltered_width(1024, 1.0, 200.0, 32.0) == photos.MIN_WIDTH
    for span, dist, f in [(5.0, 7.0, 32.0), (30.0, 13.0, 64.0), (150.0, 60.0, 128.0)]:
        w = photos.prefiltered_width(1024, span, dist, f)
        per_pixel = w / (span * f / dist)
        assert w == 1024 or photos.TEXELS_PER_PIXEL <= per_pixel < 2 * photos.TEXELS_PER_PIXEL
    img = np.random.default_rng(0).random((64, 128, 3)).astype(np.float32)
    small = photos.downsample(img, 32)
    assert small.shape == (16, 32, 3)
    np.testing.assert_allclose(small[0, 0], img[:4, :4].mean(axis=(0, 1)), rtol=1e-5)


def test_surface_distances_for_the_prefilter():
    from stillbox_gen import photos

    assert photos.object_distance([0, 0, 10], [4, 2, 2], [0, 0, 0]) == pytest.approx(8.0)
    assert photos.object_distance([0, 0, 1], [4, 2, 2], [0, 0, 0]) == 1.0  # camera inside
    # box centred 10 m off along x: planes at 40 and 60 m in x, 50 m in y and z
    d = photos.wall_distance([10, 0, 0], [50, 50, 50], [0, 0, 0])
    assert d == pytest.approx((60 + 40 + 4 * 50) / 6)
