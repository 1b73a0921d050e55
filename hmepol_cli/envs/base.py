"""Batched continuous 2-D navigation worlds: the common physics of slope, corridor and multigrid.

A world is a *class* of configurations M_1..M_I (thesis 2.1.1) that share the arena, the state
space (position (x, y)) and the action space (a displacement clipped to [-0.2, 0.2] per axis).
Configurations differ by their walls and by an external force (a slope, a wind) that is added to
the agent's displacement. Every method works on a whole batch of agents at once, as tensors, on
the device the world was moved to.

Walls are solid axis-aligned rectangles. A step moves along x, then along y; each axis move is
stopped just short of the first wall face it would cross (and by the arena's edge), so the agent
slides along walls, never tunnels through a thin wall however large the step, and never ends
strictly inside a wall or outside the arena.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

MAX_ACTION = 0.2  # per-axis action bound of every world (thesis 5.1)
WALL_GAP = 1e-4  # how far short of a wall face a blocked move stops


@dataclass(frozen=True)
class Box:
    """Axis-aligned rectangle [x0, x1] x [y0, y1]."""

    x0: float
    y0: float
    x1: float
    y1: float

    @property
    def area(self) -> float:
        return (self.x1 - self.x0) * (self.y1 - self.y0)

    def contains(self, x: float, y: float) -> bool:
        return self.x0 <= x <= self.x1 and self.y0 <= y <= self.y1


class NavigationWorld:
    """A class of 2-D navigation configurations, stepped in batches.

    Subclasses set ``name``, ``arena``, ``start``, ``config_names``, ``config_probs`` and
    ``walls`` (one list of :class:`Box` per configuration) and implement :meth:`force`.
    """

    name: str = "world"
    state_dim: int = 2
    action_dim: int = 2
    max_action: float = MAX_ACTION
    arena: Box
    start: Box
    config_names: tuple[str, ...]
    config_probs: tuple[float, ...]
    walls: tuple[tuple[Box, ...], ...]

    def __init__(self) -> None:
        self.device = torch.device("cpu")
        self.dtype = torch.float32
        self._build_tensors()

    # ------------------------------------------------------------------ set-up
    @property
    def n_configs(self) -> int:
        return len(self.config_probs)

    def to(self, device: torch.device | str, dtype: torch.dtype = torch.float32) -> NavigationWorld:
        self.device, self.dtype = torch.device(device), dtype
        self._build_tensors()
        return self

    def _build_tensors(self) -> None:
        most = max(1, max(len(w) for w in self.walls))
        # Padding rectangles are empty (x0 > x1), so no agent is ever inside their band.
        table = np.tile(np.array([1.0, 1.0, -1.0, -1.0]) * 1e9, (self.n_configs, most, 1))
        for c, boxes in enumerate(self.walls):
            for i, b in enumerate(boxes):
                table[c, i] = (b.x0, b.y0, b.x1, b.y1)
        self._walls = torch.tensor(table, device=self.device, dtype=self.dtype)  # (C, W, 4)
        # Configurations that share their walls (slope, corridor) need no per-agent gather.
        self._shared_walls = self._walls[:1] if len(set(self.walls)) == 1 else None  # (1, W, 4)
        self._probs = torch.tensor(self.config_probs, device=self.device, dtype=torch.float64)

    # ------------------------------------------------------------------ dynamics
    def sample_configs(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """Draw n configuration indices from p_M. (n,) long."""
        return torch.multinomial(self._probs, n, replacement=True, generator=generator)

    def reset(
        self, configs: torch.Tensor, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """Initial positions, uniform in the start box. configs (N,) -> (N, 2)."""
        u = torch.rand(
            configs.shape[0], 2, device=self.device, dtype=self.dtype, generator=generator
        )
        lo = torch.tensor([self.start.x0, self.start.y0], device=self.device, dtype=self.dtype)
        hi = torch.tensor([self.start.x1, self.start.y1], device=self.device, dtype=self.dtype)
        return lo + u * (hi - lo)

    def force(
        self, positions: torch.Tensor, configs: torch.Tensor, generator: torch.Generator | None
    ) -> torch.Tensor:
        """External displacement (slope, wind) at each position. (N, 2) -> (N, 2)."""
        return torch.zeros_like(positions)

    def step(
        self,
        positions: torch.Tensor,
        actions: torch.Tensor,
        configs: torch.Tensor,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Next positions: clipped action plus the configuration's force, stopped by walls.

        positions (N, 2), actions (N, 2), configs (N,) -> (N, 2).
        """
        displacement = actions.clamp(-self.max_action, self.max_action)
        displacement = displacement + self.force(positions, configs, generator)
        return self.move(positions, displacement, configs)

    def move(
        self, positions: torch.Tensor, displacement: torch.Tensor, configs: torch.Tensor
    ) -> torch.Tensor:
        if self._shared_walls is None:
            walls = self._walls.index_select(0, configs)  # (N, W, 4)
        else:
            walls = self._shared_walls  # (1, W, 4)
        x, y = positions[:, 0], positions[:, 1]
        x = _slide(
            x, y, displacement[:, 0], walls[..., 0], walls[..., 2], walls[..., 1], walls[..., 3]
        )
        x = x.clamp(self.arena.x0, self.arena.x1)
        y = _slide(
            y, x, displacement[:, 1], walls[..., 1], walls[..., 3], walls[..., 0], walls[..., 2]
        )
        y = y.clamp(self.arena.y0, self.arena.y1)
        return torch.stack((x, y), dim=-1)

    # ------------------------------------------------------------------ geometry
    def inside_wall(self, positions: torch.Tensor, configs: torch.Tensor) -> torch.Tensor:
        """True where a position lies strictly inside one of its configuration's walls. (N,)"""
        walls = self._walls[configs]
        x, y = positions[:, :1], positions[:, 1:]
        inside = (
            (x > walls[..., 0]) & (x < walls[..., 2]) & (y > walls[..., 1]) & (y < walls[..., 3])
        )
        return inside.any(dim=-1)

    def inside_arena(self, positions: torch.Tensor) -> torch.Tensor:
        a = self.arena
        x, y = positions[:, 0], positions[:, 1]
        return (x >= a.x0) & (x <= a.x1) & (y >= a.y0) & (y <= a.y1)

    def free_mask(self, config: int, resolution: int = 1000) -> np.ndarray:
        """Raster of free space, (resolution, resolution) bool, row 0 at y0 (bottom)."""
        a = self.arena
        xs = np.linspace(a.x0, a.x1, resolution + 1)
        ys = np.linspace(a.y0, a.y1, resolution + 1)
        cx, cy = (xs[:-1] + xs[1:]) / 2, (ys[:-1] + ys[1:]) / 2
        gx, gy = np.meshgrid(cx, cy)
        free = np.ones_like(gx, dtype=bool)
        for b in self.walls[config]:
            free &= ~((gx > b.x0) & (gx < b.x1) & (gy > b.y0) & (gy < b.y1))
        return free

    def free_area(self, config: int | None = None) -> float:
        """Area of free space of one configuration (or of the least free one when None).

        log(free area) is the entropy of the uniform distribution over free space: the
        highest entropy any visitation can reach.
        """
        if config is None:
            return min(self.free_area(c) for c in range(self.n_configs))
        mask = self.free_mask(config)
        return float(mask.mean()) * self.arena.area


def _slide(
    along: torch.Tensor,
    across: torch.Tensor,
    delta: torch.Tensor,
    lo: torch.Tensor,
    hi: torch.Tensor,
    band_lo: torch.Tensor,
    band_hi: torch.Tensor,
) -> torch.Tensor:
    """Move ``along`` one axis by ``delta``, stopping short of the first wall face crossed.

    along, across, delta (N,); lo, hi, band_lo, band_hi (N, W) or (1, W): each wall spans [lo, hi]
    on the moving axis and (band_lo, band_hi) on the other one.
    """
    target = (along + delta)[:, None]
    start = along[:, None]
    # Closed band: a path along the seam of two touching walls, or along a wall's corner,
    # is blocked too (conservative; an agent never slides *along* a face, it stops WALL_GAP short).
    in_band = (across[:, None] >= band_lo) & (across[:, None] <= band_hi)
    inf = torch.full_like(lo, float("inf"))
    # Moving forwards: a wall whose near face lies between start and target stops us.
    hit_fwd = in_band & (lo >= start) & (lo < target)
    stop_fwd = torch.where(hit_fwd, lo - WALL_GAP, inf).amin(dim=-1)
    # Moving backwards: the far face of a wall behind us.
    hit_back = in_band & (hi <= start) & (hi > target)
    stop_back = torch.where(hit_back, hi + WALL_GAP, -inf).amax(dim=-1)
    moved = along + delta
    moved = torch.where(delta > 0, torch.minimum(moved, stop_fwd), moved)
    moved = torch.where(delta < 0, torch.maximum(moved, stop_back), moved)
    return moved


def truncated_normal(
    mean: float,
    std: float,
    low: float,
    high: float,
    shape: tuple[int, ...],
    *,
    device: torch.device,
    dtype: torch.dtype,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Samples of N(mean, std^2) truncated to [low, high], by inverting the CDF."""
    normal = torch.distributions.Normal(torch.tensor(mean, dtype=torch.float64), std)
    cdf_lo = float(normal.cdf(torch.tensor(low, dtype=torch.float64)))
    cdf_hi = float(normal.cdf(torch.tensor(high, dtype=torch.float64)))
    u = torch.rand(shape, device=device, dtype=torch.float64, generator=generator)
    z = torch.special.ndtri(cdf_lo + u * (cdf_hi - cdf_lo))
    return (mean + std * z).clamp(low, high).to(dtype)
