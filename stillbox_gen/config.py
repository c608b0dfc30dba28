"""Generator configuration: presets (TOML files in ``scene_presets/``) plus command-line overrides.

A :class:`DatasetConfig` fully determines the scenes of a dataset together with the seed: two runs
with equal configs and seeds produce the same scene descriptions. Run options that do not change
content (number of scenes, workers, threads, output folder) live outside it.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import tomllib
import types
import typing
from collections.abc import Callable, Collection
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from . import camera
from .arguments import parse_point, parse_resolution, parse_shares
from .conventions import LIMITS
from .errors import ConfigError
from .layout import FLOW_FORMATS
from .shapes import SHAPES

# Every shape kind (the table shapes.SHAPES); random scenes draw the ``random`` ones by default
# (objects.kinds), the others (the flat "plane", ground of the toy "horizon" scene) when named.
SHAPE_KINDS = tuple(SHAPES)
PRIMITIVE_KINDS = tuple(k for k, s in SHAPES.items() if s.random)  # objects.kinds default
# Fixed scenes (objects.fixed): a named layout built by scene.FIXED_SCENES instead of random
# primitives; "flower" and "horizon" are the toy problems of thesis 4.6.1 (Fig. 4.11).
FIXED_SCENES = ("flower", "horizon")
IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp")
IMAGE_FORMATS = ("png", "jpg")
PHOTO_SOURCES = ("bundled", "none")
DISTANCE_LAWS = ("uniform", "volume")
PATTERNS = ("noise", "voronoi", "wave", "magic", "checker", "brick", "gradient_stripes")
# The last three have hard edges that alias at 1 sample (at 128 px, 1 sample + denoiser vs 256
# samples: checker/brick/stripes 19-28 dB, noise/Voronoi 29-34 dB), so they are opt-in.
SMOOTH_PATTERNS = PATTERNS[:4]


def limit_problem(key: str, value: int) -> str | None:
    """Why ``value`` is beyond LIMITS[key] ("must be at most ..."), None when it is not."""
    most, unit = LIMITS[key]
    if value <= most:
        return None
    return f"must be at most {most:,} {unit}, got {value:,}"


# ---------------------------------------------------------------- command-line flags


@dataclass(frozen=True)
class Flag:
    """The ``stillbox-gen generate`` option that sets a config field, declared once in the
    field's metadata (:func:`flag`); stillbox_gen.cli makes the click option of it and
    ``build_config`` applies it, and error messages about the field name it (FLAGS)."""

    name: str  # e.g. "--frames"
    help: str  # the --help text, without the default note
    order: int  # position in generate --help among every generate option (see stillbox_gen.cli)
    type: object = str  # int, float, str, "path" (a file or folder) or a tuple of choices
    parse: Callable | None = None  # text -> value (a tuple of values for several fields)
    fields: tuple[str, ...] = ()  # the fields it sets when more than its own (e.g. --res)
    also: tuple[tuple[str, object], ...] = ()  # (field, value) set with it (--fov: focal_px)
    # "preset": help ends "[default: preset, V]" (V: the field's default, what a preset that
    # does not set the key gives); "plain": "[default: V]"; "click": click shows the default,
    # which the option takes (the flag is then always given); "": no note.
    note: str = ""
    is_flag: bool = False  # an on/off switch setting True


def flag(name: str, help: str, order: int, **options) -> dict:
    """Field metadata declaring the command-line flag that sets the field (:class:`Flag`)."""
    return {"flag": Flag(name, help, order, **options)}


def _textures(path) -> tuple[str, tuple[str, ...]]:
    """--textures DIR -> (materials.textures_dir, materials.texture_files)."""
    from pathlib import Path as _Path

    return str(_Path(path).resolve()), list_texture_files(str(path))


@dataclass(frozen=True)
class CameraConfig:
    """Intrinsics and motion: angles in degrees, distances in metres, OpenCV pixel convention."""

    width: int = field(
        default=64,
        metadata=flag(
            "--res",
            "Frame size in pixels: N (square) or WxH.",
            10,
            parse=parse_resolution,
            fields=("width", "height"),
            note="preset",
        ),
    )
    height: int = 64
    fov_deg: float = field(  # horizontal; ignored when focal_px is set
        default=90.0,
        metadata=flag(
            "--fov",
            "Horizontal field of view, degrees.",
            90,
            type=float,
            also=(("focal_px", None),),
            note="preset",
        ),
    )
    focal_px: float | None = field(
        default=None,
        metadata=flag("--focal", "Focal length in pixels (instead of --fov).", 100, type=float),
    )
    principal_point: tuple[float, float] | None = field(  # None = centred ((W-1)/2, (H-1)/2)
        default=None,
        metadata=flag(
            "--principal-point",
            "CX,CY in pixels, pixel-centre convention.  [default: ((W-1)/2, (H-1)/2)]",
            110,
            parse=parse_point,
        ),
    )
    frames: int = field(
        default=10, metadata=flag("--frames", "Frames per scene.", 120, type=int, note="preset")
    )
    displacement: float = field(  # metres per frame
        default=0.1,
        metadata=flag(
            "--displacement",
            "Camera displacement per frame, metres.",
            130,
            type=float,
            note="preset",
        ),
    )
    time_step: float = 1.0 / 30.0  # seconds per frame; speed = displacement / time_step
    random_orientation: bool = True  # fixed random orientation per scene (else world axes)
    # Direction of motion [x, y, z] in the first frame's camera axes (x right, y down, z forward;
    # normalised, length = displacement), or None: a uniformly random direction per scene.
    direction: tuple[float, float, float] | None = None
    rotation_noise_deg: float = field(  # std of per-frame orientation noise (thesis 6.4)
        default=0.0,
        metadata=flag(
            "--rotation-noise",
            "Per-frame orientation noise std, degrees.",
            160,
            type=float,
            note="preset",
        ),
    )
    rotation_speed_deg: float = field(  # constant angular speed per frame (unstabilised camera)
        default=0.0,
        metadata=flag(
            "--rotation-speed",
            "Constant camera rotation, degrees per frame (unstabilised).",
            170,
            type=float,
            note="preset",
        ),
    )
    # [min, max] degrees per frame, or None: a rotation speed drawn per scene, uniform in it,
    # constant over the scene, about a random axis (the rotating StillBox of thesis 5.3); it
    # takes the place of rotation_speed_deg, which must then be 0.
    rotation_speed_range_deg: tuple[float, float] | None = None

    def focal(self) -> float:
        if self.focal_px is not None:
            return float(self.focal_px)
        return camera.focal_from_fov(self.fov_deg, self.width)

    def K(self) -> np.ndarray:
        cx, cy = self.principal_point or camera.centred_principal_point(self.width, self.height)
        return camera.intrinsics_matrix(self.focal(), cx, cy)


@dataclass(frozen=True)
class ObjectsConfig:
    """Random primitives around the camera path."""

    count: int = 20
    kinds: tuple[str, ...] = PRIMITIVE_KINDS
    size_range: tuple[float, float] = (0.0, 14.0)  # largest extent, metres
    distance_range: tuple[float, float] = (4.0, 30.0)  # from the first camera position, metres
    distance_law: str = "volume"  # "uniform" in distance or "volume" (uniform in the shell)
    behind_fraction: float = 0.05  # share placed anywhere around the camera (else in view)
    path_clearance: float = 0.1  # metres kept between the camera path and any surface
    # A fixed scene by name (FIXED_SCENES) instead of ``count`` random primitives: the same
    # objects, walls and light for every scene index and seed (see scene.FIXED_SCENES).
    fixed: str | None = None


@dataclass(frozen=True)
class MaterialsConfig:
    """Shares of material kinds; ``texture_files`` is filled from ``--textures``, else the
    photos bundled with bpy are used (``photos = "bundled"``, see photos.py)."""

    texture_ratio: float = 0.5  # share of surfaces (objects and walls) with a photo texture
    plain_ratio: float = 0.1  # share of the others with a plain colour
    glossy_ratio: float = 0.3  # share of surfaces with low roughness
    mirror_ratio: float = 0.05  # share of objects that are metallic mirrors
    patterns: tuple[str, ...] = SMOOTH_PATTERNS  # procedural patterns drawn uniformly
    photos: str = field(  # without --textures: "bundled" photos or "none" (patterns only)
        default="bundled",
        metadata=flag(
            "--photos",
            "Without --textures: bundled photos, or none (procedural patterns only).",
            150,
            type=PHOTO_SOURCES,
            note="preset",
        ),
    )
    textures_dir: str | None = field(
        default=None,
        metadata=flag(
            "--textures",
            f"Folder of your photos used as textures (texture ratio {texture_ratio:g}).  "
            "[default: the photos bundled with bpy]",
            140,
            type="path",
            parse=_textures,
            fields=("textures_dir", "texture_files"),
        ),
    )
    texture_files: tuple[str, ...] = ()  # names relative to textures_dir, sorted


@dataclass(frozen=True)
class BoxConfig:
    """The textured box around everything; centred near the first camera position."""

    half_extent_range: tuple[float, float] = (50.0, 75.0)  # metres, per axis
    offset_max: float = 10.0  # metres, per axis, of the box centre from the camera start


@dataclass(frozen=True)
class LightConfig:
    sun_strength_range: tuple[float, float] = (1.5, 5.0)  # W/m^2
    sun_elevation_range_deg: tuple[float, float] = (15.0, 90.0)
    ambient_strength_range: tuple[float, float] = (0.5, 1.2)  # world background strength
    colour_jitter: float = 0.15  # max deviation of light colour channels from white


SHADINGS = ("direct", "path")
# OpenImageDenoise quality modes; "auto" = "fast" below DENOISE_BALANCED_FROM_PX squared pixels
# (where per-frame costs dominate), "balanced" from there (about +1 dB at 256 px for about 20 %
# more time).
DENOISE_QUALITIES = ("auto", "fast", "balanced", "high")
DENOISE_BALANCED_FROM_PX = 192


@dataclass(frozen=True)
class RenderConfig:
    """Cycles settings. ``shading``: "direct" = sun (hard shadows, highlights) + ambient term,
    no diffuse bounces, so the only sampling noise is anti-aliasing; "path" = path tracing with
    world light and ``max_bounces`` (diffuse capped at 1), noisier and slower.
    ``max_bounces`` counts glossy bounces under "direct" (mirrors need 1)."""

    shading: str = "direct"
    samples: int = field(  # per pixel, box filter: anti-aliasing by area integration
        default=4,
        metadata=flag("--samples", "Cycles samples per pixel (after --quality).", 190, type=int),
    )
    denoise: bool = False  # OpenImageDenoise (albedo + normal guided, fast prefilter)
    denoise_quality: str = "auto"
    max_bounces: int = 1
    persistent: bool = True  # keep scene data between the frames of a scene (same pixels)
    # Cycles' light tree picks among many lights; with our one sun it only costs time: off, a
    # frame's sampling takes 7-8 % less, 4 % of pixels move, most by 1/255
    # (docs/results/generator-speed/README.md)
    light_tree: bool = False
    max_distance: float = 200.0  # metres, camera clip end; farther surfaces are misses
    near_clip: float = 0.05  # metres
    image_format: str = field(  # png (lossless) or jpg
        default="png",
        metadata=flag("--image-format", "RGB file format.", 200, type=IMAGE_FORMATS, note="plain"),
    )
    legacy: bool = field(  # also write .jpg + .npy for the original DepthNet loaders
        default=False,
        metadata=flag(
            "--legacy",
            "Also write .jpg frames and .npy depth for the original DepthNet code.",
            210,
            is_flag=True,
        ),
    )
    # also write optical flow, validity and occlusion masks of each frame pair of
    # stillbox_gen.layout.flow_pairs, from the rendered depth and the poses (docs/FORMAT.md)
    flow: bool = field(
        default=False,
        metadata=flag(
            "--flow",
            "Also write optical flow (.flo) with validity and occlusion masks (PNG) for frame "
            "pairs t, t+1 and t, t+3, both ways.",
            215,
            is_flag=True,
        ),
    )
    # the flow files' format (stillbox_gen.layout.FLOW_FORMATS): Middlebury .flo (float32) or
    # KITTI's 16-bit PNG (u, v, valid; 1/64 px, |flow| up to 512 px); with render.flow only
    flow_format: str = field(
        default="flo",
        metadata=flag(
            "--flow-format",
            "File format of the --flow files: Middlebury .flo (float32) or KITTI's 16-bit PNG "
            "(1/64 px steps, within 512 px). Implies --flow.",
            216,
            type=FLOW_FORMATS,
            also=(("flow", True),),
            note="plain",
        ),
    )


# --quality: render-section values (measured with `stillbox-gen bench`, see docs/SPEED.md);
# "default" is RenderConfig's own.
QUALITY = {
    "fast": {"shading": "direct", "samples": 1, "denoise": False},
    "default": {
        "shading": RenderConfig.shading,
        "samples": RenderConfig.samples,
        "denoise": RenderConfig.denoise,
    },
    "high": {"shading": "direct", "samples": 16, "denoise": False},
}


# --device: where Cycles renders. Not part of DatasetConfig: the device changes no scene (only,
# perhaps, pixels by sampling noise). "auto" takes the first GPU backend of GPU_BACKENDS that
# Cycles finds a device of, else the CPU. dataset.json's render.device records the backend used.
CPU_DEVICE = "CPU"
GPU_BACKENDS = ("OPTIX", "CUDA", "HIP", "ONEAPI", "METAL")  # Cycles' names, auto's preference
DEVICES = ("auto", "cpu", *(b.lower() for b in GPU_BACKENDS))


def denoise_quality(name: str, width: int, height: int) -> str:
    """The OpenImageDenoise mode used for ``render.denoise_quality`` at a frame size."""
    if name != "auto":
        return name
    return "fast" if width * height < DENOISE_BALANCED_FROM_PX**2 else "balanced"


@dataclass(frozen=True)
class DatasetConfig:
    preset: str = field(
        default="stillbox",
        metadata=flag(
            "--preset", "Preset name in scene_presets/ or path to a .toml file.", 80, note="click"
        ),
    )
    seed: int = field(
        default=0,
        metadata=flag(
            "--seed",
            "Dataset seed; scene k depends only on (seed, k).",
            40,
            type=int,
            note="click",
        ),
    )
    camera: CameraConfig = field(default_factory=CameraConfig)
    objects: ObjectsConfig = field(default_factory=ObjectsConfig)
    materials: MaterialsConfig = field(default_factory=MaterialsConfig)
    box: BoxConfig = field(default_factory=BoxConfig)
    light: LightConfig = field(default_factory=LightConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    split: tuple[float, float, float] = field(  # train / val / test shares by scene
        default=(0.8, 0.1, 0.1),
        metadata=flag(
            "--split",
            "Shares of scenes in train,val,test (by scene, from (seed, k)).",
            220,
            parse=parse_shares,
            note="plain",
        ),
    )

    def to_dict(self) -> dict:
        """Every field, but those of OMITTED_AT_DEFAULT at the value their absence means: keys
        added after datasets were published are left out at their old behaviour, so that those
        datasets' configs (and fingerprints) stay what they were."""
        d = dataclasses.asdict(self)
        for key, absent in OMITTED_AT_DEFAULT.items():
            sec, name = key.split(".")
            if d[sec][name] == absent:
                del d[sec][name]
        return d

    def fingerprint(self) -> str:
        """Hash of everything that determines scene content (used to refuse mixing datasets)."""
        from .formats import canonical_json

        return hashlib.sha256(canonical_json(self.to_dict()).encode()).hexdigest()[:16]


# Config keys added after datasets were written: {key: the value their absence means}. A key at
# that value is left out of dataset.json, so the older datasets' configs and fingerprints stay
# valid; from_dict fills it back. render.light_tree was on before the key existed.
OMITTED_AT_DEFAULT = {
    "camera.direction": None,
    "camera.rotation_speed_range_deg": None,
    "objects.fixed": None,
    "render.light_tree": True,
    "render.flow": False,
    "render.flow_format": "flo",
}

SECTIONS = {
    "camera": CameraConfig,
    "objects": ObjectsConfig,
    "materials": MaterialsConfig,
    "box": BoxConfig,
    "light": LightConfig,
    "render": RenderConfig,
}


def available_presets() -> list[str]:
    return sorted(
        p.name[:-5] for p in resources.files("scene_presets").iterdir() if p.name.endswith(".toml")
    )


def _find_preset(name_or_path: str):
    """(file, origin, name) of a preset: a path to a TOML file, or a name in scene_presets/."""
    path = Path(name_or_path)
    if path.suffix == ".toml" or path.exists():
        if not path.is_file():
            raise ConfigError(f"--preset: no such preset file '{path}'")
        return path, str(path), path.stem
    res = resources.files("scene_presets") / f"{name_or_path}.toml"
    if not res.is_file():
        raise ConfigError(
            f"--preset: unknown preset '{name_or_path}' "
            f"(available: {', '.join(available_presets())}, or a path to a .toml file)"
        )
    return res, f"scene_presets/{name_or_path}.toml", name_or_path


def preset_origin(name_or_path: str) -> str:
    """How error messages name a preset's file (as given, or ``scene_presets/NAME.toml``)."""
    return _find_preset(name_or_path)[1]


def load_preset(name_or_path: str) -> DatasetConfig:
    """Load a preset by name (``scene_presets/NAME.toml``) or by path to a TOML file; every value
    must have its field's type (ConfigError naming the file and key)."""
    file, origin, name = _find_preset(name_or_path)
    where = _namer(origin)
    try:
        data = tomllib.loads(file.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"preset {origin}: not valid TOML ({e})") from None
    except UnicodeDecodeError as e:
        raise ConfigError(
            f"preset {origin}: not UTF-8 text (byte {e.start}: {e.reason}); TOML files are UTF-8"
        ) from None
    except OSError as e:
        raise ConfigError(f"preset {origin}: cannot read it ({e.strerror})") from None
    data.pop("description", None)
    sections = {}
    for key, value in data.items():
        if key not in SECTIONS:
            raise ConfigError(f"preset {origin}: unknown section or key '{key}'")
        if not isinstance(value, dict):
            raise ConfigError(f"{where(key)} must be a table of keys ([{key}]), got {_show(value)}")
        cls = SECTIONS[key]
        names = {f.name for f in dataclasses.fields(cls)}
        for k in value:
            if k not in names:
                raise ConfigError(f"preset {origin}: unknown key '{key}.{k}'")
        sections[key] = _section(cls, value)
    cfg = DatasetConfig(preset=name, **sections)
    _check_types(cfg, where)
    return cfg


def _section(cls, values: dict):
    """A config section from TOML/JSON values (lists become tuples)."""
    return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in values.items()})


def from_dict(d: dict) -> DatasetConfig:
    """Inverse of :meth:`DatasetConfig.to_dict` (e.g. the ``config`` of dataset.json)."""
    d = {**d, **{name: dict(d[name]) for name in SECTIONS}}
    for key, absent in OMITTED_AT_DEFAULT.items():
        sec, name = key.split(".")
        d[sec].setdefault(name, absent)
    sections = {name: _section(cls, d[name]) for name, cls in SECTIONS.items()}
    return DatasetConfig(preset=d["preset"], seed=d["seed"], split=tuple(d["split"]), **sections)


def replace(cfg: DatasetConfig, **sections: dict) -> DatasetConfig:
    """Copy of cfg with some fields of some sections replaced, e.g. camera={'width': 128}."""
    changes = {}
    for sec, values in sections.items():
        if values:
            changes[sec] = dataclasses.replace(getattr(cfg, sec), **values)
    return dataclasses.replace(cfg, **changes)


def list_texture_files(directory: str) -> tuple[str, ...]:
    """Sorted names of the images in a folder (files whose contents OpenCV recognises as an
    image, others are ignored); each is decoded once here, and ConfigError names the first
    one that cannot be decoded whole (e.g. a cut-off JPEG), or says there are none."""
    import cv2

    d = Path(directory)
    if not d.is_dir():
        raise ConfigError(f"--textures: '{directory}' is not a folder")
    try:
        names = sorted(p.name for p in d.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS)
    except OSError as e:
        raise ConfigError(f"--textures: cannot read folder '{directory}' ({e.strerror})") from None
    good = []
    for n in names:
        try:
            ok = cv2.haveImageReader(str(d / n))
        except cv2.error:
            ok = False
        if ok:
            _check_photo(d / n, "--textures:")
            good.append(n)
    if not good:
        raise ConfigError(
            f"--textures: no readable images in '{directory}' "
            f"(looked for {', '.join(IMAGE_EXTENSIONS)})"
        )
    return tuple(good)


def _check_photo(path: Path, where: str) -> None:
    """Decode one photo of a textures folder (ConfigError starting with ``where`` when it is
    missing or does not decode whole)."""
    from . import photos

    if not path.is_file():
        raise ConfigError(f"{where} no image file '{path}'")
    try:
        photos.check_user(path)
    except ValueError as e:
        raise ConfigError(f"{where} {e}") from None


def is_plain_name(name: object) -> bool:
    """A file name without any folder part: not empty, no '/' or '\\', not '.' or '..'."""
    return (
        isinstance(name, str)
        and name not in ("", ".", "..")
        and not any(c in name for c in "/\\\x00")
    )


def check_texture_files(cfg: MaterialsConfig, where: Callable[[str], str]) -> None:
    """A preset's own photos: ``texture_files`` plain names of images in ``textures_dir``
    (each decoded once, as ``--textures`` does); one without the other is refused."""
    if not cfg.texture_files and not cfg.textures_dir:
        return
    if not cfg.texture_files or not cfg.textures_dir:
        missing = "texture_files" if cfg.textures_dir else "textures_dir"
        key = "materials.textures_dir" if cfg.textures_dir else "materials.texture_files"
        raise ConfigError(f"{where(key)} needs materials.{missing} too")
    where_files = where("materials.texture_files")
    bad = [n for n in cfg.texture_files if not is_plain_name(n)]
    if bad:
        raise ConfigError(
            f"{where_files} must be plain file names inside materials.textures_dir, "
            f"got {_show(bad[0])}"
        )
    folder = Path(cfg.textures_dir)
    if not folder.is_dir():
        raise ConfigError(f"{where('materials.textures_dir')} '{cfg.textures_dir}' is not a folder")
    for name in cfg.texture_files:
        _check_photo(folder / name, where_files)


# ---------------------------------------------------------------- validation


def config_flags() -> dict[str, Flag]:
    """{key: Flag} of every config field with a command-line flag (keys as in LIMITS:
    "section.name", or "seed", "preset", "split" for DatasetConfig's own fields)."""
    found = {}
    for section, cls in [("", DatasetConfig), *SECTIONS.items()]:
        for f in dataclasses.fields(cls):
            if "flag" in f.metadata:
                found[f"{section}.{f.name}" if section else f.name] = f.metadata["flag"]
    return found


def _flag_names() -> dict[str, str]:
    """{key: flag name} of every field a flag sets (--res: camera.width and camera.height)."""
    names = {}
    for key, fl in config_flags().items():
        section = key.rpartition(".")[0]
        for name in fl.fields or (key.rpartition(".")[2],):
            names[f"{section}.{name}" if section else name] = fl.name
    return names


# Config fields set by a command-line flag: their errors name the flag when the flag was given.
FLAGS = _flag_names()


def _namer(origin: str | None, given: Collection[str] | None = None) -> Callable[[str], str]:
    """``where(key)``: how an error names a config field ("section.name", or "seed"/"split").

    With no preset ``origin`` a field is named by its flag (FLAGS) when it has one, else by
    its key. With an origin, the fields in ``given`` (set on the command line) are named by
    their flag, the others as "preset ORIGIN: section.name" (a value from the preset file).
    """

    def where(key: str) -> str:
        from_flag = origin is None or "." not in key or key in (given or ())
        if from_flag and key in FLAGS:
            return f"{FLAGS[key]}:"
        return f"preset {origin}: {key}" if origin is not None else f"{key}:"

    return where


def _show(value) -> str:
    """A value as in the preset file: strings quoted, booleans lowercase, sequences in [ ]."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list | tuple):
        return f"[{', '.join(_show(v) for v in value)}]"
    return repr(value)


_NOUNS = {bool: "true or false", int: "an integer", float: "a finite number", str: "a string"}
_PLURALS = {bool: "booleans", int: "integers", float: "finite numbers", str: "strings"}


def _fits(value, hint) -> bool:
    if hint is bool:
        return isinstance(value, bool)
    if isinstance(value, bool):  # bool is an int subclass, but not an integer here
        return False
    if hint is int:
        return isinstance(value, int)
    if hint is float:
        return isinstance(value, int | float) and math.isfinite(value)
    return isinstance(value, hint)


def type_problem(value, hint) -> str | None:
    """Why ``value`` does not fit a config field annotated ``hint`` (None when it does).

    Numbers must be finite (floats accept integers), integers and booleans are distinct,
    ``tuple[float, float]`` is a list of exactly two numbers, ``tuple[str, ...]`` of strings,
    ``X | None`` takes None or an X.
    """
    if typing.get_origin(hint) in (types.UnionType, typing.Union):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        if value is None:
            return None
        hint = args[0]
    if typing.get_origin(hint) is tuple:
        args = typing.get_args(hint)
        if args[-1] is Ellipsis:
            item, n, wanted = args[0], None, f"a list of {_PLURALS[args[0]]}"
        else:
            item, n, wanted = args[0], len(args), f"a list of {len(args)} {_PLURALS[args[0]]}"
        ok = isinstance(value, list | tuple) and (n is None or len(value) == n)
        if ok and all(_fits(v, item) for v in value):
            return None
        return f"must be {wanted}, got {_show(value)}"
    return None if _fits(value, hint) else f"must be {_NOUNS[hint]}, got {_show(value)}"


def _check_types(cfg: DatasetConfig, where: Callable[[str], str]) -> None:
    for sec, cls in SECTIONS.items():
        values = getattr(cfg, sec)
        for name, hint in typing.get_type_hints(cls).items():
            problem = type_problem(getattr(values, name), hint)
            if problem:
                raise ConfigError(f"{where(f'{sec}.{name}')} {problem}")
    if type_problem(cfg.seed, int) or cfg.seed < 0:  # numpy's SeedSequence: any integer >= 0
        raise ConfigError(f"{where('seed')} must be a non-negative integer, got {_show(cfg.seed)}")
    problem = type_problem(cfg.split, tuple[float, float, float])
    if problem:
        raise ConfigError(f"{where('split')} {problem}")


def _check_range(
    where: Callable[[str], str],
    key: str,
    r: tuple[float, float],
    lo: float = 0.0,
    hi: float = math.inf,
) -> None:
    """[min, max] with lo <= min <= max <= hi (metres unless the key says otherwise)."""
    if not lo <= r[0] <= r[1] <= hi:
        limits = f"{lo:g} <= min <= max" + (f" <= {hi:g}" if hi < math.inf else "")
        raise ConfigError(f"{where(key)} must be [min, max] with {limits}, got {_show(r)}")


def validate(
    cfg: DatasetConfig, origin: str | None = None, given: Collection[str] | None = None
) -> None:
    """Raise ConfigError naming the first bad parameter: wrong type, not finite, out of range,
    or inconsistent with another, beyond LIMITS, or a preset's photo (materials.texture_files)
    that is no plain name of an image that decodes. ``origin`` (the preset's file, see
    preset_origin) and ``given`` (keys "section.name" set by command-line flags) choose how the
    message names it: the flag, or the preset file and key (see _namer)."""
    where = _namer(origin, given)
    _check_types(cfg, where)
    _check_limits(cfg, where)
    c, o, m, b, r, lc = cfg.camera, cfg.objects, cfg.materials, cfg.box, cfg.render, cfg.light
    if c.width <= 0 or c.height <= 0:
        key = "camera.width" if c.width <= 0 else "camera.height"
        raise ConfigError(f"{where(key)} must be positive (pixels), got {c.width}x{c.height}")
    if c.focal_px is None and not 0 < c.fov_deg < 180:
        raise ConfigError(f"{where('camera.fov_deg')} must be in (0, 180) degrees, got {c.fov_deg}")
    if c.focal_px is not None and c.focal_px <= 0:
        raise ConfigError(f"{where('camera.focal_px')} must be positive (pixels), got {c.focal_px}")
    if c.principal_point is not None:
        cx, cy = c.principal_point
        if not (-0.5 <= cx <= c.width - 0.5 and -0.5 <= cy <= c.height - 0.5):
            raise ConfigError(
                f"{where('camera.principal_point')} ({cx}, {cy}) lies outside the "
                f"{c.width}x{c.height} image"
            )
    if c.frames < 2:
        raise ConfigError(
            f"{where('camera.frames')} must be at least 2 frames per scene, got {c.frames}"
        )
    if not c.displacement > 0:
        raise ConfigError(
            f"{where('camera.displacement')} must be positive (metres/frame), got {c.displacement}"
        )
    if not c.time_step > 0:
        raise ConfigError(
            f"{where('camera.time_step')} must be positive (seconds), got {c.time_step}"
        )
    if c.direction is not None and not any(x != 0 for x in c.direction):
        raise ConfigError(
            f"{where('camera.direction')} must be a non-zero vector [x, y, z] (camera axes), "
            f"got {_show(c.direction)}"
        )
    for key in ("rotation_noise_deg", "rotation_speed_deg"):
        if getattr(c, key) < 0:
            raise ConfigError(
                f"{where(f'camera.{key}')} must be >= 0 degrees, got {getattr(c, key)}"
            )
    _check_rotation_speed_range(c, where, given or ())
    if o.count < 0:
        raise ConfigError(f"{where('objects.count')} must be >= 0, got {o.count}")
    bad = [k for k in o.kinds if k not in SHAPE_KINDS]
    if bad or not o.kinds:
        raise ConfigError(
            f"{where('objects.kinds')} must be a non-empty list of {list(SHAPE_KINDS)}, "
            f"got {_show(o.kinds)}"
        )
    _check_fixed(cfg, where)
    _check_range(where, "objects.size_range", o.size_range)
    _check_range(where, "objects.distance_range", o.distance_range)
    if o.distance_law not in DISTANCE_LAWS:
        raise ConfigError(
            f"{where('objects.distance_law')} must be one of {DISTANCE_LAWS}, "
            f"got {o.distance_law!r}"
        )
    if o.path_clearance < 0:
        raise ConfigError(
            f"{where('objects.path_clearance')} must be >= 0 metres, got {o.path_clearance}"
        )
    bad = [p for p in m.patterns if p not in PATTERNS]
    if bad or not m.patterns:
        raise ConfigError(
            f"{where('materials.patterns')} must be a non-empty list of {list(PATTERNS)}, "
            f"got {_show(m.patterns)}"
        )
    if m.photos not in PHOTO_SOURCES:
        raise ConfigError(
            f"{where('materials.photos')} must be one of {PHOTO_SOURCES}, got {m.photos!r}"
        )
    if "materials.texture_files" not in (given or ()):  # --textures has decoded its own
        check_texture_files(m, where)
    for name in ("texture_ratio", "plain_ratio", "glossy_ratio", "mirror_ratio"):
        if not 0 <= getattr(m, name) <= 1:
            raise ConfigError(
                f"{where(f'materials.{name}')} must be in [0, 1], got {getattr(m, name)}"
            )
    if not 0 <= o.behind_fraction <= 1:
        raise ConfigError(
            f"{where('objects.behind_fraction')} must be in [0, 1], got {o.behind_fraction}"
        )
    _check_range(where, "box.half_extent_range", b.half_extent_range)
    if b.offset_max < 0:
        raise ConfigError(f"{where('box.offset_max')} must be >= 0 metres, got {b.offset_max}")
    path_len = c.displacement * (c.frames - 1)
    inner = b.half_extent_range[0] - b.offset_max
    if inner <= path_len + 1.0:
        given = given or ()
        key = next(
            (k for k in ("camera.displacement", "camera.frames") if k in given),
            "box.half_extent_range",
        )
        raise ConfigError(
            f"{where(key)} the camera path ({path_len:.2f} m) does not fit in the smallest box "
            f"(box.half_extent_range min {b.half_extent_range[0]} m, offset_max {b.offset_max} m)"
        )
    _check_range(where, "light.sun_strength_range", lc.sun_strength_range)
    _check_range(where, "light.sun_elevation_range_deg", lc.sun_elevation_range_deg, -90, 90)
    _check_range(where, "light.ambient_strength_range", lc.ambient_strength_range)
    if not 0 <= lc.colour_jitter <= 1:
        raise ConfigError(
            f"{where('light.colour_jitter')} must be in [0, 1], got {lc.colour_jitter}"
        )
    if r.shading not in SHADINGS:
        raise ConfigError(f"{where('render.shading')} must be one of {SHADINGS}, got {r.shading!r}")
    if r.denoise_quality not in DENOISE_QUALITIES:
        raise ConfigError(
            f"{where('render.denoise_quality')} must be one of {DENOISE_QUALITIES}, "
            f"got {r.denoise_quality!r}"
        )
    if r.max_bounces < 0:
        raise ConfigError(f"{where('render.max_bounces')} must be >= 0, got {r.max_bounces}")
    if r.samples < 1:
        raise ConfigError(f"{where('render.samples')} must be >= 1, got {r.samples}")
    if r.image_format not in IMAGE_FORMATS:
        raise ConfigError(
            f"{where('render.image_format')} must be one of {IMAGE_FORMATS}, got {r.image_format!r}"
        )
    if r.flow_format not in FLOW_FORMATS:
        raise ConfigError(
            f"{where('render.flow_format')} must be one of {FLOW_FORMATS}, got {r.flow_format!r}"
        )
    if r.flow_format != "flo" and not r.flow:
        raise ConfigError(
            f"{where('render.flow_format')} {r.flow_format!r} needs render.flow = true (the "
            "format of flow files that would not be written)"
        )
    if not 0 < r.near_clip < r.max_distance:
        raise ConfigError(
            f"{where('render.near_clip')} must be in (0, render.max_distance) metres, "
            f"got {r.near_clip} and max_distance {r.max_distance}"
        )
    if min(cfg.split) < 0 or not math.isclose(sum(cfg.split), 1.0):
        raise ConfigError(
            f"{where('split')} must be three non-negative shares summing to 1, "
            f"got {_show(cfg.split)}"
        )


def _check_rotation_speed_range(
    c: CameraConfig, where: Callable[[str], str], given: Collection[str]
) -> None:
    """camera.rotation_speed_range_deg: [min, max] in [0, 180] degrees per frame (beyond 180 a
    rotation looks like a smaller one the other way), and rotation_speed_deg left at 0."""
    r = c.rotation_speed_range_deg
    if r is None:
        return
    _check_range(where, "camera.rotation_speed_range_deg", r, 0.0, 180.0)
    if c.rotation_speed_deg > 0:
        keys = ["camera.rotation_speed_range_deg", "camera.rotation_speed_deg"]
        if keys[1] in given:  # blame the flag, not the preset it overrode
            keys.reverse()
        other = _show(getattr(c, keys[1].split(".")[1]))
        raise ConfigError(
            f"{where(keys[0])} excludes {keys[1]} = {other}: a constant rotation speed is "
            "either the same for every scene (rotation_speed_deg) or drawn per scene "
            "(rotation_speed_range_deg)"
        )


def _check_fixed(cfg: DatasetConfig, where: Callable[[str], str]) -> None:
    """objects.fixed: a name of FIXED_SCENES, seen by a camera in world axes (no random
    orientation), whose surfaces use named bundled photos (so neither materials.photos =
    "none" nor a preset's or --textures' own photos)."""
    fixed, m = cfg.objects.fixed, cfg.materials
    if fixed is None:
        return
    if fixed not in FIXED_SCENES:
        raise ConfigError(
            f"{where('objects.fixed')} must be one of {FIXED_SCENES}, got {_show(fixed)}"
        )
    if cfg.camera.random_orientation:
        raise ConfigError(
            f"{where('camera.random_orientation')} must be false with objects.fixed: the fixed "
            "scenes are laid out in the camera's axes (world axes)"
        )
    if m.photos != "bundled" or m.texture_files or m.textures_dir:
        key = "materials.photos" if m.photos != "bundled" else "materials.texture_files"
        raise ConfigError(
            f"{where(key)} the fixed scene '{fixed}' (objects.fixed) is textured with bundled "
            "photos: it takes neither --textures nor --photos none"
        )


def _check_limits(cfg: DatasetConfig, where: Callable[[str], str]) -> None:
    """Every config field of LIMITS at most its bound (ConfigError naming the flag or key)."""
    for key in LIMITS:
        if "." in key:
            sec, name = key.split(".")
            problem = limit_problem(key, getattr(getattr(cfg, sec), name))
            if problem:
                raise ConfigError(f"{where(key)} {problem}")
