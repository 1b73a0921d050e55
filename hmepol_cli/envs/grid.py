"""Gridworlds on [-1, 1]^2 whose walls are laid out as 10 x 10 blocks, with a slope force.

Shared by the slope world (one layout, two slopes) and multigrid (ten layouts, ten slopes).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from hmepol_cli.envs.base import Box, NavigationWorld

ARENA = Box(-1.0, -1.0, 1.0, 1.0)
START = Box(-1.0, -1.0, -0.5, -0.5)  # bottom-left room (thesis Fig. 5.1)
SLOPE_STD = 0.01  # public reference implementation of [22]
SLOPE_RANGE = (0.0, 0.2)  # the slope's magnitude is truncated to this range (thesis 5.1)


@dataclass(frozen=True)
class SlopeSpec:
    """A stochastic force of magnitude ~ N(mean, 0.01) truncated to [0, 0.2], along direction.

    ``region`` limits it to a part of the arena (None: everywhere).
    """

    direction: tuple[float, float] = (0.0, 0.0)
    mean: float = 0.0
    region: Box | None = None


def walls_from_ascii(rows: list[str], arena: Box = ARENA) -> tuple[Box, ...]:
    """Rectangles for the '#' blocks of an ASCII layout (first row = top), one per run of a row."""
    n_rows, n_cols = len(rows), len(rows[0])
    if any(len(r) != n_cols for r in rows):
        raise ValueError("every row of a layout must have the same length")
    w = (arena.x1 - arena.x0) / n_cols
    h = (arena.y1 - arena.y0) / n_rows
    # Runs of '#' per row, then identical runs of consecutive rows merged into one rectangle.
    open_runs: dict[tuple[int, int], int] = {}  # (first col, end col) -> first row
    spans: list[tuple[int, int, int, int]] = []  # (first row, end row, first col, end col)
    for i, row in enumerate([*rows, "." * n_cols]):
        runs, j = set(), 0
        while j < n_cols:
            if row[j] != "#":
                j += 1
                continue
            start = j
            while j < n_cols and row[j] == "#":
                j += 1
            runs.add((start, j))
        for run in list(open_runs):
            if run not in runs:
                spans.append((open_runs.pop(run), i, *run))
        for run in runs:
            open_runs.setdefault(run, i)
    return tuple(
        Box(arena.x0 + c0 * w, arena.y1 - r1 * h, arena.x0 + c1 * w, arena.y1 - r0 * h)
        for r0, r1, c0, c1 in sorted(spans)
    )


# Four rooms joined by one-block hallways; walls are two blocks (0.4) wide (thesis Fig. 5.1).
FOUR_ROOMS = [
    "....##....",
    "....##....",
    "..........",
    "....##....",
    "##.####.##",
    "##.####.##",
    "....##....",
    "..........",
    "....##....",
    "....##....",
]


class GridWorld(NavigationWorld):
    """Configurations given as (ASCII layout, slope) pairs on the [-1, 1]^2 arena."""

    arena = ARENA
    start = START

    def __init__(
        self,
        layouts: list[list[str]],
        slopes: list[SlopeSpec],
        probs: tuple[float, ...],
        names: tuple[str, ...],
    ) -> None:
        if not len(layouts) == len(slopes) == len(probs) == len(names):
            raise ValueError("one layout, slope, probability and name per configuration")
        self.layouts = layouts
        self.slopes = slopes
        self.walls = tuple(walls_from_ascii(rows) for rows in layouts)
        self.config_probs = tuple(probs)
        self.config_names = tuple(names)
        super().__init__()

    def _build_tensors(self) -> None:
        super()._build_tensors()
        kw = dict(device=self.device, dtype=self.dtype)
        self._slope_dir = torch.tensor([s.direction for s in self.slopes], **kw)  # (C, 2)
        self._slope_mean = torch.tensor([s.mean for s in self.slopes], **kw)  # (C,)
        big = 1e9
        regions = [s.region or Box(-big, -big, big, big) for s in self.slopes]
        self._slope_region = torch.tensor([(r.x0, r.y0, r.x1, r.y1) for r in regions], **kw)

    def force(
        self, positions: torch.Tensor, configs: torch.Tensor, generator: torch.Generator | None
    ) -> torch.Tensor:
        n = positions.shape[0]
        # Standard truncated normal scaled per configuration: magnitude ~ N(mean, std) in range.
        # Sampled once per agent so that every configuration shares one random stream.
        z = torch.randn(n, device=self.device, dtype=torch.float64, generator=generator)
        mean = self._slope_mean[configs].double()
        lo = (SLOPE_RANGE[0] - mean) / SLOPE_STD
        hi = (SLOPE_RANGE[1] - mean) / SLOPE_STD
        # Truncation at >= 7 standard deviations: resampling would change nothing measurable,
        # clamping keeps the support exact.
        magnitude = (mean + SLOPE_STD * z.clamp(lo, hi)).to(self.dtype)
        region = self._slope_region[configs]
        x, y = positions[:, 0], positions[:, 1]
        inside = (
            (x >= region[:, 0]) & (x <= region[:, 2]) & (y >= region[:, 1]) & (y <= region[:, 3])
        )
        magnitude = torch.where(inside & (mean > 0), magnitude, torch.zeros_like(magnitude))
        return magnitude[:, None] * self._slope_dir[configs]
