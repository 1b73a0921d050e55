"""Means and Student-t 95% confidence intervals over seeds, and differences between algorithms.

Every interval in the report is a t-interval: the seeds of one group are treated as an i.i.d.
sample of runs. With a single seed the interval is undefined (NaN) and the figures draw no band.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats

CONFIDENCE = 0.95
FINAL_FRACTION = 0.1  # "final" entropy: mean over the last 10% of epochs of a run


@dataclass(frozen=True)
class MeanCI:
    """Sample mean with a two-sided t-interval; ``half_width`` is NaN when n < 2."""

    mean: float
    half_width: float
    n: int

    @property
    def low(self) -> float:
        return self.mean - self.half_width

    @property
    def high(self) -> float:
        return self.mean + self.half_width


@dataclass(frozen=True)
class DiffCI:
    """Difference of means ``b - a`` with its t-interval and the method used."""

    diff: float
    half_width: float
    method: str  # "paired t" | "Welch t" | "undefined (n < 2)"
    n_a: int
    n_b: int

    @property
    def low(self) -> float:
        return self.diff - self.half_width

    @property
    def high(self) -> float:
        return self.diff + self.half_width


def t_quantile(df: float, confidence: float = CONFIDENCE) -> float:
    """Two-sided critical value t_{(1+confidence)/2, df}."""
    return float(stats.t.ppf(0.5 + confidence / 2, df))


def mean_ci(samples, confidence: float = CONFIDENCE) -> MeanCI:
    """Mean and t-interval half-width t_{0.975, n-1} * s / sqrt(n) of the finite samples."""
    x = np.asarray(samples, dtype=float).ravel()
    x = x[np.isfinite(x)]
    n = int(x.size)
    if n == 0:
        return MeanCI(math.nan, math.nan, 0)
    mean = float(x.mean())
    if n < 2:
        return MeanCI(mean, math.nan, 1)
    sem = float(x.std(ddof=1)) / math.sqrt(n)
    return MeanCI(mean, t_quantile(n - 1, confidence) * sem, n)


def curve_ci(curves: np.ndarray, confidence: float = CONFIDENCE) -> tuple[np.ndarray, ...]:
    """Point-wise mean, half-width and n of curves (n_seeds, n_points); NaN entries are ignored.

    Returns three (n_points,) arrays; the half-width is NaN where fewer than two seeds have a value.
    """
    curves = np.atleast_2d(np.asarray(curves, dtype=float))
    finite = np.isfinite(curves)
    n = finite.sum(axis=0)
    total = np.where(finite, curves, 0.0).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(n > 0, total / np.maximum(n, 1), np.nan)
        dev = np.where(finite, curves - mean, 0.0)
        var = (dev**2).sum(axis=0) / np.maximum(n - 1, 1)
        tq = np.array([t_quantile(k - 1, confidence) if k >= 2 else np.nan for k in n])
        half = tq * np.sqrt(var) / np.sqrt(np.maximum(n, 1))
    half = np.where(n >= 2, half, np.nan)
    return mean, half, n


def difference_ci(
    a: dict[int, float], b: dict[int, float], confidence: float = CONFIDENCE
) -> DiffCI:
    """CI of mean(b) - mean(a) from per-seed values ``{seed: value}``.

    Paired t-interval on the per-seed differences when both groups ran exactly the same seeds
    (common random numbers make the pairs dependent); otherwise Welch's t-interval with
    Welch-Satterthwaite degrees of freedom.
    """
    a = {s: float(v) for s, v in a.items() if np.isfinite(v)}
    b = {s: float(v) for s, v in b.items() if np.isfinite(v)}
    xa, xb = np.array(list(a.values())), np.array(list(b.values()))
    na, nb = xa.size, xb.size
    if na == 0 or nb == 0:
        return DiffCI(math.nan, math.nan, "undefined (no values)", na, nb)
    diff = float(xb.mean() - xa.mean())
    if set(a) == set(b) and na >= 2:
        d = np.array([b[s] - a[s] for s in sorted(a)])
        ci = mean_ci(d, confidence)
        return DiffCI(ci.mean, ci.half_width, "paired t", na, nb)
    if na < 2 or nb < 2:
        return DiffCI(diff, math.nan, "undefined (n < 2)", na, nb)
    va, vb = xa.var(ddof=1) / na, xb.var(ddof=1) / nb
    se = math.sqrt(va + vb)
    if se == 0:
        return DiffCI(diff, 0.0, "Welch t", na, nb)
    df = (va + vb) ** 2 / (va**2 / (na - 1) + vb**2 / (nb - 1))
    return DiffCI(diff, t_quantile(df, confidence) * se, "Welch t", na, nb)


def final_value(values, fraction: float = FINAL_FRACTION) -> float:
    """Mean of the last ``fraction`` of a run's per-epoch values (at least one epoch).

    Epochs where the value is missing (a configuration not drawn that epoch) are dropped first,
    so the window holds the last observed values.
    """
    x = np.asarray(values, dtype=float)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return math.nan
    k = max(1, math.ceil(fraction * x.size))
    return float(x[-k:].mean())
