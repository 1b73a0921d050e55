"""End-to-end: the real command, configurations, bad input, resume and reproducibility."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra
from omegaconf import OmegaConf

from hmepol_cli.config import validate

# A run small enough for seconds: same code path as the thesis scale.
TINY = [
    "algo.trajectories=10",
    "algo.horizon=40",
    "algo.batch_size=5",
    "algo.max_off_iters=5",
    "algo.lr=1e-3",
    "algo.kl_threshold=0.5",
    "estimator.k=5",
    "policy.hidden=[32,32]",
    "policy.encoder_hidden=[32,32]",
    "policy.history_size=8",
    "eval.trajectories=4",
    "eval.horizon=20",
    "progress=false",
]


def hmepol(*args: str, cwd: Path, check: bool = True, **kw) -> subprocess.CompletedProcess:
    proc = subprocess.run(
        [sys.executable, "-m", "hmepol_cli", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=300,
        **kw,
    )
    if check and proc.returncode != 0:
        raise AssertionError(f"hmepol {' '.join(args)} failed:\n{proc.stdout}\n{proc.stderr}")
    return proc


@pytest.fixture()
def hydra_compose():
    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="hmepol_cli.conf", version_base="1.3"):
        yield compose
    GlobalHydra.instance().clear()


def group_options(group: str) -> list[str]:
    return sorted(GlobalHydra.instance().config_loader().get_group_options(group))


def _needs_missing_mujoco(cfg) -> bool:
    """A Gymnasium MuJoCo preset (env=ant_xy) on a machine without the mujoco extra."""
    import importlib.util

    import gymnasium

    if cfg.env.name != "gym" or importlib.util.find_spec("mujoco") is not None:
        return False
    return gymnasium.spec(cfg.env.id).entry_point.startswith("gymnasium.envs.mujoco")


@pytest.mark.slow  # heavy: make test runs it, make test-fast does not
def test_every_shipped_config_composes_and_validates(hydra_compose):
    groups = ["env", "algo", "policy", "estimator", "experiment"]
    seen = {}
    for group in groups:
        options = group_options(group)
        assert options, f"no options found for {group}"
        seen[group] = options
        for option in options:
            overrides = [f"{group}={option}"]
            if (group, option) == ("env", "gym"):
                overrides.append("env.id=Pendulum-v1")  # the bare entry: the id is the user's
            cfg = hydra_compose(config_name="config", overrides=overrides)
            if not _needs_missing_mujoco(cfg):
                validate(cfg)
    assert {"slope", "corridor", "multigrid", "gym", "ant_xy", "mountaincar"} <= set(seen["env"])
    assert {"mepol", "alphamepol", "hmepol"} <= set(seen["algo"])
    assert {"markov", "recursive", "twohead", "gru", "lstm"} <= set(seen["policy"])


def test_algo_hmepol_selects_recursive_policy_but_any_combination_works(hydra_compose):
    assert hydra_compose(config_name="config", overrides=["algo=hmepol"]).policy.name == "recursive"
    assert hydra_compose(config_name="config", overrides=["algo=mepol"]).policy.name == "markov"
    mixed = hydra_compose(config_name="config", overrides=["algo=hmepol", "policy=gru"])
    assert mixed.policy.name == "gru"


def test_thesis_presets_carry_table_values(hydra_compose):
    cfg = hydra_compose(config_name="config", overrides=["experiment=corridor_hmepol"])
    assert (cfg.env.name, cfg.algo.name, cfg.policy.name) == ("corridor", "hmepol", "recursive")
    assert (cfg.algo.trajectories, cfg.algo.batch_size, cfg.algo.kl_threshold, cfg.algo.lr) == (
        100,
        1,
        0.1,
        4e-5,
    )
    demo = hydra_compose(config_name="config", overrides=["experiment=demo"])
    assert demo.epochs == 15 and demo.algo.trajectories == 40  # presets win over top-level defaults
    exact = hydra_compose(config_name="config", overrides=["experiment=corridor_hmepol_exact"])
    assert exact.algo.trust_region == "exact"
    exact.algo.trust_region = cfg.algo.trust_region
    assert exact == cfg  # ours: the thesis preset with only the trust region changed
    reset = hydra_compose(config_name="config", overrides=["experiment=corridor_hmepol_adam_reset"])
    assert reset.algo.adam_reset == "epoch"
    reset.algo.adam_reset = cfg.algo.adam_reset
    assert reset == cfg  # ours: the thesis preset with only Adam's reset changed
    cfg = hydra_compose(config_name="config", overrides=["experiment=multigrid_alphamepol"])
    assert (cfg.algo.objective, cfg.algo.alpha, cfg.env.name) == ("cvar", 0.1, "multigrid")


@pytest.mark.slow  # heavy: make test runs it, make test-fast does not
def test_presets_hold_only_what_they_change(hydra_compose):
    """Every key of an experiment preset differs from what its world and algorithm compose to
    without it (for the presets that leave the algorithm open, with at least one algorithm)."""
    import yaml

    def leaves(node: dict, prefix: str = ""):
        for key, value in node.items():
            if isinstance(value, dict):
                yield from leaves(value, f"{prefix}{key}.")
            else:
                yield f"{prefix}{key}", value

    for path in sorted((Path(__file__).parents[1] / "conf" / "experiment").glob("*.yaml")):
        preset = yaml.safe_load(path.read_text())
        chosen = [  # an entry that names another preset builds on it (experiment=<it>)
            *(
                f"experiment={d}"
                for d in preset["defaults"]
                if isinstance(d, str) and d != "_self_"
            ),
            *(
                f"{k.removeprefix('override /')}={v}"
                for d in preset.pop("defaults")
                if isinstance(d, dict)
                for k, v in d.items()
            ),
        ]
        algos = [[]] if any(c.startswith("algo=") for c in chosen) else [
            [f"algo={a}"] for a in ("mepol", "alphamepol", "hmepol")
        ]  # fmt: skip
        bases = [hydra_compose(config_name="config", overrides=[*chosen, *a]) for a in algos]
        for key, value in leaves(preset):
            assert any(OmegaConf.select(b, key) != value for b in bases), f"{path.name}: {key}"


def test_slurm_launcher_config_composes(hydra_compose):
    cfg = hydra_compose(
        config_name="config", overrides=["hydra/launcher=slurm"], return_hydra_config=True
    )
    assert cfg.hydra.launcher._target_.endswith("SlurmLauncher")
    assert cfg.hydra.launcher.max_num_timeout >= 1


@pytest.mark.slow
def test_the_installed_command_reports_bad_input_in_one_line(tmp_path):
    """The console script end to end (tests/test_bad_input.py covers the cases in-process)."""
    proc = hmepol(
        "train", "estimator.k=0", f"hydra.run.dir={tmp_path}/run", cwd=tmp_path, check=False
    )
    assert proc.returncode == 2 and proc.stderr.startswith("hmepol: error: estimator.k=0")
    assert "Traceback" not in proc.stderr + proc.stdout and not (tmp_path / "run").exists()


@pytest.mark.slow
def test_training_raises_entropy_above_the_random_policy(tmp_path):
    run = tmp_path / "run"
    hmepol(
        "train",
        "experiment=demo",
        "eval.trajectories=4",
        "progress=false",
        "seed=1",
        f"hydra.run.dir={run}",
        cwd=tmp_path,
    )
    rows = pd.read_csv(run / "epochs.csv")
    assert list(rows.epoch) == list(range(15))  # the demo's 15 epochs
    # The favourable configuration (p = 0.8) is drawn in every epoch; the epoch's mean mixes in
    # the rare one a random number of times, so compare within configuration 0: the initial
    # policy (epoch 0) against the last three epochs (measured over seeds 1-3 and both edge
    # rules: +0.17 to +0.36 nats; single epochs move by ~0.1).
    first, last = rows.entropy_c0.iloc[0], rows.entropy_c0.iloc[-3:].mean()
    assert last > first + 0.15, rows[["epoch", "entropy_c0", "kl", "off_iters"]]
    assert (rows.kl <= 0.5 + 1e-9).all()


def _tiny_run_args(algo: str, seed: int, run: Path) -> list[str]:
    return ["train", *TINY, "epochs=2", f"algo={algo}", f"seed={seed}", f"hydra.run.dir={run}"]


@pytest.fixture(scope="module")
def tiny_runs(tmp_path_factory) -> Path:
    """A folder, runs/, of four finished tiny runs, <algo>-<seed> for mepol and hmepol and seeds
    0 and 1: trained once for the tests that read them (each is a process of its own)."""
    folder = tmp_path_factory.mktemp("tiny")
    for algo in ("mepol", "hmepol"):
        for seed in (0, 1):
            hmepol(*_tiny_run_args(algo, seed, folder / "runs" / f"{algo}-{seed}"), cwd=folder)
    return folder / "runs"


@pytest.mark.slow
@pytest.mark.xdist_group("tiny_runs")
def test_same_seed_and_config_give_the_same_curves(tmp_path, tiny_runs):
    hmepol(*_tiny_run_args("hmepol", 0, tmp_path / "again"), cwd=tmp_path)
    a = pd.read_csv(tiny_runs / "hmepol-0" / "epochs.csv")
    b = pd.read_csv(tmp_path / "again" / "epochs.csv")
    cols = ["entropy", "objective", "entropy_iw", "kl", "off_iters"]
    assert len(a) == 2
    pd.testing.assert_frame_equal(a[cols], b[cols])
    c = pd.read_csv(tiny_runs / "hmepol-1" / "epochs.csv")  # another seed
    assert not a["entropy"].equals(c["entropy"])


TIMING = ["seconds", "collect_seconds", "neighbours_seconds", "update_seconds", "wall_time"]


@pytest.mark.slow
def test_killed_run_resumes_with_every_epoch_once_and_the_same_curves(tmp_path):
    """SIGKILL in the middle of an epoch, then resume: every epoch once, and every number of
    every epoch equal to a run that was never interrupted (timings aside)."""
    epochs = 6
    config = [*TINY, f"epochs={epochs}", "algo.max_off_iters=30"]
    run = tmp_path / "killed"
    proc = subprocess.Popen(
        [sys.executable, "-m", "hmepol_cli", "train", *config, f"hydra.run.dir={run}"],
        cwd=tmp_path,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    deadline = time.time() + 120
    csv = run / "epochs.csv"
    while time.time() < deadline:
        if csv.exists() and len(pd.read_csv(csv)) >= 2:
            break
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)  # in the middle of an epoch
    proc.wait()
    done_before = len(pd.read_csv(csv))
    assert 2 <= done_before < epochs, "the run was not killed in the middle"
    info = json.loads((run / "run.json").read_text())
    assert info["status"] == "running"  # a killed process records nothing
    hmepol("train", f"resume={run}", cwd=tmp_path)
    resumed = pd.read_csv(run / "epochs.csv")
    assert list(resumed.epoch) == list(range(epochs))
    full = tmp_path / "uninterrupted"
    hmepol("train", *config, f"hydra.run.dir={full}", cwd=tmp_path)
    uninterrupted = pd.read_csv(full / "epochs.csv")
    pd.testing.assert_frame_equal(resumed.drop(columns=TIMING), uninterrupted.drop(columns=TIMING))
    for name in ("batches.csv",):
        pd.testing.assert_frame_equal(pd.read_csv(run / name), pd.read_csv(full / name))
    assert json.loads((run / "run.json").read_text())["status"] == "finished"
    assert len((run / "commands.log").read_text().splitlines()) == 2  # started, resumed


@pytest.mark.slow
@pytest.mark.xdist_group("tiny_runs")
def test_report_and_finetune_read_what_training_wrote(tmp_path, tiny_runs):
    hmepol(
        "finetune",
        f"init={tiny_runs}/hmepol-0",
        "epochs=2",
        "episodes=4",
        "horizon=20",
        "targets=1",
        "config=0",
        "progress=false",
        f"hydra.run.dir={tmp_path}/ft",
        cwd=tmp_path,
    )
    assert len(pd.read_csv(tmp_path / "ft/finetune.csv")) == 2
    # the runs where training left them, the fine-tuning elsewhere: one report of both folders
    proc = hmepol(
        "report", str(tiny_runs), str(tmp_path / "ft"), "--out", str(tmp_path / "report"),
        cwd=tmp_path,
    )  # fmt: skip
    assert "report written to" in proc.stdout
    index = (tmp_path / "report" / "index.html").read_text()
    figures = sorted(p.name for p in (tmp_path / "report" / "figures").glob("*.png"))
    for expected in (
        "slope_entropy_epochs.png",
        "slope_heatmaps.png",
        "slope_finetune_returns.png",
    ):
        assert expected in figures, figures
    assert all(name in index for name in figures)
    summary = pd.read_csv(tmp_path / "report" / "summary.csv")
    assert set(summary.loc[summary.config == "average", "n_seeds"]) == {2}


@pytest.mark.slow
def test_show_draws_a_world(tmp_path):
    proc = hmepol(
        "show", "env=corridor", "wind=0.25", "--out", str(tmp_path / "c.png"), cwd=tmp_path
    )
    assert (tmp_path / "c.png").stat().st_size > 10_000 and "drawn to" in proc.stdout
    bad = hmepol("show", "env=corridor", "wind=abc", cwd=tmp_path, check=False)
    assert bad.returncode != 0 and "wind='abc' is not a number" in bad.stderr


@pytest.mark.slow
def test_report_of_a_folder_without_runs_is_one_clear_line(tmp_path):
    proc = hmepol("report", str(tmp_path / "nothing"), cwd=tmp_path, check=False)
    assert proc.returncode != 0 and proc.stderr.startswith("hmepol: error:")
    assert "Traceback" not in proc.stderr


@pytest.mark.parametrize("population", [[], ["seeds=[0,1]"]])
def test_train_composes_its_config_once_and_checks_it_before_writing(
    tmp_path, monkeypatch, population
):
    """`hmepol train` composes its config once (Hydra's compose, with its own node), checks it,
    and runs it as Hydra's job: one composition, and each config validated once."""
    from hydra._internal.hydra import Hydra

    import hmepol_cli.checks as checks
    from hmepol_cli.cli import main

    composed, validated = [], []
    real_compose, real_validate = Hydra.compose_config, checks.validate
    monkeypatch.setattr(
        Hydra,
        "compose_config",
        lambda self, *a, **k: composed.append(1) or real_compose(self, *a, **k),
    )
    monkeypatch.setattr(checks, "validate", lambda cfg: validated.append(1) or real_validate(cfg))
    run = tmp_path / "run"
    main(["train", *TINY, "epochs=1", *population, f"hydra.run.dir={run}"])
    # validated once each: the job's config, and each member's (seeds=[0,1]: two more)
    assert (len(composed), len(validated)) == (1, 3 if population else 1)
    assert (run / "seed1" / "run.json").exists() if population else (run / "run.json").exists()
