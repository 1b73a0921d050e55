"""The report's figures (thesis ch. 5 and appendix A), each drawn only when the runs allow it.

Every figure function takes the groups of one environment and returns :class:`FigureRecord`s
(the PNG path, its title and caption, the thesis figure it reproduces). This module draws: the
numbers come from frames.py, the words (legends, captions) from captions.py, and how a series
and its spread look from series.py. Curves and bars are the mean over the independent units
(seeds; for fine-tuning, pre-training runs), with what their number allows beside it: from
MIN_UNITS on, the Student-t 95% confidence interval; with fewer, each unit's own curve or dot.
"""

from __future__ import annotations

import hashlib
import math
import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from hmepol_cli.plots import (
    BOUND_COLOUR,
    TRAJECTORIES,
    WorldMap,
    algo_colour,
    heatmap_grid,
    new_figure,
    save,
    trajectory_grid,
)
from hmepol_cli.report import captions
from hmepol_cli.report.aggregate_figure import draw_aggregates
from hmepol_cli.report.captions import (
    THESIS_FIGURES,
    init_epochs_text,
    median_of,
    n_text,
    scale_text,
    spread_title,
    wind_title,
)
from hmepol_cli.report.diagnostics import diagnosed, draw_diagnostics, has_steps
from hmepol_cli.report.frames import (
    at_wind,
    average_bound,
    config_bound,
    epochs_label,
    final_windows,
    finetune_curves,
    finetune_frame,
    finetune_winds,
    ordered_inits,
    return_range,
    wind_finals,
    winds_of,
)
from hmepol_cli.report.rules import old_rules, old_rules_text
from hmepol_cli.report.runs import Group, Run, algo_label, format_wind
from hmepol_cli.report.series import (
    Style,
    draw_bound,
    figure_legend,
    fit_to_lines,
    plot_units,
    series_styles,
)
from hmepol_cli.report.stats import MIN_UNITS, mean_ci

MAX_CONFIG_BARS = 5  # more configurations than this (multigrid): bars for average and config 0
MAX_TRAJECTORY_SEEDS = 3


@dataclass
class FigureRecord:
    path: Path
    title: str
    caption: str
    thesis: str  # the thesis figure it reproduces ("" when it has no counterpart)
    env: str


# ------------------------------------------------------------------------------------- helpers
def world_map_of(runs: Iterable[Run]) -> WorldMap | None:
    """The map of these runs' world (one env) that their run.json records; None when none
    records one (a world without a map, or runs made before run.json recorded it: their maps
    are drawn without walls)."""
    return next((run.world_map for run in runs if run.world_map is not None), None)


def slug(text: str, limit: int = 80) -> str:
    """A file-name part for a label; long labels (many differing keys) are cut and hashed, so
    names stay unique and within every filesystem's limit."""
    text = text.replace("α", "alpha").lower()
    name = re.sub(r"[^a-z0-9]+", "-", text).strip("-")
    if len(name) <= limit:
        return name
    digest = hashlib.sha1(name.encode()).hexdigest()[:10]
    return f"{name[: limit - 11]}-{digest}"


def wind_tag(wind: float, several: bool) -> str:
    return f"_wind{format_wind(wind)}" if several else ""


def rules_title(groups: list[Group]) -> str:
    """A title's second line naming the old rules, where every group ran with the same ones."""
    made = {tuple(old_rules(g).items()) for g in groups}
    if made == {()}:
        return ""
    if len(made) == 1:
        return (
            "\nmade with the old rules (" + ", ".join(f"{k}={v}" for k, v in next(iter(made))) + ")"
        )
    return "\nsome groups made with the old rules (caption)"


def shown_labels(styles: dict[str, Style]) -> list[str]:
    """The series' names as the legends show them."""
    return [style.label for style in styles.values()]


def draw_curve(ax, group: Group, style: Style, config: int | None, sampled: bool = False) -> None:
    """``sampled``: the group's seeds do not all draw each configuration every epoch, so a
    point's n is at most the group's (one seed: its gaps are the epochs it did not draw)."""
    epochs, curves = group.curves(config)
    if curves.size == 0:
        return
    n = len(group.runs)
    label = f"{style.label} ({n_text(n)})"
    if sampled and n > 1:
        label = f"{style.label} (n≤{n} per epoch{', each seed drawn' if n < MIN_UNITS else ''})"
    plot_units(ax, epochs, curves, style.colour, style.linestyle, label)


def sampled_configurations(group: Group) -> bool:
    """Whether some epoch of some configuration's curve lacks one of the group's seeds (the
    multigrid samples configurations each epoch)."""
    for config in range(group.n_configurations):
        _, curves = group.curves(config)
        if curves.size and (np.isfinite(curves).sum(axis=0) < len(group.runs)).any():
            return True
    return False


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
    fig.suptitle(f"{env}: average entropy per epoch\n{spread_title(groups)}{rules_title(groups)}")
    figure_legend(fig, axes)
    path = save(fig, out_dir / f"{env}_entropy_epochs.png")
    caption = captions.entropy_curves_caption(groups, shown_labels(styles), winds)
    thesis = THESIS_FIGURES.get((env, "curves"), "")
    return [FigureRecord(path, f"{env}: average entropy per epoch", caption, thesis, env)]


def entropy_curves_by_config(env: str, groups: list[Group], out_dir: Path) -> list[FigureRecord]:
    """Entropy per epoch in each configuration, one panel per (wind, configuration) (A.1b, A.1c)."""
    styles = series_styles(groups)
    sampled = {g.label: sampled_configurations(g) for g in groups}
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
                draw_curve(ax, group, styles[group.label], c, sampled[group.label])
            draw_bound(ax, config_bound(members[0].first, c), "log(free area) of the configuration")
            fit_to_lines(ax)
            ax.set_title(f"config {c}: {names[c]}{wind_title(wind, several)}", fontsize=10)
            ax.set_xlabel("epoch")
            if c % cols == 0:
                ax.set_ylabel("entropy (nats)")
            ax.grid(alpha=0.3)
    fig.suptitle(
        f"{env}: entropy per epoch in each configuration\n{spread_title(groups)}"
        + rules_title(groups)
    )
    figure_legend(fig, axes)
    path = save(fig, out_dir / f"{env}_entropy_epochs_by_config.png")
    caption = captions.entropy_by_config_caption(
        groups, shown_labels(styles), any(sampled.values())
    )
    thesis = THESIS_FIGURES.get((env, "curves_by_config"), "")
    return [FigureRecord(path, f"{env}: entropy per epoch per configuration", caption, thesis, env)]


# ------------------------------------------------------------------------ final entropy bars
def final_entropy_bars(env: str, groups: list[Group], out_dir: Path) -> list[FigureRecord]:
    """Final entropy as bars: average and per configuration, one panel per wind (5.2, 5.7, 5.12)."""
    styles = series_styles(groups)
    winds = winds_of(groups)
    several = len(winds) > 1
    windows = final_windows(groups, winds)
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
                    label=f"{style.label} ({n_text(ci.n)})" if x == 0 else None,
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
        cut = f" ({epochs_label(windows[wind])})" if windows else ""  # --unfinished cut some
        ax.set_title(f"wind {format_wind(wind)}{cut}" if several else "")
        ax.grid(axis="y", alpha=0.3)
    # One range for every wind, as the panels share their y-axis.
    finite = np.array([v for v in shown_values if np.isfinite(v)])
    pad = max(0.15 * float(finite.max() - finite.min()), 0.25)
    for ax in axes.ravel():
        ax.set_ylim(finite.min() - pad, finite.max() + pad)
    for j in range(len(winds), rows * cols):
        axes[j // cols, j % cols].set_axis_off()
    fig.suptitle(
        f"{env}: final entropy, last 10% of epochs {spread_title(groups)}{rules_title(groups)}"
    )
    figure_legend(fig, axes)
    path = save(fig, out_dir / f"{env}_final_entropy_bars.png")
    every_config = len(configurations) == len(names) + 1
    caption = captions.final_bars_caption(groups, shown_labels(styles), every_config)
    thesis = THESIS_FIGURES.get((env, "bars"), "")
    return [FigureRecord(path, f"{env}: final entropy per configuration", caption, thesis, env)]


def entropy_against_wind(env: str, groups: list[Group], out_dir: Path) -> list[FigureRecord]:
    """Final average entropy against the wind force, one line per algorithm (5.10)."""
    styles = series_styles(groups)
    winds = winds_of(groups)
    fig = new_figure(5.5, 4.2)
    ax = fig.subplots()
    span = (max(winds) - min(winds)) or 1.0
    for s, (label, style) in enumerate(styles.items()):
        finals_at = wind_finals(groups, label)
        ns = finals_at.n
        offset = (s - (len(styles) - 1) / 2) * 0.01 * span  # keep error bars apart
        # Under MIN_UNITS seeds the seeds themselves, not a t = 12.7 bar.
        few = ns < MIN_UNITS
        for group in (g for g in groups if g.label == label and len(g.runs) < MIN_UNITS):
            finals = np.array(list(group.finals().values()))
            ax.scatter(np.full(finals.size, group.wind + offset), finals, s=10,
                       color=style.colour, alpha=0.6, lw=0, zorder=3)  # fmt: skip
        ax.errorbar(
            finals_at.wind + offset,
            finals_at.mean,
            yerr=np.where(few, 0.0, np.nan_to_num(finals_at.half_width)),
            color=style.colour,
            ls=style.linestyle,
            marker="o",
            capsize=4,
            label=f"{style.label} (n={ns.min()}–{ns.max()})"
            if ns.min() != ns.max()
            else f"{style.label} (n={ns[0]})",
        )
    bound = average_bound(groups[0].first)
    draw_bound(ax, bound)
    low, high = ax.get_ylim()
    if np.isfinite(bound) and bound > high - 0.03 * (high - low):  # off the frame's top edge
        ax.set_ylim(low, bound + 0.06 * (high - low))
    windows = final_windows(groups, winds)  # wind by wind, when --unfinished cut some
    ticks = [format_wind(w) + (f"\n{epochs_label(windows[w])}" if windows else "") for w in winds]
    ax.set_xticks(winds, ticks, fontsize=8 if windows else None)
    ax.set_xlabel("wind force")
    ax.set_ylabel("final average entropy (nats)")
    ax.grid(alpha=0.3)
    window = "last 10% of each wind's epochs, under its tick" if windows else "last 10% of epochs"
    ax.set_title(f"{env}: final entropy vs wind force\n({window})", fontsize=11)
    figure_legend(fig, ax)  # below the axes: inside, it hid the error bars it fell on
    path = save(fig, out_dir / f"{env}_entropy_vs_wind.png")
    caption = captions.entropy_against_wind_caption(groups, shown_labels(styles), windows)
    thesis = THESIS_FIGURES.get((env, "wind"), "")
    return [FigureRecord(path, f"{env}: entropy against wind force", caption, thesis, env)]


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
        draw_aggregates(members, styles, title, path)
        caption = captions.aggregates_caption(members)
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
        without = [styles[g.label].label for g in members if not any(map(has_steps, g.runs))]
        caption = captions.diagnostics_caption(members, without)
        records.append(FigureRecord(path, f"{title}: diagnostics", caption, "", env))
    return records


def heatmaps(env: str, groups: list[Group], out_dir: Path) -> list[FigureRecord]:
    """Log visitation probability of the final policies, one figure per wind (5.3, 5.8, 5.11)."""
    records = []
    styles = series_styles(groups)
    for _, at, title, name in per_wind(env, groups, "heatmaps"):
        members = [g for g in at if g.representative().positions]
        if not members:
            continue
        world_map = world_map_of(run for g in members for run in g.runs)
        names = members[0].configuration_names
        chosen = [(g, g.representative()) for g in members]
        rows = [
            (f"{styles[g.label].label}: seed {run.seed} ({median_of(g)})", run.positions)
            for g, run in chosen
        ]
        cols = min(len(names), 5)
        blocks = len(rows) * math.ceil(len(names) / cols)
        fig = new_figure(2.5 * cols + 1.2, 2.75 * blocks + 0.5)
        heatmap_grid(fig, world_map, rows, names)
        some = next(iter(chosen[0][1].positions.values()))
        fig.suptitle(
            f"{title}: log probability of state visitation\n"
            f"{some.shape[0]} trajectories of T={some.shape[1] - 1} steps per configuration, "
            "dashed: start area"
        )
        path = save(fig, out_dir / name)
        caption = captions.heatmaps_caption(chosen, some.shape[0], some.shape[1] - 1)
        thesis = THESIS_FIGURES.get((env, "heatmaps"), "")
        records.append(FigureRecord(path, f"{title}: visitation heatmaps", caption, thesis, env))
    return records


def trajectories(env: str, groups: list[Group], out_dir: Path) -> list[FigureRecord]:
    """Ten trajectories per configuration for a few seeds of each group (5.5, 5.6)."""
    records = []
    styles = series_styles(groups)
    several = len(winds_of(groups)) > 1
    for group in groups:
        runs = [r for r in group.runs if r.positions]
        if not runs:
            continue
        first = group.representative()
        runs = [first] + [r for r in runs if r is not first][: MAX_TRAJECTORY_SEEDS - 1]
        world_map = world_map_of(group.runs)
        names = group.configuration_names
        cols = min(len(names), 5)
        blocks = len(runs) * math.ceil(len(names) / cols)
        fig = new_figure(2.5 * cols + 1.0, 2.75 * blocks + 0.5)
        trajectory_grid(fig, world_map, [(f"seed {r.seed}", r.positions) for r in runs], names)
        steps = next(iter(first.positions.values())).shape[1] - 1
        fig.suptitle(
            f"{env}{wind_title(group.wind, several)}: {styles[group.label].label}\n{TRAJECTORIES} "
            f"trajectories of T={steps} steps per configuration, coloured by step",
            fontsize=10,
        )
        name = f"{env}{wind_tag(group.wind, several)}_trajectories_{slug(group.label)}.png"
        path = save(fig, out_dir / name)
        caption = captions.trajectories_caption(group, runs)
        thesis = THESIS_FIGURES.get((env, "trajectories", group.algo), "")
        records.append(
            FigureRecord(
                path, f"{env}: trajectories of {styles[group.label].label}", caption, thesis, env
            )
        )
    return records


# ------------------------------------------------------------------------------- fine-tuning
def _axis_for(bounds: tuple[float, float]) -> tuple[float, float] | None:
    """y-limits a little outside a bounded quantity's range (None: unbounded, autoscale)."""
    low, high = bounds
    if not (np.isfinite(low) and np.isfinite(high)):
        return None
    pad = 0.05 * (high - low)
    return low - pad, high + pad


def finetune_returns(
    env: str, frame: pd.DataFrame, names: list[str], runs: list[Run], out_dir: Path
) -> list[FigureRecord]:
    """Fine-tuning returns per epoch, per configuration, per initialisation (5.9)."""
    records = []
    parts = finetune_winds(frame)
    several = len(parts) > 1
    for wind, part in parts:
        curves = finetune_curves(part)
        configurations = sorted({c for _, c in curves})
        inits = ordered_inits(curves)
        fig = new_figure(4.6 * len(configurations), 3.6)
        axes = fig.subplots(1, len(configurations), squeeze=False, sharey=True)[0]
        for ax, config in zip(axes, configurations, strict=True):
            for init in inits:
                if (init, config) not in curves:
                    continue
                drawn = curves[(init, config)]
                units = drawn.unit_curves()
                name = "TRPO from scratch" if init == "scratch" else f"{algo_label(init)} init"
                unit = "fine-tuning run" if init == "scratch" else "pre-training run"
                n = units.shape[0]
                label = (
                    f"{name}{init_epochs_text(part, init)} (n={n} {unit}{'s' if n != 1 else ''})"
                )
                colour = algo_colour(init)
                plot_units(ax, drawn.epochs, units, colour, "-", label, drawn.bounds)
            title = names[config] if config < len(names) else f"{config}"
            ax.set_title(f"config {config}: {title}", fontsize=10)
            limits = _axis_for(return_range(part))
            if limits is not None:  # a goal task's return is a share of episodes: [0, 1]
                ax.set_ylim(*limits)
            ax.set_xlabel("fine-tuning epoch")
            ax.set_ylabel("average return")
            ax.grid(alpha=0.3)
        fig.suptitle(f"{env}{wind_title(wind, several)}: TRPO fine-tuning on goal reaching")
        figure_legend(fig, axes)
        path = save(fig, out_dir / f"{env}{wind_tag(wind, several)}_finetune_returns.png")
        caption = captions.finetune_caption(part, inits, [r for r in runs if r.env == env])
        thesis = THESIS_FIGURES.get((env, "finetune"), "")
        records.append(FigureRecord(path, f"{env}: fine-tuning returns", caption, thesis, env))
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
            rules = old_rules_text(members)
            for record in drawn:
                record.caption += scale_text(members) + (f" {rules}" if rules else "")
            paths = trajectories(env, members, out_dir)
            for record in paths:  # a trajectory's world follows its rules too
                record.caption += f" {rules}" if rules else ""
            records += drawn + paths
        runs = [r for r in finetune_runs if r.env == env]
        frame = finetune_frame(runs)
        if not frame.empty:
            names = next((r.configuration_names for r in runs), [])
            records += finetune_returns(env, frame, names, runs, out_dir)
    return records
