"""A member's alarms (hmepol_cli.alarms): which values stop a run and how the stop is worded,
and when divergence, precision drift and a stall warn; on hand-made epoch statistics."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from hmepol_cli.alarms import MemberAlarms, precision_drift
from hmepol_cli.config import AlarmConfig
from hmepol_cli.records import EpochStats, UpdateResult


def stats(update: dict | None = None, **changes) -> EpochStats:
    """A calm epoch of two mini-batches; ``changes`` set fields of it, ``update`` of its
    off-policy loop's result."""
    result = UpdateResult(
        entropies=np.array([1.0, 1.1]), kl=0.01, off_iters=3, backtracks=0, lr=1e-3
    )
    for key, value in (update or {}).items():
        setattr(result, key, value)
    epoch = EpochStats(
        entropies=np.array([1.0, 1.2]),
        batch_configurations=np.array([0, 1]),
        objective=1.1,
        update=result,
        history_max=1.0,
        action_max=0.5,
    )
    for key, value in changes.items():
        setattr(epoch, key, value)
    return epoch


def params(**changes) -> dict[str, torch.Tensor]:
    own = {"log_std": torch.full((2,), -1.5), "mean.weight": torch.ones(2, 3)}
    own.update(changes)
    return own


@pytest.fixture
def alarms(tmp_path) -> MemberAlarms:
    bounds = OmegaConf.structured(AlarmConfig(stall_epochs=2))
    return MemberAlarms(bounds, tmp_path / "run", seed=7, lr_backtrack_tries=10)


def test_a_finite_epoch_goes_on(alarms):
    assert alarms.failure(4, stats(), params()) is None


@pytest.mark.parametrize(
    ("epoch_changes", "param_changes", "names"),
    [
        ({"entropies": np.array([1.0, math.nan])}, {}, "entropy"),
        ({"update": {"kl": math.inf}}, {}, "KL"),
        ({"history_max": math.nan}, {}, "history"),
        ({"action_max": -math.inf}, {}, "actions"),
        ({}, {"log_std": torch.tensor([-1.5, math.nan])}, "log-std, policy weights"),
        ({}, {"mean.weight": torch.tensor([[math.inf]])}, "policy weights"),
    ],
)
def test_a_value_that_is_not_finite_stops_the_member_naming_it(
    alarms, epoch_changes, param_changes, names
):
    reason = alarms.failure(4, stats(**epoch_changes), params(**param_changes))
    assert reason == f"non-finite {names} at epoch 4: the run stopped there"


def test_the_rollouts_broken_values_are_named_first_and_alone(alarms):
    broken = stats({"kl": math.nan}, broken=["positions"])
    reason = alarms.failure(0, broken, params(log_std=torch.tensor([math.nan])))
    assert reason == "non-finite positions at epoch 0: the run stopped there"


def test_divergence_is_past_a_bound_and_warns_naming_it(alarms, caplog):
    assert not alarms.diverged(stats(history_max=1e3, action_max=10.0))  # at the bounds
    assert alarms.diverged(stats(history_max=1001.0))
    assert alarms.diverged(stats(action_max=10.5))
    with caplog.at_level(logging.WARNING, logger="hmepol"):
        assert alarms.warn(3, stats(action_max=10.5)) == "diverging"
    assert "epoch 3: the policy is diverging" in caplog.text
    assert "max |a| = 10.5 (alarms.action_bound = 10)" in caplog.text


def test_a_stall_warns_after_stall_epochs_and_an_accepted_step_ends_it(alarms, caplog):
    with caplog.at_level(logging.WARNING, logger="hmepol"):
        assert alarms.warn(0, stats({"off_iters": 0})) is None
        assert alarms.warn(1, stats({"off_iters": 0})) == "seed 7 stalled"
        assert "no off-policy step accepted for 2 epochs (to epoch 1)" in caplog.text
        assert "after 10 learning-rate reductions" in caplog.text
        assert alarms.warn(2, stats({"off_iters": 1})) is None
        assert alarms.stalled_for == 0
        assert alarms.warn(3, stats({"off_iters": 0})) is None  # counting starts over


def test_a_lowered_precision_that_drifts_warns(alarms, caplog):
    assert precision_drift(stats()) == 0.0  # full precision: nothing recomputed
    assert precision_drift(stats({"kl": 0.0, "kl_full_precision": 1e-13})) == 0.0  # both ~0
    assert precision_drift(stats({"kl": 0.0105, "kl_full_precision": 0.01})) == pytest.approx(0.05)
    with caplog.at_level(logging.WARNING, logger="hmepol"):
        assert alarms.warn(5, stats({"kl": 0.01005, "kl_full_precision": 0.01})) is None  # 0.5 %
        assert caplog.text == ""
        alarms.warn(6, stats({"kl": 0.0105, "kl_full_precision": 0.01}))
    assert "epoch 6: the lowered precision's KL is 5.0% off" in caplog.text
    assert "use precision=float32" in caplog.text


def test_a_member_that_stops_is_noted_on_the_bar_by_its_seed(alarms):
    assert alarms.failed_note() == "seed 7 failed"
