"""Contact sheet of a dataset: first and last RGB frames beside colour-mapped depth."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from .dataset import Dataset  # noqa: E402
from .formats import atomic_write  # noqa: E402


def contact_sheet(root: Path | Dataset, out: Path, scenes: int, max_depth: float) -> None:
    """Write a PNG with one row per scene (the first ``scenes`` of the dataset): frame 0, last
    frame, depth of frame 0 and of the last frame (metres, colour scale 0 to ``max_depth``).
    Raises DatasetError naming the file that cannot be read."""
    ds = root if isinstance(root, Dataset) else Dataset(root)
    chosen = ds.scenes(limit=scenes)
    fig, axes = plt.subplots(len(chosen), 4, figsize=(10, 2.6 * len(chosen)), squeeze=False)
    image = None
    for r, scene in enumerate(chosen):
        shown = (0, scene.frames - 1)
        for col, f in enumerate(shown):
            axes[r, col].imshow(scene.load_rgb(f))
            axes[r, col].set_title(f"scene {scene.index} frame {f}", fontsize=8)
        for col, f in enumerate(shown, start=2):
            depth = scene.load_depth(f)
            image = axes[r, col].imshow(depth, cmap="magma_r", vmin=0, vmax=max_depth)
            axes[r, col].set_title(f"depth {f} (m)", fontsize=8)
        for ax in axes[r]:
            ax.set_axis_off()
    fig.colorbar(
        image, ax=axes.ravel().tolist(), label="depth (m), clipped for display", shrink=0.8
    )
    try:
        atomic_write(out, lambda f: fig.savefig(f, format="png", dpi=100))
    finally:
        plt.close(fig)
