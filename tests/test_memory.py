"""Memory is necessary: a cue seen only at the first step decides where to go later.

The world is :class:`CueCorridorWorld`: the configuration shows only in the start position (top
pad: go left; bottom pad: go right), the first step puts every agent on the origin whatever it
does, and the goal is the corridor's left end in config 0, its right end in config 1. Both
policies are trained with this project's TRPO (``TRPO.update`` on ``collect_episodes`` rollouts),
each epoch on episodes of both configurations together.

Why the Markovian policy cannot succeed: from s_1 = (0, 0) on, its actions depend on the state
only, and the state no longer depends on the configuration, so s_1..s_T has the same law in
both configurations (with the same random numbers, the very same trajectory; tested below).
An episode of ``MEMORY_HORIZON`` steps is too short to visit both goals (at least 3 moves to one
goal, 5 more to the other, 7 moves in all; tested below), so P(reach left) + P(reach right)
<= 1: the success rate averaged over the two configurations is at most 1/2, whatever the
training, up to sampling noise (~0.02 with 400 evaluation episodes a configuration). The
recursive policy can carry s_0 in its history h'_t and reach the right goal almost always.

The recursive policy has a one-layer encoder and learns with full back-propagation through the
history (``bptt=None``): with the default initialisation a deeper ReLU encoder shrinks the cue
~20 times a step and TRPO settles on one side before it learns to keep it. Mixing the
configurations in one update is sound although TRPO's value function reads only the state and
the time: any such function is an unbiased baseline.
"""

from __future__ import annotations

import itertools

import pytest
import torch

from hmepol_cli.finetune.task import GoalTask, TaskRollout, collect_episodes
from hmepol_cli.finetune.trpo import TRPO, TRPOSettings
from hmepol_cli.policies.base import Policy
from hmepol_cli.policies.markov import MarkovPolicy
from hmepol_cli.policies.recursive import RecursivePolicy
from tests.cue_world import GOALS, MEMORY_HORIZON, CueCorridorWorld

EPOCHS = 30
EPISODES = 128  # per epoch, half in each configuration
EVAL_EPISODES = 400  # per configuration
SEED = 0
SETTINGS = TRPOSettings(
    max_kl=0.05, bptt=None, value_hidden=(32, 32), value_epochs=5, value_batch=256
)


def goal_tasks() -> list[GoalTask]:
    return [GoalTask(GOALS[c], c, MEMORY_HORIZON) for c in range(2)]


def markov_policy(seed: int = SEED) -> MarkovPolicy:
    torch.manual_seed(seed)
    return MarkovPolicy(2, 2, hidden=[32, 32], init_log_std=-0.5)


def recursive_policy(seed: int = SEED) -> RecursivePolicy:
    torch.manual_seed(seed)
    return RecursivePolicy(
        2, 2, hidden=[32, 32], encoder_hidden=[], history_size=16, init_log_std=-0.5
    )


def concatenate(rollouts: list[TaskRollout]) -> TaskRollout:
    """One rollout of the episodes of all ``rollouts``, padded to the longest (masked steps)."""
    steps = max(r.alive.shape[1] for r in rollouts)

    def padded(x: torch.Tensor, length: int) -> torch.Tensor:
        shape = (x.shape[0], length - x.shape[1], *x.shape[2:])
        return torch.cat((x, torch.zeros(shape, dtype=x.dtype)), dim=1)

    fields = {"states": torch.cat([padded(r.states, steps + 1) for r in rollouts])}
    for key in ("actions", "means", "histories", "log_probs", "alive", "ended"):
        fields[key] = torch.cat([padded(getattr(r, key), steps) for r in rollouts])
    fields["configurations"] = torch.cat([r.configurations for r in rollouts])
    return TaskRollout(**fields, log_std=rollouts[0].log_std, horizon=rollouts[0].horizon,
                       goal=True)  # fmt: skip


def success_rates(
    world: CueCorridorWorld, policy: Policy, episodes: int, generator: torch.Generator
) -> list[float]:
    """Share of episodes that reach their goal, per configuration."""
    return [
        float(collect_episodes(world, policy, task, episodes, generator).succeeded.float().mean())
        for task in goal_tasks()
    ]


def train(policy: Policy, seed: int = SEED, epochs: int = EPOCHS) -> list[float]:
    """TRPO on both configurations at once; -> success rate per configuration after training."""
    world, tasks = CueCorridorWorld(), goal_tasks()
    generator = torch.Generator().manual_seed(seed)
    trpo = TRPO(policy, world, MEMORY_HORIZON, SETTINGS, generator)
    for _ in range(epochs):
        rollouts = [collect_episodes(world, policy, t, EPISODES // 2, generator) for t in tasks]
        trpo.update(concatenate(rollouts))
    return success_rates(world, policy, EVAL_EPISODES, generator)


# --------------------------------------------------------------------------- the world
def test_the_cue_is_gone_after_the_first_step():
    world = CueCorridorWorld()
    gen = torch.Generator().manual_seed(0)
    configurations = torch.tensor([0, 1]).repeat_interleave(50)
    start = world.reset(configurations, gen)
    assert (start[:50, 1] > 0.3).all() and (start[50:, 1] < -0.3).all()  # the cue
    actions = torch.randn(100, 2, generator=gen)
    assert torch.equal(world.step(start, actions, configurations), torch.zeros(100, 2))
    position = torch.zeros(100, 2)
    for _ in range(20):  # the walls keep every agent in the corridor
        position = world.step(position, torch.randn(100, 2, generator=gen), configurations)
        assert (position[:, 1].abs() <= 0.2).all()


def test_no_episode_visits_both_goals():
    """Every sequence of 7 moves of -0.2, 0 or +0.2 along x from the origin."""
    moves = MEMORY_HORIZON - 1
    dx = torch.tensor(list(itertools.product((-0.2, 0.0, 0.2), repeat=moves)))  # (3^7, 7)
    world = CueCorridorWorld()
    configurations = torch.zeros(dx.shape[0], dtype=torch.long)
    position = torch.zeros(dx.shape[0], 2)
    left_task, right_task = goal_tasks()
    left = torch.zeros(dx.shape[0], dtype=torch.bool)
    right = torch.zeros_like(left)
    for t in range(moves):
        action = torch.stack((dx[:, t], torch.zeros_like(dx[:, t])), dim=-1)
        position = world.step(position, action, configurations)
        left |= left_task.reached(position)
        right |= right_task.reached(position)
    assert left.any() and right.any() and not (left & right).any()


def test_a_markovian_policy_walks_the_same_path_in_both_configurations():
    """The heart of the bound: with the same random numbers, s_1..s_T do not depend on the cue
    under a Markovian policy; under a recursive one they do."""
    world = CueCorridorWorld()
    for policy, same in ((markov_policy(), True), (recursive_policy(), False)):
        left, right = (
            collect_episodes(world, policy, task, 32, torch.Generator().manual_seed(1))
            for task in goal_tasks()
        )
        steps = min(left.alive.shape[1], right.alive.shape[1])
        assert not torch.equal(left.states[:, 0], right.states[:, 0])  # s_0 holds the cue
        assert torch.equal(left.states[:, 1 : steps + 1], right.states[:, 1 : steps + 1]) == same


# --------------------------------------------------------------------------- learning
@pytest.mark.slow  # heavy: make test runs it, make test-fast does not
def test_the_recursive_policy_learns_to_remember_the_cue():
    policy = recursive_policy()
    before = success_rates(
        CueCorridorWorld(), policy, EVAL_EPISODES, torch.Generator().manual_seed(SEED)
    )
    assert max(before) < 0.5, before  # a random walk rarely gets there: the policy must learn
    rates = train(policy)
    assert min(rates) >= 0.8, rates


@pytest.mark.slow  # heavy: make test runs it, make test-fast does not
def test_the_markovian_policy_cannot_beat_chance():
    rates = train(markov_policy())
    assert sum(rates) / 2 <= 0.6, rates
