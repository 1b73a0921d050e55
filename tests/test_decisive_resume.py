"""docs/results/decisive/resume.sh status, on a run tree built by hand: a running run's pace is
the median of its last 10 epochs' seconds and the time left is that pace times the epochs left."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pandas as pd

SCRIPT = Path(__file__).resolve().parent.parent / "docs" / "results" / "decisive" / "resume.sh"


def run_folder(out: Path, name: str, seconds: list[float], status: str) -> None:
    run = out / "mepol" / name
    run.mkdir(parents=True)
    pd.DataFrame({"epoch": range(len(seconds)), "seconds": seconds}).to_csv(
        run / "epochs.csv", index=False)  # fmt: skip
    (run / "run.json").write_text(json.dumps({"status": status, "epochs": 500}))


def test_status_gives_a_running_run_its_pace_and_the_hours_left(tmp_path):
    tree = tmp_path / "decisive"
    (tree / ".venv" / "bin").mkdir(parents=True)
    (tree / ".venv" / "bin" / "python").symlink_to(sys.executable)
    out = tree / "outputs" / "decisive"
    # 140 epochs: an early slow stretch (1000 s), then the last 10: nine at 30 s and one at
    # 1000 s, median 30 s (their mean is 127 s, the median of all 140 is 1000 s).
    run_folder(out, "seed-0", [1000.0] * 130 + [30.0] * 9 + [1000.0], "running")
    run_folder(out, "seed-1", [50.0] * 500, "finished")
    env = {**os.environ, "DECISIVE_TREE": str(tree)}
    text = subprocess.run(["bash", str(SCRIPT), "status"], capture_output=True, text=True,
                          check=True, env=env).stdout  # fmt: skip
    [running] = [line for line in text.splitlines() if "seed-0" in line]
    # (500 - 140) epochs x 30 s = 10,800 s = 3.0 h
    assert running.split()[1:] == ["140", "epochs", "running", "30", "s/epoch,", "3.0", "h",
                                   "left", "at", "that", "pace"]  # fmt: skip
    [finished] = [line for line in text.splitlines() if "seed-1" in line]
    assert finished.split()[1:] == ["500", "epochs", "finished"]
    assert "chain A not running" in text
