"""Contact sheet of a dataset: first and last RGB frames beside colour-mapped depth."""

from __future__ import annotations

from pathlib import Path

import cv2
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from . import formats, manifest  # noqa: E402
from .config import ConfigError  # noqa: E402


def _frame_path(root: Path, row: dict, key: str) -> Path:
    """The checked path of a manifest row's ``rgb`` or ``depth`` file (never outside ``root``)."""
    where = f"manifest.parquet: scene {row['scene']} frame {row['frame']} {key}"
    return formats.resolve_inside(root, row[key], where)


def contact_sheet(root: Path, out: Path, scenes: int, max_depth: float) -> None:
    """Write a PNG with one row per scene: frame 0, last frame, depth of frame 0 and last frame."""
    table = manifest.read_manifest(root / "manifest.parquet").to_pylist()
    by_scene: dict[int, list[dict]] = {}
    for row in table:
        by_scene.setdefault(row["scene"], []).append(row)
    chosen = sorted(by_scene)[:scenes]
    fig, axes = plt.subplots(len(chosen), 4, figsize=(10, 2.6 * len(chosen)), squeeze=False)
    image = None
    for r, k in enumerate(chosen):
        rows = sorted(by_scene[k], key=lambda x: x["frame"])
        shown = (rows[0], rows[-1])
        for col, row in enumerate(shown):
            path = _frame_path(root, row, "rgb")
            img = cv2.imread(str(path))
            if img is None:
                raise ConfigError(f"DATASET: cannot read image '{path}'")
            axes[r, col].imshow(img[..., ::-1])
            axes[r, col].set_title(f"scene {k} frame {row['frame']}", fontsize=8)
        for col, row in enumerate(shown, start=2):
            path = _frame_path(root, row, "depth")
            try:
                depth = formats.read_depth_exr(path)
            except Exception as e:  # noqa: BLE001 - any reader failure is the user's file
                raise ConfigError(f"DATASET: cannot read depth '{path}' ({e})") from None
            image = axes[r, col].imshow(depth, cmap="magma_r", vmin=0, vmax=max_depth)
            axes[r, col].set_title(f"depth {row['frame']} (m)", fontsize=8)
        for ax in axes[r]:
            ax.set_axis_off()
    fig.colorbar(
        image, ax=axes.ravel().tolist(), label="depth (m), clipped for display", shrink=0.8
    )
    tmp = out.with_name(f".{out.name}.tmp.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    tmp.replace(out)
