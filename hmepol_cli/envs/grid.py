"""Gridworlds on [-1, 1]^2 whose walls are laid out as 10 x 10 blocks, with a slope force.

Shared by the slope world (one layout, two slopes) and multigrid (ten layouts, ten slopes).
Maps are read as printed, north at the top (docs/worlds.md): the first row of a layout is
the northern edge y in [0.8, 1], the first column the western edge x in [-1, -0.8]. The start
area is the 0.5 x 0.5 square in the north-west corner.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from hmepol_cli.envs.base import MAX_ACTION, Box, NavigationWorld, lattice

ARENA = Box(-1.0, -1.0, 1.0, 1.0)
START = Box(-1.0, 0.5, -0.5, 1.0)  # north-west corner (docs/worlds.md)
NORTHERN_HALF = Box(-1.0, 0.0, 1.0, 1.0)  # the half that holds the start room
SLOPE_STD = MAX_ACTION / 20  # 0.01: sd of every slope's magnitude (reference)

NORTH, SOUTH, EAST = (0.0, 1.0), (0.0, -1.0), (1.0, 0.0)
# South-east: the magnitude is added to both axes, not normalised (reference).
SOUTH_EAST = (1.0, -1.0)


@dataclass(frozen=True)
class SlopeSpec:
    """A force ``magnitude * direction``, magnitude ~ N(mean, 0.01) truncated to [0, high],
    drawn afresh for every agent and step; only inside ``region`` (None: the whole arena).

    A magnitude of mean 0 is no slope at all.
    """

    direction: tuple[float, float] = (0.0, 0.0)
    mean: float = 0.0
    high: float = 0.0
    region: Box | None = None

    @classmethod
    def centred(
        cls, direction: tuple[float, float], mean: float, region: Box | None = None
    ) -> SlopeSpec:
        """Truncated to [0, 2 * mean], symmetric about the mean, as every slope of [22] is."""
        return cls(direction, mean, 2 * mean, region)


def walls_from_ascii(rows: list[str], arena: Box = ARENA) -> tuple[Box, ...]:
    """Rectangles for the '#' blocks of an ASCII layout (first row = north), one per run of a row
    merged with identical runs of the rows below it."""
    n_rows, n_cols = len(rows), len(rows[0])
    if any(len(r) != n_cols for r in rows):
        raise ValueError("every row of a layout must have the same length")
    w = (arena.x1 - arena.x0) / n_cols
    h = (arena.y1 - arena.y0) / n_rows
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

    def edge(value: float) -> float:  # -1 + 4 * 0.2 is -0.19999999999999996: say -0.2
        return round(value, 12)

    return tuple(
        Box(
            edge(arena.x0 + c0 * w),
            edge(arena.y1 - r1 * h),
            edge(arena.x0 + c1 * w),
            edge(arena.y1 - r0 * h),
        )
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
    force_noise = 1  # one uniform per agent and step: the slope's magnitude

    def __init__(
        self,
        layouts: list[list[str]],
        slopes: list[SlopeSpec],
        probs: tuple[float, ...],
        names: tuple[str, ...],
        edge: str = "slide",
    ) -> None:
        if not len(layouts) == len(slopes) == len(probs) == len(names):
            raise ValueError("one layout, slope, probability and name per configuration")
        self.layouts = layouts
        self.slopes = slopes
        self.walls = tuple(walls_from_ascii(rows) for rows in layouts)
        self.configuration_probs = tuple(probs)
        self.configuration_names = tuple(names)
        super().__init__(edge)

    def _build_tensors(self) -> None:
        super()._build_tensors()
        kw = dict(device=self.device, dtype=torch.float64)
        self._slope_dir = torch.tensor([s.direction for s in self.slopes], **kw)  # (C, 2)
        self._slope_on = torch.tensor([s.mean > 0 for s in self.slopes], device=self.device)
        # The truncation points as quantiles of N(mean, sd): inverse-CDF sampling is exact.
        mean = torch.tensor([s.mean for s in self.slopes], **kw)
        high = torch.tensor([s.high for s in self.slopes], **kw)
        normal = torch.distributions.Normal(0.0, 1.0)
        self._slope_mean = mean
        self._slope_cdf_lo = normal.cdf((0.0 - mean) / SLOPE_STD)  # (C,)
        self._slope_cdf_hi = normal.cdf((high - mean) / SLOPE_STD)
        self._slope_high = high
        big = 1e9
        regions = [s.region or Box(-big, -big, big, big) for s in self.slopes]
        self._slope_region = torch.tensor(
            [(r.x0, r.y0, r.x1, r.y1) for r in regions], device=self.device, dtype=self.dtype
        )

    def describe(self, config: int) -> str:
        slope = self.slopes[config]
        if slope.mean <= 0:
            return "no slope"
        text = f"slope {compass(slope.direction)} ~ N({slope.mean:.3g}, {SLOPE_STD:g})"
        if slope.region == NORTHERN_HALF:
            text += ", north half"
        return text

    def force_region(self, config: int) -> Box | None:
        slope = self.slopes[config]
        return (slope.region or self.arena) if slope.mean > 0 else None

    def arrow_candidates(self, config: int) -> tuple[list[tuple[np.ndarray, np.ndarray]], float]:
        """Arrows every other block, on block corners or on block centres (one-block corridors
        get arrows too)."""
        slope, a = self.slopes[config], self.arena
        if slope.mean <= 0:
            return [], 0.0
        r, n = slope.region or a, 5  # 0.4 apart
        block = (a.x1 - a.x0) / 10
        candidates = []
        for shift in (0.0, block / 2):
            points = lattice(a.x0, a.y0, a.x1, a.y1, n) - shift
            inside = (points[:, 0] >= max(r.x0, a.x0)) & (points[:, 0] <= min(r.x1, a.x1))
            inside &= (points[:, 1] >= max(r.y0, a.y0)) & (points[:, 1] <= min(r.y1, a.y1))
            points = points[inside]
            candidates.append(
                (points, np.tile(np.asarray(slope.direction, float), (len(points), 1)))
            )
        return candidates, 0.4 * (a.x1 - a.x0) / n  # 0.8 block: fits a one-block corridor

    def slope_magnitude(self, configurations: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """N(mean, 0.01) truncated to [0, high] of each agent's configuration, by inverting the
        CDF at a uniform draw. configurations (N,), noise (N,) in [0, 1) -> (N,) float64"""
        lo, hi = self._slope_cdf_lo[configurations], self._slope_cdf_hi[configurations]
        z = torch.special.ndtri(lo + noise.double() * (hi - lo))
        magnitude = self._slope_mean[configurations] + SLOPE_STD * z
        return magnitude.clamp(torch.zeros_like(magnitude), self._slope_high[configurations])

    def force(
        self,
        positions: torch.Tensor,
        configurations: torch.Tensor,
        noise: torch.Tensor,
        strength: torch.Tensor | None = None,
    ) -> torch.Tensor:
        magnitude = self.slope_magnitude(configurations, noise[:, 0])
        region = self._slope_region[configurations]
        x, y = positions[:, 0], positions[:, 1]
        inside = (x >= region[:, 0]) & (x <= region[:, 2]) & (y >= region[:, 1])
        inside &= (y <= region[:, 3]) & self._slope_on[configurations]
        magnitude = torch.where(inside, magnitude, torch.zeros_like(magnitude))
        return (magnitude[:, None] * self._slope_dir[configurations]).to(positions.dtype)


def compass(direction: tuple[float, float]) -> str:
    names = (
        "east",
        "north-east",
        "north",
        "north-west",
        "west",
        "south-west",
        "south",
        "south-east",
    )
    angle = math.degrees(math.atan2(direction[1], direction[0])) % 360
    return names[round(angle / 45) % 8]
