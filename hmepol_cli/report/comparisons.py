"""Comparisons of arms of paired seeds: a run's metric over a window of epochs, the paired
difference with its t-interval and exact sign-flip p-value, the seeds a half-width needs, and
AdaStop's group-sequential decision stage by stage.

The one API that ``hmepol study`` and its ``--status`` use. The interval and the seeds needed
come from :mod:`hmepol_cli.report.stats`; AdaStop is Mathieu et al., "AdaStop: adaptive
statistical testing for sound comparisons of Deep RL agents" (the ``adastop`` package).
"""

from __future__ import annotations

import contextlib
import io
import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from hmepol_cli.report.stats import CONFIDENCE, Spread, mean_ci, seeds_for_half_width

EXACT_FLIPS = 20  # up to 2^20 sign assignments enumerated; beyond, a seeded Monte Carlo sample
SAMPLED_FLIPS = 200_000


def window_metric(
    epochs: pd.DataFrame, columns: Sequence[str], first: int, last: int, failed: bool = False
) -> float:
    """The mean over ``columns`` of each column's mean over the epochs ``first``..``last``.

    A run that the algorithm ended early (``failed``) keeps its place: its window is the same
    number of epochs ending at its own last epoch."""
    if failed and len(epochs):
        end = min(last, int(epochs.epoch.max()))
        first, last = end - (last - first), end
    rows = epochs[(epochs.epoch >= first) & (epochs.epoch <= last)]
    if not len(rows):
        return math.nan
    return float(np.mean([rows[c].astype(float).mean() for c in columns]))


def sign_flip_p(differences: Sequence[float], seed: int = 0) -> float:
    """Two-sided sign-flip permutation p-value of mean(d) = 0: the share of sign assignments
    whose |mean| is at least the observed one. Exact (all 2^n) up to n = EXACT_FLIPS, else a
    seeded sample of SAMPLED_FLIPS assignments."""
    d = np.asarray(differences, dtype=float)
    n = d.size
    if n == 0:
        return math.nan
    observed = abs(float(d.mean()))
    if n <= EXACT_FLIPS:
        flips = np.array(list(itertools.product((-1.0, 1.0), repeat=n)))
    else:
        flips = np.random.default_rng(seed).choice((-1.0, 1.0), size=(SAMPLED_FLIPS, n))
    return float((np.abs((flips * np.abs(d)).mean(1)) >= observed - 1e-12).mean())


@dataclass(frozen=True)
class Paired:
    """b - a over paired seeds: mean, 95% Student-t interval, sign-flip p, the seeds a
    ±``target`` half-width needs at the observed sd (NaN when n < 2)."""

    n: int
    mean: float
    low: float
    high: float
    p: float
    target: float
    seeds_needed: float

    def answer(self, b: str = "b", a: str = "a") -> str:
        """ "b ends above a" / "below" when the interval excludes 0; else not resolved."""
        if self.n < 2 or not math.isfinite(self.low):
            return f"undefined at n = {self.n}"
        if self.low > 0:
            return f"{b} ends above {a}"
        if self.high < 0:
            return f"{b} ends below {a}"
        need = "inf" if math.isinf(self.seeds_needed) else f"{self.seeds_needed:.0f}"
        return f"not resolved at n = {self.n} (a ±{self.target:g} half-width needs {need} seeds)"

    def text(self) -> str:
        return (
            f"{self.mean:+.3f} [{self.low:+.3f}, {self.high:+.3f}], sign-flip p {self.p:.2f}"
            f" (n = {self.n})"
        )


def paired(a: Mapping[int, float], b: Mapping[int, float], target: float = 0.3) -> Paired:
    """The paired comparison b - a over the seeds both arms have (finite values only)."""
    seeds = sorted(s for s in set(a) & set(b) if np.isfinite(a[s]) and np.isfinite(b[s]))
    d = np.array([b[s] - a[s] for s in seeds], dtype=float)
    n = d.size
    if n < 2:
        mean = float(d.mean()) if n else math.nan
        return Paired(n, mean, math.nan, math.nan, math.nan, target, math.nan)
    ci = mean_ci(d, CONFIDENCE)
    need = seeds_for_half_width(Spread(float(d.std(ddof=1))), target)
    return Paired(n, ci.mean, ci.low, ci.high, sign_flip_p(d), target, need)


@dataclass(frozen=True)
class Stage:
    """AdaStop's state after one stage: {(a, b): decision} with decisions in
    {"larger", "smaller", "equal", "continue"} ("larger": a's mean above b's)."""

    number: int  # 1-based
    seeds: int  # seeds per arm so far
    decisions: dict[tuple[str, str], str]
    finished: bool


def adastop(
    values: Mapping[str, Sequence[float]],
    n: int,
    stages: int,
    comparisons: Sequence[tuple[str, str]],
    alpha: float = 0.05,
    beta: float = 0.0,
    permutations: int = 10_000,
    seed: int = 0,
) -> list[Stage]:
    """AdaStop's decisions stage by stage over each arm's values in seed order (the first n
    are stage 1, the next n stage 2, ...), for every complete stage, until it finishes.

    A stage is complete when every arm of a comparison still undecided (every arm, at stage 1)
    has its n values: an arm whose comparisons are all decided needs no more seeds, as AdaStop
    tests only the undecided comparisons at a later stage."""
    from adastop import MultipleAgentsComparator

    arms = list(values)
    index = {arm: i for i, arm in enumerate(arms)}
    pairs = np.array([(index[a], index[b]) for a, b in comparisons])
    comparator = MultipleAgentsComparator(
        n=n, K=stages, B=permutations, comparisons=pairs, alpha=alpha, beta=beta, seed=seed
    )
    playing = set(arms)
    out: list[Stage] = []
    for k in range(stages):
        if any(len(values[arm]) < (k + 1) * n for arm in playing):
            break
        so_far = {arm: np.asarray(values[arm][: (k + 1) * n], dtype=float) for arm in arms}
        with contextlib.redirect_stdout(io.StringIO()):  # its own progress prints
            comparator.partial_compare(so_far, verbose=False)
        decisions = {
            (a, b): str(comparator.decisions[str(np.array([index[a], index[b]]))])
            for a, b in comparisons
        }
        out.append(Stage(k + 1, (k + 1) * n, decisions, bool(comparator.is_finished)))
        if comparator.is_finished:
            break
        playing = undecided_arms(decisions)
    return out


def undecided_arms(decisions: Mapping[tuple[str, str], str]) -> set[str]:
    """The arms of the comparisons AdaStop has not decided: those the next stage trains."""
    return {arm for pair, decision in decisions.items() if decision == "continue" for arm in pair}


def decision_text(a: str, b: str, decision: str) -> str:
    """One decision in words: what it says, and for "equal" what it does not."""
    if decision == "larger":
        return f"{a} > {b}"
    if decision == "smaller":
        return f"{a} < {b}"
    if decision == "equal":
        return f"{a} = {b} (no difference detected at the last stage; not proof of equivalence)"
    return f"{a} ? {b}: continue (more seeds needed)"
