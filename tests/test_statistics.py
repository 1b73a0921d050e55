"""report/stats.py against cases computed by hand and published tables: intervals over the unit of
independence, bounded intervals, Wilson's interval, and the seeds a question needs."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hmepol_cli.report.stats import (
    Spread,
    detectable_difference,
    difference_ci,
    mean_ci,
    nested_mean_ci,
    proportion_ci,
    seeds_for_half_width,
    seeds_for_power,
    t_test_power,
)

T_975_1 = 12.706204736  # t_{0.975, 1}
Z_975 = 1.959963985  # z_{0.975}
Z_80 = 0.841621234  # z_{0.80}


def test_two_clusters_of_five_identical_curves_give_the_interval_of_two_samples():
    # Two pre-training runs, five targets each, every target of a run ending at the run's value.
    values = [0.2] * 5 + [0.6] * 5
    units = ["run a"] * 5 + ["run b"] * 5
    ci = nested_mean_ci(values, units)
    # The unit means are 0.2 and 0.6: s = 0.2 sqrt(2), half-width t_{0.975,1} s / sqrt(2).
    assert ci.n == 2 and ci.mean == pytest.approx(0.4)
    assert ci.half_width == pytest.approx(T_975_1 * 0.2, rel=1e-9)
    # Taken as ten independent curves the interval would be 17 times narrower.
    assert mean_ci(values).half_width < ci.half_width / 15
    # A return in [0, 1]: the interval is cut to the bounds, not past them.
    bounded = nested_mean_ci(values, units, bounds=(0.0, 1.0))
    assert (bounded.low, bounded.high) == (0.0, 1.0)
    assert bounded.half_width == ci.half_width  # the t half-width itself is kept


def test_units_are_weighted_alike_whatever_their_number_of_curves():
    # Run a has three curves at 0, run b one at 1: the mean over runs is 1/2, not 1/4.
    ci = nested_mean_ci([0.0, 0.0, 0.0, 1.0], ["a", "a", "a", "b"])
    assert ci.mean == pytest.approx(0.5) and ci.n == 2


def test_one_unit_has_no_interval_however_many_curves_it_holds():
    ci = nested_mean_ci([0.1, 0.5, 0.9], ["a"] * 3, bounds=(0.0, 1.0))
    assert ci.n == 1 and math.isnan(ci.low) and math.isnan(ci.high)


def test_wilson_interval_of_ten_out_of_ten_ends_at_one():
    p = proportion_ci(10, 10)
    # Wilson at p = 1: upper (1 + z^2/2n + z^2/2n) / (1 + z^2/n) = 1, lower 1 / (1 + z^2/n).
    assert p.high == 1.0
    assert p.low == pytest.approx(1 / (1 + Z_975**2 / 10), abs=1e-8)
    assert p.low < 1.0 and p.share == 1.0
    zero = proportion_ci(0, 10)
    assert zero.low == 0.0 and zero.high == pytest.approx(1 - p.low, abs=1e-8)


def test_wilson_interval_by_the_formula():
    k, n, z = 3, 10, Z_975
    p = k / n
    centre = (p + z**2 / (2 * n)) / (1 + z**2 / n)
    half = z / (1 + z**2 / n) * math.sqrt(p * (1 - p) / n + z**2 / (4 * n**2))
    ci = proportion_ci(k, n)
    assert (ci.low, ci.high) == pytest.approx((centre - half, centre + half), abs=1e-8)


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(st.integers(0, 3), st.floats(0.0, 1.0, allow_nan=False)),
        min_size=1,
        max_size=30,
    )
)
def test_bounded_intervals_stay_in_their_bounds(pairs):
    units, values = zip(*pairs, strict=True)
    ci = nested_mean_ci(values, units, bounds=(0.0, 1.0))
    if ci.n >= 2:
        assert 0.0 <= ci.low <= ci.mean + 1e-12 and ci.mean - 1e-12 <= ci.high <= 1.0


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 500).flatmap(lambda n: st.tuples(st.integers(0, n), st.just(n))))
def test_proportion_intervals_stay_in_zero_one_and_hold_the_share(case):
    k, n = case
    ci = proportion_ci(k, n)
    assert 0.0 <= ci.low <= k / n + 1e-12 and k / n - 1e-12 <= ci.high <= 1.0


def test_seeds_for_a_half_width_against_the_t_closed_form():
    # A paired difference with s = 1 and a half-width of 0.5: t_{0.975,n-1} / sqrt(n) <= 0.5.
    # n = 17: 2.119905 / 4.123106 = 0.514 (too wide); n = 18: 2.109816 / 4.242641 = 0.4973.
    assert seeds_for_half_width(Spread(1.0), 0.5) == 18
    # Two arms with s = 0.5 each (Welch, equal variances: df = 2n - 2): t sqrt(0.5 / n) <= 0.3.
    # n = 22: 2.018082 * 0.150756 = 0.3042; n = 23: 2.015368 * 0.147442 = 0.2972.
    assert seeds_for_half_width(Spread.welch(0.25, 0.25), 0.3) == 23
    assert seeds_for_half_width(Spread(0.0), 0.25) == 2  # no spread: the fewest an interval needs
    assert math.isnan(seeds_for_half_width(Spread(math.nan), 0.25))


def test_seeds_for_power_against_cohens_table():
    # Cohen (1988), Table 2.4.1: two-sided alpha 0.05, power 0.80, n per group for effect sizes
    # d = 0.5, 0.8, 1.0 is 64, 26, 17 (two arms with sigma = 1 each).
    unit_variance = Spread.welch(1.0, 1.0)
    assert [seeds_for_power(unit_variance, d) for d in (0.5, 0.8, 1.0)] == [64, 26, 17]


def test_what_the_seeds_at_hand_can_resolve():
    # With very many degrees of freedom the t-test is the z-test: (z_0.975 + z_0.80) se.
    assert detectable_difference(0.1, 1e7) == pytest.approx((Z_975 + Z_80) * 0.1, rel=1e-4)
    # Fewer degrees of freedom resolve less with the same standard error.
    assert detectable_difference(0.1, 2) > detectable_difference(0.1, 20)
    assert t_test_power(0.1, 5, detectable_difference(0.1, 5)) == pytest.approx(0.8, abs=1e-6)


def test_a_difference_carries_the_spread_that_plans_its_seeds():
    # Paired: d = [1, 2, 3], s_d = 1: the planning spread is s_d on n - 1 degrees of freedom.
    paired = difference_ci({0: 1, 1: 2, 2: 3}, {0: 2, 1: 4, 2: 6})
    assert paired.spread == Spread(1.0, 1.0)
    assert paired.se == pytest.approx(1 / math.sqrt(3)) and paired.df == 2
    # Welch: a = [1, 2, 3] (s^2 = 1), b = [2, 4, 6, 8] (s^2 = 20/3).
    welch = difference_ci({0: 1, 1: 2, 2: 3}, {0: 2, 1: 4, 2: 6, 3: 8})
    total = 1 + 20 / 3
    assert welch.spread.sigma == pytest.approx(math.sqrt(total))
    assert welch.spread.df_per_seed == pytest.approx(total**2 / (1 + (20 / 3) ** 2))
    assert welch.se**2 == pytest.approx(2.0)


def test_bounds_cut_a_plain_mean_interval_too():
    ci = mean_ci(np.array([0.9, 1.0, 1.0]), bounds=(0.0, 1.0))
    assert ci.high == 1.0 and ci.low < ci.mean < 1.0
