"""The tasks of fine-tuning: the sparse goal-reaching task of the 2-D worlds (thesis 5.2, Fig.
5.9), and a Gymnasium world's own reward (:class:`RewardTask`).

A task fixes one configuration of a world and a target area, a square box in free space. The
reward is 1 on the step the agent enters the box, 0 on every other step, and the episode ends
there (the box is absorbing), or after ``horizon`` steps. So an episode's undiscounted return is
1 when it reached the target and 0 otherwise, and the discount makes earlier arrivals worth more.
Ending on arrival keeps the return bounded and leaves no reward to farm by stepping out and in.

Random targets are drawn from a seed, target k from its own stream ``[seed, k]``: a square of
side ``0.1 * arena side`` by default (0.2 on the [-1, 1]^2 gridworlds, 1.2 in the corridor)
lying entirely in the configuration's free space and away from the start area (an agent must
move to earn the reward). The same candidate stream serves every configuration, so worlds whose
configurations share their walls (slope, corridor) get the same five targets in each
configuration; multigrid's layouts can differ, and so can its targets.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch

from hmepol_cli.envs.base import Box, NavigationWorld
from hmepol_cli.envs.world import World
from hmepol_cli.policies.base import Policy
from hmepol_cli.rollout import Rollout, collect_single

TARGET_SCALE = 0.1  # default target side, as a fraction of the arena side
MASK_RESOLUTION = 400  # free-space raster used to check that a target lies in free space
MAX_DRAWS = 100_000


class TargetError(ValueError):
    """No target area fits the request (a box too large for the free space)."""


@dataclass(frozen=True)
class GoalTask:
    """Reach ``target`` in configuration ``config`` within ``horizon`` steps."""

    target: Box
    config: int
    horizon: int
    # An episode's undiscounted return is 1 when it reached the target (the box is absorbing)
    # and 0 otherwise, so an epoch's mean return is its success rate: the report's intervals
    # of returns stay inside these bounds.
    return_bounds: ClassVar[tuple[float, float]] = (0.0, 1.0)

    def reached(self, positions: torch.Tensor) -> torch.Tensor:
        """True where a position lies in the target box. positions (N, 2) -> (N,) bool."""
        b = self.target
        x, y = positions[:, 0], positions[:, 1]
        return (x >= b.x0) & (x <= b.x1) & (y >= b.y0) & (y <= b.y1)


@dataclass(frozen=True)
class RewardTask:
    """A Gymnasium world's own task in configuration ``config``: the environment's reward and
    termination, episodes of at most ``horizon`` steps."""

    config: int
    horizon: int
    target = None  # no target area: the environment's reward says what to do
    return_bounds: ClassVar[tuple[float, float]] = (-math.inf, math.inf)  # any reward: no bound
    reached = None  # episodes end when the environment ends them


def recorded_return_bounds(maps: bool) -> list[float | None]:
    """The bounds of the returns of the task a fine-tuning runs in a world with a map (``maps``:
    a goal task) or without one (the world's own reward), as run.json records them for the
    report: [low, high], null where a side is unbounded."""
    task = GoalTask if maps else RewardTask
    return [bound if math.isfinite(bound) else None for bound in task.return_bounds]


@dataclass
class TaskRollout(Rollout):
    """Episodes of one fine-tuning task, with what the task makes of them. The trajectories may
    be shorter than the task's horizon T when every episode ended before it."""

    horizon: int = 0  # the task's T
    goal: bool = False  # a goal task: the reward is reaching the target, which ends the episode

    @property
    def rewards(self) -> torch.Tensor:
        """1 on the step an episode reaches the target of a goal task, 0 otherwise; or the
        environment's reward. (..., T)"""
        return self.ended.to(self.states.dtype) if self.goal else self.reward

    @property
    def ends(self) -> torch.Tensor:
        """True on the step an episode ended (reached its target, or the environment ended it)."""
        return self.ended

    @property
    def returns(self) -> torch.Tensor:
        """Undiscounted return of each episode. (..., N)"""
        return (self.rewards * self.alive).sum(dim=-1)

    @property
    def success(self) -> torch.Tensor | None:
        """A goal task: the step an episode reached the target (None: no target). (..., T)"""
        return self.ended if self.goal else None

    @property
    def succeeded(self) -> torch.Tensor:
        return self.success.any(dim=-1)

    @property
    def lengths(self) -> torch.Tensor:
        return self.alive.sum(dim=-1)


def collect_episodes(
    world: World,
    policy: Policy,
    task: GoalTask | RewardTask,
    episodes: int,
    generator: torch.Generator,
) -> TaskRollout:
    """``episodes`` episodes of one fine-tuning task, stepped together until all have ended or
    the task's horizon is spent. (N, T, ...)"""
    configurations = torch.full((episodes,), task.config, dtype=torch.long, device=world.device)
    rollout = collect_single(
        world, policy, configurations, task.horizon, generator,
        ends_episode=task.reached, until_ended=True,
    )  # fmt: skip
    return TaskRollout(**vars(rollout), horizon=task.horizon, goal=task.reached is not None)


def default_target_side(world: NavigationWorld) -> float:
    a = world.arena
    return TARGET_SCALE * min(a.x1 - a.x0, a.y1 - a.y0)


def box_around(center: tuple[float, float], side: float) -> Box:
    x, y = center
    return Box(x - side / 2, y - side / 2, x + side / 2, y + side / 2)


def _overlaps(a: Box, b: Box) -> bool:
    return a.x0 < b.x1 and b.x0 < a.x1 and a.y0 < b.y1 and b.y0 < a.y1


def _box_is_free(free: np.ndarray, arena: Box, box: Box) -> bool:
    """Every raster cell whose centre lies in ``box`` is free. free (R, R) bool, row 0 at y0."""
    rows, cols = free.shape
    cw, ch = (arena.x1 - arena.x0) / cols, (arena.y1 - arena.y0) / rows
    # Indices of the cell centres inside [x0, x1]: centre_i = x0_arena + (i + 1/2) cw.
    c0 = max(0, int(np.ceil((box.x0 - arena.x0) / cw - 0.5)))
    c1 = min(cols - 1, int(np.floor((box.x1 - arena.x0) / cw - 0.5)))
    r0 = max(0, int(np.ceil((box.y0 - arena.y0) / ch - 0.5)))
    r1 = min(rows - 1, int(np.floor((box.y1 - arena.y0) / ch - 0.5)))
    if c1 < c0 or r1 < r0:
        return True  # smaller than a cell: judged by its centre cell below
    return bool(free[r0 : r1 + 1, c0 : c1 + 1].all())


def draw_target(world: NavigationWorld, config: int, index: int, seed: int, side: float) -> Box:
    """Target ``index`` of ``seed``: a free square of ``side`` away from the start area."""
    arena = world.arena
    if side <= 0 or side >= min(arena.x1 - arena.x0, arena.y1 - arena.y0):
        raise TargetError(f"goal_size={side!r} must be > 0 and smaller than the arena side")
    free = world.free_mask(config, MASK_RESOLUTION)
    rng = np.random.default_rng([int(seed), int(index)])
    half = side / 2
    for _ in range(MAX_DRAWS):
        cx = rng.uniform(arena.x0 + half, arena.x1 - half)
        cy = rng.uniform(arena.y0 + half, arena.y1 - half)
        box = box_around((cx, cy), side)
        if not _overlaps(box, world.start) and _box_is_free(free, arena, box):
            return box
    raise TargetError(
        f"goal_size={side!r}: no free square of that side found in {world.name} config {config}; "
        "use a smaller goal_size"
    )


def make_tasks(
    world: NavigationWorld,
    config: int,
    horizon: int,
    goal: str | list,
    targets: int,
    seed: int,
    side: float | None,
) -> list[GoalTask]:
    """The fine-tuning tasks of one configuration.

    ``goal`` is ``"random"`` (``targets`` boxes drawn from ``seed``) or a list of ``[x, y]``
    target centres (then ``targets`` is ignored).
    """
    side = default_target_side(world) if side is None else float(side)
    if isinstance(goal, str):
        boxes = [draw_target(world, config, k, seed, side) for k in range(targets)]
    else:
        boxes = [box_around((float(x), float(y)), side) for x, y in goal]
        free = world.free_mask(config, MASK_RESOLUTION)
        a = world.arena
        for (x, y), box in zip(goal, boxes, strict=True):
            inside = a.x0 <= box.x0 and box.x1 <= a.x1 and a.y0 <= box.y0 and box.y1 <= a.y1
            if not inside or not _box_is_free(free, a, box):
                raise TargetError(
                    f"goal=[{x:g}, {y:g}]: a target of side {side:g} there is not in the free "
                    f"space of {world.name} configuration {config}; choose a centre in free space"
                )
    return [GoalTask(box, config, horizon) for box in boxes]
