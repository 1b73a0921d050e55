"""An epoch's statistics as the rows its run directory's tables get: one row of epochs.csv,
the mini-batches' rows of batches.csv and, with diagnostics, the off-policy steps' rows of
steps.csv (README, What a run writes, says when each column is measured)."""

from __future__ import annotations

import dataclasses
import math
import time

import pandas as pd

from hmepol_cli.mepol import EpochStats


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
