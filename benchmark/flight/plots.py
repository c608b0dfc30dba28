"""The top-down figure of one flown episode: the obstacles' footprints, the trajectory, start,
goal and where it collided.

Footprints come from the World (never from the estimated depth): grey where the flight plane
(the start's altitude, episodes are horizontal) cuts an obstacle, light grey where an obstacle
lies anywhere within ``band`` metres above or below it; a dotted line marks the drone's
collision sphere around them (``drone_radius``). World axes X (east) and Y (north), metres.
"""

from __future__ import annotations

import numpy as np

from .world import World

GRID = 160  # samples per side of the footprint grid
BAND = 2.0  # metres above and below the flight plane for the light footprint


def footprints(world: World, z: float, extent: tuple, band: float = BAND, grid: int = GRID):
    """(xs, ys, plane, column): the grid's axes (grid,) and the obstacles' signed distance (m)
    at altitude ``z`` and its least value over [z - band, z + band] (walls left out), (grid,
    grid), rows along y."""
    xs = np.linspace(extent[0], extent[1], grid)
    ys = np.linspace(extent[2], extent[3], grid)
    gx, gy = np.meshgrid(xs, ys)

    def at(height: float) -> np.ndarray:
        pts = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, height)], axis=1)
        d = np.full(len(pts), np.inf)
        for obstacle in world.obstacles:
            d = np.minimum(d, obstacle.signed_distance(pts))
        return d.reshape(gx.shape)

    plane = at(z)
    column = np.min([plane, *(at(z + dz) for dz in np.linspace(-band, band, 9))], axis=0)
    return xs, ys, plane, column


def episode_figure(
    world: World,
    start: np.ndarray,
    goal: np.ndarray,
    positions: np.ndarray,
    outcome: str,
    title: str,
    drone_radius: float,
    reach_radius: float,
):
    """A matplotlib Figure (not shown) of one episode seen from above."""
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle

    pts = np.vstack([positions[:, :2], start[None, :2], goal[None, :2]])
    lo, hi = pts.min(axis=0) - 6.0, pts.max(axis=0) + 6.0
    side = float((hi - lo).max())
    mid = (lo + hi) / 2
    extent = (mid[0] - side / 2, mid[0] + side / 2, mid[1] - side / 2, mid[1] + side / 2)
    xs, ys, plane, column = footprints(world, float(start[2]), extent)
    fig = Figure(figsize=(5.5, 5.5))
    ax = fig.add_subplot()
    ax.contourf(xs, ys, column, levels=[-1e9, 0], colors=["0.85"])
    ax.contourf(xs, ys, plane, levels=[-1e9, 0], colors=["0.45"])
    ax.contour(xs, ys, plane, levels=[drone_radius], colors=["0.45"], linestyles=":")
    ax.plot(positions[:, 0], positions[:, 1], "-", color="tab:blue", lw=1.5, label="flown")
    ax.plot(*zip(start[:2], goal[:2], strict=True), "--", color="0.6", lw=0.8, label="straight")
    ax.plot(*start[:2], "o", color="tab:green", label="start")
    ax.add_patch(Circle(goal[:2], reach_radius, fill=False, color="tab:orange"))
    ax.plot(*goal[:2], "*", color="tab:orange", ms=12, label="goal")
    if outcome == "collided":
        ax.plot(*positions[-1, :2], "x", color="tab:red", ms=12, mew=2.5, label="collision")
    ax.set_xlim(extent[:2])
    ax.set_ylim(extent[2:])
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title, fontsize=9)
    ax.legend(loc="upper right", fontsize=7)
    fig.tight_layout()
    return fig
