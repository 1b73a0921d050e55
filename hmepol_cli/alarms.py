"""A member's alarms: when an epoch's numbers stop the run, and when they only warn.

A value that is not finite (a position, an action, the history, an entropy, the KL, the log-std
or a weight) stops the member at that epoch: :meth:`MemberAlarms.failure` says why, and the
trainer records the member as failed while the others go on. Three things warn, in the log and
on the progress bar, and the run goes on (the bounds are ``alarms.*``,
:class:`hmepol_cli.config.AlarmConfig`):

- divergence: the largest |h'_t| past ``history_bound`` or the largest |a_t| past
  ``action_bound`` (the epoch's row says ``diverged``);
- precision drift: with a lowered precision (bf16), the accepted step's KL differs from the one
  recomputed in full precision by more than the share ``precision_drift``;
- a stall: no off-policy step accepted for ``stall_epochs`` epochs in a row.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from hmepol_cli.records import EpochStats

log = logging.getLogger("hmepol")


def precision_drift(stats: EpochStats) -> float:
    """Relative difference of the accepted step's KL in the lowered and in full precision
    (0 in full precision, or when both are ~0)."""
    u = stats.update
    if not math.isfinite(u.kl_full_precision) or u.kl_full_precision < 1e-12:
        return 0.0
    return abs(u.kl - u.kl_full_precision) / u.kl_full_precision


class MemberAlarms:
    """The alarm monitor of one member's run: its bounds, and the epochs it has stalled."""

    def __init__(
        self, bounds: DictConfig, run_dir: Path, seed: int, lr_backtrack_tries: int
    ) -> None:
        """``bounds``: the ``alarms`` entry of the config (AlarmConfig); ``lr_backtrack_tries``
        is named in the stall's warning."""
        self.bounds, self.run_dir, self.seed = bounds, Path(run_dir), seed
        self.lr_backtrack_tries = lr_backtrack_tries
        self.stalled_for = 0  # consecutive epochs in which no off-policy step was accepted

    # ------------------------------------------------------------------ what stops the run
    def failure(self, epoch: int, stats: EpochStats, params: dict[str, torch.Tensor]) -> str | None:
        """Why the member stops at ``epoch`` (None: it goes on): the quantities that are not
        finite, those of the rollout (``stats.broken``) first. ``params``: the member's own
        parameters, each without the population's member dimension."""
        broken = stats.broken or self.non_finite(stats, params)
        if not broken:
            return None
        return f"non-finite {', '.join(broken)} at epoch {epoch}: the run stopped there"

    def non_finite(self, stats: EpochStats, params: dict[str, torch.Tensor]) -> list[str]:
        """The quantities of the member's epoch that are not finite, by name."""
        checks = {
            "entropy": bool(np.isfinite(stats.entropies).all()),
            "KL": math.isfinite(stats.update.kl),
            "history": math.isfinite(stats.history_max),
            "actions": math.isfinite(stats.action_max),
            "log-std": bool(torch.isfinite(params["log_std"]).all()),
            "policy weights": all(bool(torch.isfinite(v).all()) for v in params.values()),
        }
        return [name for name, ok in checks.items() if not ok]

    # ------------------------------------------------------------------ what only warns
    def diverged(self, stats: EpochStats) -> bool:
        """The history or the actions past their bounds (the epoch's ``diverged``)."""
        return (
            stats.history_max > self.bounds.history_bound
            or stats.action_max > self.bounds.action_bound
        )

    def warn(self, epoch: int, stats: EpochStats) -> str | None:
        """Log the warnings of an epoch the member has recorded, and count its stall.
        -> a note for the progress bar (None: nothing to note)"""
        bounds = self.bounds
        diverged = self.diverged(stats)
        if diverged:
            log.warning(
                "%s: epoch %d: the policy is diverging: max |h'| = %.3g (alarms.history_bound = "
                "%g), max |a| = %.3g (alarms.action_bound = %g)",
                self.run_dir,
                epoch,
                stats.history_max,
                bounds.history_bound,
                stats.action_max,
                bounds.action_bound,
            )
        drift = precision_drift(stats)
        if drift > bounds.precision_drift:
            log.warning(
                "%s: epoch %d: the lowered precision's KL is %.1f%% off the full-precision one "
                "(alarms.precision_drift = %g): use precision=float32 from here",
                self.run_dir,
                epoch,
                100 * drift,
                bounds.precision_drift,
            )
        self.stalled_for = self.stalled_for + 1 if stats.update.off_iters == 0 else 0
        if self.stalled_for >= bounds.stall_epochs:
            log.warning(
                "%s: no off-policy step accepted for %d epochs (to epoch %d): the trust region "
                "rejects every step even after %d learning-rate reductions",
                self.run_dir,
                self.stalled_for,
                epoch,
                self.lr_backtrack_tries,
            )
            return f"seed {self.seed} stalled"
        return "diverging" if diverged else None

    def failed_note(self) -> str:
        """The progress bar's note for a member that stopped."""
        return f"seed {self.seed} failed"
