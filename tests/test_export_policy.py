"""An exported run keeps its final policy (weights only) and fine-tuning starts from it, and its
launch log; the resume kit, with its optimizer state, is exported only when asked."""

from __future__ import annotations

import pandas as pd
import pytest
import torch

from hmepol_cli.report.export import export_runs
from hmepol_cli.run import CHECKPOINT, COMMANDS, FINAL_POLICY, load_checkpoint, load_trained_policy
from tests.test_cli import TINY, hmepol


@pytest.mark.slow
def test_an_exported_run_keeps_its_final_policy_for_finetuning(tmp_path):
    run = tmp_path / "runs" / "mepol-0"
    hmepol("train", *TINY, "algo=mepol", "epochs=2", f"hydra.run.dir={run}", cwd=tmp_path)
    (kept,) = export_runs(tmp_path / "runs", tmp_path / "kept")
    assert not (kept / CHECKPOINT).exists()
    assert (kept / COMMANDS).read_text() == (run / COMMANDS).read_text()  # when it was launched
    policy = load_checkpoint(kept / FINAL_POLICY)
    assert "optimizer" not in policy and "generator" not in policy
    full = load_checkpoint(run / CHECKPOINT)
    assert policy["epoch"] == full["epoch"] == 2
    for name, weights in full["policy"].items():
        assert torch.equal(policy["policy"][name], weights)
    trained, _, epochs = load_trained_policy(kept)  # the same policy, from the export alone
    original, _, _ = load_trained_policy(run)
    assert epochs == 2
    for a, b in zip(trained.parameters(), original.parameters(), strict=True):
        assert torch.equal(a, b)
    hmepol("finetune", f"init={kept}", "epochs=1", "episodes=4", "horizon=20", "targets=1",
           "config=0", "progress=false", f"hydra.run.dir={tmp_path / 'ft'}",
           cwd=tmp_path)  # fmt: skip
    assert len(pd.read_csv(tmp_path / "ft" / "finetune.csv")) == 1
    (with_kit,) = export_runs(tmp_path / "runs", tmp_path / "moved", kits=True)
    assert (with_kit / CHECKPOINT).read_bytes() == (run / CHECKPOINT).read_bytes()
