"""``stillbox-bench`` commands of thesis chapter 6: infer (depth of your own video) and
eval-multishift (frame-shift strategies on generated sequences)."""

from __future__ import annotations

from pathlib import Path

import click

from stillbox_gen.arguments import check_out_folder
from stillbox_gen.conventions import MAX_DEPTH

from ..core.multishift import BETA_MEAN, EMA_LAMBDA, MULTISHIFT_MAX_SHIFT
from .limits import FLOAT, INT, INTS, RESOLUTION
from .options import (
    DEVICE_OPTION,
    UserError,
    dataset_dir,
    int_option,
    locked_out,
    torch_device,
    user_error,
)

BETA_MEAN_OPTION = click.option(
    "--beta-mean",
    type=FLOAT,
    default=BETA_MEAN,
    show_default=True,
    help="The β = output/θ_max the shifts aim at and the fusion favours (thesis 6.2-6.3).",
)


#: the options of the footage, its motion and its camera, shared by infer and finetune (in
#: this order): --speed, --poses, --fps, --fov, --focal, --res, --train-fov
FOOTAGE_OPTIONS = (
    click.option("--speed", type=FLOAT, help="Constant camera speed, m/s (or --poses)."),
    click.option(
        "--poses",
        type=click.Path(path_type=Path),
        help="CSV, one row per frame: x,y,z (m) or vx,vy,vz (m/s), optional t (s).",
    ),
    click.option("--fps", type=FLOAT, help="Frames per second.  [default: the video's]"),
    click.option(
        "--fov",
        type=FLOAT,
        help="Horizontal field of view of the video, degrees.  [default: the training camera's]",
    ),  # fmt: skip
    click.option(
        "--focal", type=FLOAT, help="Focal length of the video, pixels (instead of --fov)."
    ),
    click.option(
        "--res",
        type=RESOLUTION,
        help="Network input WxH, multiples of 64.  [default: the training size]",
    ),
    click.option(
        "--train-fov",
        type=FLOAT,
        help="Horizontal FOV (degrees) of the training camera, for checkpoints that record none; "
        "needs --res.",
    ),
)


def footage_options(function):
    """Decorate a command with FOOTAGE_OPTIONS (``--res`` comes as (W, H) pixels or None)."""
    for option in reversed(FOOTAGE_OPTIONS):
        function = option(function)
    return function


@click.command()
@click.option(
    "--ckpt",
    type=click.Path(path_type=Path),
    required=True,
    help="Checkpoint of a depth network written by 'run'.",
)
@click.option(
    "--input",
    "input_",
    type=click.Path(path_type=Path),
    required=True,
    help="Video file, or folder of frames (png/jpg/bmp/tif, in name order).",
)
@click.option(
    "--out",
    type=click.Path(path_type=Path),
    required=True,
    help="Output folder (new or empty): depth/, depth_png/, preview.mp4, frames.csv, summary.json.",
)
@footage_options
@int_option("--shifts", 1, "Frame pairs per frame: depth clusters of thesis 6.3 (1..4).")
@click.option("--fixed-shift", type=INT, help="Always this frame shift (no adaptation).")
@click.option(
    "--max-shift",
    type=INT,
    help="Largest frame shift considered.  [default: twice the shift reaching the nominal "
    "displacement, at least 8]",
)
@click.option(
    "--ema",
    type=FLOAT,
    default=EMA_LAMBDA,
    show_default=True,
    help="Smoothing λ of the target displacement (eq. 6.2), 0 <= λ < 1.",
)
@BETA_MEAN_OPTION
@click.option(
    "--depth-format",
    type=click.Choice(["npy", "exr"]),
    default="npy",
    show_default=True,
    help="Depth files: float32 .npy or single-channel .exr, metres.",
)
@click.option(
    "--max-depth",
    type=FLOAT,
    default=MAX_DEPTH,
    show_default=True,
    help="Depth (m) at the end of the colour map of depth_png/ and preview.mp4.",
)
@DEVICE_OPTION
@click.option("--quiet", is_flag=True, help="No progress bar.")
def infer(input_: Path, res: tuple[int, int] | None, **o) -> None:
    """Depth maps of your own stabilised video with a depth network (thesis chapter 6).

    The depth of frame t comes from pairs (frame t - shift, frame t), shifts chosen from the
    depth of the previous frames (--shifts N: N pairs fused per frame); frame 0 gets none.
    """
    from ..engine.footage_job import InferOptions, prepare
    from ..video.infer import describe
    from ..video.infer import run as run_inference

    opts = InferOptions(input=input_, res=res, **o)
    try:
        job = prepare(opts)
    except ValueError as e:
        raise user_error(e) from None
    if job.warning:
        click.echo(f"stillbox-bench: warning: {job.warning}", err=True)
    try:
        summary = run_inference(job, opts)
    except ValueError as e:
        raise user_error(e) from None
    click.echo(describe(summary, opts.out))


@click.command("eval-multishift")
@click.option(
    "--ckpt",
    "ckpts",
    type=click.Path(path_type=Path),
    multiple=True,
    required=True,
    help="Depth checkpoint written by 'run' (repeat to compare networks).",
)
@click.option(
    "--data",
    type=click.Path(path_type=Path),
    required=True,
    help="Dataset of long sequences, e.g. stillbox-gen --frames 30 --rotation-noise 0.0331.",
)
@click.option(
    "--split",
    type=click.Choice(["train", "val", "test"]),
    default="test",
    show_default=True,
    help="Split of sequences to score.",
)
@click.option(
    "--shifts",
    type=INTS,
    default="1,2,3",  # multishift_eval.DEFAULT_SHIFT_COUNTS (not imported: torch)
    show_default=True,
    help="Comma-separated pairs per frame to score, n.",
)
@int_option("--max-shift", MULTISHIFT_MAX_SHIFT, "Largest frame shift; frames t >= it are scored.")
@BETA_MEAN_OPTION
@click.option("--scenes", type=INT, help="Score only the split's first N sequences.")
@click.option("--out", type=click.Path(path_type=Path), required=True, help="Results folder.")
@DEVICE_OPTION
@click.option("--quiet", is_flag=True, help="No progress bar.")
def eval_multishift(
    ckpts: tuple[Path, ...],
    data: Path,
    split: str,
    shifts: tuple[int, ...],
    max_shift: int,
    beta_mean: float,
    scenes: int | None,
    out: Path,
    device: str,
    quiet: bool,
) -> None:
    """Score frame-shift strategies on generated sequences (thesis 6.2-6.4, Fig. 6.6): the
    nominal shift, the optimal shift (n=1) and n-pair fusion, per checkpoint; MAE/MRE/MLE overall
    and per depth band, and network time per frame."""
    from ..video.multishift_eval import run as run_multishift

    for ckpt in ckpts:
        if not ckpt.is_file():
            raise UserError(f"--ckpt: no such file '{ckpt}'")
    data = dataset_dir(data)
    check_out_folder(out, error=UserError)
    dev = torch_device(device)
    with locked_out(out):  # checkpoints and data are checked before --out is written
        try:
            _, md = run_multishift(
                list(ckpts), data, out, split, shifts, max_shift, dev, beta_mean=beta_mean,
                limit=scenes, progress=not quiet,
            )  # fmt: skip
        except ValueError as e:  # the library's names for --shifts and --scenes
            raise user_error(e, counts="--shifts", limit="--scenes") from None
    click.echo(md)
    click.echo(f"results in {out}")
