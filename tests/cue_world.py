r"""Cue corridor: a world where only a memory of the first state tells the agent where to go.

A test world for memory (a task a Markovian policy cannot solve), not one of the registered
pre-training worlds. The arena is [-1, 1]^2. Two full-width walls (y in [0.2, 0.3] and
[-0.3, -0.2]) cut it into three bands, the corridor (|y| < 0.2) and two *pads* (|y| > 0.3),
and no path joins a pad to the corridor::

           x = -1                  x = 1
           +-----------------------+
           |          [c0]         |  top pad: config 0 starts at y in [0.8, 0.9]
           |                       |
           |#######################|
           |GGGGG      o      RRRRR|  corridor; o the origin, G / R the goal of config 0 / 1
           |#######################|
           |                       |
           |          [c1]         |  bottom pad: config 1 starts at y in [-0.9, -0.8]
           +-----------------------+

- The configuration is the *cue*: config 0 (``left``) starts in the top pad, config 1
  (``right``) in the bottom pad, uniform in a 0.2 x 0.1 box. That first state is the only
  thing that differs between the two: they share walls and dynamics, and no force acts.
- A step from a pad, whatever the action, puts the agent on the origin (0, 0) of the corridor,
  and the walls keep it there afterwards: s_1 = (0, 0) in both configurations, and the cue is
  gone from the state.
- The goal of config 0 is the corridor's left end (x <= -0.5), of config 1 its right end
  (x >= 0.5): ``GOALS[c]``, the box of a goal task.

Why a Markovian policy cannot beat chance, on average over the two configurations: from s_1 on
its actions depend on the state only, and the state does not depend on the configuration, so
the trajectory s_1..s_T has one law in both. Reaching a goal from the origin takes at least 3
moves (0.6 > 0.5 at 0.2 a move), going on to the other goal at least 5 more, so an episode of
``MEMORY_HORIZON`` steps (the jump, then 7 moves) never visits both goals: P(reach left) +
P(reach right) <= 1, and the success rate averaged over the configurations is at most 1/2.
A policy that remembers s_0 can reach its goal almost always.
"""

from __future__ import annotations

import torch

from hmepol_cli.envs.base import Box, NavigationWorld

ARENA = Box(-1.0, -1.0, 1.0, 1.0)
CORRIDOR = Box(-1.0, -0.2, 1.0, 0.2)
PADS = (Box(-0.1, 0.8, 0.1, 0.9), Box(-0.1, -0.9, 0.1, -0.8))  # start box of config 0, 1
PAD_EDGE = 0.3  # |y| > PAD_EDGE: on a pad
WALLS = (
    Box(-1.0, 0.2, 1.0, 0.3),  # between the top pad and the corridor
    Box(-1.0, -0.3, 1.0, -0.2),  # between the corridor and the bottom pad
)
GOALS = (Box(-1.0, -0.2, -0.5, 0.2), Box(0.5, -0.2, 1.0, 0.2))  # left end (config 0), right end (1)
MEMORY_HORIZON = 8  # the longest episode (the jump included) that cannot visit both goals


class CueCorridorWorld(NavigationWorld):
    """The start pad is the cue; after the first step both configurations look alike."""

    name = "cue"
    arena = ARENA
    start = Box(-0.1, -0.9, 0.1, 0.9)  # spans both pads, so drawn targets avoid them
    configuration_names = ("left", "right")
    configuration_probs = (0.5, 0.5)
    walls = (WALLS, WALLS)

    def reset(
        self, configurations: torch.Tensor, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """Uniform in the pad of each configuration. configurations (N,) -> (N, 2)."""
        u = torch.rand(
            configurations.shape[0], 2, device=self.device, dtype=self.dtype, generator=generator
        )
        pads = torch.tensor(
            [[p.x0, p.y0, p.x1, p.y1] for p in PADS], device=self.device, dtype=self.dtype
        )[configurations]  # (N, 4)
        return pads[:, :2] + u * (pads[:, 2:] - pads[:, :2])

    def step(
        self,
        positions: torch.Tensor,
        actions: torch.Tensor,
        configurations: torch.Tensor,
        generator: torch.Generator | None = None,
        *,
        noise: torch.Tensor | None = None,
        strength: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """As the base world in the corridor; from a pad, to the origin whatever the action."""
        moved = super().step(positions, actions, configurations, generator, noise=noise)
        on_pad = (positions[:, 1].abs() > PAD_EDGE).unsqueeze(-1)
        return torch.where(on_pad, torch.zeros_like(moved), moved)
