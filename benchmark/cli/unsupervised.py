"""``stillbox-bench toy``: the toy-problem study of thesis §4.6 (Table 4.1, Figs. 4.13-4.18),
:mod:`benchmark.unsupervised.toy` run from one command, writing results.json, table.md and the
figures, ``--resume`` going on from the last finished run of an interrupted study
(:mod:`benchmark.unsupervised.toy_runs`); ``stillbox-bench finetune``: a depth network
fine-tuned on a user's footage without depth (thesis §5.4.5,
:mod:`benchmark.unsupervised.finetune`); ``stillbox-bench eval-sequences``: depth networks
scored on 5-frame sequences as thesis §5.4.3-5.4.4 does (:mod:`benchmark.unsupervised
.sequence_report`). User mistakes raise
``UserError`` (exit code 2), which ``stillbox-bench`` prints as one line.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import click
import numpy as np

from stillbox_gen.arguments import check_out_folder
from stillbox_gen.formats import atomic_write_text

from ..core import runfolder
from ..unsupervised import finetune as finetune_lib
from ..unsupervised import toy as study
from ..unsupervised import toy_jobs, toy_plots, toy_runs
from ..unsupervised.reprojection import SMOOTH_LOSSES
from ..unsupervised.sequence_eval import PAIR_TARGET_DEPTH, SEQUENCE_LENGTH
from ..unsupervised.training import smooth_settings
from .limits import FLOAT, FLOATS, INT
from .options import (
    DEVICE_OPTION,
    UserError,
    dataset_dir,
    locked_out,
    setting_option,
    torch_device,
    user_error,
)
from .video import footage_options

RESULTS_JSON = "results.json"
TABLE_MD = "table.md"
DEPTHS_NPZ = "depths.npz"


def _load(option: str, root: Path, name: str) -> study.ToyScene:
    """The toy dataset of ``option``; a missing or unreadable one is a one-line UsageError
    giving the command that renders it."""
    make = f"stillbox-gen --preset {study.PRESETS[name]} --out {root}"
    if not root.exists():
        raise UserError(f"{option}: no dataset at '{root}'; render it with '{make}'")
    try:
        return study.load_scene(root, name)
    except (study.ToyDataError, OSError) as e:
        raise UserError(f"{option}: {e} (render it with '{make}')") from None


def _losses_option(text: str | None) -> tuple[str, ...] | None:
    """``"diffusion,tv"`` -> ("diffusion", "tv"); a UsageError naming --losses for an unknown
    name."""
    if text is None:
        return None
    names = tuple(n.strip() for n in text.split(","))
    unknown = [n for n in names if n not in SMOOTH_LOSSES]
    if unknown or not names:
        known = ", ".join(SMOOTH_LOSSES)
        raise UserError(f"--losses: unknown loss '{','.join(unknown)}' (known: {known})")
    return names


def write_outputs(
    out: Path, results: dict, best: dict[str, study.BestRun], scenes: list[study.ToyScene]
) -> None:
    """results.json, table.md, depths.npz (best depth of every run and scene, metres) and the
    figures, into ``out``."""
    atomic_write_text(out / RESULTS_JSON, json.dumps(results, indent=2) + "\n")
    atomic_write_text(out / TABLE_MD, study.table_markdown(results))
    arrays = {f"{k}/{n}": r.depth[n][0, 0].numpy() for k, r in best.items() for n in r.depth}
    runfolder.atomic_write_binary(out / DEPTHS_NPZ, lambda f: np.savez_compressed(f, **arrays))
    odm_settings = sorted({k.endswith("odm-on") for k in results["runs"]})
    for odm in odm_settings:
        tag = "odm-on" if odm else "odm-off"
        toy_plots.heatmaps(results, odm, out / f"heatmaps_{tag}.png")
        runs = [r for k, r in best.items() if k.endswith(tag)]
        if not odm:
            runs = [best["photometric"], *runs]  # Fig. 4.13 as the first row
        for s in scenes:
            title = f"{s.name}: best (λ, κ) of each loss, ODM {'on' if odm else 'off'}"
            toy_plots.panels(s, runs, title, out / f"{s.name}_{tag}.png")
    pair = [best[k] for k in (study.run_key("diffusion", False), study.run_key("diffusion", True))
            if k in best]  # fmt: skip
    flower = [s for s in scenes if s.name == "flower"]
    if len(pair) == 2 and flower:
        title = "Flower, diffusion: ODM off / on (thesis Fig. 4.18)"
        toy_plots.panels(flower[0], pair, title, out / "flower_diffusion_odm.png")
    curves = [r for k, r in best.items() if k != "photometric"]
    toy_plots.le_curves(curves, results["le0"], out / "le_curves.png")


def _summary(results: dict, seconds: float) -> str:
    g = f"{len(results['lambdas'])}x{len(results['kappas'])}"
    runs = results["runs"]
    parts = []
    for loss in dict.fromkeys(k.split("/")[0] for k in runs):
        keys = [study.run_key(loss, odm) for odm in (False, True)]
        ms = [runs[k]["best"]["m"] for k in keys if k in runs]
        parts.append(f"{loss} " + " -> ".join(f"{m:.2f}" for m in ms))
    photo = results["photometric"]["best"]["m"]
    return (
        f"toy: {1 + len(runs)} runs of {results['iterations']} iterations, {g} grid, "
        f"{seconds:.0f} s; best M (ODM off -> on): {', '.join(parts)}; photometric alone "
        f"M {photo:.2f}"
    )


@click.command("toy")
@click.option(
    "--flower",
    type=click.Path(path_type=Path),
    default=Path("data/toy-flower"),
    show_default=True,
    help="Dataset of the Flower toy scene (stillbox-gen --preset toy-flower).",
)
@click.option(
    "--horizon",
    type=click.Path(path_type=Path),
    default=Path("data/toy-horizon"),
    show_default=True,
    help="Dataset of the Horizon toy scene (stillbox-gen --preset toy-horizon).",
)
@click.option(
    "--out",
    type=click.Path(path_type=Path),
    required=True,
    help="Folder for results.json, table.md, depths.npz and the figures.",
)
@click.option(
    "--iterations",
    type=INT,
    help=f"Adam steps of every optimisation.  [default: {study.ITERATIONS}; "
    f"--quick: {study.QUICK_ITERATIONS}]",
)
@click.option(
    "--odm-every",
    type=INT,
    help=f"Iterations between two computations of the occlusion mask.  [default: "
    f"{study.ODM_EVERY}; --quick: {study.QUICK_ODM_EVERY}]",
)
@click.option(
    "--lambdas",
    type=FLOATS,
    help="Comma-separated λ grid (smooth-loss weights).  [default: "
    + ",".join(f"{v:g}" for v in study.LAMBDAS)
    + "]",
)
@click.option(
    "--kappas",
    type=FLOATS,
    help="Comma-separated κ grid (edge sensitivities).  [default: "
    + ",".join(f"{v:g}" for v in study.KAPPAS)
    + "]",
)
@click.option("--losses", help="Comma-separated smooth losses to run.  [default: all six]")
@click.option(
    "--quick",
    is_flag=True,
    help=f"A {len(study.QUICK_LAMBDAS)}x{len(study.QUICK_KAPPAS)} (λ, κ) grid and "
    f"{study.QUICK_ITERATIONS} iterations (CI).",
)
@DEVICE_OPTION
@click.option(
    "--threads",
    type=INT,
    default=1,
    show_default=True,
    help="Threads of the optimiser's kernels (the results do not depend on it) and of torch. 1 "
    "by default: on a shared machine threads wait for each other (measured up to 10x slower with "
    "2 torch threads on 2 busy cores).",
)
@click.option(
    "--resume",
    is_flag=True,
    help=f"Continue the unfinished study in --out (its finished runs are kept in "
    f"--out/{toy_runs.FOLDER}/ until the study ends) with the same settings and data.",
)
@click.option(
    "--jobs",
    type=INT,
    default=1,
    show_default=True,
    help="Worker processes running the study's runs side by side, one thread each, costliest "
    "first (the results do not depend on it). On a shared machine N processes keep their pace "
    "where N kernel threads (--threads) wait for each other.",
)
@click.option(
    "--keep-runs",
    is_flag=True,
    help=f"Keep --out/{toy_runs.FOLDER}/ (every run's results) when the study ends, to combine "
    "studies of other --losses into one with --resume (docs/results/toy/README.md).",
)
@click.option("--quiet", is_flag=True, help="No progress bar.")
def toy_cmd(
    flower: Path,
    horizon: Path,
    out: Path,
    iterations: int | None,
    odm_every: int | None,
    lambdas: tuple[float, ...] | None,
    kappas: tuple[float, ...] | None,
    losses: str | None,
    quick: bool,
    device: str,
    threads: int,
    resume: bool,
    jobs: int,
    keep_runs: bool,
    quiet: bool,
) -> None:
    """Toy problems (thesis §4.6, Table 4.1): optimise the centre frame's depth of Flower and
    Horizon by reprojection from frames t-1 and t+1, with the photometric loss alone and with
    each smooth loss over a log grid of (λ, κ), ODM off and on; report LE, M and ΔM beside the
    thesis' Table 4.1."""
    import torch
    from tqdm import tqdm

    try:
        toy_kernels = study.kernels()
    except ModuleNotFoundError as e:
        raise UserError(str(e)) from None
    check_out_folder(out, error=UserError)  # the numbers' ranges: limits.LIMITS
    if jobs > 1 and threads > 1:
        raise UserError(f"--jobs: its workers run one thread each; drop --threads {threads}")
    dev = torch_device(device)
    cfg = (
        study.StudyConfig.quick(iterations)
        if quick
        else study.StudyConfig(iterations or study.ITERATIONS)
    )
    if odm_every is not None:
        cfg.odm_every = odm_every
    cfg.lambdas = lambdas or cfg.lambdas  # each within limits.LIMITS
    cfg.kappas = kappas or cfg.kappas
    cfg.losses = _losses_option(losses) or cfg.losses
    if resume and not quick:  # what was not given again: the unfinished study's
        _keep_saved(out, cfg, iterations=iterations, odm_every=odm_every, lambdas=lambdas,
                    kappas=kappas)  # fmt: skip
    scenes = [_load("--horizon", horizon, "horizon"), _load("--flower", flower, "flower")]
    settings = toy_runs.settings(cfg, scenes)
    # one study per --out at a time, until the command ends (released by click's context)
    click.get_current_context().with_resource(locked_out(out))
    keys = _check_resume(out, settings, resume)
    try:
        out = runfolder.make_folder(out)
    except ValueError as e:
        raise user_error(e) from None
    done = _load_or_start(out, settings, keys, resume)
    torch.set_num_threads(threads)
    toy_kernels.set_threads(threads)
    bar = tqdm(total=cfg.runs * cfg.iterations, initial=len(done) * cfg.iterations, unit="it",
               disable=quiet, dynamic_ncols=True)  # fmt: skip
    t0 = time.perf_counter()

    def save(key: str, block: dict, b: study.BestRun) -> None:
        toy_runs.save(out, key, block, b, settings)
        if jobs > 1:  # the workers' steps arrive through run_parallel's on_progress
            bar.set_description(f"{jobs} workers, {key} done")

    with bar:
        computed = {}
        if jobs > 1:
            bar.set_description(f"{jobs} workers")
            computed = toy_jobs.run_parallel(scenes, cfg, jobs, done, save, bar.update)
        results, best = study.run_study(
            [s.to(dev) for s in scenes],
            cfg,
            on_run=bar.set_description,
            on_step=bar.update,
            done={**done, **computed},
            on_done=save,
        )
    # a resumed study's time: this command's wall time and the resumed runs' own
    earlier = sum(block["seconds"] for block, _ in done.values())
    seconds = time.perf_counter() - t0 + earlier
    results["seconds"] = round(seconds, 1)
    results["device"] = str(dev)
    write_outputs(out, results, best, scenes)
    if not keep_runs:
        toy_runs.remove(out)
    resumed = f" ({len(done)} of them resumed)" if done else ""
    click.echo(f"{_summary(results, seconds)}{resumed}; results in {out}")


#: settings of a toy study that --resume keeps from its study.json when their flag is not given
#: again (--losses and the ODM settings choose runs: toy_runs.SELECTION)
KEPT_SETTINGS = ("iterations", "odm_every", "lambdas", "kappas")


def _keep_saved(out: Path, cfg: study.StudyConfig, **given) -> None:
    """``cfg`` with the unfinished study's value of each KEPT_SETTINGS setting whose option is
    not ``given`` (None); nothing when ``out`` holds no study (_check_resume says so)."""
    try:
        saved = toy_runs.read_settings(out)
    except ValueError as e:
        raise UserError(f"--out: {e}") from None
    for name in KEPT_SETTINGS:
        if saved is not None and given[name] is None and name in saved:
            value = saved[name]
            setattr(cfg, name, tuple(value) if isinstance(value, list) else value)


def _check_resume(out: Path, settings: dict, resume: bool) -> list[str]:
    """Keys of the runs an unfinished study left in ``out``, to take as they are with
    ``--resume`` (same settings and data, else a one-line error). Without --resume a study
    starts anew, but finished runs of an unfinished one are refused (the error names
    --resume), not discarded."""
    try:
        saved = toy_runs.read_settings(out)
    except ValueError as e:
        raise UserError(f"--out: {e}") from None
    keys = toy_runs.finished(out)
    if not resume:
        if saved is not None and keys:
            raise UserError(
                f"--out: '{out}' holds an unfinished toy study ({len(keys)} finished runs); "
                f"add --resume to continue it, or remove {toy_runs.folder(out)}"
            )
        return []
    if saved is None:
        raise UserError(f"--resume: '{out}' holds no unfinished toy study")
    changed = toy_runs.difference(saved, settings)
    if changed:
        raise UserError(f"--resume: '{out}' holds a study of other settings ({changed})")
    wanted = {"photometric"} | {
        study.run_key(loss, odm) for loss in settings["losses"] for odm in settings["odm"]
    }
    return [k for k in keys if k in wanted]


def _load_or_start(
    out: Path, settings: dict, keys: list[str], resume: bool
) -> dict[str, study.Finished]:
    """The finished runs ``keys`` read back (--resume), or a new study's settings written."""
    try:
        if resume:
            return {k: toy_runs.load(out, k, settings) for k in keys}
        toy_runs.start(out, settings)
        return {}
    except (ValueError, OSError) as e:
        raise UserError(f"--out: {e}") from None


@click.command("finetune")
@click.option(
    "--ckpt",
    type=click.Path(path_type=Path),
    help="Checkpoint of a depth network written by 'run' (e.g. depthnet's best.pt).",
)
@click.option(
    "--input",
    "input_",
    type=click.Path(path_type=Path),
    help="Stabilised video file, or folder of frames (png/jpg/bmp/tif, in name order).",
)
@click.option(
    "--out",
    type=click.Path(path_type=Path),
    required=True,
    help="Run folder; checkpoints/best.pt is the fine-tuned depth network.",
)
@footage_options
@click.option(
    "--steps",
    type=INT,
    help="Optimiser steps in all (the warm-up's included; --resume: the run's unless given).  "
    f"[default: {finetune_lib.STEPS}]",
)
@click.option(
    "--pose-warmup",
    type=INT,
    help="First steps with the DepthNet frozen, PoseNet alone learning (a random PoseNet's "
    f"wrong poses would push the depth the wrong way).  [default: {finetune_lib.POSE_WARMUP}]",
)
@setting_option("lr", "finetune")
@setting_option("batch_size", "finetune")
@click.option(
    "--occlusion",
    is_flag=True,
    help="Drop the pixels the occlusion module finds hidden from the photometric loss "
    "(thesis 4.5.6).",
)
@click.option(
    "--smooth-weight",
    type=FLOAT,
    help="λ of the smooth loss (eq. 5.5; 0: photometric loss alone; depthnet-unsup trains with "
    f"{smooth_settings(None, None, False)[0]:g}).  [default: {finetune_lib.SMOOTH_WEIGHT:g}]",
)
@click.option(
    "--known-motion",
    is_flag=True,
    default=None,
    help="Warp with the camera motion of --poses (camera axes, e.g. from GPS) instead of "
    "PoseNet's translations: only the DepthNet learns.  [default: off; the pose warm-up is 0 "
    "with it]",
)
@setting_option("seed", "finetune")
@click.option(
    "--resume",
    is_flag=True,
    help="Continue the fine-tuning in --out from checkpoints/last.pt (its options are kept).",
)
@setting_option("threads", "finetune")
@DEVICE_OPTION
@setting_option("ckpt_every", "finetune")
@setting_option("log_every", "finetune")
@click.option("--quiet", is_flag=True, help="No progress bars.")
def finetune_cmd(
    input_: Path | None, res: tuple[int, int] | None, out: Path, resume: bool, **o
) -> None:
    """Fine-tune a depth network on your own stabilised footage, without depth (thesis 5.4.5).

    The network learns from sequences of 5 frames with the photometric loss of chapter 5 and a
    fresh PoseNet (first alone: --pose-warmup); the footage, its motion and the camera are read
    as 'infer' reads them. checkpoints/best.pt loads in 'infer' and 'eval'.
    """
    from ..unsupervised.finetune import FinetuneOptions, describe, finetune

    check_out_folder(out, error=UserError)
    last = runfolder.checkpoint_path(out, "last")
    if resume and not last.is_file():
        raise UserError("--resume: give the --out folder of an earlier finetune (with "
                        "checkpoints/last.pt)")  # fmt: skip
    if not resume and last.exists():
        raise UserError(f"--out: '{out}' already holds a run; add --resume or choose another --out")
    opts = FinetuneOptions(out=out, input=input_, res=res, resume=resume, **o)
    try:
        summary = finetune(opts)
    except ValueError as e:
        raise user_error(e) from None
    click.echo(describe(summary))


@click.command(
    "eval-sequences",
    help=f"""Score depth networks the way thesis 5.4.3-5.4.4 does (Tables 5.2-5.3): the depth
    of the last frame of every {SEQUENCE_LENGTH}-frame sequence, from the pair whose mean DepthNet
    output is closest to {PAIR_TARGET_DEPTH:g} m (frames stabilised by the known orientation, or
    PoseNet's for 6-DoF networks), scaled by the measured displacement (P); SFMLearner scaled by
    PoseNet (P) and by the ground-truth median (GT); a constant plane (GT); for networks with a
    PoseNet, the cosine between its translation and the true one. Writes results.md (the
    thesis' numbers beside), .csv, .json.""",
)
@click.option(
    "--ckpt",
    "ckpts",
    type=click.Path(path_type=Path),
    multiple=True,
    required=True,
    help="Depth checkpoint written by 'run': depthnet*, depthnet-unsup*, sfmlearner* (repeat "
    "to score several).",
)
@click.option(
    "--data",
    type=click.Path(path_type=Path),
    required=True,
    help=f"Dataset whose scenes have {SEQUENCE_LENGTH} frames or more (stabilised or rotating).",
)
@click.option(
    "--split",
    type=click.Choice(["train", "val", "test"]),
    default="test",
    show_default=True,
    help="Split of scenes to score.",
)
@click.option(
    "--upside-down",
    "upside",
    is_flag=True,
    help="Also score every model on the same frames turned upside down (thesis Table 5.3).",
)
@click.option("--scenes", type=INT, help="Score only the split's first N scenes.")
@click.option("--out", type=click.Path(path_type=Path), required=True, help="Results folder.")
@DEVICE_OPTION
@click.option("--quiet", is_flag=True, help="No progress bar.")
def eval_sequences_cmd(
    ckpts: tuple[Path, ...],
    data: Path,
    split: str,
    upside: bool,
    scenes: int | None,
    out: Path,
    device: str,
    quiet: bool,
) -> None:
    """The command's help is above (its numbers are sequence_eval's constants)."""
    from ..unsupervised.sequence_report import run as run_sequences

    data = dataset_dir(data)
    check_out_folder(out, error=UserError)
    dev = torch_device(device)
    with locked_out(out):  # checkpoints and data are checked before --out is written
        try:
            rows, md = run_sequences(list(ckpts), data, out, split, upside, dev, scenes, not quiet)
        except ValueError as e:
            raise user_error(e, limit="--scenes") from None
    click.echo(md)
    best = min((r for r in rows if r["orientation"] == "upright"), key=lambda r: r["mae"])
    click.echo(
        f"Scored {len(ckpts)} checkpoint(s) and a constant plane on {rows[0]['sequences']} "
        f"sequences of {data} ({split} split{', upright and upside down' if upside else ''}); "
        f"lowest upright MAE: {best['model']} ({best['scale']}) {best['mae']:.3f} m. "
        f"Results in {out}."
    )
