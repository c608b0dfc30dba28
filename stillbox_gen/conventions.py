"""Conventions shared by the generator, the reader and the benchmark: depth range, the nominal
pair, the default dataset folder and the limits of sizes and counts. Imports nothing of the
project."""

from __future__ import annotations

from pathlib import Path

#: Frames between the two images of a nominal StillBox pair (i, i + 3): the benchmark's fixed
#: evaluation pairs, the displacement its depth targets are expressed for (3 frames of 0.1 m, as
#: in the thesis), and the shift of ``stillbox-gen stats``.
NOMINAL_SHIFT = 3

#: Metres. Depth is clipped to [0, MAX_DEPTH] for training and scoring (files hold it unclipped).
MAX_DEPTH = 100.0


def default_root(width: int, height: int) -> Path:
    """The generator's default ``--out`` for frames of width x height pixels:
    ``data/stillbox-<W>`` when square, ``data/stillbox-<W>x<H>`` otherwise (relative path)."""
    res = f"{width}" if width == height else f"{width}x{height}"
    return Path("data") / f"stillbox-{res}"


# Upper bounds of every size and count a user sets, by config key ("section.name") or run option
# (generate's --scenes, --workers, --threads): ConfigError beyond them, before anything is
# written (stillbox_gen.config.limit_problem). Each is far above any real use yet below what
# exhausts memory or what Blender refuses late, in the workers (Cycles takes at most 1024
# bounces). Here, not in config, because stillbox-bench bounds its options by them too
# (benchmark/cli/limits.py) and must not load the generator's config.
LIMITS: dict[str, tuple[int, str]] = {  # key: (largest value, unit)
    "camera.width": (8192, "pixels"),  # 8K frames: a 256 MB float32 depth map per frame
    "camera.height": (8192, "pixels"),
    "camera.frames": (10_000, "frames per scene"),  # StillBox: 10
    "objects.count": (1000, "objects"),  # StillBox: 20; 1000 samples a layout in about 2 s
    "render.samples": (4096, "samples per pixel"),  # anti-aliasing only: 16 is --quality high
    "render.max_bounces": (1024, "bounces"),  # Cycles' own maximum
    "scenes": (10_000_000, "scenes"),  # 125 times StillBox's 80,000
    "workers": (256, "workers"),  # about 500 MB of memory each
    "threads": (1024, "threads"),  # more than any CPU has
}
