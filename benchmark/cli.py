"""``stillbox-bench``: train, score and compare depth-from-motion models on stillbox-gen data.

User mistakes print one line ``stillbox-bench: error: ...`` and exit with code 2.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

import click

from . import models


class UserError(click.ClickException):
    exit_code = 2


def _dataset_dir(data: Path) -> Path:
    if not (data / "manifest.parquet").is_file():
        raise UserError(
            f"--data: '{data}' is not a finished stillbox-gen dataset (no manifest.parquet)"
        )
    return data


def score_checkpoint(
    ckpt: Path,
    data: Path,
    split: str,
    out: Path,
    device: str,
    batch_size: int,
    save_predictions: bool,
    progress: bool = True,
) -> dict:
    """Evaluate a checkpoint on a split and write summary.json/.md, per_sample.csv, plots/."""
    from .data import FrameStore, PairDataset, load_scenes
    from .evaluate import evaluate
    from .report import write_run_report
    from .train import load_checkpoint, resolve_device

    ck = load_checkpoint(ckpt)
    name = ck["model_name"]
    model = models.build_model(name)
    model.load_state_dict(ck["model"])
    dev = resolve_device(device)
    model.to(dev)
    scenes = load_scenes(data, split)
    if not scenes and split == "test":
        split, scenes = "val", load_scenes(data, "val")
    if not scenes:
        raise UserError(f"--data: '{data}' has no scenes in split '{split}'")
    store = FrameStore(scenes, progress=progress)
    dataset = PairDataset(store, "eval", ck.get("shift", 3))
    t0 = time.perf_counter()
    result = evaluate(
        model,
        dataset,
        dev,
        batch_size,
        ck["nominal_displacement"],
        predictions_dir=out / "predictions" if save_predictions else None,
    )
    info = {
        "dataset": str(data),
        "split": split,
        "scenes": len(scenes),
        "shift": ck.get("shift", 3),
        "checkpoint": str(ckpt),
        "nominal_displacement": ck["nominal_displacement"],
        "training_state": ck.get("state"),
        "eval_seconds": round(time.perf_counter() - t0, 2),
    }
    return write_run_report(out, name, result, info)


DATA_OPTION = click.option(
    "--data",
    type=click.Path(path_type=Path),
    required=True,
    help="Dataset folder made by stillbox-gen.",
)
DEVICE_OPTION = click.option(
    "--device", default="auto", show_default=True, help="auto | cpu | cuda | cuda:N."
)
PREDICTIONS_OPTION = click.option(
    "--save-predictions",
    is_flag=True,
    help="Store predicted depth maps (float32 .npy, full resolution).",
)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def cli() -> None:
    """Train and score depth-from-motion baselines on stillbox-gen datasets.

    \b
    stillbox-bench run depthnet --data data/stillbox-64      train -> evaluate -> report
    stillbox-bench eval --ckpt runs/R/checkpoints/best.pt --data data/stillbox-64
    stillbox-bench report runs/*                             one comparison table
    stillbox-bench list                                      registered models
    """


@cli.command("list")
def list_cmd() -> None:
    """Registered models with their parameter counts."""
    for name in models.list_models():
        spec = models.MODELS[name]
        n = models.count_parameters(spec.build()) / 1e6
        click.echo(f"{name:16s} {n:7.2f} M parameters  {spec.description}")


@cli.command()
@click.argument("model")
@DATA_OPTION
@click.option(
    "--out",
    type=click.Path(path_type=Path),
    help="Run folder.  [default: runs/<model>-<dataset>-<time>]",
)
@click.option(
    "--epochs",
    type=int,
    help="Epochs (one sample per training frame each).  [default: model's, 55]",
)
@click.option("--max-steps", type=int, help="Stop after this many optimiser steps (smoke runs).")
@click.option("--batch-size", type=int, help="Samples per optimiser step.  [default: model's, 256]")
@click.option("--lr", type=float, help="Initial SGD learning rate.  [default: model's, 0.01]")
@DEVICE_OPTION
@click.option(
    "--threads",
    type=int,
    default=0,
    show_default=True,
    help="Torch CPU threads (0 = torch default).",
)
@click.option(
    "--seed",
    type=int,
    default=0,
    show_default=True,
    help="Seed of initialisation and pair sampling.",
)
@click.option(
    "--pretrained",
    type=click.Path(path_type=Path),
    help="Checkpoint to start from (curriculum 64->128->...).",
)
@click.option("--resume", is_flag=True, help="Continue the run in --out from checkpoints/last.pt.")
@click.option(
    "--ckpt-every",
    type=int,
    default=200,
    show_default=True,
    help="Steps between mid-epoch checkpoints.",
)
@click.option(
    "--log-every", type=int, default=10, show_default=True, help="Steps between steps.csv rows."
)
@PREDICTIONS_OPTION
@click.option("--quiet", is_flag=True, help="No progress bars.")
def run(model: str, data: Path, out: Path | None, **o) -> None:
    """Train MODEL on the train split, then score the best checkpoint and write a report."""
    from .train import TrainConfig, Trainer

    if model not in models.MODELS:
        raise UserError(f"MODEL: unknown '{model}' (registered: {', '.join(models.list_models())})")
    data = _dataset_dir(data)
    if o["resume"] and (out is None or not (out / "checkpoints" / "last.pt").is_file()):
        raise UserError(
            "--resume: give the --out folder of an earlier run (with checkpoints/last.pt)"
        )
    if out is None:
        out = Path("runs") / f"{model}-{data.resolve().name}-{time.strftime('%Y%m%d-%H%M%S')}"
    if out.exists() and not out.is_dir():
        raise UserError(f"--out: '{out}' is a file")
    if not o["resume"] and (out / "checkpoints" / "last.pt").exists():
        raise UserError(f"--out: '{out}' already holds a run; add --resume or choose another --out")
    for flag in ("epochs", "max_steps", "batch_size"):
        if o[flag] is not None and o[flag] < 1:
            raise UserError(f"--{flag.replace('_', '-')}: must be at least 1")
    if o["pretrained"] is not None and not o["pretrained"].is_file():
        raise UserError(f"--pretrained: no such file '{o['pretrained']}'")
    defaults = {
        k: v
        for k, v in models.MODELS[model].defaults.items()
        if k in {f.name for f in dataclasses.fields(TrainConfig)}
    }
    cfg = TrainConfig(model=model, data=str(data), out=str(out), **defaults)
    overrides = {k: o[k] for k in ("epochs", "max_steps", "batch_size", "lr") if o[k] is not None}
    cfg = dataclasses.replace(
        cfg,
        **overrides,
        device=o["device"],
        threads=o["threads"],
        seed=o["seed"],
        pretrained=str(o["pretrained"]) if o["pretrained"] else None,
        resume=o["resume"],
        ckpt_every=o["ckpt_every"],
        log_every=o["log_every"],
        save_predictions=o["save_predictions"],
        progress=not o["quiet"],
    )
    out.mkdir(parents=True, exist_ok=True)
    trainer = Trainer(cfg)
    try:
        trainer.setup()
    except ValueError as e:
        raise UserError(str(e)) from None
    t0 = time.perf_counter()
    trainer.fit()
    train_seconds = time.perf_counter() - t0
    if not trainer.main:
        return
    ckpt = out / "checkpoints" / "best.pt"
    summary = score_checkpoint(
        ckpt,
        data,
        "test",
        out,
        o["device"],
        cfg.eval_batch_size,
        cfg.save_predictions,
        progress=not o["quiet"],
    )
    summary["training_seconds"] = round(train_seconds, 1)
    m = summary["metrics"]
    click.echo(
        f"{model}: MAE {m['mae']:.3f} m, MRE {m['mre']:.3f}, MLE {m['mle']:.3f}, "
        f"depth error {m['depth_error']:.3f} m on {summary['split']} "
        f"({m['images']} pairs); report in {out / 'summary.md'}"
    )


@cli.command("eval")
@click.option(
    "--ckpt",
    type=click.Path(path_type=Path),
    required=True,
    help="Checkpoint (.pt) written by 'run'.",
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
    help="Report folder.  [default: <ckpt folder>/../eval-<dataset>-<split>]",
)
@click.option(
    "--batch-size",
    type=int,
    default=64,
    show_default=True,
    help="Pairs per forward pass (does not change results).",
)
@DEVICE_OPTION
@PREDICTIONS_OPTION
def eval_cmd(
    ckpt: Path,
    data: Path,
    split: str,
    out: Path | None,
    batch_size: int,
    device: str,
    save_predictions: bool,
) -> None:
    """Score a checkpoint on a dataset split (writes summary.json/.md, per_sample.csv, plots)."""
    if not ckpt.is_file():
        raise UserError(f"--ckpt: no such file '{ckpt}'")
    data = _dataset_dir(data)
    out = out or ckpt.resolve().parent.parent / f"eval-{data.resolve().name}-{split}"
    out.mkdir(parents=True, exist_ok=True)
    try:
        s = score_checkpoint(ckpt, data, split, out, device, batch_size, save_predictions)
    except ValueError as e:
        raise UserError(str(e)) from None
    m = s["metrics"]
    click.echo(
        f"{s['model']}: MAE {m['mae']:.3f} m, MRE {m['mre']:.3f}, MLE {m['mle']:.3f} on "
        f"{s['split']} ({m['images']} pairs); report in {out / 'summary.md'}"
    )


@cli.command()
@click.argument("runs", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option(
    "--out",
    type=click.Path(path_type=Path),
    default=Path("report"),
    show_default=True,
    help="Writes OUT.md and OUT.csv.",
)
def report(runs: tuple[Path, ...], out: Path) -> None:
    """One comparison table (markdown + CSV) of several runs' summary.json."""
    from .report import compare_runs

    missing = [str(r) for r in runs if not (r / "summary.json").is_file()]
    if missing:
        raise UserError(f"RUNS: no summary.json in {', '.join(missing)}")
    md, csv_text = compare_runs(list(runs))
    out.with_suffix(".md").write_text(md + "\n")
    out.with_suffix(".csv").write_text(csv_text)
    click.echo(md)


def main(argv: list[str] | None = None) -> None:
    try:
        cli.main(args=argv, prog_name="stillbox-bench", standalone_mode=False)
    except click.ClickException as e:
        click.echo(f"stillbox-bench: error: {e.format_message()}", err=True)
        sys.exit(2)
    except (click.exceptions.Abort, KeyboardInterrupt):
        click.echo("stillbox-bench: interrupted; continue with --resume --out <run>", err=True)
        sys.exit(130)


if __name__ == "__main__":
    main()
