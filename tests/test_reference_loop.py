"""The population's off-policy loop (mepol.off_policy_loop: masks, one host sync an iteration,
members that stop at different points) computes exactly what Algorithm 3.1's loop for one
member computes (mepol.reference_loop, written as the thesis does): bit for bit on a CPU, for
every option of the loop, with members that have hyperparameters of their own."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from hmepol_cli import estimators, mepol
from hmepol_cli.population import PolicyPopulation, PopulationAdam
from hmepol_cli.rollout import collect, draw_configurations
from hmepol_cli.surrogate import Surrogate, _select_batches
from hmepol_cli.trainer import Trainer
from tests.test_trainer import compose_cfg

# Each member its own learning rate, trust region and iterations: a loose one that takes every
# step, and tight ones whose steps are rejected first, later, or after a few (backtracking).
MEMBERS = [
    ("algo.lr=1e-3", "algo.kl_threshold=0.5", "algo.max_off_iters=5"),
    ("algo.lr=1e-2", "algo.kl_threshold=0.05", "algo.max_off_iters=6"),
    ("algo.lr=3e-2", "algo.kl_threshold=0.02", "algo.max_off_iters=4"),
    ("algo.lr=4e-3", "algo.kl_threshold=0.1", "algo.max_off_iters=12"),
]
SMALL = ("algo.horizon=20", "policy.hidden=[16,16]", "policy.encoder_hidden=[16,16]",
         "policy.history_size=4")  # fmt: skip
OPTIONS = {
    "reference backtracking": ("algo=mepol",),
    "first-step backtracking": ("algo=mepol", "algo.backtracking=first_step"),
    "restore Adam too": ("algo=mepol", "algo.backtrack_restore=parameters_and_adam"),
    "first step, restore Adam": ("algo=hmepol", "algo.backtracking=first_step",
                                 "algo.backtrack_restore=parameters_and_adam"),  # fmt: skip
    "HMepol, one-step KL": ("algo=hmepol",),
    "HMepol, exact trust region": ("algo=hmepol", "algo.trust_region=exact"),
    "HMepol, bptt=full": ("algo=hmepol", "policy.bptt=full"),
    "HMepol, bptt=3, diagnostics": ("algo=hmepol", "policy.bptt=3", "diagnostics=true"),
    "Adam reset every epoch": ("algo=hmepol", "algo.adam_reset=epoch"),
    "alpha-Mepol (CVaR)": ("algo=alphamepol", "algo.alpha=0.5"),
}


def one_member(trainer: Trainer, m: int) -> tuple[PolicyPopulation, PopulationAdam]:
    """Member m of the trainer's population as a population of one, with its Adam state."""
    single = PolicyPopulation([trainer.population.member(m)]).to("cpu", trainer.dtype)
    adam = PopulationAdam(single.params)
    adam.load_member_state_dict(0, trainer.optimizer.member_state_dict(m))
    return single, adam


def assert_same_result(population: mepol.UpdateResult, single: mepol.UpdateResult) -> None:
    for f in dataclasses.fields(mepol.UpdateResult):
        a, b = getattr(population, f.name), getattr(single, f.name)
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b, err_msg=f.name)
        else:
            assert a == b or (a != a and b != b), (f.name, a, b)  # NaN equals NaN here


@pytest.mark.parametrize("option", OPTIONS, ids=list(OPTIONS))
def test_the_population_loop_is_algorithm_3_1_for_every_member(tmp_path, option):
    cfgs = [compose_cfg(*SMALL, *OPTIONS[option], *own, f"seed={s}", "epochs=2")
            for s, own in enumerate(MEMBERS)]  # fmt: skip
    trainer = Trainer(cfgs, [tmp_path / f"m{s}" for s in range(len(MEMBERS))])
    singles = [one_member(trainer, m) for m in range(len(MEMBERS))]
    settings, a = trainer.settings, trainer.cfg.algo
    members = torch.arange(len(MEMBERS))
    tried = set()
    for epoch in range(2):  # the second epoch starts from the Adam state the first one left
        generators = [m.generator for m in trainer.members]
        configurations = torch.stack(
            [draw_configurations(trainer.world, a.trajectories, a.batch_size, g)
             for g in generators]
        )  # fmt: skip
        rollout = collect(trainer.world, trainer.population, None, configurations, a.horizon,
                          generators)  # fmt: skip
        particles = estimators.particles_by_batch(rollout.particles.flatten(0, 1), a.batch_size)
        neighbours = settings.estimator.search(particles)
        surrogate = Surrogate(trainer.population, rollout, neighbours, members, settings)
        results = mepol.off_policy_loop(
            trainer.population, trainer.optimizer, surrogate, members, settings
        )
        batches = neighbours.radius.shape[0] // len(MEMBERS)
        for m, (single, adam) in enumerate(singles):
            own = dataclasses.replace(settings, members=(settings.members[m],))
            mine = torch.tensor([m])
            alone = Surrogate(single, rollout.rows(mine),
                                    _select_batches(neighbours, mine, batches),
                                    torch.tensor([0]), own)  # fmt: skip
            expected = mepol.reference_loop(single, adam, alone, own)
            assert_same_result(results[m], expected)
            tried.add((results[m].off_iters, results[m].backtracks))
            for k, v in trainer.population.params.items():
                assert torch.equal(v[m], single.params[k][0]), (epoch, m, k)
            state, kept = trainer.optimizer.member_state_dict(m), adam.member_state_dict(0)
            assert torch.equal(state["step"], kept["step"])
            for k in state["exp_avg"]:
                assert torch.equal(state["exp_avg"][k], kept["exp_avg"][k]), (epoch, m, k)
                assert torch.equal(state["exp_avg_sq"][k], kept["exp_avg_sq"][k]), (epoch, m, k)
    # The members went different ways: some backtracked, first or after accepted steps.
    assert len(tried) >= 3 and any(b > 0 for _, b in tried), tried
