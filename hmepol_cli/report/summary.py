"""Summary tables: final entropy per group and configuration, differences between algorithms,
and fine-tuning returns. Written as CSV (full precision) and Markdown (rounded).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from hmepol_cli.algorithms import SCRATCH
from hmepol_cli.report.aggregates import METHOD as AGGREGATES_METHOD
from hmepol_cli.report.aggregates import improvement_interval, iqm_interval, mean_interval
from hmepol_cli.report.comparisons import paired
from hmepol_cli.report.diagnostics import (
    DROP_FROM,
    DROP_NATS,
    diagnosed,
    drop_table,
    pooled_drops,
)
from hmepol_cli.report.frames import (
    config_bound,
    finetune_curves,
    finetune_frame,
    ordered_inits,
    return_range,
)
from hmepol_cli.report.resolution import (
    DETECTABLE_COLUMN,
    PLANNED_DIFFERENCE,
    PLANNED_HALF_WIDTHS,
    PLANNED_POWER,
    SEEDS_COLUMN,
    few_units_note,
    format_seeds,
    planning_columns,
    resolution_line,
)
from hmepol_cli.report.runs import Group, Run, algo_label
from hmepol_cli.report.stats import (
    curve_ci,
    difference_ci,
    final_value,
    mean_ci,
    nested_mean_ci,
)


@dataclass(frozen=True)
class ReportCounts:
    """What one report holds, counted once for both the command's last line and index.html."""

    pretraining_runs: int  # in the groups, one per seed
    finetune_runs: int
    groups: int
    skipped: int
    figures: int
    merged: int = 0  # directories holding a run found elsewhere too, counted once
    # Unfinished runs included: the env and wind settings cut, each at its epoch.
    cuts: dict[str, int] = field(default_factory=dict)

    @property
    def runs_used(self) -> int:
        return self.pretraining_runs + self.finetune_runs

    def text(self) -> str:
        merged = (
            f", {self.merged} identical {'copy' if self.merged == 1 else 'copies'} merged"
            if self.merged
            else ""
        )
        cut = ""
        if len(self.cuts) == 1:
            ((where, epoch),) = self.cuts.items()
            cut = f", unfinished runs included: {where} cut at epoch {epoch}"
        elif self.cuts:
            each = "; ".join(f"{where} at epoch {epoch}" for where, epoch in self.cuts.items())
            cut = (
                ", unfinished runs included, each setting's runs cut at the last epoch all of "
                f"them wrote: {each}"
            )
        return (
            f"{self.runs_used} runs used ({self.groups} groups), {self.skipped} skipped{merged}, "
            f"{self.figures} figures{cut}"
        )


def _config_rows(group: Group) -> list[tuple[int | None, str]]:
    return [(None, "average")] + [(c, f"{c}: {n}") for c, n in enumerate(group.configuration_names)]


def _average_scores(group: Group) -> np.ndarray:
    """(n_seeds, 1): each seed's final average entropy, in seed order (finite ones)."""
    finals = group.finals(None)
    values = np.array([finals[s] for s in group.seeds], dtype=float)
    return values[np.isfinite(values)].reshape(-1, 1)


def final_entropy_table(groups: list[Group]) -> pd.DataFrame:
    """One row per group and configuration: mean final entropy over seeds and its 95% t-interval,
    then rliable's IQM and mean with bootstrap intervals over runs. Every number of a row
    estimates the same quantity: the "average" row's are over each seed's average entropy (its
    configurations weighted by their probabilities, as the objective and ``mean_nats``), not over
    the configurations pooled with equal weights, which made a mean that could lie outside its
    own interval where the probabilities differ (slope: 0.8, 0.2)."""
    rows = []
    for group in groups:
        run = group.first
        for config, name in _config_rows(group):
            ci = mean_ci(list(group.finals(config).values()))
            bound = config_bound(run, config)
            scores = group.scores(config) if config is not None else _average_scores(group)
            middle, mean = iqm_interval(scores), mean_interval(scores)
            rows.append(
                {
                    "env": group.env,
                    "wind": group.wind,
                    "group": group.label,
                    "config": name,
                    "n_seeds": ci.n,
                    "seeds": " ".join(map(str, group.seeds)),
                    "final_epochs": group.final_epochs(config),
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
    runs (the "average" row's over every configuration). Then the seeds per arm the planned
    precisions need and the difference these seeds find with 80% power (resolution.py).
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
                        "final_epochs_a": a.final_epochs(config),
                        "final_epochs_b": b.final_epochs(config),
                        "p_improvement": p.estimate,
                        "p_boot95_low": p.low,
                        "p_boot95_high": p.high,
                        **planning_columns(d),
                    }
                )
    return pd.DataFrame(rows)


def finetune_table(runs: list[Run]) -> pd.DataFrame:
    """Per env, wind, configuration and initialisation: final return (per curve the mean over
    the last 10% of epochs) with its 95% CI over the independent units, and the first epoch at
    which the mean curve reaches the Mepol-initialised runs' final return.

    The unit is the pre-training run (from scratch, the fine-tuning run): a unit's targets and
    fine-tuning seeds are averaged first, and the t-interval is over the unit means
    (:func:`nested_mean_ci`), cut to the return's bounds (a goal task's [0, 1])."""
    frame = finetune_frame(runs)
    if frame.empty:
        return pd.DataFrame()
    rows = []
    for (env, wind), part in frame.groupby(["env", "wind"], sort=False, dropna=False):
        curves = finetune_curves(part)
        finals = {
            key: nested_mean_ci([final_value(x) for x in c.curves], c.units, bounds=c.bounds)
            for key, c in curves.items()
        }
        for (init, config), c in sorted(curves.items(), key=lambda kv: (kv[0][1], kv[0][0])):
            ci = finals[(init, config)]
            mepol = finals.get(("mepol", config))
            sub = part[(part["algo_init"] == init) & (part["config"] == config)]
            rows.append(
                {
                    "env": env,
                    "wind": wind,
                    "config": config,
                    "init": init_label(init),
                    "unit": "fine-tuning run" if init == SCRATCH.name else "pre-training run",
                    "n_units": ci.n,
                    "n_pretrain": sub["pretraining_run"].nunique(),
                    "n_finetune_seeds": sub["seed"].nunique(),
                    "n_targets": sub["target"].nunique(),
                    "n_curves": len(c.curves),
                    "final_return": ci.mean,
                    "ci95_low": ci.low,
                    "ci95_high": ci.high,
                    "ci95_half_width": ci.half_width,  # the t half-width, before the cut
                    "first_epoch_reaching_mepol_final": first_epoch_reaching(
                        c.epochs, curve_ci(c.unit_curves())[0], mepol.mean if mepol else math.nan
                    ),
                }
            )
    return pd.DataFrame(rows)


FINETUNE_HALF_WIDTH = 0.2  # a difference of returns in [0, 1] known to +-0.2: the pairs it needs


def init_label(init: str) -> str:
    return "from scratch" if init == SCRATCH.name else algo_label(init)


def first_epoch_reaching(epochs: np.ndarray, curve: np.ndarray, target: float) -> float:
    """The first epoch at which ``curve`` is at least ``target`` (NaN: never, or no target)."""
    if not np.isfinite(target):
        return math.nan
    reached = np.flatnonzero(np.asarray(curve, dtype=float) >= target)
    return float(epochs[reached[0]]) if len(reached) else math.nan


def finetune_difference_table(runs: list[Run]) -> pd.DataFrame:
    """Paired differences of final return between two initialisations, over the fine-tuning
    seeds both have, all configurations they share pooled.

    The pre-training run's seed pairs them (from scratch, the fine-tuning seed:
    :attr:`Run.pairing_seed`); every run draws its targets from ``goal_seed``, so paired runs
    face the same targets. Per initialisation and seed, R is the
    mean of its curves' final returns (each curve's mean over the last 10% of epochs) over its
    targets and the shared configurations; d = R_b - R_a per seed, with the mean, its 95%
    Student-t interval cut to the range a difference of returns can take, the exact sign-flip
    p-value and the pairs a +-FINETUNE_HALF_WIDTH interval would need. Last column: the first
    epoch at which b's mean curve (each of its independent units' mean curve over targets,
    configurations and seeds, then their mean) reaches a's R averaged over the paired seeds."""
    frame = finetune_frame(runs)
    if frame.empty:
        return pd.DataFrame()
    rows = []
    for (env, wind), part in frame.groupby(["env", "wind"], sort=False, dropna=False):
        inits = ordered_inits(finetune_curves(part))
        for a, b in itertools.combinations(inits, 2):
            pair = part[part["algo_init"].isin([a, b])]
            shared = set(pair.loc[pair["algo_init"] == a, "config"])
            shared &= set(pair.loc[pair["algo_init"] == b, "config"])
            pair = pair[pair["config"].isin(shared)]
            table = pair.pivot_table(
                index="epoch",
                columns=["algo_init", "pairing_seed", "unit", "run", "config", "target"],
                values="return",
            )
            finals = table.apply(final_value).rename("final").reset_index()
            per_seed = finals.groupby(["algo_init", "pairing_seed"])["final"].mean().unstack(0)
            per_seed = per_seed.dropna(subset=[a, b])
            if per_seed.empty:
                continue
            low, high = return_range(pair)
            r = paired(per_seed[a].to_dict(), per_seed[b].to_dict(), FINETUNE_HALF_WIDTH)
            span = high - low  # a difference of returns lies in [-span, span]
            curve_b = table[b][per_seed.index.to_list()]
            unit_curves = curve_b.T.groupby(level="unit", sort=False).mean()
            rows.append(
                {
                    "env": env,
                    "wind": wind,
                    "configs": " ".join(str(c) for c in sorted(shared)),
                    "comparison": f"{init_label(b)} − {init_label(a)}",
                    "n_pairs": r.n,
                    "seeds": " ".join(str(s) for s in per_seed.index),
                    "return_a": float(per_seed[a].mean()),
                    "return_b": float(per_seed[b].mean()),
                    "diff": r.mean,
                    "ci95_low": float(np.clip(r.low, -span, span)),
                    "ci95_high": float(np.clip(r.high, -span, span)),
                    "ci95_half_width": r.high - r.mean,  # the t half-width, before the cut
                    "p_sign_flip": r.p,
                    f"{SEEDS_COLUMN}hw{FINETUNE_HALF_WIDTH:g}": r.seeds_needed,
                    "first_epoch_b_reaching_a": first_epoch_reaching(
                        table.index.to_numpy(float),
                        unit_curves.mean(axis=0).to_numpy(float),
                        float(per_seed[a].mean()),
                    ),
                }
            )
    return pd.DataFrame(rows)


def format_number(column: str, value, digits: int = 3) -> str | None:
    """A float as the tables show it ('n/a' for NaN); None for anything that is not a float."""
    if not isinstance(value, float | np.floating):
        return None
    if column.startswith(SEEDS_COLUMN):
        return format_seeds(float(value))
    if not np.isfinite(value):
        return "n/a"
    if column == "wind" or column.startswith("first_epoch"):
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


# Each table of the report: its title, and a caption that says its unit, method and columns
# (Markdown: `code`), written under the title in summary.md and index.html alike.
TABLE_TITLES = {
    "summary": "Final entropy per group and configuration (nats)",
    "differences": "Differences between algorithms (nats; same env and wind)",
    "finetune": "Fine-tuning returns",
    "finetune_differences": "Differences between initialisations in fine-tuning (paired by seed)",
    "drops": "Drops and the KL of the updates before them (runs with diagnostics)",
    "drops_pooled": "Drops per group, pooled over seeds",
}


def table_caption(name: str) -> str:
    """What table ``name`` holds, over which unit, by which method."""
    planned = ", ".join(f"±{h:g}" for h in PLANNED_HALF_WIDTHS)
    captions = {
        "summary": (
            "Final entropy: per seed, the mean entropy (nats) over the last 10% of epochs "
            "(`final_epochs`: which; more than one where seeds ran different lengths). The "
            "unit is the seed (one pre-training run). `mean_nats`, `ci95_*`: the mean over seeds "
            "with its Student-t 95% interval (n/a with one seed). `iqm_nats`, `*_boot95_*`: "
            "rliable's interquartile mean and mean (Agarwal et al., 2021) with 95% intervals by "
            f"a {AGGREGATES_METHOD}; the average row's are over each seed's average entropy (the "
            "configurations weighted by their probabilities, as `mean_nats`)."
        ),
        "differences": (
            "Final entropy of the later algorithm minus the earlier one (order Mepol, α-Mepol, "
            "HMepol), each over its last 10% of epochs (`final_epochs_a`, `_b`: which); the unit "
            "is the seed. 95% CI: paired t-interval on the per-seed "
            "differences when both groups ran the same seeds, Welch's t-interval "
            "(Welch-Satterthwaite degrees of freedom) otherwise (column `method`). "
            "`p_improvement`: the probability that a run of the later algorithm scores higher "
            "than a run of the earlier (per configuration the share of seed pairs, ties one "
            "half; the average row averages it over configurations), with its interval by the "
            f"same bootstrap over runs. `{SEEDS_COLUMN}*`: the seeds per arm for a 95% interval "
            f"of {planned} nats (`hw`) and for {PLANNED_POWER:.0%} power against a "
            f"{PLANNED_DIFFERENCE:g}-nat difference (`power`), from the observed spread (the t "
            "quantile searched on n; power from the noncentral t). "
            f"`{DETECTABLE_COLUMN}`: the smallest true difference these seeds find with "
            f"{PLANNED_POWER:.0%} power."
        ),
        "finetune": (
            "Final return: per (fine-tuning run, seed, target) curve the mean over the last 10% "
            "of epochs. The unit of independence is the pre-training run (`unit`; from scratch, "
            "the fine-tuning run): the targets and fine-tuning seeds of one unit are averaged "
            "first, and `ci95_*` is the Student-t 95% interval over the `n_units` unit means, cut "
            "to the range of the return (a goal task's return is the share of episodes that "
            "reached the target: [0, 1]); `ci95_half_width` is the t half-width before the cut. "
            "`n_pretrain` pre-training runs, `n_finetune_seeds` fine-tuning seeds, `n_targets` "
            "targets and `n_curves` curves in all. Last column: the first epoch at which the "
            "mean curve reaches the final mean return of the Mepol-initialised runs."
        ),
        "finetune_differences": (
            "Final return of initialisation b minus a (`comparison`: b − a), paired by the "
            "pre-training run's seed (from scratch, the fine-tuning seed; targets come from "
            "`goal_seed`, so paired runs face the same ones). Per initialisation and "
            "seed, R is the mean final return (each curve's mean over the last 10% of epochs) "
            "over its targets and the configurations both initialisations ran (`configs`, "
            "pooled); `return_a`, `return_b` average R over the `n_pairs` seeds (`seeds`). "
            "`diff`, `ci95_*`: the mean of the per-seed differences with its Student-t 95% "
            "interval, cut to the range a difference of returns can take ([-1, 1] for a goal "
            "task); `ci95_half_width` before the cut. `p_sign_flip`: the two-sided exact "
            "sign-flip p-value of a zero mean difference. "
            f"`{SEEDS_COLUMN}hw{FINETUNE_HALF_WIDTH:g}`: the pairs a ±{FINETUNE_HALF_WIDTH:g} "
            "interval needs at the observed spread. Last column: the first epoch at which b's "
            "mean curve (its independent units' mean curves, averaged) reaches `return_a`."
        ),
        "drops": (
            f"A drop: a fall of more than {DROP_NATS:g} nat in one configuration's entropy "
            "(`entropy_c<c>`) from one epoch to the next, epoch e against epoch e - 1 in that "
            f"configuration (none where either lacks it), from epoch {DROP_FROM} on. Per run: "
            "`drops_c<c>` counts configuration c's drops, `drops` the epochs with a drop in any "
            "configuration (pooled over configurations). KL ratio: the exact KL of an accepted "
            "update over its one-step KL (median over the updates just before a drop, and over "
            "the others)."
        ),
        "drops_pooled": (
            "The drops above summed over each group's seeds (`drops`, `drops_c<c>`), their mean "
            "per run, and the share of runs with at least one drop with Wilson's 95% interval: "
            "the run is the unit, the epochs of one run are not independent."
        ),
    }
    return captions[name]


def window_note(name: str, table: pd.DataFrame) -> str:
    """A warning when rows of the differences compare finals taken at different epochs (a
    group that ran fewer epochs against a longer one): '' when none do."""
    if name != "differences" or table.empty:
        return ""
    apart = table[table["final_epochs_a"] != table["final_epochs_b"]]
    if apart.empty:
        return ""
    pairs = sorted(set(zip(apart["final_epochs_a"], apart["final_epochs_b"], strict=True)))
    shown = "; ".join(f"{a} against {b}" for a, b in pairs[:3])
    shown += "; ..." if len(pairs) > 3 else ""
    return (
        f"{len(apart)} of {len(table)} rows compare finals taken at different epochs ({shown}): "
        "they compare runs at different stages of training, not the algorithms at one."
    )


def table_sections(tables: dict[str, pd.DataFrame]) -> list[tuple[str, str, str, str, str]]:
    """(name, title, caption, notice (too few units, finals at different epochs), resolution
    line) of each table to show: the entropy tables always, the others when they have rows."""
    shown = [n for n in TABLE_TITLES if n in ("summary", "differences") or not tables[n].empty]
    sections = []
    for name in shown:
        notes = (few_units_note(name, tables[name]), window_note(name, tables[name]))
        notice = " ".join(n for n in notes if n)
        line = resolution_line(name, tables[name])
        sections.append((name, TABLE_TITLES[name], table_caption(name), notice, line))
    return sections


def write_summary(
    groups: list[Group], finetune_runs: list[Run], out_dir: Path
) -> tuple[dict[str, pd.DataFrame], list[Path]]:
    """Write summary.csv, differences.csv, finetune.csv, finetune_differences.csv, drops.csv,
    drops_pooled.csv (each when not empty) and summary.md; return the tables and the files
    written."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    drops = drop_table(diagnosed(groups))
    tables = {
        "summary": final_entropy_table(groups),
        "differences": difference_table(groups),
        "finetune": finetune_table(finetune_runs),
        "finetune_differences": finetune_difference_table(finetune_runs),
        "drops": drops,
        "drops_pooled": pooled_drops(drops),
    }
    files = []
    for name, table in tables.items():
        if not table.empty:
            files.append(out_dir / f"{name}.csv")
            table.to_csv(files[-1], index=False)
    text = ["# hmepol report: summary\n"]
    for name, title, caption, notice, line in table_sections(tables):
        text += [f"## {title}\n", caption + "\n"]
        text += [f"**{notice}**\n"] if notice else []
        text += [to_markdown(tables[name])]
        text += [f"_{line}_\n"] if line else []
    files.append(out_dir / "summary.md")
    files[-1].write_text("\n".join(text))
    return tables, files
