"""``stillbox-bench`` commands of closed-loop flight (thesis 6.5, in simulation): fly (one depth
source over the episodes of a seed) and fly-compare (one table of several fly runs).

benchmark.flight (which samples scenes with the generator's config) is imported inside the
commands only: importing the command line loads the data contract alone (tests/test_imports.py).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import click

from stillbox_gen.arguments import check_out_folder
from stillbox_gen.errors import ConfigError

from ..core import registry, runfolder
from ..core.errors import FieldError
from ..flight.choices import MAX_STEPS, RENDERERS, YAW_MODES
from .limits import FLOAT, RESOLUTION
from .options import (
    DATA_OPTION,
    DEVICE_OPTION,
    UserError,
    dataset_dir,
    int_option,
    is_default,
    locked_out,
    setting_option,
    torch_device,
    training_settings,
    user_error,
)
from .supervised import check_comparison_out

BUILT_IN = ("oracle", "constant")
THREADS_OPTION = setting_option("threads", "run")
#: config.json entries a resumed run may change
RESUMABLE = ("episodes", "device")


def _check_out(out: Path, resume: bool) -> dict | None:
    """--out (before anything starts): a folder, not a finished run, an unfinished fly run only
    with --resume; returns the unfinished run's config.json (None for a new run)."""
    check_out_folder(out, error=UserError)
    try:
        config = runfolder.read_config(out)
    except ValueError as e:
        raise UserError(f"--out: {e}") from None
    if runfolder.has_summary(out):
        raise UserError(f"--out: '{out}' already holds a finished run; choose another --out")
    if config is not None and not resume:
        raise UserError(f"--out: '{out}' holds an unfinished fly run; add --resume to continue it")
    if resume and config is None:
        raise UserError("--resume: give the --out folder of an unfinished fly run")
    if out.is_dir() and config is None and any(p.name != ".stillbox.lock" for p in out.iterdir()):
        raise UserError(f"--out: '{out}' is not empty and holds no fly run")
    return config


def _checkpoint_kind(path: Path) -> registry.Kind:
    from ..core.checkpoint import load_checkpoint

    try:
        ck = load_checkpoint(path, "depth")
    except ValueError as e:
        raise user_error(e) from None
    return registry.MODELS[ck["model_name"]].kind


def _constant_depth(value: float | None, data: Path, rule: str | None = None) -> tuple[float, str]:
    """--constant-depth, else the median depth of --data's training split (as compare's
    ``constant``); (metres, how it was obtained)."""
    if value is not None:  # within limits.LIMITS (or a resumed run's, with its ``rule``)
        return value, rule or CONSTANT_GIVEN
    from ..core.data import load_scenes
    from ..engine.runner import median_depth

    try:
        depth, frames = median_depth(load_scenes(dataset_dir(data), "train"))
    except ValueError as e:
        raise user_error(e) from None
    return depth, f"median of the training split of {data} over {frames} frames"


def _source(o: dict, res: tuple[int, int], device) -> tuple[object, dict]:
    """The depth source of --depth and what config.json records of it."""
    from ..flight import simulate, sources
    from ..flight.episodes import flight_scene_config

    depth: str = o["depth"]
    if depth == "oracle":
        return simulate.oracle, {"depth_kind": "oracle"}
    if depth == "constant":
        value, rule = _constant_depth(o["constant_depth"], o["data"], o.get("constant_rule"))
        return simulate.constant(value), {
            "depth_kind": "constant", "constant_depth_m": value, "constant_rule": rule,
        }  # fmt: skip
    path = Path(depth)
    if not path.is_file():
        raise UserError(f"--depth: expected oracle, constant or a checkpoint file, got '{depth}'")
    if o["renderer"] not in ("blender",):
        raise UserError(
            f"--renderer {o['renderer']}: renders depth only, no image for the network of "
            f"--depth '{depth}' (use --renderer blender)"
        )
    kind = _checkpoint_kind(path)
    camera = flight_scene_config(width=res[0], height=res[1]).camera
    try:
        if kind.scored_as is registry.Scoring.FLOW:
            src = sources.FlowDepth(path, device, camera.K())
            return src, {"depth_kind": "flow network", **src.info}
        if res[0] % 64 or res[1] % 64:
            w, h = res
            raise UserError(f"--res: the network needs multiples of 64 pixels, got {w}x{h}")
        src = sources.NetworkDepth(path, device, o["shifts"])
    except ValueError as e:
        raise user_error(e) from None
    fov = src.info["fov_deg"]
    if abs(fov - camera.fov_deg) > 0.01:
        raise UserError(
            f"--depth: '{depth}' was trained with a {fov:g} deg camera; the flight camera's is "
            f"{camera.fov_deg:g} deg"
        )
    info = {k: src.info[k] for k in ("model_name", "depth_range", "clamp")}
    return src, {"depth_kind": "depth network", **info, "nominal_displacement_m": src.scale.d0}


@click.command("fly")
@click.option(
    "--depth",
    help="Depth source: oracle (the rendered depth), constant, or a checkpoint written by "
    "'run' (a depth network through the infer pipeline, or a flow network: depth from flow).  "
    "[required; --resume: the run's]",
)
@click.option(
    "--out",
    type=click.Path(path_type=Path),
    required=True,
    help="Run folder: config.json, episodes/, episodes.csv, plots/, summary.json.",
)
@int_option("--episodes", 20, "Episodes to fly (0 .. N-1 of --seed: the same for every source).")
@int_option("--seed", 0, "Seed of the episodes (scenes, starts and goals).")
@click.option(
    "--res",
    type=RESOLUTION,
    default="64",
    show_default=True,
    help="Camera frames, N or WxH pixels.",
)
@click.option(
    "--renderer",
    type=click.Choice(RENDERERS),
    default="blender",
    show_default=True,
    help="blender: a persistent Blender worker, the dataset's renderer (needs the gen extra); "
    "analytic: exact depth of the primitives, no image (oracle and constant only).",
)
@int_option("--shifts", 1, "A depth network's frame pairs per frame (infer --shifts, 1..4).")
@click.option(
    "--constant-depth",
    type=FLOAT,
    help="Depth (m) of --depth constant.  [default: the median depth of --data's training split]",
)
@DATA_OPTION
@click.option(
    "--yaw",
    type=click.Choice(YAW_MODES),
    default="line",
    show_default=True,
    help="line: the camera keeps the heading of the straight line (frames differ by a "
    "translation, as the networks were trained); goal: it turns towards the goal.",
)
@int_option("--max-steps", MAX_STEPS, "Control steps before an episode times out.")
@click.option("--resume", is_flag=True, help="Continue the unfinished run in --out.")
@DEVICE_OPTION
@THREADS_OPTION
@click.option("--quiet", is_flag=True, help="No progress bar.")
def fly_cmd(**o) -> None:
    """Fly the episodes of --seed with one depth source and a predictive controller (thesis
    6.5); collisions are checked against the scene's true geometry."""
    import torch

    from ..flight.run import describe
    from ..flight.simulate import FlightConfig

    out: Path = o["out"]
    earlier = _check_out(out, o["resume"])
    if earlier is not None:
        _keep_recorded(o, earlier)
    if o["depth"] is None:
        raise UserError("--depth: missing (oracle, constant or a checkpoint file)")
    res: tuple[int, int] = o["res"]
    _check_numbers(o)
    settings = training_settings({"device": o["device"], "threads": o["threads"]})
    _check_renderer(o["renderer"])
    if settings["threads"] > 0:
        torch.set_num_threads(settings["threads"])
    learned = o["depth"] not in BUILT_IN
    device = torch_device(settings["device"]) if learned else torch.device("cpu")
    source, described = _source(o, res, device)
    flight = FlightConfig(yaw=o["yaw"], max_steps=o["max_steps"])
    config = _jsonable({
        "depth": o["depth"], **described, "episodes": o["episodes"], "seed": o["seed"],
        "res": list(res), "renderer": o["renderer"], "shifts": o["shifts"],
        "device": o["device"], "flight": dataclasses.asdict(flight),
    })  # fmt: skip
    if earlier is not None:
        _check_resumed(out, earlier, config)
    summary = _fly(out, config, source, flight, earlier is None, not o["quiet"])
    click.echo(describe(summary, out))


#: options and the config.json entries that record them: an option left out of --resume takes
#: the run's value (--constant-depth: below; --data is recorded only inside constant_rule)
RECORDED = {
    "depth": "depth", "episodes": "episodes", "seed": "seed", "res": "res",
    "renderer": "renderer", "shifts": "shifts", "yaw": "flight.yaw",
    "max_steps": "flight.max_steps", "device": "device",
}  # fmt: skip
CONSTANT_GIVEN = "given with --constant-depth"


def _keep_recorded(o: dict, earlier: dict) -> None:
    """``o`` with the resumed run's values (config.json ``earlier``) for the options not given
    again; a --depth constant run keeps its depth (given, or the median of its --data) unless
    --constant-depth or --data is given again."""
    then = _flat(earlier)
    for name, key in RECORDED.items():
        given = o[name] is not None if name == "depth" else not is_default(name)
        if key in then and not given:
            o[name] = tuple(then[key]) if name == "res" else then[key]
    constant = o["depth"] == "constant" and then.get("depth_kind") == "constant"
    if constant and is_default("constant_depth") and is_default("data"):
        o["constant_depth"] = then.get("constant_depth_m")
        o["constant_rule"] = then.get("constant_rule")


def _check_numbers(o: dict) -> None:
    """--shifts and --constant-depth against --depth (their ranges: limits.LIMITS)."""
    if o["depth"] in BUILT_IN and not is_default("shifts"):
        raise UserError("--shifts: only for a depth network's checkpoint (--depth PATH)")
    if o["constant_depth"] is not None and o["depth"] != "constant":
        raise UserError("--constant-depth: only with --depth constant")
    if not is_default("data") and (o["depth"] != "constant" or o["constant_depth"] is not None):
        raise UserError(
            "--data: only with --depth constant (its median depth) and no --constant-depth"
        )


def _check_renderer(kind: str) -> None:
    """--renderer blender needs bpy: one line naming the gen extra otherwise."""
    from ..flight.render import check_renderer

    try:
        check_renderer(kind)
    except ConfigError as e:
        raise UserError(f"--renderer {kind}: {e}") from None


#: config.json entries set by a flag not named after them (the rest: "--" + their name, or
#: none for the flight model's constants)
FLAG_OF = {
    "flight.yaw": "--yaw",
    "flight.max_steps": "--max-steps",
    **dict.fromkeys(
        ("depth_kind", "model_name", "depth_range", "clamp", "nominal_displacement_m"), "--depth"
    ),
    **dict.fromkeys(("constant_depth_m", "constant_rule"), "--constant-depth"),
}


def _flat(config: dict, prefix: str = "") -> dict:
    """``{"flight": {"yaw": ...}}`` -> ``{"flight.yaw": ...}``."""
    flat = {}
    for k, v in config.items():
        if isinstance(v, dict):
            flat.update(_flat(v, f"{prefix}{k}."))
        else:
            flat[f"{prefix}{k}"] = v
    return flat


def _check_resumed(out: Path, earlier: dict, config: dict) -> None:
    """--resume continues a run of the same settings (but RESUMABLE's): the first one that
    differs is named by its flag (or its config.json name) with both values."""
    then, now = _flat(earlier), _flat(config)
    keys = [*now, *(k for k in then if k not in now)]  # config.json's order: --depth first
    changed = [k for k in keys if k not in RESUMABLE and then.get(k) != now.get(k)]
    if not changed:
        return
    key = changed[0]
    if key in FLAG_OF or "." not in key:
        name = FLAG_OF.get(key, "--" + key.replace("_", "-"))
        detail = "" if name == "--" + key.replace("_", "-") else f" ({key})"
    else:  # a constant of the flight model: no flag changes it
        name, detail = f"'{key}'", " (a constant of this version's flight model)"
    raise UserError(
        f"--resume: '{out}' was flown with {name}{detail} {then.get(key)!r}, not "
        f"{now.get(key)!r}; give the run's value or start a new --out"
    )


def _fly(out: Path, config: dict, source, flight, new: bool, progress: bool) -> dict:
    """flight.run.fly_run holding --out's lock; a new run stopped before its first episode
    leaves nothing behind (no run to resume)."""
    from stillbox_gen.lock import folder_lock

    from ..flight.run import fly_run
    from ..flight.sources import Scored

    try:
        with folder_lock(out, "--out"):
            runfolder.write_config(out, config)
            try:
                return fly_run(
                    out, config, Scored(source, flight.sensing.max_range), flight, progress=progress
                )
            except BaseException:
                if new and not runfolder.read_episodes(out):
                    (out / runfolder.CONFIG_JSON).unlink()
                raise
    except ConfigError as e:
        raise UserError(str(e)) from None
    except FieldError as e:
        raise user_error(e) from None


def _jsonable(value):
    """Tuples as lists (what config.json reads back as), recursively."""
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    return value


@click.command("fly-compare")
@click.argument("runs", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option(
    "--out",
    type=click.Path(path_type=Path),
    help="Writes OUT.md and OUT.csv.  [default: fly-comparison beside the first run]",
)
def fly_compare(runs: tuple[Path, ...], out: Path | None) -> None:
    """One table of fly runs (one row per run): success rate and its 95 % interval, collisions,
    timeouts, clearance, path ratio, the depth error of each source and time per step."""
    from ..flight.summary import comparison_markdown, comparison_row

    rows = []
    for run in runs:
        try:
            rows.append(comparison_row(str(run), runfolder.read_flight_summary(run)))
        except ValueError as e:
            raise UserError(f"RUN: {e}") from None
    out = out if out is not None else runs[0].parent / "fly-comparison"
    paths = runfolder.comparison_paths(out)
    check_comparison_out(out)
    md = comparison_markdown(rows)
    with locked_out(out.parent):  # the folder of OUT.md and OUT.csv, as report's
        try:
            runfolder.write_comparison(out, md, runfolder.csv_text(rows))
        except ValueError as e:
            raise user_error(e) from None
    click.echo(md, nl=False)
    click.echo(f"table in {paths['md']} and {paths['csv']}")
