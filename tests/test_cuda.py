"""device=cuda end to end, on a machine with a CUDA GPU (skipped elsewhere): training for every
algorithm, policy and bptt mode, populations under vmap against the member loop, resume,
evaluation, fine-tuning and the report."""

from __future__ import annotations

import pandas as pd
import pytest
import torch

from hmepol_cli.rollout import collect, draw_configurations
from tests.test_cli import TINY, hmepol
from tests.test_trainer import compare_vmap_with_the_member_loop, compose_cfg

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU here")


CASES = [
    ("mepol", "markov", "1"),
    ("alphamepol", "markov", "1"),
    ("hmepol", "recursive", "1"),
    ("hmepol", "recursive", "3"),
    ("hmepol", "recursive", "full"),
    ("hmepol", "twohead", "1"),
    ("hmepol", "gru", "full"),
    ("hmepol", "lstm", "3"),
]


@pytest.mark.parametrize("algo, policy, bptt", CASES)
def test_a_population_trains_on_the_gpu(tmp_path, algo, policy, bptt):
    from hmepol_cli.trainer import Trainer

    overrides = (f"algo={algo}", f"policy={policy}", f"policy.bptt={bptt}", "device=cuda")
    cfgs = [compose_cfg(*overrides, "epochs=2", f"seed={s}") for s in (0, 1)]
    trainer = Trainer(cfgs, [tmp_path / f"seed{s}" for s in (0, 1)])
    assert trainer.population._vmapped() and trainer.population.device.type == "cuda"
    trainer.train()
    for s in (0, 1):
        rows = pd.read_csv(tmp_path / f"seed{s}" / "epochs.csv")
        assert len(rows) == 2 and rows.entropy.notna().all() and (rows.off_iters > 0).all()
        assert (tmp_path / f"seed{s}" / "eval" / "final.npz").is_file()


@pytest.mark.parametrize("algo, policy, bptt", CASES)
def test_vmap_on_the_gpu_equals_the_member_loop_on_the_gpu(tmp_path, algo, policy, bptt):
    overrides = (f"algo={algo}", f"policy={policy}", f"policy.bptt={bptt}", "device=cuda")
    compare_vmap_with_the_member_loop(tmp_path, *overrides, grad_rtol=1e-8)


@pytest.mark.parametrize("algo, policy, bptt", CASES[:3] + CASES[-2:])
def test_a_captured_rollout_replays_what_the_steps_compute(tmp_path, algo, policy, bptt):
    """cuda_graphs: after an epoch (which captured the rollout and then changed the policies),
    a replay of the graph equals the same rollout stepped eagerly, from the same random
    streams (float64)."""
    from hmepol_cli.trainer import Trainer

    overrides = (f"algo={algo}", f"policy={policy}", f"policy.bptt={bptt}", "precision=float64")
    cfgs = [compose_cfg(*overrides, "device=cuda", f"seed={s}") for s in (0, 1)]
    trainer = Trainer(cfgs, [tmp_path / f"seed{s}" for s in (0, 1)])
    trainer.epoch()
    assert len(trainer.graphs) == 1
    gens = [m.generator for m in trainer.members]
    configurations = torch.stack([draw_configurations(trainer.world, 10, 5, g) for g in gens])
    states = [g.get_state() for g in gens]
    replayed = collect(
        trainer.world, trainer.population, None, configurations, 40, gens, graphs=trainer.graphs
    )
    for g, state in zip(gens, states, strict=True):
        g.set_state(state)
    stepped = collect(trainer.world, trainer.population, None, configurations, 40, gens)
    assert len(trainer.graphs) == 1  # replayed, not captured again
    for field in ("states", "actions", "histories", "log_probs"):
        torch.testing.assert_close(
            getattr(replayed, field), getattr(stepped, field), rtol=1e-12, atol=1e-12
        )


def test_cli_train_resume_sweep_finetune_and_report_on_the_gpu(tmp_path):
    run = tmp_path / "run"
    train = ("train", *TINY, "algo=hmepol", "epochs=2", "device=cuda", f"hydra.run.dir={run}")
    hmepol(*train, cwd=tmp_path)
    hmepol("train", f"resume={run}", "epochs=3", "device=cuda", cwd=tmp_path)
    assert len(pd.read_csv(run / "epochs.csv")) == 3
    sweep = ("sweep", *TINY, "epochs=2", "device=cuda", "seed=0,1,2", "hydra/launcher=population")
    hmepol(*sweep, f"hydra.sweep.dir={tmp_path / 'sweep'}", cwd=tmp_path)
    finetune = ("finetune", f"init={run}", "epochs=2", "episodes=4", "horizon=30", "targets=1")
    hmepol(*finetune, "config=0", "device=cuda", f"output_dir={tmp_path / 'ft'}", cwd=tmp_path)
    assert len(pd.read_csv(tmp_path / "ft" / "finetune.csv")) == 2
    report = hmepol("report", str(tmp_path), "--out", str(tmp_path / "report"), cwd=tmp_path)
    # The training run, the sweep's three members and the fine-tuning.
    assert "5 runs used" in report.stdout
