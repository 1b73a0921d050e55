"""The policy interface the trainer talks to: a diagonal Gaussian on a history encoding.

Every policy carries a recurrent *history* tensor ``(N, H)`` between steps (thesis 4.2.1:
h'_0 = 0, h'_t = g(s_t, h'_{t-1})); a Markovian policy has H = 0 and ignores it. One step maps
(s_t, h'_{t-1}) to (mean of a_t, h'_t). The log-std is a state-independent parameter.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from hmepol_cli import blas
from hmepol_cli.precision import lowered_history

ACTIVATIONS = {"relu": nn.ReLU, "tanh": nn.Tanh}


class Linear(nn.Linear):
    """``nn.Linear`` whose float32 CPU products run through the library ``blas`` selects
    (:mod:`hmepol_cli.blas`); the same parameters, state dict and function."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return blas.linear(x, self.weight, self.bias)


class OutputLinear(Linear):
    """The layer that gives the action mean: its product is never lowered in precision
    (``precision=bf16`` lowers the hidden layers'), so the likelihoods are computed from
    full-precision means. Its input is cast to the weights' dtype."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        with torch.autocast(x.device.type, enabled=False):
            return blas.linear(x.to(self.weight.dtype), self.weight, self.bias)


class HistoryLinear(Linear):
    """A layer whose output is (part of) the history h'_t: in full precision while the
    likelihoods run the recursion over several steps (``bptt`` > 1), where rounding would
    accumulate; a hidden layer like any other at bptt = 1, where h'_t is computed once from
    the stored h'_{t-1} (``hmepol_cli.precision.lowered_history``)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if lowered_history():
            return super().forward(x)
        with torch.autocast(x.device.type, enabled=False):
            return blas.linear(x.to(self.weight.dtype), self.weight, self.bias)


class MLP(nn.Sequential):
    """Linear layers, ReLU between them, and an optional output activation. Where OpenBLAS
    runs the products (:func:`hmepol_cli.blas.fuses`: float32 on a CPU, no autocast, so every
    layer kind is a plain linear layer) the Linear/ReLU layers run as one stack, row block by
    row block (:func:`hmepol_cli.blas.mlp`); elsewhere one module after the other."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        modules = list(self)
        if not (
            modules
            and isinstance(modules[0], Linear)
            and blas.fuses(x, modules[0].weight)
            and not any(m._forward_hooks or m._forward_pre_hooks for m in modules)
        ):  # hooks on a layer see its call: then one layer after the other
            return super().forward(x)
        layers: list[blas.Layer] = []
        i = 0
        while i < len(modules) and isinstance(modules[i], Linear):
            relu = i + 1 < len(modules) and isinstance(modules[i + 1], nn.ReLU)
            layers.append(blas.Layer(modules[i].weight, modules[i].bias, relu))
            i += 2 if relu else 1
        x = blas.mlp(x, layers)
        for module in modules[i:]:
            x = module(x)
        return x


def mlp(
    sizes: list[int], out_activation: str | None = None, output: type[nn.Linear] = OutputLinear
) -> MLP:
    """Linear layers with ReLU between them, and ``out_activation`` (relu, tanh) after the last,
    which is of kind ``output``: :class:`OutputLinear` for an action mean,
    :class:`HistoryLinear` for a history, :class:`Linear` for a hidden layer's output."""
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        kind = output if i == len(sizes) - 2 else Linear
        layers.append(kind(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2:
            layers.append(nn.ReLU())
    if out_activation is not None:
        layers.append(ACTIVATIONS[out_activation]())
    return MLP(*layers)


WEIGHT_INITS = ("xavier", "torch")


class Policy(nn.Module):
    """pi_theta(a | h): diagonal Gaussian whose mean reads the encoded history."""

    history_size: int = 0

    def __init__(
        self,
        state_dim: int,
        action_dim: int,
        init_log_std: float = -1.5,
        init_weights: str = "xavier",
        init_mean_scale: float = 0.01,
    ) -> None:
        super().__init__()
        if init_weights not in WEIGHT_INITS:
            raise ValueError(f"init_weights={init_weights!r}; choose one of {WEIGHT_INITS}")
        self.state_dim, self.action_dim = state_dim, action_dim
        self.log_std = nn.Parameter(torch.full((action_dim,), float(init_log_std)))
        self._init_weights, self._init_mean_scale = init_weights, float(init_mean_scale)

    def initialise(self, mean_layer: nn.Linear) -> None:
        """The reference start (docs/worlds.md): Xavier-uniform weights in every linear
        layer (biases as torch draws them), and a near-zero mean action: ``mean_layer``, the
        layer that outputs the mean, scaled by ``init_mean_scale`` with a zero bias. (The
        reference fits its network to output zero for ~50 supervised steps instead; scaling
        the last layer gives a near-zero mean for every input, histories included.)
        Subclasses call this at the end of their constructor."""
        with torch.no_grad():
            if self._init_weights == "xavier":
                for module in self.modules():
                    if isinstance(module, nn.Linear):
                        nn.init.xavier_uniform_(module.weight)
            mean_layer.weight.mul_(self._init_mean_scale)
            mean_layer.bias.zero_()

    # -- to implement ----------------------------------------------------------------------
    @classmethod
    def from_config(cls, cfg, state_dim: int, action_dim: int, **start) -> Policy:
        """The policy of a ``policy`` config group entry; ``start`` holds the initialisation."""
        raise NotImplementedError

    def step(
        self, states: torch.Tensor, history: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(s_t (N, d), h'_{t-1} (N, H)) -> (mean of a_t (N, a), h'_t (N, H))."""
        raise NotImplementedError

    # -- shared ----------------------------------------------------------------------------
    def initial_history(self, n: int, device=None, dtype=None) -> torch.Tensor:
        """h'_0 = 0 for n trajectories. (n, H)"""
        return torch.zeros(n, self.history_size, device=device, dtype=dtype)

    def gaussian_log_prob(self, mean: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """log N(actions; mean, diag(exp(log_std))^2), summed over action dims. (...,)"""
        log_std = self.log_std
        z = (actions - mean) * torch.exp(-log_std)
        return (-0.5 * z.pow(2) - log_std - 0.5 * math.log(2 * math.pi)).sum(dim=-1)

    @torch.no_grad()
    def act(
        self, states: torch.Tensor, history: torch.Tensor, noise: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """a_t = mean + std * noise, with noise ~ N(0, I) given (None: the mean action).

        -> (actions (N, a), log pi(a_t | h_t) (N,), h'_t (N, H), means (N, a)).
        """
        mean, next_history = self.step(states, history)
        actions = mean if noise is None else mean + noise * torch.exp(self.log_std)
        return actions, self.gaussian_log_prob(mean, actions), next_history, mean

    def log_prob(
        self,
        states: torch.Tensor,
        actions: torch.Tensor,
        histories: torch.Tensor,
        bptt: int | None = 1,
    ) -> torch.Tensor:
        """log pi_theta(a_t | h_t) of stored trajectories under the current parameters.

        states (N, T, d) are s_0..s_{T-1}, actions (N, T, a), histories (N, T, H) the h'_{t-1}
        each step of the *sampling* policy read. ``bptt`` sets how far back the recursion is
        recomputed under the current parameters: 1 (the stored h'_{t-1} is the input; thesis),
        n (from the stored h'_{t-n}), None (the whole trajectory from h'_0 = 0: exact
        likelihoods). Gradients flow through the recomputed steps only. -> (N, T)
        """
        n, t, _ = states.shape
        if self.history_size == 0 or bptt == 1:
            mean, _ = self.step(states.reshape(n * t, -1), histories.reshape(n * t, -1))
            return self.gaussian_log_prob(mean.view(n, t, -1), actions)
        if bptt is None or bptt >= t:
            return self._log_prob_full(states, actions)
        return self._log_prob_truncated(states, actions, histories, bptt)

    def _log_prob_full(self, states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        n, t, _ = states.shape
        history = self.initial_history(n, states.device, states.dtype)
        means = []
        for step in range(t):
            mean, history = self.step(states[:, step], history)
            means.append(mean)
        return self.gaussian_log_prob(torch.stack(means, dim=1), actions)

    def _log_prob_truncated(
        self, states: torch.Tensor, actions: torch.Tensor, histories: torch.Tensor, n_back: int
    ) -> torch.Tensor:
        n, t, d = states.shape
        steps = torch.arange(t, device=states.device)
        first = (steps - n_back + 1).clamp_min(0)  # first recomputed step of each t
        history = histories[:, first]  # stored h'_{first-1}, detached data: (N, T, H)
        mean = None
        for i in range(n_back):
            src = steps - n_back + 1 + i  # the step whose state this pass reads
            valid = (src >= 0).view(1, t, 1)
            s = states[:, src.clamp_min(0)]
            step_mean, step_history = self.step(s.reshape(n * t, d), history.reshape(n * t, -1))
            history = torch.where(valid, step_history.view(n, t, -1), history)
            mean = step_mean.view(n, t, -1)  # the last pass (src = t) is always valid
        return self.gaussian_log_prob(mean, actions)
