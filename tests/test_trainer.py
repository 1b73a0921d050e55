"""The trust-region loop in-process: the KL bound holds, backtracking engages and is undone,
a population trains its members exactly as their own runs would, the exact trust region
catches what the one-step one misses, and divergence is reported."""

from __future__ import annotations

import logging

import numpy as np
import pandas as pd
import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra

from hmepol_cli import estimators, mepol
from hmepol_cli.rollout import collect, draw_configurations
from hmepol_cli.surrogate import Surrogate
from hmepol_cli.trainer import Trainer
from tests.test_cli import TINY


def compose_cfg(*overrides: str):
    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="hmepol_cli.conf", version_base="1.3"):
        cfg = compose(config_name="config", overrides=[*TINY, *overrides])
    GlobalHydra.instance().clear()
    return cfg


def tiny_trainer(tmp_path, *overrides: str) -> Trainer:
    return Trainer(compose_cfg(*overrides), tmp_path / "run")


def population(tmp_path, seeds, *overrides: str) -> Trainer:
    cfgs = [compose_cfg(*overrides, f"seed={s}") for s in seeds]
    return Trainer(cfgs, [tmp_path / f"member{s}" for s in seeds])


def test_every_accepted_update_stays_inside_the_trust_region(tmp_path):
    threshold = 1e-4
    trainer = tiny_trainer(tmp_path, f"algo.kl_threshold={threshold}", "algo.lr=1e-2")
    for _ in range(3):
        (stats,) = trainer.epoch()
        assert stats.update.kl <= threshold
    # With so tight a region and so large a step the first step overshoots: lr is halved ...
    assert stats.update.backtracks > 0 and stats.update.lr < 1e-2
    # ... for that epoch only: the next one starts again from algo.lr.
    assert stats.update.lr == pytest.approx(1e-2 / 2**stats.update.backtracks)


def test_a_loose_region_runs_every_off_policy_iteration(tmp_path):
    trainer = tiny_trainer(tmp_path, "algo.kl_threshold=1e9", "algo.max_off_iters=4")
    (stats,) = trainer.epoch()
    assert stats.update.off_iters == 4 and stats.update.backtracks == 0
    # The IW objective of the accepted policy improved on the sampling policy's estimate.
    assert float(stats.update.entropies.mean()) > float(stats.entropies.mean())


# ------------------------------------------------------------------ populations
@pytest.mark.parametrize(
    "algo, policy",
    [
        ("mepol", "markov"),
        ("alphamepol", "markov"),
        ("hmepol", "recursive"),
        ("hmepol", "markov"),
        ("mepol", "recursive"),
    ],
)
def test_each_member_of_a_population_trains_exactly_as_its_own_run(tmp_path, algo, policy):
    """Three seeds in one population and three separate runs: identical epochs, although the
    members stop their off-policy loops at different iterations."""
    overrides = (
        f"algo={algo}",
        f"policy={policy}",
        "algo.kl_threshold=0.02",
        "algo.max_off_iters=8",
    )
    seeds = (0, 1, 2)
    together = population(tmp_path / "population", seeds, *overrides)
    runs = [tiny_trainer(tmp_path / f"seed{s}", *overrides, f"seed={s}") for s in seeds]
    stopped_at = set()
    for _ in range(2):
        members = together.epoch()
        for s, run in enumerate(runs):
            (alone,) = run.epoch()
            mine = members[s]
            np.testing.assert_array_equal(mine.entropies, alone.entropies)
            np.testing.assert_array_equal(mine.batch_configurations, alone.batch_configurations)
            np.testing.assert_array_equal(mine.update.entropies, alone.update.entropies)
            assert (mine.update.kl, mine.update.off_iters, mine.update.backtracks) == (
                alone.update.kl,
                alone.update.off_iters,
                alone.update.backtracks,
            )
            stopped_at.add((mine.update.off_iters, mine.update.backtracks))
            for name, value in run.population.params.items():
                assert torch.equal(together.population.params[name][s], value[0]), name
    assert len(stopped_at) > 1, "the members should stop at different points"


def compare_vmap_with_the_member_loop(tmp_path, *overrides: str, grad_rtol: float = 1e-9):
    """Two seeds, float64, the same random streams: vmap over the members (what a GPU runs)
    and a loop over them (what a CPU runs) give the same rollout, likelihoods and gradients."""
    rollouts, values = [], []
    for vmap in ("off", "on"):
        trainer = population(
            tmp_path / vmap, (0, 1), "precision=float64", *overrides, f"vmap={vmap}"
        )
        assert trainer.population._vmapped() == (vmap == "on")
        gens = [m.generator for m in trainer.members]
        configurations = torch.stack([draw_configurations(trainer.world, 10, 5, g) for g in gens])
        rollout = collect(trainer.world, trainer.population, None, configurations, 40, gens)
        log_p = trainer.population.log_prob(
            None, rollout.inputs, rollout.actions, rollout.histories, trainer.settings.bptt
        )
        grads = torch.autograd.grad(
            log_p.sin().sum(), list(trainer.population.params.values()), allow_unused=True
        )
        rollouts.append(rollout)
        values.append((log_p, grads))
    torch.testing.assert_close(rollouts[0].states, rollouts[1].states, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(values[0][0], values[1][0], rtol=1e-10, atol=1e-10)
    for a, b in zip(values[0][1], values[1][1], strict=True):
        assert (a is None) == (b is None)  # twohead's history head is unused at bptt = 1
        if a is not None:
            torch.testing.assert_close(a, b, rtol=grad_rtol, atol=1e-10)


@pytest.mark.parametrize("name", ["markov", "recursive", "twohead", "gru", "lstm"])
@pytest.mark.parametrize("bptt", ["1", "3", "full"])
def test_vmap_and_the_member_loop_compute_the_same_function(tmp_path, name, bptt):
    if name == "markov" and bptt != "1":
        pytest.skip("a Markovian policy has no history")
    compare_vmap_with_the_member_loop(tmp_path, f"policy={name}", f"policy.bptt={bptt}")


def test_a_member_due_later_sits_out_the_epochs_it_already_has(tmp_path):
    """A population restored with members at different epochs (a crash between two members'
    checkpoints) runs each epoch only for the members that need it."""
    trainer = population(tmp_path, (0, 1), "epochs=3")
    trainer.members[1].start_epoch = 1
    before = trainer.population.member_state_dict(1)
    (stats,) = trainer.epoch([0])
    after = trainer.population.member_state_dict(1)
    assert all(torch.equal(before[k], after[k]) for k in before)
    assert stats.update.off_iters > 0


# ------------------------------------------------------------------ the exact trust region
def first_step(tmp_path, trust_region: str, kl_threshold: float):
    """One off-policy step of a recursive policy whose recursion is near-critical: a one-layer
    ReLU encoder h'_t = relu(W_s s_t + 0.99 h'_{t-1} + 0.05), as a ReLU recursion becomes when
    training makes it expansive. A step that changes the recursion a little changes every later
    history: the one-step likelihoods (stored h'_{t-1} as input) see one step of that change,
    the exact ones all of it. -> (update result, trainer, rollout, neighbours)"""
    trainer = tiny_trainer(
        tmp_path / f"{trust_region}-{kl_threshold}",
        "algo=hmepol",
        "policy.bptt=1",
        "policy.encoder_hidden=[]",
        "policy.init_mean_scale=1",
        "precision=float64",
        "algo.horizon=200",
        "algo.lr=1e-4",
        "algo.max_off_iters=1",
        "algo.lr_backtrack_tries=0",
        f"algo.trust_region={trust_region}",
        f"algo.kl_threshold={kl_threshold}",
    )
    params = trainer.population.params
    with torch.no_grad():
        history_size = params["encoder.0.weight"].shape[1]
        eye = torch.eye(history_size, dtype=torch.float64)
        params["encoder.0.weight"][0, :, 2:] = 0.99 * eye
        params["encoder.0.bias"][0] = 0.05
    gen = trainer.members[0].generator
    configurations = draw_configurations(trainer.world, 10, 5, gen)[None]
    rollout = collect(trainer.world, trainer.population, None, configurations, 200, [gen])
    particles = estimators.particles_by_batch(rollout.particles.flatten(0, 1), 5)
    neighbours = estimators.nearest_neighbours(particles, 5)
    members = torch.tensor([0])
    surrogate = Surrogate(trainer.population, rollout, neighbours, members, trainer.settings)
    (result,) = mepol.off_policy_loop(
        trainer.population, trainer.optimizer, surrogate, members, trainer.settings
    )
    return result, trainer, rollout, neighbours


def test_the_exact_trust_region_rejects_a_step_the_one_step_kl_accepts(tmp_path):
    one_step, *_ = first_step(tmp_path, "gradient", 1e9)
    exact, trainer, rollout, neighbours = first_step(tmp_path, "exact", 1e9)
    # The same step (the gradient uses bptt = 1 in both), judged by two KLs.
    for name, value in trainer.population.params.items():
        assert value.isfinite().all(), name
    # The exact KL, recomputed here from likelihoods over the whole history.
    full = trainer.population.log_prob(
        None, rollout.inputs, rollout.actions, rollout.histories, None
    ).detach()
    weights = estimators.importance_weights((full - rollout.log_probs).flatten(0, 1), 5)
    assert exact.kl == pytest.approx(float(estimators.kl_divergence(weights, neighbours).mean()))
    assert exact.kl > 3 * one_step.kl > 0  # measured: 4.99 and 0.97
    # A threshold between the two: the one-step region accepts the step, the exact one does not.
    threshold = (one_step.kl + exact.kl) / 2
    accepted, *_ = first_step(tmp_path, "gradient", threshold)
    rejected, *_ = first_step(tmp_path, "exact", threshold)
    assert accepted.off_iters == 1
    assert rejected.off_iters == 0


# ------------------------------------------------------------------ divergence is reported
def test_a_diverging_run_says_so_in_its_log_and_its_csv(tmp_path, caplog):
    trainer = tiny_trainer(
        tmp_path, "algo=hmepol", "epochs=2", "alarms.history_bound=1e-6", "progress=false"
    )
    with caplog.at_level(logging.WARNING, logger="hmepol"):
        trainer.train()
    rows = pd.read_csv(tmp_path / "run" / "epochs.csv")
    assert rows.diverged.all() and (rows.history_max > 1e-6).all()
    assert "diverging" in caplog.text and "alarms.history_bound" in caplog.text
    calm = tiny_trainer(tmp_path / "calm", "algo=hmepol", "epochs=1", "progress=false")
    calm.train()
    assert not pd.read_csv(tmp_path / "calm" / "run" / "epochs.csv").diverged.any()


# ------------------------------------------------------------------ float64 (the reference's)
@pytest.mark.parametrize("policy", ["markov", "recursive", "twohead", "gru", "lstm"])
@pytest.mark.parametrize("algo", ["mepol", "alphamepol", "hmepol"])
def test_float64_runs_every_algorithm_and_policy(tmp_path, algo, policy):
    trainer = tiny_trainer(
        tmp_path, f"algo={algo}", f"policy={policy}", "precision=float64", "policy.bptt=2"
    )
    assert all(v.dtype == torch.float64 for v in trainer.population.params.values())
    (stats,) = trainer.epoch()
    assert np.isfinite(stats.entropies).all() and np.isfinite(stats.update.entropies).all()
    assert stats.update.off_iters > 0 and 0 <= stats.update.kl <= 0.5
    assert all(v.dtype == torch.float64 for v in trainer.population.params.values())


# ------------------------------------------------------------------ diagnostics
def test_exact_and_one_step_kl_agree_at_full_bptt_and_are_zero_at_the_start(tmp_path):
    trainer = tiny_trainer(
        tmp_path, "algo=hmepol", "policy.bptt=full", "precision=float64", "diagnostics=true"
    )
    gen = trainer.members[0].generator
    configurations = draw_configurations(trainer.world, 10, 5, gen)[None]
    rollout = collect(trainer.world, trainer.population, None, configurations, 40, [gen])
    particles = estimators.particles_by_batch(rollout.particles.flatten(0, 1), 5)
    neighbours = estimators.nearest_neighbours(particles, 5)
    members = torch.tensor([0])
    surrogate = Surrogate(trainer.population, rollout, neighbours, members, trainer.settings)
    start = surrogate(torch.tensor([0]))
    assert float(start.kl_one_step.detach()) == 0.0 and float(start.kl_exact) == 0.0
    (result,) = mepol.off_policy_loop(
        trainer.population, trainer.optimizer, surrogate, members, trainer.settings
    )
    assert len(result.steps) == result.off_iters + result.backtracks > 0
    for step in result.steps:
        assert step.kl_exact == pytest.approx(step.kl_one_step, rel=1e-9, abs=1e-12)
        assert step.kl == step.kl_one_step  # the trust region judged by the one-step KL


def test_diagnostics_write_every_step_and_change_no_number(tmp_path):
    overrides = ("algo=hmepol", "epochs=2", "algo.kl_threshold=0.05", "algo.lr=1e-2")
    plain = tiny_trainer(tmp_path / "plain", *overrides)
    plain.train()
    traced = tiny_trainer(tmp_path / "traced", *overrides, "diagnostics=true")
    traced.train()
    a = pd.read_csv(tmp_path / "plain" / "run" / "epochs.csv")
    b = pd.read_csv(tmp_path / "traced" / "run" / "epochs.csv")
    same = ["entropy", "entropy_iw", "kl", "off_iters", "backtracks", "lr", "history_max"]
    pd.testing.assert_frame_equal(a[same], b[same])
    assert a.kl_exact.isna().all() and b.kl_exact.notna().all()
    steps = pd.read_csv(tmp_path / "traced" / "run" / "steps.csv")
    assert not (tmp_path / "plain" / "run" / "steps.csv").exists()
    per_epoch = steps.groupby("epoch")
    assert (per_epoch.accepted.sum().values == b.off_iters.values).all()
    assert (per_epoch.size().values == (b.off_iters + b.backtracks).values).all()
    last = steps[steps.accepted].groupby("epoch").last()
    np.testing.assert_allclose(last.kl.values, b.kl.values)
    np.testing.assert_allclose(last.kl_exact.values, b.kl_exact.values)
    assert ((b.log_std < 0) & (b.clip_share >= 0) & (b.clip_share <= 1)).all()


def test_kept_checkpoints_hold_the_policy_of_their_epoch(tmp_path):
    from hmepol_cli.run import load_checkpoint, resolve_checkpoint

    trainer = tiny_trainer(tmp_path, "epochs=4", "checkpoint.keep_every=2")
    trainer.train()
    run = tmp_path / "run"
    kept = sorted(p.name for p in (run / "checkpoints").iterdir())
    assert kept == ["epoch_0002.pt", "epoch_0004.pt", "last.pt"]
    assert load_checkpoint(resolve_checkpoint(f"{run}@2")[1])["epoch"] == 2
    last, four = (load_checkpoint(run / "checkpoints" / n) for n in ("last.pt", "epoch_0004.pt"))
    assert all(torch.equal(last["policy"][k], four["policy"][k]) for k in last["policy"])
    from hmepol_cli.errors import RunDirError

    with pytest.raises(RunDirError, match="it has: 2, 4"):
        resolve_checkpoint(f"{run}@3")


def test_fine_tuning_starts_from_a_kept_checkpoint_and_records_its_epoch(tmp_path):
    import json

    from hmepol_cli.finetune import finetune

    tiny_trainer(tmp_path, "epochs=2", "checkpoint.keep_every=1").train()
    run = tmp_path / "run"
    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="hmepol_cli.conf", version_base="1.3"):
        cfg = compose(
            config_name="finetune",
            overrides=[f"init={run}@1", "epochs=1", "episodes=2", "horizon=20", "targets=1",
                       "config=0", "progress=false", f"output_dir={tmp_path / 'ft'}"],
        )  # fmt: skip
    GlobalHydra.instance().clear()
    out = finetune(cfg)
    rows = pd.read_csv(out / "finetune.csv")
    assert (rows.init_epoch == 1).all() and rows.init.str.endswith("@1").all()
    assert json.loads((out / "run.json").read_text())["init_epoch"] == 1


# ------------------------------------------------------------------ members of their own
def compare_members_with_their_runs(tmp_path, member_overrides, epochs: int = 2):
    """One population of members with their own overrides against a run of each alone: the
    same epochs, bit for bit (on a CPU each member's calls are its own run's)."""
    cfgs = [compose_cfg(*o) for o in member_overrides]
    together = Trainer(cfgs, [tmp_path / f"member{i}" for i in range(len(cfgs))])
    runs = [Trainer(c, tmp_path / f"alone{i}") for i, c in enumerate(cfgs)]
    for _ in range(epochs):
        members = together.epoch()
        for mine, run in zip(members, runs, strict=True):
            (alone,) = run.epoch()
            np.testing.assert_array_equal(mine.entropies, alone.entropies)
            np.testing.assert_array_equal(mine.batch_configurations, alone.batch_configurations)
            np.testing.assert_array_equal(mine.objective, alone.objective)
            np.testing.assert_array_equal(mine.update.kl, alone.update.kl)
            np.testing.assert_array_equal(mine.update.entropies, alone.update.entropies)
            assert (mine.update.off_iters, mine.update.backtracks) == (
                alone.update.off_iters,
                alone.update.backtracks,
            )
    return together


def test_members_with_their_own_winds_and_seeds_train_as_their_own_runs(tmp_path):
    members = [
        ("env=corridor", "algo=hmepol", f"wind={w}", f"seed={s}", "algo.trajectories=4",
         "algo.batch_size=1")
        for w in (0.05, 0.4)
        for s in (0, 1)
    ]  # fmt: skip
    together = compare_members_with_their_runs(tmp_path, members)
    assert [together.world.facts(s)["wind"] for s in range(4)] == [0.05, 0.05, 0.4, 0.4]


def test_mepol_and_alpha_mepol_are_members_of_one_population(tmp_path):
    members = [(f"algo={a}", "algo.alpha=0.35" if a == "alphamepol" else "algo.alpha=1.0",
                f"seed={s}") for a in ("mepol", "alphamepol") for s in (0, 1)]  # fmt: skip
    together = compare_members_with_their_runs(tmp_path, members)
    objectives = [m.objective for m in together.settings.members]
    assert objectives == ["mean", "mean", "cvar", "cvar"]


def test_members_with_their_own_learning_rates_and_trust_regions(tmp_path):
    members = [(f"algo.lr={lr}", f"algo.kl_threshold={kl}") for lr, kl in
               ((1e-3, 0.5), (1e-2, 0.05), (3e-3, 0.2))]  # fmt: skip
    compare_members_with_their_runs(tmp_path, members)


def test_runs_that_differ_in_the_program_cannot_share_a_population(tmp_path):
    from hmepol_cli.errors import ConfigError

    with pytest.raises(ConfigError, match="policy.hidden"):
        Trainer(
            [compose_cfg("seed=0"), compose_cfg("seed=1", "policy.hidden=[8]")],
            [tmp_path / "a", tmp_path / "b"],
        )


def test_members_stepped_in_chunks_train_as_all_together(tmp_path):
    """chunk_members=2 steps a population of four as two batched calls: the same epochs."""
    seeds = (0, 1, 2, 3)
    whole = population(tmp_path / "whole", seeds)
    chunked = population(tmp_path / "chunked", seeds, "chunk_members=2")
    assert (whole.chunk, chunked.chunk) == (4, 2)
    for _ in range(2):
        for a, b in zip(whole.epoch(), chunked.epoch(), strict=True):
            np.testing.assert_array_equal(a.entropies, b.entropies)
            np.testing.assert_array_equal(a.update.entropies, b.update.entropies)
            assert (a.update.off_iters, a.update.kl) == (b.update.off_iters, b.update.kl)


def test_a_gpu_population_is_cut_to_the_free_memory():
    from hmepol_cli.config import PolicyConfig
    from hmepol_cli.policies import make_policy
    from hmepol_cli.population import PolicyPopulation

    cfg = PolicyConfig(name="recursive")  # the thesis' (300, 300) networks, |h'| = 100
    pop = PolicyPopulation([make_policy(cfg, 2, 2)])
    # The corridor's 40,000 particles: every layer's output (300 x 4 + 100 + 2) plus h', x 3,
    # in float32: ~0.65 GB a member.
    assert 0.5e9 < pop.bytes_per_member(40_000) < 0.8e9
