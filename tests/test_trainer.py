"""The trust-region loop in-process: the KL bound holds, backtracking engages, lr is restored."""

from __future__ import annotations

from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra

from hmepol_cli.cli import register_configs  # noqa: F401  (schema and resolvers)
from hmepol_cli.trainer import Trainer
from tests.test_cli import TINY


def tiny_trainer(tmp_path, *overrides: str) -> Trainer:
    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="hmepol_cli.conf", version_base="1.3"):
        cfg = compose(config_name="config", overrides=[*TINY, *overrides])
    GlobalHydra.instance().clear()
    return Trainer(cfg, tmp_path / "run")


def test_every_accepted_update_stays_inside_the_trust_region(tmp_path):
    threshold = 1e-4
    trainer = tiny_trainer(tmp_path, f"algo.kl_threshold={threshold}", "algo.lr=1e-2")
    for _ in range(3):
        stats = trainer.epoch()
        assert stats.update.kl <= threshold
        assert trainer.optimizer.param_groups[0]["lr"] == 1e-2  # restored after backtracking
    # With so tight a region and so large a step the first step overshoots: lr is halved.
    assert stats.update.backtracks > 0 and stats.update.lr < 1e-2


def test_a_loose_region_runs_every_off_policy_iteration(tmp_path):
    trainer = tiny_trainer(tmp_path, "algo.kl_threshold=1e9", "algo.max_off_iters=4")
    stats = trainer.epoch()
    assert stats.update.off_iters == 4 and stats.update.backtracks == 0
    # The IW objective of the accepted policy improved on the sampling policy's estimate.
    assert float(stats.update.entropies.mean()) > float(stats.entropies.mean())
