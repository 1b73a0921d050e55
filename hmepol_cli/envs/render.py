"""Pictures of a world's configurations: walls, start area, and the force (slope or wind).

``draw_world`` draws one configuration on a matplotlib axis (the report's heatmaps and
trajectory plots draw on top of it); ``show_world`` saves every configuration side by side.
Only matplotlib's object API is used (no pyplot), so the caller's backend is left alone.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from hmepol_cli.envs.base import NavigationWorld

WALL_COLOUR = "0.55"
START_COLOUR = "#f2c500"  # the thesis highlights the start area in yellow
FORCE_COLOUR = "#1f5fbf"
REGION_COLOUR = "#9ec3ff"


def draw_world(
    ax: Axes,
    world: NavigationWorld,
    config: int,
    *,
    force: bool = True,
    start: bool = True,
    zorder: float = 2.0,
) -> None:
    """Draw configuration ``config`` of ``world`` on ``ax``: arena, walls, start box, force.

    ``force`` adds the wind arrows (corridor), or the slope arrows over the shaded region the
    slope acts on (gridworlds). Walls are opaque at ``zorder``, so a heatmap drawn below them
    is hidden where the agent can never be.
    """
    a = world.arena
    if force:
        _draw_force_region(ax, world, config, zorder - 0.5)
    for b in world.walls[config]:
        ax.add_patch(
            Rectangle(
                (b.x0, b.y0),
                b.x1 - b.x0,
                b.y1 - b.y0,
                facecolor=WALL_COLOUR,
                edgecolor="none",
                zorder=zorder,
            )
        )
    if start:
        s = world.start
        ax.add_patch(
            Rectangle(
                (s.x0, s.y0),
                s.x1 - s.x0,
                s.y1 - s.y0,
                facecolor=START_COLOUR,
                alpha=0.5,
                edgecolor=START_COLOUR,
                linewidth=1.0,
                zorder=zorder - 0.1,  # under the walls: only its free part shows
            )
        )
    if force:
        points, directions, length = force_arrows(world, config)
        if len(points):
            tails = points - directions * length / 2
            ax.quiver(
                tails[:, 0],
                tails[:, 1],
                directions[:, 0],
                directions[:, 1],
                angles="xy",
                scale_units="xy",
                scale=1 / length,
                width=0.007,
                headwidth=4,
                headlength=4,
                headaxislength=3.5,
                color=FORCE_COLOUR,
                zorder=zorder + 0.2,
            )
    ax.add_patch(
        Rectangle(
            (a.x0, a.y0),
            a.x1 - a.x0,
            a.y1 - a.y0,
            facecolor="none",
            edgecolor="black",
            linewidth=1.2,
            zorder=zorder + 0.3,
        )
    )
    ax.set_xlim(a.x0, a.x1)
    ax.set_ylim(a.y0, a.y1)
    ax.set_aspect("equal")


def show_world(world: NavigationWorld, path: str | Path, *, panel_size: float = 3.4) -> Path:
    """Save one PNG with a panel per configuration, titled with its name and probability."""
    n = world.n_configurations
    cols = min(n, 5)
    rows = math.ceil(n / cols)
    fig = Figure(figsize=(panel_size * cols, (panel_size + 0.35) * rows + 0.5))
    axes = fig.subplots(rows, cols, squeeze=False)
    for c, ax in enumerate(axes.flat):
        if c >= n:
            ax.axis("off")
            continue
        draw_world(ax, world, c)
        ax.set_title(
            f"{c}: {world.configuration_names[c]} (p = {world.configuration_probs[c]:.2g})\n"
            f"{world.describe(c)}",
            fontsize=9.5,
        )
        ax.tick_params(labelsize=7)
    areas = sorted({round(world.free_area(c), 2) for c in range(n)})
    area = f"{areas[0]:.3g}" if len(areas) == 1 else f"{areas[0]:.3g} to {areas[-1]:.3g}"
    fig.suptitle(
        f"{world.name}: free area {area}; north up; walls grey, start area yellow, force as arrows",
        fontsize=11,
    )
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    return path


def force_arrows(world: NavigationWorld, config: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Where to draw force arrows: centres (M, 2), unit directions (M, 2), and arrow length.

    The world proposes lattices of arrows over the region its force acts on
    (``arrow_candidates``); this keeps the arrows that touch no wall, from the fullest lattice.
    """
    candidates, length = world.arrow_candidates(config)
    best = np.zeros((0, 2)), np.zeros((0, 2)), 0.0
    for lattice, direction in candidates:
        keep = np.abs(direction).sum(axis=1) > 0
        for offset in (-length / 2, 0.0, length / 2):
            keep &= _free(world, config, lattice + offset * direction, margin=0.1 * length)
        if keep.sum() > len(best[0]):
            best = lattice[keep], direction[keep], length
    return best


def _free(world: NavigationWorld, config: int, points: np.ndarray, margin: float) -> np.ndarray:
    """True where a point is at least ``margin`` away from every wall and inside the arena."""
    x, y = points[:, 0], points[:, 1]
    a = world.arena
    free = (x >= a.x0 + margin) & (x <= a.x1 - margin) & (y >= a.y0 + margin) & (y <= a.y1 - margin)
    for b in world.walls[config]:
        free &= ~(
            (x > b.x0 - margin) & (x < b.x1 + margin) & (y > b.y0 - margin) & (y < b.y1 + margin)
        )
    return free


def _draw_force_region(ax: Axes, world: NavigationWorld, config: int, zorder: float) -> None:
    region = world.force_region(config)
    if region is None:
        return
    a = world.arena
    x0, y0 = max(region.x0, a.x0), max(region.y0, a.y0)
    x1, y1 = min(region.x1, a.x1), min(region.y1, a.y1)
    ax.add_patch(
        Rectangle(
            (x0, y0),
            x1 - x0,
            y1 - y0,
            facecolor=REGION_COLOUR,
            alpha=0.3,
            edgecolor="none",
            zorder=zorder,
        )
    )
