"""rliable's aggregates over seeds and configurations, with scipy's bootstrap.

Agarwal et al. (2021, "Deep RL at the edge of the statistical precipice") compare algorithms on
a score matrix of runs x tasks; here a task is a configuration of the class and a score is a
run's final entropy in that configuration (nats, as the objective averages them). For each group:

- the interquartile mean (IQM: the mean of the middle 50% of all run x configuration scores,
  ``scipy.stats.trim_mean(·, 0.25)``) and the mean, each with a bootstrap 95% interval;
- the probability of improvement P(X > Y) of one group over another: per configuration the
  Mann-Whitney statistic, the share of (x seed, y seed) pairs where x scores higher (a tie counts
  one half), averaged over configurations, with the same kind of interval;
- the performance profile: the share of run x configuration scores above each threshold tau,
  with a pointwise interval.

The bootstrap resamples what is independent, the run: a resampled run brings its scores in every
configuration with it, since one run (one policy) made all of them. rliable's stratified bootstrap
resamples each task's runs on their own, which is right when every task had its own runs and here
would treat a run's configurations as independent draws. Two groups are resampled each on its own.
The interval is the percentile interval of 2,000 resamples, drawn from a fixed generator, so the
same runs give the same intervals. Below MIN_UNITS runs a group has no interval (NaN): a bootstrap
of two runs can only return values between them, with a coverage far below 95%.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
from scipy.stats import bootstrap, trim_mean

from hmepol_cli.report.stats import MIN_UNITS

RESAMPLES = 2000
CONFIDENCE = 0.95
SEED = 0  # the bootstrap generator's seed: intervals are a function of the scores only
# How the intervals were made, for captions and tables.
METHOD = (
    "bootstrap over runs (a run resampled whole, with its score in every configuration; "
    f"{RESAMPLES:,} percentile resamples; no interval under {MIN_UNITS} seeds)"
)


@dataclass(frozen=True)
class Interval:
    """A point estimate with its bootstrap interval (NaN bounds when it is undefined)."""

    estimate: float
    low: float
    high: float


def iqm(scores) -> float:
    """Interquartile mean of all scores (any shape): the mean of the middle 50%."""
    return float(trim_mean(np.asarray(scores, dtype=float).ravel(), 0.25))


def _matrix(scores) -> np.ndarray:
    """A score matrix (n_runs, n_tasks); one run's scores as a row, a 1-D array as one task."""
    scores = np.asarray(scores, dtype=float)
    return scores[:, None] if scores.ndim == 1 else scores


def _over_runs(matrices: list[np.ndarray], statistic) -> Interval:
    """``statistic(*matrices)`` with the percentile interval of a bootstrap that resamples the
    rows (runs) of each (n_runs, n_tasks) matrix, whole and each matrix on its own.

    ``statistic`` takes matrices with leading batch dimensions, (..., n_runs, n_tasks) -> (...).
    scipy resamples the row indices; the statistic looks the rows up."""
    matrices = [_matrix(m) for m in matrices]
    estimate = float(statistic(*matrices))
    if any(m.shape[0] < MIN_UNITS for m in matrices):
        return Interval(estimate, math.nan, math.nan)

    def resampled(*rows, axis=-1):
        return statistic(*(m[r] for m, r in zip(matrices, rows, strict=True)))

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a resample of equal scores is a valid, zero-width case
        result = bootstrap(
            tuple(np.arange(m.shape[0]) for m in matrices),
            resampled,
            n_resamples=RESAMPLES,
            confidence_level=CONFIDENCE,
            method="percentile",
            vectorized=True,
            rng=np.random.default_rng(SEED),
        )
    ci = result.confidence_interval
    return Interval(estimate, float(ci.low), float(ci.high))


def _pooled(statistic):
    """A statistic of every run x task score pooled, over the last two axes."""

    def pooled(scores: np.ndarray) -> np.ndarray:
        return statistic(scores.reshape(*scores.shape[:-2], -1), axis=-1)

    return pooled


def iqm_interval(scores) -> Interval:
    """IQM of every score of the matrix (n_runs, n_configurations)."""
    return _over_runs([scores], _pooled(lambda x, axis: trim_mean(x, 0.25, axis=axis)))


def mean_interval(scores) -> Interval:
    """Mean of every score of the matrix (n_runs, n_configurations)."""
    return _over_runs([scores], _pooled(np.mean))


def _improvement(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Per task the share of run pairs with x > y (ties one half), averaged over the tasks.
    x (..., n_x, T), y (..., n_y, T) -> (...)."""
    diff = x[..., :, None, :] - y[..., None, :, :]
    return ((diff > 0) + 0.5 * (diff == 0)).mean(axis=(-3, -2)).mean(axis=-1)


def improvement_interval(x_scores, y_scores) -> Interval:
    """P(X > Y) of two score matrices over the same tasks (columns)."""
    x, y = _matrix(x_scores), _matrix(y_scores)
    if x.shape[1] != y.shape[1]:
        raise ValueError(f"{x.shape[1]} tasks against {y.shape[1]}")
    return _over_runs([x, y], _improvement)


def performance_profile(scores, taus: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Share of run x task scores above each tau, with pointwise bootstrap bounds."""
    points = [
        _over_runs([scores], _pooled(lambda x, axis, tau=tau: np.mean(x > tau, axis=axis)))
        for tau in taus
    ]
    return tuple(np.array([getattr(p, f) for p in points]) for f in ("estimate", "low", "high"))
