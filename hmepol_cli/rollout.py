"""Particles: trajectories of a population of policies in a world, all stepped together.

Storage is allocated up front with shape (S, N, T, ...): members, trajectories, steps (the
estimators group particles by trajectory). Histories reset to h'_0 = 0 at every trajectory
start. Member s's randomness comes from its own generator, drawn up front in a fixed order
(start positions, action noise (N, T, a), world noise (N, T, k)), so it does not depend on the
other members or on how the steps are computed: member s of a population sees exactly the
random numbers of a run of its own.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from hmepol_cli.envs.base import NavigationWorld
from hmepol_cli.policies.base import Policy
from hmepol_cli.population import PolicyPopulation


@dataclass
class Rollout:
    """N trajectories of T steps for each of S members."""

    states: torch.Tensor  # (S, N, T + 1, d): s_0 .. s_T
    actions: torch.Tensor  # (S, N, T, a): a_t drawn at s_t (before clipping by the world)
    histories: torch.Tensor  # (S, N, T, H): h'_{t-1}, the history step t read (h'_{-1} = 0)
    log_probs: torch.Tensor  # (S, N, T): log pi(a_t | h_t) of the sampling policy
    configs: torch.Tensor  # (S, N) long: configuration of each trajectory

    @property
    def particles(self) -> torch.Tensor:
        """s_1 .. s_T, the states the actions produced: the particles of the estimate."""
        return self.states[..., 1:, :]

    @property
    def inputs(self) -> torch.Tensor:
        """s_0 .. s_{T-1}, the states the policy acted on. (S, N, T, d)"""
        return self.states[..., :-1, :]

    def member(self, s: int) -> Rollout:
        """Member s's trajectories, without the member dimension: (N, T, ...)."""
        return Rollout(
            self.states[s], self.actions[s], self.histories[s], self.log_probs[s], self.configs[s]
        )


def draw_configs(
    world: NavigationWorld, n_trajectories: int, batch_size: int, generator: torch.Generator
) -> torch.Tensor:
    """One configuration per mini-batch of B trajectories, drawn from p_M (thesis 4.2.3). (N,)"""
    per_batch = world.sample_configs(n_trajectories // batch_size, generator)
    return per_batch.repeat_interleave(batch_size)


def collect(
    world: NavigationWorld,
    population: PolicyPopulation,
    members: torch.Tensor | None,
    configs: torch.Tensor,
    horizon: int,
    generators: Sequence[torch.Generator],
    deterministic: bool = False,
) -> Rollout:
    """Run one trajectory per entry of ``configs`` (S', N) for ``horizon`` steps, member i of
    the selection ``members`` (None: all) acting in row i with randomness from generators[i]."""
    s, n = configs.shape
    device, dtype = world.device, world.dtype
    # Storage is made outside inference mode: the off-policy loop differentiates through it.
    states = torch.empty(s, n, horizon + 1, world.state_dim, device=device, dtype=dtype)
    actions = torch.empty(s, n, horizon, world.action_dim, device=device, dtype=dtype)
    histories = torch.empty(s, n, horizon, population.history_size, device=device, dtype=dtype)
    log_probs = torch.empty(s, n, horizon, device=device, dtype=dtype)
    with torch.inference_mode():  # no autograd bookkeeping on the ~100 small ops of each step
        starts, action_noise, world_noise = [], [], []
        for i, generator in enumerate(generators):
            kw = dict(device=device, dtype=dtype, generator=generator)
            starts.append(world.reset(configs[i], generator))
            action_noise.append(torch.randn(n, horizon, world.action_dim, **kw))
            world_noise.append(torch.rand(n, horizon, world.noise_size, **kw))
        position = torch.stack(starts)  # (S', N, d)
        action_noise = torch.stack(action_noise)  # (S', N, T, a)
        world_noise = torch.stack(world_noise).flatten(0, 1)  # (S' N, T, k)
        flat_configs = configs.flatten()
        history = population.initial_history(s, n)
        states[:, :, 0] = position
        for t in range(horizon):
            histories[:, :, t] = history
            noise = None if deterministic else action_noise[:, :, t]
            action, log_prob, history = population.act(members, position, history, noise)
            position = world.step(
                position.flatten(0, 1),
                action.flatten(0, 1),
                flat_configs,
                noise=world_noise[:, t],
            ).view(s, n, -1)
            actions[:, :, t], log_probs[:, :, t] = action, log_prob
            states[:, :, t + 1] = position
    return Rollout(states, actions, histories, log_probs, configs)


def collect_single(
    world: NavigationWorld,
    policy: Policy,
    configs: torch.Tensor,
    horizon: int,
    generator: torch.Generator,
    deterministic: bool = False,
) -> Rollout:
    """The rollout of one policy (a population of one, with a copy of its weights): configs
    (N,) -> a Rollout of shapes (N, T, ...), without the member dimension."""
    population = PolicyPopulation([policy]).to(world.device, world.dtype)
    rollout = collect(world, population, None, configs[None], horizon, [generator], deterministic)
    return rollout.member(0)
