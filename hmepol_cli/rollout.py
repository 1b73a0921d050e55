"""Particles: trajectories of a population of policies in a world, all stepped together.

Storage is allocated up front with shape (S, N, T, ...): members, trajectories, steps (the
estimators group particles by trajectory). Histories reset to h'_0 = 0 at every trajectory
start. Member s's randomness comes from its own generator, drawn up front by the world in a
fixed order (:meth:`~hmepol_cli.envs.world.World.begin`), so it does not depend on the other
members or on how the steps are computed: member s of a population sees exactly the random
numbers of a run of its own.

One step loop serves every world (:class:`~hmepol_cli.envs.world.World`): the world's episodes
map (t, states, actions) to a :class:`~hmepol_cli.envs.world.Transition`. A world whose steps
are tensor operations only (the 2-D worlds) replays on a GPU as one captured CUDA graph.
Episodes may end before T when the environment ends them (Gymnasium worlds) or when
``ends_episode`` says so (a fine-tuning goal); ``until_ended`` stops the rollout once all have.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields, replace

import torch

from hmepol_cli.envs.world import Episodes, World
from hmepol_cli.policies.base import Policy
from hmepol_cli.population import PolicyPopulation

# positions (S' N, d) -> (S' N,) bool: the episode ends on reaching this state (a goal)
EndTest = Callable[[torch.Tensor], torch.Tensor]


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
    # Episodes that can end before T (None: every step of every trajectory was taken):
    alive: torch.Tensor | None = None  # (S, N, T) bool: step t was taken while it ran
    reward: torch.Tensor | None = None  # (S, N, T): the environment's reward (0 after the end)
    ended: torch.Tensor | None = None  # (S, N, T) bool: the episode ended on step t

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
        return self._each(lambda k, v: v[s])

    def rows(self, rows: torch.Tensor) -> Rollout:
        """The members in ``rows`` (R,) long."""
        return self._each(lambda k, v: v.index_select(0, rows))

    def episodes(self, index: torch.Tensor) -> Rollout:
        """Some trajectories of a member's rollout (no member dimension). index (n,) long"""
        return self._each(lambda k, v: v if k == "log_std" else v[index])

    def _each(self, part: Callable[[str, torch.Tensor], torch.Tensor]) -> Rollout:
        """The same kind of rollout with ``part`` of every tensor."""
        tensors = {k: part(k, v) for k, v in vars(self).items() if isinstance(v, torch.Tensor)}
        return replace(self, **tensors)


def draw_configurations(
    world: World, n_trajectories: int, batch_size: int, generator: torch.Generator
) -> torch.Tensor:
    """One configuration per mini-batch of B trajectories, drawn from p_M (thesis 4.2.3). (N,)"""
    per_batch = world.sample_configurations(n_trajectories // batch_size, generator)
    return per_batch.repeat_interleave(batch_size)


@dataclass
class EpisodeLog:
    """Which steps each episode took, and how it ended, (S', N, T)."""

    alive: torch.Tensor
    reward: torch.Tensor | None = None
    ended: torch.Tensor | None = None

    def record(self, t: int, running: torch.Tensor, step: _Step) -> torch.Tensor:
        """Write step t; -> the episodes still running after it. (S', N) bool"""
        self.alive[:, :, t] = running
        if self.reward is not None:
            reward = step.reward
            self.reward[:, :, t] = torch.where(running, reward, torch.zeros_like(reward))
        ended = step.ended
        if self.ended is not None:
            self.ended[:, :, t] = running & ended
        return running & ~ended

    def truncate(self, steps: int) -> EpisodeLog:
        cut = {k: v[:, :, :steps] for k, v in vars(self).items() if isinstance(v, torch.Tensor)}
        return EpisodeLog(**{**vars(self), **cut})


@dataclass
class _Step:
    """What the step loop needs of a transition: the next states, the reward, the ends."""

    states: torch.Tensor
    reward: torch.Tensor | None
    ended: torch.Tensor


def collect(
    world: World,
    population: PolicyPopulation,
    members: torch.Tensor | None,
    configurations: torch.Tensor,
    horizon: int,
    generators: Sequence[torch.Generator],
    deterministic: bool = False,
    graphs: dict | None = None,
    ends_episode: EndTest | None = None,
    until_ended: bool = False,
) -> Rollout:
    """Run one trajectory per entry of ``configurations`` (S', N) for ``horizon`` steps, member i of
    the selection ``members`` (None: all) acting in row i with randomness from generators[i].

    ``ends_episode``: a state that ends its episode (a fine-tuning goal); ``until_ended``: stop
    the rollout once every episode has ended (fine-tuning) instead of running all T steps (the
    particles of pre-training). ``graphs``: on a GPU, a cache in which the T steps of a capturable
    world are captured once as a CUDA graph and replayed for every later rollout of the same
    shape (one launch instead of ~100 a step).
    """
    s, n = configurations.shape
    with torch.inference_mode():
        episodes, action_noise = world.begin(configurations, horizon, generators, members)
    log_std = population.params["log_std"].detach().clone()
    log_std = log_std if members is None else log_std.index_select(0, members)
    records = world.episodes_end or ends_episode is not None
    capture = graphs is not None and world.capturable and world.device.type == "cuda"
    if capture and not records:
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
            graphs[key] = CapturedSteps(
                world, population, members, episodes, horizon, deterministic
            )
        return graphs[key].run(episodes, action_noise, configurations, log_std)
    log = None
    if records:
        alive = torch.zeros(s, n, horizon, dtype=torch.bool, device=world.device)
        reward = None
        if world.episodes_end:
            reward = torch.zeros(s, n, horizon, device=world.device, dtype=world.dtype)
        log = EpisodeLog(alive, reward=reward, ended=torch.zeros_like(alive))
    buffers = _storage(world, population, s, n, horizon)
    steps = _steps(population, members, episodes, action_noise, deterministic, *buffers,
                   log=log, ends_episode=ends_episode, until_ended=until_ended)  # fmt: skip
    states, actions, histories, log_probs, means = buffers
    if steps < horizon:  # every episode ended early
        states, actions, histories = (
            states[:, :, : steps + 1],
            actions[:, :, :steps],
            histories[:, :, :steps],
        )
        log_probs, means = log_probs[:, :, :steps], means[:, :, :steps]
        log = log.truncate(steps)
    episode_fields = {} if log is None else vars(log)
    return Rollout(states, actions, histories, log_probs, configurations, means, log_std,
                   **episode_fields)  # fmt: skip


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
    episodes: Episodes,
    action_noise: torch.Tensor,
    deterministic: bool,
    states: torch.Tensor,
    actions: torch.Tensor,
    histories: torch.Tensor,
    log_probs: torch.Tensor,
    means: torch.Tensor,
    log: EpisodeLog | None = None,
    ends_episode: EndTest | None = None,
    until_ended: bool = False,
) -> int:
    """The T steps of a rollout, written into the storage. -> the steps taken"""
    s, n, horizon = actions.shape[:3]
    with torch.inference_mode():  # no autograd bookkeeping on the ~100 small ops of each step
        position = episodes.start
        history = population.initial_history(s, n)
        running = torch.ones(s, n, dtype=torch.bool, device=position.device)
        states[:, :, 0] = position
        for t in range(horizon):
            histories[:, :, t] = history
            noise = None if deterministic else action_noise[:, :, t]
            action, log_prob, history, mean = population.act(members, position, history, noise)
            moved = episodes.step(t, position, action)
            position = moved.states
            actions[:, :, t], log_probs[:, :, t], means[:, :, t] = action, log_prob, mean
            states[:, :, t + 1] = position
            if log is not None:
                running = log.record(t, running, _ends(moved, position, ends_episode))
                if until_ended and not running.any():  # every episode ended
                    return t + 1
    return horizon


def _ends(moved, position: torch.Tensor, ends_episode: EndTest | None) -> _Step:
    """Which episodes end on this step: the environment's ends, or a goal's."""
    ended = moved.ended
    if ends_episode is not None:
        s, n = position.shape[:2]
        reached = ends_episode(position.flatten(0, 1)).view(s, n)
        ended = reached if ended is None else ended | reached
    if ended is None:
        ended = torch.zeros(position.shape[:2], dtype=torch.bool, device=position.device)
    return _Step(position, moved.reward, ended)


class CapturedSteps:
    """The T steps of a rollout of one shape in a capturable world as a CUDA graph, replayed on
    fresh inputs.

    The graph reads the population's parameters from their storage, which the optimizer
    updates in place, so a replay always acts with the current policies; it reads the episodes'
    tensors (start states, world noise) from static copies that every replay refills."""

    def __init__(
        self,
        world: World,
        population: PolicyPopulation,
        members: torch.Tensor | None,
        episodes: Episodes,
        horizon: int,
        deterministic: bool,
    ) -> None:
        s, n = episodes.start.shape[:2]
        kw = dict(device=world.device, dtype=world.dtype)
        self.action_noise = torch.zeros(s, n, horizon, world.action_dim, **kw)
        self.episodes = _static_copy(episodes)
        self.outputs = _storage(world, population, s, n, horizon)
        members = None if members is None else members.clone()

        def body() -> None:
            _steps(population, members, self.episodes, self.action_noise, deterministic,
                   *self.outputs)  # fmt: skip

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
        episodes: Episodes,
        action_noise: torch.Tensor,
        configurations: torch.Tensor,
        log_std: torch.Tensor,
    ) -> Rollout:
        with torch.no_grad():
            for f in fields(self.episodes):
                value = getattr(self.episodes, f.name)
                if isinstance(value, torch.Tensor):
                    value.copy_(getattr(episodes, f.name))
            self.action_noise.copy_(action_noise)
        self.graph.replay()
        states, actions, histories, log_probs, means = (t.clone() for t in self.outputs)
        return Rollout(states, actions, histories, log_probs, configurations, means, log_std)


def _static_copy(episodes: Episodes) -> Episodes:
    """The same episodes with every tensor field in fresh storage a graph can read from."""
    return type(episodes)(
        **{
            f.name: getattr(episodes, f.name).clone()
            if isinstance(getattr(episodes, f.name), torch.Tensor)
            else getattr(episodes, f.name)
            for f in fields(episodes)
        }
    )


def collect_single(
    world: World,
    policy: Policy,
    configurations: torch.Tensor,
    horizon: int,
    generator: torch.Generator,
    deterministic: bool = False,
    ends_episode: EndTest | None = None,
    until_ended: bool = False,
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
        ends_episode=ends_episode,
        until_ended=until_ended,
    )
    return rollout.member(0)


def non_finite_rows(rollout: Rollout) -> dict[int, list[str]]:
    """Rows (members) of a rollout holding non-finite positions, actions or histories, with
    their names. One transfer."""
    checks = {"positions": rollout.states, "actions": rollout.actions, "history": rollout.histories}
    finite = torch.stack(
        [
            torch.isfinite(v).flatten(1).all(dim=1)
            if v.numel()
            else torch.ones(v.shape[0], dtype=torch.bool, device=v.device)
            for v in checks.values()
        ]
    ).cpu()  # (3, S')
    names = list(checks)
    return {
        i: [names[j] for j in range(len(names)) if not finite[j, i]]
        for i in range(finite.shape[1])
        if not finite[:, i].all()
    }
