"""Run the author's ``train_img_pairs.py`` (github.com/ClementPinard/unsupervised-depthnet)
unmodified, with the substitutions listed in README.md ("Changes to the author's code").

This file runs under the *author's* Python environment (torch 2.13 CPU, imageio, path,
tensorboardX, blessings, progressbar2, scikit-image, matplotlib), not this project's: it imports
nothing of stillbox-gen. Started as::

    python launcher.py CODE KEEP_DIR -- <train_img_pairs.py arguments>

with the working directory where the author's ``checkpoints/`` folder is to go. Before the
script runs (every line of the author's code then runs as it is):

1. ``logger.TermLogger``: plain lines on stdout instead of screen positions (blessings needs a
   terminal; the harness runs headless).
2. ``matplotlib.cm.get_cmap``: ``matplotlib.colormaps[name]`` (the same colormap), which
   matplotlib 3.9 removed; ``utils.py`` calls it when imported (for TensorBoard images only).
3. ``utils.save_checkpoint``: also copies both networks' checkpoints of every epoch to
   ``KEEP_DIR/epoch<N>_{depthnet,posenet}.pth.tar`` (the author's code keeps only the last and
   the best), for the learning curve.
"""

from __future__ import annotations

import runpy
import shutil
import sys
from pathlib import Path


class _Bar:
    def start(self, *_):
        pass

    def update(self, *_):
        pass

    def finish(self, *_):
        pass


class _Lines:
    def write(self, text: str) -> None:
        print(text.rstrip("\r\n"), flush=True)

    def flush(self) -> None:
        pass


class LineLogger:
    """logger.TermLogger's interface, printing its lines without a terminal."""

    def __init__(self, n_epochs, train_size, valid_size):
        self.epoch_bar, self.train_bar, self.valid_bar = _Bar(), _Bar(), _Bar()
        self.train_writer = self.valid_writer = _Lines()

    def reset_train_bar(self, train_size=None):
        pass

    def reset_valid_bar(self):
        pass


def main(argv: list[str]) -> None:
    sep = argv.index("--")
    code, keep_dir = (Path(a).resolve() for a in argv[:sep])
    sys.path.insert(0, str(code))

    import matplotlib
    import matplotlib.cm

    if not hasattr(matplotlib.cm, "get_cmap"):
        matplotlib.cm.get_cmap = lambda name: matplotlib.colormaps[name]

    import logger
    import utils

    save = utils.save_checkpoint

    def save_checkpoint(save_path, depthnet_state, posenet_state, is_best,
                        filename="checkpoint.pth.tar"):  # fmt: skip
        save(save_path, depthnet_state, posenet_state, is_best, filename)
        keep_dir.mkdir(parents=True, exist_ok=True)
        epoch = depthnet_state["epoch"]
        for prefix in ("depthnet", "posenet"):
            shutil.copyfile(
                Path(save_path) / f"{prefix}_{filename}",
                keep_dir / f"epoch{epoch}_{prefix}.pth.tar",
            )

    logger.TermLogger = LineLogger
    utils.save_checkpoint = save_checkpoint
    sys.argv = [str(code / "train_img_pairs.py"), *argv[sep + 1 :]]
    runpy.run_path(str(code / "train_img_pairs.py"), run_name="__main__")


if __name__ == "__main__":
    main(sys.argv[1:])
