"""Means and their 95% confidence intervals over the unit of independence, differences between
algorithms, proportions, and the seeds a question needs.

An interval counts what was drawn independently: the pre-training run (one seed) for entropies;
for fine-tuning, the pre-training run a policy came from, with its targets and fine-tuning seeds
nested inside it (:func:`nested_mean_ci` averages within each unit first, then takes a Student-t
interval over the unit means). A quantity known to lie in [low, high] (a goal task's return) has
its interval cut to those bounds: the true mean lies inside them, so the cut interval covers it
whenever the t-interval does. Proportions of independent units get Wilson's interval. With a
single unit an interval is undefined (NaN) and the figures draw no band. docs/statistics.md gives
every formula and its reference.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import optimize, stats

CONFIDENCE = 0.95
FINAL_FRACTION = 0.1  # "final" entropy: mean over the last 10% of epochs of a run
UNBOUNDED = (-math.inf, math.inf)
MIN_UNITS = 3  # below this a t-interval has 1 degree of freedom (t = 12.7): a guess, not a result
MAX_SEEDS = 1_000_000  # seeds-needed searches stop here (inf beyond)


@dataclass(frozen=True)
class MeanCI:
    """Sample mean with a two-sided t-interval; ``half_width`` is NaN when n < 2.

    ``half_width`` is the t half-width; ``low`` and ``high`` are cut to ``bounds``, the range the
    quantity can take (a goal task's return lies in [0, 1])."""

    mean: float
    half_width: float
    n: int
    bounds: tuple[float, float] = UNBOUNDED

    @property
    def low(self) -> float:
        return float(np.clip(self.mean - self.half_width, *self.bounds))

    @property
    def high(self) -> float:
        return float(np.clip(self.mean + self.half_width, *self.bounds))


@dataclass(frozen=True)
class Spread:
    """How the standard error of a mean, or of a difference of means, shrinks with n seeds per
    arm: se(n) = sigma / sqrt(n) on df(n) = df_per_seed * (n - 1) degrees of freedom.

    One group, or a paired difference: sigma = s (of the values, of the differences),
    df_per_seed = 1. Two independent arms of n seeds each (Welch): sigma^2 = s_a^2 + s_b^2 and
    df_per_seed = (s_a^2 + s_b^2)^2 / (s_a^4 + s_b^4), the Welch-Satterthwaite degrees of freedom
    per seed (between 1 and 2; 2, the pooled test's 2n - 2, when the variances are equal)."""

    sigma: float
    df_per_seed: float = 1.0

    @classmethod
    def welch(cls, var_a: float, var_b: float) -> Spread:
        total = var_a + var_b
        if total == 0:
            return cls(0.0, 2.0)
        return cls(math.sqrt(total), total**2 / (var_a**2 + var_b**2))

    def se(self, n: float) -> float:
        return self.sigma / math.sqrt(n)

    def df(self, n: float) -> float:
        return self.df_per_seed * (n - 1)


@dataclass(frozen=True)
class DiffCI:
    """Difference of means ``b - a`` with its t-interval and the method used."""

    diff: float
    half_width: float
    method: str  # "paired t" | "Welch t" | "undefined (n < 2)"
    n_a: int
    n_b: int
    se: float = math.nan  # the standard error the half-width is t * se of
    df: float = math.nan
    spread: Spread = Spread(math.nan)  # to plan how many seeds a smaller interval needs

    @property
    def low(self) -> float:
        return self.diff - self.half_width

    @property
    def high(self) -> float:
        return self.diff + self.half_width


def t_quantile(df: float, confidence: float = CONFIDENCE) -> float:
    """Two-sided critical value t_{(1+confidence)/2, df}."""
    return float(stats.t.ppf(0.5 + confidence / 2, df))


def mean_ci(
    samples, confidence: float = CONFIDENCE, bounds: tuple[float, float] = UNBOUNDED
) -> MeanCI:
    """Mean and t-interval half-width t_{0.975, n-1} * s / sqrt(n) of the finite samples, the
    interval cut to ``bounds``."""
    x = np.asarray(samples, dtype=float).ravel()
    x = x[np.isfinite(x)]
    n = int(x.size)
    if n == 0:
        return MeanCI(math.nan, math.nan, 0, bounds)
    mean = float(x.mean())
    if n < 2:
        return MeanCI(mean, math.nan, 1, bounds)
    sem = float(x.std(ddof=1)) / math.sqrt(n)
    return MeanCI(mean, t_quantile(n - 1, confidence) * sem, n, bounds)


def unit_means(values, units: Sequence) -> np.ndarray:
    """The mean of each unit's finite values, units in order of first appearance."""
    frame = pd.DataFrame({"unit": list(units), "value": np.asarray(values, dtype=float)})
    frame = frame[np.isfinite(frame["value"])]
    return frame.groupby("unit", sort=False)["value"].mean().to_numpy()


def nested_mean_ci(
    values,
    units: Sequence,
    confidence: float = CONFIDENCE,
    bounds: tuple[float, float] = UNBOUNDED,
) -> MeanCI:
    """Mean and t-interval of values nested in independent units: the t-interval of the unit
    means, n the number of units (the analysis of cluster means; with few units it holds its
    level where a bootstrap over units cannot, docs/statistics.md)."""
    return mean_ci(unit_means(values, units), confidence, bounds)


@dataclass(frozen=True)
class Proportion:
    """``successes`` of ``n`` independent units with Wilson's score interval (inside [0, 1])."""

    successes: int
    n: int
    low: float
    high: float

    @property
    def share(self) -> float:
        return self.successes / self.n if self.n else math.nan


def proportion_ci(successes: int, n: int, confidence: float = CONFIDENCE) -> Proportion:
    """Wilson's (1927) score interval of a proportion: never past 0 or 1, and not empty at
    0 / n or n / n as the Wald interval is."""
    if n == 0:
        return Proportion(0, 0, math.nan, math.nan)
    ci = stats.binomtest(int(successes), int(n)).proportion_ci(confidence, method="wilson")
    return Proportion(int(successes), int(n), float(ci.low), float(ci.high))


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
        sd = float(d.std(ddof=1))
        return DiffCI(
            ci.mean, ci.half_width, "paired t", na, nb, sd / math.sqrt(na), na - 1, Spread(sd)
        )
    if na < 2 or nb < 2:
        return DiffCI(diff, math.nan, "undefined (n < 2)", na, nb)
    spread = Spread.welch(float(xa.var(ddof=1)), float(xb.var(ddof=1)))
    va, vb = xa.var(ddof=1) / na, xb.var(ddof=1) / nb
    se = math.sqrt(va + vb)
    if se == 0:
        return DiffCI(diff, 0.0, "Welch t", na, nb, 0.0, math.nan, spread)
    df = (va + vb) ** 2 / (va**2 / (na - 1) + vb**2 / (nb - 1))
    return DiffCI(diff, t_quantile(df, confidence) * se, "Welch t", na, nb, se, df, spread)


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


# ------------------------------------------------------------------------- how many seeds
def half_width_with(spread: Spread, n: int, confidence: float = CONFIDENCE) -> float:
    """The t half-width t_{(1+c)/2, df(n)} * se(n) that n seeds per arm would give."""
    return t_quantile(spread.df(n), confidence) * spread.se(n)


def t_test_power(se: float, df: float, delta: float, confidence: float = CONFIDENCE) -> float:
    """Power of the two-sided t-test at level 1 - confidence against a true difference ``delta``:
    its statistic is noncentral t on ``df`` degrees of freedom with noncentrality delta / se."""
    critical = t_quantile(df, confidence)
    shift = abs(delta) / se
    lower = stats.nct.cdf(-critical, df, shift)
    if not np.isfinite(lower):  # scipy's NaN far in the tail: P(T < -c) < P(T < 0) = Phi(-shift)
        lower = 0.0 if stats.norm.cdf(-shift) < 1e-12 else math.nan
    return float(stats.nct.sf(critical, df, shift) + lower)


def _smallest_n(enough: Callable[[int], bool]) -> float:
    """The smallest n >= 2 at which ``enough`` (false, then true as n grows) holds; inf past
    MAX_SEEDS. Doubling, then bisection: the t quantile changes with n, so there is no formula."""
    low, high = 1, 2
    while not enough(high):
        if high >= MAX_SEEDS:
            return math.inf
        low, high = high, min(2 * high, MAX_SEEDS)
    while high - low > 1:
        middle = (low + high) // 2
        low, high = (low, middle) if enough(middle) else (middle, high)
    return float(high)


def seeds_for_half_width(
    spread: Spread, half_width: float, confidence: float = CONFIDENCE
) -> float:
    """Seeds per arm for an interval of at most +-``half_width``: the smallest n >= 2 with
    t_{(1+c)/2, df(n)} * sigma / sqrt(n) <= half_width (NaN when the spread is unknown)."""
    if not np.isfinite(spread.sigma):
        return math.nan
    return _smallest_n(lambda n: half_width_with(spread, n, confidence) <= half_width)


def seeds_for_power(
    spread: Spread, delta: float, power: float = 0.8, confidence: float = CONFIDENCE
) -> float:
    """Seeds per arm for the two-sided t-test to find a true difference ``delta`` with
    probability ``power`` (noncentral t, :func:`t_test_power`); NaN when the spread is unknown."""
    if not np.isfinite(spread.sigma):
        return math.nan
    if spread.sigma == 0:
        return 2.0
    return _smallest_n(
        lambda n: t_test_power(spread.se(n), spread.df(n), delta, confidence) >= power
    )


def detectable_difference(
    se: float, df: float, power: float = 0.8, confidence: float = CONFIDENCE
) -> float:
    """The smallest true difference that the two-sided t-test with this ``se`` and ``df`` finds
    with probability ``power``: what the seeds at hand can resolve."""
    if not (np.isfinite(se) and np.isfinite(df)):
        return math.nan
    if se == 0:
        return 0.0
    high = se * (t_quantile(df, confidence) + 2.0)
    while t_test_power(se, df, high, confidence) < power:
        high *= 2
    return float(optimize.brentq(lambda d: t_test_power(se, df, d, confidence) - power, 0.0, high))
