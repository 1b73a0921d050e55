"""What runs made with ``diagnostics=true`` tell about a collapse (the collapse study): single-epoch
entropy drops, and the exact KL of each accepted update against the one-step KL the trust
region judged.

A *drop* is a fall of more than ``DROP_NATS`` in one configuration's entropy from one epoch to
the next (epoch e against epoch e - 1, in that configuration; none where either epoch lacks it),
counted from epoch ``DROP_FROM`` on (the first epochs of every run climb steeply and noisily).
A run's drops are counted per configuration and pooled over configurations (the epochs with a
drop in any), and a group's pooled over its seeds, with the share of runs that had one.

Row e of epochs.csv describes the rollout of the policy the update of epoch e - 1 made,
so the update *before* a drop at row e is epoch e - 1's. Its KL ratio is kl_exact / kl_one_step
of the last accepted off-policy step of that epoch (steps.csv): how much more the policy changed
over whole histories than the surrogate's stored histories showed (1 for a Markovian policy,
whose two KLs are one; NaN without steps.csv).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd

from hmepol_cli.report.runs import Group, Run
from hmepol_cli.report.stats import proportion_ci
from hmepol_cli.run import STEPS_CSV

DROP_NATS = 1.0
DROP_FROM = 30


def has_steps(run: Run) -> bool:
    return any((run.path / name).is_file() for name in (STEPS_CSV, f"{STEPS_CSV}.gz"))


def accepted_kl(run: Run) -> pd.DataFrame:
    """Per epoch, the last accepted step's kl_one_step and kl_exact (index: epoch)."""
    name = next(n for n in (STEPS_CSV, f"{STEPS_CSV}.gz") if (run.path / n).is_file())
    steps = pd.read_csv(run.path / name)
    accepted = steps[steps["accepted"].astype(str) == "True"]
    last = accepted.groupby("epoch").tail(1).set_index("epoch")
    return last[["kl_one_step", "kl_exact"]].astype(float)


def kl_ratio(run: Run) -> pd.Series:
    """kl_exact / kl_one_step of each epoch's accepted update; 1 where the policy is Markovian."""
    kl = accepted_kl(run)
    ratio = kl["kl_exact"] / kl["kl_one_step"]
    if kl["kl_exact"].isna().all():  # a Markovian policy: the one-step KL is the exact one
        ratio = pd.Series(1.0, index=kl.index)
    return ratio.where(kl["kl_one_step"] > 0)


def config_changes(run: Run) -> pd.DataFrame:
    """Per epoch from DROP_FROM on (index) and configuration c (column c): the change of its
    entropy since the epoch before (nats, negative = a fall; NaN where either lacks it)."""
    epochs = run.epochs.set_index("epoch")
    columns = [f"entropy_c{c}" for c in range(run.n_configurations)]
    change = epochs[columns].astype(float).diff()
    change.columns = range(run.n_configurations)
    return change[change.index >= DROP_FROM]


def entropy_changes(run: Run) -> pd.DataFrame:
    """Per epoch from DROP_FROM on: the largest fall of any configuration's entropy since the
    epoch before (``change``, nats, negative = a fall) and the configuration it fell in."""
    change = config_changes(run)
    worst = change.min(axis=1)
    # An epoch may have no change at all (multigrid samples some configurations an epoch):
    # idxmin refuses an all-NaN row, so it looks only at the rows that have one.
    config = pd.Series(pd.NA, index=change.index, dtype="string")
    some = worst.notna()
    config[some] = change[some].idxmin(axis=1).astype(str)
    return pd.DataFrame({"change": worst, "config": config})


def diagnosed(groups: list[Group]) -> list[Group]:
    """The groups compared with a group run with diagnostics (a steps.csv): every group of an
    (env, wind) in which one is, so that runs without it (a Markovian baseline) show beside it."""
    settings = {(g.env, repr(g.wind)) for g in groups if any(has_steps(r) for r in g.runs)}
    return [g for g in groups if (g.env, repr(g.wind)) in settings]


def drop_table(groups: list[Group]) -> pd.DataFrame:
    """One row per run: its drops (``drops``: epochs with a drop in any configuration;
    ``drops_c<c>``: configuration c's), their epochs, and the median KL ratio of the updates just
    before a drop against that of every other update from DROP_FROM on."""
    rows = []
    for group in groups:
        for run in sorted(group.runs, key=lambda r: r.seed):
            changes = entropy_changes(run)
            dropped = changes.index[changes["change"] < -DROP_NATS]
            per_config = (config_changes(run) < -DROP_NATS).sum()
            ratio = kl_ratio(run) if has_steps(run) else pd.Series(dtype=float)
            before = ratio.reindex(dropped - 1)
            others = ratio.reindex(changes.index.difference(dropped) - 1)
            rows.append(
                {
                    "env": group.env,
                    "wind": group.wind,
                    "group": group.label,
                    "seed": run.seed,
                    "epochs": len(run.epochs),
                    "drops": len(dropped),
                    **{f"drops_c{c}": int(n) for c, n in per_config.items()},
                    "drop_epochs": " ".join(map(str, dropped)),
                    "largest_fall": float(-changes["change"].min()),
                    "kl_ratio_before_drops": _median(before),
                    "kl_ratio_other_updates": _median(others),
                    "final_entropy": run.final_entropy(),
                }
            )
    return pd.DataFrame(rows)


def pooled_drops(table: pd.DataFrame) -> pd.DataFrame:
    """Per group, :func:`drop_table`'s counts summed over its runs, their mean per run, and the
    share of runs with a drop with Wilson's 95% interval (the run is the unit)."""
    if table.empty:
        return pd.DataFrame()
    counts = [c for c in table.columns if c == "drops" or c.startswith("drops_c")]
    rows = []
    for (env, wind, group), runs in table.groupby(["env", "wind", "group"], sort=False):
        hit = proportion_ci(int((runs["drops"] > 0).sum()), len(runs))
        rows.append(
            {
                "env": env,
                "wind": wind,
                "group": group,
                "runs": len(runs),
                "runs_with_drops": hit.successes,
                "share_with_drops": hit.share,
                "share_wilson95_low": hit.low,
                "share_wilson95_high": hit.high,
                **{c: int(runs[c].sum()) for c in counts},
                "drops_per_run": float(runs["drops"].mean()),
            }
        )
    return pd.DataFrame(rows)


def _median(values: pd.Series) -> float:
    values = values.dropna()
    return float(values.median()) if len(values) else math.nan


MARKERS = ("o", "^", "s", "D", "v", "P")


def draw_diagnostics(groups: list[Group], styles: dict, title: str, path: Path) -> Path:
    """Four panels: the KL ratio over epochs, drops per seed, the fall of entropy against the
    ratio of the update before it, and the share of actions at the clip."""
    from hmepol_cli.plots import new_figure, save

    table = drop_table(groups)
    fig = new_figure(12.0, 8.0)
    (ratio_ax, drops_ax), (scatter_ax, clip_ax) = fig.subplots(2, 2)
    for g, group in enumerate(groups):
        style = styles[group.label]
        colour, dashes = style.colour, style.linestyle
        marker = MARKERS[g % len(MARKERS)]
        runs = [r for r in group.runs if has_steps(r)]
        ratios = pd.concat([kl_ratio(r).rename(r.seed) for r in runs], axis=1) if runs else None
        if ratios is not None and not ratios.isna().all().all():
            for seed in ratios:
                ratio_ax.plot(ratios.index, ratios[seed], color=colour, lw=0.5, alpha=0.35)
            median = ratios.median(axis=1)
            ratio_ax.plot(
                median.index, median, color=colour, ls=dashes, lw=1.8,
                label=f"{style.label} (median of n={ratios.shape[1]})",
            )  # fmt: skip
        counts = table[table["group"] == group.label]["drops"].to_numpy()
        jitter = np.linspace(-0.15, 0.15, len(counts)) if len(counts) > 1 else np.zeros(1)
        # Groups down the y-axis, so that their names can be read at the legends' size.
        drops_ax.scatter(counts, g + jitter, color=colour, marker=marker, s=30, zorder=3)
        drops_ax.plot([counts.mean()] * 2, [g - 0.25, g + 0.25], color=colour, ls=dashes, lw=2)
        for run in runs:
            changes = entropy_changes(run)
            before = kl_ratio(run).reindex(changes.index - 1).to_numpy()
            scatter_ax.scatter(
                before, changes["change"], color=colour, marker=marker, s=8, alpha=0.5, lw=0,
                label=style.label if run is runs[0] else None,
            )  # fmt: skip
        epochs, clip = _curves(group, "clip_share")
        if np.isfinite(clip).any():
            mean = np.nanmean(np.where(np.isfinite(clip), clip, np.nan), axis=0)
            clip_ax.plot(epochs, mean, color=colour, ls=dashes, lw=1.5, label=style.label)
    ratio_ax.set_yscale("log")
    ratio_ax.axhline(1.0, color="0.3", lw=0.8, ls="--")
    ratio_ax.set_xlabel("epoch")
    ratio_ax.set_ylabel("exact KL / one-step KL (accepted update)")
    ratio_ax.set_title("Exact against one-step KL (thin: each seed; thick: median)", fontsize=10)
    names = [styles[g.label].label.replace(" (", "\n(") for g in groups]
    drops_ax.set_yticks(range(len(groups)), names, fontsize=8)
    drops_ax.set_ylim(len(groups) - 0.5, -0.5)
    drops_ax.set_xlabel(f"drops > {DROP_NATS:g} nat from epoch {DROP_FROM}")
    drops_ax.set_title("Single-epoch drops per seed (dots; bar: mean)", fontsize=10)
    if any(len(c.get_offsets()) for c in scatter_ax.collections):  # runs of under DROP_FROM
        scatter_ax.set_xscale("log")
    scatter_ax.axhline(-DROP_NATS, color="0.3", lw=0.8, ls="--")
    scatter_ax.set_xlabel("KL ratio of the update before")
    scatter_ax.set_ylabel("lowest change of a configuration's entropy\n(nats; negative: a fall)")
    scatter_ax.set_title("Entropy change against the update before it", fontsize=10)
    clip_ax.set_xlabel("epoch")
    clip_ax.set_ylabel("share of action components past the clip")
    clip_ax.set_title("Saturation (mean over seeds)", fontsize=10)
    for ax in (ratio_ax, drops_ax, scatter_ax, clip_ax):
        ax.grid(alpha=0.3)
    for ax in (ratio_ax, scatter_ax, clip_ax):
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    fig.suptitle(f"{title}: diagnostics of the updates", fontsize=11)
    return save(fig, path)


def _curves(group: Group, column: str) -> tuple[np.ndarray, np.ndarray]:
    """A column of every seed's epochs.csv aligned on epoch (NaN for runs made without it)."""
    table = pd.concat(
        [
            r.epochs.set_index("epoch")
            .get(column, pd.Series(dtype=float))
            .astype(float)
            .rename(r.seed)
            for r in group.runs
        ],
        axis=1,
    ).sort_index()
    return table.index.to_numpy(float), table.to_numpy(float).T
