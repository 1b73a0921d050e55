"""Independent implementations of the arena's edge, for tests to hold hmepol_cli.envs against,
and the investigations (investigations/) to measure with:

- :func:`slide_path`: the reference's edge rule on one move, written out on scalars;
- :func:`edge_distance`: how far agents pushing north into the edge stay from it;
- the reference implementation's three defects as switches on our slope and multigrid worlds
  (:func:`make_variant`, :func:`reference_edge`; investigations/reference_defects.py measures
  what each costs in entropy).

The reference implementation of the worlds is the public Mepol code ([22] in the README's
references); docs/worlds.md states its edge rule.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import torch

from hmepol_cli.envs.base import EDGE_ROUNDS, NavigationWorld, _segment_touches_box
from hmepol_cli.envs.multigrid import MultiGridWorld
from hmepol_cli.envs.slope import SlopeWorld

DEFECTS = ("leave", "tunnel", "corner")


def slide_path(
    p: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray, rounds: int = EDGE_ROUNDS
) -> list[np.ndarray] | None:
    """The points a move passes under the reference's edge rule (docs/worlds.md): its
    start, every point where it crosses an edge, its end; None if it is still turning after
    ``rounds`` crossings. At a crossing the rest of the move, outward part n and part t along
    the edge, becomes |n| along the edge in the direction of t and |t| back inside (t = 0:
    straight back by |n|); a point exactly on the edge counts as beyond it."""
    p, d = np.array(p, dtype=float), np.array(d, dtype=float)
    points = [p.copy()]
    for _ in range(rounds):
        crossing = None  # (fraction of d, axis) of the first edge ahead
        for axis in (0, 1):
            if d[axis] == 0:
                continue
            edge = hi[axis] if d[axis] > 0 else lo[axis]
            fraction = max((edge - p[axis]) / d[axis], 0.0)
            if fraction <= 1 and (crossing is None or fraction < crossing[0]):
                crossing = (fraction, axis)
        if crossing is None:
            points.append(p + d)
            return points
        fraction, axis = crossing
        outward = 1.0 if d[axis] > 0 else -1.0
        p = p + fraction * d
        p[axis] = hi[axis] if outward > 0 else lo[axis]
        points.append(p.copy())
        rest = (1 - fraction) * d
        n, t = abs(rest[axis]), rest[1 - axis]
        d = np.zeros(2)
        if t == 0:
            d[axis] = -outward * n
        else:
            d[axis], d[1 - axis] = -outward * abs(t), np.sign(t) * n
        if not d.any():
            return points
    return None


def edge_distance(world, n: int = 100, steps: int = 400, seed: int = 0) -> float:
    """Mean distance from the north edge of agents pushing north (mean action 0.2, sd 0.05) in
    multigrid configuration 7's open northern floor (no slope), after 50 steps."""
    g = torch.Generator().manual_seed(seed)
    configurations = torch.full((n,), 7)
    positions = torch.stack([torch.full((n,), 0.0), torch.full((n,), 0.5)], dim=1).double()
    positions = positions.to(world.dtype)
    gaps = []
    for t in range(steps):
        actions = torch.tensor([0.0, 0.2]) + 0.05 * torch.randn(n, 2, generator=g)
        positions = world.step(positions, actions.to(world.dtype), configurations, g)
        if t >= 50:
            gaps.append(world.arena.y1 - positions[:, 1])
    return float(torch.cat(gaps).mean())


# The reference turns a move off the edges at most five times (recursion depth 0-4); at the
# fifth it gives up and returns the last crossing point.
REFERENCE_ROUNDS = 5


# ------------------------------------------------------------------ the reference's edge rule
def _to_reference(v: torch.Tensor) -> torch.Tensor:
    """Our frame (x east, y north) -> the reference's (first axis south, second east)."""
    return torch.stack([-v[:, 1], v[:, 0]], dim=1)


def _from_reference(v: torch.Tensor) -> torch.Tensor:
    return torch.stack([v[:, 1], -v[:, 0]], dim=1)


def _plus_minus(condition: torch.Tensor) -> torch.Tensor:
    return torch.where(condition, 1.0, -1.0).to(torch.float64)


def _crossing(p: torch.Tensor, d: torch.Tensor, edge: torch.Tensor, axis: int) -> torch.Tensor:
    """The other coordinate of the point where the line p + s d meets ``edge`` on ``axis``, as
    the reference computes it: from the slope of the move, and the agent's own coordinate
    (clipped to the arena) when that slope is not finite or the point lies beyond the arena."""
    other = 1 - axis
    ratio = d[:, other] / d[:, axis]  # +-inf or NaN where the move runs along the edge
    at = ratio * (edge - p[:, axis]) + p[:, other]
    fallback = p[:, other].clamp(-1.0, 1.0)
    bad = ~torch.isfinite(ratio) | ~(at.abs() <= 1.0)
    return torch.where(bad, fallback, at)


def _reference_turn(p: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """One turn of the reference's edge rule, in its frame, for moves that end at or beyond an
    edge of [-1, 1]^2: -> (crossing point q, turned remainder); the move ends at q + remainder
    unless that is beyond an edge again. (N, 2) float64 each."""
    e = p + d
    beyond = e.abs() >= 1.0
    # Both edges reached: the angle test (from the first axis) picks the one to turn off.
    corner = torch.sign(e)
    to_corner = corner - p
    angle_corner = torch.rad2deg(torch.arccos(to_corner[:, 0] / to_corner.norm(dim=1)))
    angle_move = torch.rad2deg(torch.arccos(d[:, 0] / d.norm(dim=1)))
    second_axis = beyond.all(dim=1) & (angle_move >= angle_corner)
    first_axis = beyond[:, 0] & ~second_axis
    # The edge crossed on the first axis: its side is the agent's own (start) side.
    edge0 = -_plus_minus(p[:, 0] < 0)
    q1 = _crossing(p, d, edge0, 0)
    along = e[:, 1] - q1
    s0 = _plus_minus(d[:, 1] >= 0) * _plus_minus(e[:, 0] < 0)
    q_first = torch.stack([edge0, q1], dim=1)
    turn_first = torch.stack([s0 * along, s0 * (edge0 - e[:, 0])], dim=1)
    # ... or on the second axis.
    edge1 = -_plus_minus(p[:, 1] < 0)
    q0 = _crossing(p, d, edge1, 1)
    along = e[:, 0] - q0
    s1 = torch.where(e[:, 1] < 0, _plus_minus(d[:, 0] > 0), -_plus_minus(d[:, 0] >= 0))
    q_second = torch.stack([q0, edge1], dim=1)
    turn_second = torch.stack([s1 * (edge1 - e[:, 1]), s1 * along], dim=1)
    pick = first_axis[:, None]
    return torch.where(pick, q_first, q_second), torch.where(pick, turn_first, turn_second)


def reference_edge(
    positions: torch.Tensor, displacement: torch.Tensor, walls: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Where a move ends under the reference's edge rule on the arena [-1, 1]^2, and (given
    ``walls`` (N or 1, W, 4)) whether a straight piece of its path touches a wall.

    The rule as the reference applies it, turn after turn, from wherever the agent is (inside
    the arena or outside it): the crossing point and the quarter turn of the remainder, with
    its angle test for a move that ends beyond two edges. positions, displacement (N, 2) ->
    (end (N, 2), blocked (N,) bool; all False without ``walls``)."""
    dtype = positions.dtype
    p = _to_reference(positions.double())
    d = _to_reference(displacement.double())
    end = p + d
    active = (end.abs() >= 1.0).any(dim=1)
    blocked = torch.zeros(len(p), dtype=torch.bool, device=p.device)

    def touches(start: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
        if walls is None:
            return torch.zeros_like(blocked)
        start, delta = _from_reference(start).to(dtype), _from_reference(delta).to(dtype)
        return _segment_touches_box(start, delta, walls)

    if walls is not None:
        blocked |= ~active & touches(p, d)
    for level in range(REFERENCE_ROUNDS):
        if not bool(active.any()):
            break
        q, turned = _reference_turn(p, d)
        blocked |= active & touches(p, q - p)
        if level == REFERENCE_ROUNDS - 1:  # it gives up: the last crossing point
            end = torch.where(active[:, None], p, end)
            break
        new = q + turned
        again = (new.abs() >= 1.0).any(dim=1)
        settled = active & ~again
        blocked |= settled & touches(q, turned)
        end = torch.where(settled[:, None], new, end)
        active = active & again
        p = torch.where(active[:, None], q, p)
        d = torch.where(active[:, None], turned, d)
    return _from_reference(end).to(dtype), blocked


# ------------------------------------------------------------------ our worlds with the defects
class ReferenceDefects:
    """Mixed into one of our grid worlds: its step with some of the reference's defects.

    ``defects`` is a subset of :data:`DEFECTS`; none gives our world exactly."""

    def __init__(self, defects: Iterable[str] = (), edge: str = "slide") -> None:
        unknown = set(defects) - set(DEFECTS)
        if unknown:
            raise ValueError(f"unknown defects {sorted(unknown)}; choose from {DEFECTS}")
        if edge != "slide":
            raise ValueError("the defects are emulated on the reference's edge rule (slide)")
        self.defects = frozenset(defects)
        super().__init__(edge=edge)

    def force(self, positions, configurations, noise, strength=None):  # noqa: D102
        if "leave" in self.defects:
            # The reference's slope region is a band of its first (north-south) coordinate only:
            # an agent beyond the east or west edge is still pushed. Our regions span the
            # arena's width, so clamping east-west into the arena reads them the same way.
            lo, hi = self._arena_lo[0], self._arena_hi[0]
            positions = torch.stack([positions[:, 0].clamp(lo, hi), positions[:, 1]], dim=1)
        return super().force(positions, configurations, noise, strength)

    def move(self, positions, displacement, configurations, push_noise):  # noqa: D102
        if self._shared_obstacles is None:
            walls = self._walls.index_select(0, configurations)
        else:
            walls = self._walls[:1]
        lo, hi = self._arena_lo, self._arena_hi
        tunnel = "tunnel" in self.defects

        moved, hit = self._slide(positions, displacement, walls)
        theirs = torch.zeros(len(positions), dtype=torch.bool, device=positions.device)
        if "corner" in self.defects:  # a move that ends beyond two edges at once
            end = positions + displacement
            theirs |= ((end <= lo) | (end >= hi)).all(dim=1)
        if "leave" in self.defects:  # an agent outside the arena: only the reference's rule
            theirs |= ((positions < lo) | (positions > hi)).any(dim=1)
        if bool(theirs.any()):
            ref_end, ref_hit = reference_edge(positions, displacement, walls)
            moved = torch.where(theirs[:, None], ref_end, moved)
            hit = torch.where(theirs, ref_hit, hit)
        if tunnel:
            hit = self.inside_wall(moved, configurations)

        back = -torch.sign(displacement) * push_noise * self.push_back
        if "leave" in self.defects:
            pushed = positions + back
            stuck = _segment_touches_box(positions, back, walls)
        else:
            pushed, stuck = self._slide(positions, back, walls)
        if tunnel:
            stuck = self.inside_wall(pushed, configurations)
        fallback = torch.where(stuck[:, None], positions, pushed)
        return torch.where(hit[:, None], fallback, moved)


class ReferenceSlope(ReferenceDefects, SlopeWorld):
    """The slope world with some of the reference's defects."""


class ReferenceMultiGrid(ReferenceDefects, MultiGridWorld):
    """MultiGrid with some of the reference's defects."""


WORLDS: dict[str, type[NavigationWorld]] = {
    "slope": ReferenceSlope,
    "multigrid": ReferenceMultiGrid,
}


def make_variant(name: str, defects: Iterable[str]) -> NavigationWorld:
    """World ``name`` (slope | multigrid) with ``defects``, in float64 on the CPU."""
    return WORLDS[name](defects=defects).to("cpu", torch.float64)
