"""Drawing blocks shared by the report and the evaluation: walls, visitation heatmaps, trajectories.

Figures are built with :class:`matplotlib.figure.Figure` directly (no pyplot state, no GUI
backend), so plotting works headless and from worker processes. A world is drawn from plain
geometry (:class:`WorldMap`: arena, start area, walls), the one run.json records, so the report
draws a run's world without building it (and without the training code).
"""

from __future__ import annotations

import math
import re
import textwrap
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.collections import LineCollection
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from hmepol_cli.algorithms import ALGORITHMS, SCRATCH

OTHER_COLOURS = ("#ff7f0e", "#9467bd", "#8c564b", "#17becf", "#e377c2", "#bcbd22")
LINESTYLES = ("-", (0, (5, 2)), (0, (1, 1)), (0, (5, 2, 1, 2)))
BOUND_COLOUR = "0.25"  # the log(free area) line
HEATMAP_CMAP = "viridis"
TIME_CMAP = "plasma"  # a trajectory's colour by step: dark purple at the start, yellow at the end
START_OUTLINE = "#d62728"  # the start area's outline on heatmaps
TRAJECTORIES = 5  # trajectories per panel: more lines of one colour map cannot be followed
DPI = 110
WALL_COLOUR = "0.55"

Rect = tuple[float, float, float, float]  # x0, y0, x1, y1 of an axis-aligned rectangle


def algo_colour(algo: str) -> str:
    """One colour per algorithm in every figure (algorithms.py), others by their name's hash."""
    known = {**ALGORITHMS, SCRATCH.name: SCRATCH}
    if algo in known:
        return known[algo].colour
    return OTHER_COLOURS[sum(map(ord, algo)) % len(OTHER_COLOURS)]


def new_figure(width: float, height: float) -> Figure:
    return Figure(figsize=(width, height), dpi=DPI, layout="constrained")


def save(fig: Figure, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path


# ------------------------------------------------------------------------------------ the world
@dataclass(frozen=True)
class WorldMap:
    """What a picture of a 2-D world draws, as plain numbers: the arena, the start area and each
    configuration's walls, every one a rectangle (x0, y0, x1, y1).

    run.json records it as ``world_map`` (:meth:`to_json`; null for a world without a map, a
    Gymnasium world), so a run's pictures and the report's are drawn from the same numbers."""

    arena: Rect
    start: Rect
    walls: tuple[tuple[Rect, ...], ...]  # one tuple of rectangles per configuration

    @classmethod
    def from_json(cls, data: Mapping[str, Any] | None) -> WorldMap | None:
        """The map run.json's ``world_map`` holds; None for null (a world without a map)."""
        if data is None:
            return None

        def rect(values: Sequence[float]) -> Rect:
            x0, y0, x1, y1 = (float(v) for v in values)
            return x0, y0, x1, y1

        return cls(
            arena=rect(data["arena"]),
            start=rect(data["start"]),
            walls=tuple(tuple(rect(w) for w in config) for config in data["walls"]),
        )

    def to_json(self) -> dict[str, Any]:
        """{"arena": [x0, y0, x1, y1], "start": [...], "walls": [[[x0, y0, x1, y1], ...], ...]}"""
        return {
            "arena": list(self.arena),
            "start": list(self.start),
            "walls": [[list(w) for w in config] for config in self.walls],
        }


def has_map(world_map: WorldMap | None) -> bool:
    """True for a world drawn as a map (an arena with walls); False (None) for a world whose map
    is unknown or a Gymnasium world, whose pictures show a projection of the observation on two
    indices."""
    return world_map is not None


def world_extent(
    world_map: WorldMap | None, positions: np.ndarray | None = None
) -> tuple[float, float, float, float]:
    """(x0, x1, y0, y1) of the arena, or of the data when the world has no map."""
    if world_map is not None:
        x0, y0, x1, y1 = world_map.arena
        return x0, x1, y0, y1
    if positions is None or positions.size == 0:
        return -1.0, 1.0, -1.0, 1.0
    xy = positions.reshape(-1, 2)
    lo, hi = np.nanmin(xy, axis=0), np.nanmax(xy, axis=0)
    pad = 0.02 * float(max(hi - lo)) or 1.0
    return lo[0] - pad, hi[0] + pad, lo[1] - pad, hi[1] + pad


def draw_rectangles(ax: Axes, rects: Sequence[Rect], zorder: float) -> None:
    """Walls: opaque grey rectangles at ``zorder``, so data drawn below them is hidden where the
    agent can never be."""
    for x0, y0, x1, y1 in rects:
        ax.add_patch(
            Rectangle(
                (x0, y0), x1 - x0, y1 - y0, facecolor=WALL_COLOUR, edgecolor="none", zorder=zorder
            )
        )


def draw_arena(ax: Axes, arena: Rect, zorder: float) -> None:
    """The arena's black outline, and the axes cut to it at equal scales."""
    x0, y0, x1, y1 = arena
    ax.add_patch(
        Rectangle(
            (x0, y0), x1 - x0, y1 - y0, facecolor="none", edgecolor="black", linewidth=1.2,
            zorder=zorder,
        )
    )  # fmt: skip
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")


def draw_walls(ax: Axes, world_map: WorldMap | None, config: int) -> None:
    """The walls of one configuration and the arena's outline, above the data."""
    if world_map is None:
        return
    draw_rectangles(ax, world_map.walls[config], zorder=3)
    draw_arena(ax, world_map.arena, zorder=3.3)


def outline_start(ax: Axes, world_map: WorldMap | None) -> None:
    """The start area as a dashed outline above the data and the walls."""
    if world_map is None:
        return
    x0, y0, x1, y1 = world_map.start
    # A white rim under the dashes keeps the outline visible on any colour of the heatmap.
    for colour, width, dashes in (("white", 2.6, "-"), (START_OUTLINE, 1.4, (0, (3, 2)))):
        ax.add_patch(
            Rectangle(
                (x0, y0),
                x1 - x0,
                y1 - y0,
                facecolor="none",
                edgecolor=colour,
                linestyle=dashes,
                linewidth=width,
                zorder=4,
            )
        )


def _map_axes(
    ax, extent: tuple[float, float, float, float], title: str | None = None, is_map: bool = True
) -> None:
    """A map keeps its proportions and needs no ticks; a projection of observations (two indices
    on unrelated scales, such as position and velocity) fills the panel and shows its values."""
    x0, x1, y0, y1 = extent
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    if is_map:
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
    else:
        ax.set_aspect("auto")
        ax.tick_params(labelsize=6)
    if title:
        ax.set_title(title, fontsize=9)


# ------------------------------------------------------------------------------------- heatmaps
def default_bins(extent: tuple[float, float, float, float]) -> int:
    """Bins per axis: 0.04-wide bins on the [-1, 1]^2 grid worlds, at most 100 on larger arenas."""
    side = max(extent[1] - extent[0], extent[3] - extent[2])
    return int(min(100, max(50, round(25 * side))))


def visitation_log_prob(
    positions: np.ndarray, extent: tuple[float, float, float, float], bins: int
) -> np.ma.MaskedArray:
    """log of the fraction of visited states in each bin; unvisited bins masked.

    positions (n_traj, T+1, 2) -> (bins, bins), row 0 at the bottom (y0).
    """
    xy = positions.reshape(-1, 2)
    xy = xy[np.isfinite(xy).all(axis=1)]
    counts, _, _ = np.histogram2d(xy[:, 0], xy[:, 1], bins=bins, range=[extent[:2], extent[2:]])
    total = counts.sum()
    with np.errstate(divide="ignore"):
        logp = np.log(counts / total) if total > 0 else np.full_like(counts, -np.inf)
    return np.ma.masked_invalid(logp.T)


def category_labels(
    labels: Sequence[str], axis_inches: float, fontsize: float = 8.0
) -> tuple[list[str], float]:
    """Labels for ticks side by side on an axis ``axis_inches`` wide: each broken before its
    parenthesis and after its commas ("HMepol (a=1, b=2)" -> three lines), and one type size
    for all, smaller where a line is wider than its tick's share of the axis (~16 characters
    of 8-point type an inch), never under 5 points."""
    broken = [re.sub(r",\s*", ",\n", label.replace(" (", "\n(")) for label in labels]
    widest = max((len(line) for label in broken for line in label.split("\n")), default=1)
    fits = 16.0 * 8.0 / fontsize * axis_inches / max(len(labels), 1)
    return broken, max(5.0, min(fontsize, fontsize * fits / widest))


def _blocks(fig: Figure, n_blocks: int, rows_per_block: int, cols: int, labels: Sequence[str]):
    """One subfigure per block (a run, a group), titled by its label; returns the axes grids.

    Subfigures keep the block titles out of the panels' way (equal-aspect maps leave a row
    label no reliable room).
    """
    subfigs = fig.subfigures(n_blocks, 1, squeeze=False)[:, 0]
    grids = []
    for subfig, label in zip(subfigs, labels, strict=True):
        if label:
            text, size = block_title(label, 8.0 * subfig.figure.get_figwidth())
            subfig.suptitle(text, fontsize=size, fontweight="bold")
        grids.append(subfig.subplots(rows_per_block, cols, squeeze=False))
    return grids


def block_title(label: str, fits: float) -> tuple[str, float]:
    """A block's title and its type size, for a width that ``fits`` bold 10-point characters
    (~8 an inch): a longer label is broken at a space into two lines, and gets smaller type
    only where its longer line still does not fit."""
    if len(label) <= fits:
        return label, 10.0
    width = max(int(fits), math.ceil(len(label) / 2))
    lines = textwrap.wrap(label, width, break_long_words=False)
    while len(lines) > 2:
        width += 1
        lines = textwrap.wrap(label, width, break_long_words=False)
    return "\n".join(lines), min(10.0, 10.0 * fits / max(len(line) for line in lines))


def heatmap_grid(
    fig: Figure,
    world_map: WorldMap | None,
    rows: Sequence[tuple[str, dict[int, np.ndarray]]],
    configuration_names: Sequence[str],
    max_cols: int = 5,
) -> None:
    """Heatmaps of log visitation probability: one block of panels per row, one panel per config.

    ``rows`` holds (label, {config: positions (n, T+1, 2)}). All panels share one colour scale,
    shown by one colour bar at the right.
    """
    n_configurations = len(configuration_names)
    cols = min(n_configurations, max_cols)
    rows_per_block = math.ceil(n_configurations / cols)
    some = next((p for _, by_c in rows for p in by_c.values()), None)
    extent = world_extent(world_map, some)
    bins = default_bins(extent)
    maps = [
        {c: visitation_log_prob(p, extent, bins) for c, p in by_config.items()}
        for _, by_config in rows
    ]
    values = [m.compressed() for block in maps for m in block.values() if m.count()]
    vmin = float(min(v.min() for v in values)) if values else -10.0
    vmax = float(max(v.max() for v in values)) if values else 0.0
    panels, bar_fig = fig.subfigures(1, 2, width_ratios=[cols * 2.5, 1.2])
    grids = _blocks(panels, len(rows), rows_per_block, cols, [label for label, _ in rows])
    image = None
    for axes, block in zip(grids, maps, strict=True):
        for c in range(rows_per_block * cols):
            ax = axes[c // cols, c % cols]
            if c >= n_configurations:
                ax.set_axis_off()
                continue
            _map_axes(ax, extent, f"config {c}: {configuration_names[c]}", has_map(world_map))
            ax.set_facecolor("white")
            if c in block:
                image = ax.imshow(
                    block[c],
                    origin="lower",
                    extent=extent,
                    cmap=HEATMAP_CMAP,
                    vmin=vmin,
                    vmax=vmax,
                    interpolation="nearest",
                    aspect="equal" if has_map(world_map) else "auto",
                    zorder=2,
                )
            draw_walls(ax, world_map, c)
            outline_start(ax, world_map)
    if image is not None:
        cax = bar_fig.add_axes((0.15, 0.1, 0.18, 0.8))
        bar = bar_fig.colorbar(image, cax=cax)
        bar.set_label("log probability of visitation (per bin)")


# --------------------------------------------------------------------------------- trajectories
def draw_trajectories(ax, positions: np.ndarray, n_trajectories: int = TRAJECTORIES):
    """The first trajectories as lines through every step, coloured by the step (TIME_CMAP); a
    white circle marks each start, a black square each end. Returns the line collections' colour
    mapping, for a colour bar.

    positions (n_traj, T+1, 2). Every step is drawn, so no segment crosses a wall (one step is
    shorter than any wall is thick).
    """
    steps = positions.shape[1] - 1
    norm = Normalize(0, max(steps, 1))
    lines = None
    for traj in positions[:n_trajectories]:
        segments = np.stack([traj[:-1], traj[1:]], axis=1)
        lines = LineCollection(
            segments, cmap=TIME_CMAP, norm=norm, linewidths=0.9, zorder=5, clip_on=False
        )
        lines.set_array(np.arange(steps))
        ax.add_collection(lines)
        marks = {"zorder": 6, "clip_on": False, "markersize": 4.5}
        ax.plot(*traj[0], "o", mfc="white", mec="black", mew=0.8, **marks)
        ax.plot(*traj[-1], "s", mfc="black", mec="white", mew=0.5, **marks)
    return lines


def trajectory_grid(
    fig: Figure,
    world_map: WorldMap | None,
    rows: Sequence[tuple[str, dict[int, np.ndarray]]],
    configuration_names: Sequence[str],
    n_trajectories: int = TRAJECTORIES,
    max_cols: int = 5,
) -> None:
    """Trajectory panels: one block per row (a seed, a run), one panel per configuration, and
    one colour bar for the step."""
    n_configurations = len(configuration_names)
    cols = min(n_configurations, max_cols)
    rows_per_block = math.ceil(n_configurations / cols)
    some = next((p for _, by_c in rows for p in by_c.values()), None)
    extent = world_extent(world_map, some)
    panels, bar_fig = fig.subfigures(1, 2, width_ratios=[cols * 2.5, 1.0])
    grids = _blocks(panels, len(rows), rows_per_block, cols, [label for label, _ in rows])
    lines = None
    for axes, (_, by_config) in zip(grids, rows, strict=True):
        for c in range(rows_per_block * cols):
            ax = axes[c // cols, c % cols]
            if c >= n_configurations:
                ax.set_axis_off()
                continue
            _map_axes(ax, extent, f"config {c}: {configuration_names[c]}", has_map(world_map))
            draw_walls(ax, world_map, c)
            if c in by_config:
                lines = draw_trajectories(ax, by_config[c], n_trajectories) or lines
    if lines is not None:
        cax = bar_fig.add_axes((0.15, 0.1, 0.18, 0.8))
        bar_fig.colorbar(lines, cax=cax).set_label("step (circle: start, square: end)")


# ----------------------------------------------------------------------------- one run (trainer)
def save_run_plots(
    world,
    positions_by_config: dict[int, np.ndarray],
    out_dir: Path,
    n_trajectories: int = TRAJECTORIES,
) -> list[Path]:
    """Write ``heatmap.png`` and ``trajectories.png`` of one evaluation of one run into out_dir.

    positions_by_config: {config: (n_traj, T+1, 2)} rollouts of the policy in each configuration.
    """
    out_dir = Path(out_dir)
    names = list(
        world.configuration_names
        if world is not None
        else [f"config {c}" for c in sorted(positions_by_config)]
    )
    n_configurations = len(names)
    cols = min(n_configurations, 5)
    rows = math.ceil(n_configurations / cols)
    some = next(iter(positions_by_config.values()))
    n_traj, steps = some.shape[0], some.shape[1] - 1
    facts = {} if world is None else world.facts()
    world_map = WorldMap.from_json(facts.get("world_map"))  # what run.json records of it
    world_name = facts.get("env_id") or (world.name if world is not None else "world")
    projection = None if world is None or world.maps else world.projection
    axes = "" if projection is None else f"\nx: observation[{projection[0]}], y: [{projection[1]}]"

    fig = new_figure(2.6 * cols + 1.2, 2.6 * rows + 0.6)
    heatmap_grid(fig, world_map, [("", positions_by_config)], names)
    fig.suptitle(
        f"{world_name}: log probability of state visitation\n"
        f"{n_traj} trajectories of T={steps} steps per configuration"
        f"{'' if projection is not None else ', dashed: start area'}{axes}",
        **({} if projection is None else {"fontsize": 9}),
    )
    heatmap = save(fig, out_dir / "heatmap.png")

    fig = new_figure(2.6 * cols + 1.0, 2.6 * rows + 0.6)
    trajectory_grid(fig, world_map, [("", positions_by_config)], names, n_trajectories)
    fig.suptitle(
        f"{world_name}: {min(n_trajectories, n_traj)} trajectories of T={steps} steps per "
        f"configuration\ncolour: step{axes}",
        fontsize=10,
    )
    trajectories = save(fig, out_dir / "trajectories.png")
    return [heatmap, trajectories]
