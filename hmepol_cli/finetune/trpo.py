"""TRPO (Schulman et al. 2015, thesis [29]) for Markovian and recursive policies.

One update reads like sb3-contrib's ``trpo.py``:

1. advantages by GAE(lambda) with a learned value function;
2. g, the gradient of the surrogate mean(ratio * A) at the sampling policy;
3. s ~= F^-1 g by conjugate gradient, where F v is the Hessian-vector product of the mean KL
   between the sampling policy and the updated one, on the stored trajectories;
4. the step s scaled so that 1/2 s^T F s = max_kl, then a backtracking line search that accepts
   the first shrunk step which improves the surrogate and keeps the KL <= max_kl, and restores the
   parameters when none does;
5. a few epochs of Adam on the value function.

Non-Markovian policies: the rollout carries the history h'_t through the episode (h'_0 = 0 at
its start, never reset inside it) and stores the h'_{t-1} each step read. The update computes
likelihoods with ``policy.log_prob(..., bptt)``: ``bptt=1`` (default, as the thesis' HMepol) feeds
the stored h'_{t-1} and back-propagates one encoder step; ``n`` recomputes n steps from the stored
h'_{t-n}; ``None`` ("full") recomputes the whole history from h'_0 (exact likelihoods, slower).
At the sampling parameters every choice gives the sampling policy exactly, so the KL and the
ratios start at 0 and 1 whatever the choice.

The Gaussian KL is analytic. The policy interface exposes log-likelihoods, not means, so the KL
is written through them: for diagonal Gaussians with the sampling mean mu_0 (stored during the
rollout) and log-std log sigma_0,
    KL(pi_0 || pi) = -log pi(mu_0 | h) - sum log sigma_0 + sum sigma_0^2 / (2 sigma^2)
                     - d/2 (1 + log 2 pi),
which is the closed form sum[log sigma/sigma_0 + (sigma_0^2 + (mu_0 - mu)^2) / (2 sigma^2) - 1/2].

The value function reads the state (scaled to the arena, or to a Gymnasium world's bounded
observation indices) and the time left, t / T, never the history: the fine-tuning task fixes one
configuration, and any function of the state is an unbiased baseline; the time input makes the
horizon's end a true terminal state.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, fields

import torch
from torch import nn

from hmepol_cli.config import TRPOConfig
from hmepol_cli.envs.world import World
from hmepol_cli.finetune.task import TaskRollout
from hmepol_cli.policies.base import Policy, mlp
from hmepol_cli.rollout import Rollout


@dataclass
class TRPOSettings(TRPOConfig):
    """The hyperparameters (defaults in :class:`hmepol_cli.config.TRPOConfig`) and how far back
    the likelihoods recompute a recursive policy's history (``policy.bptt``: 1, n, None)."""

    bptt: int | None = 1

    @classmethod
    def from_config(cls, cfg, bptt: int | None) -> TRPOSettings:
        """The settings of a (checked) fine-tuning config."""
        values = {f.name: cfg[f.name] for f in fields(TRPOConfig)}
        values["value_hidden"] = [int(h) for h in values["value_hidden"]]
        return cls(**values, bptt=bptt)


# --------------------------------------------------------------------------- value, GAE
class ValueFunction(nn.Module):
    """V(s_t, t / T): an MLP on the state scaled to [-1, 1] and the elapsed share of the horizon.

    ``low``, ``high``: the bounds of each state index (the arena of a 2-D world, a Gymnasium
    world's observation space); an unbounded index is left unscaled."""

    def __init__(
        self,
        low: list[float],
        high: list[float],
        horizon: int,
        hidden: tuple[int, ...] = (64, 64),
    ) -> None:
        super().__init__()
        self.horizon = horizon
        self.net = mlp([len(low) + 1, *hidden, 1])
        center, half = [], []
        for lo, hi in zip(low, high, strict=True):
            bounded = math.isfinite(lo) and math.isfinite(hi) and hi > lo
            center.append((lo + hi) / 2 if bounded else 0.0)
            half.append((hi - lo) / 2 if bounded else 1.0)
        self.register_buffer("center", torch.tensor(center))
        self.register_buffer("half_side", torch.tensor(half))

    def forward(self, states: torch.Tensor, steps: torch.Tensor) -> torch.Tensor:
        """states (..., d), steps (...) -> values (...)."""
        x = (states - self.center.to(states.dtype)) / self.half_side.to(states.dtype)
        tau = (steps.to(states.dtype) / self.horizon).unsqueeze(-1)
        return self.net(torch.cat((x, tau), dim=-1)).squeeze(-1)


def gae(
    rewards: torch.Tensor,
    values: torch.Tensor,
    next_values: torch.Tensor,
    ends: torch.Tensor,
    gamma: float,
    lam: float,
) -> torch.Tensor:
    """Generalised advantage estimates (Schulman et al. 2016), all (N, T).

    ``next_values`` is V(s_{t+1}), already 0 where the episode ends at t; ``ends`` stops the
    recursion there: A_t = delta_t + gamma lambda (1 - end_t) A_{t+1}.
    """
    deltas = rewards + gamma * next_values - values
    keep = gamma * lam * (~ends).to(values.dtype)
    advantages = torch.zeros_like(values)
    last = torch.zeros_like(values[:, 0])
    for t in reversed(range(values.shape[1])):
        last = deltas[:, t] + keep[:, t] * last
        advantages[:, t] = last
    return advantages


# --------------------------------------------------------------------------- the solver pieces
def flat_grad(
    output: torch.Tensor,
    params: list[torch.Tensor],
    create_graph: bool = False,
    retain_graph: bool | None = None,
) -> torch.Tensor:
    grads = torch.autograd.grad(
        output, params, create_graph=create_graph, retain_graph=retain_graph, allow_unused=True
    )
    return torch.cat(
        [
            (torch.zeros_like(p) if g is None else g).reshape(-1)
            for g, p in zip(grads, params, strict=True)
        ]
    )


def get_flat(params: list[torch.Tensor]) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1) for p in params])


@torch.no_grad()
def set_flat(params: list[torch.Tensor], flat: torch.Tensor) -> None:
    i = 0
    for p in params:
        p.copy_(flat[i : i + p.numel()].view_as(p))
        i += p.numel()


def conjugate_gradient(
    matvec: Callable[[torch.Tensor], torch.Tensor],
    b: torch.Tensor,
    iters: int = 10,
    tol: float = 1e-10,
) -> torch.Tensor:
    """Approximate x = A^-1 b for a symmetric positive-definite A given as ``matvec``."""
    x = torch.zeros_like(b)
    r = b.clone()  # residual b - A x
    p = r.clone()
    rr = r @ r
    for _ in range(iters):
        if rr <= tol:
            break
        ap = matvec(p)
        alpha = rr / (p @ ap)
        x += alpha * p
        r -= alpha * ap
        rr_new = r @ r
        p = r + (rr_new / rr) * p
        rr = rr_new
    return x


def fisher_vector_product(
    kl: torch.Tensor, params: list[torch.Tensor], damping: float = 0.0
) -> Callable[[torch.Tensor], torch.Tensor]:
    """v -> (H_KL + damping I) v, H_KL the Hessian of the mean KL (a scalar with its graph).

    At the sampling parameters the KL's Hessian is the Fisher information matrix F.
    """
    grad_kl = flat_grad(kl, params, create_graph=True)

    def product(v: torch.Tensor) -> torch.Tensor:
        return flat_grad(grad_kl @ v, params, retain_graph=True) + damping * v

    return product


@dataclass
class LineSearchResult:
    accepted: bool
    objective: float  # surrogate at the parameters the search ends with
    kl: float  # KL at the parameters the search ends with (0 when restored)
    fraction: float  # the accepted fraction of the full step (0 when restored)
    tries: int


def line_search(
    params: list[torch.Tensor],
    full_step: torch.Tensor,
    evaluate: Callable[[], tuple[float, float]],
    base_objective: float,
    max_kl: float,
    tries: int = 10,
    shrink: float = 0.8,
) -> LineSearchResult:
    """Backtracking search along ``full_step`` from the current parameters.

    ``evaluate()`` returns (surrogate, KL) at the parameters as they are set. A fraction
    ``shrink^i`` of the step is accepted when the surrogate improves on ``base_objective`` and
    the KL is <= ``max_kl`` (both finite); after ``tries`` rejected fractions the parameters are
    restored exactly.
    """
    start = get_flat(params)
    fraction = 1.0
    for i in range(tries):
        set_flat(params, start + fraction * full_step)
        objective, kl = evaluate()
        if (
            math.isfinite(objective)
            and math.isfinite(kl)
            and kl <= max_kl
            and objective > base_objective
        ):
            return LineSearchResult(True, objective, kl, fraction, i + 1)
        fraction *= shrink
    set_flat(params, start)
    return LineSearchResult(False, base_objective, 0.0, 0.0, tries)


# --------------------------------------------------------------------------- the update
def gaussian_kl(policy: Policy, rollout: Rollout, bptt: int | None) -> torch.Tensor:
    """KL(pi_0(.|h_t) || pi_theta(.|h_t)) at every stored step, in closed form. (N, T)"""
    d = rollout.means.shape[-1]
    log_std_0 = rollout.log_std
    log_lik = policy.log_prob(rollout.inputs, rollout.means, rollout.histories, bptt=bptt)
    variance_ratio = torch.exp(2 * (log_std_0 - policy.log_std)).sum()
    return -log_lik - log_std_0.sum() + 0.5 * variance_ratio - 0.5 * d * (1 + math.log(2 * math.pi))


def masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    return (x * mask).sum() / mask.sum().clamp_min(1)


@dataclass
class TRPOStep:
    """One TRPO update."""

    kl: float  # KL of the accepted step (0 when the line search restored the policy)
    accepted: bool
    tries: int
    surrogate_gain: float
    expected_gain: float
    value_loss: float


class TRPO:
    """Trust-region updates of ``policy`` on goal-task rollouts, with its own value function."""

    def __init__(
        self,
        policy: Policy,
        world: World,
        horizon: int,
        settings: TRPOSettings,
        generator: torch.Generator | None = None,
    ) -> None:
        self.policy, self.settings, self.generator = policy, settings, generator
        device = policy.log_std.device
        low, high = world.state_bounds()
        self.value = ValueFunction(low, high, horizon, settings.value_hidden).to(
            device, world.dtype
        )
        self.value_optimizer = torch.optim.Adam(self.value.parameters(), lr=settings.value_lr)
        self.params = [p for p in policy.parameters() if p.requires_grad]

    def advantages(self, rollout: TaskRollout) -> tuple[torch.Tensor, torch.Tensor]:
        """(advantages, value targets), both (N, T)."""
        s = self.settings
        n, t_len = rollout.alive.shape
        steps = torch.arange(t_len + 1, device=rollout.states.device).expand(n, -1)
        with torch.no_grad():
            v = self.value(rollout.states, steps)  # V(s_t), t = 0..T'
        timeout = steps[:, 1:] >= rollout.horizon  # the step that spends the last of the horizon
        ends = rollout.ends | timeout  # reached the target, or the environment ended it
        next_values = torch.where(ends, torch.zeros_like(v[:, 1:]), v[:, 1:])
        adv = gae(rollout.rewards, v[:, :-1], next_values, ends, s.gamma, s.gae_lambda)
        return adv, adv + v[:, :-1]

    def update(self, rollout: TaskRollout) -> TRPOStep:
        """One update from a goal-task rollout of the policy (no member dimension)."""
        s, policy = self.settings, self.policy
        mask = rollout.alive.to(rollout.rewards.dtype)
        # 1. advantages by GAE(lambda)
        advantages, targets = self.advantages(rollout)
        if s.normalize_advantage:
            mean = masked_mean(advantages, mask)
            std = masked_mean((advantages - mean) ** 2, mask).sqrt()
            advantages = (advantages - mean) / (std + 1e-8)
        args = (rollout.inputs, rollout.actions, rollout.histories)
        with torch.no_grad():
            old_log_prob = policy.log_prob(*args, bptt=s.bptt)

        def surrogate() -> torch.Tensor:
            ratio = torch.exp(policy.log_prob(*args, bptt=s.bptt) - old_log_prob)
            return masked_mean(ratio * advantages, mask)

        def mean_kl() -> torch.Tensor:
            return masked_mean(gaussian_kl(policy, rollout, s.bptt), mask)

        # 2. policy gradient g; 3. s ~= F^-1 g by conjugate gradient on Fisher-vector products
        objective = surrogate()
        g = flat_grad(objective, self.params)
        fvp = fisher_vector_product(self.fisher_kl(rollout), self.params, s.damping)
        direction = conjugate_gradient(fvp, g, s.cg_iters)
        curvature = float(direction @ fvp(direction))  # s^T F s
        base = float(objective.detach())
        if not curvature > 0 or not math.isfinite(curvature):
            result = LineSearchResult(False, base, 0.0, 0.0, 0)
            expected = 0.0
        else:  # 4. the step scaled to the KL bound, then the backtracking line search
            full_step = math.sqrt(2 * s.max_kl / curvature) * direction  # 1/2 s^T F s = delta
            expected = float(g @ full_step)

            @torch.no_grad()
            def evaluate() -> tuple[float, float]:
                return float(surrogate()), float(mean_kl())

            result = line_search(
                self.params,
                full_step,
                evaluate,
                base,
                s.max_kl,
                s.line_search_steps,
                s.line_search_shrink,
            )
        value_loss = self.fit_value(rollout, targets, mask)  # 5. the value function
        return TRPOStep(
            kl=result.kl,
            accepted=result.accepted,
            tries=result.tries,
            surrogate_gain=result.objective - base,
            expected_gain=expected,
            value_loss=value_loss,
        )

    def fisher_kl(self, rollout: TaskRollout) -> torch.Tensor:
        """Mean KL (with its graph) over the share ``fisher_fraction`` of the episodes."""
        n = rollout.alive.shape[0]
        keep = max(1, round(self.settings.fisher_fraction * n))
        if keep < n:
            index = torch.randperm(n, device=rollout.alive.device, generator=self.generator)[:keep]
            rollout = rollout.episodes(index)
        mask = rollout.alive.to(rollout.rewards.dtype)
        return masked_mean(gaussian_kl(self.policy, rollout, self.settings.bptt), mask)

    def fit_value(self, rollout: TaskRollout, targets: torch.Tensor, mask: torch.Tensor) -> float:
        """Regress V on the lambda-returns of the live steps, in shuffled mini-batches."""
        s = self.settings
        n, t_len = mask.shape
        keep = mask.reshape(-1).bool()
        steps = torch.arange(t_len, device=mask.device).expand(n, -1).reshape(-1)[keep]
        states = rollout.inputs.reshape(n * t_len, -1)[keep]
        targets = targets.reshape(-1)[keep]
        count = states.shape[0]
        losses = []
        for _ in range(s.value_epochs):
            order = torch.randperm(count, device=mask.device, generator=self.generator)
            for start in range(0, count, s.value_batch):
                idx = order[start : start + s.value_batch]
                loss = (self.value(states[idx], steps[idx]) - targets[idx]).pow(2).mean()
                self.value_optimizer.zero_grad()
                loss.backward()
                self.value_optimizer.step()
                losses.append(loss.item())
        return sum(losses) / max(1, len(losses))
