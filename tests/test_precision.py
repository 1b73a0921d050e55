"""Mixed precision: which products are lowered, which are not, and that the
trust region starts from exactly 0 whatever the precision."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from omegaconf import OmegaConf

from hmepol_cli import estimators, mepol
from hmepol_cli.config import PolicyConfig
from hmepol_cli.errors import ConfigError
from hmepol_cli.policies import make_policy
from hmepol_cli.policies.base import HistoryLinear, OutputLinear
from hmepol_cli.precision import PRECISIONS, precision_of
from hmepol_cli.rollout import collect, draw_configurations
from hmepol_cli.surrogate import Surrogate
from tests.test_trainer import tiny_trainer


def dtypes_seen(policy: torch.nn.Module, run) -> dict[str, set[torch.dtype]]:
    """The output dtype of every linear layer of ``policy`` during ``run()``, by kind."""
    seen: dict[str, set[torch.dtype]] = {"hidden": set(), "output": set(), "history": set()}

    def hook(module, inputs, output):
        kind = (
            "output"
            if isinstance(module, OutputLinear)
            else "history"
            if isinstance(module, HistoryLinear)
            else "hidden"
        )
        seen[kind].add(output.dtype)

    handles = [
        m.register_forward_hook(hook) for m in policy.modules() if isinstance(m, torch.nn.Linear)
    ]
    try:
        run()
    finally:
        for h in handles:
            h.remove()
    return seen


@pytest.mark.parametrize("bptt, history", [(1, torch.bfloat16), (None, torch.float32)])
def test_bf16_lowers_the_hidden_layers_never_the_mean_and_the_history_only_at_bptt_1(bptt, history):
    torch.manual_seed(0)
    cfg = PolicyConfig(name="recursive", hidden=[16, 16], encoder_hidden=[16], history_size=6)
    policy = make_policy(cfg, 2, 2)
    states, actions = torch.randn(3, 7, 2), torch.randn(3, 7, 2)
    histories = torch.rand(3, 7, 6)

    def run():
        with PRECISIONS["bf16"].products(torch.device("cpu"), bptt):
            log_p = policy.log_prob(states, actions, histories, bptt)
        assert log_p.dtype == torch.float32

    seen = dtypes_seen(policy, run)
    assert seen == {"hidden": {torch.bfloat16}, "output": {torch.float32}, "history": {history}}
    # Outside the off-policy loop (rollouts, evaluation) nothing is lowered.
    plain = dtypes_seen(policy, lambda: policy.log_prob(states, actions, histories, bptt))
    assert set().union(*plain.values()) == {torch.float32}


@pytest.mark.parametrize("bptt", ["1", "full"])
def test_at_theta_prime_equal_theta_every_kl_is_exactly_zero_in_bf16(tmp_path, bptt):
    trainer = tiny_trainer(
        tmp_path, "algo=hmepol", "precision=bf16", f"policy.bptt={bptt}", "diagnostics=true"
    )
    gen = trainer.members[0].generator
    configurations = draw_configurations(trainer.world, 10, 5, gen)[None]
    rollout = collect(trainer.world, trainer.population, None, configurations, 40, [gen])
    particles = estimators.particles_by_batch(rollout.particles.flatten(0, 1), 5)
    neighbours = trainer.settings.estimator.search(particles)
    surrogate = Surrogate(
        trainer.population, rollout, neighbours, torch.tensor([0]), trainer.settings
    )
    start = surrogate(torch.tensor([0]))
    assert float(start.kl_one_step.detach()) == 0.0 and float(start.kl_exact) == 0.0
    on_policy = trainer.settings.estimator.entropy(neighbours)
    torch.testing.assert_close(start.entropies.detach()[0], on_policy, rtol=0, atol=1e-6)


def test_a_bf16_epoch_trains_and_changes_no_float32_state(tmp_path):
    trainer = tiny_trainer(tmp_path, "algo=hmepol", "precision=bf16")
    (stats,) = trainer.epoch()
    assert stats.update.off_iters > 0 and 0 <= stats.update.kl <= 0.5
    assert all(v.dtype == torch.float32 for v in trainer.population.params.values())
    assert all(v.dtype == torch.float32 for v in trainer.optimizer.exp_avg.values())


def test_precisions_are_checked_and_old_runs_keep_theirs():
    from hmepol_cli.config import check_precision

    with pytest.raises(ConfigError, match="GPU precision"):
        check_precision("tf32", "cpu")
    with pytest.raises(ConfigError, match="choose one of"):
        check_precision("fp8", "cpu")
    old = OmegaConf.create({"dtype": "float64", "matmul_precision": "highest"})
    assert precision_of(old).name == "float64"
    assert (
        precision_of(OmegaConf.create({"dtype": "float32", "matmul_precision": "high"})).name
        == "tf32"
    )
    assert precision_of(OmegaConf.create({"precision": "bf16"})).name == "bf16"


def test_a_bf16_epoch_is_checked_against_full_precision_and_float32_is_not(tmp_path):
    """The accepted policy's KL and IW entropy, recomputed in float32 at the end of the loop:
    the same numbers a float32 surrogate gives at those parameters."""
    trainer = tiny_trainer(tmp_path, "algo=hmepol", "precision=bf16")
    gen = trainer.members[0].generator
    configurations = draw_configurations(trainer.world, 10, 5, gen)[None]
    rollout = collect(trainer.world, trainer.population, None, configurations, 40, [gen])
    particles = estimators.particles_by_batch(rollout.particles.flatten(0, 1), 5)
    neighbours = trainer.settings.estimator.search(particles)
    members = torch.tensor([0])
    surrogate = Surrogate(trainer.population, rollout, neighbours, members, trainer.settings)
    (result,) = mepol.off_policy_loop(
        trainer.population, trainer.optimizer, surrogate, members, trainer.settings
    )
    full = dataclasses.replace(trainer.settings, precision=PRECISIONS["float32"])
    reference = Surrogate(trainer.population, rollout, neighbours, members, full)
    reference.behaviour = surrogate.behaviour_full  # the sampling likelihoods, in float32
    estimate = reference(torch.tensor([0]))
    assert result.kl_full_precision == pytest.approx(float(estimate.kl.detach()), rel=1e-6)
    assert result.entropy_iw_full_precision == pytest.approx(
        float(estimate.entropies.detach().mean()), rel=1e-6
    )
    assert result.kl_full_precision == pytest.approx(result.kl, rel=0.05)  # tiny, early: close
    (plain,) = tiny_trainer(tmp_path / "f32", "algo=hmepol").epoch()
    assert math.isnan(plain.update.kl_full_precision)
