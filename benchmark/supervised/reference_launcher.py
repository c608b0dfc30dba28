"""Run the author's DepthNet ``train.py`` (github.com/ClementPinard/DepthNet) unmodified, with
the harness substitutions of benchmark.supervised.reference.

This file runs under the *author's* Python environment, not this project's: it imports nothing
of stillbox-gen. It is started as::

    python reference_launcher.py CODE SPLIT_JSON KEEP_DIR KEEP_EPOCHS -- <train.py arguments>

and substitutes, before ``train.py`` runs (every other line of the author's code runs as is):

1. ``datasets.stillbox.make_dataset``: returns the train scenes and validation pairs listed in
   SPLIT_JSON (written by ``reference.author_split``), so both codes train on the same scenes;
   the author's own version draws its split from its seed (it also seeds Python's ``random``,
   which draws the flips: this one does too).
2. ``util.save_checkpoint``: also copies the checkpoint of every epoch in KEEP_EPOCHS
   (comma-separated, 1-based) to ``KEEP_DIR/epoch<N>.pth.tar``; the author's code keeps only
   the last and the best one.
3. ``terminal_logger.TermLogger``: lines to stdout instead of screen positions (blessings
   needs a terminal; the harness runs headless).
4. ``torchvision``: a module with ``transforms.Compose`` and ``transforms.Normalize`` (the only
   parts ``train.py`` uses), because torchvision's wheel on PyPI does not load beside the CPU
   build of torch 2.13 (``operator torchvision::nms does not exist``).
"""

from __future__ import annotations

import json
import random
import runpy
import shutil
import sys
import types
from pathlib import Path


def torchvision_stand_in() -> None:
    """``torchvision.transforms.Compose`` / ``Normalize`` for (C, H, W) tensors."""
    import torch

    class Compose:
        def __init__(self, steps):
            self.steps = list(steps)

        def __call__(self, x):
            for step in self.steps:
                x = step(x)
            return x

    class Normalize:
        def __init__(self, mean, std):
            self.mean = torch.tensor(mean, dtype=torch.float32).view(-1, 1, 1)
            self.std = torch.tensor(std, dtype=torch.float32).view(-1, 1, 1)

        def __call__(self, x):
            return (x - self.mean) / self.std

    package = types.ModuleType("torchvision")
    transforms = types.ModuleType("torchvision.transforms")
    transforms.Compose, transforms.Normalize = Compose, Normalize
    package.transforms = transforms
    sys.modules["torchvision"], sys.modules["torchvision.transforms"] = package, transforms


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
    """TermLogger's interface, printing its lines (per-epoch summaries) without a terminal."""

    def __init__(self, n_epochs, train_size, test_size):
        self.epoch_bar, self.train_bar, self.test_bar = _Bar(), _Bar(), _Bar()
        self.train_writer = self.test_writer = _Lines()

    def reset_train_bar(self):
        pass

    def reset_test_bar(self):
        pass


def main(argv: list[str]) -> None:
    sep = argv.index("--")
    code, split_json, keep_dir, keep = argv[:sep]
    train_args = argv[sep + 1 :]
    code, keep_dir = Path(code).resolve(), Path(keep_dir).resolve()
    keep_epochs = {int(e) for e in keep.split(",") if e}
    split = json.loads(Path(split_json).read_text())
    torchvision_stand_in()
    sys.path.insert(0, str(code))

    import datasets.stillbox as stillbox
    import numpy as np
    import terminal_logger
    import util

    val = [[pair, depth, np.array(d, np.float32)] for pair, depth, d in split["val"]]

    def make_dataset(root_dir, split_percent=0, shift=3, seed=None):
        random.seed(seed)  # as the replaced function does: it seeds the random flips
        return split["train"], val

    save = util.save_checkpoint

    def save_checkpoint(save_path, state, is_best, filename="checkpoint.pth.tar"):
        save(save_path, state, is_best, filename)
        if state["epoch"] in keep_epochs:
            keep_dir.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(Path(save_path) / filename, keep_dir / f"epoch{state['epoch']}.pth.tar")

    stillbox.make_dataset = make_dataset
    util.save_checkpoint = save_checkpoint
    terminal_logger.TermLogger = LineLogger
    sys.argv = [str(code / "train.py"), *train_args]
    runpy.run_path(str(code / "train.py"), run_name="__main__")


if __name__ == "__main__":
    main(sys.argv[1:])
