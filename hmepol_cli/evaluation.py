"""Fresh rollouts of trained policies in every configuration, saved as raw data and pictures.

``eval/<name>.npz`` holds ``positions_c{c}``: (n, T + 1, 2) float32 positions of n trajectories in
configuration c (in a Gymnasium world, the observation's two ``env.projection`` indices). The
report draws heatmaps and trajectory plots from these files, so it never has to run a policy.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from hmepol_cli.envs import World
from hmepol_cli.plots import save_run_plots
from hmepol_cli.population import PolicyPopulation
from hmepol_cli.rollout import collect
from hmepol_cli.run import save_positions


def rollout_positions(
    world: World,
    population: PolicyPopulation,
    trajectories: int,
    horizon: int,
    generators: Sequence[torch.Generator],
) -> list[dict[int, np.ndarray]]:
    """Positions of ``trajectories`` fresh trajectories per configuration, for every member
    (member s with randomness from generators[s]). -> [{config: (n, T+1, 2)}] per member"""
    size = population.size
    positions: list[dict[int, np.ndarray]] = [{} for _ in range(size)]
    for c in range(world.n_configurations):
        configurations = torch.full((size, trajectories), c, dtype=torch.long, device=world.device)
        rollout = collect(world, population, None, configurations, horizon, generators)
        # What a heatmap draws: the position, or a Gymnasium world's two projection indices.
        states = world.plane(rollout.states).float().cpu().numpy()
        for s in range(size):
            positions[s][c] = states[s]
    return positions


def evaluate_and_save(
    world: World,
    population: PolicyPopulation,
    out_dirs: Sequence[Path],
    name: str,
    trajectories: int,
    horizon: int,
    generators: Sequence[torch.Generator],
    plot_trajectories: int = 5,
) -> list[Path]:
    """Roll out every member; save ``<out_dirs[s]>/<name>.npz`` and its heatmap and trajectory
    PNGs. -> the .npz paths"""
    positions = rollout_positions(world, population, trajectories, horizon, generators)
    paths = []
    for out_dir, member_positions in zip(out_dirs, positions, strict=True):
        path = Path(out_dir) / f"{name}.npz"
        save_positions(path, member_positions)
        save_run_plots(world, member_positions, Path(out_dir) / name, plot_trajectories)
        paths.append(path)
    return paths
