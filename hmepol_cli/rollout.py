"""Particles: trajectories of a policy in a world, all stepped together as tensors.

Storage is allocated up front with shape (N, T, ...) (trajectories first, as the estimators
group particles by trajectory); histories reset to h'_0 = 0 at every trajectory start.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from hmepol_cli.envs.base import NavigationWorld
from hmepol_cli.policies.base import Policy


@dataclass
class Rollout:
    """N trajectories of T steps."""

    states: torch.Tensor  # (N, T + 1, d): s_0 .. s_T
    actions: torch.Tensor  # (N, T, a): a_t drawn at s_t (before clipping by the world)
    histories: torch.Tensor  # (N, T, H): h'_{t-1}, the history step t read (h'_{-1} = 0)
    log_probs: torch.Tensor  # (N, T): log pi(a_t | h_t) of the sampling policy
    configs: torch.Tensor  # (N,) long: configuration of each trajectory

    @property
    def particles(self) -> torch.Tensor:
        """s_1 .. s_T, the states the actions produced: the particles of the estimate. (N, T, d)"""
        return self.states[:, 1:]

    @property
    def inputs(self) -> torch.Tensor:
        """s_0 .. s_{T-1}, the states the policy acted on. (N, T, d)"""
        return self.states[:, :-1]


def draw_configs(
    world: NavigationWorld, n_trajectories: int, batch_size: int, generator: torch.Generator | None
) -> torch.Tensor:
    """One configuration per mini-batch of B trajectories, drawn from p_M (thesis 4.2.3). (N,)"""
    per_batch = world.sample_configs(n_trajectories // batch_size, generator)
    return per_batch.repeat_interleave(batch_size)


def collect(
    world: NavigationWorld,
    policy: Policy,
    configs: torch.Tensor,
    horizon: int,
    generator: torch.Generator | None = None,
    deterministic: bool = False,
) -> Rollout:
    """Run one trajectory per entry of ``configs`` for ``horizon`` steps.

    The randomness of the whole rollout is drawn up front from ``generator``, in a fixed order
    (start positions, the policy's action noise (N, T, a), the world's noise (N, T, k)), so the
    stream a run consumes does not depend on how its steps are computed.
    """
    n, device, dtype = configs.shape[0], world.device, world.dtype
    # Storage is made outside inference mode: the off-policy loop differentiates through it.
    states = torch.empty(n, horizon + 1, world.state_dim, device=device, dtype=dtype)
    actions = torch.empty(n, horizon, world.action_dim, device=device, dtype=dtype)
    histories = torch.empty(n, horizon, policy.history_size, device=device, dtype=dtype)
    log_probs = torch.empty(n, horizon, device=device, dtype=dtype)
    with torch.inference_mode():  # no autograd bookkeeping on the ~100 small ops of each step
        position = world.reset(configs, generator)
        kw = dict(device=device, dtype=dtype, generator=generator)
        action_noise = torch.randn(n, horizon, world.action_dim, **kw)
        world_noise = torch.rand(n, horizon, world.noise_size, **kw)
        history = policy.initial_history(n, device, dtype)
        states[:, 0] = position
        for t in range(horizon):
            histories[:, t] = history
            noise = None if deterministic else action_noise[:, t]
            action, log_prob, history = policy.act(position, history, noise)
            position = world.step(position, action, configs, noise=world_noise[:, t])
            actions[:, t], log_probs[:, t], states[:, t + 1] = action, log_prob, position
    return Rollout(states, actions, histories, log_probs, configs)
