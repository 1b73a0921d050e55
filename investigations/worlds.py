"""How the arena's edge rule shapes a zero-mean policy's visitation (docs/worlds.md).

Under the reference's start policy (zero-mean Gaussian actions, std exp(-1.5) = 0.22; 100
trajectories x 400 steps per configuration), for each edge rule: the share of steps in the
southern half, the share within 0.05 of the start room's north wall (the arena's north edge
along the north-west room, x <= -0.2), the kNN entropy (k = 30) of all 40,000 states and its
mean over mini-batches of 5 trajectories (2,000 particles, the thesis' B x T), and, for agents
pushed steadily north into the edge in open floor, their mean distance from it::

    python -m investigations.worlds                 # both rules, slope 0/1, multigrid 0
"""

from __future__ import annotations

import argparse
import math

import torch
from omegaconf import OmegaConf

from hmepol_cli import estimators
from hmepol_cli.envs import make_world
from tests.reference_edges import edge_distance

CASES = (("slope", 0), ("slope", 1), ("multigrid", 0))
STD = math.exp(-1.5)


def zero_mean_states(world, config: int, n: int, steps: int, seed: int) -> torch.Tensor:
    """States s_1..s_T of n trajectories under zero-mean actions of sd STD. (n, T, 2)"""
    g = torch.Generator().manual_seed(seed)
    configurations = torch.full((n,), config)
    positions = world.reset(configurations, g)
    visited = []
    for _ in range(steps):
        actions = STD * torch.randn(n, 2, generator=g, dtype=world.dtype)
        positions = world.step(positions, actions, configurations, g)
        visited.append(positions)
    return torch.stack(visited, dim=1)


def measure(edge: str, n: int, steps: int, seed: int) -> list[dict]:
    rows = []
    for name, config in CASES:
        world = make_world(OmegaConf.create({"name": name, "edge": edge})).to("cpu", torch.float64)
        states = zero_mean_states(world, config, n, steps, seed)
        flat = states.reshape(-1, 2)
        x, y = flat[:, 0], flat[:, 1]
        whole = estimators.nearest_neighbours(flat[None].float(), 30)
        batches = estimators.nearest_neighbours(
            estimators.particles_by_batch(states.float(), 5), 30
        )
        rows.append(
            {
                "edge": edge,
                "world": f"{name} {config}",
                "south": float((y < 0).double().mean()),
                "north_wall": float(((y >= world.arena.y1 - 0.05) & (x <= -0.2)).double().mean()),
                "entropy_all": float(estimators.knn_entropy(whole)[0]),
                "entropy_batches": float(estimators.knn_entropy(batches).mean()),
                "coinciding": 1.0 - len(torch.unique(flat, dim=0)) / len(flat),
            }
        )
    rows.append({"edge": edge, "world": "edge gap", "gap": edge_distance(world)})
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--edges", nargs="+", default=["slide", "mirror"])
    parser.add_argument("--trajectories", type=int, default=100)
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--seed", type=int, default=0)
    ns = parser.parse_args(argv)
    print(
        "| edge | world, config | steps in the south | within 0.05 of the start room's north "
        "wall | kNN entropy, 40,000 states | mean over mini-batches of 2,000 | coinciding |"
    )
    print("|---|---|---|---|---|---|---|")
    for edge in ns.edges:
        for r in measure(edge, ns.trajectories, ns.steps, ns.seed):
            if "gap" in r:
                print(f"| {edge} | pushed north into the edge: mean gap {r['gap']:.4f} | | | | | |")
                continue
            print(
                f"| {edge} | {r['world']} | {r['south']:.3f} | {r['north_wall']:.3f} | "
                f"{r['entropy_all']:.3f} | {r['entropy_batches']:.3f} | {r['coinciding']:.4f} |"
            )


if __name__ == "__main__":
    main()
