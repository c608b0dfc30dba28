"""``stillbox-bench`` commands of thesis chapter 3: list, run, eval, report, compare, speed."""

from __future__ import annotations

import time
from pathlib import Path

import click

from stillbox_gen.arguments import check_out_folder, unwritable

from ..core import registry
from ..core.config import EVAL_BATCH_SIZE, default
from ..core.models import count_parameters
from ..core.runfolder import (
    COMPARISON,
    SUMMARY_JSON,
    SUMMARY_MD,
    checkpoint_path,
    comparison_paths,
    has_summary,
)
from ..supervised import speed as speed_table
from .limits import FLOAT, INTS
from .options import (
    DATA_OPTION,
    DEVICE_OPTION,
    PREDICTIONS_OPTION,
    UserError,
    dataset_dir,
    int_option,
    is_default,
    locked_out,
    model_names,
    setting_options,
    torch_device,
    training_settings,
    user_error,
)

#: run's setting options in the --help order they have always had; a new TrainConfig setting
#: with a flag needs no entry here: it follows them
RUN_HELP_ORDER = (
    "epochs", "max_steps", "batch_size", "lr", "device", "threads", "seed", "pretrained", "resume",
    "ckpt_every", "log_every", "shift", "depth_range", "channels_last", "compile", "amp",
    "save_predictions", "progress",
)  # fmt: skip


@click.command("list")
def list_cmd() -> None:
    """Registered models with their parameter counts."""
    width = max(map(len, registry.list_models()))
    for name in registry.list_models():
        spec = registry.MODELS[name]
        if spec.trainable:
            n = f"{count_parameters(spec.build()) / 1e6:7.2f} M parameters"
        else:
            n = f"{'no network':>20s}"
        click.echo(f"{name:{width}s} {n}  {spec.description}")


@click.command()
@click.argument("model")
@DATA_OPTION
@click.option(
    "--out",
    type=click.Path(path_type=Path),
    help="Run folder.  [default: runs/<model>-<dataset>-<time>]  A folder holding "
    "checkpoints/last.pt needs --resume (or another --out); the logs of a run killed before "
    "its first checkpoint are replaced, as there is nothing to resume.",
)
@setting_options("run", RUN_HELP_ORDER)
def run(model: str, data: Path, out: Path | None, **o) -> None:
    """Train MODEL on the train split, then score the best checkpoint and write a report.

    Methods without a network (oracle-flow, constant) are scored directly; training options are
    ignored for them.
    """
    if model not in registry.MODELS:
        known = ", ".join(registry.list_models())
        raise UserError(f"MODEL: unknown '{model}' (registered: {known})")
    data = dataset_dir(data)
    trainable = registry.MODELS[model].trainable
    if o["resume"] and (out is None or not checkpoint_path(out, "last").is_file()):
        raise UserError(
            "--resume: give the --out folder of an earlier run (with checkpoints/last.pt)"
        )
    if out is None:
        out = Path("runs") / f"{model}-{data.resolve().name}-{time.strftime('%Y%m%d-%H%M%S')}"
    check_out_folder(out, error=UserError)
    if not o["resume"] and checkpoint_path(out, "last").exists():
        raise UserError(f"--out: '{out}' already holds a run; add --resume or choose another --out")
    if o["resume"] and is_default("seed"):
        o["seed"] = None  # the run's own (runner.train_config)
    settings = training_settings(o)  # --clamp's range and --shift: Trainer.setup
    if o["pretrained"] is not None and not o["pretrained"].is_file():
        raise UserError(f"--pretrained: no such file '{o['pretrained']}'")
    if not trainable and (o["pretrained"] or o["resume"]):
        raise UserError(f"MODEL: '{model}' has no network (no --pretrained or --resume)")
    summary = _run_one(model, data, out, settings)
    if summary is None:
        return
    m = summary["metrics"]
    epe = f", EPE {m['epe']:.3f} px" if "epe" in m else ""
    click.echo(
        f"{model}: MAE {m['mae']:.3f} m, MRE {m['mre']:.3f}, MLE {m['mle']:.3f}, "
        f"depth error {m['depth_error']:.3f} m{epe}{_gt_scaled(m)} on {summary['split']} "
        f"({m['images']} pairs); report in {out / SUMMARY_MD}"
    )


def _gt_scaled(m: dict) -> str:
    """A scale-free depth's (sfmlearner's) scores with the ground truth's median scale ("GT";
    the others are with PoseNet's, "P"), or "" for other methods."""
    if "gt_mae" not in m:
        return ""
    return f" (P scale; GT median scale: MAE {m['gt_mae']:.3f} m, MRE {m['gt_mre']:.3f})"


def _run_one(model: str, data: Path, out: Path, settings: dict) -> dict | None:
    """runner.run_method with TrainConfig ``settings`` from the command line (training_settings;
    those a command lacks take TrainConfig's defaults); ValueError -> UserError."""
    from ..engine.runner import run_method

    try:
        return run_method(model, data, out, **settings)
    except ValueError as e:
        raise user_error(e) from None


@click.command("eval")
@click.option(
    "--ckpt",
    type=click.Path(path_type=Path),
    help="Checkpoint (.pt) written by 'run'.",
)
@click.option(
    "--predictions",
    type=click.Path(path_type=Path),
    help="Folder of another method's depth maps, the dataset's layout: "
    "<chunk>/depth_<s>_<f>.npy (float32 metres) or .png (16-bit, depth × 256); docs/RUNS.md.",
)
@click.option(
    "--model",
    "user_model",
    metavar="MODULE:CALLABLE",
    help="Your own network: a function (in an importable module or a file.py) that returns a "
    "torch.nn.Module with its weights; contract in benchmark/core/contract.py.",
)
@DATA_OPTION
@click.option(
    "--split",
    type=click.Choice(["train", "val", "test"]),
    default="test",
    show_default=True,
    help="Split to score (test falls back to val when empty).",
)
@click.option(
    "--out",
    type=click.Path(path_type=Path),
    help="Report folder.  [default: --ckpt: <ckpt folder>/../eval-<dataset>-<split>; "
    "--predictions: beside it, eval-<its name>-<dataset>-<split>; --model: "
    "eval-<callable>-<dataset>-<split>]",
)
@click.option(
    "--median-scaling",
    is_flag=True,
    help="Multiply each depth map by median(ground truth) / median(map) before scoring "
    "(methods that know depth only up to a scale).",
)
@click.option(
    "--displacement",
    type=FLOAT,
    help="--model: metres of camera motion its depth answers for.  [default: 3 frames of the "
    "split's median motion per frame, what a network trained here answers for]",
)
@int_option("--batch-size", EVAL_BATCH_SIZE, "Pairs per forward pass (does not change results).")
@DEVICE_OPTION
@PREDICTIONS_OPTION
def eval_cmd(
    ckpt: Path | None,
    predictions: Path | None,
    user_model: str | None,
    data: Path,
    split: str,
    out: Path | None,
    median_scaling: bool,
    displacement: float | None,
    batch_size: int,
    device: str,
    save_predictions: bool,
) -> None:
    """Score a checkpoint, another method's depth files or your own network on a dataset split
    (writes summary.json/.md, per_sample.csv, plots). A checkpoint is scored on frames of the
    size it was trained on."""
    given = [f for f, v in (("--ckpt", ckpt), ("--predictions", predictions),
                            ("--model", user_model)) if v is not None]  # fmt: skip
    if len(given) != 1:
        raise UserError(
            "give one of --ckpt, --predictions, --model"
            + (f" (got {' and '.join(given)})" if given else "")
        )
    if displacement is not None and user_model is None:
        raise UserError("--displacement: only with --model")
    if save_predictions and predictions is not None:
        raise UserError("--save-predictions: not with --predictions (they are the input)")
    if ckpt is not None and not ckpt.is_file():
        raise UserError(f"--ckpt: no such file '{ckpt}'")
    data = dataset_dir(data)
    name = data.resolve().name
    if ckpt is not None:
        out = out or ckpt.resolve().parent.parent / f"eval-{name}-{split}"
    elif predictions is not None:
        out = out or predictions.resolve().parent / f"eval-{predictions.name}-{name}-{split}"
    else:
        out = out or Path(f"eval-{user_model.rpartition(':')[2]}-{name}-{split}")
    check_out_folder(out, error=UserError)
    for flag, folder in (("--data", data), ("--predictions", predictions)):
        if folder is not None and out.resolve().is_relative_to(folder.resolve()):
            raise UserError(
                f"--out: '{out}' is inside {flag} '{folder}'; write the report elsewhere"
            )
    from ..engine import runner

    # checks the method and the data before anything is written to --out (its lock aside)
    with locked_out(out):
        try:
            if ckpt is not None:
                s = runner.score_checkpoint(
                    ckpt, data, split, out, device, batch_size, save_predictions,
                    median_scaling=median_scaling,
                )  # fmt: skip
            elif predictions is not None:
                s = runner.score_predictions(
                    predictions, data, split, out, batch_size, median_scaling
                )
            else:
                s = runner.score_user_model(
                    user_model, data, split, out, device, batch_size, displacement,
                    median_scaling, save_predictions,
                )  # fmt: skip
        except ValueError as e:
            raise user_error(e) from None
    m = s["metrics"]
    click.echo(
        f"{s['model']}: MAE {m['mae']:.3f} m, MRE (AbsRel) {m['mre']:.3f}, MLE {m['mle']:.3f}, "
        f"RMSE {m['sae']:.3f} m, δ<1.25 {m['p1.25']:.3f}{_gt_scaled(m)} on {s['split']} "
        f"({m['images']} pairs); report in {out / SUMMARY_MD}"
    )


@click.command()
@click.argument("runs", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option(
    "--out",
    type=click.Path(path_type=Path),
    default=Path("report"),
    show_default=True,
    help="Writes OUT.md, OUT.csv and OUT-error_vs_foe_distance.png.",
)
def report(runs: tuple[Path, ...], out: Path) -> None:
    """One comparison table (markdown + CSV) of several runs' summary.json, and one figure of
    error vs distance to the focus of expansion with every run on it."""
    missing = [str(r) for r in runs if not has_summary(r)]
    if missing:
        raise UserError(f"RUNS: no {SUMMARY_JSON} in {', '.join(missing)}")
    check_comparison_out(out)
    with locked_out(out.parent):  # the folder of OUT.md, OUT.csv and the figure
        click.echo(_comparison(list(runs), out))


def check_comparison_out(out: Path, flag: str = "--out") -> None:
    """The files of a comparison named ``out`` (runfolder.comparison_paths: OUT.md, OUT.csv and
    the figure) can be written, checked before any work: none of them is a folder, and their
    folder can be made. UserError naming ``flag`` otherwise."""
    for path in comparison_paths(out).values():
        if path.exists() and not path.is_file():
            raise UserError(f"{flag}: '{path}' is a folder, not a file")
    if problem := unwritable(Path(out).parent):
        raise UserError(f"{flag}: {problem}")


def _comparison(runs: list[Path], out: Path) -> str:
    """report.write_comparison, shared by report and compare: an unreadable summary.json or
    pixels.npz, or an --out not made, is one line (UserError), never a traceback."""
    from ..engine.report import write_comparison

    try:
        return write_comparison(runs, out)
    except ValueError as e:
        raise user_error(e) from None


@click.command()
@DATA_OPTION
@click.option(
    "--models",
    "names",
    default="depthnet,flownets-depth,flownets-flow,oracle-flow,constant",
    show_default=True,
    help="Comma-separated registered methods.",
)
@click.option(
    "--out",
    type=click.Path(path_type=Path),
    help="Folder: one run folder per method + comparison.{md,csv} and the FOE figure.  "
    "[default: runs/compare-<dataset>-<time>]",
)
@setting_options("compare")
def compare(data: Path, names: str, out: Path | None, **o) -> None:
    """Run every method of --models on --data (reusing finished runs in --out), then write one
    comparison table and one error-vs-FOE-distance figure with every method."""
    chosen = model_names(names)
    data = dataset_dir(data)
    settings = training_settings(o)
    if out is None:
        out = Path("runs") / f"compare-{data.resolve().name}-{time.strftime('%Y%m%d-%H%M%S')}"
    check_out_folder(out, error=UserError)
    # one compare per --out at a time (each method's run folder holds its own lock too)
    click.get_current_context().with_resource(locked_out(out))
    runs = []
    for name in chosen:
        run_dir = out / name
        if has_summary(run_dir):
            click.echo(f"{name}: reusing {run_dir}")
        else:
            if checkpoint_path(run_dir, "last").exists():
                raise UserError(
                    f"--out: '{run_dir}' holds an unfinished run; finish it with "
                    f"'stillbox-bench run {name} --resume --out {run_dir}' or remove it"
                )
            click.echo(f"{name}: running into {run_dir}")
            _run_one(name, data, run_dir, settings)
        runs.append(run_dir)
    click.echo(_comparison(runs, out / COMPARISON))
    click.echo(f"comparison in {comparison_paths(out / COMPARISON)['md']}")


def _multiples_of_64(option: str, values: tuple[int, ...]) -> tuple[int, ...]:
    """Square sizes (pixels, within limits.LIMITS) that the networks take: multiples of 64."""
    if any(v % 64 for v in values):
        shown = ",".join(map(str, values))
        raise UserError(f"{option}: sizes must be positive multiples of 64, got '{shown}'")
    return values


@click.command()
@click.option(
    "--models",
    "names",
    default=None,
    help="Comma-separated registered networks. [default: "
    + ",".join(speed_table.DEFAULT_MODELS)
    + "; with --train: "
    + ",".join(speed_table.TRAIN_MODELS)
    + "]",
)
@click.option(
    "--train",
    is_flag=True,
    help="Time training steps instead (forward, loss, backward, optimiser step): samples/s at "
    "--batches, on --data's training pairs or random batches at --time-res px.",
)
@click.option(
    "--batches",
    type=INTS,
    default=",".join(map(str, speed_table.TRAIN_BATCHES)),
    show_default=True,
    help="--train: comma-separated batch sizes.",
)
@click.option(
    "--data",
    type=click.Path(path_type=Path),
    default=None,
    help="--train: time on this dataset's training pairs (default: random inputs and targets).",
)
@click.option(
    "--baseline",
    is_flag=True,
    help="--train: also time the step with the speed levers off, alternating in the same run.",
)
@click.option(
    "--compile",
    "compile_",
    is_flag=True,
    help="--train: torch.compile the network (levers-on rows).",
)
@click.option(
    "--amp",
    is_flag=True,
    help="--train: also time the levers-on step under bfloat16 autocast (run's --amp), "
    "alternating in the same run; its ratio is against the float32 levers-on step.",
)
@click.option(
    "--resolutions",
    type=INTS,
    default=",".join(map(str, speed_table.DEFAULT_MAC_SIZES)),
    show_default=True,
    help="Square input sizes (px) for the GMAC columns.",
)
@int_option(
    "--time-res",
    speed_table.DEFAULT_TIME_SIZE,
    "Square input size (px) of the latency/throughput measurements.",
)
@int_option(
    "--warmup",
    speed_table.DEFAULT_WARMUP,
    "Untimed passes first (--train: steps; default 24 samples' worth, at least 1).",
)
@int_option(
    "--repeats",
    speed_table.DEFAULT_REPEATS,
    "Timed passes (median) (--train: steps; default 160 samples' worth, at least 3).",
)
@DEVICE_OPTION
@int_option("--threads", default("threads"), "Torch CPU threads.")
@click.option(
    "--out",
    type=click.Path(path_type=Path),
    default=Path("runs") / "speed",
    show_default=True,
    help="Folder of the CSV (named after device, threads and torch version).",
)
def speed(
    names: str | None,
    train: bool,
    batches: tuple[int, ...],
    data: Path | None,
    baseline: bool,
    compile_: bool,
    amp: bool,
    resolutions: tuple[int, ...],
    time_res: int,
    warmup: int,
    repeats: int,
    device: str,
    threads: int,
    out: Path,
) -> None:
    """Parameters, GMACs, batch-1 latency and batch-8 throughput of each network (Table 3.6);
    with --train, samples/s of training steps."""
    import torch

    if train:
        return _train_speed(
            names, batches, data, baseline, compile_, amp, time_res, device, threads, out
        )
    if data is not None:
        raise UserError("--data: only with --train (the sizes are timed on random inputs)")
    if amp:
        raise UserError("--amp: only with --train (the latency is timed in float32)")
    chosen = model_names(names or ",".join(speed_table.DEFAULT_MODELS))
    no_net = [n for n in chosen if not registry.MODELS[n].trainable]
    if no_net:
        raise UserError(f"--models: {', '.join(no_net)} ha(s) no network to time")
    sizes = _multiples_of_64("--resolutions", resolutions)  # the ranges: limits.LIMITS
    _multiples_of_64("--time-res", (time_res,))
    check_out_folder(out, error=UserError)
    dev = torch_device(device)
    if threads > 0:
        torch.set_num_threads(threads)
    path = out / speed_table.csv_name(dev)
    with locked_out(out):
        rows = speed_table.measure(chosen, dev, sizes, time_res, warmup=warmup, repeats=repeats)
        speed_table.write_csv(rows, path)
    click.echo(
        f"device {dev}, {torch.get_num_threads()} threads, torch {torch.__version__}; "
        f"timing at {time_res} px, median of {repeats} after {warmup} warm-up passes"
    )
    click.echo(speed_table.markdown(rows))
    click.echo(f"written to {path}")


def _train_speed(
    names, batches, data, baseline, compile_, amp, time_res, device, threads, out
) -> None:
    """speed --train: samples/s of training steps (benchmark.supervised.train_speed)."""
    import torch

    from ..core.data import DataError
    from ..supervised import train_speed

    chosen = model_names(names or ",".join(speed_table.TRAIN_MODELS))
    no_net = [n for n in chosen if not registry.MODELS[n].trainable]
    if no_net:
        raise UserError(f"--models: {', '.join(no_net)} ha(s) no network to train")
    sizes = batches  # each within limits.LIMITS
    _multiples_of_64("--time-res", (time_res,))
    ctx = click.get_current_context()
    given = {
        k: ctx.params[k]
        for k in ("warmup", "repeats")
        if ctx.get_parameter_source(k) is not click.core.ParameterSource.DEFAULT
    }
    if data is not None and not data.is_dir():
        raise UserError(f"--data: '{data}' is not a dataset folder")
    check_out_folder(out, error=UserError)
    dev = torch_device(device)
    if threads > 0:
        torch.set_num_threads(threads)
    path = out / train_speed.train_csv_name(dev)
    with locked_out(out):
        try:
            rows = train_speed.measure(
                chosen, dev, sizes, data, time_res, baseline, compile_, given.get("warmup"),
                given.get("repeats"), amp=amp,
            )  # fmt: skip
        except (ValueError, DataError) as e:
            raise user_error(e) from None
        speed_table.write_csv(rows, path)
    source = f"training pairs of {data}" if data is not None else "random inputs and targets"
    click.echo(
        f"training step (data, forward, loss, backward, optimiser step) on {source}; "
        f"device {dev}, {torch.get_num_threads()} threads, torch {torch.__version__}; median "
        "step time after warm-up"
        + ("; levers off = baseline, alternating" if baseline else "")
        + ("; bf16 = levers on under bfloat16 autocast, against levers on" if amp else "")
    )
    click.echo(train_speed.markdown(rows))
    click.echo(f"written to {path}")
