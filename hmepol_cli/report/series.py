"""How the report draws a series: its style (a colour of its own, a dash and hatching for an
algorithm's variants), its mean with what the number of units allows beside it (from MIN_UNITS
on the Student-t 95% band, under it each unit's own curve), the entropy bound, one y-range that
holds every line and band, and one legend for a figure.
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from matplotlib.collections import LineCollection, PolyCollection

from hmepol_cli.plots import BOUND_COLOUR, LINESTYLES, OTHER_COLOURS, algo_colour
from hmepol_cli.report.rules import thesis_settings
from hmepol_cli.report.runs import Group, algo_label
from hmepol_cli.report.stats import MIN_UNITS, UNBOUNDED, curve_ci

HATCHES = ("", "//", "..", "xx")
VARIANT_COLOURS = OTHER_COLOURS  # none is an algorithm's


@dataclass(frozen=True)
class Style:
    """How one series is drawn, the same in every figure of its env."""

    colour: str
    linestyle: object
    hatch: str  # for bars: the second series of one algorithm is hatched
    label: str


def variant_colour_order(label: str) -> list[str]:
    """The spare colours in the order a variant labelled ``label`` tries them: its first choice
    comes from a hash of the label (not Python's salted hash), so one variant has one colour in
    every report."""
    start = int(hashlib.sha1(label.encode()).hexdigest(), 16) % len(VARIANT_COLOURS)
    return [
        VARIANT_COLOURS[(start + i) % len(VARIANT_COLOURS)] for i in range(len(VARIANT_COLOURS))
    ]


def series_styles(groups: Iterable[Group]) -> dict[str, Style]:
    """label -> style, a colour of its own for every series, chosen by what the series is and not
    where it comes: an algorithm's main series (the one at the algorithm's own settings, else
    the one labelled by the algorithm alone) takes the algorithm's colour; a variant the first
    free colour of its own order (:func:`variant_colour_order`; variants take theirs in label
    order, so the choice does not depend on the groups' order), and a dash (and hatching on
    bars) from its label too, so that it reads as one of its algorithm's. Where an algorithm has
    several series, the one at its own settings says so in its label: "HMepol (thesis
    settings)"."""
    groups = list(dict((g.label, g) for g in groups).values())
    thesis: set[str] = set()
    for key in dict.fromkeys((g.env, repr(g.wind)) for g in groups):
        thesis |= thesis_settings([g for g in groups if (g.env, repr(g.wind)) == key])
    main: dict[str, str] = {}
    for group in groups:
        if group.label in thesis or (
            group.label == algo_label(group.algo) and group.algo not in main
        ):
            main[group.algo] = group.label
    taken = {algo_colour(a) for a in main}
    colours: dict[str, str] = {}
    for label in sorted(g.label for g in groups if g.label not in main.values()):
        colour = next((c for c in variant_colour_order(label) if c not in taken), None)
        colours[label] = colour or variant_colour_order(label)[0]  # more variants than colours
        taken.add(colours[label])
    styles: dict[str, Style] = {}
    for group in groups:
        if group.label in main.values():
            k, colour = 0, algo_colour(group.algo)
        else:
            k = 1 + int(hashlib.sha1(group.label.encode()).hexdigest(), 16) % (len(LINESTYLES) - 1)
            colour = colours[group.label]
        styles[group.label] = Style(
            colour, LINESTYLES[k], HATCHES[k % len(HATCHES)], _shown_label(group, groups, thesis)
        )
    return styles


def _shown_label(group: Group, groups: list[Group], thesis: set[str]) -> str:
    """The group's label, marked "thesis settings" where its algorithm has other series."""
    if group.label not in thesis:
        return group.label
    plain = algo_label(group.algo)
    if group.label == plain:
        return f"{plain} (thesis settings)"
    return f"{plain} (thesis settings: {group.label[len(plain) + 2 : -1]})"


def draw_bound(ax, value: float, label: str | None = "") -> None:
    """The entropy bound (log of the free area) as a dashed line; nothing when it is unknown.
    ``label``: its legend entry ("": one that gives the value; None: none). Panels that each
    have their own bound pass one label for all, so that the legend has one entry for them."""
    if np.isfinite(value):
        ax.axhline(
            value,
            color=BOUND_COLOUR,
            ls="--",
            lw=1.0,
            label=f"log(free area) = {value:.2f} nats" if label == "" else label,
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


def figure_legend(fig, axes) -> None:
    """One legend for the figure, below the panels, from the union of the panels' handles."""
    seen: dict[str, object] = {}
    for ax in np.ravel(axes):
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            seen.setdefault(label, handle)
    seen = merged_counts(seen)
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


PLAIN_COUNT = re.compile(r"(?P<name>.+) \(n=(?P<n>\d+)\)")  # a series drawn with its band


def merged_counts(entries: dict[str, object]) -> dict[str, object]:
    """One entry per series whose panels hold different numbers of seeds: "Mepol (n=4)" and
    "Mepol (n=8)" (the same style in two panels) become "Mepol (n=4–8)", in the first's place;
    any other label is kept as it is."""
    counts: dict[str, list[int]] = {}
    for label in entries:
        if match := PLAIN_COUNT.fullmatch(label):
            counts.setdefault(match["name"], []).append(int(match["n"]))
    out: dict[str, object] = {}
    for label, handle in entries.items():
        match = PLAIN_COUNT.fullmatch(label)
        if match is None or len(counts[match["name"]]) == 1:
            out[label] = handle
            continue
        ns = counts[match["name"]]
        out.setdefault(f"{match['name']} (n={min(ns)}–{max(ns)})", handle)
    return out
