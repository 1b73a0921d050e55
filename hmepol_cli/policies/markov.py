"""Markovian policy (Mepol, alpha-Mepol): an MLP on the current state (thesis 4.2.2)."""

from __future__ import annotations

import torch

from hmepol_cli.policies.base import Policy, mlp


class MarkovPolicy(Policy):
    history_size = 0

    def __init__(self, state_dim: int, action_dim: int, hidden: list[int], **init):
        super().__init__(state_dim, action_dim, **init)
        self.mean_net = mlp([state_dim, *hidden, action_dim])
        self.initialise(self.mean_net[-1])

    @classmethod
    def from_config(cls, cfg, state_dim: int, action_dim: int, **start) -> MarkovPolicy:
        return cls(state_dim, action_dim, hidden=list(cfg.hidden), **start)

    def step(
        self, states: torch.Tensor, history: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        return self.mean_net(states), history
