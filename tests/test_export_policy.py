"""An exported run keeps its final policy (weights only) and fine-tuning starts from it, and its
launch log; the resume kit, with its optimizer state, is exported only when asked."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import torch

from hmepol_cli.report.export import export_runs
from hmepol_cli.run import (
    CHECKPOINT,
    COMMANDS,
    FINAL_POLICY,
    load_checkpoint,
    load_trained_policy,
    save_checkpoint,
)
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


def _run_with_everything(run):
    """A run directory with every file the export reads: tables, final positions, checkpoint."""
    (run / "eval").mkdir(parents=True)
    (run / "run.json").write_text('{"status": "finished"}')
    (run / "epochs.csv").write_text("epoch,entropy_c0\n0,1.0\n")
    (run / "steps.csv").write_text("epoch,accepted,kl_one_step,kl_exact\n0,True,0.1,0.2\n")
    np.savez(run / "eval" / "final.npz", positions_c0=np.zeros((2, 3, 2), np.float32))
    weights = {"w": torch.arange(4.0)}
    save_checkpoint(run / CHECKPOINT, {"epoch": 1, "policy": weights, "optimizer": {"m": 1.0}})


def test_an_export_without_diagnostics_or_policy_leaves_them_out_and_removes_stale_copies(
    tmp_path,
):
    _run_with_everything(tmp_path / "runs" / "r")
    (full,) = export_runs(tmp_path / "runs", tmp_path / "kept")
    assert (full / "steps.csv.gz").is_file() and (full / FINAL_POLICY).is_file()
    (lean,) = export_runs(tmp_path / "runs", tmp_path / "kept", diagnostics=False, policy=False)
    assert lean == full
    assert not (lean / "steps.csv.gz").exists()  # the earlier, partial copy is gone too
    assert not (lean / FINAL_POLICY).exists()
    assert (lean / "epochs.csv").read_text() == "epoch,entropy_c0\n0,1.0\n"
    assert (lean / "eval" / "final.npz").is_file()
    (bare,) = export_runs(tmp_path / "runs", tmp_path / "kept", policy=False, positions=False)
    assert not (bare / "eval" / "final.npz").exists()  # the earlier copy is gone as well
    assert (bare / "epochs.csv").read_text() == "epoch,entropy_c0\n0,1.0\n"
    (diagnosed,) = export_runs(tmp_path / "runs", tmp_path / "other", policy=False)
    assert (diagnosed / "steps.csv.gz").is_file() and not (diagnosed / FINAL_POLICY).exists()
    (kit,) = export_runs(tmp_path / "runs", tmp_path / "moved", kits=True, policy=False)
    assert (kit / CHECKPOINT).is_file() and not (kit / FINAL_POLICY).exists()
    (policy,) = export_runs(tmp_path / "runs", tmp_path / "weights", diagnostics=False)
    weights_only = load_checkpoint(policy / FINAL_POLICY)
    assert set(weights_only) == {"epoch", "policy"} and not (policy / "steps.csv.gz").exists()
    assert torch.equal(weights_only["policy"]["w"], torch.arange(4.0))
