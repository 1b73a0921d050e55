"""Sweeps on the joblib launcher: a run per job, finished jobs skipped, failures isolated."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from omegaconf import OmegaConf

from tests.test_cli import TINY


def sweep(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "hmepol_cli.cli",
            "sweep",
            *TINY,
            "epochs=1",
            *args,
            f"hydra.sweep.dir={tmp_path / 'sweep'}",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
    )


def runs(root: Path) -> dict[Path, OmegaConf]:
    return {
        p.parent: OmegaConf.load(p) for p in root.rglob("config.yaml") if p.parent.name != ".hydra"
    }


def test_wind_by_seed_sweep_leaves_one_run_per_job_and_skips_them_when_run_again(tmp_path):
    proc = sweep(tmp_path, "env=corridor", "wind=0.05,0.4", "seed=0,1")
    assert proc.returncode == 0, proc.stderr[-3000:]
    found = runs(tmp_path / "sweep")
    assert len(found) == 4
    recorded = sorted((cfg.env.wind, cfg.wind, cfg.seed) for cfg in found.values())
    assert recorded == [(0.05, 0.05, 0), (0.05, 0.05, 1), (0.4, 0.4, 0), (0.4, 0.4, 1)]
    for run_dir in found:
        assert (run_dir / "epochs.csv").read_text().count("\n") == 2  # header + 1 epoch
    again = sweep(tmp_path, "env=corridor", "wind=0.05,0.4", "seed=0,1")
    assert again.returncode == 0, again.stderr[-3000:]
    assert again.stdout.count("already finished") == 4


def test_a_failed_job_does_not_stop_the_others(tmp_path):
    proc = sweep(tmp_path, "estimator.k=0,3")
    finished = [d for d, cfg in runs(tmp_path / "sweep").items() if (d / "epochs.csv").exists()]
    assert [runs(tmp_path / "sweep")[d].estimator.k for d in finished] == [3]
    assert "estimator.k=0" in proc.stderr
