"""Pictures of a world's configurations: walls, start area, and the force (slope or wind).

``draw_world`` draws one configuration of a 2-D world on a matplotlib axis (the report's
heatmaps and trajectory plots draw on top of it); ``show_world`` saves every configuration of
any world side by side (``hmepol show``): a 2-D world's map, or, for a world without one (a
Gymnasium world), where episodes of uniformly random actions take its state, in the two
indices pictures draw (``projection``), from :func:`random_visits`. Only matplotlib's object API
is used (no pyplot), so the caller's backend is left alone.
"""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

import numpy as np
import torch
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from hmepol_cli.envs.base import NavigationWorld
from hmepol_cli.envs.world import World
from hmepol_cli.plots import draw_arena, draw_rectangles

START_COLOUR = "#f2c500"  # the thesis highlights the start area in yellow
FORCE_COLOUR = "#1f5fbf"
REGION_COLOUR = "#9ec3ff"
# A world without a map is shown by where random actions take it: this many episodes of this
# many steps per configuration (a few seconds for a MuJoCo world).
SHOW_EPISODES = 32
SHOW_HORIZON = 200


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
    if force:
        _draw_force_region(ax, world, config, zorder - 0.5)
    draw_rectangles(ax, [(b.x0, b.y0, b.x1, b.y1) for b in world.walls[config]], zorder)
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
    a = world.arena
    draw_arena(ax, (a.x0, a.y0, a.x1, a.y1), zorder + 0.3)


def show_world(world: World, path: str | Path, *, panel_size: float = 3.4) -> Path:
    """Save one PNG with a panel per configuration, titled with its name and probability: the
    map of a 2-D world, or where random actions take a world without one."""
    n = world.n_configurations
    cols = min(n, 5)
    rows = math.ceil(n / cols)
    fig = Figure(figsize=(panel_size * cols, (panel_size + 0.35) * rows + 0.5))
    axes = fig.subplots(rows, cols, squeeze=False)
    visits = None if world.maps else random_visits(world, SHOW_EPISODES, SHOW_HORIZON)
    for c, ax in enumerate(axes.flat):
        if c >= n:
            ax.axis("off")
            continue
        if visits is None:
            draw_world(ax, world, c)
        else:
            draw_visits(ax, world, visits[c])
        ax.set_title(
            f"{c}: {world.configuration_names[c]} (p = {world.configuration_probs[c]:.2g})\n"
            f"{world.describe(c)}",
            fontsize=9.5,
        )
        ax.tick_params(labelsize=7)
    if world.maps:
        areas = sorted({round(world.free_area(c), 2) for c in range(n)})
        area = f"{areas[0]:.3g}" if len(areas) == 1 else f"{areas[0]:.3g} to {areas[-1]:.3g}"
        title = (
            f"{world.name}: free area {area}; north up; walls grey, start area yellow, force as "
            "arrows"
        )
    else:
        i, j = world.projection
        label = world.facts().get("env_id") or world.name
        title = (
            f"{label}: {SHOW_EPISODES} episodes of {SHOW_HORIZON} steps of uniformly random "
            f"actions per configuration, state indices {i} and {j}; starts yellow"
        )
        title = textwrap.fill(title, width=38 * cols)  # one panel is narrower than the line
    fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    return path


def random_visits(
    world: World, episodes: int, horizon: int, seed: int = 0
) -> dict[int, np.ndarray]:
    """Where ``episodes`` episodes of ``horizon`` steps of uniformly random actions (within the
    action bounds; in [-1, 1] along an unbounded dimension) take the world's state, in every
    configuration: the two coordinates pictures draw (``world.plane``). The same ``seed``, the
    same picture. -> {configuration: (episodes, T + 1, 2)}"""
    generator = torch.Generator(device=world.device).manual_seed(seed)
    low, high = world.action_bounds()
    bounded = torch.isfinite(low) & torch.isfinite(high)
    visits = {}
    for c in range(world.n_configurations):
        configurations = torch.full((1, episodes), c, dtype=torch.long, device=world.device)
        begun, _ = world.begin(configurations, horizon, [generator])
        states = [begun.start]  # (1, N, d) each
        for t in range(horizon):
            u = torch.rand(
                (1, episodes, world.action_dim), generator=generator, device=world.device,
                dtype=world.dtype,
            )  # fmt: skip
            actions = torch.where(bounded, low + (high - low) * u, 2 * u - 1)
            states.append(begun.step(t, states[-1], actions).states)
        plane = world.plane(torch.stack(states, dim=2))  # (1, N, T + 1, 2)
        visits[c] = plane[0].float().cpu().numpy()
    return visits


def draw_visits(ax: Axes, world: World, positions: np.ndarray) -> None:
    """Trajectories (n, T + 1, 2) in a world without a map: a line each, their starts yellow; the
    state bounds of the two indices where they are finite, the data's extent elsewhere."""
    for trajectory in positions:
        ax.plot(trajectory[:, 0], trajectory[:, 1], color=FORCE_COLOUR, lw=0.6, alpha=0.35)
    ax.scatter(
        positions[:, 0, 0], positions[:, 0, 1], s=9, color=START_COLOUR, edgecolor="black",
        linewidth=0.3, zorder=3,
    )  # fmt: skip
    low, high = world.state_bounds()
    i, j = world.projection
    if math.isfinite(low[i]) and math.isfinite(high[i]):
        ax.set_xlim(low[i], high[i])
    if math.isfinite(low[j]) and math.isfinite(high[j]):
        ax.set_ylim(low[j], high[j])
    ax.set_xlabel(f"state[{i}]", fontsize=8)
    ax.set_ylabel(f"state[{j}]", fontsize=8)


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
