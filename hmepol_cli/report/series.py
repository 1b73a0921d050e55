"""How the report draws a series: its style (a colour of its own, a dash and hatching for an
algorithm's variants), its mean with what the number of units allows beside it (from MIN_UNITS
on the Student-t 95% band, under it each unit's own curve), the entropy bound, one y-range that
holds every line and band, and one legend for a figure.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from matplotlib.collections import LineCollection, PolyCollection

from hmepol_cli.plots import BOUND_COLOUR, LINESTYLES, OTHER_COLOURS, algo_colour
from hmepol_cli.report.runs import Group, algo_label
from hmepol_cli.report.stats import MIN_UNITS, UNBOUNDED, curve_ci

HATCHES = ("", "//", "..", "xx")


@dataclass(frozen=True)
class Style:
    """How one series is drawn, the same in every figure of its env."""

    colour: str
    linestyle: object
    hatch: str  # for bars: the second series of one algorithm is hatched
    label: str


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


def draw_bound(ax, value: float, label: bool = True) -> None:
    """The entropy bound (log of the free area) as a dashed line; nothing when it is unknown."""
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
