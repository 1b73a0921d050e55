"""What one epoch of Algorithm 3.1 reads from the config, once: the settings every member of a
population shares (:class:`OffPolicySettings`), the hyperparameters each member has of its own
(:class:`MemberSettings`, :mod:`hmepol_cli.members`), and each member's objective over its
mini-batch entropies (:func:`member_objectives`: the mean, or the CVaR_alpha of eq. 3.3)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from omegaconf import DictConfig

from hmepol_cli import estimators
from hmepol_cli.config import backtracking_rule, parse_bptt
from hmepol_cli.objectives import objective
from hmepol_cli.precision import PRECISIONS, Precision, precision_of


@dataclass(frozen=True)
class OffPolicySettings:
    """What one epoch of Algorithm 3.1 needs from the config, read once. ``members`` holds what
    each member of a population may have of its own (:mod:`hmepol_cli.members`)."""

    trajectories: int  # N
    horizon: int  # T
    batch_size: int  # B, trajectories per mini-batch
    estimator: estimators.KNNEstimator  # entropy, IW entropy and KL (eqs. 2.6-2.8)
    members: tuple[MemberSettings, ...]  # per member of the population
    backtracking: str  # reference | first_step
    backtrack_tries: int
    backtrack_factor: float
    restore: str  # parameters | parameters_and_adam
    adam_reset: bool  # fresh Adam moments at the start of every epoch's loop (ours)
    exact_kl: bool  # judge steps by the KL of likelihoods over the whole history
    bptt: int | None  # steps of the recursion the likelihoods recompute (None: all)
    diagnostics: bool = False  # record every step (StepRecord), the exact KL among them
    precision: Precision = PRECISIONS["float32"]  # how the likelihoods' products are computed

    @classmethod
    def from_config(
        cls,
        cfg: DictConfig,
        history_size: int,
        member_cfgs: Sequence[DictConfig] = (),
        precision: Precision | None = None,
    ) -> OffPolicySettings:
        """The settings of ``cfg``; ``member_cfgs`` (default: [cfg]) the population's members,
        which differ only in member-scalar keys; ``precision``: the one the run resolved
        (``precision=auto`` is resolved once, by whoever builds the run; None: resolve it)."""
        a = cfg.algo
        return cls(
            trajectories=int(a.trajectories),
            horizon=int(a.horizon),
            batch_size=int(a.batch_size),
            estimator=estimators.make_estimator(cfg.estimator),
            members=tuple(MemberSettings.from_config(c) for c in (member_cfgs or [cfg])),
            backtracking=backtracking_rule(a),  # an older run keeps its own rule
            backtrack_tries=int(a.lr_backtrack_tries),
            backtrack_factor=float(a.lr_backtrack_factor),
            restore=str(a.get("backtrack_restore", "parameters_and_adam")),
            adam_reset=a.get("adam_reset") == "epoch",
            exact_kl=a.trust_region == "exact" and history_size > 0,
            bptt=parse_bptt(cfg.policy.bptt),
            diagnostics=bool(cfg.get("diagnostics", False)),
            precision=precision_of(cfg) if precision is None else precision,
        )


@dataclass(frozen=True)
class MemberSettings:
    """The hyperparameters one member of a population has of its own."""

    lr: float
    kl_threshold: float  # delta
    max_off_iters: int
    objective: str = "mean"  # mean | cvar
    alpha: float = 1.0  # CVaR level (eq. 3.3)

    @classmethod
    def from_config(cls, cfg: DictConfig) -> MemberSettings:
        a = cfg.algo
        return cls(
            lr=float(a.lr),
            kl_threshold=float(a.kl_threshold),
            max_off_iters=int(a.max_off_iters),
            objective=str(a.objective),
            alpha=float(a.alpha),
        )


def member_objectives(
    entropies: torch.Tensor, members: Sequence[int], settings: OffPolicySettings
) -> torch.Tensor:
    """Each row's objective over its mini-batch entropies, with its member's own objective and
    alpha. entropies (R, M), members (R,) population indices -> (R,)"""
    rows = []
    for i, m in enumerate(members):
        hyper = settings.members[m]
        rows.append(objective(entropies[i : i + 1], hyper.objective, hyper.alpha)[0])
    return torch.stack(rows)
