"""Any Gymnasium environment as a world: ``env=gym env.id=<id>``.

The class of environments M_1..M_I is one Gymnasium id made with I keyword sets
(``env.configs``: ``gymnasium.make(id, **configs[i])``, e.g. two gravities), drawn with
probabilities p_M (``env.probs``, uniform by default). The policy sees the whole observation;
the entropy is computed on the observation indices ``env.features`` (default: all), so Ant can
explore its x-y plane while it acts on its whole state.

Stepping: every trajectory of a rollout (S members x N trajectories) is one sub-environment of
one Gymnasium vector environment, stepped together; observations and actions cross between
numpy and torch once per step for the whole batch, and actions are clipped to the action space.
``env.workers = 0`` steps the sub-environments in this process (``SyncVectorEnv``);
``env.workers = W`` spreads them over W worker processes (``AsyncVectorEnv`` of W workers, each a
``SyncVectorEnv`` of its share), for environments slow enough to be worth the transfers.

Each sub-environment is a :class:`ConfigurationSlot`: it holds one environment per configuration
(made the first time the slot is asked for it) and runs the next episode in the configuration
the rollout sets, so one vector environment serves every mix of configurations an epoch draws.

Randomness: every episode is reset with its own seed, drawn from the run's generator, so an
episode is fixed by (configuration, seed, actions), whatever slot or worker runs it: the same
seed and config give the same curves on the same machine, with any number of workers.

Episodes the environment ends before the horizon T (``terminated`` or ``truncated``) keep their
last state for the remaining steps, so every trajectory keeps T slots; the steps after the end are
marked not ``alive``: they are no particles of the estimate (``estimators.Neighbours.live``) and
their actions count in no importance weight. Gymnasium's registered
time limit is not applied (``max_episode_steps=-1`` unless a configuration sets it): the horizon
is hmepol's T.
"""

from __future__ import annotations

import difflib
import importlib
import math
from collections.abc import Sequence
from functools import partial
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AsyncVectorEnv, AutoresetMode, SyncVectorEnv
from omegaconf import OmegaConf

from hmepol_cli.envs.world import Transition, action_noise
from hmepol_cli.errors import ConfigError

SEED_BOUND = 2**31 - 1  # episode seeds are drawn in [0, SEED_BOUND)


def make_env(env_id: str, kwargs: dict[str, Any]) -> gym.Env:
    """``gymnasium.make(env_id, **kwargs)`` without the registered time limit (T is hmepol's),
    unless ``kwargs`` sets ``max_episode_steps`` itself."""
    return gym.make(env_id, **{"max_episode_steps": -1, **kwargs})


class ConfigurationSlot(gym.Env):
    """One sub-environment of the vector environment: one environment per configuration, made
    when the slot is first asked for it; ``configuration`` (set through the vector environment's
    ``set_attr`` before a reset) picks the one the next episode runs in."""

    def __init__(self, env_id: str, configurations: Sequence[dict[str, Any]]) -> None:
        self.env_id, self.configurations = env_id, list(configurations)
        self._envs: dict[int, gym.Env] = {}
        self.configuration = 0
        self._active = self._env(0)
        self.observation_space = self._active.observation_space
        self.action_space = self._active.action_space

    def _env(self, c: int) -> gym.Env:
        if c not in self._envs:
            self._envs[c] = make_env(self.env_id, self.configurations[c])
        return self._envs[c]

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        self._active = self._env(int(self.configuration))
        return self._active.reset(seed=seed, options=options)

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        return self._active.step(action)

    def close(self) -> None:
        for env in self._envs.values():
            env.close()


class SlotGroup(gym.Env):
    """k slots stepped in one worker process: what each process of the worker pool runs.

    Its observation is the (k, d) batch of its slots, its action the (k, a) batch; the slots
    reset themselves on the step after an episode ends (Gymnasium's next-step autoreset).
    """

    def __init__(self, env_id: str, configurations: Sequence[dict[str, Any]], k: int) -> None:
        slot = partial(ConfigurationSlot, env_id, list(configurations))
        self.slots = SyncVectorEnv([slot] * k, autoreset_mode=AutoresetMode.NEXT_STEP)
        self.observation_space = self.slots.observation_space
        self.action_space = self.slots.action_space

    @property
    def configuration(self) -> list[int]:
        return list(self.slots.get_attr("configuration"))

    @configuration.setter
    def configuration(self, values: Sequence[int]) -> None:
        self.slots.set_attr("configuration", list(values))

    def reset(
        self, *, seed: Sequence[int] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        observations, _ = self.slots.reset(seed=None if seed is None else list(seed))
        return observations, {}

    def step(
        self, action: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        observations, rewards, terminated, truncated, _ = self.slots.step(action)
        return observations, rewards, terminated, truncated, {}

    def close(self) -> None:
        self.slots.close()


class SlotPool:
    """``m`` slots behind one Gymnasium vector environment: in this process (workers = 0) or
    spread over ``workers`` processes, each stepping ceil(m / workers) slots (padding slots run
    configuration 0 with zero actions and are never read)."""

    def __init__(
        self, env_id: str, configurations: Sequence[dict[str, Any]], m: int, workers: int
    ) -> None:
        self.m = m
        self.workers = min(workers, m)
        if self.workers == 0:
            slot = partial(ConfigurationSlot, env_id, list(configurations))
            self.vector = SyncVectorEnv([slot] * m, autoreset_mode=AutoresetMode.NEXT_STEP)
            self.per_worker = m
        else:
            self.per_worker = math.ceil(m / self.workers)
            group = partial(SlotGroup, env_id, list(configurations), self.per_worker)
            # The groups reset their own slots after an episode ends; the pool never autoresets.
            self.vector = AsyncVectorEnv(
                [group] * self.workers, autoreset_mode=AutoresetMode.DISABLED
            )
        self.action_shape = self.vector.single_action_space.shape[-1:]

    def _split(self, values: Sequence[Any], fill: Any) -> list[Any]:
        """m per-slot values -> one list per worker (padded), or the m values themselves."""
        if self.workers == 0:
            return list(values)
        padded = list(values) + [fill] * (self.workers * self.per_worker - self.m)
        k = self.per_worker
        return [padded[i * k : (i + 1) * k] for i in range(self.workers)]

    def reset(self, configurations: Sequence[int], seeds: Sequence[int]) -> np.ndarray:
        """Start an episode in every slot: configuration and seed per slot. -> (m, d)"""
        self.vector.set_attr("configuration", self._split(configurations, 0))
        observations, _ = self.vector.reset(seed=self._split(seeds, 0))
        return observations.reshape(-1, observations.shape[-1])[: self.m]

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """actions (m, a) -> observations (m, d), rewards (m,), ended (m,) bool."""
        if self.workers:
            padded = np.zeros((self.workers * self.per_worker, *self.action_shape), actions.dtype)
            padded[: self.m] = actions
            actions = padded.reshape(self.workers, self.per_worker, *self.action_shape)
        observations, rewards, terminated, truncated, _ = self.vector.step(actions)
        ended = (np.asarray(terminated) | np.asarray(truncated)).reshape(-1)[: self.m]
        return (
            observations.reshape(-1, observations.shape[-1])[: self.m],
            np.asarray(rewards, dtype=np.float64).reshape(-1)[: self.m],
            ended,
        )

    def close(self) -> None:
        self.vector.close()


class GymEpisodes:
    """S' x N episodes in progress, one per slot of a pool, stepped together (the world's
    :class:`~hmepol_cli.envs.world.Episodes`).

    An episode the environment ends keeps its last state (and gets reward 0) in the slots of its
    remaining steps, marked not alive (no particles); once every episode has ended the
    environments are no longer stepped."""

    def __init__(
        self, world: GymWorld, pool: SlotPool, configurations: torch.Tensor, seeds: torch.Tensor
    ) -> None:
        """configurations, seeds (S', N): each episode's configuration and reset seed."""
        self.world, self.pool, self.shape = world, pool, tuple(configurations.shape)
        self.running = np.ones(pool.m, dtype=bool)
        observations = pool.reset(configurations.flatten().tolist(), seeds.flatten().tolist())
        self.start = world.as_states(observations).view(*self.shape, -1)  # (S', N, d)

    def step(self, t: int, states: torch.Tensor, actions: torch.Tensor) -> Transition:
        """(S', N, d) states, (S', N, a) actions -> next states (S', N, d), rewards (S', N),
        ended (S', N) bool (the environment ended the episode on this step)."""
        world = self.world
        if not self.running.any():
            zeros = torch.zeros(self.shape, device=world.device, dtype=world.dtype)
            ended = torch.ones(self.shape, dtype=torch.bool, device=world.device)
            return Transition(states, zeros, ended)
        clipped = actions.flatten(0, 1).clamp(world.action_low, world.action_high)
        observations, rewards, ended = self.pool.step(
            clipped.to("cpu").numpy().astype(world.action_space.dtype, copy=False)
        )
        running = torch.as_tensor(self.running, device=world.device).view(*self.shape, 1)
        next_states = torch.where(running, world.as_states(observations).view_as(states), states)
        rewards = np.where(self.running, rewards, 0.0)
        self.running &= ~ended
        return Transition(
            next_states,
            torch.as_tensor(rewards, device=world.device, dtype=world.dtype).view(self.shape),
            torch.as_tensor(ended, device=world.device).view(self.shape),
        )


def _configuration_names(configurations: list[dict[str, Any]]) -> tuple[str, ...]:
    """Each configuration named by the keywords in which it differs from the others
    ("g=5.0", "g=15.0"); one alone, or one with nothing of its own, is "default"."""
    shared = {
        k
        for k in set().union(*configurations)
        if all(k in c and c[k] == configurations[0].get(k) for c in configurations)
    }
    return tuple(
        ", ".join(f"{k}={v}" for k, v in c.items() if k not in shared) or "default"
        for c in configurations
    )


class GymWorld:
    """A class of Gymnasium environments M_1..M_I, one id with I keyword sets, stepped in
    batches. The interface the trainer, the rollout and the evaluation use is the one of
    :class:`~hmepol_cli.envs.base.NavigationWorld`; the 2-D drawing of walls has no meaning
    here, so the heatmaps plot a projection of the observation on two of its indices."""

    name = "gym"
    arena = None  # no map to draw: plots take their extent from the data
    maps = False
    episodes_end = True  # an environment may end an episode before T
    capturable = False  # steps run outside torch

    def __init__(
        self,
        env_id: str,
        features: Sequence[int] | None = None,
        configurations: Sequence[dict[str, Any]] | None = None,
        probs: Sequence[float] | None = None,
        projection: Sequence[int] | None = None,
        workers: int = 0,
    ) -> None:
        self.env_id = _check_id(env_id)
        self.configurations = [dict(c) for c in (configurations or [{}])]
        n = len(self.configurations)
        self.configuration_names = _configuration_names(self.configurations)
        self.configuration_probs = _check_probs(probs, n)
        if isinstance(workers, bool) or not isinstance(workers, int) or workers < 0:
            raise ConfigError(f"env.workers={workers!r} must be a whole number >= 0")
        self.workers = workers
        self.observation_space, self.action_space = _spaces(self.env_id, self.configurations)
        self.state_dim = int(self.observation_space.shape[0])
        self.action_dim = int(self.action_space.shape[0])
        self.features = _check_indices("env.features", features, self.state_dim)
        if projection is None:
            projection = self.features[:2] if len(self.features) >= 2 else self.features * 2
        self.projection = _check_indices("env.projection", projection, self.state_dim)
        if len(self.projection) != 2:
            raise ConfigError(
                f"env.projection={list(projection)} must name two observation indices"
            )
        self._pools: dict[int, SlotPool] = {}
        self.to("cpu", torch.float32)

    @classmethod
    def from_config(cls, env_cfg) -> GymWorld:
        """The world of an ``env`` config group entry (``env=gym env.id=...``)."""
        if not getattr(env_cfg, "id", None):
            raise ConfigError("env=gym needs env.id=<a Gymnasium id>, e.g. env.id=Pendulum-v1")
        configurations = getattr(env_cfg, "configs", None)
        if OmegaConf.is_config(configurations):
            configurations = OmegaConf.to_container(configurations, resolve=True)
        if configurations is not None and (
            not isinstance(configurations, list)
            or not configurations
            or not all(isinstance(c, dict) for c in configurations)
        ):
            raise ConfigError(
                f"env.configs={configurations!r} must be a non-empty list of keyword sets, "
                "e.g. [{g: 5.0}, {g: 15.0}]"
            )
        return cls(
            str(env_cfg.id),
            features=_plain(getattr(env_cfg, "features", None)),
            configurations=configurations,
            probs=_plain(getattr(env_cfg, "probs", None)),
            projection=_plain(getattr(env_cfg, "projection", None)),
            workers=int(getattr(env_cfg, "workers", 0) or 0),
        )

    @classmethod
    def check_config(cls, env_cfg) -> None:
        """Refuse a bad ``env`` entry in one line (the id, every configuration's spaces, the
        indices) before anything is written."""
        cls.from_config(env_cfg).close()

    # ------------------------------------------------------------------ as a world
    @property
    def n_configurations(self) -> int:
        return len(self.configuration_probs)

    def to(self, device: torch.device | str, dtype: torch.dtype = torch.float32) -> GymWorld:
        self.device, self.dtype = torch.device(device), dtype
        kw = dict(device=self.device, dtype=dtype)
        self.action_low = torch.as_tensor(self.action_space.low, **kw)
        self.action_high = torch.as_tensor(self.action_space.high, **kw)
        self._probs = torch.tensor(
            self.configuration_probs, device=self.device, dtype=torch.float64
        )
        self._features = torch.tensor(self.features, device=self.device)
        self._projection = torch.tensor(self.projection, device=self.device)
        return self

    def sample_configurations(
        self, n: int, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """Draw n configuration indices from p_M. (n,) long."""
        return torch.multinomial(self._probs, n, replacement=True, generator=generator)

    def describe(self, config: int) -> str:
        return f"{self.env_id}: {self.configuration_names[config]}"

    def free_area(self, config: int | None = None) -> float:
        """Unknown: no bound on the entropy is drawn for a Gymnasium world (NaN)."""
        return math.nan

    def entropy_features(self, states: torch.Tensor) -> torch.Tensor:
        """The indices ``env.features`` of states, what the entropy is computed on.
        (..., d) -> (..., p)"""
        if len(self.features) == self.state_dim and self.features == tuple(range(self.state_dim)):
            return states
        return states.index_select(-1, self._features)

    def plane(self, states: torch.Tensor) -> torch.Tensor:
        """The two indices ``env.projection`` of states, what heatmaps draw. (..., d) -> (..., 2)"""
        return states.index_select(-1, self._projection)

    def action_bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Where actions are clipped, per dimension: the action space. (low (a,), high (a,))"""
        return self.action_low, self.action_high

    def state_bounds(self) -> tuple[list[float], list[float]]:
        """The observation space's bounds per index (infinite where it is unbounded)."""
        return (
            [float(v) for v in self.observation_space.low],
            [float(v) for v in self.observation_space.high],
        )

    def as_states(self, observations: np.ndarray) -> torch.Tensor:
        """A batch of observations as one tensor on the world's device. (m, d) -> (m, d)"""
        return torch.as_tensor(np.asarray(observations), device=self.device, dtype=self.dtype)

    # ------------------------------------------------------------------ episodes
    def draw_seeds(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """Reset seeds of n episodes from a run's generator. (n,) long"""
        return torch.randint(
            0, SEED_BOUND, (n,), generator=generator, device=generator.device, dtype=torch.long
        )

    def begin(
        self,
        configurations: torch.Tensor,
        horizon: int,
        generators: Sequence[torch.Generator],
        members: torch.Tensor | None = None,
    ) -> tuple[GymEpisodes, torch.Tensor]:
        """S' x N episodes on a pool of slots (one pool per size, kept between rollouts), each
        reset with its own seed; member i draws its N seeds, then its action noise."""
        seeds, noise = [], []
        for generator in generators:
            seeds.append(self.draw_seeds(configurations.shape[1], generator))
            noise.append(action_noise(configurations.shape[1], horizon, self, generator))
        m = configurations.numel()
        if m not in self._pools:
            self._pools[m] = SlotPool(self.env_id, self.configurations, m, self.workers)
        episodes = GymEpisodes(self, self._pools[m], configurations, torch.stack(seeds))
        return episodes, torch.stack(noise)

    def facts(self, member: int | None = None) -> dict[str, object]:
        """The Gymnasium id, and no map (pictures project the observation on two indices)."""
        return {"env_id": self.env_id, "world_map": None}

    def for_members(self, env_cfgs) -> GymWorld:
        """A population's members share one Gymnasium world (their env entries are equal)."""
        return self

    def close(self) -> None:
        """Close the environments (and stop the worker processes); later rollouts reopen them."""
        for pool in self._pools.values():
            pool.close()
        self._pools.clear()

    def __getstate__(self) -> dict[str, Any]:
        # Pools hold processes and simulators: a copy of the world starts without them.
        return {**self.__dict__, "_pools": {}}


# ---------------------------------------------------------------------- checks
def _plain(value: Any) -> Any:
    return OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value


def _check_id(env_id: str) -> str:
    """A registered id, or ``module:id``: Gymnasium's way to name an id that ``module``
    registers when imported (your own environment), which gymnasium.make understands too."""
    module, _, name = env_id.rpartition(":")
    if module:
        try:
            importlib.import_module(module)
        except ImportError as error:
            raise ConfigError(
                f"env.id={env_id!r}: the module {module!r} that should register {name!r} cannot "
                f"be imported ({error}); is it on PYTHONPATH?"
            ) from None
    try:
        gym.spec(name)
    except gym.error.Error:
        close = difflib.get_close_matches(name, list(gym.registry), n=3)
        hint = f"; did you mean {', '.join(close)}?" if close else ""
        raise ConfigError(
            f"env.id={env_id!r} is not a registered Gymnasium id{hint} (ids are listed by "
            "gymnasium.pprint_registry())"
        ) from None
    return env_id


def _check_probs(probs: Sequence[float] | None, n: int) -> tuple[float, ...]:
    if probs is None:
        return (1.0 / n,) * n
    values = list(probs)
    if (
        len(values) != n
        or not all(isinstance(p, int | float) and math.isfinite(p) and p >= 0 for p in values)
        or not sum(values) > 0
    ):
        raise ConfigError(
            f"env.probs={values!r} must hold {n} finite number{'s' if n > 1 else ''} >= 0, one "
            f"per configuration of env.configs, not all 0"
        )
    total = float(sum(values))
    if abs(total - 1.0) > 1e-6:
        raise ConfigError(
            f"env.probs={values!r} sum to {total:g}: p_M must sum to 1 (nothing is renormalised)"
        )
    return tuple(float(p) for p in values)


def _check_indices(key: str, indices: Sequence[int] | None, dim: int) -> tuple[int, ...]:
    if indices is None:
        return tuple(range(dim))
    values = list(indices)
    if (
        not values
        or not all(isinstance(i, int) and not isinstance(i, bool) for i in values)
        or not all(0 <= i < dim for i in values)
        or (key == "env.features" and len(set(values)) != len(values))
    ):
        raise ConfigError(
            f"{key}={values!r} must be {'distinct ' if key == 'env.features' else ''}"
            f"observation indices in 0..{dim - 1} (the observation has {dim})"
        )
    return tuple(values)


def _spaces(
    env_id: str, configurations: list[dict[str, Any]]
) -> tuple[gym.spaces.Box, gym.spaces.Box]:
    """The observation and action spaces every configuration shares, or one clear line."""
    spaces = []
    for c, kwargs in enumerate(configurations):
        try:
            env = make_env(env_id, kwargs)
        except (gym.error.DependencyNotInstalled, ImportError) as error:
            raise ConfigError(
                f"env.id={env_id!r} needs a package that is not installed "
                f"({str(error).splitlines()[0][:120]}); for MuJoCo: pip install 'hmepol[mujoco]'"
            ) from None
        except (TypeError, ValueError, gym.error.Error) as error:
            raise ConfigError(
                f"env.configs[{c}]={kwargs!r}: gymnasium.make({env_id!r}) refused it "
                f"({str(error).splitlines()[0][:160]})"
            ) from None
        spaces.append((env.observation_space, env.action_space))
        env.close()
    observation, action = spaces[0]
    for name, space in (("observation", observation), ("action", action)):
        if not isinstance(space, gym.spaces.Box) or len(space.shape) != 1:
            raise ConfigError(
                f"env.id={env_id!r} has a {name} space {space}; hmepol needs a flat Box "
                "(a vector of numbers)"
            )
    for c, (obs_c, act_c) in enumerate(spaces[1:], start=1):
        for name, mine, first in (("observation", obs_c, observation), ("action", act_c, action)):
            if mine != first:
                raise ConfigError(
                    f"env.configs[{c}]={configurations[c]!r} gives the {name} space "
                    f"{_describe(mine, first)}, configuration 0 {_describe(first, mine)}: every "
                    "configuration must share the observation and action spaces"
                )
    return observation, action


def _describe(space: gym.Space, other: gym.Space) -> str:
    """A space in a few words: its shape and dtype, or its bounds where only they differ."""
    shape = getattr(space, "shape", None)
    if shape != getattr(other, "shape", None) or space.dtype != other.dtype:
        return f"{type(space).__name__}{shape} {space.dtype}"
    return f"with bounds [{space.low.min():g}, {space.high.max():g}]"
