"""Sweeps on the joblib launcher: a run per job, finished jobs skipped, failures isolated."""

# Each test runs the real command (a subprocess) over several jobs.

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
from omegaconf import OmegaConf

from tests.test_cli import TINY


def sweep(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "hmepol_cli",
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
        # Unbuffered, as on CI: each job's lines must reach the shared pipe whole.
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )


def runs(root: Path) -> dict[Path, OmegaConf]:
    return {
        p.parent: OmegaConf.load(p) for p in root.rglob("config.yaml") if p.parent.name != ".hydra"
    }


def test_a_job_line_reaches_the_shared_stream_in_one_write():
    from hmepol_cli.cli import say

    class Recorder:
        def __init__(self):
            self.writes = []

        def write(self, text):
            self.writes.append(text)

        def flush(self):
            pass

    stream = Recorder()
    say("hmepol: job 3 finished", stream)
    assert stream.writes == ["hmepol: job 3 finished\n"]  # print would write the newline apart


# The sweep's grid: two winds by two seeds of the corridor. One joblib sweep of it serves the
# tests that only read its runs (the slowest part of the suite; each job is a process of its own).
# threads=1: both launchers then run every job on one thread. With torch's default, joblib's jobs
# take cores / jobs threads each and the population all cores, and on some CPUs (AVX-512) a
# reduction split over two threads rounds differently (entropy_iw moves by ~3e-8).
GRID = ("env=corridor", "algo=mepol", "wind=0.05,0.4", "seed=0,1", "algo.batch_size=1",
        "algo.trajectories=4", "progress=true", "threads=1")  # fmt: skip


@pytest.fixture(scope="module")
def grid_sweep(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    """(folder, the finished sweep) of GRID on the default (joblib) launcher, in folder/sweep."""
    folder = tmp_path_factory.mktemp("plain")
    return folder, sweep(folder, *GRID)


@pytest.mark.slow
@pytest.mark.xdist_group("grid_sweep")
def test_wind_by_seed_sweep_leaves_one_run_per_job_and_skips_them_when_run_again(grid_sweep):
    tmp_path, proc = grid_sweep
    assert proc.returncode == 0, proc.stderr[-3000:]
    found = runs(tmp_path / "sweep")
    assert len(found) == 4
    recorded = sorted((cfg.env.wind, cfg.wind, cfg.seed) for cfg in found.values())
    assert recorded == [(0.05, 0.05, 0), (0.05, 0.05, 1), (0.4, 0.4, 0), (0.4, 0.4, 1)]
    for run_dir in found:
        assert (run_dir / "epochs.csv").read_text().count("\n") == 2  # header + 1 epoch
    # Progress a person can read: no bars of parallel jobs sharing a line, no joblib banner,
    # one line per finished job naming it, its entropy and its folder.
    assert "Joblib.Parallel" not in proc.stdout + proc.stderr
    assert "\r" not in proc.stderr
    finished = [line for line in proc.stdout.splitlines() if " finished: corridor/" in line]
    assert len(finished) == 4, proc.stdout[-4000:]
    assert all("H=" in line and " -> " in line for line in finished)
    again = sweep(tmp_path, *GRID)
    assert again.returncode == 0, again.stderr[-3000:]
    assert again.stdout.count("already finished") == 4


@pytest.mark.slow
def test_a_sweep_with_a_bad_value_is_refused_before_anything_is_written(tmp_path):
    proc = sweep(tmp_path, "estimator.k=0,3")
    assert proc.returncode == 2 and "estimator.k=0" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "sweep").exists()


@pytest.mark.slow
def test_two_identical_sweeps_into_one_folder_the_second_is_refused_in_a_table(tmp_path):
    by_seed = "hydra.sweep.subdir=seed${seed}"
    first = subprocess.Popen(
        [sys.executable, "-m", "hmepol_cli", "sweep", *TINY, "epochs=300", "seed=0",
         by_seed, f"hydra.sweep.dir={tmp_path / 'sweep'}"],
        cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        while not (tmp_path / "sweep" / "seed0" / "epochs.csv").exists():
            assert first.poll() is None, first.communicate()
            time.sleep(0.1)
        second = sweep(tmp_path, "seed=0", by_seed, "epochs=300")
        assert second.returncode == 1 and "Traceback" not in second.stderr, second.stderr
        assert "1 of 1 jobs failed" in second.stderr and "is being written by pid" in second.stderr
    finally:
        first.kill()
        first.wait()


@pytest.mark.slow
def test_a_failed_job_does_not_stop_the_others_and_the_sweep_says_so(tmp_path):
    """One job's directory is held by another live process: that job fails, the other runs,
    the sweep exits 1 with a table of the failed job, and a re-run retries it."""
    by_seed = "hydra.sweep.subdir=seed${seed}"
    seed0, seed1 = tmp_path / "sweep" / "seed0", tmp_path / "sweep" / "seed1"
    holder = subprocess.Popen(["sleep", "300"])
    try:
        seed0.mkdir(parents=True)
        lock = {"pid": holder.pid, "host": socket.gethostname(), "started": "earlier"}
        (seed0 / ".lock").write_text(json.dumps(lock))
        first = sweep(tmp_path, "seed=0,1", by_seed)
        assert first.returncode == 1, first.stderr[-2000:]
        assert "1 of 2 jobs failed" in first.stderr and f"pid {holder.pid}" in first.stderr
        assert "Traceback" not in first.stderr  # the table, and no Hydra traceback
        assert len(pd.read_csv(seed1 / "epochs.csv")) == 1  # the other job went on
        assert sorted(p.name for p in seed0.iterdir()) == [".lock"]  # the held one: untouched
    finally:
        holder.kill()
        holder.wait()
    retry = sweep(tmp_path, "seed=0,1", by_seed)  # the holder is gone: its lock is taken over
    assert retry.returncode == 0, retry.stderr[-2000:]
    assert "already finished" in retry.stdout and "is gone" in retry.stderr
    assert len(pd.read_csv(seed0 / "epochs.csv")) == 1 and not (seed0 / ".lock").exists()


def test_jobs_whose_programs_are_equal_become_one_population():
    """The grouping on a stand-in for the composed program: algo=mepol and algo=hmepol differ
    in the policy (two programs), seeds and winds do not."""
    from hydra_plugins.hmepol_population_launcher.population_launcher import group_jobs

    def program(overrides):
        return {"policy": "recursive" if "algo=hmepol" in overrides else "markov"}

    jobs = [
        ["algo=mepol", "seed=0"],
        ["algo=hmepol", "seed=0"],
        ["algo=mepol", "seed=1"],
        ["algo=hmepol", "seed=1"],
        ["algo=mepol", "seed=2", "wind=0.05"],
    ]
    grouped, summary = group_jobs(jobs, program)
    assert grouped == [
        ["algo=mepol", 'members=["seed=0","seed=1","seed=2 wind=0.05"]'],
        ["algo=hmepol", 'members=["seed=0","seed=1"]'],
    ]
    assert summary == (
        "5 runs as 2 jobs (populations of 3, 2 members); not one population: they differ in policy"
    )
    grouped, _ = group_jobs(jobs, program, max_members=2)
    assert grouped == [
        ["algo=mepol", 'members=["seed=0","seed=1"]'],
        ["algo=mepol", "seed=2", "wind=0.05"],
        ["algo=hmepol", 'members=["seed=0","seed=1"]'],
    ]


@pytest.mark.slow
@pytest.mark.xdist_group("grid_sweep")
def test_a_sweep_over_winds_and_seeds_runs_as_one_population_of_four(tmp_path, grid_sweep):
    """hmepol sweep env=corridor algo=mepol wind=0.05,0.4 seed=0,1 with the
    population launcher is one job of four members, each with its wind in its config and
    run.json, in the run directories the ordinary sweep writes (the same configs, the same
    curves), which the report reads like any others and a second sweep skips."""
    plain_folder, plain = grid_sweep
    assert plain.returncode == 0, plain.stderr[-3000:]
    grouped = sweep(tmp_path, *GRID, "hydra/launcher=population")
    assert grouped.returncode == 0, grouped.stderr[-3000:]
    assert "4 runs as 1 job (populations of 4 members)" in grouped.stdout
    members, separate = runs(tmp_path / "sweep"), runs(plain_folder / "sweep")
    assert sorted(d.name for d in members) == sorted(d.name for d in separate)
    assert len(members) == 4
    for run_dir, cfg in members.items():
        info = json.loads((run_dir / "run.json").read_text())
        assert info["wind"] == cfg.wind == cfg.env.wind and info["seed"] == cfg.seed
    assert sorted((c.wind, c.seed) for c in members.values()) == [
        (0.05, 0), (0.05, 1), (0.4, 0), (0.4, 1)
    ]  # fmt: skip
    drop = ["seconds", "collect_seconds", "neighbours_seconds", "update_seconds", "wall_time"]
    for run_dir in separate:
        twin = tmp_path / "sweep" / run_dir.name
        # the same config but for progress, a display switch that parallel jobs turn off
        same, other = members[twin].copy(), separate[run_dir].copy()
        assert (same.pop("progress"), other.pop("progress")) == (True, False)
        assert OmegaConf.to_yaml(same) == OmegaConf.to_yaml(other)
        a = pd.read_csv(twin / "epochs.csv")
        b = pd.read_csv(run_dir / "epochs.csv")
        pd.testing.assert_frame_equal(a.drop(columns=drop), b.drop(columns=drop), check_exact=True)
    report = subprocess.run(
        [sys.executable, "-m", "hmepol_cli", "report", str(tmp_path / "sweep")],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert report.returncode == 0 and "4 runs used" in report.stdout, report.stderr[-2000:]
    again = sweep(tmp_path, *GRID, "hydra/launcher=population")
    assert again.returncode == 0 and again.stdout.count("already finished") == 4


@pytest.mark.slow
def test_a_population_runs_as_one_submitit_job(tmp_path):
    """population_local wraps submitit's local executor the way population_slurm wraps SLURM:
    one submitted job trains the seeds together and leaves their run directories."""
    proc = sweep(tmp_path, "seed=0,1", "hydra/launcher=population_local")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "2 runs as 1 job (populations of 2 members)" in proc.stdout + proc.stderr
    found = runs(tmp_path / "sweep")
    assert sorted(cfg.seed for cfg in found.values()) == [0, 1]
    for run_dir in found:
        assert json.loads((run_dir / "run.json").read_text())["status"] == "finished"
    assert len(list((tmp_path / "sweep" / ".submitit").iterdir())) >= 1  # one job folder


def test_the_slurm_population_launcher_composes(tmp_path):
    from hydra import compose as hydra_compose
    from hydra import initialize_config_module

    from hmepol_cli.cli import compose  # noqa: F401  (registers the schema)

    with initialize_config_module(config_module="hmepol_cli.conf", version_base="1.3"):
        cfg = hydra_compose(
            "config", overrides=["hydra/launcher=population_slurm"], return_hydra_config=True
        )
    launcher = cfg.hydra.launcher
    assert launcher._target_.endswith("PopulationLauncher") and launcher.max_members == 8
    assert launcher.inner._target_.endswith("SlurmLauncher") and launcher.inner.gpus_per_node == 1


@pytest.mark.parametrize(
    "overrides",
    [
        ["seed=0,1,2", "algo=mepol,hmepol", "wind=0.1"],
        ["experiment=demo", "+x=1,2", "seed=3"],
        ["algo.lr=1e-3,1e-4", "policy.hidden=[8,8]", "epochs=range(1,3)"],
    ],
)
def test_sweep_jobs_and_folders_are_named_as_hydra_names_them(overrides):
    """hmepol_cli.sweeps (public override grammar) against Hydra's own basic sweeper and job
    naming (private API, used here only to check)."""
    from hydra._internal.config_loader_impl import get_overrides_dirname
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper

    from hmepol_cli import sweeps

    parsed = sweeps.parse(overrides)
    theirs = [job for batch in BasicSweeper.split_arguments(parsed, None) for job in batch]
    assert sweeps.jobs(overrides) == theirs
    for job in theirs:
        expected = get_overrides_dirname(sweeps.parse(job), ["seed"], "_", "-")
        assert sweeps.override_dirname(job, ["seed"], "_", "-") == expected


@pytest.mark.slow
def test_chapter_5_slope_is_two_programs(tmp_path):
    """make chapter5's slope sweep, planned (dry run): Mepol and alpha-Mepol's 16 runs are one
    population (one network; the objective and alpha are member-scalar), HMepol's 8 another."""
    proc = subprocess.run(
        [sys.executable, "-m", "hmepol_cli", "sweep",
         "experiment=slope_mepol,slope_alphamepol,slope_hmepol", "seed=0,1,2,3,4,5,6,7",
         "hydra/launcher=population", "hydra.launcher.dry_run=true",
         f"hydra.sweep.dir={tmp_path / 'sweep'}"],
        cwd=tmp_path, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "24 runs as 2 jobs (populations of 16, 8 members)" in proc.stdout
    assert "they differ in policy.name" in proc.stdout
    assert not list((tmp_path / "sweep").glob("*/run.json"))  # nothing ran
