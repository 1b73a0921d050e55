"""rliable's aggregates over seeds and configurations, with scipy's bootstrap.

Agarwal et al. (2021, "Deep RL at the edge of the statistical precipice") compare algorithms on
a score matrix of runs x tasks; here a task is a configuration of the class and a score is a
run's final entropy in that configuration (nats, as the objective averages them). For each group:

- the interquartile mean (IQM: the mean of the middle 50% of all run x configuration scores,
  ``scipy.stats.trim_mean(·, 0.25)``) and the mean, each with a stratified-bootstrap 95%
  interval: every configuration's seeds are resampled on their own (scipy's bootstrap resamples
  each sample it is given independently), the percentile interval of 2,000 resamples;
- the probability of improvement P(X > Y) of one group over another: per configuration the
  Mann-Whitney statistic, the share of (x seed, y seed) pairs where x scores higher (a tie counts
  one half), averaged over configurations, with the same stratified interval;
- the performance profile: the share of run x configuration scores above each threshold tau,
  with a pointwise interval.

The resamples are drawn from a fixed generator, so the same runs give the same intervals. A group
with fewer than two seeds in some configuration has no interval (NaN).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
from scipy.stats import bootstrap, trim_mean

RESAMPLES = 2000
CONFIDENCE = 0.95
SEED = 0  # the bootstrap generator's seed: intervals are a function of the scores only


@dataclass(frozen=True)
class Interval:
    """A point estimate with its bootstrap interval (NaN bounds when it is undefined)."""

    estimate: float
    low: float
    high: float


def iqm(scores) -> float:
    """Interquartile mean of all scores (any shape): the mean of the middle 50%."""
    return float(trim_mean(np.asarray(scores, dtype=float).ravel(), 0.25))


def _stratified(tasks: list[np.ndarray], statistic) -> Interval:
    """``statistic(*tasks, axis=-1)`` with its stratified-bootstrap percentile interval."""
    estimate = float(statistic(*tasks, axis=-1))
    if any(t.size < 2 for t in tasks):
        return Interval(estimate, math.nan, math.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a resample of equal scores is a valid, zero-width case
        result = bootstrap(
            tuple(tasks),
            statistic,
            n_resamples=RESAMPLES,
            confidence_level=CONFIDENCE,
            method="percentile",
            vectorized=True,
            rng=np.random.default_rng(SEED),
        )
    ci = result.confidence_interval
    return Interval(estimate, float(ci.low), float(ci.high))


def _pooled(statistic):
    """A statistic of all tasks' scores pooled, for scipy's vectorised resamples."""

    def pooled(*tasks, axis=-1):
        return statistic(np.concatenate(tasks, axis=axis), axis=axis)

    return pooled


def iqm_interval(tasks: list[np.ndarray]) -> Interval:
    """IQM of the scores of every task (one array of seeds per configuration)."""
    return _stratified(tasks, _pooled(lambda x, axis: trim_mean(x, 0.25, axis=axis)))


def mean_interval(tasks: list[np.ndarray]) -> Interval:
    """Mean of the scores of every task."""
    return _stratified(tasks, _pooled(lambda x, axis: np.mean(x, axis=axis)))


def _improvement(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Share of pairs with x > y (ties one half) over the last axis of both."""
    diff = x[..., :, None] - y[..., None, :]
    return ((diff > 0) + 0.5 * (diff == 0)).mean(axis=(-2, -1))


def improvement_interval(x_tasks: list[np.ndarray], y_tasks: list[np.ndarray]) -> Interval:
    """P(X > Y): per task the Mann-Whitney share, averaged over tasks (same tasks in both)."""
    if len(x_tasks) != len(y_tasks):
        raise ValueError(f"{len(x_tasks)} tasks against {len(y_tasks)}")
    n = len(x_tasks)

    def statistic(*samples, axis=-1):
        return np.mean([_improvement(samples[t], samples[n + t]) for t in range(n)], axis=0)

    return _stratified(list(x_tasks) + list(y_tasks), statistic)


def performance_profile(
    tasks: list[np.ndarray], taus: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Share of run x task scores above each tau, with pointwise bootstrap bounds."""
    points = [
        _stratified(tasks, _pooled(lambda x, axis, tau=tau: np.mean(x > tau, axis=axis)))
        for tau in taus
    ]
    return tuple(np.array([getattr(p, f) for p in points]) for f in ("estimate", "low", "high"))
