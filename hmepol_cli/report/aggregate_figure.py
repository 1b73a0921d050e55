"""The aggregates figure: IQM and mean with their intervals, and the performance profile."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hmepol_cli.plots import new_figure, save
from hmepol_cli.report.aggregates import iqm_interval, mean_interval, performance_profile
from hmepol_cli.report.runs import Group

PROFILE_POINTS = 60


def _interval_panel(ax, groups: list[Group], styles: dict, statistic, name: str):
    for row, group in enumerate(groups):
        value = statistic(group.scores())
        colour = styles[group.label].colour
        if np.isfinite(value.low):
            ax.plot([value.low, value.high], [row, row], color=colour, lw=6, alpha=0.45)
        ax.plot([value.estimate], [row], "|", color=colour, ms=16, mew=2.5)
    ax.set_yticks(range(len(groups)), [styles[g.label].label for g in groups], fontsize=8)
    ax.set_ylim(len(groups) - 0.5, -0.5)
    ax.set_title(name, fontsize=10)
    ax.set_xlabel("final entropy (nats)")
    ax.grid(axis="x", alpha=0.3)


def draw_aggregates(groups: list[Group], styles: dict, title: str, path: Path) -> Path:
    """Left: IQM and mean per group; right: the performance profiles, on one entropy axis
    (``styles``: each group's colour and name, :func:`~hmepol_cli.report.series.series_styles`)."""
    scores = np.concatenate([g.scores().ravel() for g in groups])
    lo, hi = float(scores.min()), float(scores.max())
    pad = 0.05 * (hi - lo) or 0.1
    taus = np.linspace(lo - pad, hi + pad, PROFILE_POINTS)
    fig = new_figure(11.0, 1.2 + 0.45 * len(groups) + 1.6)
    left, middle, right = fig.subplots(1, 3, width_ratios=[1, 1, 1.6])
    _interval_panel(left, groups, styles, iqm_interval, "IQM")
    _interval_panel(middle, groups, styles, mean_interval, "Mean")
    middle.set_yticklabels([])
    for group in groups:
        share, low, high = performance_profile(group.scores(), taus)
        colour = styles[group.label].colour
        right.plot(
            taus,
            share,
            color=colour,
            lw=1.6,
            label=f"{styles[group.label].label} (n={len(group.runs)})",
        )
        if np.isfinite(low).all():
            right.fill_between(taus, low, high, color=colour, alpha=0.2, lw=0)
    right.set_xlabel("final entropy tau (nats)")
    right.set_ylabel("share of scores > tau")
    right.set_ylim(-0.02, 1.02)
    right.set_title("Performance profile", fontsize=10)
    right.grid(alpha=0.3)
    right.legend(fontsize=7, loc="lower left")
    for ax in (left, middle):
        ax.set_xlim(lo - pad, hi + pad)
    fig.suptitle(f"{title}: aggregates over seeds and configurations", fontsize=11)
    return save(fig, path)
