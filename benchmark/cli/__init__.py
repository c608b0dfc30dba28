"""``stillbox-bench``: train, score and compare depth-from-motion models on stillbox-gen data.

User mistakes print one line ``stillbox-bench: error: ...`` and exit with code 2; a full disk
(or quota) prints one line ``stillbox-bench: failed: disk full writing '<path>' ...`` and exits
with code 1, as ``stillbox-gen`` does; Ctrl-C exits with code 130.
"""

from __future__ import annotations

import importlib.util
import sys

if importlib.util.find_spec("torch") is None:  # installed without the `bench` extra
    print(
        "stillbox-bench: error: the benchmark needs PyTorch: pip install 'stillbox-gen[bench]'",
        file=sys.stderr,
    )
    raise SystemExit(2)

import click  # noqa: E402 - after the check, which must run before torch is imported below

from stillbox_gen.errors import WorkerDied  # noqa: E402
from stillbox_gen.formats import disk_full_message, is_disk_full  # noqa: E402

# the chapters' training steps, registered in benchmark.engine.steps when imported (the depth and
# flow steps are the engine's own: engine.pair_step)
from ..unsupervised import training as _video_step  # noqa: E402, F401
from . import export, flight, supervised, unsupervised, video  # noqa: E402

#: how to go on after a full disk: every file is written whole (temporary name, then renamed)
AFTER_DISK_FULL = (
    "the files written before are whole: free space, then re-run the same command (run, "
    "finetune, fly: with --resume --out <run>)"
)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def cli() -> None:
    """Train and score depth-from-motion baselines on stillbox-gen datasets.

    \b
    stillbox-bench run depthnet --data data/stillbox-64      train -> evaluate -> report
    stillbox-bench run oracle-flow --data data/stillbox-64   score a method without a network
    stillbox-bench eval --ckpt runs/R/checkpoints/best.pt --data data/stillbox-64
    stillbox-bench compare --data D --models depthnet,flownets-flow,oracle-flow,constant
    stillbox-bench report runs/*                             one comparison table + figure
    stillbox-bench speed                                     size and speed table
    stillbox-bench infer --ckpt C --input flight.mp4 --speed 9 --out out/  depth of a video
    stillbox-bench eval-multishift --ckpt C --data SEQ --out R  shift strategies on sequences
    stillbox-bench toy --out runs/toy                        thesis 4.6: losses without ground truth
    stillbox-bench finetune --ckpt C --input flight.mp4 --speed 9 --out runs/ft  your footage
    stillbox-bench eval-sequences --ckpt C --data D --out R  thesis 5.4.3: Tables 5.2/5.3
    stillbox-bench fly --depth oracle --out runs/fly-oracle  thesis 6.5: closed-loop flight
    stillbox-bench fly-compare runs/fly-*                    one table of fly runs
    stillbox-bench export --ckpt C --out depthnet.onnx       a network for use elsewhere
    stillbox-bench list                                      registered models
    """


for command in (
    supervised.list_cmd,
    supervised.run,
    supervised.eval_cmd,
    supervised.report,
    supervised.compare,
    supervised.speed,
    export.export_cmd,
    video.infer,
    video.eval_multishift,
    unsupervised.toy_cmd,
    unsupervised.finetune_cmd,
    unsupervised.eval_sequences_cmd,
    flight.fly_cmd,
    flight.fly_compare,
):
    cli.add_command(command)


def main(argv: list[str] | None = None) -> None:
    try:
        cli.main(args=argv, prog_name="stillbox-bench", standalone_mode=False)
    except click.ClickException as e:
        click.echo(f"stillbox-bench: error: {e.format_message()}", err=True)
        sys.exit(2)
    except (click.exceptions.Abort, KeyboardInterrupt):
        click.echo("stillbox-bench: interrupted; continue with --resume --out <run>", err=True)
        sys.exit(130)
    except WorkerDied as e:  # fly's Blender worker died or hung: its finished episodes are kept
        click.echo(f"stillbox-bench: failed: {e}; continue with --resume --out <run>", err=True)
        sys.exit(1)
    except OSError as e:
        if not is_disk_full(e):
            raise
        click.echo(f"stillbox-bench: failed: {disk_full_message(e, AFTER_DISK_FULL)}", err=True)
        sys.exit(1)
