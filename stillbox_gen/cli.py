"""Command line: ``stillbox-gen [generate] OPTIONS``, ``stillbox-gen validate``, ``... preview``.

User mistakes print one line ``stillbox-gen: error: ...`` and exit with code 2, writing nothing.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import click

from . import config
from .conventions import MAX_DEPTH, NOMINAL_SHIFT, default_root
from .errors import ConfigError, DatasetError
from .formats import disk_full_message, is_disk_full
from .layout import enclosing_dataset
from .lock import MAX_SHARDS
from .workers import Terminated, sigterm_as_interrupt

if TYPE_CHECKING:
    from .generate import RunOptions


class DefaultGroup(click.Group):
    """A group that runs ``generate`` when the first argument is not a sub-command."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        if not args or (args[0] not in self.commands and args[0] not in ("--help", "-h")):
            args = ["generate", *args]
        return super().parse_args(ctx, args)

    def format_help(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        super().format_help(ctx, formatter)
        gen = self.commands["generate"]
        sub = click.Context(gen, info_name="generate", parent=ctx)
        params = [
            p
            for p in gen.get_params(sub)
            if not isinstance(p, click.Option) or "--help" not in p.opts
        ]
        rows = [r for p in params if (r := p.get_help_record(sub))]
        with formatter.section("Generate options (stillbox-gen [generate] ...)"):
            formatter.write_dl(rows)


@click.group(cls=DefaultGroup, context_settings={"help_option_names": ["-h", "--help"]})
def cli() -> None:
    """StillBox-style depth-from-motion datasets rendered by Blender.

    \b
    stillbox-gen --res 256 --scenes 3000          (same as: stillbox-gen generate ...)
    stillbox-gen validate data/stillbox-256
    stillbox-gen preview data/stillbox-256 --out preview.png
    """


class PathArg(click.Path):
    """A path option or argument (``--out``, ``DATASET``, ``--textures``...): a Path, never the
    empty string, which Path would silently read as the current folder."""

    def __init__(self) -> None:
        super().__init__(path_type=Path)

    def convert(self, value, param, ctx):
        if isinstance(value, str) and not value.strip():
            self.fail(f"must be a path, got {value!r}", param, ctx)
        return super().convert(value, param, ctx)


def _show(value: object) -> str:
    """A default as the help shows it: numbers without trailing zeros, sequences comma-joined."""
    if isinstance(value, tuple):
        return ",".join(_show(v) for v in value)
    return f"{value:g}" if isinstance(value, float) else str(value)


def _run_default(name: str) -> object:
    """The default of a generate.RunOptions field: the CLI's default for its flag."""
    from .generate import RunOptions

    return next(f.default for f in dataclasses.fields(RunOptions) if f.name == name)


_DEVICE = click.option(
    "--device",
    type=click.Choice(config.DEVICES),
    default="auto",
    show_default=True,
    help="Cycles render device: auto = the first of "
    + ", ".join(b.lower() for b in config.GPU_BACKENDS)
    + " with a device Cycles finds, else cpu. Changes no scene.",
)
DEFAULT_SCENES = 100  # --scenes
DEFAULT_FIXED_SCENES = 1  # --scenes of a fixed scene (objects.fixed): every scene is the same

# generate's options that set no config field (those are declared with their field: config.Flag),
# with their place in generate --help (the order of config.Flag).
_RUN_OPTIONS = [
    (
        20,
        click.option(
            "--scenes",
            type=int,
            help=f"Number of scenes.  [default: {DEFAULT_SCENES}; {DEFAULT_FIXED_SCENES} with a "
            "fixed scene (objects.fixed, e.g. --preset toy-flower)]",
        ),
    ),
    (
        30,
        click.option(
            "--out", type=PathArg(), help="Output folder.  [default: data/stillbox-<W>[x<H>]]"
        ),
    ),
    (
        50,
        click.option(
            "--workers",
            type=int,
            default=_run_default("workers"),
            show_default=True,
            help="Blender worker processes.",
        ),
    ),
    (
        60,
        click.option(
            "--threads",
            type=int,
            default=_run_default("threads"),
            show_default=True,
            help="Cycles threads per worker (0 = all cores).",
        ),
    ),
    (70, _DEVICE),
    (
        180,
        click.option(
            "--quality",
            type=click.Choice(list(config.QUALITY)),
            help="Samples per pixel (anti-aliasing; the shading has no noise): "
            + ", ".join(f"{q} {v['samples']}" for q, v in config.QUALITY.items())
            + " (docs/SPEED.md has the measured costs).  [default: preset]",
        ),
    ),
    (
        230,
        click.option(
            "--shard",
            help="I/N: render only scenes k with k % N == I (0 <= I < N), for job arrays. Into "
            "one shared folder: the last shard to finish indexes it (or `stillbox-gen index "
            "OUT`); into separate folders: join them with `stillbox-gen merge OUT FOLDERS...`.",
        ),
    ),
    (
        240,
        click.option(
            "--scene-timeout",
            type=float,
            default=_run_default("scene_timeout"),
            show_default=True,
            help="Seconds without any finished scene before the workers are replaced and their "
            "scenes retried (watchdog for hung workers).",
        ),
    ),
    (
        250,
        click.option(
            "--backend",
            type=click.Choice(["local", "ray"]),
            default=_run_default("backend"),
            show_default=True,
            help="local: Blender processes on this machine; ray: Ray actors on a Ray cluster "
            "(pip install 'stillbox-gen[ray]'), each using --threads CPUs (1 when 0).",
        ),
    ),
    (
        260,
        click.option(
            "--ray-address",
            help="Ray cluster to join (auto, HOST:PORT or ray://HOST:PORT) with --backend ray.  "
            "[default: start a local Ray instance]",
        ),
    ),
    (270, click.option("--quiet", is_flag=True, help="No progress bar.")),
]


def _dest(fl: config.Flag) -> str:
    """The key of a flag's value in the options dict (``--rotation-noise``: rotation_noise)."""
    return fl.name.lstrip("-").replace("-", "_")


def _field_defaults(key: str, fl: config.Flag) -> list:
    """The defaults of the fields a flag sets (the dataclass defaults, as a preset that does not
    set the key gives them)."""
    section, _, name = key.rpartition(".")
    owner = config.SECTIONS[section] if section else config.DatasetConfig
    defaults = {f.name: f.default for f in dataclasses.fields(owner)}
    return [defaults[n] for n in fl.fields or (name,)]


def _flag_option(key: str, fl: config.Flag):
    """The click option of a config field's flag, its help ending in the default note."""
    values = _field_defaults(key, fl)
    shown = _show(values[0]) if len(set(values)) == 1 else "x".join(_show(v) for v in values)
    notes = {"preset": f"  [default: preset, {shown}]", "plain": f"  [default: {shown}]"}
    kind = {int: int, float: float, str: None, "path": PathArg()}
    attrs: dict = {"help": fl.help + notes.get(fl.note, "")}
    if fl.is_flag:
        attrs["is_flag"] = True
    elif isinstance(fl.type, tuple):
        attrs["type"] = click.Choice(fl.type)
    elif kind[fl.type] is not None:
        attrs["type"] = kind[fl.type]
    if fl.note == "click":
        attrs.update(default=values[0], show_default=True)
    return click.option(fl.name, **attrs)


def _generate_options(command):
    """``command`` with every generate option, in the order of its --help: the flags of config
    fields (config.Flag) and _RUN_OPTIONS."""
    flags = [(fl.order, _flag_option(key, fl)) for key, fl in config.config_flags().items()]
    for _, option in sorted([*flags, *_RUN_OPTIONS], key=lambda o: o[0], reverse=True):
        command = option(command)
    return command


@cli.command()
@_generate_options
def generate(**o) -> None:
    """Render a dataset (resumes when --out holds an unfinished one with the same parameters)."""
    from .generate import generate as run
    from .workers import choose_device

    cfg = build_config(o)
    opts = run_options(o, cfg)
    device, device_line = choose_device(o["device"], opts.backend)  # before anything is written
    opts = dataclasses.replace(opts, device=device)
    c, out, shard = cfg.camera, opts.out, opts.shard
    banner = (
        f"stillbox-gen: {opts.scenes} scenes of {c.frames} frames at {c.width}x{c.height} "
        f"(preset {cfg.preset}, seed {cfg.seed}) -> {out}"
    )
    if shard != (0, 1):
        banner += f", shard {shard[0]}/{shard[1]}"
    summary = run(cfg, opts, announce=lambda: click.echo(f"{banner}\n{device_line}", err=True))
    if summary.frames == 0:  # a shard that left scenes to others: nothing indexed yet
        click.echo(
            f"shard {shard[0]}/{shard[1]} done: {summary.rendered_now} scenes rendered in "
            f"{summary.seconds:.1f} s; the dataset is indexed when every shard has finished",
            err=True,
        )
        return
    click.echo("\n".join(["done:", *("  " + line for line in summary.lines())]), err=True)


def run_options(o: dict, cfg: config.DatasetConfig) -> RunOptions:
    """The generate.RunOptions of the command-line options ``o`` (ConfigError naming the flag)."""
    from .generate import RunOptions

    if o["scenes"] is None:
        o = {**o, "scenes": DEFAULT_FIXED_SCENES if cfg.objects.fixed else DEFAULT_SCENES}
    for flag in ("scenes", "workers"):
        if o[flag] < 1:
            raise ConfigError(f"--{flag}: must be at least 1, got {o[flag]}")
    if o["threads"] < 0:
        raise ConfigError(f"--threads: must be >= 0, got {o['threads']}")
    for flag in ("scenes", "workers", "threads"):
        problem = config.limit_problem(flag, o[flag])
        if problem:
            raise ConfigError(f"--{flag}: {problem}")
    shard = parse_shard(o["shard"]) if o["shard"] else (0, 1)
    timeout = o["scene_timeout"]
    if not (timeout > 0 and math.isfinite(timeout)):
        raise ConfigError(
            f"--scene-timeout: must be a positive finite number of seconds, got {timeout}"
        )
    if o["ray_address"] and o["backend"] != "ray":
        raise ConfigError("--ray-address: only with --backend ray")
    if o["backend"] == "ray":
        from .ray_pool import require_ray

        require_ray()
    return RunOptions(
        backend=o["backend"],
        ray_address=o["ray_address"],
        scene_timeout=o["scene_timeout"],
        shard=shard,
        out=o["out"] or default_root(cfg.camera.width, cfg.camera.height),
        scenes=o["scenes"],
        workers=o["workers"],
        threads=o["threads"],
        progress=not o["quiet"],
    )


def parse_shard(value: str) -> tuple[int, int]:
    try:
        i, n = (int(v) for v in value.split("/"))
    except ValueError:
        raise ConfigError(f"--shard: expected I/N (e.g. 0/4), got '{value}'") from None
    if not (1 <= n <= MAX_SHARDS and 0 <= i < n):
        raise ConfigError(f"--shard: need 1 <= N <= {MAX_SHARDS:,} and 0 <= I < N, got '{value}'")
    return i, n


@cli.command()
@click.argument("dataset", type=PathArg())
def index(dataset: Path) -> None:
    """Index a folder filled by --shard runs: metadata.json, manifest.parquet, dataset.json."""
    from .writer import index_dataset

    summary = index_dataset(dataset)
    click.echo(f"{dataset}: indexed {summary.scenes} scenes, {summary.frames} frames")


@cli.command()
@click.argument("out", type=PathArg())
@click.argument("sources", nargs=-1, required=True, type=PathArg())
def merge(out: Path, sources: tuple[Path, ...]) -> None:
    """Join datasets rendered by --shard I/N into separate folders (SOURCES) into OUT, indexed;
    the files equal a single run with the same seed. OUT may be one of the SOURCES."""
    from .merge import merge_datasets

    with reading():  # merge's messages name SOURCES and the scene themselves
        copied, summary = merge_datasets(out, list(sources))
    click.echo(
        f"{out}: merged {copied} scenes from {len(sources)} folders; "
        f"indexed {summary.scenes} scenes, {summary.frames} frames"
    )


@cli.command()
@click.argument("dataset", type=PathArg())
@click.option(
    "--format",
    "fmt",
    type=click.Choice(["webdataset"]),
    default="webdataset",
    show_default=True,
    help="webdataset: tar shards of whole scenes (docs/FORMAT.md, Packed shards).",
)
@click.option("--out", type=PathArg(), required=True, help="New or empty folder for the shards.")
@click.option(
    "--scenes-per-shard",
    type=int,
    default=100,
    show_default=True,
    help="Scenes per tar shard (a split's last shard may hold fewer).",
)
def pack(dataset: Path, fmt: str, out: Path, scenes_per_shard: int) -> None:
    """Pack a finished dataset into tar shards of whole scenes, with index.json (checksums);
    read them with stillbox_gen.packed."""
    from .pack import pack_webdataset

    with reading("DATASET"):
        summary = pack_webdataset(dataset, out, scenes_per_shard)
    click.echo(
        f"{out}: packed {summary.scenes} scenes into {summary.shards} shards "
        f"({summary.bytes / 1e6:.1f} MB)"
    )


def build_config(o: dict) -> config.DatasetConfig:
    """The dataset config of the generate options ``o``: the preset with the flags' values
    (config.Flag: each sets its fields) over it, validated (ConfigError naming the flag, or the
    preset file and key)."""
    cfg = config.load_preset(o["preset"])
    if o["fov"] is not None and o["focal"] is not None:
        raise ConfigError("--fov and --focal: give one or the other")
    sections: dict[str, dict] = {name: {} for name in config.SECTIONS}
    if o["quality"]:
        sections["render"].update(config.QUALITY[o["quality"]])
    top: dict = {}
    for key, fl in config.config_flags().items():
        value = o[_dest(fl)]
        if key == "preset" or value is None or value is False:  # not given
            continue
        section, _, name = key.rpartition(".")
        value = fl.parse(value) if fl.parse else value
        names = fl.fields or (name,)
        updates = dict(zip(names, value if len(names) > 1 else (value,), strict=True))
        (sections[section] if section else top).update({**updates, **dict(fl.also)})
    cfg = dataclasses.replace(config.replace(cfg, **sections), **top)
    given = {f"{section}.{key}" for section, values in sections.items() for key in values}
    config.validate(cfg, origin=config.preset_origin(o["preset"]), given=given)
    if cfg.objects.fixed is not None:  # its camera path against its surfaces, before any file
        from .scene import sample_scene

        sample_scene(cfg, 0)  # the same layout at every index: ConfigError if the path hits it
    return cfg


@cli.command()
@click.argument("dataset", type=PathArg())
@click.option(
    "--quick",
    is_flag=True,
    help="Check structure and metadata only, not every file's checksum and pixels.",
)
def validate(dataset: Path, quick: bool) -> None:
    """Check a dataset against the documented format and its records' checksums; list problems
    by file (exit 1 if any)."""
    from .validate import validate_dataset

    if not dataset.is_dir():
        raise ConfigError(f"DATASET: '{dataset}' is not a folder")
    problems, stats = validate_dataset(dataset, check_pixels=not quick)
    for p in problems:
        click.echo(p)
    for note in stats["notes"]:
        click.echo(f"note: {note}")
    if problems:
        click.echo(f"{dataset}: {len(problems)} problem(s)", err=True)
        sys.exit(1)
    click.echo(
        f"{dataset}: valid ({stats['scenes']} scenes, {stats['frames']} frames, "
        f"{stats['rows']} manifest rows)"
    )


@cli.command()
@click.argument("dataset", type=PathArg())
@click.option(
    "--out",
    type=PathArg(),
    default=Path("preview.png"),
    show_default=True,
    help="PNG contact sheet to write.",
)
@click.option(
    "--scenes", type=int, default=4, show_default=True, help="Number of scenes shown (first ones)."
)
@click.option(
    "--max-depth",
    type=float,
    default=MAX_DEPTH,
    show_default=True,
    help="Top of the depth colour scale, metres.",
)
def preview(dataset: Path, out: Path, scenes: int, max_depth: float) -> None:
    """Draw a contact sheet: first and last frame of a few scenes, with colour-mapped depth."""
    from .dataset import Dataset
    from .preview import contact_sheet

    with reading("DATASET"):
        ds = Dataset(dataset)
        ds.indices()  # a dataset without manifest.parquet is refused before the flags
        if scenes < 1:
            raise ConfigError(f"--scenes: must be at least 1, got {scenes}")
        if not (max_depth > 0 and math.isfinite(max_depth)):
            raise ConfigError(f"--max-depth: must be a positive finite number, got {max_depth}")
        check_out_file(out)
        contact_sheet(ds, out, scenes, max_depth)
    click.echo(f"wrote {out}")


@cli.command()
@click.argument("dataset", type=PathArg())
@click.option(
    "--scenes",
    type=int,
    default=200,
    show_default=True,
    help="Measure the first N scenes (all when fewer).",
)
@click.option(
    "--shift",
    type=int,
    default=NOMINAL_SHIFT,
    show_default=True,
    help="Nominal frame shift S: flow and residuals on pairs (i, i+S).",
)
@click.option(
    "--flicker",
    type=int,
    default=0,
    show_default=True,
    help="Re-render the pose of frame 0 of the first K scenes with Blender, as another frame of "
    "its scene (same-pose flicker) and with another scene seed, against the stored frames.",
)
@click.option(
    "--out",
    type=PathArg(),
    help="Folder for stats.json and stats.png.  [default: DATASET]",
)
@click.option(
    "--max-depth",
    type=float,
    default=MAX_DEPTH,
    show_default=True,
    help="Top of the depth histogram in stats.json / stats.png, metres.",
)
def stats(dataset: Path, scenes: int, shift: int, flicker: int, out, max_depth: float) -> None:
    """Data-quality report: depth bands, walls vs objects, true flow, photometric residuals
    (and render flicker), beside StillBox's published figures; writes stats.json, stats.png."""
    from .stats.report import table
    from .stats.run import run

    with reading("DATASET"):
        result = run(dataset, scenes, shift, flicker, out, max_depth, progress=True)
    click.echo(table(result))
    where = out or dataset
    click.echo(f"wrote {where / 'stats.json'} and {where / 'stats.png'}", err=True)


@cli.command()
@click.option(
    "--res",
    "resolutions",
    default="64:40,128:16,256:6",
    show_default=True,
    help="Comma-separated PIXELS:SCENES pairs (square frames).",
)
@click.option(
    "--configs",
    default="fast,default,high,plain",
    show_default=True,
    help="Render configurations: quality levels and 'plain' (8 samples, 1 bounce, no denoiser).",
)
@click.option(
    "--workers",
    type=int,
    default=_run_default("workers"),
    show_default=True,
    help="Blender worker processes.",
)
@click.option(
    "--threads",
    type=int,
    default=_run_default("threads"),
    show_default=True,
    help="Cycles threads per worker (0 = all cores).",
)
@click.option(
    "--psnr-scenes",
    type=int,
    default=2,
    show_default=True,
    help="Scenes whose first and last frames are re-rendered with 256 samples for PSNR.",
)
@_DEVICE
@click.option("--csv", "csv_path", type=PathArg(), help="Also write the table here.")
@click.option(
    "--profile",
    is_flag=True,
    help="After each timed run, print where its time went per frame (phases of the workers "
    "and the driver, wall and CPU ms; Cycles' sync, sampling and result apart).",
)
def bench(
    resolutions: str,
    configs: str,
    workers: int,
    threads: int,
    psnr_scenes: int,
    device: str,
    csv_path,
    profile: bool,
) -> None:
    """Measure frames/s (whole process) and PSNR per resolution and configuration."""
    import tempfile

    from . import bench as b
    from .workers import choose_device

    pairs = []
    for item in resolutions.split(","):
        try:
            px, n = (int(v) for v in item.split(":"))
        except ValueError:
            raise ConfigError(f"--res: expected PIXELS:SCENES pairs, got '{item}'") from None
        if px <= 0 or n <= 0:
            raise ConfigError(f"--res: pixels and scenes must be positive, got '{item}'")
        for key, value in (("camera.width", px), ("scenes", n)):
            if problem := config.limit_problem(key, value):
                raise ConfigError(f"--res: {problem} ('{item}')")
        pairs.append((px, n))
    names = [n.strip() for n in configs.split(",") if n.strip()]
    b.configurations(names)  # fails early on unknown names
    if workers < 1 or psnr_scenes < 1:
        raise ConfigError("--workers and --psnr-scenes: must be at least 1")
    if threads < 0:
        raise ConfigError(f"--threads: must be >= 0, got {threads}")
    for flag, value in (("workers", workers), ("threads", threads)):
        if problem := config.limit_problem(flag, value):
            raise ConfigError(f"--{flag}: {problem}")
    device, device_line = choose_device(device)
    click.echo(f"environment: {generate_versions()}, {os.cpu_count()} CPUs", err=True)
    click.echo(device_line, err=True)
    with tempfile.TemporaryDirectory(prefix="stillbox-bench-") as tmp:
        rows = b.run_bench(
            pairs, names, workers, psnr_scenes, Path(tmp), click.echo, device, profile, threads
        )
    click.echo(b.markdown_table(rows))
    if rows:
        click.echo(b.reference_line(rows))
    if csv_path:
        b.write_csv(rows, csv_path)
        click.echo(f"wrote {csv_path}", err=True)


def check_out_file(out: Path, flag: str = "--out") -> None:
    """A file to write: not a folder, in an existing folder (ConfigError naming ``flag``)."""
    if out.is_dir():
        raise ConfigError(f"{flag}: '{out}' is a folder; give a file name such as preview.png")
    if not out.parent.is_dir():
        raise ConfigError(f"{flag}: the folder of '{out}' does not exist")
    dataset = enclosing_dataset(out.parent)
    if dataset is not None:  # `validate` would then report a stray file
        raise ConfigError(f"{flag}: '{out}' is inside the dataset '{dataset}'; write elsewhere")


def generate_versions() -> str:
    from .writer import versions

    return ", ".join(f"{k} {v}" for k, v in versions().items())


@contextlib.contextmanager
def reading(argument: str | None = None):
    """A DatasetError inside the block becomes a ConfigError (a one-line user error) naming
    ``argument``, the command line's name of the dataset: ``DATASET: '...' has no
    manifest.parquet``. Without ``argument``, the message is kept as it is."""
    try:
        yield
    except DatasetError as e:
        raise ConfigError(f"{argument}: {e}" if argument else str(e)) from None


def main(argv: list[str] | None = None) -> None:
    try:
        with sigterm_as_interrupt():
            cli.main(args=argv, prog_name="stillbox-gen", standalone_mode=False)
    except (ConfigError, click.UsageError) as e:
        message = e.format_message() if isinstance(e, click.ClickException) else str(e)
        click.echo(f"stillbox-gen: error: {message}", err=True)
        sys.exit(2)
    except (click.exceptions.Abort, KeyboardInterrupt) as e:  # click turns Ctrl-C into Abort
        click.echo("stillbox-gen: interrupted; re-run the same command to resume", err=True)
        terminated = isinstance(e, Terminated) or isinstance(e.__cause__, Terminated)
        sys.exit(128 + signal.SIGTERM if terminated else 130)
    except RuntimeError as e:
        click.echo(f"stillbox-gen: failed: {e}", err=True)
        sys.exit(1)
    except OSError as e:
        if not is_disk_full(e):
            raise
        click.echo(f"stillbox-gen: failed: {disk_full_message(e)}", err=True)
        sys.exit(1)


if __name__ == "__main__":
    main()
