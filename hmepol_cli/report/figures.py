"""The report's figures (thesis ch. 5 and appendix A), each drawn only when the runs allow it.

Every figure function takes the groups of one environment and returns :class:`FigureRecord`s
(the PNG path and a caption that says what was compared, over how many seeds, and how).
Curves and bars are the mean over the independent units (seeds; for fine-tuning, pre-training
runs). What is drawn beside the mean is what their number allows: from MIN_UNITS on, the
Student-t 95% confidence interval (inside the axes, and inside a bounded quantity's range);
with fewer, each unit's own curve or dot, as a two-seed band (t = 12.7) would cover the axis.
Each group has a colour of its own.
"""

from __future__ import annotations

import hashlib
import math
import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
from matplotlib.collections import LineCollection, PolyCollection

from hmepol_cli.algorithms import SCRATCH
from hmepol_cli.plots import (
    BOUND_COLOUR,
    LINESTYLES,
    OTHER_COLOURS,
    TRAJECTORIES,
    algo_colour,
    heatmap_grid,
    new_figure,
    save,
    trajectory_grid,
)
from hmepol_cli.report.aggregate_figure import draw_aggregates
from hmepol_cli.report.aggregates import METHOD as AGGREGATES_METHOD
from hmepol_cli.report.diagnostics import DROP_FROM, DROP_NATS, diagnosed, draw_diagnostics
from hmepol_cli.report.runs import ALGO_ORDER, Group, Run, algo_label, format_wind
from hmepol_cli.report.stats import MIN_UNITS, UNBOUNDED, curve_ci, mean_ci, t_quantile

MAX_CONFIG_BARS = 5  # more configurations than this (multigrid): bars for average and config 0
MAX_TRAJECTORY_SEEDS = 3
HATCHES = ("", "//", "..", "xx")

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


@dataclass
class FigureRecord:
    path: Path
    title: str
    caption: str
    thesis: str  # the thesis figure it reproduces ("" when it has no counterpart)
    env: str


@dataclass(frozen=True)
class Style:
    colour: str
    linestyle: object
    hatch: str  # for bars: the second series of one algorithm is hatched
    label: str


# ------------------------------------------------------------------------------------- helpers
def series_styles(groups: Iterable[Group]) -> dict[str, Style]:
    """label -> style, a colour of its own for every series: an algorithm's main series (the
    one labelled by the algorithm alone, else its first) takes the algorithm's colour, its
    variants the next unused colours of OTHER_COLOURS; a variant also gets a dash (and hatching
    on bars), so that it reads as one of its algorithm's."""
    groups = list(dict((g.label, g) for g in groups).values())
    main: dict[str, str] = {}
    for group in groups:
        main.setdefault(group.algo, group.label)
        if group.label == algo_label(group.algo):
            main[group.algo] = group.label
    spare = [c for c in OTHER_COLOURS if c not in {algo_colour(a) for a in main}]
    styles: dict[str, Style] = {}
    per_algo: dict[str, int] = {}
    variants = 0
    for group in groups:
        if group.label == main[group.algo]:
            k, colour = 0, algo_colour(group.algo)
        else:
            k = per_algo[group.algo] = per_algo.get(group.algo, 0) + 1
            colour, variants = spare[variants % len(spare)], variants + 1
        styles[group.label] = Style(
            colour, LINESTYLES[k % len(LINESTYLES)], HATCHES[k % len(HATCHES)], group.label
        )
    return styles


def load_world(env: str, wind: float):
    """The world's geometry (walls, arena), or None when this env cannot be built here."""
    try:
        from hmepol_cli.envs import make_world

        return make_world(SimpleNamespace(name=env, wind=wind if np.isfinite(wind) else 0.0))
    except Exception:
        return None


def slug(text: str, limit: int = 80) -> str:
    """A file-name part for a label; long labels (many differing keys) are cut and hashed, so
    names stay unique and within every filesystem's limit."""
    text = text.replace("α", "alpha").lower()
    name = re.sub(r"[^a-z0-9]+", "-", text).strip("-")
    if len(name) <= limit:
        return name
    digest = hashlib.sha1(name.encode()).hexdigest()[:10]
    return f"{name[: limit - 11]}-{digest}"


def winds_of(groups: list[Group]) -> list[float]:
    return sorted({g.wind for g in groups}, key=lambda w: np.nan_to_num(w, nan=-1.0))


def at_wind(groups: list[Group], wind: float) -> list[Group]:
    return [g for g in groups if g.wind == wind or (np.isnan(g.wind) and np.isnan(wind))]


def n_text(n: int) -> str:
    """Legend suffix: the number of seeds, and that fewer than MIN_UNITS have no interval."""
    if n >= MIN_UNITS:
        return f"n={n}"
    return f"n={n}, no CI" if n == 1 else f"n={n}, each seed drawn"


def wind_tag(wind: float, several: bool) -> str:
    return f"_wind{format_wind(wind)}" if several else ""


def wind_title(wind: float, several: bool) -> str:
    return f", wind {format_wind(wind)}" if several else ""


def _seeds(n: int) -> str:
    return f"{n} seed{'s' if n != 1 else ''}"


def _median_of(n: int) -> str:
    return "the only seed" if n == 1 else f"median of {n} seeds"


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


def spread_title(groups: list[Group]) -> str:
    """The title's '(mean, 95% CI over seeds)', or '(mean and each seed)' under MIN_UNITS."""
    if all(len(g.runs) >= MIN_UNITS for g in groups):
        return "(mean, 95% CI over seeds)"
    if all(len(g.runs) < MIN_UNITS for g in groups):
        return "(mean and each seed)"
    return "(mean; 95% CI over seeds, or each seed under 3)"


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


def average_bound(run: Run) -> float:
    """Highest average entropy: sum_c p_M(c) log(free area of c), the uniform visitation."""
    logs, probs = np.array(run.log_free_area), np.array(run.configuration_probs)
    return float((logs * probs).sum() / probs.sum()) if np.isfinite(logs).all() else math.nan


def config_bound(run: Run, config: int | None) -> float:
    return average_bound(run) if config is None else run.log_free_area[config]


def draw_bound(ax, value: float, label: bool = True) -> None:
    if np.isfinite(value):
        ax.axhline(
            value,
            color=BOUND_COLOUR,
            ls="--",
            lw=1.0,
            label=f"log(free area) = {value:.2f} nats" if label else None,
        )


def isolated(values: np.ndarray) -> np.ndarray:
    """Mask of the finite values whose neighbours are both missing: a line draws nothing there."""
    finite = np.isfinite(values)
    before = np.concatenate([[False], finite[:-1]])
    after = np.concatenate([finite[1:], [False]])
    return finite & ~before & ~after


def plot_mean(
    ax,
    x: np.ndarray,
    mean: np.ndarray,
    half: np.ndarray,
    colour: str,
    ls,
    label: str,
    bounds: tuple[float, float] = UNBOUNDED,
) -> None:
    """Mean curve (n_points,) with its confidence band of half-width ``half``, cut to ``bounds``
    (the values the quantity can take).

    A point with no neighbour (a run of one epoch, a configuration drawn in one epoch between
    gaps) gets a marker, and its interval a bar: a line and a band through one point are empty.
    """
    low, high = np.clip(mean - half, *bounds), np.clip(mean + half, *bounds)
    ax.plot(x, mean, color=colour, ls=ls, lw=1.5, label=label)
    if np.isfinite(half).any():
        ax.fill_between(x, low, high, color=colour, alpha=0.2, lw=0)
    alone = isolated(mean)
    ax.plot(x[alone], mean[alone], ls="none", marker="o", ms=5, color=colour)
    bar = alone & np.isfinite(half)
    ax.vlines(x[bar], low[bar], high[bar], color=colour, alpha=0.4)


def plot_units(
    ax,
    x: np.ndarray,
    curves: np.ndarray,
    colour: str,
    ls,
    label: str,
    bounds: tuple[float, float] = UNBOUNDED,
) -> None:
    """The mean of the curves (n_units, n_points) of independent units, and what their number
    allows beside it: under MIN_UNITS, each unit's own curve (thin), as a t-band on one degree of
    freedom (t = 12.7) would cover the axis; from MIN_UNITS on, the Student-t 95% band."""
    mean, half, n = curve_ci(curves)
    if curves.shape[0] > 1 and curves.shape[0] < MIN_UNITS:
        for curve in curves:
            ax.plot(x, curve, color=colour, ls="-", lw=0.6, alpha=0.5)
    half = np.where(n >= MIN_UNITS, half, np.nan)  # also where a point has fewer units
    plot_mean(ax, x, mean, half, colour, ls, label, bounds)


def draw_curve(ax, group: Group, style: Style, config: int | None) -> None:
    epochs, curves = group.curves(config)
    if curves.size == 0:
        return
    label = f"{style.label} ({n_text(len(group.runs))})"
    plot_units(ax, epochs, curves, style.colour, style.linestyle, label)


def _band_values(ax) -> list[np.ndarray]:
    """The y of every band (fill_between) and interval bar (vlines) drawn on ``ax``."""
    return [
        np.asarray(path.vertices[:, 1], dtype=float)
        for collection in ax.collections
        if isinstance(collection, PolyCollection | LineCollection)
        for path in collection.get_paths()
    ]


def fit_to_lines(axes) -> None:
    """One y-range for ``axes`` (one panel, or panels that share their y-axis) that holds their
    lines (means, seeds' own curves, bounds) and bands. Bands are drawn only from MIN_UNITS
    seeds on, where they are a few standard errors wide, so they fit without flattening the
    curves."""
    lines = [line for ax in np.ravel(axes) for line in ax.get_lines()]
    bands = [v for ax in np.ravel(axes) for v in _band_values(ax)]
    values = np.concatenate(
        [np.asarray(line.get_ydata(), dtype=float) for line in lines] + bands + [[]]
    )
    values = values[np.isfinite(values)]
    if values.size == 0:
        return
    lo, hi = float(values.min()), float(values.max())
    pad = max(0.15 * (hi - lo), 0.25)
    for ax in np.ravel(axes):
        ax.set_ylim(lo - pad, hi + pad)


def _legend(fig, axes) -> None:
    """One legend for the figure, below the panels, from the union of the panels' handles."""
    seen: dict[str, object] = {}
    for ax in np.ravel(axes):
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            seen.setdefault(label, handle)
    if seen:
        # As many columns as fit the figure's width (about 0.075 inch a character at 10 pt).
        entry = 0.075 * max(map(len, seen)) + 0.7
        cols = max(1, min(len(seen), int(fig.get_figwidth() / entry)))
        fig.legend(
            list(seen.values()),
            list(seen.keys()),
            loc="outside lower center",
            ncols=cols,
            frameon=False,
        )


# ------------------------------------------------------------------------- entropy per epoch
def entropy_curves(env: str, groups: list[Group], out_dir: Path) -> list[FigureRecord]:
    """Average entropy per epoch, one panel per wind (A.1a, A.2, 5.13)."""
    styles = series_styles(groups)
    winds = winds_of(groups)
    several = len(winds) > 1
    cols = min(len(winds), 2)
    rows = math.ceil(len(winds) / cols)
    fig = new_figure(5.0 * cols, 3.4 * rows + 0.6)
    axes = fig.subplots(rows, cols, squeeze=False, sharey=True)
    for i, wind in enumerate(winds):
        ax = axes[i // cols, i % cols]
        members = at_wind(groups, wind)
        for group in members:
            draw_curve(ax, group, styles[group.label], None)
        draw_bound(ax, average_bound(members[0].first))
        ax.set_title(f"wind {format_wind(wind)}" if several else "average over configurations")
        ax.set_xlabel("epoch")
        ax.set_ylabel("entropy (nats)")
        ax.grid(alpha=0.3)
    fit_to_lines(axes)  # one scale for every wind, as the panels share their y-axis
    for j in range(len(winds), rows * cols):
        axes[j // cols, j % cols].set_axis_off()
    compared = " vs ".join(styles)
    fig.suptitle(f"{env}: average entropy per epoch\n{spread_title(groups)}")
    _legend(fig, axes)
    path = save(fig, out_dir / f"{env}_entropy_epochs.png")
    caption = (
        f"Average state entropy (kNN estimate, nats) at the start of each epoch, mean over "
        f"mini-batches of all configurations, for {compared}"
        + (f", one panel per wind force ({', '.join(map(format_wind, winds))})" if several else "")
        + f". Line: mean over seeds; {spread_text(groups)}. "
        "Dashed: log(free area) weighted by p_M, the entropy of a uniform visitation."
    )
    return [
        FigureRecord(
            path,
            f"{env}: average entropy per epoch",
            caption,
            THESIS_FIGURES.get((env, "curves"), ""),
            env,
        )
    ]


def entropy_curves_by_config(env: str, groups: list[Group], out_dir: Path) -> list[FigureRecord]:
    """Entropy per epoch in each configuration, one panel per (wind, configuration) (A.1b, A.1c)."""
    styles = series_styles(groups)
    winds = winds_of(groups)
    several = len(winds) > 1
    names = groups[0].configuration_names
    n_configurations = len(names)
    cols = min(n_configurations, 5)
    per_wind = math.ceil(n_configurations / cols)
    fig = new_figure(4.0 * cols, 3.0 * per_wind * len(winds) + 0.6)
    # Each configuration on its own scale: their entropies differ by more than a curve's rise.
    axes = fig.subplots(per_wind * len(winds), cols, squeeze=False)
    for w, wind in enumerate(winds):
        members = at_wind(groups, wind)
        for c in range(per_wind * cols):
            ax = axes[w * per_wind + c // cols, c % cols]
            if c >= n_configurations:
                ax.set_axis_off()
                continue
            for group in members:
                draw_curve(ax, group, styles[group.label], c)
            draw_bound(ax, config_bound(members[0].first, c))
            fit_to_lines(ax)
            ax.set_title(f"config {c}: {names[c]}{wind_title(wind, several)}", fontsize=10)
            ax.set_xlabel("epoch")
            if c % cols == 0:
                ax.set_ylabel("entropy (nats)")
            ax.grid(alpha=0.3)
    compared = " vs ".join(styles)
    fig.suptitle(f"{env}: entropy per epoch in each configuration {spread_title(groups)}")
    _legend(fig, axes)
    path = save(fig, out_dir / f"{env}_entropy_epochs_by_config.png")
    caption = (
        f"State entropy (nats) per epoch computed only on the mini-batches drawn in each "
        f"configuration, for {compared}. Line: mean over seeds; {spread_text(groups)}; gaps "
        "are epochs where no seed drew that configuration, a dot an "
        "epoch between gaps. Each panel has its own y-scale. Dashed: log(free area) of the "
        "configuration."
    )
    return [
        FigureRecord(
            path,
            f"{env}: entropy per epoch per configuration",
            caption,
            THESIS_FIGURES.get((env, "curves_by_config"), ""),
            env,
        )
    ]


# ------------------------------------------------------------------------ final entropy bars
def final_entropy_bars(env: str, groups: list[Group], out_dir: Path) -> list[FigureRecord]:
    """Final entropy as bars: average and per configuration, one panel per wind (5.2, 5.7, 5.12)."""
    styles = series_styles(groups)
    winds = winds_of(groups)
    several = len(winds) > 1
    names = groups[0].configuration_names
    configurations: list[int | None] = [None] + list(
        range(len(names) if len(names) <= MAX_CONFIG_BARS else 1)
    )
    cols = min(len(winds), 2)
    rows = math.ceil(len(winds) / cols)
    fig = new_figure(
        max(6.0, 1.0 * len(configurations) * len(styles) ** 0.5 + 1.5) * cols, 3.6 * rows + 0.7
    )
    axes = fig.subplots(rows, cols, squeeze=False, sharey=True)
    width = 0.8 / len(styles)
    rng = np.random.default_rng(0)  # jitter of the seed dots only
    shown_values = [0.0]  # bars start at 0
    for i, wind in enumerate(winds):
        ax = axes[i // cols, i % cols]
        members = at_wind(groups, wind)
        for s, label in enumerate(styles):
            group = next((g for g in members if g.label == label), None)
            if group is None:
                continue
            style = styles[label]
            for x, config in enumerate(configurations):
                finals = np.array(list(group.finals(config).values()))
                ci = mean_ci(finals)
                pos = x - 0.4 + width * (s + 0.5)
                ax.bar(
                    pos,
                    ci.mean,
                    width * 0.9,
                    color=style.colour,
                    alpha=0.75,
                    hatch=style.hatch,
                    edgecolor="white",
                    label=f"{label} ({n_text(ci.n)})" if x == 0 else None,
                )
                if ci.n >= MIN_UNITS:  # fewer: the seeds' dots say more than a t = 12.7 bar
                    ax.errorbar(pos, ci.mean, yerr=ci.half_width, color="black", capsize=4, lw=1.2)
                    shown_values += [ci.low, ci.high]
                jitter = rng.uniform(-0.2, 0.2, finals.size) * width
                ax.scatter(
                    pos + jitter,
                    finals,
                    s=8,
                    color="black",
                    alpha=0.6,
                    zorder=4,
                    lw=0,
                    label="one seed" if (x == 0 and s == 0) else None,
                )
        run = members[0].first
        for x, config in enumerate(configurations):
            bound = config_bound(run, config)
            if np.isfinite(bound):
                ax.hlines(
                    bound,
                    x - 0.45,
                    x + 0.45,
                    color=BOUND_COLOUR,
                    ls="--",
                    lw=1.0,
                    label="log(free area)" if x == 0 else None,
                )
        # Limits from the bars, their error bars, the seed dots and the bounds.
        shown_values += (
            [p.get_height() for p in ax.patches]
            + [float(v) for c in ax.collections for v in np.asarray(c.get_offsets())[:, 1]]
            + [config_bound(run, c) for c in configurations]
        )
        ticks = ["average"] + [f"config {c}\n{names[c]}" for c in configurations[1:]]
        ax.set_xticks(range(len(configurations)), ticks)
        ax.set_ylabel("final entropy (nats)")
        ax.set_title(f"wind {format_wind(wind)}" if several else "")
        ax.grid(axis="y", alpha=0.3)
    # One range for every wind, as the panels share their y-axis.
    finite = np.array([v for v in shown_values if np.isfinite(v)])
    pad = max(0.15 * float(finite.max() - finite.min()), 0.25)
    for ax in axes.ravel():
        ax.set_ylim(finite.min() - pad, finite.max() + pad)
    for j in range(len(winds), rows * cols):
        axes[j // cols, j % cols].set_axis_off()
    compared = " vs ".join(styles)
    fig.suptitle(f"{env}: entropy at the end of training {spread_title(groups)}")
    _legend(fig, axes)
    path = save(fig, out_dir / f"{env}_final_entropy_bars.png")
    shown = "the average over configurations and " + (
        "each configuration"
        if len(configurations) == len(names) + 1
        else "configuration 0 (the hardest)"
    )
    caption = (
        f"Final entropy (nats; per seed the mean over the last 10% of epochs) of {compared}: "
        f"{shown}. Bars: mean over seeds; {spread_text(groups, 'error bars', 'no error bars')}. "
        "Dots: individual seeds. Dashed: log(free area), the entropy of a uniform visitation "
        "(weighted by p_M for the average)."
    )
    return [
        FigureRecord(
            path,
            f"{env}: final entropy per configuration",
            caption,
            THESIS_FIGURES.get((env, "bars"), ""),
            env,
        )
    ]


def entropy_against_wind(env: str, groups: list[Group], out_dir: Path) -> list[FigureRecord]:
    """Final average entropy against the wind force, one line per algorithm (5.10)."""
    styles = series_styles(groups)
    winds = winds_of(groups)
    fig = new_figure(5.5, 3.8)
    ax = fig.subplots()
    span = (max(winds) - min(winds)) or 1.0
    for s, (label, style) in enumerate(styles.items()):
        xs, means, halves, ns = [], [], [], []
        for group in (g for g in groups if g.label == label):
            ci = mean_ci(list(group.finals().values()))
            xs.append(group.wind)
            means.append(ci.mean)
            halves.append(ci.half_width)
            ns.append(ci.n)
        offset = (s - (len(styles) - 1) / 2) * 0.01 * span  # keep error bars apart
        order = np.argsort(xs)
        x = np.array(xs)[order] + offset
        # Under MIN_UNITS seeds the seeds themselves, not a t = 12.7 bar.
        few = np.array(ns)[order] < MIN_UNITS
        for group in (g for g in groups if g.label == label and len(g.runs) < MIN_UNITS):
            finals = np.array(list(group.finals().values()))
            ax.scatter(np.full(finals.size, group.wind + offset), finals, s=10,
                       color=style.colour, alpha=0.6, lw=0, zorder=3)  # fmt: skip
        ax.errorbar(
            x,
            np.array(means)[order],
            yerr=np.where(few, 0.0, np.nan_to_num(np.array(halves)[order])),
            color=style.colour,
            ls=style.linestyle,
            marker="o",
            capsize=4,
            label=f"{label} (n={min(ns)}–{max(ns)})"
            if min(ns) != max(ns)
            else f"{label} (n={ns[0]})",
        )
    draw_bound(ax, average_bound(groups[0].first))
    ax.set_xticks(winds, [format_wind(w) for w in winds])
    ax.set_xlabel("wind force")
    ax.set_ylabel("final average entropy (nats)")
    ax.grid(alpha=0.3)
    compared = " vs ".join(styles)
    ax.set_title(f"{env}: entropy at convergence vs wind force", fontsize=11)
    ax.legend(fontsize=8)
    path = save(fig, out_dir / f"{env}_entropy_vs_wind.png")
    caption = (
        f"Average entropy at convergence (nats; per seed the mean over the last 10% of epochs) "
        f"against the wind force, {compared}. Markers: mean over seeds; "
        f"{spread_text(groups, 'error bars', 'small dots: each seed')}. Dashed: log(free area) "
        "weighted by p_M."
    )
    return [
        FigureRecord(
            path,
            f"{env}: entropy against wind force",
            caption,
            THESIS_FIGURES.get((env, "wind"), ""),
            env,
        )
    ]


# -------------------------------------------------------------------------- heatmaps and paths
def per_wind(
    env: str, groups: list[Group], name: str
) -> Iterator[tuple[float, list[Group], str, str]]:
    """For each wind of ``groups``: the wind, its groups, the figure's title and file name
    (the wind is named in both only when the groups have several)."""
    winds = winds_of(groups)
    several = len(winds) > 1
    for wind in winds:
        tag = wind_tag(wind, several)
        yield (
            wind,
            at_wind(groups, wind),
            f"{env}{wind_title(wind, several)}",
            f"{env}{tag}_{name}.png",
        )


def aggregates_figure(env: str, groups: list[Group], out_dir: Path) -> list[FigureRecord]:
    """rliable's IQM and mean and the performance profile of the final entropies, per wind."""
    records = []
    styles = series_styles(groups)  # the env's: a group's colour is the same in every figure
    for _, members, title, name in per_wind(env, groups, "aggregates"):
        path = out_dir / name
        draw_aggregates(members, {k: s.colour for k, s in styles.items()}, title, path)
        caption = (
            "rliable's aggregates of the final entropies (Agarwal et al., 2021), a score being one "
            "seed's final entropy in one configuration. Left: interquartile mean (IQM) and mean of "
            f"all seed x configuration scores with 95% intervals by a {AGGREGATES_METHOD}. Right: "
            "performance profile, the share of scores above each entropy, with pointwise "
            "intervals. The probability of improvement of each pair is in differences.csv "
            f"(p_improvement) and the table below. Seeds: {seeds_text(members)}."
        )
        records.append(FigureRecord(path, f"{title}: aggregates over seeds", caption, "", env))
    return records


def diagnostics_figure(env: str, groups: list[Group], out_dir: Path) -> list[FigureRecord]:
    """Drops and the exact against the one-step KL, for groups run with diagnostics=true."""
    records = []
    for _, at, title, name in per_wind(env, groups, "diagnostics"):
        members = diagnosed(at)
        if not members:
            continue
        styles = series_styles(groups)  # the env's: a group's colour is the same in every figure
        path = out_dir / name
        draw_diagnostics(members, styles, title, path)
        caption = (
            "Runs made with diagnostics=true. Top left: the exact KL of each epoch's accepted "
            "update (likelihoods recomputed over whole histories) over the one-step KL the "
            "gradient's likelihoods give (eq. 2.8), per seed and their median; 1 for a "
            f"Markovian policy. Top right: single-epoch falls of more than {DROP_NATS:g} nat in "
            f"one configuration's entropy from epoch {DROP_FROM} on, per seed. Bottom left: "
            "each epoch's largest fall against the KL ratio of the update before it. Bottom "
            "right: the share of action components past the clip. drops.csv lists the drops "
            f"and the median ratios before and away from them. Seeds: {seeds_text(members)}."
        )
        records.append(FigureRecord(path, f"{title}: diagnostics", caption, "", env))
    return records


def heatmaps(env: str, groups: list[Group], out_dir: Path) -> list[FigureRecord]:
    """Log visitation probability of the final policies, one figure per wind (5.3, 5.8, 5.11)."""
    records = []
    for wind, at, title, name in per_wind(env, groups, "heatmaps"):
        members = [g for g in at if g.representative().positions]
        if not members:
            continue
        world = load_world(env, wind)
        names = members[0].configuration_names
        chosen = [(g, g.representative()) for g in members]
        rows = [
            (f"{g.label}: seed {run.seed} ({_median_of(len(g.runs))})", run.positions)
            for g, run in chosen
        ]
        cols = min(len(names), 5)
        blocks = len(rows) * math.ceil(len(names) / cols)
        fig = new_figure(2.5 * cols + 1.2, 2.75 * blocks + 0.5)
        heatmap_grid(fig, world, rows, names)
        some = next(iter(chosen[0][1].positions.values()))
        fig.suptitle(
            f"{title}: log probability of state visitation\n"
            f"{some.shape[0]} trajectories of T={some.shape[1] - 1} steps per configuration, "
            "dashed: start area"
        )
        path = save(fig, out_dir / name)
        who = "; ".join(f"{g.label}: seed {run.seed} of {len(g.runs)}" for g, run in chosen)
        caption = (
            f"Log probability of state visitation (2-D histogram over the arena, one shared colour "
            f"scale; white: never visited; grey: walls) of {some.shape[0]} fresh trajectories of "
            f"{some.shape[1] - 1} steps per configuration, collected with the final policy of one "
            f"representative seed per algorithm (the seed with the median final entropy): {who}. "
            "Red dashed box: the start area."
        )
        records.append(
            FigureRecord(
                path,
                f"{title}: visitation heatmaps",
                caption,
                THESIS_FIGURES.get((env, "heatmaps"), ""),
                env,
            )
        )
    return records


def trajectories(env: str, groups: list[Group], out_dir: Path) -> list[FigureRecord]:
    """Ten trajectories per configuration for a few seeds of each group (5.5, 5.6)."""
    records = []
    several = len(winds_of(groups)) > 1
    for group in groups:
        runs = [r for r in group.runs if r.positions]
        if not runs:
            continue
        first = group.representative()
        runs = [first] + [r for r in runs if r is not first][: MAX_TRAJECTORY_SEEDS - 1]
        world = load_world(env, group.wind)
        names = group.configuration_names
        cols = min(len(names), 5)
        blocks = len(runs) * math.ceil(len(names) / cols)
        fig = new_figure(2.5 * cols + 1.0, 2.75 * blocks + 0.5)
        trajectory_grid(fig, world, [(f"seed {r.seed}", r.positions) for r in runs], names)
        steps = next(iter(first.positions.values())).shape[1] - 1
        fig.suptitle(
            f"{env}{wind_title(group.wind, several)}: {group.label}\n{TRAJECTORIES} "
            f"trajectories of T={steps} steps per configuration, coloured by step",
            fontsize=10,
        )
        name = f"{env}{wind_tag(group.wind, several)}_trajectories_{slug(group.label)}.png"
        path = save(fig, out_dir / name)
        caption = (
            f"{TRAJECTORIES} trajectories of the final {group.label} policy in each "
            f"configuration (columns) for seed{'s' if len(runs) > 1 else ''} "
            f"{', '.join(str(r.seed) for r in runs)} (rows; {_seeds(len(group.runs))} in all; "
            "the first has the median final entropy), drawn through every step and coloured by "
            "the step (colour bar); a white circle marks each start, a black square each end; "
            "grey: walls." + scale_text([group])
        )
        thesis = THESIS_FIGURES.get((env, "trajectories", group.algo), "")
        records.append(
            FigureRecord(path, f"{env}: trajectories of {group.label}", caption, thesis, env)
        )
    return records


# ------------------------------------------------------------------------------- fine-tuning
def finetune_frame(runs: list[Run]) -> pd.DataFrame:
    """All fine-tuning returns, one row per (run, seed, target, config, epoch), with the
    independent unit of each (the pre-training run, or the fine-tuning run from scratch) and the
    bounds of its return."""
    frames = []
    for run in runs:
        if run.finetune is None:
            continue
        frame = run.finetune.copy()
        frame["env"] = run.env
        frame["wind"] = run.wind
        frame["run"] = str(run.path)
        frame["pretraining_run"] = run.pretraining_run
        frame["unit"] = run.independent_unit
        frame["bound_low"], frame["bound_high"] = run.return_bounds
        frames.append(frame)
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


@dataclass(frozen=True)
class FinetuneCurves:
    """The return curves of one initialisation in one configuration."""

    epochs: np.ndarray  # (n_epochs,)
    curves: np.ndarray  # (n_curves, n_epochs): one per (run, seed, target)
    units: np.ndarray  # (n_curves,): the independent unit each curve is nested in
    bounds: tuple[float, float]  # of a return: every run's range together

    def unit_curves(self) -> np.ndarray:
        """Each unit's mean curve over its targets and seeds, (n_units, n_epochs)."""
        frame = pd.DataFrame(self.curves)
        return frame.groupby(self.units, sort=False).mean().to_numpy(float)


def finetune_curves(frame: pd.DataFrame) -> dict[tuple[str, int], FinetuneCurves]:
    """(algo_init, config) -> its curves."""
    out = {}
    for (init, config), part in frame.groupby(["algo_init", "config"], sort=False):
        table = part.pivot_table(
            index="epoch", columns=["unit", "run", "seed", "target"], values="return"
        )
        out[(str(init), int(config))] = FinetuneCurves(
            table.index.to_numpy(float),
            table.to_numpy(float).T,
            table.columns.get_level_values("unit").to_numpy(),
            (float(part["bound_low"].min()), float(part["bound_high"].max())),
        )
    return out


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


def _axis_for(bounds: tuple[float, float]) -> tuple[float, float] | None:
    """y-limits a little outside a bounded quantity's range (None: unbounded, autoscale)."""
    low, high = bounds
    if not (np.isfinite(low) and np.isfinite(high)):
        return None
    pad = 0.05 * (high - low)
    return low - pad, high + pad


def _init_epochs(frame: pd.DataFrame, init: str) -> str:
    """ ", from epoch 75": the pre-training epochs of the policies the fine-tunings of ``init``
    started from (finetune.csv's init_epoch; "" from scratch and for runs that predate it)."""
    if init == "scratch" or "init_epoch" not in frame:
        return ""
    epochs = frame.loc[frame["algo_init"] == init, "init_epoch"].dropna().unique()
    return f", from epoch {', '.join(str(int(e)) for e in sorted(epochs))}" if len(epochs) else ""


def finetune_returns(
    env: str, frame: pd.DataFrame, names: list[str], runs: list[Run], out_dir: Path
) -> list[FigureRecord]:
    """Fine-tuning returns per epoch, per configuration, per initialisation (5.9)."""
    records = []
    # Worlds without a wind (slope, multigrid) record none: one group for them.
    winds = sorted(frame["wind"].dropna().unique()) + ([None] if frame["wind"].isna().any() else [])
    several = len(winds) > 1
    order = [*ALGO_ORDER, SCRATCH.name]
    for wind in winds:
        part = frame[frame["wind"].isna()] if wind is None else frame[frame["wind"] == wind]
        curves = finetune_curves(part)
        configurations = sorted({c for _, c in curves})
        inits = sorted(
            {i for i, _ in curves}, key=lambda i: (order.index(i) if i in order else 9, i)
        )
        fig = new_figure(4.6 * len(configurations), 3.6)
        axes = fig.subplots(1, len(configurations), squeeze=False, sharey=True)[0]
        for ax, config in zip(axes, configurations, strict=True):
            for init in inits:
                if (init, config) not in curves:
                    continue
                drawn = curves[(init, config)]
                units = drawn.unit_curves()
                name = "TRPO from scratch" if init == "scratch" else f"{algo_label(init)} init"
                label = f"{name}{_init_epochs(part, init)} (n={units.shape[0]})"
                colour = algo_colour(init)
                plot_units(ax, drawn.epochs, units, colour, "-", label, drawn.bounds)
            title = names[config] if config < len(names) else f"{config}"
            ax.set_title(f"config {config}: {title}", fontsize=10)
            limits = _axis_for((part["bound_low"].min(), part["bound_high"].max()))
            if limits is not None:  # a goal task's return is a share of episodes: [0, 1]
                ax.set_ylim(*limits)
            ax.set_xlabel("fine-tuning epoch")
            ax.set_ylabel("average return")
            ax.grid(alpha=0.3)
        fig.suptitle(f"{env}{wind_title(wind, several)}: TRPO fine-tuning on goal reaching")
        _legend(fig, axes)
        path = save(fig, out_dir / f"{env}{wind_tag(wind, several)}_finetune_returns.png")
        who = "; ".join(f"{algo_label(i)}: {units_text(part, i)}" for i in inits)
        low, high = part["bound_low"].min(), part["bound_high"].max()
        cut = (
            f", cut to the return's range [{low:g}, {high:g}]"
            if np.isfinite([low, high]).all()
            else ""
        )
        caption = (
            "Average return per epoch of TRPO on a sparse goal-reaching task, per configuration, "
            "started from a pre-trained policy or from scratch. The unit of independence is the "
            "pre-training run (from scratch, the fine-tuning run): its targets and fine-tuning "
            "seeds are nested in it. Line: mean over the units of each unit's mean curve; with "
            f"fewer than {MIN_UNITS} units, thin lines: each unit's curve; from {MIN_UNITS} on, "
            f"band: Student-t 95% CI over the units{cut} ({who})."
            + finetune_scale([r for r in runs if r.env == env])
        )
        records.append(
            FigureRecord(
                path,
                f"{env}: fine-tuning returns",
                caption,
                THESIS_FIGURES.get((env, "finetune"), ""),
                env,
            )
        )
    return records


# ------------------------------------------------------------------------------------ all
def make_figures(
    groups: list[Group], finetune_runs: list[Run], out_dir: Path
) -> list[FigureRecord]:
    """Every figure the runs allow, in thesis order within each environment."""
    out_dir = Path(out_dir)
    records: list[FigureRecord] = []
    envs = list(dict.fromkeys([g.env for g in groups] + [r.env for r in finetune_runs]))
    for env in envs:
        members = [g for g in groups if g.env == env]
        if members:
            drawn = []
            drawn += entropy_curves(env, members, out_dir)
            drawn += entropy_curves_by_config(env, members, out_dir)
            drawn += final_entropy_bars(env, members, out_dir)
            drawn += aggregates_figure(env, members, out_dir)
            drawn += diagnostics_figure(env, members, out_dir)
            if len(winds_of(members)) > 1:
                drawn += entropy_against_wind(env, members, out_dir)
            drawn += heatmaps(env, members, out_dir)
            for record in drawn:
                record.caption += scale_text(members)
            records += drawn + trajectories(env, members, out_dir)
        runs = [r for r in finetune_runs if r.env == env]
        frame = finetune_frame(runs)
        if not frame.empty:
            names = next((r.configuration_names for r in runs), [])
            records += finetune_returns(env, frame, names, runs, out_dir)
    return records
