"""Plain, serialisable scene descriptions and their random sampling (no Blender here).

Scene ``k`` of a dataset depends only on ``(seed, k)`` and the :class:`DatasetConfig`: its random
stream is PCG64 seeded by ``SeedSequence([seed, k])`` (numpy's ``default_rng``). All arithmetic
from the draws to the spec is :mod:`portable`, so a spec has the same bits on every machine.
Blender only renders a :class:`SceneSpec`; every random choice is made here.

World frame: right-handed, metres, +Z up (for the sun). The first camera position is the origin.
Camera poses are OpenCV camera-to-world matrices (x right, y down, z forward).
"""

from __future__ import annotations

import colorsys
import math

import numpy as np

from . import camera, photos, portable, shapes
from .config import CameraConfig, DatasetConfig, MaterialsConfig, is_plain_name
from .errors import ConfigError
from .record import BoxSpec, CameraSpec, LightSpec, MaterialSpec, PrimitiveSpec, SceneSpec

# Pattern frequencies (features per metre), low enough that textures stay legible at 64 px with a
# 90 deg FOV: one pixel covers distance / 32 metres, i.e. ~0.5 m on an object at 15 m and ~2 m
# on a wall at 60 m, so a feature spans at least about 4 pixels.
OBJECT_TEXTURE_SCALE = (0.08, 0.5)
WALL_TEXTURE_SCALE = (0.02, 0.08)
# Photos (images per metre): one photo spans 5-30 m on an object and 50-250 m on a wall, so a
# surface shows a random crop of it rather than many repeats.
OBJECT_PHOTO_SCALE = (1 / 30, 1 / 5)
WALL_PHOTO_SCALE = (1 / 250, 1 / 50)
MAX_ATTEMPTS = 1000


def _plain_floats(x) -> list:
    """Plain floats for JSON (float64 round-trips exactly through json)."""
    return np.asarray(x, dtype=float).tolist()


def _uniform(rng: np.random.Generator, r: tuple[float, float]) -> float:
    return float(rng.uniform(r[0], r[1]))


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return portable.exp(rng.uniform(portable.log(lo), portable.log(hi)))


def _colour(rng: np.random.Generator, value: float) -> list[float]:
    r, g, b = colorsys.hsv_to_rgb(rng.random(), rng.uniform(0.1, 0.9), value)
    return [portable.power(c, 2.2) for c in (r, g, b)]  # sRGB-ish to linear


def photo_files(cfg: MaterialsConfig) -> tuple[str, ...]:
    """Photos to draw from: the --textures folder's, else the bundled ones (unless turned off)."""
    if cfg.texture_files:
        return cfg.texture_files
    return photos.BUNDLED_PHOTOS if cfg.photos == "bundled" else ()


def foreign_photos(record: dict, cfg: MaterialsConfig) -> list:
    """Photo names of a scene record's materials (its primitives' and walls') that are not among
    the dataset's photos (photo_files of its config) as plain file names: what a reader must
    refuse before opening ``textures_dir / name``. Empty for a record the generator wrote."""
    allowed = {n for n in photo_files(cfg) if is_plain_name(n)}
    prims = record.get("primitives")
    surfaces = [*(prims if isinstance(prims, list) else []), record.get("box")]
    found = []
    for surface in surfaces:
        mat = surface.get("material") if isinstance(surface, dict) else None
        image = mat.get("image") if isinstance(mat, dict) else None
        if image is not None and image not in allowed:
            found.append(image)
    return found


def sample_material(
    rng: np.random.Generator,
    cfg: MaterialsConfig,
    scale_range: tuple[float, float],
    photo_scale_range: tuple[float, float],
    allow_plain: bool = True,
    allow_mirror: bool = True,
) -> MaterialSpec:
    """One surface. ``scale_range`` (pattern features per metre) and ``photo_scale_range``
    (photos per metre) depend on the typical viewing distance."""
    files = photo_files(cfg)
    use_image = bool(files) and rng.random() < cfg.texture_ratio
    plain = not use_image and rng.random() < cfg.plain_ratio and allow_plain
    mirror = rng.random() < cfg.mirror_ratio and allow_mirror
    glossy = rng.random() < cfg.glossy_ratio
    roughness = 0.0 if mirror else float(rng.uniform(0.05, 0.3) if glossy else rng.uniform(0.5, 1))
    common = dict(
        roughness=roughness,
        metallic=1.0 if mirror else 0.0,
        scale=_log_uniform(rng, *(photo_scale_range if use_image else scale_range)),
        offset=_plain_floats(rng.uniform(-100, 100, size=3)),
        rotation=_plain_floats(rng.uniform(0, 2 * math.pi, size=3)),
    )
    if use_image:
        image = files[int(rng.integers(len(files)))]
        tint = [1.0, 1.0, 1.0] if mirror else _plain_floats(rng.uniform(0.7, 1.0, size=3))
        return MaterialSpec(
            "image", None, colors=[tint], positions=[], detail=0.0, image=image, **common
        )
    if plain:
        colour = _colour(rng, rng.uniform(0.1, 1))
        return MaterialSpec(
            "plain", None, colors=[colour], positions=[], detail=0.0, image=None, **common
        )
    pattern = cfg.patterns[int(rng.integers(len(cfg.patterns)))]
    n = int(rng.integers(2, 5))
    # alternate dark and bright stops so every pattern has visible contrast
    colors = [
        _colour(rng, rng.uniform(0.02, 0.35) if i % 2 else rng.uniform(0.5, 1.0)) for i in range(n)
    ]
    # stops spread over [0.25, 0.75], where most pattern values fall
    positions = _plain_floats(0.25 + 0.5 * (np.arange(n) + rng.uniform(0.2, 0.8, size=n)) / n)
    return MaterialSpec(
        "procedural",
        pattern,
        colors=colors,
        positions=positions,
        detail=float(rng.uniform(0, 1)),
        image=None,
        **common,
    )


def sample_distance(rng: np.random.Generator, r: tuple[float, float], law: str) -> float:
    """Distance in metres within ``r``: "uniform" in distance, or "volume", uniform in the volume
    of the shell (density proportional to distance squared, so more objects far than near)."""
    if law == "uniform":
        return _uniform(rng, r)
    lo, hi = r[0] * r[0] * r[0], r[1] * r[1] * r[1]
    return portable.cbrt(rng.uniform(lo, hi))


def scene_rotation_speed_deg(rng: np.random.Generator, c: CameraConfig) -> float:
    """The scene's constant rotation speed, degrees per frame: drawn uniformly in
    ``rotation_speed_range_deg`` when it is set (one draw from ``rng``), else
    ``rotation_speed_deg`` (no draw, so scenes without a range keep their random stream)."""
    if c.rotation_speed_range_deg is None:
        return c.rotation_speed_deg
    return _uniform(rng, c.rotation_speed_range_deg)


def sample_camera(rng: np.random.Generator, cfg: DatasetConfig) -> CameraSpec:
    """The camera of a scene: a random orientation and direction and, when the camera rotates,
    a spin about a random axis of frame 0 at a constant speed (scene_rotation_speed_deg) times
    per-frame noise. Without noise the speed is the angle of the record's orientation[1]."""
    c = cfg.camera
    r0 = camera.random_rotation(rng) if c.random_orientation else np.eye(3)
    if c.direction is None:  # in the first frame's camera axes
        direction = camera.random_unit_vector(rng)
    else:
        direction = np.array(portable.normalise(c.direction))
    # portable.* products (not numpy's @): the same bits on every CPU
    speed = direction * c.displacement / c.time_step
    spin_axis = camera.random_unit_vector(rng)
    spin_deg = scene_rotation_speed_deg(rng, c)
    rotating = c.rotation_noise_deg > 0 or spin_deg > 0 or c.rotation_speed_range_deg is not None
    poses, quats = [], []
    for i in range(c.frames):
        rel = np.eye(3)
        if rotating:
            spin = spin_axis * math.radians(spin_deg) * i
            noise = rng.normal(0.0, math.radians(c.rotation_noise_deg), size=3)
            if i == 0:  # the first frame defines the reference axes
                noise[:] = 0.0
            rel = portable.matmul(
                camera.rotation_vector_to_matrix(spin), camera.rotation_vector_to_matrix(noise)
            )
            quats.append(_plain_floats(camera.matrix_to_quat(rel)))
        position = portable.matvec(r0, direction * c.displacement * i)
        poses.append(_plain_floats(camera.pose_matrix(portable.matmul(r0, rel), position)))
    return CameraSpec(
        width=c.width,
        height=c.height,
        K=_plain_floats(c.K()),
        time_step=c.time_step,
        speed=_plain_floats(speed),
        orientation=quats,
        cam2world=poses,
        near_clip=cfg.render.near_clip,
        far_clip=cfg.render.max_distance,
    )


def sample_primitive(
    rng: np.random.Generator, cfg: DatasetConfig, cam: CameraSpec
) -> PrimitiveSpec:
    o = cfg.objects
    kind = o.kinds[int(rng.integers(len(o.kinds)))]
    size = _uniform(rng, o.size_range)
    dims = shapes.random_dimensions(rng, kind, size)
    distance = sample_distance(rng, o.distance_range, o.distance_law)
    if rng.random() < o.behind_fraction:
        ray = camera.random_unit_vector(rng)
    else:  # uniformly over the first frame's image
        u = rng.uniform(-0.5, cam.width - 0.5)
        v = rng.uniform(-0.5, cam.height - 0.5)
        ray = portable.normalise(camera.pixel_ray(cam.K, u, v))
    pose0 = np.array(cam.cam2world[0])
    offset = portable.matvec(pose0[:3, :3], [x * distance for x in ray])
    location = [a + float(b) for a, b in zip(offset, pose0[:3, 3], strict=True)]
    rotation = camera.matrix_to_quat(camera.random_rotation(rng))
    material = sample_material(rng, cfg.materials, OBJECT_TEXTURE_SCALE, OBJECT_PHOTO_SCALE)
    return PrimitiveSpec(kind, dims, _plain_floats(location), _plain_floats(rotation), material)


def path_hits(prim: PrimitiveSpec, cam: CameraSpec, clearance: float) -> bool:
    """True if the camera centre comes within ``clearance`` metres of the primitive (or inside)."""
    p0 = np.array(cam.cam2world[0])[:3, 3]
    p1 = np.array(cam.cam2world[-1])[:3, 3]
    n = max(2, int(math.ceil(portable.norm(p1 - p0) / 0.005)) + 1)
    pts = p0 + np.linspace(0, 1, n)[:, None] * (p1 - p0)
    rot_t = camera.quat_to_matrix(prim.rotation).T
    local = portable.transform_rows(rot_t, pts - np.array(prim.location))  # R^T (p - t)
    return bool(
        np.any(shapes.signed_distance(prim.kind, np.array(prim.dimensions), local) < clearance)
    )


def sample_light(rng: np.random.Generator, cfg: DatasetConfig) -> LightSpec:
    lc = cfg.light
    elevation = math.radians(_uniform(rng, lc.sun_elevation_range_deg))
    azimuth = rng.uniform(0, 2 * math.pi)
    to_sun = [
        portable.cos(elevation) * portable.cos(azimuth),
        portable.cos(elevation) * portable.sin(azimuth),
        portable.sin(elevation),
    ]
    jitter = lambda: _plain_floats(1.0 - rng.uniform(0, lc.colour_jitter, size=3))  # noqa: E731
    return LightSpec(
        sun_direction=_plain_floats(-np.array(to_sun)),
        sun_strength=_uniform(rng, lc.sun_strength_range),
        sun_color=jitter(),
        ambient_color=jitter(),
        ambient_strength=_uniform(rng, lc.ambient_strength_range),
    )


def sample_box(rng: np.random.Generator, cfg: DatasetConfig) -> BoxSpec:
    b = cfg.box
    return BoxSpec(
        center=_plain_floats(rng.uniform(-b.offset_max, b.offset_max, size=3)),
        half_extents=_plain_floats(rng.uniform(*b.half_extent_range, size=3)),
        material=sample_material(
            rng,
            cfg.materials,
            WALL_TEXTURE_SCALE,
            WALL_PHOTO_SCALE,
            allow_plain=False,
            allow_mirror=False,
        ),
    )


def scene_seed(seed: int, index: int) -> int:
    """63-bit seed of scene ``index`` (also the root of its random stream)."""
    return int(
        np.random.SeedSequence([seed, index]).generate_state(1, np.uint64)[0] >> np.uint64(1)
    )


def sample_scene(cfg: DatasetConfig, index: int) -> SceneSpec:
    """Scene ``index`` of the dataset, resampled until the camera path is clear of objects;
    with ``objects.fixed``, the fixed scene of that name (fixed_scene)."""
    rng = portable.Generator(np.random.PCG64(np.random.SeedSequence([cfg.seed, index])))
    if cfg.objects.fixed is not None:
        return fixed_scene(cfg, index, sample_camera(rng, cfg))
    for attempt in range(MAX_ATTEMPTS):
        cam = sample_camera(rng, cfg)
        prims = [sample_primitive(rng, cfg, cam) for _ in range(cfg.objects.count)]
        if not any(path_hits(p, cam, cfg.objects.path_clearance) for p in prims):
            return SceneSpec(
                index=index,
                seed=scene_seed(cfg.seed, index),
                rejected=attempt,
                camera=cam,
                primitives=prims,
                box=sample_box(rng, cfg),
                light=sample_light(rng, cfg),
            )
    raise RuntimeError(
        f"scene {index}: {MAX_ATTEMPTS} samples all put an object on the camera path; "
        "lower objects.count or raise objects.distance_range"
    )


# ---------------------------------------------------------------- fixed scenes
# The toy problems of thesis 4.6.1 (Fig. 4.11): objects, walls and light built from the camera
# path, with no random draw, so that every scene index and seed gives the same scene. The walls
# lie beyond the far clip (their pixels are misses, depth 1e10: the "sky"), with a plain
# material that is never seen. Under "direct" shading (black world) the sky is black; under
# "path" shading it is the world's ambient colour: texture-less either way.
# The disc's size and the camera's height are not in the thesis; they are set so that each
# scene's starting error (mean |log| error of 10 m everywhere over the pixels within 100 m)
# is the one Table 4.1's rows imply (M = sqrt(M_Horizon M_Flower), M_S = 1 - LE / LE_0,
# fitted over its 12 rows): Flower 0.57 = (disc's share of the frame) x log(10 / 1), Horizon
# 1.22. The disc is at 1 m rather than farther and larger because only then does the
# photometric loss alone end worse than it started on Flower too (Fig. 4.13; measured at 1,
# 1.5, 2 and 3 m: docs/results/toy/README.md).
FLOWER_DISTANCE = 1.0  # m, the foreground disc in front of the middle frame's camera
FLOWER_DIAMETER = 1.13  # m: 113 px of a 200 px frame at 90 deg (thesis LE_0 0.57, see above)
FLOWER_PHOTO = "interior.exr"
FLOWER_PHOTO_SPAN = 1.25 * FLOWER_DIAMETER  # m, one photo across the disc (a crop of it)
BACKGROUND_DISTANCE = 10.0  # m (thesis: "depth starting points are equal to background, 10m")
BACKGROUND_PHOTO = "forest.exr"
BACKGROUND_PHOTO_SPAN = 25.0  # m, one photo across the background at 10 m (about 20 m seen)
HORIZON_HEIGHT = 1.4  # m, camera above the ground plane (thesis LE_0 1.22, see above)
HORIZON_PHOTO = "forest.exr"
HORIZON_PHOTO_SPAN = 8.0  # m of ground per photo repeat
# Photo turns: upright facing the camera (sky up); on the ground, the photo's rows run along
# the view, so its textured lower half lies under the camera (turned upright, its sky would be
# a texture-less band across the near ground)
UPRIGHT = -math.pi / 2
ALONG_VIEW = 0.0
FIXED_SUN_STRENGTH = 2.0  # W/m^2: with the ambient term, the brightest texels just reach 1
FIXED_AMBIENT_STRENGTH = 0.5


def _photo_material(name: str, span_m: float, turn: float) -> MaterialSpec:
    """A matte surface textured with the bundled photo ``name``, one photo per ``span_m``
    metres, untinted, turned by ``turn`` radians about the surface normal (local z), the
    photo's centre at the primitive's centre (the offset is added after the scale and turn, in
    photo widths: Blender's Mapping node)."""
    return MaterialSpec(
        "image",
        None,
        colors=[[1.0, 1.0, 1.0]],
        positions=[],
        scale=1.0 / span_m,
        detail=0.0,
        offset=[0.5, 0.5, 0.5],
        rotation=[0.0, 0.0, turn],
        roughness=1.0,
        metallic=0.0,
        image=name,
    )


def _facing(location, dimensions: list[float], material: MaterialSpec, normal_axis: int):
    """A flat primitive at a world ``location`` whose local +z is world axis ``normal_axis``
    negated (facing a camera that looks along world +z, or down world +y)."""
    # quaternions [w, x, y, z]: local +z -> world -z (half turn about x), or -> world -y
    # (quarter turn about x: local y -> world z, so the rectangle lies along the view)
    half = math.sqrt(0.5)  # correctly rounded (IEEE 754): the same bits everywhere
    rotation = [0.0, 1.0, 0.0, 0.0] if normal_axis == 2 else [half, half, 0.0, 0.0]
    return PrimitiveSpec("plane", dimensions, _plain_floats(location), rotation, material)


def _far_box(centre, cam: CameraSpec) -> BoxSpec:
    """Walls twice the far clip away from ``centre``: never within the render distance."""
    plain = MaterialSpec(
        "plain", None, [[0.5, 0.5, 0.5]], [], 1.0, 0.0, [0.0] * 3, [0.0] * 3, 1.0, 0.0, None
    )
    return BoxSpec(_plain_floats(centre), [2.0 * cam.far_clip] * 3, plain)


def _fixed_light(travel: list[float]) -> LightSpec:
    """White sun travelling along ``travel`` (world) and white ambient light."""
    return LightSpec(
        sun_direction=_plain_floats(portable.normalise(travel)),
        sun_strength=FIXED_SUN_STRENGTH,
        sun_color=[1.0, 1.0, 1.0],
        ambient_color=[1.0, 1.0, 1.0],
        ambient_strength=FIXED_AMBIENT_STRENGTH,
    )


def flower_layout(cam: CameraSpec) -> tuple[list[PrimitiveSpec], BoxSpec, LightSpec]:
    """The "Flower" scene: a photo-textured disc FLOWER_DISTANCE m in front of the middle
    frame's camera, on its optical axis, parallel to the image plane, before a photo-textured
    plane at BACKGROUND_DISTANCE m that fills every frame. Needs a camera in world axes (no
    random orientation), the middle frame's optical axis along world +z."""
    centre = np.array(cam.cam2world[len(cam.cam2world) // 2])[:3, 3]
    thickness = 0.02  # m; the textured face is at FLOWER_DISTANCE
    disc_at = [
        float(centre[0]),
        float(centre[1]),
        float(centre[2]) + FLOWER_DISTANCE + thickness / 2,
    ]
    wall_at = [float(centre[0]), float(centre[1]), float(centre[2]) + BACKGROUND_DISTANCE]
    disc = PrimitiveSpec(
        "cylinder",
        [FLOWER_DIAMETER, FLOWER_DIAMETER, thickness],
        _plain_floats(disc_at),
        [0.0, 1.0, 0.0, 0.0],  # local +z (the textured face) towards the camera
        _photo_material(FLOWER_PHOTO, FLOWER_PHOTO_SPAN, UPRIGHT),
    )
    side = 8.0 * BACKGROUND_DISTANCE  # far wider than any frame's view of it
    wall = _facing(
        wall_at,
        [side, side, 0.0],
        _photo_material(BACKGROUND_PHOTO, BACKGROUND_PHOTO_SPAN, UPRIGHT),
        2,
    )
    return [disc, wall], _far_box(centre, cam), _fixed_light([0.1, 0.2, 1.0])


def horizon_layout(cam: CameraSpec) -> tuple[list[PrimitiveSpec], BoxSpec, LightSpec]:
    """The "Horizon" scene: a photo-textured horizontal plane HORIZON_HEIGHT m below the first
    frame's camera (world +y is down, as the camera's y), reaching past the far clip in every
    direction seen: ground up to the horizon, sky above it. Needs a camera in world axes."""
    start = np.array(cam.cam2world[0])[:3, 3]
    ground_at = [float(start[0]), float(start[1]) + HORIZON_HEIGHT, float(start[2])]
    side = 4.0 * cam.far_clip  # the plane's edge stays beyond the far clip
    ground = _facing(
        ground_at,
        [side, side, 0.0],
        _photo_material(HORIZON_PHOTO, HORIZON_PHOTO_SPAN, ALONG_VIEW),
        1,
    )
    return [ground], _far_box(start, cam), _fixed_light([0.2, 1.0, 0.5])


FIXED_SCENES = {"flower": flower_layout, "horizon": horizon_layout}  # config.FIXED_SCENES


def fixed_scene(cfg: DatasetConfig, index: int, cam: CameraSpec) -> SceneSpec:
    """Scene ``index`` of a dataset of fixed scenes (``objects.fixed``): the same layout,
    camera path and light for every index and seed; only ``index`` and ``seed`` (hence the
    placement of anti-aliasing samples) differ. ConfigError if the camera path comes within
    ``objects.path_clearance`` of a surface (too long a path; cli.build_config checks it before
    anything is written)."""
    prims, box, light = FIXED_SCENES[cfg.objects.fixed](cam)
    if any(path_hits(p, cam, cfg.objects.path_clearance) for p in prims):
        raise ConfigError(
            f"camera.displacement: the camera path of the fixed scene '{cfg.objects.fixed}' "
            f"(objects.fixed) comes within {cfg.objects.path_clearance} m of a surface; "
            "shorten camera.displacement or camera.frames"
        )
    return SceneSpec(
        index=index,
        seed=scene_seed(cfg.seed, index),
        rejected=0,
        camera=cam,
        primitives=prims,
        box=box,
        light=light,
    )
