"""Fresh rollouts of a trained policy in every configuration, saved as raw data and pictures.

``eval/<name>.npz`` holds ``positions_c{c}``: (n, T + 1, 2) float32 positions of n trajectories in
configuration c. The report draws heatmaps and trajectory plots from these files, so it never
has to run a policy itself.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import torch

from hmepol_cli.checkpoint import atomic_write_bytes
from hmepol_cli.envs.base import NavigationWorld
from hmepol_cli.policies.base import Policy
from hmepol_cli.report.plots import save_run_plots
from hmepol_cli.rollout import collect


def rollout_positions(
    world: NavigationWorld,
    policy: Policy,
    trajectories: int,
    horizon: int,
    generator: torch.Generator,
) -> dict[int, np.ndarray]:
    """Positions of ``trajectories`` fresh trajectories per configuration. {c: (n, T+1, 2)}"""
    positions = {}
    for c in range(world.n_configs):
        configs = torch.full((trajectories,), c, dtype=torch.long, device=world.device)
        rollout = collect(world, policy, configs, horizon, generator)
        positions[c] = rollout.states.float().cpu().numpy()
    return positions


def save_positions(path: Path, positions: dict[int, np.ndarray]) -> None:
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **{f"positions_c{c}": p for c, p in positions.items()})
    atomic_write_bytes(path, buffer.getvalue())


def load_positions(path: Path) -> dict[int, np.ndarray]:
    with np.load(path, allow_pickle=False) as data:
        return {
            int(k.removeprefix("positions_c")): data[k]
            for k in data.files
            if k.startswith("positions_c")
        }


def evaluate_and_save(
    world: NavigationWorld,
    policy: Policy,
    out_dir: Path,
    name: str,
    trajectories: int,
    horizon: int,
    generator: torch.Generator,
    plot_trajectories: int = 10,
    plot_every: int = 10,
) -> Path:
    """Roll out, save ``<out_dir>/<name>.npz`` and the run's heatmap and trajectory PNGs."""
    positions = rollout_positions(world, policy, trajectories, horizon, generator)
    path = Path(out_dir) / f"{name}.npz"
    save_positions(path, positions)
    save_run_plots(world, positions, Path(out_dir) / name, plot_trajectories, plot_every)
    return path
