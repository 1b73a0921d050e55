"""Where the initial kNN entropy differs from the reference's: its three defects, one at a time.

Side by side with the public reference implementation of the worlds ([22]; REFERENCE_WORLDS.md)
on identical actions, our edge rule matches where it matters, yet the initial kNN entropy sits
~0.1-0.14 nats below the reference's. What is left is the reference's own behaviour, which this
project does not copy. Here each of its three defects is emulated as a switch on top of our
slope and multigrid worlds (``hmepol_cli.envs`` is not touched):

- ``leave``: the wall push-back is not kept in the arena (the reference adds it to the position
  and checks only the walls), so an agent near an edge can be pushed out of the arena. What the
  reference then does with an agent outside comes with it: its edge rule from a point outside
  (:func:`reference_edge`; ours never starts outside) and its slope region, which looks only at
  the north-south coordinate (the slope keeps pushing an agent beyond the east or west edge);
- ``tunnel``: only a move's end point is checked against the walls, not its path, so moves cut
  wall corners and cross walls thinner than the move;
- ``corner``: a move whose end lies beyond two edges at once is turned off the edge the
  reference's angle test picks. The test compares the angle between the move and the
  reference's first axis (our south) with that of the line from the agent to the corner; that
  picks the edge the path reaches first in the two southern corners, and the edge it reaches
  *second* in the two northern ones (north-west and north-east), where the reference then takes
  the agent's own projection on that edge as the crossing point and turns the whole remainder
  from there: (-0.95, 0.9) + (-0.2, 0.15) ends at (-1.0, 0.8) (ours: (-0.866, 0.934)), and
  (0.95, 0.9) + (0.2, 0.15) at (1.0, 0.8). Single-edge moves and the southern corners agree
  with ours (tests/test_reference_defects.py).

For slope configs 0 and 1 and multigrid config 0, under the zero-mean start policy of
``benchmarks.worlds`` (std exp(-1.5); 100 trajectories x 400 steps, the same seeds for every
variant, so every variant sees the same actions and world noise): the kNN entropy (k = 30) of
all 40,000 states and its mean over mini-batches of 5 trajectories, the share of states outside
the arena and the share within 0.05 of the start room's north wall, for ours, ours with each
defect alone and ours with all three::

    python -m benchmarks.reference_defects              # seeds 0-2, about 2 minutes, one core
    python -m benchmarks.reference_defects --seeds $(seq 0 19) --pairs   # each one's share
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Iterable
from itertools import combinations

import torch

from benchmarks.measure import cpu_name
from benchmarks.worlds import CASES, zero_mean_states
from hmepol_cli import estimators
from hmepol_cli.envs.base import NavigationWorld, _segment_touches_box
from hmepol_cli.envs.multigrid import MultiGridWorld
from hmepol_cli.envs.slope import SlopeWorld

DEFECTS = ("leave", "tunnel", "corner")
VARIANTS: dict[str, tuple[str, ...]] = {
    "ours": (),
    "+ leaves the arena": ("leave",),
    "+ tunnels through walls": ("tunnel",),
    "+ corner rule": ("corner",),
    "+ all three": DEFECTS,
}
# With --pairs: every subset of the defects, for a split of the total among them (Shapley).
PAIRS: dict[str, tuple[str, ...]] = {
    "+ leaves + tunnels": ("leave", "tunnel"),
    "+ leaves + corner rule": ("leave", "corner"),
    "+ tunnels + corner rule": ("tunnel", "corner"),
}
NAMES = {"leave": "leaving the arena", "tunnel": "tunnelling", "corner": "the corner rule"}
# The reference turns a move off the edges at most five times (recursion depth 0-4); at the
# fifth it gives up and returns the last crossing point.
REFERENCE_ROUNDS = 5
NORTH_WALL_BAND = 0.05


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


# ------------------------------------------------------------------ the measurement
def measure_variant(
    name: str, config: int, defects: Iterable[str], n: int, steps: int, seed: int
) -> dict[str, float]:
    """The numbers of one world, configuration, set of defects and seed."""
    world = make_variant(name, defects)
    states = zero_mean_states(world, config, n, steps, seed)
    flat = states.reshape(-1, 2)
    x, y = flat[:, 0], flat[:, 1]
    a = world.arena
    outside = (x < a.x0) | (x > a.x1) | (y < a.y0) | (y > a.y1)
    whole = estimators.nearest_neighbours(flat[None].float(), 30)
    batches = estimators.nearest_neighbours(estimators.particles_by_batch(states.float(), 5), 30)
    return {
        "entropy_all": float(estimators.knn_entropy(whole)[0]),
        "entropy_batches": float(estimators.knn_entropy(batches).mean()),
        "outside": float(outside.double().mean()),
        "north_wall": float(((y >= a.y1 - NORTH_WALL_BAND) & (x <= -0.2)).double().mean()),
        "south": float((y < 0).double().mean()),
    }


METRICS = ("entropy_all", "entropy_batches", "outside", "north_wall", "south")


def _mean_and_error(values: list[float]) -> tuple[float, float]:
    """Mean and its standard error over seeds (NaN error with one seed)."""
    m = sum(values) / len(values)
    if len(values) < 2:
        return m, math.nan
    var = sum((v - m) ** 2 for v in values) / (len(values) - 1)
    return m, math.sqrt(var / len(values))


def shapley(entropy: dict[frozenset, float], defect: str) -> float:
    """The share of the change (all defects against none) that falls to ``defect``: its mean
    marginal change over the orders in which the defects can be added. ``entropy`` holds
    every subset of :data:`DEFECTS`."""
    others = [d for d in DEFECTS if d != defect]
    share = 0.0
    for size in range(len(DEFECTS)):
        subsets = [frozenset(c) for c in combinations(others, size)]
        weight = math.factorial(size) * math.factorial(len(DEFECTS) - size - 1)
        weight /= math.factorial(len(DEFECTS))
        share += weight * sum(entropy[c | {defect}] - entropy[c] for c in subsets)
    return share


def measure(
    n: int, steps: int, seeds: list[int], pairs: bool = False
) -> tuple[list[dict], list[dict]]:
    """One row per world and variant: each metric's mean over seeds, and the change of the
    entropies from ours, paired seed by seed (mean and standard error). With ``pairs``, also
    each defect's share of the total change (Shapley), per world. -> (rows, shares)"""
    rows, shares = [], []
    variants = {**VARIANTS, **PAIRS} if pairs else VARIANTS
    for name, config in CASES:
        runs = {
            label: [measure_variant(name, config, defects, n, steps, s) for s in seeds]
            for label, defects in variants.items()
        }
        for label, values in runs.items():
            row = {"world": f"{name} {config}", "variant": label, "seeds": len(seeds)}
            for key in METRICS:
                row[key] = _mean_and_error([v[key] for v in values])[0]
            for key in ("entropy_all", "entropy_batches"):
                deltas = [v[key] - o[key] for v, o in zip(values, runs["ours"], strict=True)]
                row[f"{key}_change"], row[f"{key}_error"] = _mean_and_error(deltas)
            rows.append(row)
        if not pairs:
            continue
        for defect in DEFECTS:
            share = {"world": f"{name} {config}", "defect": NAMES[defect]}
            for key in ("entropy_all", "entropy_batches"):
                per_seed = [
                    shapley(
                        {frozenset(d): runs[label][i][key] for label, d in variants.items()},
                        defect,
                    )
                    for i in range(len(seeds))
                ]
                share[key], share[f"{key}_error"] = _mean_and_error(per_seed)
            shares.append(share)
    return rows, shares


def _change(row: dict, key: str) -> str:
    if row["variant"] == "ours":
        return ""
    error = row[f"{key}_error"]
    return f"{row[f'{key}_change']:+.3f}" + ("" if math.isnan(error) else f" ± {error:.3f}")


def markdown(
    rows: list[dict], seeds: list[int], seconds: float, n: int = 100, steps: int = 400
) -> str:
    several = len(seeds) > 1
    lines = [
        f"Zero-mean start policy (std {math.exp(-1.5):.3f}), {n} trajectories x {steps} steps per "
        f"world and seed; seed{'s' if several else ''} {', '.join(map(str, seeds))}, the same "
        "actions and world noise in every variant of a world and seed; kNN k = 30."
        + (
            " Numbers are means over the seeds; a change is ours' subtracted seed by seed "
            "(± its standard error)."
            if several
            else ""
        )
        + f" Machine: {cpu_name()}, {torch.get_num_threads()} thread(s), {seconds:.0f} s.",
        "",
        "| world, config | variant | kNN entropy, all states | change | mean over mini-batches "
        "of 5 trajectories | change | outside the arena | within 0.05 of the north wall | "
        "in the south |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['world']} | {r['variant']} | {r['entropy_all']:.3f} | "
            f"{_change(r, 'entropy_all')} | {r['entropy_batches']:.3f} | "
            f"{_change(r, 'entropy_batches')} | {100 * r['outside']:.2f}% | "
            f"{r['north_wall']:.3f} | {r['south']:.3f} |"
        )
    return "\n".join(lines)


def shares_markdown(rows: list[dict], shares: list[dict]) -> str:
    """Each defect's share of the change with all three (Shapley: its marginal change averaged
    over the orders in which the defects can be added; the shares sum to the total)."""
    total = {r["world"]: r for r in rows if r["variant"] == "+ all three"}
    lines = [
        "Each defect's share of the change with all three: its change averaged over the six "
        "orders in which the three can be added (Shapley; the shares add up to the total).",
        "",
        "| world, config | defect | share, all states | share, mini-batches | of the total |",
        "|---|---|---|---|---|",
    ]

    def pm(value: float, error: float) -> str:
        return f"{value:+.3f}" + ("" if math.isnan(error) else f" ± {error:.3f}")

    for s in shares:
        t = total[s["world"]]
        lines.append(
            f"| {s['world']} | {s['defect']} | {pm(s['entropy_all'], s['entropy_all_error'])} | "
            f"{pm(s['entropy_batches'], s['entropy_batches_error'])} | "
            f"{100 * s['entropy_all'] / t['entropy_all_change']:.0f}% |"
        )
    for world, t in total.items():
        lines.append(
            f"| {world} | all three | {_change(t, 'entropy_all')} | "
            f"{_change(t, 'entropy_batches')} | 100% |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trajectories", type=int, default=100)
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument(
        "--pairs", action="store_true", help="also the pairs of defects, and each one's share"
    )
    ns = parser.parse_args(argv)
    torch.set_num_threads(ns.threads)
    start = time.perf_counter()
    rows, shares = measure(ns.trajectories, ns.steps, ns.seeds, ns.pairs)
    print(markdown(rows, ns.seeds, time.perf_counter() - start, ns.trajectories, ns.steps))
    if shares:
        print()
        print(shares_markdown(rows, shares))


if __name__ == "__main__":
    main()
