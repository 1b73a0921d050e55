"""What an epoch of Algorithm 3.1 records (:class:`EpochStats`, its :class:`UpdateResult` and,
with diagnostics, a :class:`StepRecord` per off-policy step tried), and those records as the rows
its run directory's tables get: one row of epochs.csv, the mini-batches' rows of batches.csv and
the off-policy steps' rows of steps.csv (docs/run-directory.md says when each column is
measured)."""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np
import pandas as pd


@dataclass
class StepRecord:
    """One off-policy step tried (``OffPolicySettings.diagnostics``): steps.csv's row."""

    step: int  # 0, 1, ... in the order tried
    lr: float
    accepted: bool
    kl: float  # the KL the trust region judged the step by
    kl_one_step: float  # eq. 2.8 from the likelihoods the gradient uses (policy.bptt)
    kl_exact: float  # eq. 2.8 from likelihoods over the whole history (NaN: Markovian)
    iw_entropy: float  # the surrogate: mean IW entropy of the mini-batches (eq. 2.7)
    objective: float


@dataclass
class UpdateResult:
    """One member's off-policy loop in one epoch."""

    entropies: np.ndarray  # (M,) IW entropies of the accepted policy
    kl: float  # KL of the accepted policy (the one the trust region judged by)
    off_iters: int  # accepted steps
    backtracks: int  # learning-rate reductions
    lr: float  # the learning rate of the last step tried
    kl_exact: float = math.nan  # the exact KL of the accepted policy (diagnostics)
    # A lowered precision (bf16): the accepted policy's KL and mean IW entropy in full precision
    kl_full_precision: float = math.nan
    entropy_iw_full_precision: float = math.nan
    steps: list[StepRecord] = field(default_factory=list)  # every step tried (diagnostics)
    # What was not finite where no step could mend it (at the sampling policy, or at every
    # step tried): the member stops (EpochStats.broken)
    non_finite: list[str] = field(default_factory=list)


@dataclass
class EpochStats:
    """One member's epoch."""

    entropies: np.ndarray  # (M,) on-policy kNN entropy of each mini-batch (eq. 2.6)
    batch_configurations: np.ndarray  # (M,) configuration of each mini-batch
    objective: float
    update: UpdateResult
    history_max: float = 0.0  # largest |h'_t| of the rollout: a diverging recursion shows here
    action_max: float = 0.0  # largest |a_t| drawn (before clipping): diverging means show here
    floor_share: float = 0.0  # share of particles whose ball volume hit the estimator's floor
    log_std: float = 0.0  # the sampling policy's log-std, averaged over action dimensions
    clip_share: float = 0.0  # share of action components past the action bounds
    seconds: dict[str, float] = field(default_factory=dict)
    broken: list[str] = field(default_factory=list)  # non-finite in the rollout: the member stops


def epoch_rows(
    epoch: int, stats: EpochStats, diverged: bool, n_configurations: int
) -> tuple[dict, pd.DataFrame, pd.DataFrame | None]:
    """One member's epoch as its epochs.csv row, batches.csv rows and steps.csv rows."""
    u = stats.update
    row = {"epoch": epoch, "entropy": float(stats.entropies.mean()), "objective": stats.objective}
    for c in range(n_configurations):
        drawn = stats.batch_configurations == c
        row[f"entropy_c{c}"] = float(stats.entropies[drawn].mean()) if drawn.any() else math.nan
    row.update(
        entropy_iw=float(u.entropies.mean()),
        kl=u.kl,
        kl_exact=u.kl_exact,
        kl_full_precision=u.kl_full_precision,
        entropy_iw_full_precision=u.entropy_iw_full_precision,
        off_iters=u.off_iters,
        backtracks=u.backtracks,
        lr=u.lr,
        history_max=stats.history_max,
        action_max=stats.action_max,
        log_std=stats.log_std,
        clip_share=stats.clip_share,
        diverged=diverged,
        floor_share=stats.floor_share,
        seconds=stats.seconds["epoch"],
        collect_seconds=stats.seconds["collect"],
        neighbours_seconds=stats.seconds["neighbours"],
        update_seconds=stats.seconds["update"],
        wall_time=time.time(),
    )
    batches = pd.DataFrame(
        {
            "epoch": epoch,
            "batch": range(len(stats.entropies)),
            "config": stats.batch_configurations,
            "entropy": stats.entropies,
        }
    )
    steps = None
    if u.steps:
        steps = pd.DataFrame([{"epoch": epoch, **dataclasses.asdict(r)} for r in u.steps])
    return row, batches, steps
