"""The off-policy loop of Algorithm 3.1 on hand-built surrogates: the backtracking rules step
by step, what a rejection restores, and members that stop at different points."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from hmepol_cli.estimators import KNNEstimator
from hmepol_cli.mepol import off_policy_loop
from hmepol_cli.population import PolicyPopulation, PopulationAdam
from hmepol_cli.settings import MemberSettings, OffPolicySettings
from hmepol_cli.surrogate import Estimate

LR = 0.1


def settings(size: int = 1, **changes) -> OffPolicySettings:
    """The loop's settings; the member-scalar ones (lr, kl_threshold, max_off_iters) for each of
    ``size`` members."""
    own = {k: changes.pop(k) for k in ("lr", "kl_threshold", "max_off_iters") if k in changes}
    member = MemberSettings(**{"lr": LR, "kl_threshold": 0.15, "max_off_iters": 30, **own})
    base = OffPolicySettings(
        trajectories=10, horizon=4, batch_size=5, estimator=KNNEstimator(2),
        members=(member,) * size, backtracking="reference", backtrack_tries=10,
        backtrack_factor=2.0, restore="parameters", adam_reset=False, exact_kl=False, bptt=1,
    )  # fmt: skip
    return dataclasses.replace(base, **changes)


class Quadratic:
    """A surrogate whose objective is sum(log_std) and whose KL is |log_std - log_std_0|^2.

    The gradient is constant, so every Adam step moves each of the two log-std entries by the
    learning rate (m / sqrt(v) = 1): after steps of rates lr_1, lr_2, ... the KL is
    2 (lr_1 + lr_2 + ...)^2. With lr = 0.1: 0.02 after one full step, 0.08 after two, 0.18
    after three; a threshold of 0.15 accepts two full steps and rejects the third."""

    def __init__(self, population: PolicyPopulation, scale: torch.Tensor | None = None) -> None:
        self.population = population
        self.start = population.params["log_std"].detach().clone()
        self.scale = torch.ones(population.size, dtype=torch.float64) if scale is None else scale
        self.row_of = {m: m for m in range(population.size)}
        self.calls = 0

    def rows(self, members):
        return torch.tensor(list(members))

    def full_precision(self):
        return None  # no lowered precision to check

    def __call__(self, rows: torch.Tensor):
        self.calls += 1
        log_std = self.population.params["log_std"].index_select(0, rows)
        value = log_std.sum(-1)
        kl = self.scale[rows] * (log_std - self.start[rows]).pow(2).sum(-1).detach()
        entropies = value[:, None].detach().repeat(1, 2)
        return Estimate(entropies, kl, value, torch.zeros(len(rows), 1, 1), kl)


def population(size: int = 1) -> tuple[PolicyPopulation, PopulationAdam]:
    from hmepol_cli.config import PolicyConfig
    from hmepol_cli.policies import make_policy

    cfg = PolicyConfig(name="markov", hidden=[4])
    policies = [make_policy(cfg, 2, 2).double() for _ in range(size)]
    pop = PolicyPopulation(policies)
    return pop, PopulationAdam(pop.params)


def moved(pop: PolicyPopulation, surrogate: Quadratic, s: int = 0) -> float:
    """How far member s's log-std moved, in units of LR (both entries move alike)."""
    delta = pop.params["log_std"][s].detach() - surrogate.start[s]
    assert torch.allclose(delta[0], delta[1])
    return float(delta[0]) / LR


def run(rule: str, threshold: float, **changes):
    pop, adam = population()
    surrogate = Quadratic(pop)
    s = settings(backtracking=rule, kl_threshold=threshold, **changes)
    (result,) = off_policy_loop(pop, adam, surrogate, torch.tensor([0]), s)
    return result, moved(pop, surrogate), adam


def test_reference_a_rejected_third_step_is_retried_smaller_and_ends_the_epoch():
    result, distance, adam = run("reference", 0.15)
    # Steps 1 and 2 accepted (KL 0.08); step 3 (0.18) rejected, undone, retried at lr / 2
    # (KL 2 x 0.25^2 = 0.125): accepted, and the epoch ends there.
    assert (result.off_iters, result.backtracks) == (3, 1)
    assert result.lr == LR / 2
    assert distance == pytest.approx(2.5, rel=1e-6)
    assert result.kl == pytest.approx(2 * (2.5 * LR) ** 2, rel=1e-6)
    # parameters only were restored: Adam counted the rejected step too (4 steps tried).
    assert float(adam.steps[0]) == 4


def test_first_step_rule_a_rejected_third_step_ends_the_epoch_without_a_smaller_step():
    result, distance, adam = run("first_step", 0.15, restore="parameters_and_adam")
    assert (result.off_iters, result.backtracks) == (2, 0)
    assert result.lr == LR
    assert distance == pytest.approx(2.0, rel=1e-6)
    assert float(adam.steps[0]) == 2  # the Adam state was returned to the second step's


def test_reference_a_rejected_first_step_is_retried_until_one_fits_then_the_epoch_ends():
    # 0.003 rejects a full step (0.02) and a half (0.005), accepts a quarter (0.00125).
    result, distance, _ = run("reference", 0.003)
    assert (result.off_iters, result.backtracks) == (1, 2)
    assert result.lr == LR / 4
    assert distance == pytest.approx(0.25, rel=1e-6)


def test_first_step_rule_retries_a_rejected_first_step_and_goes_on_at_the_reduced_rate():
    # 0.019: a full step (0.02) is rejected, a half step (0.005) accepted; the next half step
    # reaches the full step's 0.02 and ends the epoch (with a constant gradient two reduced
    # steps add up to the rejected one, so here both rules stop after one step).
    result, distance, _ = run("first_step", 0.019, restore="parameters_and_adam")
    assert (result.off_iters, result.backtracks) == (1, 1)
    assert result.lr == LR / 2
    assert distance == pytest.approx(0.5, rel=1e-6)


def test_reference_when_every_try_is_rejected_the_policy_stays_where_it_was():
    result, distance, adam = run("reference", 0.0, backtrack_tries=4)
    assert (result.off_iters, result.backtracks) == (0, 3)  # tries: lr, lr/2, lr/4, lr/8
    assert result.lr == LR / 8
    assert distance == 0.0
    assert result.kl == 0.0


def test_restoring_the_adam_state_too_returns_its_step_count():
    _, _, kept = run("reference", 0.15, restore="parameters")
    _, distance, restored = run("reference", 0.15, restore="parameters_and_adam")
    assert float(kept.steps[0]) == 4 and float(restored.steps[0]) == 3
    assert distance == pytest.approx(2.5, rel=1e-6)


def test_the_loop_stops_at_max_off_iters():
    result, distance, _ = run("reference", 1e9, max_off_iters=7)
    assert (result.off_iters, result.backtracks) == (7, 0)
    assert distance == pytest.approx(7.0, rel=1e-6)


def test_members_backtrack_and_stop_each_on_their_own():
    """Three members whose KLs grow at different speeds: each follows the rule alone, and a
    member that stopped does not move while the others go on."""
    pop, adam = population(3)
    surrogate = Quadratic(pop, scale=torch.tensor([1.0, 4.0, 1e-6], dtype=torch.float64))
    s = settings(3, kl_threshold=0.15, max_off_iters=10)
    results = off_policy_loop(pop, adam, surrogate, torch.tensor([0, 1, 2]), s)
    # Member 0 as above; member 1 (KL 8 lr^2 j^2): 0.08 after one step, 0.32 after two: the
    # retry at lr / 2 (KL 0.18) is rejected, at lr / 4 (0.125) accepted; member 2 never leaves.
    assert [(r.off_iters, r.backtracks) for r in results] == [(3, 1), (2, 2), (10, 0)]
    assert [moved(pop, surrogate, m) for m in range(3)] == pytest.approx(
        [2.5, 1.25, 10.0], rel=1e-6
    )
    for m, single in enumerate(results):
        pop1, adam1 = population()
        alone = Quadratic(pop1, scale=surrogate.scale[m : m + 1])
        (r,) = off_policy_loop(pop1, adam1, alone, torch.tensor([0]), settings(1, max_off_iters=10))
        assert (r.off_iters, r.backtracks, r.lr) == (single.off_iters, single.backtracks, single.lr)


def test_adam_reset_starts_each_epoch_with_fresh_moments_for_the_members_in_it():
    # Adam's first step from fresh moments is lr * g / (|g| + eps) (m = (1 - b1) g and
    # v = (1 - b2) g^2, both bias-corrected back to g and g^2): computed here by hand.
    pop, adam = population(2)
    ones = torch.ones(2, dtype=torch.bool)
    for _ in range(3):  # a history of one gradient...
        adam.step(
            {k: torch.ones_like(v) for k, v in pop.params.items()}, torch.full((2,), LR), ones
        )
    adam.reset(torch.tensor([True, False]))
    assert float(adam.steps[0]) == 0 and float(adam.steps[1]) == 3
    before = {k: v.detach().clone() for k, v in pop.params.items()}
    g = {k: -2.0 * torch.ones_like(v) for k, v in pop.params.items()}  # ...then the opposite one
    adam.step(g, torch.full((2,), LR), ones)
    for k, v in pop.params.items():
        step = before[k] - v.detach()
        assert torch.allclose(step[0], torch.full_like(step[0], -LR * 2 / (2 + adam.eps)))
        assert not torch.allclose(step[1], step[0])  # member 1 still carries its momentum


def test_adam_reset_epoch_counts_only_the_epochs_own_steps():
    for reset, expected in ((False, 8), (True, 4)):
        pop, adam = population()
        for _ in range(2):  # two epochs of 4 tried steps each (see the first test)
            surrogate = Quadratic(pop)
            off_policy_loop(pop, adam, surrogate, torch.tensor([0]), settings(adam_reset=reset))
        assert float(adam.steps[0]) == expected


class Poisoned(Quadratic):
    """The quadratic surrogate, with a gradient that is not finite (NaN, through a hook on the
    objective's input) for the members ``poisoned`` on the calls ``calls`` (1 = theta' = theta,
    2 = after the first step, ...): the objective stays finite, so only the gradient is broken."""

    def __init__(self, population, poisoned: set[int], calls) -> None:
        super().__init__(population)
        self.poisoned, self.poison_calls = poisoned, calls

    def __call__(self, rows: torch.Tensor):
        estimate = super().__call__(rows)
        if self.calls not in self.poison_calls:
            return estimate
        log_std = self.population.params["log_std"].index_select(0, rows) * 1.0
        bad = torch.tensor([int(r) in self.poisoned for r in rows])
        log_std.register_hook(lambda g: torch.where(bad[:, None], torch.nan, g))
        estimate.objective = log_std.sum(-1)
        return estimate


def adam_is_finite(adam: PopulationAdam, s: int = 0) -> bool:
    moments = [*adam.exp_avg.values(), *adam.exp_avg_sq.values()]
    return all(bool(torch.isfinite(v[s]).all()) for v in moments)


@pytest.mark.parametrize("restore", ["parameters", "parameters_and_adam"])
def test_a_non_finite_gradient_is_rejected_and_the_next_epoch_steps_as_usual(restore):
    """The gradient after the first step is NaN: that step is rejected where the NaN arises
    and retried smaller, Adam's moments stay finite, and the next epoch takes its steps (on
    the old code the NaN entered Adam and every later step of the member was rejected)."""
    pop, adam = population()
    s = settings(restore=restore)
    poisoned = Poisoned(pop, {0}, calls={2})
    (first,) = off_policy_loop(pop, adam, poisoned, torch.tensor([0]), s)
    # The first step's point has a NaN gradient: rejected, retried at lr / 2, accepted; the
    # epoch ends there (the reference's rule).
    assert (first.off_iters, first.backtracks) == (1, 1)
    assert first.non_finite == []  # mended by the smaller step: the member goes on
    assert moved(pop, poisoned) == pytest.approx(0.5, rel=1e-6)
    assert adam_is_finite(adam)
    (second,) = off_policy_loop(pop, adam, Quadratic(pop), torch.tensor([0]), s)
    assert second.off_iters >= 2 and adam_is_finite(adam)
    assert all(torch.isfinite(v).all() for v in pop.params.values())


def test_a_gradient_that_stays_non_finite_stops_the_member_and_names_it():
    """Every step's gradient is NaN for member 0: every try is rejected and the member's
    result names what broke; member 1, in the same loop, steps exactly as on its own."""
    pop, adam = population(2)
    s = settings(2)
    poisoned = Poisoned(pop, {0}, calls=range(2, 100))
    results = off_policy_loop(pop, adam, poisoned, torch.tensor([0, 1]), s)
    assert results[0].off_iters == 0 and results[0].backtracks == s.backtrack_tries - 1
    assert results[0].non_finite == ["gradient of the objective at every step tried"]
    assert moved(pop, poisoned, 0) == 0.0 and adam_is_finite(adam, 0)
    pop1, adam1 = population()
    (alone,) = off_policy_loop(pop1, adam1, Quadratic(pop1), torch.tensor([0]), settings())
    assert (results[1].off_iters, results[1].backtracks, results[1].non_finite) == (
        alone.off_iters, alone.backtracks, [],
    )  # fmt: skip


def test_a_non_finite_gradient_at_the_sampling_policy_stops_the_member_before_a_step():
    pop, adam = population()
    poisoned = Poisoned(pop, {0}, calls={1})
    (result,) = off_policy_loop(pop, adam, poisoned, torch.tensor([0]), settings())
    assert result.off_iters == 0 and float(adam.steps[0]) == 0
    assert result.non_finite == ["gradient of the objective at the sampling policy"]


def test_an_overflowing_adam_state_is_rejected_and_restored():
    """A finite but huge gradient (1e30: its square overflows float32's Adam second moment to
    inf, which would freeze the member: m / sqrt(inf) = 0) is rejected like a NaN, and the
    Adam state is restored to the last accepted step's."""
    from hmepol_cli.config import PolicyConfig
    from hmepol_cli.policies import make_policy

    pop = PolicyPopulation([make_policy(PolicyConfig(name="markov", hidden=[4]), 2, 2)])
    adam = PopulationAdam(pop.params)

    class Huge(Quadratic):
        def __call__(self, rows):
            estimate = super().__call__(rows)
            if self.calls == 3:  # the gradient at the second step's point: 1e30 per entry
                log_std = self.population.params["log_std"].index_select(0, rows)
                estimate.objective = (log_std * 1e30).sum(-1) - (log_std * 1e30).sum(-1).detach()
                estimate.objective = estimate.objective + log_std.sum(-1).detach()
            return estimate

    (result,) = off_policy_loop(pop, adam, Huge(pop), torch.tensor([0]), settings())
    assert adam_is_finite(adam)
    assert result.non_finite == [] and result.off_iters >= 1


def test_a_member_whose_gradient_is_never_finite_fails_in_one_line_naming_epoch_and_quantity(
    tmp_path, monkeypatch
):
    """End to end: member 1 of a population of two gets NaN gradients from the start. It stops
    at epoch 0 with a one-line failure naming the epoch and the quantity (never a silent stall),
    and member 0 trains on to the end."""
    import json

    from hmepol_cli import mepol
    from hmepol_cli.trainer import Trainer
    from tests.test_trainer import compose_cfg

    real = mepol._gradients

    def poisoned(value, params):
        grads = real(value, params)
        return {k: torch.cat([g[:1], torch.full_like(g[1:], torch.nan)]) for k, g in grads.items()}

    monkeypatch.setattr(mepol, "_gradients", poisoned)
    cfgs = [compose_cfg("epochs=2", "progress=false", f"seed={s}") for s in (0, 1)]
    trainer = Trainer(cfgs, [tmp_path / f"seed{s}" for s in (0, 1)])
    trainer.train()
    failure = json.loads((tmp_path / "seed1" / "run.json").read_text())["failure"]
    assert failure["epoch"] == 0
    assert failure["reason"] == (
        "non-finite gradient of the objective at the sampling policy at epoch 0: the run stopped "
        "there"
    )
    assert json.loads((tmp_path / "seed0" / "run.json").read_text())["status"] == "finished"
