"""The words of the report's figures: the seed counts of legends, the spread a title names,
each figure's caption (what was compared, over how many units, and how), and the thesis figure
it reproduces. figures.py draws; what it says about a figure is written here.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import pandas as pd

from hmepol_cli.algorithms import SCRATCH
from hmepol_cli.plots import TRAJECTORIES
from hmepol_cli.report.aggregates import METHOD as AGGREGATES_METHOD
from hmepol_cli.report.diagnostics import DROP_FROM, DROP_NATS
from hmepol_cli.report.frames import return_range
from hmepol_cli.report.runs import Group, Run, algo_label, format_wind
from hmepol_cli.report.stats import MIN_UNITS, t_quantile

# Which thesis figure each kind of figure reproduces, per environment.
THESIS_FIGURES = {
    ("slope", "curves"): "Fig. A.1a",
    ("slope", "curves_by_config"): "Fig. A.1b, A.1c",
    ("slope", "bars"): "Fig. 5.2",
    ("slope", "heatmaps"): "Fig. 5.3",
    ("corridor", "curves"): "Fig. A.2",
    ("corridor", "bars"): "Fig. 5.7",
    ("corridor", "wind"): "Fig. 5.10",
    ("corridor", "heatmaps"): "Fig. 5.8",
    ("corridor", "trajectories", "mepol"): "Fig. 5.5",
    ("corridor", "trajectories", "hmepol"): "Fig. 5.6",
    ("corridor", "finetune"): "Fig. 5.9",
    ("multigrid", "curves"): "Fig. 5.13",
    ("multigrid", "bars"): "Fig. 5.12",
    ("multigrid", "heatmaps"): "Fig. 5.11",
}


# ----------------------------------------------------------------------- legends and titles
def n_text(n: int) -> str:
    """Legend suffix: the number of seeds, and that fewer than MIN_UNITS have no interval."""
    if n >= MIN_UNITS:
        return f"n={n}"
    return f"n={n}, no CI" if n == 1 else f"n={n}, each seed drawn"


def wind_title(wind: float, several: bool) -> str:
    return f", wind {format_wind(wind)}" if several else ""


def _seeds(n: int) -> str:
    return f"{n} seed{'s' if n != 1 else ''}"


def median_of(group: Group) -> str:
    """Why a map shows the seed it does (:meth:`Group.representative`): the one whose final
    average entropy is the median of the seeds with maps, the lower of the middle two for an
    even count."""
    n = sum(1 for r in group.runs if r.positions) or len(group.runs)
    if n == 1:
        return "the only seed"
    which = "lower median" if n % 2 == 0 else "median"
    return f"its final entropy is the {which} of {n}"


def spread_title(groups: list[Group]) -> str:
    """The title's '(mean, 95% CI over seeds)', or '(mean and each seed)' under MIN_UNITS."""
    if all(len(g.runs) >= MIN_UNITS for g in groups):
        return "(mean, 95% CI over seeds)"
    if all(len(g.runs) < MIN_UNITS for g in groups):
        return "(mean and each seed)"
    return "(mean; 95% CI over seeds, or each seed under 3)"


def init_epochs_text(frame: pd.DataFrame, init: str) -> str:
    """ ", from epoch 75": the pre-training epochs of the policies the fine-tunings of ``init``
    started from (finetune.csv's init_epoch; "" from scratch and for runs that predate it)."""
    if init == "scratch" or "init_epoch" not in frame:
        return ""
    epochs = frame.loc[frame["algo_init"] == init, "init_epoch"].dropna().unique()
    return f", from epoch {', '.join(str(int(e)) for e in sorted(epochs))}" if len(epochs) else ""


# ------------------------------------------------------------------------ parts of captions
def seeds_text(groups: list[Group]) -> str:
    """'8 seeds each' or 'Mepol 8 seeds, HMepol 3 seeds'; notes a group with no CI."""
    counts = {g.label: len(g.runs) for g in groups}
    if len(set(counts.values())) == 1:
        n = next(iter(counts.values()))
        text = f"{n} seed{'s' if n > 1 else ''}" + (" each" if len(counts) > 1 else "")
    else:
        text = ", ".join(f"{label} {n} seed{'s' if n > 1 else ''}" for label, n in counts.items())
    return text


def spread_text(
    groups: list[Group],
    interval: str = "band",
    instead: str = "thin lines: each seed's own curve",
) -> str:
    """What is drawn beside the means: '<interval>: Student-t 95% CI over seeds' from MIN_UNITS
    seeds on, ``instead`` under it, or both, by group (with the seed counts)."""
    few = [g for g in groups if len(g.runs) < MIN_UNITS]
    ci = f"{interval}: Student-t 95% CI over seeds"
    seeds = f"{instead} (under {MIN_UNITS} seeds a t-interval on one degree of freedom, "
    seeds += f"±{t_quantile(1):.1f} standard errors, would cover the axis)"
    if not few:
        text = ci
    elif len(few) == len(groups):
        text = seeds
    else:
        text = f"{ci} where a group has {MIN_UNITS} seeds or more; {seeds}"
    return f"{text} ({seeds_text(groups)})"


def _pretraining_scale(group: Group) -> str:
    """'4 seeds, 200 epochs of 100 trajectories x 400 steps' (epochs: the fewest any seed has)."""
    config = group.first.config
    epochs = min(len(r.epochs) for r in group.runs)
    return (
        f"{_seeds(len(group.runs))}, {epochs} epoch{'s' if epochs != 1 else ''} of "
        f"{config.get('algo.trajectories', '?')} trajectories x {config.get('algo.horizon', '?')} "
        "steps"
    )


def scale_text(groups: list[Group]) -> str:
    """The caption's last sentence: the runs' scale, once when every group shares it."""
    scales = {g.label: _pretraining_scale(g) for g in groups}
    if len(set(scales.values())) == 1:
        text = next(iter(scales.values())) + (" each" if len(scales) > 1 else "")
    else:
        text = "; ".join(f"{label}: {scale}" for label, scale in scales.items())
    return f" Scale: {text}."


def finetune_scale(runs: list[Run]) -> str:
    """'6 epochs of 10 episodes x 150 steps' of the fine-tuning runs."""
    scales = sorted(
        {
            f"{r.config.get('epochs', '?')} epochs of {r.config.get('episodes', '?')} episodes x "
            f"{r.config.get('horizon', '?')} steps"
            for r in runs
        }
    )
    return f" Scale: {'; '.join(scales)}."


def units_text(part: pd.DataFrame, init: str) -> str:
    """'2 pre-training runs x 1 fine-tuning seed x 5 targets' of one initialisation."""
    rows = part[part["algo_init"] == init]

    def count(n: int, what: str) -> str:
        return f"{n} {what}{'s' if n != 1 else ''}"

    seeds = count(rows["seed"].nunique(), "fine-tuning seed")
    targets = count(rows["target"].nunique(), "target")
    if init == SCRATCH.name:
        return f"{count(rows['run'].nunique(), 'fine-tuning run')} ({seeds}) x {targets}"
    return f"{count(rows['unit'].nunique(), 'pre-training run')} x {seeds} x {targets}"


# ---------------------------------------------------------------------------------- captions
# Each caption says what was compared, over how many units, and what is drawn beside the mean;
# make_figures adds the pre-training runs' scale_text.
def entropy_curves_caption(groups: list[Group], labels: Iterable[str], winds: list[float]) -> str:
    several = len(winds) > 1
    return (
        f"Average state entropy (kNN estimate, nats) at the start of each epoch, mean over "
        f"mini-batches of all configurations, for {' vs '.join(labels)}"
        + (f", one panel per wind force ({', '.join(map(format_wind, winds))})" if several else "")
        + f". Line: mean over seeds; {spread_text(groups)}. "
        "Dashed: log(free area) weighted by p_M, the entropy of a uniform visitation."
    )


def entropy_by_config_caption(groups: list[Group], labels: Iterable[str], sampled: bool) -> str:
    """``sampled``: some epochs of a configuration lack some seeds (configurations are drawn)."""
    per_epoch = (
        " Configurations are sampled each epoch, so an epoch's point is the mean over the seeds "
        "that drew the configuration in it: n≤ in the legend is the group's seeds, the most a "
        "point has."
        if sampled
        else ""
    )
    return (
        f"State entropy (nats) per epoch computed only on the mini-batches drawn in each "
        f"configuration, for {' vs '.join(labels)}. Line: mean over seeds; {spread_text(groups)}; "
        "gaps are epochs where no seed drew that configuration, a dot an "
        f"epoch between gaps.{per_epoch} Each panel has its own y-scale. Dashed: log(free area) "
        "of the configuration."
    )


def final_bars_caption(groups: list[Group], labels: Iterable[str], every_config: bool) -> str:
    """``every_config``: a bar for each configuration, else for configuration 0 only."""
    shown = "the average over configurations and " + (
        "each configuration" if every_config else "configuration 0 (the hardest)"
    )
    return (
        f"Final entropy (nats; per seed the mean over the last 10% of epochs) of "
        f"{' vs '.join(labels)}: {shown}. Bars: mean over seeds; "
        f"{spread_text(groups, 'error bars', 'no error bars')}. "
        "Dots: individual seeds. Dashed: log(free area), the entropy of a uniform visitation "
        "(weighted by p_M for the average)."
    )


def entropy_against_wind_caption(
    groups: list[Group], labels: Iterable[str], windows: dict[float, str] | None = None
) -> str:
    """``windows``: the epochs each wind's final values average, where they differ."""
    cut = (
        " Runs still going: each wind compares its arms over the epochs under its tick ("
        + "; ".join(f"wind {format_wind(w)}: {e}" for w, e in windows.items())
        + "), so the winds are not at one epoch."
        if windows
        else ""
    )
    return (
        f"Final average entropy (nats; per seed the mean over the last 10% of its epochs) "
        f"against the wind force, {' vs '.join(labels)}. Markers: mean over seeds; "
        f"{spread_text(groups, 'error bars', 'small dots: each seed')}. Dashed: log(free area) "
        f"weighted by p_M.{cut}"
    )


def aggregates_caption(groups: list[Group]) -> str:
    return (
        "rliable's aggregates of the final entropies (Agarwal et al., 2021), a score being one "
        "seed's final entropy in one configuration. Left: interquartile mean (IQM) and mean of "
        f"all seed x configuration scores with 95% intervals by a {AGGREGATES_METHOD}. Right: "
        "performance profile, the share of scores above each entropy, with pointwise "
        "intervals. The probability of improvement of each pair is in differences.csv "
        f"(p_improvement) and the table below. Seeds: {seeds_text(groups)}."
    )


def diagnostics_caption(groups: list[Group], without: list[str]) -> str:
    """``without``: the groups (as the figure names them) with no diagnostics (steps.csv)."""
    absent = (
        f" {' and '.join(without)} {'has' if len(without) == 1 else 'have'} no steps.csv (run "
        "without diagnostics=true), so no KL ratio: absent from the two panels on the left, "
        "shown in the other two."
        if without
        else ""
    )
    return (
        "Runs made with diagnostics=true. Top left: the exact KL of each epoch's accepted "
        "update (likelihoods recomputed over whole histories) over the one-step KL the "
        "gradient's likelihoods give (eq. 2.8), per seed (thin) and their median (thick; n in "
        "the legend); 1 for a Markovian policy. Top right: single-epoch falls of more than "
        f"{DROP_NATS:g} nat in one configuration's entropy from epoch {DROP_FROM} on, per "
        "seed. Bottom left: each epoch's lowest change of a configuration's entropy since the "
        "epoch before (negative: a fall; dashed: the drop threshold) against the KL ratio of "
        "the update before it. Bottom right: the share of action components past the clip. "
        f"drops.csv lists the drops and the median ratios before and away from them.{absent} "
        f"Seeds: {seeds_text(groups)}."
    )


def heatmaps_caption(shown: list[tuple[Group, Run]], trajectories: int, steps: int) -> str:
    """``shown``: each group and the seed whose visitation is drawn."""
    who = "; ".join(f"{g.label}: seed {run.seed} ({median_of(g)})" for g, run in shown)
    return (
        f"Log probability of state visitation (2-D histogram over the arena, one shared colour "
        f"scale; grey: walls) of {trajectories} fresh trajectories of {steps} steps per "
        "configuration, collected with the final policy of one seed per algorithm: the seed "
        "whose final average entropy (per seed the mean over the last 10% of epochs) is the "
        "median of its group's, the lower of the two middle ones for an even number of seeds, "
        f"so that the map is a typical seed's and not the best's: {who}. White: bins that no "
        "state of these trajectories fell in (probability 0, whose log is off the colour "
        "scale), not bins the policy cannot reach. Red dashed box: the start area."
    )


def trajectories_caption(group: Group, runs: list[Run]) -> str:
    """``runs``: the seeds drawn, the representative first."""
    return (
        f"{TRAJECTORIES} trajectories of the final {group.label} policy in each "
        f"configuration (columns) for seed{'s' if len(runs) > 1 else ''} "
        f"{', '.join(str(r.seed) for r in runs)} (rows; {_seeds(len(group.runs))} in all; "
        "the first has the median final entropy), drawn through every step and coloured by "
        "the step (colour bar); a white circle marks each start, a black square each end; "
        "grey: walls." + scale_text([group])
    )


def finetune_caption(part: pd.DataFrame, inits: list[str], runs: list[Run]) -> str:
    """The fine-tuning rows of one wind, the initialisations drawn, the env's fine-tuning runs."""
    who = "; ".join(f"{algo_label(i)}: {units_text(part, i)}" for i in inits)
    low, high = return_range(part)
    cut = (
        f", cut to the return's range [{low:g}, {high:g}]" if np.isfinite([low, high]).all() else ""
    )
    return (
        "Average return per epoch of TRPO on a sparse goal-reaching task, per configuration, "
        "started from a pre-trained policy or from scratch. The unit of independence is the "
        "pre-training run (from scratch, the fine-tuning run): its targets and fine-tuning "
        "seeds are nested in it; n in the legend counts these units: pre-training runs, and "
        "for from scratch fine-tuning runs. Line: mean over the units of each unit's mean "
        f"curve; with fewer than {MIN_UNITS} units, thin lines: each unit's own curve (a "
        "pre-training run's, averaged over its targets and fine-tuning seeds; from scratch, "
        f"a fine-tuning run's); from {MIN_UNITS} on, "
        f"band: Student-t 95% CI over the units{cut} ({who})." + finetune_scale(runs)
    )
