"""Non-Markovian policies built on a recursive history encoder (thesis chapter 4, and ch. 6).

- ``RecursivePolicy``: the thesis architecture. Encoder g: MLP on [s_t, h'_{t-1}] with ReLU
  output, giving h'_t; Gaussian head: MLP on h'_t (Fig. 4.4). A ReLU output is unbounded, and
  trained with bptt=1 the recursion can become expansive (h'_t growing geometrically over the
  400 steps); ``encoder_activation="tanh"`` bounds it.
- ``TwoHeadPolicy``: one network with two outputs, the action mean and the next history.
- ``GRUPolicy`` / ``LSTMPolicy``: gated recurrent encoders; the LSTM's history tensor holds
  [h, c] side by side, so every policy carries one (N, H) tensor. Their gates are written out
  on linear layers (the equations of ``torch.nn.GRUCell`` / ``LSTMCell``), so a population of
  them runs under ``torch.vmap``, which has no batching rule for the fused cells.
"""

from __future__ import annotations

import torch
from torch import nn

from hmepol_cli.policies.base import HistoryLinear, Linear, OutputLinear, Policy, mlp


class RecursivePolicy(Policy):
    def __init__(
        self,
        state_dim: int,
        action_dim: int,
        hidden: list[int],
        encoder_hidden: list[int],
        history_size: int,
        encoder_activation: str = "relu",
        **init,
    ):
        super().__init__(state_dim, action_dim, **init)
        self.history_size = history_size
        self.encoder = mlp(
            [state_dim + history_size, *encoder_hidden, history_size],
            out_activation=encoder_activation,
            output=HistoryLinear,
        )
        self.head = mlp([history_size, *hidden, action_dim])
        self.initialise(self.head[-1])

    @classmethod
    def from_config(cls, cfg, state_dim: int, action_dim: int, **start) -> RecursivePolicy:
        return cls(
            state_dim,
            action_dim,
            hidden=list(cfg.hidden),
            encoder_hidden=list(cfg.encoder_hidden),
            history_size=cfg.history_size,
            # Runs saved before the option existed used the thesis' ReLU encoder output.
            encoder_activation=getattr(cfg, "encoder_activation", "relu"),
            **start,
        )

    def step(
        self, states: torch.Tensor, history: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        next_history = self.encoder(torch.cat((states, history), dim=-1))  # h'_t = g(s_t, h'_{t-1})
        return self.head(next_history), next_history


class TwoHeadPolicy(Policy):
    def __init__(
        self,
        state_dim: int,
        action_dim: int,
        hidden: list[int],
        history_size: int,
        encoder_activation: str = "relu",
        **init,
    ):
        super().__init__(state_dim, action_dim, **init)
        self.history_size = history_size
        self.trunk = mlp([state_dim + history_size, *hidden], out_activation="relu", output=Linear)
        self.mean_head = nn.Sequential(OutputLinear(hidden[-1], action_dim))
        self.history_head = mlp(
            [hidden[-1], history_size], out_activation=encoder_activation, output=HistoryLinear
        )
        self.initialise(self.mean_head[-1])

    @classmethod
    def from_config(cls, cfg, state_dim: int, action_dim: int, **start) -> TwoHeadPolicy:
        return cls(
            state_dim,
            action_dim,
            hidden=list(cfg.hidden),
            history_size=cfg.history_size,
            encoder_activation=getattr(cfg, "encoder_activation", "relu"),
            **start,
        )

    def step(
        self, states: torch.Tensor, history: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        features = self.trunk(torch.cat((states, history), dim=-1))
        return self.mean_head(features), self.history_head(features)


class GRUPolicy(Policy):
    def __init__(
        self,
        state_dim: int,
        action_dim: int,
        hidden: list[int],
        history_size: int,
        **init,
    ):
        super().__init__(state_dim, action_dim, **init)
        self.history_size = history_size
        self.input_gates = HistoryLinear(state_dim, 3 * history_size)  # reset, update, new
        self.hidden_gates = HistoryLinear(history_size, 3 * history_size)
        self.head = mlp([history_size, *hidden, action_dim])
        self.initialise(self.head[-1])

    @classmethod
    def from_config(cls, cfg, state_dim: int, action_dim: int, **start) -> GRUPolicy:
        return cls(state_dim, action_dim, list(cfg.hidden), cfg.history_size, **start)

    def step(
        self, states: torch.Tensor, history: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        x_r, x_z, x_n = self.input_gates(states).chunk(3, dim=-1)
        h_r, h_z, h_n = self.hidden_gates(history).chunk(3, dim=-1)
        reset = torch.sigmoid(x_r + h_r)
        update = torch.sigmoid(x_z + h_z)
        new = torch.tanh(x_n + reset * h_n)
        next_history = (1 - update) * new + update * history
        return self.head(next_history), next_history


class LSTMPolicy(Policy):
    def __init__(
        self,
        state_dim: int,
        action_dim: int,
        hidden: list[int],
        history_size: int,
        **init,
    ):
        super().__init__(state_dim, action_dim, **init)
        self.cell_size = history_size
        self.history_size = 2 * history_size  # [h, c]
        self.input_gates = HistoryLinear(state_dim, 4 * history_size)  # input, forget, cell, output
        self.hidden_gates = HistoryLinear(history_size, 4 * history_size)
        self.head = mlp([history_size, *hidden, action_dim])
        self.initialise(self.head[-1])

    @classmethod
    def from_config(cls, cfg, state_dim: int, action_dim: int, **start) -> LSTMPolicy:
        return cls(state_dim, action_dim, list(cfg.hidden), cfg.history_size, **start)

    def step(
        self, states: torch.Tensor, history: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        h, c = history.split(self.cell_size, dim=-1)
        gates = self.input_gates(states) + self.hidden_gates(h)
        i, f, g, o = gates.chunk(4, dim=-1)
        c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
        h = torch.sigmoid(o) * torch.tanh(c)
        return self.head(h), torch.cat((h, c), dim=-1)
