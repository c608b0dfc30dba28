"""Flight episodes: a generated scene, a start and a goal, reproducible from (seed, episode).

Episode ``k`` of seed ``s`` is StillBox scene ``k`` of :func:`flight_scene_config` (seed ``s``)
and a horizontal straight segment of ``EpisodeConfig.distance`` metres drawn from the stream
``SeedSequence([s, k, EPISODE_STREAM])``: its middle near a randomly chosen primitive, redrawn
until some obstacle lies on (by default: across) the straight line and start and goal are clear
of every surface.
Nothing depends on the depth source, so every source flies the same episodes.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from stillbox_gen import config
from stillbox_gen.config import DatasetConfig
from stillbox_gen.record import SceneSpec
from stillbox_gen.scene import sample_scene

from .world import World

EPISODE_STREAM = 0x666C79  # "fly": separates the episode's draws from the scene's own stream

#: Scene overrides of the default DatasetConfig for flying: fewer, smaller objects, anywhere
#: around the scene's origin (not only in its first camera's view), in a smaller room.
FLIGHT_SCENE = {
    "objects": {
        "count": 12,
        "size_range": (1.0, 5.0),
        "distance_range": (2.0, 12.0),
        "behind_fraction": 1.0,
    },
    "box": {"half_extent_range": (25.0, 30.0), "offset_max": 2.0},
}


def flight_scene_config(seed: int = 0, width: int = 64, height: int = 64) -> DatasetConfig:
    """The default DatasetConfig with FLIGHT_SCENE's overrides, ``seed`` and the frame size."""
    return config.replace(
        DatasetConfig(seed=seed), camera={"width": width, "height": height}, **FLIGHT_SCENE
    )


@dataclass(frozen=True)
class EpisodeConfig:
    """``distance``: start to goal (m); ``clearance``: least distance (m) of start and goal
    from any surface; ``near``: the straight segment passes within this distance (m) of an
    obstacle, or through it (0, the default: flying straight collides); ``lateral``,
    ``vertical``: largest offsets (m) of the segment's middle from the chosen primitive's
    centre; ``attempts``: draws before giving up."""

    distance: float = 20.0
    clearance: float = 2.0
    near: float = 0.0
    lateral: float = 1.0
    vertical: float = 0.5
    attempts: int = 500


@dataclass(frozen=True)
class Episode:
    """A flight from ``start`` to ``goal`` (world, m, same altitude) in ``scene``."""

    seed: int
    index: int
    scene: SceneSpec
    start: np.ndarray
    goal: np.ndarray
    world: World = field(repr=False)

    @property
    def K(self) -> np.ndarray:
        """Intrinsics (pixels) of the scene's camera: the resolution and FOV to render."""
        return np.asarray(self.scene.camera.K, float)


def segment_clearance(world: World, a: np.ndarray, b: np.ndarray, spacing: float = 0.05) -> float:
    """Least clearance (m) of the points of segment a-b (sampled every ``spacing`` m)."""
    n = max(2, int(math.ceil(np.linalg.norm(b - a) / spacing)) + 1)
    t = np.linspace(0.0, 1.0, n)[:, None]
    return float(world.clearance(a + t * (b - a)).min())


def _draw_segment(rng: np.random.Generator, world: World, cfg: EpisodeConfig):
    """One candidate (start, goal): horizontal, its middle near a random primitive."""
    blocker = world.obstacles[int(rng.integers(len(world.obstacles)))]
    heading = rng.uniform(0.0, 2 * math.pi)
    along = np.array([math.cos(heading), math.sin(heading), 0.0])
    across = np.array([-along[1], along[0], 0.0])
    middle = (
        blocker.location
        + across * rng.uniform(-cfg.lateral, cfg.lateral)
        + np.array([0.0, 0.0, rng.uniform(-cfg.vertical, cfg.vertical)])
        + along * rng.uniform(-cfg.distance / 4, cfg.distance / 4)
    )
    return middle - along * cfg.distance / 2, middle + along * cfg.distance / 2


def make_episode(
    seed: int,
    index: int,
    cfg: EpisodeConfig = EpisodeConfig(),  # noqa: B008 (frozen)
    scene_cfg: DatasetConfig | None = None,
) -> Episode:
    """Episode ``index`` of ``seed`` (scene from ``scene_cfg``, default flight_scene_config).
    RuntimeError if no segment of ``cfg.attempts`` draws satisfies ``cfg``."""
    scene_cfg = dataclasses.replace(scene_cfg or flight_scene_config(), seed=seed)
    scene = sample_scene(scene_cfg, index)  # the scene's own stream: (seed, index)
    world = World.from_scene(scene)
    if not world.obstacles:
        raise ValueError("an episode needs a scene with at least one primitive")
    rng = np.random.default_rng(np.random.SeedSequence([seed, index, EPISODE_STREAM]))
    for _ in range(cfg.attempts):
        start, goal = _draw_segment(rng, world, cfg)
        ends = world.clearance(np.stack([start, goal]))
        if ends.min() >= cfg.clearance and segment_clearance(world, start, goal) <= cfg.near:
            return Episode(seed, index, scene, start, goal, world)
    raise RuntimeError(f"episode {index} of seed {seed}: no start and goal in {cfg.attempts} draws")
