"""The surrogate of Algorithm 3.1's off-policy loop: the objective and the KL of target
parameters theta' on one epoch's fixed particles, sampled under theta (eqs. 2.7, 2.8, 3.3).

The importance weight of particle t is the product of the policy ratios up to t, normalised over
its mini-batch (:func:`hmepol_cli.estimators.importance_weights`); the likelihoods of the
sampling policy are computed exactly as theta' computes its own, so that at theta' = theta the
log-ratios, and both KLs, are exactly 0. Rows of a rollout are members of a population.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from hmepol_cli import estimators
from hmepol_cli.population import PolicyPopulation
from hmepol_cli.rollout import Rollout
from hmepol_cli.settings import OffPolicySettings, member_objectives


@dataclass
class Estimate:
    """The surrogate at some parameters theta', for R rows of a rollout."""

    entropies: torch.Tensor  # (R, M) IW entropies of the mini-batches (eq. 2.7)
    kl: torch.Tensor  # (R,) the KL the trust region judges by
    objective: torch.Tensor  # (R,) mean or CVaR of the entropies (differentiable)
    likelihoods: torch.Tensor  # (R, N, T) log pi_theta'(a_t | h_t) the gradient uses, detached
    kl_one_step: torch.Tensor  # (R,) eq. 2.8 from those likelihoods
    kl_exact: torch.Tensor | None = None  # (R,) eq. 2.8 from likelihoods over the whole history


class Surrogate:
    """The objective and the KL of target parameters theta' on one epoch's fixed particles,
    sampled under theta (eqs. 2.7, 2.8, 3.3), for the members of a rollout.

    Rows of the rollout are members ``members[i]``; calls take rows."""

    def __init__(
        self,
        population: PolicyPopulation,
        rollout: Rollout,
        neighbours: estimators.Neighbours,
        members: torch.Tensor,
        settings: OffPolicySettings,
    ) -> None:
        self.population, self.rollout, self.neighbours = population, rollout, neighbours
        self.members, self.settings = members, settings
        self.batches = neighbours.radius.shape[0] // len(members)  # M per member
        self.row_of = {int(m): i for i, m in enumerate(members.tolist())}
        self.behaviour: torch.Tensor | None = None  # log pi_theta(a_t | h_t), as theta' computes it
        self.behaviour_exact: torch.Tensor | None = None  # the same over the whole history
        # A lowered precision is checked once an epoch against the same estimate in full.
        self.behaviour_full: torch.Tensor | None = None
        self.behaviour_exact_full: torch.Tensor | None = None
        recursive = population.history_size > 0
        self.with_exact = recursive and (settings.exact_kl or settings.diagnostics)

    def rows(self, members: Sequence[int]) -> torch.Tensor:
        return torch.tensor([self.row_of[int(m)] for m in members], device=self.members.device)

    def __call__(self, rows: torch.Tensor) -> Estimate:
        """The estimate at the current parameters for rollout rows ``rows`` (R,).

        The first call (theta' = theta) also fixes the behaviour likelihoods: the sampling
        policy's, computed exactly as theta' computes its own, so the log-ratios start at 0."""
        s, r = self.settings, self.rollout
        inputs, actions = r.inputs.index_select(0, rows), r.actions.index_select(0, rows)
        histories = r.histories.index_select(0, rows)
        who = self.members.index_select(0, rows)
        alive = None if r.alive is None else r.alive.index_select(0, rows)
        with s.precision.products(inputs.device, s.bptt):
            target = self.population.log_prob(who, inputs, actions, histories, s.bptt)
        if self.behaviour is None:
            self.behaviour = target.detach()
            if s.precision.autocast is not None:  # the full-precision check's baselines
                with torch.no_grad():
                    log_prob = self.population.log_prob
                    self.behaviour_full = log_prob(who, inputs, actions, histories, s.bptt)
                    if s.exact_kl and self.with_exact:
                        self.behaviour_exact_full = log_prob(who, inputs, actions, histories, None)
        behaviour = self.behaviour.index_select(0, rows)
        nb = _select_batches(self.neighbours, rows, self.batches)
        weights = estimators.importance_weights(
            _live(target - behaviour, alive).flatten(0, 1), s.batch_size, nb.live
        )
        entropies = s.estimator.iw_entropy(weights, nb).view(len(rows), -1)  # eq. 2.7
        one_step = s.estimator.kl(weights, nb).view(len(rows), -1).mean(-1)  # eq. 2.8
        exact = self._exact_kl(who, inputs, actions, histories, alive, rows, nb)
        return Estimate(
            entropies=entropies,
            kl=exact if s.exact_kl and exact is not None else one_step,
            objective=member_objectives(entropies, who.tolist(), s),
            likelihoods=target.detach(),
            kl_one_step=one_step,
            kl_exact=exact,
        )

    @torch.no_grad()
    def full_precision(self) -> tuple[torch.Tensor, torch.Tensor] | None:
        """With a lowered precision: the KL the trust region judges by and the mean IW
        entropy at the current parameters, computed in full precision, for every row (the
        check of the lowered one). -> (KL (R,), IW entropy (R,)), or None in full precision."""
        if self.behaviour_full is None:
            return None
        s, r, who = self.settings, self.rollout, self.members
        rows = torch.arange(len(who), device=who.device)
        nb = _select_batches(self.neighbours, rows, self.batches)

        def weights(bptt: int | None, behaviour: torch.Tensor) -> torch.Tensor:
            target = self.population.log_prob(who, r.inputs, r.actions, r.histories, bptt)
            log_ratios = _live(target - behaviour, r.alive).flatten(0, 1)
            return estimators.importance_weights(log_ratios, s.batch_size, nb.live)

        objective_weights = weights(s.bptt, self.behaviour_full)
        entropy = s.estimator.iw_entropy(objective_weights, nb).view(len(rows), -1).mean(-1)
        if s.exact_kl and self.behaviour_exact_full is not None:
            objective_weights = weights(None, self.behaviour_exact_full)
        kl = s.estimator.kl(objective_weights, nb).view(len(rows), -1).mean(-1)
        return kl, entropy

    @torch.no_grad()
    def _exact_kl(self, who, inputs, actions, histories, alive, rows, nb) -> torch.Tensor | None:
        """What the one-step likelihoods do not see: the KL of the same step computed from
        likelihoods over the whole history, against the exact sampling likelihoods."""
        if not self.with_exact:
            return None
        s = self.settings
        with s.precision.products(inputs.device, None):
            exact = self.population.log_prob(who, inputs, actions, histories, None)
        if self.behaviour_exact is None:  # theta' = theta: the sampling likelihoods, so computed
            self.behaviour_exact = exact
        sampling = self.behaviour_exact.index_select(0, rows)
        weights = estimators.importance_weights(
            _live(exact - sampling, alive).flatten(0, 1), s.batch_size, nb.live
        )
        return s.estimator.kl(weights, nb).view(len(rows), -1).mean(-1)


def _live(log_ratios: torch.Tensor, alive: torch.Tensor | None) -> torch.Tensor:
    """Log-ratios of the actions that moved the state: an action drawn after the environment
    ended its episode (Gymnasium worlds) changes no particle, so it counts in no weight.
    (S', N, T), alive (S', N, T) bool or None (every step counts)."""
    if alive is None:
        return log_ratios
    return torch.where(alive, log_ratios, torch.zeros_like(log_ratios))


def _select_batches(
    neighbours: estimators.Neighbours, rows: torch.Tensor, m_batches: int
) -> estimators.Neighbours:
    """The mini-batches of rollout rows ``rows`` (R,), in that order: neighbours of (S' M)
    mini-batches -> (R M). Always gathered: rows may be every row in another order."""

    def select(values: torch.Tensor) -> torch.Tensor:
        return values.view(-1, m_batches, *values.shape[1:]).index_select(0, rows).flatten(0, 1)

    live = neighbours.live
    return estimators.Neighbours(
        indices=select(neighbours.indices),
        radius=select(neighbours.radius),
        dim=neighbours.dim,
        live=None if live is None else select(live),
    )
