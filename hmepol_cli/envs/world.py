"""The interface every world implements, and what a rollout, the trainer, the evaluation,
fine-tuning and the report talk to: the 2-D navigation worlds
(:class:`~hmepol_cli.envs.base.NavigationWorld`) and any Gymnasium environment
(:class:`~hmepol_cli.envs.gym_world.GymWorld`) alike.

A world is made from its ``env`` config entry (:meth:`World.from_config`, which
:func:`hmepol_cli.envs.make_world` calls; :meth:`World.check_config` refuses a bad entry before a
run starts).

A rollout of S' members x N trajectories asks the world to :meth:`World.begin` its episodes
(start states and the random numbers the world and the policy's actions will use, drawn up front
from each member's generator, in the world's own order), then steps them T times with
:meth:`Episodes.step`, which returns a :class:`Transition`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import torch


@dataclass
class Transition:
    """One step of S' x N episodes."""

    states: torch.Tensor  # (S', N, d): s_{t+1}
    reward: torch.Tensor | None = None  # (S', N): the environment's reward (Gymnasium worlds)
    ended: torch.Tensor | None = None  # (S', N) bool: the environment ended the episode here


class Episodes(Protocol):
    """S' x N episodes a world has begun."""

    start: torch.Tensor  # (S', N, d): s_0

    def step(self, t: int, states: torch.Tensor, actions: torch.Tensor) -> Transition:
        """Step t of every episode: states (S', N, d), actions (S', N, a) as drawn."""
        ...


@runtime_checkable
class World(Protocol):
    """A class of configurations M_1..M_I sharing state and action spaces (thesis 2.1.1)."""

    name: str
    state_dim: int
    action_dim: int
    configuration_names: tuple[str, ...]
    configuration_probs: tuple[float, ...]
    device: torch.device
    dtype: torch.dtype
    maps: bool  # a 2-D map with walls: heatmaps on the arena, `hmepol show`, goal tasks
    episodes_end: bool  # the environment can end an episode before T (alive, reward, ended)
    capturable: bool  # steps are tensor operations only: a rollout can be one CUDA graph
    projection: tuple[int, int]  # the two state indices pictures draw (plane())

    @classmethod
    def from_config(cls, env_cfg: Any) -> World:
        """The world of an ``env`` config group entry (an EnvConfig or DictConfig: its name and
        the settings of this kind of world); a bad setting is a ConfigError in one line."""
        ...

    @classmethod
    def check_config(cls, env_cfg: Any) -> None:
        """Refuse a bad ``env`` entry in one line before anything is written (called last by
        :func:`hmepol_cli.config.validate`; a world may build itself to check, and close)."""
        ...

    @property
    def n_configurations(self) -> int: ...

    def to(self, device: torch.device | str, dtype: torch.dtype = torch.float32) -> World: ...

    def sample_configurations(
        self, n: int, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """n configuration indices drawn from p_M. (n,) long"""
        ...

    def begin(
        self,
        configurations: torch.Tensor,
        horizon: int,
        generators: Sequence[torch.Generator],
        members: torch.Tensor | None = None,
    ) -> tuple[Episodes, torch.Tensor]:
        """Start S' x N episodes in ``configurations`` (S', N), row i for population member
        ``members[i]`` (None: row i is member i) drawing from ``generators[i]``.
        -> (the episodes, the actions' standard-normal noise (S', N, T, a))"""
        ...

    def for_members(self, env_cfgs: Sequence) -> World:
        """The world of a population whose members' ``env`` entries are ``env_cfgs`` (the same
        world, with what each member may have of its own: the corridor's wind)."""
        ...

    def entropy_features(self, states: torch.Tensor) -> torch.Tensor:
        """The part of states the entropy is computed on. (..., d) -> (..., p)"""
        ...

    def plane(self, states: torch.Tensor) -> torch.Tensor:
        """The two coordinates pictures draw. (..., d) -> (..., 2)"""
        ...

    def state_bounds(self) -> tuple[list[float], list[float]]: ...

    def action_bounds(self) -> tuple[torch.Tensor, torch.Tensor]: ...

    def free_area(self, config: int | None = None) -> float:
        """Area of free space (NaN where unknown): log of it bounds the entropy."""
        ...

    def describe(self, config: int) -> str: ...

    def facts(self, member: int | None = None) -> dict[str, object]:
        """What run.json records about the world (of a population's ``member``) beyond its
        configurations (edge, wind, id, the map pictures draw)."""
        ...

    def close(self) -> None: ...


def action_noise(n: int, horizon: int, world: World, generator: torch.Generator) -> torch.Tensor:
    """The standard-normal noise of n trajectories' actions. (n, T, a)"""
    return torch.randn(
        n, horizon, world.action_dim, device=world.device, dtype=world.dtype, generator=generator
    )
