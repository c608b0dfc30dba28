"""Usage: python docs/results/flight/failure_frames.py RUN EPISODE CKPT OUT.png [SECONDS]

What a depth network saw before an episode of a `fly` run ended: the episode's flown positions
are replayed through the same renderer (a persistent Blender worker, same frame seeds) and the
same depth source (the checkpoint through infer's pipeline, its shift planner fed every frame in
order), and the frame SECONDS (default 1.0) before the end is drawn as camera | true depth |
network depth | pixels within the sensing range that the network put beyond it (missed, red) or
a far surface put within it (phantom, blue). Needs the gen and bench extras."""

import json
import sys
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import torch

from benchmark.flight.dynamics import camera_pose, heading
from benchmark.flight.episodes import flight_scene_config, make_episode
from benchmark.flight.simulate import HISTORY
from benchmark.flight.sources import NetworkDepth
from stillbox_gen.live import LiveRenderer


def main(run: str, episode: str, ckpt: str, out: str, seconds: str = "1.0") -> None:
    cfg = json.loads((Path(run) / "config.json").read_text())
    rec = json.loads((Path(run) / "episodes" / f"{int(episode):06d}.json").read_text())
    if cfg["flight"]["yaw"] != "line":
        raise SystemExit("only --yaw line runs are replayed (the yaw is not recorded)")
    width, height = cfg["res"]
    scene_cfg = flight_scene_config(cfg["seed"], width, height)
    e = make_episode(cfg["seed"], int(episode), scene_cfg=scene_cfg)
    yaw = heading(e.start, e.goal, 0.0)
    positions = np.asarray(rec["positions"])[:-1]  # the poses rendered (the last is the end)
    shown = max(0, len(positions) - 1 - round(float(seconds) / cfg["flight"]["dynamics"]["dt"]))
    source = NetworkDepth(ckpt, torch.device("cpu"), cfg["shifts"])
    rgbs, poses = [], []
    with LiveRenderer(scene_cfg) as live:
        live.load(e.scene)
        for k, p in enumerate(positions[: shown + 1]):
            pose = camera_pose(p, yaw)
            rgb, truth = live.render(pose, k)
            rgbs, poses = (rgbs + [rgb])[-HISTORY:], (poses + [pose])[-HISTORY:]
            depth = source(rgbs, truth, poses)
    near = cfg["flight"]["sensing"]["max_range"]
    errors = np.zeros((*truth.shape, 3))
    errors[(truth <= near) & (depth > near)] = (1, 0, 0)
    errors[(truth > near) & (depth <= near)] = (0, 0, 1)
    fig, ax = plt.subplots(1, 4, figsize=(12, 3.4))
    shown_depth = np.where(np.isfinite(depth), depth, np.nan)
    panels = [(rgb, "camera"), (truth, "true depth (m)"), (shown_depth, "network depth (m)")]
    for a, (img, title) in zip(ax, panels, strict=False):
        im = a.imshow(img, vmin=0, vmax=30) if img.ndim == 2 else a.imshow(img)
        if img.ndim == 2:
            fig.colorbar(im, ax=a, fraction=0.046)
        a.set_title(title)
    ax[3].imshow(errors)
    ax[3].set_title(f"missed (red) / phantom (blue) < {near:g} m")
    for a in ax:
        a.axis("off")
    end = rec["outcome"]
    fig.suptitle(f"episode {int(episode)}: {end} after {rec['steps']} steps; frame {shown}")
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    print(f"{out}: frame {shown} of episode {episode} ({end})")


if __name__ == "__main__":
    main(*sys.argv[1:])
