"""What the seeds at hand can resolve, and how many a question needs: the columns beside every
difference of final values, and the one-line notes under each table of the report.

A difference's planning columns come from its observed spread (stats.Spread: the standard
deviation of the paired differences, or both arms' for Welch): the seeds per arm for a 95%
interval of +-0.25 and +-0.3 nats, and for 80% power against a 0.4-nat difference, the precision
the collapse questions ask of a difference of final entropies. With few seeds the spread itself
is a rough estimate, and so are the seeds it asks for.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from hmepol_cli.report.stats import (
    MAX_SEEDS,
    MIN_UNITS,
    DiffCI,
    detectable_difference,
    seeds_for_half_width,
    seeds_for_power,
    t_quantile,
)

PLANNED_HALF_WIDTHS = (0.25, 0.3)  # nats: a 95% interval of a difference this narrow
PLANNED_DIFFERENCE = 0.4  # nats: a difference to find ...
PLANNED_POWER = 0.8  # ... this often
SEEDS_COLUMN = "seeds_per_arm_"  # the planning columns' prefix
DETECTABLE_COLUMN = f"detectable_diff_power{PLANNED_POWER * 100:.0f}"


def planning_columns(d: DiffCI) -> dict[str, float]:
    """The seeds per arm each planned precision needs, and the difference the seeds at hand
    find with PLANNED_POWER."""
    columns = {
        f"{SEEDS_COLUMN}hw{h:g}": seeds_for_half_width(d.spread, h) for h in PLANNED_HALF_WIDTHS
    }
    power = f"{SEEDS_COLUMN}power{PLANNED_POWER * 100:.0f}_d{PLANNED_DIFFERENCE:g}"
    columns[power] = seeds_for_power(d.spread, PLANNED_DIFFERENCE, PLANNED_POWER)
    columns[DETECTABLE_COLUMN] = detectable_difference(d.se, d.df, PLANNED_POWER)
    return columns


def format_seeds(value: float) -> str:
    if math.isnan(value):
        return "n/a"
    return f">{MAX_SEEDS:,}" if math.isinf(value) else f"{value:.0f}"


def _span(values, digits: int = 2, plus_minus: bool = False) -> str:
    """'0.21 to 3.4' of the finite values ('n/a' when there are none)."""
    x = np.asarray(values, dtype=float)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return "n/a"
    sign = "±" if plus_minus else ""
    low, high = (f"{sign}{v:.{digits}f}" for v in (x.min(), x.max()))
    return low if low == high else f"{low} to {high}"


def _seeds_span(values) -> str:
    x = np.asarray(values, dtype=float)
    x = x[~np.isnan(x)]
    if x.size == 0:
        return "n/a"
    low, high = format_seeds(x.min()), format_seeds(x.max())
    return low if low == high else f"{low} to {high}"


def _n_text(values) -> str:
    x = pd.Series(values).dropna().astype(int)
    return "n/a" if x.empty else str(x.min()) if x.min() == x.max() else f"{x.min()}–{x.max()}"


def _means_line(table: pd.DataFrame) -> str:
    n = table["n_seeds"]
    fewest = int(n.min())
    t = f"; t = {t_quantile(fewest - 1):.2f} with {fewest} seeds" if fewest >= 2 else ""
    return (
        f"What these seeds resolve: with {_n_text(n)} seeds a group, a final entropy is known "
        f"to {_span(table['ci95_half_width'], plus_minus=True)} nats (95% t half-widths{t})."
    )


def _differences_line(table: pd.DataFrame) -> str:
    half = table["ci95_high"] - table["diff_nats"]
    needed = [
        f"±{h:g} nats {_seeds_span(table[f'{SEEDS_COLUMN}hw{h:g}'])}" for h in PLANNED_HALF_WIDTHS
    ]
    power = table[f"{SEEDS_COLUMN}power{PLANNED_POWER * 100:.0f}_d{PLANNED_DIFFERENCE:g}"]
    return (
        f"What these seeds resolve: with {_n_text(pd.concat([table['n_a'], table['n_b']]))} "
        f"seeds an arm, a difference of final entropies is known to "
        f"{_span(half, plus_minus=True)} nats, and a true difference is found with "
        f"{PLANNED_POWER:.0%} power from {_span(table[DETECTABLE_COLUMN])} nats on. Seeds an "
        f"arm needed, from the observed spread: {', '.join(needed)}, "
        f"{PLANNED_POWER:.0%} power against {PLANNED_DIFFERENCE:g} nats {_seeds_span(power)}."
    )


def _returns_line(table: pd.DataFrame) -> str:
    width = table["ci95_high"] - table["ci95_low"]
    cut = int((width < 2 * table["ci95_half_width"] - 1e-12).sum())
    return (
        f"What these units resolve: with {_n_text(table['n_units'])} independent units a row, a "
        f"final return is known to {_span(table['ci95_half_width'], plus_minus=True)} (95% t "
        f"half-widths); {cut} of {len(table)} intervals reach past the return's range and are "
        "cut to it."
    )


RESOLUTION_LINES = {
    "summary": _means_line,
    "differences": _differences_line,
    "finetune": _returns_line,
}
# The columns that hold a row's number of independent units, per table; what the units are;
# and what a row on too few of them cannot tell.
UNIT_COLUMNS = {
    "summary": ("n_seeds",),
    "differences": ("n_a", "n_b"),
    "finetune": ("n_units",),
    "finetune_differences": ("n_pairs",),
}
UNIT_NAMES = {
    "summary": "seeds",
    "differences": "seeds in an arm",
    "finetune": "units (pre-training runs; from scratch, fine-tuning runs)",
    "finetune_differences": "seed pairs",
}
FEW_UNITS_CAVEATS = {
    "summary": "and no bootstrap interval is given",
    "differences": (
        "no bootstrap interval is given, and the spread behind the seeds needed is itself a "
        "guess from two values"
    ),
    "finetune": "so that the interval of a return in [0, 1] is mostly the whole range",
    "finetune_differences": "so that the interval of a difference of returns is mostly its "
    "whole range",
}


def resolution_line(name: str, table: pd.DataFrame) -> str:
    """The one line under table ``name`` that says what its n can resolve ('' for none)."""
    if table.empty or name not in RESOLUTION_LINES:
        return ""
    return RESOLUTION_LINES[name](table)


def few_units_note(name: str, table: pd.DataFrame) -> str:
    """A warning when rows of table ``name`` rest on fewer than MIN_UNITS independent units
    ('' when none do)."""
    if table.empty or name not in UNIT_COLUMNS:
        return ""
    units = table[list(UNIT_COLUMNS[name])].min(axis=1)
    few = int((units < MIN_UNITS).sum())
    if not few:
        return ""
    return (
        f"Fewer than {MIN_UNITS} independent units: {few} of {len(table)} rows rest on "
        f"{_n_text(units[units < MIN_UNITS])} {UNIT_NAMES[name]}. With two, a t-interval is "
        f"±{t_quantile(1):.1f} standard errors, {FEW_UNITS_CAVEATS[name]}: read these rows as a "
        "plan for the next runs, not as a result."
    )
