"""Preemption with real signals: SIGTERM (a cluster's) and SIGINT (Ctrl-C) stop a
run or a sweep where it is, record it as interrupted, release its lock, say so in one line and
exit 128 + the signal; the same command again continues to the numbers of an uninterrupted run."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from tests.test_cli import TINY

pytestmark = pytest.mark.slow

# Epochs long enough that a signal sent after the second lands in the third, with four to go.
EPOCHS = 6
SLOWER = [*TINY, "algo.trajectories=20", "algo.horizon=100", f"epochs={EPOCHS}"]
TIMES = ["seconds", "collect_seconds", "neighbours_seconds", "update_seconds", "wall_time"]


def start(tmp_path: Path, *args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "hmepol_cli", *args],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def rows(run: Path) -> int:
    try:
        return len(pd.read_csv(run / "epochs.csv"))
    except (FileNotFoundError, pd.errors.EmptyDataError):
        return 0


def interrupt_after(proc: subprocess.Popen, run: Path, signum: int, epochs: int = 2):
    """Send ``signum`` once ``run`` has ``epochs`` rows. -> (returncode, stdout, stderr)"""
    deadline = time.time() + 240
    while rows(run) < epochs:
        assert proc.poll() is None, proc.communicate()
        assert time.time() < deadline, "the run made no progress"
        time.sleep(0.1)
    proc.send_signal(signum)
    out, err = proc.communicate(timeout=240)
    return proc.returncode, out, err


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory) -> pd.DataFrame:
    """epochs.csv of SLOWER run start to end: what every interrupted run must continue to."""
    plain = tmp_path_factory.mktemp("plain") / "run"
    subprocess.run(
        [sys.executable, "-m", "hmepol_cli", "train", *SLOWER, f"hydra.run.dir={plain}"],
        cwd=plain.parent, check=True, capture_output=True, timeout=300,
    )  # fmt: skip
    return pd.read_csv(plain / "epochs.csv")


@pytest.mark.xdist_group("uninterrupted")
@pytest.mark.parametrize("signum, code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_signal_stops_a_run_which_the_same_command_continues_exactly(
    tmp_path, signum, code, uninterrupted
):
    args = ("train", *SLOWER, f"hydra.run.dir={tmp_path / 'run'}")
    returncode, _, err = interrupt_after(start(tmp_path, *args), tmp_path / "run", signum)
    assert returncode == code
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"hmepol: interrupted by {signum.name}")
    info = json.loads((tmp_path / "run" / "run.json").read_text())
    assert info["status"] == "interrupted" and info["interruption"]["signal"] == signum.name
    assert not (tmp_path / "run" / ".lock").exists()
    again = subprocess.run(
        [sys.executable, "-m", "hmepol_cli", *args],
        cwd=tmp_path, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert again.returncode == 0, again.stderr[-2000:]
    resumed = pd.read_csv(tmp_path / "run" / "epochs.csv")
    assert list(resumed.epoch) == list(range(EPOCHS))
    pd.testing.assert_frame_equal(
        resumed.drop(columns=TIMES), uninterrupted.drop(columns=TIMES), check_exact=True
    )
    assert json.loads((tmp_path / "run" / "run.json").read_text())["status"] == "finished"


def test_an_interrupted_sweep_says_which_jobs_stopped_and_which_never_started(tmp_path):
    args = ("sweep", *SLOWER, "seed=0,1", "hydra/launcher=basic",
            f"hydra.sweep.dir={tmp_path / 'sweep'}")  # fmt: skip
    proc = start(tmp_path, *args)
    deadline = time.time() + 240
    while not list((tmp_path / "sweep").glob("*/run.json")):  # the first job's run directory
        assert proc.poll() is None and time.time() < deadline, proc.communicate()
        time.sleep(0.1)
    (first,) = [p.parent for p in (tmp_path / "sweep").glob("*/run.json")]
    returncode, _, err = interrupt_after(proc, first, signal.SIGTERM)
    assert returncode == 143, err[-2000:]
    assert "Traceback" not in err
    assert "1 of 2 jobs interrupted" in err and "1 of 2 jobs did not start" in err
    assert json.loads((first / "run.json").read_text())["status"] == "interrupted"
    assert len(list((tmp_path / "sweep").glob("*/run.json"))) == 1  # the second never started
    assert not list((tmp_path / "sweep").glob(".hmepol-sweep-*"))
