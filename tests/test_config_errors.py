"""Bad generator input checked in-process (fast): non-finite numbers, seeds, preset value types
and ranges, undecodable texture files. Each is a ConfigError naming the flag or the preset file and
key, raised before anything is written; tests/test_cli_errors.py checks the command line end to
end."""

from __future__ import annotations

import dataclasses
import math
import typing

import click
import cv2
import numpy as np
import pytest

from stillbox_gen import cli, config
from stillbox_gen.errors import ConfigError


def build(*args) -> config.DatasetConfig:
    """cli.build_config of ``stillbox-gen generate ARGS`` (the options click parses)."""
    ctx = cli.generate.make_context("generate", [str(a) for a in args])
    return cli.build_config(ctx.params)


def preset(tmp_path, text: str) -> str:
    path = tmp_path / "x.toml"
    path.write_text(text)
    return str(path)


def float_fields() -> list[tuple[str, str]]:
    """(section, field) of every number-valued config field, tuples of numbers included."""
    found = []
    for sec, cls in config.SECTIONS.items():
        for name, hint in typing.get_type_hints(cls).items():
            if "float" in str(hint) or hint is float:
                found.append((sec, name))
    return found


# ---------------------------------------------------------------- non-finite numbers


@pytest.mark.parametrize(
    ("args", "line"),
    [
        (["--focal", "inf"], "--focal: must be a finite number, got inf"),
        (["--fov", "nan"], "--fov: must be a finite number, got nan"),
        (["--rotation-noise", "nan"], "--rotation-noise: must be a finite number, got nan"),
        (["--rotation-speed", "-inf"], "--rotation-speed: must be a finite number, got -inf"),
        (["--displacement", "inf"], "--displacement: must be a finite number, got inf"),
        (["--principal-point", "nan,3"], "--principal-point: must be a list of 2 finite"),
        (["--split", "0.8,nan,0.1"], "--split: must be a list of 3 finite numbers"),
    ],
)
def test_non_finite_flag_names_the_flag(args, line):
    with pytest.raises(ConfigError) as e:
        build(*args)
    assert str(e.value).startswith(line), str(e.value)


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize(("section", "name"), float_fields())
def test_every_float_field_rejects_non_finite_values(section, name, value):
    """Every float of every section (ranges and principal point included), whatever its
    other limits, names its key (or its flag) when not finite."""
    cfg = config.load_preset("stillbox")
    old = getattr(getattr(cfg, section), name)
    bad = tuple(value for _ in old) if isinstance(old, tuple) else value
    if name == "principal_point":
        bad = (value, 3.0)
    with pytest.raises(ConfigError) as e:
        config.validate(config.replace(cfg, **{section: {name: bad}}))
    flag = config.FLAGS.get(f"{section}.{name}")
    assert str(e.value).startswith(f"{flag or f'{section}.{name}'}:"), str(e.value)
    assert "finite" in str(e.value), str(e.value)


def test_non_finite_scene_timeout_is_refused():
    cfg = build()
    for value in ("nan", "inf"):
        ctx = cli.generate.make_context("generate", ["--scene-timeout", value])
        with pytest.raises(ConfigError, match=f"^--scene-timeout: .* got {value}$"):
            cli.run_options(ctx.params, cfg)


# ---------------------------------------------------------------- seeds


@pytest.mark.parametrize("seed", ["-1", "-123456789"])
def test_negative_seed_is_refused(seed):
    with pytest.raises(ConfigError) as e:
        build("--seed", seed)
    assert str(e.value) == f"--seed: must be a non-negative integer, got {seed}"


def test_large_seeds_are_accepted():
    """SeedSequence takes any non-negative integer."""
    assert build("--seed", 2**70).seed == 2**70


# ---------------------------------------------------------------- preset value types


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('[camera]\nframes = "ten"', "camera.frames must be an integer, got 'ten'"),
        ("[camera]\nframes = 10.0", "camera.frames must be an integer, got 10.0"),
        ("[camera]\nframes = true", "camera.frames must be an integer, got true"),
        ("camera = 5", "camera must be a table of keys ([camera]), got 5"),
        ('camera = "wide"', "camera must be a table of keys ([camera]), got 'wide'"),
        ("[objects]\ncount = 2.5", "objects.count must be an integer, got 2.5"),
        ("[objects]\ncount = false", "objects.count must be an integer, got false"),
        ('[camera]\nfov_deg = "90"', "camera.fov_deg must be a finite number, got '90'"),
        ("[camera]\nfov_deg = nan", "camera.fov_deg must be a finite number, got nan"),
        ("[camera]\nfov_deg = true", "camera.fov_deg must be a finite number, got true"),
        ("[camera]\nrandom_orientation = 1", "camera.random_orientation must be true or false"),
        ("[camera]\nprincipal_point = [1, 2, 3]", "camera.principal_point must be a list of 2"),
        ('[objects]\nkinds = "cube"', "objects.kinds must be a list of strings, got 'cube'"),
        ("[objects]\nkinds = [1, 2]", "objects.kinds must be a list of strings, got [1, 2]"),
        ("[objects]\nsize_range = 3.0", "objects.size_range must be a list of 2 finite numbers"),
        ("[objects]\nsize_range = [1.0]", "objects.size_range must be a list of 2 finite"),
        ("[objects]\nsize_range = [1.0, inf]", "objects.size_range must be a list of 2 finite"),
        ('[objects]\nsize_range = [1, "3"]', "objects.size_range must be a list of 2 finite"),
        ("[light]\ncolour_jitter = -inf", "light.colour_jitter must be a finite number, got -inf"),
        ("[render]\nshading = 3", "render.shading must be a string, got 3"),
        ("[render]\nsamples = 4.0", "render.samples must be an integer, got 4.0"),
        ('[render]\ndenoise = "no"', "render.denoise must be true or false, got 'no'"),
        ("[materials]\ntexture_ratio = [0.5]", "materials.texture_ratio must be a finite number"),
        (
            "[camera]\nrotation_speed_range_deg = 1.0",
            "camera.rotation_speed_range_deg must be a list of 2 finite numbers, got 1.0",
        ),
    ],
)
def test_preset_value_of_wrong_type_names_file_and_key(tmp_path, text, message):
    path = preset(tmp_path, text)
    with pytest.raises(ConfigError) as e:
        config.load_preset(path)
    assert str(e.value).startswith(f"preset {path}: {message}"), str(e.value)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[objects]\nsize_range = [-1.0, 3.0]", "objects.size_range must be [min, max]"),
        ("[objects]\nsize_range = [5.0, 3.0]", "objects.size_range must be [min, max]"),
        ("[objects]\ndistance_range = [-2.0, 3.0]", "objects.distance_range must be [min, max]"),
        ("[box]\nhalf_extent_range = [80.0, 60.0]", "box.half_extent_range must be [min, max]"),
        ("[light]\nsun_strength_range = [-1.0, 2.0]", "light.sun_strength_range must be"),
        ("[light]\nambient_strength_range = [2.0, 1.0]", "light.ambient_strength_range must be"),
        ("[light]\nsun_elevation_range_deg = [10.0, 100.0]", "light.sun_elevation_range_deg"),
        ("[light]\ncolour_jitter = 1.5", "light.colour_jitter must be in [0, 1]"),
        ("[box]\noffset_max = -1.0", "box.offset_max must be >= 0"),
        ("[objects]\npath_clearance = -0.1", "objects.path_clearance must be >= 0"),
        ("[objects]\ncount = -3", "objects.count must be >= 0, got -3"),
        ("[camera]\nfov_deg = 0.0", "camera.fov_deg must be in (0, 180) degrees, got 0.0"),
        ("[camera]\nframes = 1", "camera.frames must be at least 2"),
        ("[render]\nsamples = 0", "render.samples must be >= 1, got 0"),
        ("[materials]\nglossy_ratio = 2.0", "materials.glossy_ratio must be in [0, 1]"),
        ("[camera]\nrotation_noise_deg = -1.0", "camera.rotation_noise_deg must be >= 0"),
        (
            "[camera]\nrotation_speed_range_deg = [1.0, 0.5]",
            "camera.rotation_speed_range_deg must be [min, max] with 0 <= min <= max <= 180",
        ),
        (
            "[camera]\nrotation_speed_range_deg = [0.0, 181.0]",
            "camera.rotation_speed_range_deg must be [min, max] with 0 <= min <= max <= 180",
        ),
        (
            "[camera]\nrotation_speed_range_deg = [0.0, 1.0]\nrotation_speed_deg = 0.2",
            "camera.rotation_speed_range_deg excludes camera.rotation_speed_deg = 0.2: ",
        ),
        # beyond the limits (config.LIMITS): used to hang, exhaust memory or fail in the workers
        ("[camera]\nwidth = 3000000000", "camera.width must be at most 8,192 pixels"),
        ("[camera]\nheight = 8193", "camera.height must be at most 8,192 pixels, got 8,193"),
        ("[camera]\nframes = 10001", "camera.frames must be at most 10,000 frames per scene"),
        ("[objects]\ncount = 100000000", "objects.count must be at most 1,000 objects"),
        ("[render]\nsamples = 4097", "render.samples must be at most 4,096 samples per pixel"),
        ("[render]\nmax_bounces = 10000000000", "render.max_bounces must be at most 1,024"),
    ],
)
def test_preset_value_out_of_range_names_file_and_key(tmp_path, text, message):
    """Range, limit and consistency errors of values the preset set name the file and key."""
    path = preset(tmp_path, text)
    with pytest.raises(ConfigError) as e:
        build("--preset", path)
    assert str(e.value).startswith(f"preset {path}: {message}"), str(e.value)


def test_flag_overriding_a_preset_value_is_named_as_the_flag(tmp_path):
    """The same bad value from a flag names the flag, not the preset that it overrode."""
    path = preset(tmp_path, "[camera]\nframes = 12\n")
    with pytest.raises(
        ConfigError, match=r"^--frames: must be at least 2 frames per scene, got 1$"
    ):
        build("--preset", path, "--frames", 1)
    with pytest.raises(ConfigError, match=r"^--displacement: the camera path \(99.00 m\)"):
        build("--preset", path, "--displacement", 9)
    spin = r"^--rotation-speed: excludes camera.rotation_speed_range_deg = \[0.0, 1.0\]: "
    with pytest.raises(ConfigError, match=spin):
        build("--preset", "stillbox-rotating", "--rotation-speed", 0.5)


def test_valid_preset_file_still_loads(tmp_path):
    path = preset(tmp_path, "[camera]\nfov_deg = 60\nframes = 12\n[objects]\ncount = 0\n")
    cfg = build("--preset", path)
    assert cfg.camera.fov_deg == 60 and cfg.camera.frames == 12 and cfg.objects.count == 0
    assert dataclasses.asdict(config.load_preset("stillbox")) == dataclasses.asdict(build())


# ---------------------------------------------------------------- texture files


def _photo(path) -> bytes:
    rng = np.random.default_rng(1)
    img = cv2.resize(rng.integers(0, 256, (8, 8, 3), np.uint8), (64, 64))
    ok, buf = cv2.imencode(path.suffix, img)
    assert ok
    return buf.tobytes()


@pytest.mark.parametrize("name", ["cut.jpg", "cut.png", "cut.webp", "cut.bmp"])
def test_truncated_texture_file_is_named(tmp_path, capfd, name):
    """A file with a valid header but its data cut off decodes partly (cv2.imread pads a cut
    JPEG with grey): refused up front, naming the file, with no decoder noise on stderr."""
    good, cut = tmp_path / "good.png", tmp_path / name
    good.write_bytes(_photo(good))
    cut.write_bytes(_photo(cut)[: len(_photo(cut)) // 2])
    with pytest.raises(ConfigError) as e:
        config.list_texture_files(str(tmp_path))
    assert str(e.value) == f"--textures: '{cut}' cannot be decoded (truncated or corrupt data)"
    assert capfd.readouterr().err == ""
    cut.write_bytes(_photo(cut))  # the whole file is accepted
    assert config.list_texture_files(str(tmp_path)) == tuple(sorted(["good.png", name]))


# ---------------------------------------------------------------- limits (config.LIMITS)


@pytest.mark.parametrize(
    ("args", "line"),
    [
        (["--res", "100000"], "--res: must be at most 8,192 pixels, got 100,000"),
        (["--res", "64x8193"], "--res: must be at most 8,192 pixels, got 8,193"),
        (["--samples", 10**12], "--samples: must be at most 4,096 samples per pixel, got 1,0"),
        (["--frames", "10001"], "--frames: must be at most 10,000 frames per scene"),
    ],
)
def test_flag_beyond_its_limit_names_the_flag(args, line):
    with pytest.raises(ConfigError) as e:
        build(*args)
    assert str(e.value).startswith(line), str(e.value)


@pytest.mark.parametrize(
    ("flag", "value"), [("--scenes", 10**12), ("--threads", 10**11), ("--workers", 257)]
)
def test_run_option_beyond_its_limit_names_the_flag(flag, value):
    most, unit = config.LIMITS[flag[2:]]
    ctx = cli.generate.make_context("generate", [flag, str(value)])
    with pytest.raises(ConfigError) as e:
        cli.run_options(ctx.params, build())
    assert str(e.value) == f"{flag}: must be at most {most:,} {unit}, got {value:,}"


def test_values_at_the_limits_are_accepted(tmp_path):
    path = preset(tmp_path, "[objects]\ncount = 1000\n[render]\nmax_bounces = 1024\n")
    cfg = build("--preset", path, "--res", "8192", "--samples", 4096)
    assert (cfg.camera.width, cfg.render.samples, cfg.objects.count) == (8192, 4096, 1000)
    args = ["--scenes", 10_000_000, "--threads", 1024, "--workers", 256]
    ctx = cli.generate.make_context("generate", [str(a) for a in args])
    opts = cli.run_options(ctx.params, cfg)
    assert (opts.scenes, opts.threads, opts.workers) == (10_000_000, 1024, 256)


def test_every_limit_is_a_config_field_or_a_run_option():
    """One table for flags and preset keys: each key names a real field or generate option."""
    from stillbox_gen.generate import RunOptions

    options = {f.name for f in dataclasses.fields(RunOptions)}
    for key in config.LIMITS:
        if "." in key:
            sec, name = key.split(".")
            assert name in {f.name for f in dataclasses.fields(config.SECTIONS[sec])}, key
        else:
            assert key in options, key


# ---------------------------------------------------------------- preset files and their photos


def test_preset_that_is_not_utf8_names_the_file(tmp_path):
    path = tmp_path / "latin1.toml"
    path.write_bytes("# caf\u00e9\n[camera]\nfov_deg = 60\n".encode("latin-1"))
    with pytest.raises(ConfigError) as e:
        build("--preset", path)
    assert str(e.value).startswith(f"preset {path}: not UTF-8 text"), str(e.value)


def test_empty_res_is_refused_not_the_default():
    with pytest.raises(ConfigError, match=r"^--res: expected N or WxH in pixels, got ''$"):
        build("--res", "")


@pytest.fixture
def photo_folder(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    (folder / "good.png").write_bytes(_photo(folder / "good.png"))
    return folder


@pytest.mark.parametrize(
    ("materials", "message"),
    [
        (
            'textures_dir = "/etc"\ntexture_files = ["passwd"]',
            "materials.texture_files '/etc/passwd' cannot be decoded",
        ),
        (
            'textures_dir = "{photos}"\ntexture_files = ["../photos/good.png"]',
            "materials.texture_files must be plain file names inside materials.textures_dir, "
            "got '../photos/good.png'",
        ),
        (
            'textures_dir = "{photos}"\ntexture_files = ["/etc/passwd"]',
            "materials.texture_files must be plain file names",
        ),
        (
            'textures_dir = "{photos}"\ntexture_files = ["missing.png"]',
            "materials.texture_files no image file '{photos}/missing.png'",
        ),
        ('textures_dir = "{photos}"', "materials.textures_dir needs materials.texture_files"),
        ('texture_files = ["good.png"]', "materials.texture_files needs materials.textures_dir"),
    ],
)
def test_preset_photos_are_checked_at_config_time(tmp_path, photo_folder, materials, message):
    """A preset's own photos: plain names of images in textures_dir that decode, as --textures
    checks its folder; they used to be accepted and fail late, in the workers."""
    path = preset(tmp_path, "[materials]\n" + materials.format(photos=photo_folder))
    with pytest.raises(ConfigError) as e:
        build("--preset", path)
    assert str(e.value).startswith(f"preset {path}: {message.format(photos=photo_folder)}"), str(
        e.value
    )


def test_preset_photos_that_decode_are_accepted(tmp_path, photo_folder):
    path = preset(
        tmp_path, f'[materials]\ntextures_dir = "{photo_folder}"\ntexture_files = ["good.png"]\n'
    )
    assert build("--preset", path).materials.texture_files == ("good.png",)


# ---------------------------------------------------------------- flags declared with their field


def test_every_config_flag_is_a_generate_option_that_sets_its_fields():
    """Each config.Flag (field metadata) is an option of generate, and giving it sets the
    fields it names: the flag is declared once, next to its field."""
    options = {o for p in cli.generate.params for o in getattr(p, "opts", [])}
    samples = {int: "7", float: "0.25", str: None}
    checked = 0
    for key, fl in config.config_flags().items():
        assert fl.name in options, fl.name
        if fl.parse or fl.is_flag or samples.get(fl.type) is None:
            continue
        cfg = build(fl.name, samples[fl.type])
        section, _, name = key.rpartition(".")
        got = getattr(getattr(cfg, section) if section else cfg, name)
        assert got == fl.type(samples[fl.type]), key
        checked += 1
    assert checked >= 5


def test_generate_help_places_are_unique():
    """Every generate option has its own place in --help (config.Flag.order, cli._RUN_OPTIONS),
    and --help lists them in that order."""
    places = [fl.order for fl in config.config_flags().values()]
    places += [order for order, _ in cli._RUN_OPTIONS]
    assert len(places) == len(set(places))
    shown = [p.opts[0] for p in cli.generate.params if isinstance(p, click.Option)]
    assert shown[:4] == ["--res", "--scenes", "--out", "--seed"] and shown[-1] == "--quiet"


def test_flags_with_several_fields_set_them_all_and_name_them_in_errors():
    cfg = build("--res", "40x30", "--fov", "60", "--legacy", "--image-format", "jpg")
    assert (cfg.camera.width, cfg.camera.height, cfg.camera.fov_deg) == (40, 30, 60.0)
    assert cfg.camera.focal_px is None and cfg.render.legacy and cfg.render.image_format == "jpg"
    assert config.FLAGS["camera.width"] == config.FLAGS["camera.height"] == "--res"
    assert config.FLAGS["materials.texture_files"] == "--textures"
    with pytest.raises(ConfigError, match=r"^--res: width and height must be positive"):
        build("--res", "0x30")


# ---------------------------------------------------------------- shared command-line parsers


def test_resolution_parser_and_out_folder_check_are_shared_by_both_clis(tmp_path):
    """arguments.parse_resolution is --res of stillbox-gen and of stillbox-bench (its click
    type, whose bounds and infer's multiple-of-64 rule are checked on top); check_out_folder
    raises each CLI's own error."""
    import click

    from benchmark.cli import options as bench_options
    from benchmark.cli.limits import RESOLUTION
    from stillbox_gen import arguments

    assert arguments.parse_resolution("64") == (64, 64)
    assert arguments.parse_resolution(" 128X64 ") == (128, 64)
    assert RESOLUTION.convert(" 128X64 ", None, None) == (128, 64)
    for bad, words in (("64x", "expected N or WxH"), ("0x64", "width and height must be positive")):
        with pytest.raises(ConfigError, match=f"^--res: {words}"):
            arguments.parse_resolution(bad)
        with pytest.raises(click.BadParameter, match=f"^{words}"):
            RESOLUTION.convert(bad, None, None)
    file = tmp_path / "f"
    file.write_text("")
    arguments.check_out_folder(tmp_path)  # a folder, or a missing path, is fine
    arguments.check_out_folder(tmp_path / "new")
    for error in (ConfigError, bench_options.UserError):
        with pytest.raises(error, match=f"^--out: '{file}' is a file, not a folder$"):
            arguments.check_out_folder(file, error=error)
