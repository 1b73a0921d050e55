"""Summary tables: final entropy per group and configuration, differences between algorithms,
and fine-tuning returns. Written as CSV (full precision) and Markdown (rounded).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from hmepol_cli.report.aggregates import METHOD as AGGREGATES_METHOD
from hmepol_cli.report.aggregates import improvement_interval, iqm_interval, mean_interval
from hmepol_cli.report.diagnostics import DROP_FROM, DROP_NATS, diagnosed, drop_table
from hmepol_cli.report.figures import average_bound, finetune_curves, finetune_frame
from hmepol_cli.report.runs import Group, Run, algo_label
from hmepol_cli.report.stats import curve_ci, difference_ci, final_value, mean_ci


@dataclass(frozen=True)
class ReportCounts:
    """What one report holds, counted once for both the command's last line and index.html."""

    pretraining_runs: int  # in the groups, one per seed
    finetune_runs: int
    groups: int
    skipped: int
    figures: int

    @property
    def runs_used(self) -> int:
        return self.pretraining_runs + self.finetune_runs

    def text(self) -> str:
        return (
            f"{self.runs_used} runs used ({self.groups} groups), {self.skipped} skipped, "
            f"{self.figures} figures"
        )


def _config_rows(group: Group) -> list[tuple[int | None, str]]:
    return [(None, "average")] + [(c, f"{c}: {n}") for c, n in enumerate(group.configuration_names)]


def final_entropy_table(groups: list[Group]) -> pd.DataFrame:
    """One row per group and configuration: mean final entropy over seeds and its 95% t-interval,
    then rliable's IQM and mean with bootstrap intervals over runs (the "average" row's over
    every seed x configuration score, the others' over that configuration's seeds)."""
    rows = []
    for group in groups:
        run = group.first
        for config, name in _config_rows(group):
            ci = mean_ci(list(group.finals(config).values()))
            bound = average_bound(run) if config is None else run.log_free_area[config]
            scores = group.scores(config)
            middle, mean = iqm_interval(scores), mean_interval(scores)
            rows.append(
                {
                    "env": group.env,
                    "wind": group.wind,
                    "group": group.label,
                    "config": name,
                    "n_seeds": ci.n,
                    "seeds": " ".join(map(str, group.seeds)),
                    "mean_nats": ci.mean,
                    "ci95_low": ci.low,
                    "ci95_high": ci.high,
                    "ci95_half_width": ci.half_width,
                    "iqm_nats": middle.estimate,
                    "iqm_boot95_low": middle.low,
                    "iqm_boot95_high": middle.high,
                    "mean_boot95_low": mean.low,
                    "mean_boot95_high": mean.high,
                    "log_free_area": bound,
                }
            )
    return pd.DataFrame(rows)


def difference_table(groups: list[Group]) -> pd.DataFrame:
    """Every pair of groups with the same env and wind: final entropy of the later one minus the
    earlier one (algorithm order Mepol, alpha-Mepol, HMepol), per configuration, with its 95% CI.

    Paired t-interval when both groups ran the same seeds, Welch's t-interval otherwise
    (the ``method`` column says which). ``p_improvement`` is rliable's probability that a run of
    the later group scores higher than one of the earlier, with its bootstrap interval over
    runs (the "average" row's over every configuration).
    """
    rows = []
    by_setting: dict[tuple, list[Group]] = {}
    for group in groups:
        by_setting.setdefault((group.env, repr(group.wind)), []).append(group)
    for members in by_setting.values():
        for a, b in itertools.combinations(members, 2):
            for config, name in _config_rows(a):
                d = difference_ci(a.finals(config), b.finals(config))
                p = improvement_interval(b.scores(config), a.scores(config))
                rows.append(
                    {
                        "env": a.env,
                        "wind": a.wind,
                        "config": name,
                        "comparison": f"{b.label} − {a.label}",
                        "diff_nats": d.diff,
                        "ci95_low": d.low,
                        "ci95_high": d.high,
                        "method": d.method,
                        "n_a": d.n_a,
                        "n_b": d.n_b,
                        "p_improvement": p.estimate,
                        "p_boot95_low": p.low,
                        "p_boot95_high": p.high,
                    }
                )
    return pd.DataFrame(rows)


def finetune_table(runs: list[Run]) -> pd.DataFrame:
    """Per env, wind, configuration and initialisation: final return (mean over the last 10% of
    epochs of each curve) with its CI over (seed, target) curves, and the first epoch at which
    the mean curve reaches the Mepol-initialised curve's final mean."""
    frame = finetune_frame(runs)
    if frame.empty:
        return pd.DataFrame()
    rows = []
    for (env, wind), part in frame.groupby(["env", "wind"], sort=False):
        curves = finetune_curves(part)
        mepol_final = {}
        for (init, config), (_, data) in curves.items():
            if init == "mepol":
                mepol_final[config] = curve_ci(data)[0][-1]
        for (init, config), (epochs, data) in sorted(
            curves.items(), key=lambda kv: (kv[0][1], kv[0][0])
        ):
            ci = mean_ci([final_value(c) for c in data])
            mean = curve_ci(data)[0]
            target = mepol_final.get(config, math.nan)
            reached = np.flatnonzero(mean >= target) if np.isfinite(target) else []
            rows.append(
                {
                    "env": env,
                    "wind": wind,
                    "config": config,
                    "init": "from scratch" if init == "scratch" else algo_label(init),
                    "n_curves": ci.n,
                    "final_return": ci.mean,
                    "ci95_low": ci.low,
                    "ci95_high": ci.high,
                    "first_epoch_reaching_mepol_final": epochs[reached[0]]
                    if len(reached)
                    else math.nan,
                }
            )
    return pd.DataFrame(rows)


def format_number(column: str, value, digits: int = 3) -> str | None:
    """A float as the tables show it ('n/a' for NaN); None for anything that is not a float."""
    if not isinstance(value, float | np.floating):
        return None
    if not np.isfinite(value):
        return "n/a"
    if column in ("wind", "first_epoch_reaching_mepol_final"):
        return f"{value:g}"
    return f"{value:.{digits}f}"


def to_markdown(frame: pd.DataFrame, digits: int = 3) -> str:
    """A GitHub Markdown table (numbers rounded; NaN shown as 'n/a')."""
    if frame.empty:
        return "_(none)_\n"

    def cell(column: str, value) -> str:
        number = format_number(column, value, digits)
        return number if number is not None else str(value).replace("|", "\\|")

    header = "| " + " | ".join(frame.columns) + " |"
    rule = "|" + "|".join("---" for _ in frame.columns) + "|"
    body = [
        "| " + " | ".join(cell(c, v) for c, v in zip(frame.columns, row, strict=True)) + " |"
        for row in frame.itertuples(index=False)
    ]
    return "\n".join([header, rule, *body]) + "\n"


def write_summary(
    groups: list[Group], finetune_runs: list[Run], out_dir: Path
) -> tuple[dict[str, pd.DataFrame], list[Path]]:
    """Write summary.csv, differences.csv, finetune.csv (each when not empty) and summary.md;
    return the tables and the files written."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    tables = {
        "summary": final_entropy_table(groups),
        "differences": difference_table(groups),
        "finetune": finetune_table(finetune_runs),
        "drops": drop_table(diagnosed(groups)),
    }
    files = []
    for name, table in tables.items():
        if not table.empty:
            files.append(out_dir / f"{name}.csv")
            table.to_csv(files[-1], index=False)
    text = [
        "# hmepol report: summary\n",
        "Final entropy: per seed, the mean entropy (nats) over the last 10% of epochs; then the "
        "mean over seeds with a Student-t 95% confidence interval (n/a with one seed), and "
        "rliable's aggregates (Agarwal et al., 2021): the interquartile mean (IQM) and the mean "
        f"with 95% intervals by a {AGGREGATES_METHOD}; the average row pools every seed x "
        "configuration score.\n",
        "## Final entropy per group and configuration\n",
        to_markdown(tables["summary"]),
        "## Differences between algorithms (same env and wind)\n",
        "Later minus earlier algorithm; paired t-interval when both ran the same seeds, Welch's "
        "t-interval otherwise (column `method`). `p_improvement`: the probability that a run of "
        "the later algorithm scores higher than a run of the earlier (per configuration the "
        "share of seed pairs, ties one half; the average row averages it over configurations), "
        "with its interval by the same bootstrap.\n",
        to_markdown(tables["differences"]),
    ]
    if not tables["finetune"].empty:
        text += ["## Fine-tuning returns\n", to_markdown(tables["finetune"])]
    if not tables["drops"].empty:
        text += [
            "## Drops and the KL of the updates before them (runs with diagnostics)\n",
            f"A drop: a fall of more than {DROP_NATS:g} nat in one configuration's entropy from "
            f"one epoch to the next, from epoch {DROP_FROM} on. KL ratio: the exact KL of an "
            "accepted update over its one-step KL (median over the updates just before a drop, "
            "and over the others).\n",
            to_markdown(tables["drops"]),
        ]
    files.append(out_dir / "summary.md")
    files[-1].write_text("\n".join(text))
    return tables, files
