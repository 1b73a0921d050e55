"""What an episode's end does to the entropy estimate: MountainCarContinuous at the mountaincar
preset's estimate (20 trajectories x 400 steps in one mini-batch, k = 4, entropy on position
and velocity), driven by a policy that reaches the goal (it pushes with the velocity, the
energy-pumping policy, plus Gaussian noise of sd ``--noise``).

Gymnasium ends an episode at the goal. Before, the trajectory kept its last state for
the remaining steps as particles; now they are no particles (as the reference, whose
``real_traj_lengths`` drops them). This prints the kNN entropy (eq. 2.6) of the same states both
ways, and what the repeated copies do to it::

    python -m investigations.gym_particles
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np
import torch

from benchmarks.measure import cpu_name
from hmepol_cli import estimators


def energy_pumping(n: int, steps: int, noise: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """States s_1..s_T of n episodes (the last state repeated after an end) and which of them
    are live (reached before or at the end). -> (n, T, 2), (n, T) bool"""
    rng = np.random.default_rng(seed)
    states = np.zeros((n, steps, 2))
    live = np.zeros((n, steps), dtype=bool)
    for i in range(n):
        env = gym.make("MountainCarContinuous-v0", max_episode_steps=-1)
        obs, _ = env.reset(seed=seed + i)
        ended = False
        for t in range(steps):
            if not ended:
                push = np.sign(obs[1]) if obs[1] != 0 else 1.0
                action = np.clip(push + noise * rng.normal(), -1.0, 1.0)
                obs, _, terminated, truncated, _ = env.step(np.array([action], np.float32))
                live[i, t] = True
                ended = terminated or truncated
            states[i, t] = obs
        env.close()
    return states, live


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trajectories", type=int, default=20)
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--k", type=int, default=4)
    parser.add_argument("--noise", type=float, default=0.5)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    states, live = energy_pumping(args.trajectories, args.steps, args.noise, args.seed)
    particles = torch.from_numpy(states.reshape(1, -1, 2))
    mask = torch.from_numpy(live.reshape(1, -1))
    with_copies = estimators.nearest_neighbours(particles, args.k)
    live_only = estimators.nearest_neighbours(particles, args.k, live=mask)
    h_copies = float(estimators.knn_entropy(with_copies)[0])
    h_live = float(estimators.knn_entropy(live_only)[0])
    ended = int((~live.all(axis=1)).sum())
    copies = int((~live).sum())
    floor = float(estimators.floor_share(with_copies))
    print(f"Machine: {cpu_name()}; MountainCarContinuous-v0, energy-pumping policy + N(0, "
          f"{args.noise}), {args.trajectories} x {args.steps} steps, k = {args.k}, "
          f"seed {args.seed}")
    print()
    print("| particles | count | kNN entropy (nats) |")
    print("|---|---|---|")
    print(f"| every step, the last state repeated after an end (before) | {live.size} | "
          f"{h_copies:.3f} |")
    print(f"| live steps only (now) | {int(live.sum())} | {h_live:.3f} |")
    print()
    print(f"{ended} of {args.trajectories} episodes reached the goal; {copies} repeated copies, "
          f"{100 * floor:.1f}% of the particles at the volume floor with them; the difference "
          f"is {h_live - h_copies:.2f} nats.")


if __name__ == "__main__":
    main()
