"""rliable's aggregates (report/aggregates.py) against cases computed by hand."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hmepol_cli.report.aggregates import (
    improvement_interval,
    iqm,
    iqm_interval,
    mean_interval,
    performance_profile,
)
from hmepol_cli.report.loading import discover_runs
from hmepol_cli.report.runs import group_runs
from hmepol_cli.report.summary import difference_table, final_entropy_table, window_note
from tests.test_report import write_run


def test_iqm_is_the_mean_of_the_middle_half():
    assert iqm([8, 1, 7, 2, 6, 3, 5, 4]) == pytest.approx((3 + 4 + 5 + 6) / 4)
    # rliable's IQM on a runs x tasks matrix pools every score: 12 scores, middle 6.
    matrix = np.arange(12.0).reshape(4, 3)
    assert iqm(matrix) == pytest.approx(np.mean(np.arange(3.0, 9.0)))


def test_probability_of_improvement_by_hand():
    # x = (1, 2, 2) against y = (1.5, 3, 3): of 9 pairs only the two 2s > 1.5 -> 2/9.
    x, y = np.array([[1.0], [2.0], [2.0]]), np.array([[1.5], [3.0], [3.0]])
    assert improvement_interval(x, y).estimate == pytest.approx(2 / 9)
    # A tie counts one half; tasks are averaged: task 1 gives 1/2, task 2 (x above y) gives 1.
    p = improvement_interval(
        np.array([[1.0, 5.0], [1.0, 6.0], [1.0, 5.5]]),
        np.array([[1.0, 0.0], [1.0, 2.0], [1.0, 1.0]]),
    )
    assert p.estimate == pytest.approx(0.75)
    assert p.low == pytest.approx(0.75) and p.high == pytest.approx(0.75)  # no pair can change


def test_the_bootstrap_resamples_a_run_whole():
    # Each run scores 0 in one configuration and 10 in the other: every run's average is 5, so
    # no resample of runs can move the mean. Resampling each configuration's seeds on its own
    # (rliable's stratified bootstrap) would pair a 0 with a 0 and give a wide interval.
    scores = np.array([[0.0, 10.0], [10.0, 0.0], [0.0, 10.0], [10.0, 0.0]])
    mean = mean_interval(scores)
    assert (mean.estimate, mean.low, mean.high) == (5.0, 5.0, 5.0)
    # Each configuration's seeds agree: resampling runs cannot move the IQM either.
    middle = iqm_interval(np.column_stack([np.zeros(4), np.full(4, 10.0)]))
    assert middle.low == middle.high == middle.estimate == 5.0


def test_performance_profile_by_hand():
    scores = np.column_stack([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    share, low, high = performance_profile(scores, np.array([0.0, 2.5, 6.0]))
    assert share.tolist() == [1.0, pytest.approx(4 / 6), 0.0]
    assert low[0] == high[0] == 1.0 and low[2] == high[2] == 0.0
    assert low[1] <= share[1] <= high[1] and low[1] < high[1]


def test_fewer_than_three_runs_have_no_interval():
    # Two runs: a bootstrap can only return values between them (coverage far below 95%).
    value = iqm_interval(np.array([[1.0, 2.0], [3.0, 4.0]]))
    assert value.estimate == pytest.approx(2.5)
    assert np.isnan(value.low) and np.isnan(value.high)
    assert np.isfinite(iqm_interval(np.array([[1.0], [2.0], [3.0]])).low)


@settings(max_examples=25, deadline=None)
@given(
    st.integers(3, 6).flatmap(
        lambda runs: st.lists(
            st.lists(st.floats(-5, 5, allow_nan=False), min_size=runs, max_size=runs),
            min_size=1,
            max_size=3,
        )
    )
)
def test_intervals_hold_their_estimate_and_stay_within_the_scores(columns):
    scores = np.column_stack(columns)
    for interval in (mean_interval(scores), iqm_interval(scores)):
        assert scores.min() - 1e-9 <= interval.low <= interval.high <= scores.max() + 1e-9
    p = improvement_interval(scores, scores)
    assert p.estimate == pytest.approx(0.5)  # an algorithm against itself
    assert 0.0 <= p.low <= p.high <= 1.0


def test_same_scores_give_the_same_intervals():
    rng = np.random.default_rng(3)
    scores = rng.normal(size=(5, 2))
    assert iqm_interval(scores) == iqm_interval(scores.copy())


def test_summary_and_differences_hold_the_aggregates(tmp_path):
    # Two configurations, final entropies final + 0.1 and final - 0.1 per seed (config_finals).
    finals = {"mepol": [1.0, 1.2, 1.1, 1.45], "hmepol": [1.5, 1.4, 1.9, 1.6]}
    for algo, values in finals.items():
        for seed, value in enumerate(values):
            write_run(
                tmp_path, algo=algo, seed=seed, final=value, epochs=10,
                config_finals=(value + 0.1, value - 0.1),
            )  # fmt: skip
    groups = group_runs(discover_runs(tmp_path)[0])
    summary = final_entropy_table(groups).set_index(["group", "config"])
    # The average row is over each seed's average entropy (final), one score per seed.
    scores = np.array(finals["mepol"])
    assert summary.loc[("Mepol", "average"), "iqm_nats"] == pytest.approx(iqm(scores))
    assert summary.loc[("Mepol", "0: south"), "iqm_nats"] == pytest.approx(
        iqm(np.array(finals["mepol"]) + 0.1)
    )
    low, high = summary.loc[("Mepol", "average"), ["mean_boot95_low", "mean_boot95_high"]]
    assert low < scores.mean() < high
    diff = difference_table(groups).set_index("config")
    # P(HMepol > Mepol) in configuration 0: 15 of the 16 seed pairs (1.4 < 1.45 is the other).
    south = diff.loc["0: south"]
    hm, me = np.array(finals["hmepol"]) + 0.1, np.array(finals["mepol"]) + 0.1
    assert south["p_improvement"] == pytest.approx(15 / 16)
    assert diff.loc["average", "p_improvement"] == pytest.approx(
        np.mean(hm[:, None] > me[None, :])  # both configurations shift both groups alike
    )


def test_the_average_row_brackets_its_own_mean_when_configurations_weigh_unequally(tmp_path):
    """Slope's configurations weigh 0.8 and 0.2: a seed's average entropy (final) is not the
    equal-weight mean of its configurations' (here final + 1 and final - 3, whose equal mean is
    final - 1). The average row's bootstrap must estimate what mean_nats is, the mean of the
    seeds' averages, and hold it inside its interval."""
    values = [1.0, 1.2, 1.1, 1.45, 0.9]
    for seed, value in enumerate(values):
        write_run(tmp_path, seed=seed, final=value, epochs=10, config_finals=(value + 1, value - 3))
    groups = group_runs(discover_runs(tmp_path)[0])
    row = final_entropy_table(groups).set_index("config").loc["average"]
    assert row["mean_nats"] == pytest.approx(np.mean(values))
    assert row["mean_boot95_low"] <= row["mean_nats"] <= row["mean_boot95_high"]
    assert row["iqm_nats"] == pytest.approx(iqm(np.array(values)))


def test_differences_say_when_they_compare_finals_taken_at_different_epochs(tmp_path):
    """Mepol ran 20 epochs (its final: the mean over epochs 18-19), HMepol 10 (epoch 9 alone):
    the difference compares two stages of training, and the table and its notice say so."""
    for seed in (0, 1, 2):
        write_run(tmp_path, algo="mepol", seed=seed, epochs=20)
        write_run(tmp_path, algo="hmepol", seed=seed, epochs=10)
    groups = group_runs(discover_runs(tmp_path)[0])
    summary = final_entropy_table(groups).set_index(["group", "config"])
    assert summary.loc[("Mepol", "average"), "final_epochs"] == "18-19"
    assert summary.loc[("HMepol", "average"), "final_epochs"] == "9-9"
    diff = difference_table(groups)
    pairs = set(zip(diff["final_epochs_a"], diff["final_epochs_b"], strict=True))
    assert pairs == {("18-19", "9-9")}
    note = window_note("differences", diff)
    assert note.startswith(f"{len(diff)} of {len(diff)} rows compare finals taken at different")
    assert "18-19 against 9-9" in note


def test_differences_of_runs_of_one_length_carry_no_window_notice(tmp_path):
    for seed in (0, 1, 2):
        write_run(tmp_path, algo="mepol", seed=seed, epochs=20)
        write_run(tmp_path, algo="hmepol", seed=seed, epochs=20)
    groups = group_runs(discover_runs(tmp_path)[0])
    assert window_note("differences", difference_table(groups)) == ""
