"""Where the initial kNN entropy differs from the reference's: its three defects, one at a time.

Side by side with the public reference implementation of the worlds ([22]; docs/worlds.md)
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
``investigations.worlds`` (std exp(-1.5); 100 trajectories x 400 steps, the same seeds for every
variant, so every variant sees the same actions and world noise): the kNN entropy (k = 30) of
all 40,000 states and its mean over mini-batches of 5 trajectories, the share of states outside
the arena and the share within 0.05 of the start room's north wall, for ours, ours with each
defect alone and ours with all three::

    python -m investigations.reference_defects              # seeds 0-2, about 2 minutes, one core
    python -m investigations.reference_defects --seeds $(seq 0 19) --pairs   # each one's share
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Iterable
from itertools import combinations

import torch

from benchmarks.measure import cpu_name
from hmepol_cli import estimators
from investigations.worlds import CASES, zero_mean_states
from tests.reference_edges import DEFECTS, make_variant

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
NORTH_WALL_BAND = 0.05


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
