"""Particles: trajectories of a population of policies in a world, all stepped together.

Storage is allocated up front with shape (S, N, T, ...): members, trajectories, steps (the
estimators group particles by trajectory). Histories reset to h'_0 = 0 at every trajectory
start. Member s's randomness comes from its own generator, drawn up front in a fixed order
(start positions, action noise (N, T, a), world noise (N, T, k)), so it does not depend on the
other members or on how the steps are computed: member s of a population sees exactly the
random numbers of a run of its own.

One step loop serves every world: a *transition* maps (t, states, actions) to the next states
(and, for a Gymnasium world, the environment's rewards and which episodes it ended). The 2-D
worlds step as tensors from noise drawn up front (and on a GPU replay as a CUDA graph); a
Gymnasium world (:class:`~hmepol_cli.envs.gym_world.GymWorld`) steps its vector environment, its
episodes reset with seeds drawn from each member's generator (seeds (N,), then action noise).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from hmepol_cli.envs.base import NavigationWorld
from hmepol_cli.envs.gym_world import GymWorld
from hmepol_cli.policies.base import Policy
from hmepol_cli.population import PolicyPopulation

if TYPE_CHECKING:
    from hmepol_cli.finetune.task import GoalTask, RewardTask

World = NavigationWorld | GymWorld
# (t, states (S', N, d), actions (S', N, a)) -> (next states (S', N, d), rewards (S', N) or None,
# ended (S', N) bool or None: the environment ended the episode on this step)
Transition = Callable[
    [int, torch.Tensor, torch.Tensor],
    tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None],
]


@dataclass
class Rollout:
    """N trajectories of T steps for each of S members (or, from :meth:`member`, of one)."""

    states: torch.Tensor  # (S, N, T + 1, d): s_0 .. s_T
    actions: torch.Tensor  # (S, N, T, a): a_t drawn at s_t (before clipping by the world)
    histories: torch.Tensor  # (S, N, T, H): h'_{t-1}, the history step t read (h'_{-1} = 0)
    log_probs: torch.Tensor  # (S, N, T): log pi(a_t | h_t) of the sampling policy
    configurations: torch.Tensor  # (S, N) long: configuration of each trajectory
    means: torch.Tensor  # (S, N, T, a): the sampling policy's mean action at each step
    log_std: torch.Tensor  # (S, a): the sampling policy's log-std
    # Goal tasks and Gymnasium worlds (None otherwise): steps taken before the episode ended;
    # in fine-tuning the trajectories may be shorter than the task's horizon T.
    alive: torch.Tensor | None = None  # (S, N, T) bool
    success: torch.Tensor | None = None  # (S, N, T) bool, goal tasks: it reached the target
    horizon: int | None = None  # the task's T
    # Gymnasium worlds: the environment's reward of each step (0 after the end), and the step the
    # environment ended the episode on (terminated or truncated).
    reward: torch.Tensor | None = None  # (S, N, T)
    ended: torch.Tensor | None = None  # (S, N, T) bool

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
            **{k: v[s] if isinstance(v, torch.Tensor) else v for k, v in vars(self).items()}
        )

    def episodes(self, index: torch.Tensor) -> Rollout:
        """Some trajectories of a member's rollout (no member dimension). index (n,) long"""
        return Rollout(
            **{
                k: v[index] if isinstance(v, torch.Tensor) and k != "log_std" else v
                for k, v in vars(self).items()
            }
        )

    # -- fine-tuning tasks
    @property
    def rewards(self) -> torch.Tensor:
        """The environment's reward (Gymnasium worlds), or 1 on the step an episode reaches the
        target of a goal task, 0 otherwise. (..., T)"""
        if self.reward is not None:
            return self.reward
        return self.success.to(self.states.dtype)

    @property
    def ends(self) -> torch.Tensor:
        """True on the step an episode ended: reached its target, or the environment ended it.
        (..., T) bool"""
        return self.ended if self.ended is not None else self.success

    @property
    def returns(self) -> torch.Tensor:
        """Undiscounted return of each episode. (..., N)"""
        return (self.rewards * self.alive).sum(dim=-1)

    @property
    def succeeded(self) -> torch.Tensor:
        return self.success.any(dim=-1)

    @property
    def lengths(self) -> torch.Tensor:
        return self.alive.sum(dim=-1)


def draw_configurations(
    world: World, n_trajectories: int, batch_size: int, generator: torch.Generator
) -> torch.Tensor:
    """One configuration per mini-batch of B trajectories, drawn from p_M (thesis 4.2.3). (N,)"""
    per_batch = world.sample_configurations(n_trajectories // batch_size, generator)
    return per_batch.repeat_interleave(batch_size)


@dataclass
class EpisodeLog:
    """What an episodic rollout records besides states (goal tasks, Gymnasium worlds), (S', N, T).

    ``reached``: a goal task's test, whose first success ends the episode; ``stop``: end the
    rollout once every episode has ended (fine-tuning), instead of running all T steps (the
    particles of pre-training)."""

    alive: torch.Tensor
    success: torch.Tensor | None = None
    reward: torch.Tensor | None = None
    ended: torch.Tensor | None = None
    reached: Callable[[torch.Tensor], torch.Tensor] | None = None
    stop: bool = False

    def record(
        self,
        t: int,
        running: torch.Tensor,
        position: torch.Tensor,
        reward: torch.Tensor | None,
        ended: torch.Tensor | None,
    ) -> torch.Tensor:
        """Write step t; -> the episodes still running after it. (S', N) bool"""
        self.alive[:, :, t] = running
        if self.reached is not None:  # a goal task: reaching the target ends the episode
            s, n = running.shape
            ended = self.reached(position.flatten(0, 1)).view(s, n)
            self.success[:, :, t] = running & ended
        if self.reward is not None:
            self.reward[:, :, t] = torch.where(running, reward, torch.zeros_like(reward))
        if self.ended is not None:
            self.ended[:, :, t] = running & ended
        return running & ~ended

    def truncate(self, steps: int) -> EpisodeLog:
        cut = {k: v[:, :, :steps] for k, v in vars(self).items() if isinstance(v, torch.Tensor)}
        return EpisodeLog(**{**vars(self), **cut})


def collect(
    world: World,
    population: PolicyPopulation,
    members: torch.Tensor | None,
    configurations: torch.Tensor,
    horizon: int,
    generators: Sequence[torch.Generator],
    deterministic: bool = False,
    graphs: dict | None = None,
    task: GoalTask | RewardTask | None = None,
) -> Rollout:
    """Run one trajectory per entry of ``configurations`` (S', N) for ``horizon`` steps, member i of
    the selection ``members`` (None: all) acting in row i with randomness from generators[i].

    ``task`` (fine-tuning): a goal task, whose episodes end on the step they reach the target, or
    a Gymnasium world's own reward and termination; the rollout stops once every episode has
    ended. ``graphs``: on a GPU, a cache in which the T steps of a 2-D world are captured once as a
    CUDA graph and replayed for every later rollout of the same shape (one launch instead of ~100
    a step); a Gymnasium world steps outside torch and is never captured.
    """
    if isinstance(world, GymWorld):
        return _collect_gym(
            world, population, members, configurations, horizon, generators, deterministic, task
        )
    s, n = configurations.shape
    device, dtype = world.device, world.dtype
    with torch.inference_mode():
        starts, action_noise, world_noise = [], [], []
        for i, generator in enumerate(generators):
            kw = dict(device=device, dtype=dtype, generator=generator)
            starts.append(world.reset(configurations[i], generator))
            action_noise.append(torch.randn(n, horizon, world.action_dim, **kw))
            world_noise.append(torch.rand(n, horizon, world.noise_size, **kw))
        position = torch.stack(starts)  # (S', N, d)
        action_noise = torch.stack(action_noise)  # (S', N, T, a)
        world_noise = torch.stack(world_noise).flatten(0, 1)  # (S' N, T, k)
    log_std = _log_std(population, members)
    if graphs is not None and task is None and device.type == "cuda":
        key = (
            id(world),
            id(population),
            None if members is None else tuple(members.tolist()),
            s,
            n,
            horizon,
            deterministic,
            tuple(p.data_ptr() for p in population.params.values()),
        )
        if key not in graphs:
            graphs[key] = CapturedSteps(world, population, members, s, n, horizon, deterministic)
        return graphs[key].run(position, action_noise, world_noise, configurations, log_std)
    episodes = None
    if task is not None:
        alive = torch.zeros(s, n, horizon, dtype=torch.bool, device=device)
        success = torch.zeros_like(alive)
        episodes = EpisodeLog(alive, success=success, reached=task.reached, stop=True)
    transition = world_transition(world, configurations.flatten(), world_noise)
    return _run_steps(
        world, population, members, configurations, position, action_noise, transition,
        horizon, deterministic, log_std, episodes, task,
    )  # fmt: skip


def _collect_gym(
    world: GymWorld,
    population: PolicyPopulation,
    members: torch.Tensor | None,
    configurations: torch.Tensor,
    horizon: int,
    generators: Sequence[torch.Generator],
    deterministic: bool,
    task: RewardTask | None,
) -> Rollout:
    """The rollout in a Gymnasium world: S' x N sub-environments of one vector environment."""
    s, n = configurations.shape
    with torch.inference_mode():
        seeds, action_noise = [], []
        for generator in generators:
            seeds.append(world.draw_seeds(n, generator))
            action_noise.append(
                torch.randn(
                    n,
                    horizon,
                    world.action_dim,
                    device=world.device,
                    dtype=world.dtype,
                    generator=generator,
                )  # fmt: skip
            )
        action_noise = torch.stack(action_noise)  # (S', N, T, a)
        episodes = world.episodes((s, n))
        position = episodes.start(configurations, torch.stack(seeds))  # (S', N, d)
    alive = torch.zeros(s, n, horizon, dtype=torch.bool, device=world.device)
    log = EpisodeLog(
        alive,
        reward=torch.zeros(s, n, horizon, device=world.device, dtype=world.dtype),
        ended=torch.zeros_like(alive),
        stop=task is not None,
    )
    return _run_steps(
        world, population, members, configurations, position, action_noise, episodes.step,
        horizon, deterministic, _log_std(population, members), log, task,
    )  # fmt: skip


def _log_std(population: PolicyPopulation, members: torch.Tensor | None) -> torch.Tensor:
    log_std = population.params["log_std"].detach().clone()
    return log_std if members is None else log_std.index_select(0, members)


def _run_steps(
    world: World,
    population: PolicyPopulation,
    members: torch.Tensor | None,
    configurations: torch.Tensor,
    position: torch.Tensor,
    action_noise: torch.Tensor,
    transition: Transition,
    horizon: int,
    deterministic: bool,
    log_std: torch.Tensor,
    episodes: EpisodeLog | None,
    task: GoalTask | RewardTask | None,
) -> Rollout:
    """Storage, the step loop, and the Rollout (cut where every episode of a task ended)."""
    s, n = configurations.shape
    buffers = _storage(world, population, s, n, horizon)
    steps = _steps(population, members, position, action_noise, transition, deterministic,
                   *buffers, episodes=episodes)  # fmt: skip
    states, actions, histories, log_probs, means = buffers
    if steps < horizon:  # every episode of the fine-tuning task ended early
        states, actions, histories = (
            states[:, :, : steps + 1],
            actions[:, :, :steps],
            histories[:, :, :steps],
        )
        log_probs, means = log_probs[:, :, :steps], means[:, :, :steps]
        episodes = episodes.truncate(steps)
    record = {}
    if episodes is not None:
        record = dict(alive=episodes.alive, success=episodes.success, reward=episodes.reward,
                      ended=episodes.ended)  # fmt: skip
    return Rollout(
        states, actions, histories, log_probs, configurations, means, log_std,
        horizon=task.horizon if task is not None else None, **record,
    )  # fmt: skip


def world_transition(
    world: NavigationWorld, flat_configs: torch.Tensor, world_noise: torch.Tensor
) -> Transition:
    """A 2-D world's step for every agent at once, with the noise of step t from
    ``world_noise`` (S' N, T, k); flat_configs (S' N,)."""

    def transition(t: int, position: torch.Tensor, action: torch.Tensor):
        s, n = position.shape[:2]
        moved = world.step(
            position.flatten(0, 1), action.flatten(0, 1), flat_configs, noise=world_noise[:, t]
        )
        return moved.view(s, n, -1), None, None

    return transition


def _storage(world: World, population: PolicyPopulation, s: int, n: int, horizon: int):
    """Empty (states, actions, histories, log-likelihoods, means) of S' x N trajectories of T
    steps. Made outside inference mode: the off-policy loop differentiates through them."""
    kw = dict(device=world.device, dtype=world.dtype)
    return (
        torch.empty(s, n, horizon + 1, world.state_dim, **kw),
        torch.empty(s, n, horizon, world.action_dim, **kw),
        torch.empty(s, n, horizon, population.history_size, **kw),
        torch.empty(s, n, horizon, **kw),
        torch.empty(s, n, horizon, world.action_dim, **kw),
    )


def _steps(
    population: PolicyPopulation,
    members: torch.Tensor | None,
    position: torch.Tensor,
    action_noise: torch.Tensor,
    transition: Transition,
    deterministic: bool,
    states: torch.Tensor,
    actions: torch.Tensor,
    histories: torch.Tensor,
    log_probs: torch.Tensor,
    means: torch.Tensor,
    episodes: EpisodeLog | None = None,
) -> int:
    """The T steps of a rollout, written into the storage. -> the steps taken"""
    s, n, horizon = actions.shape[:3]
    with torch.inference_mode():  # no autograd bookkeeping on the ~100 small ops of each step
        history = population.initial_history(s, n)
        running = torch.ones(s, n, dtype=torch.bool, device=position.device)
        states[:, :, 0] = position
        for t in range(horizon):
            histories[:, :, t] = history
            noise = None if deterministic else action_noise[:, :, t]
            action, log_prob, history, mean = population.act(members, position, history, noise)
            position, reward, ended = transition(t, position, action)
            actions[:, :, t], log_probs[:, :, t], means[:, :, t] = action, log_prob, mean
            states[:, :, t + 1] = position
            if episodes is not None:
                running = episodes.record(t, running, position, reward, ended)
                if episodes.stop and not running.any():  # every episode ended
                    return t + 1
    return horizon


class CapturedSteps:
    """The T steps of a rollout of one shape in a 2-D world as a CUDA graph, replayed on fresh
    inputs.

    The graph reads the population's parameters from their storage, which the optimizer
    updates in place, so a replay always acts with the current policies."""

    def __init__(
        self,
        world: NavigationWorld,
        population: PolicyPopulation,
        members: torch.Tensor | None,
        s: int,
        n: int,
        horizon: int,
        deterministic: bool,
    ) -> None:
        kw = dict(device=world.device, dtype=world.dtype)
        self.position = torch.zeros(s, n, world.state_dim, **kw)
        self.action_noise = torch.zeros(s, n, horizon, world.action_dim, **kw)
        self.world_noise = torch.zeros(s * n, horizon, world.noise_size, **kw)
        self.configurations = torch.zeros(s * n, dtype=torch.long, device=world.device)
        self.outputs = _storage(world, population, s, n, horizon)
        members = None if members is None else members.clone()
        transition = world_transition(world, self.configurations, self.world_noise)

        def body() -> None:
            _steps(
                population,
                members,
                self.position,
                self.action_noise,
                transition,
                deterministic,
                *self.outputs,
            )

        side = torch.cuda.Stream()  # warm up (handles, allocator) away from the capture
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            body()
        torch.cuda.current_stream().wait_stream(side)
        self.graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.graph):
            body()

    def run(
        self,
        position: torch.Tensor,
        action_noise: torch.Tensor,
        world_noise: torch.Tensor,
        configurations: torch.Tensor,
        log_std: torch.Tensor,
    ) -> Rollout:
        with torch.no_grad():
            self.position.copy_(position)
            self.action_noise.copy_(action_noise)
            self.world_noise.copy_(world_noise)
            self.configurations.copy_(configurations.flatten())
        self.graph.replay()
        states, actions, histories, log_probs, means = (t.clone() for t in self.outputs)
        return Rollout(states, actions, histories, log_probs, configurations, means, log_std)


def collect_single(
    world: World,
    policy: Policy,
    configurations: torch.Tensor,
    horizon: int,
    generator: torch.Generator,
    deterministic: bool = False,
    task: GoalTask | RewardTask | None = None,
) -> Rollout:
    """The rollout of one policy (a population of one, with a copy of its weights): configurations
    (N,) -> a Rollout of shapes (N, T, ...), without the member dimension."""
    population = PolicyPopulation([policy]).to(world.device, world.dtype)
    rollout = collect(
        world,
        population,
        None,
        configurations[None],
        horizon,
        [generator],
        deterministic,
        task=task,
    )
    return rollout.member(0)


def collect_episodes(
    world: World,
    policy: Policy,
    task: GoalTask | RewardTask,
    episodes: int,
    generator: torch.Generator,
) -> Rollout:
    """``episodes`` episodes of one fine-tuning task, stepped together. (N, T, ...)"""
    configurations = torch.full((episodes,), task.config, dtype=torch.long, device=world.device)
    return collect_single(world, policy, configurations, task.horizon, generator, task=task)
