"""The report: discovery, grouping, t-intervals, skipped runs, figures and summary differences.

Run directories are written by hand in the trainer's format (run.json, .hydra/config.yaml,
epochs.csv, eval/final.npz, finetune.csv) with known numbers; what run.json records beyond the
config (the rules, the world's map) is computed as tools/backfill_run_json.py does for a run.
"""

from __future__ import annotations

import html
import json
import math
import re
import shutil
import sys
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from hmepol_cli.cli import main
from hmepol_cli.envs import make_world
from hmepol_cli.errors import UserError
from hmepol_cli.plots import WorldMap
from hmepol_cli.report import SkippedRunWarning, cut_at_common_epochs, run_report
from hmepol_cli.report.frames import epochs_label
from hmepol_cli.report.loading import discover_runs
from hmepol_cli.report.runs import (
    MapUnknownWarning,
    Run,
    drop_duplicate_seeds,
    group_runs,
    varying_keys,
)
from hmepol_cli.report.stats import curve_ci, difference_ci, final_value, mean_ci
from hmepol_cli.report.summary import difference_table, final_entropy_table

SLOPE_LOG_AREA = math.log(3.04)


def record_world(run: Path) -> None:
    """Add to the run's run.json what a run records beyond its config (the rules it ran with,
    its world's map), computed from its config as the training code does; nothing for a world
    this checkout cannot build (an unknown name, a wind it refuses)."""
    from tools.backfill_run_json import BackfillError, backfill

    try:
        backfill(run)
    except (BackfillError, ValueError):
        pass


def write_run(
    root: Path,
    *,
    env: str = "slope",
    algo: str = "mepol",
    policy: str = "markov",
    seed: int = 0,
    wind: float = 0.4,
    epochs: int = 20,
    final: float = 1.0,
    status: str = "finished",
    configuration_names: tuple[str, ...] = ("south", "north"),
    configuration_probs: tuple[float, ...] = (0.8, 0.2),
    free_area: float = 3.04,
    n_traj: int = 10,
    horizon: int = 40,
    extent: float = 1.0,
    name: str | None = None,
    extra_config: str = "",
    epochs_done: int | None = None,
    last_wall_time: float = 1.0,
    config_finals: tuple[float, ...] | None = None,
) -> Path:
    """One run directory whose entropy rises linearly to ``final`` (configuration c to
    ``config_finals[c]``, by default ``final - 0.1 * c``), so that the last-10% mean is known.

    ``extra_config``: more lines of its config.yaml; ``epochs_done``: epochs written (rows,
    run.json) when not ``epochs``, as in a run resumed for longer; ``last_wall_time``: when its
    last epoch ended (one second an epoch)."""
    done = epochs if epochs_done is None else epochs_done
    run = root / (name or f"{env}-{algo}-wind{wind}-seed{seed}")
    (run / ".hydra").mkdir(parents=True)
    (run / "eval").mkdir()
    objective, alpha = ("cvar", 0.2) if algo == "alphamepol" else ("mean", 1.0)
    (run / ".hydra" / "config.yaml").write_text(
        f"env:\n  name: {env}\n  wind: ${{wind}}\n"
        f"algo:\n  name: {algo}\n  objective: {objective}\n  alpha: {alpha}\n  lr: 1.0e-05\n"
        f"policy:\n  name: {policy}\n  bptt: '1'\n  hidden: [300, 300]\n"
        f"seed: {seed}\nepochs: {epochs}\nwind: {wind}\nresume: null\nprogress: {seed % 2 == 0}\n"
        f"device: cpu\n{extra_config}"
    )
    n_configurations = len(configuration_names)
    (run / "run.json").write_text(
        json.dumps(
            {
                "status": status,
                "epochs_done": done if status == "finished" else done // 2,
                "env": env,
                "algo": algo,
                "policy": policy,
                "seed": seed,
                "wind": wind,
                "config_names": list(configuration_names),
                "config_probs": list(configuration_probs),
                "free_area": [free_area] * n_configurations,
                "log_free_area": [math.log(free_area)] * n_configurations,
            }
        )
    )
    record_world(run)
    ramp = np.linspace(0.0, 1.0, done)
    table = {"epoch": np.arange(done), "entropy": final * ramp, "objective": final * ramp}
    if config_finals is None:
        config_finals = tuple(final - 0.1 * c for c in range(n_configurations))
    for c in range(n_configurations):
        table[f"entropy_c{c}"] = config_finals[c] * ramp
    table |= {
        "entropy_iw": final * ramp,
        "kl": 0.1,
        "off_iters": 3,
        "backtracks": 0,
        "lr": 1e-5,
        "seconds": 1.0,
        "wall_time": last_wall_time - np.arange(done)[::-1],
    }
    pd.DataFrame(table).to_csv(run / "epochs.csv", index=False)
    rng = np.random.default_rng(seed)
    steps = rng.normal(0, 0.05 * extent, size=(n_configurations, n_traj, horizon, 2))
    start = np.full((n_configurations, n_traj, 1, 2), -0.75 * extent)
    positions = np.clip(
        np.concatenate([start, start + steps.cumsum(axis=2)], axis=2), -extent, extent
    )
    np.savez(
        run / "eval" / "final.npz",
        **{f"positions_c{c}": positions[c].astype(np.float32) for c in range(n_configurations)},
    )
    return run


def write_batches(run: Path, drawn: dict[int, tuple[int, ...]]) -> None:
    """batches.csv of a run: one mini-batch of each configuration ``drawn[epoch]`` holds."""
    rows = [
        {"epoch": epoch, "batch": b, "config": config, "entropy": 0.5}
        for epoch, configurations in drawn.items()
        for b, config in enumerate(configurations)
    ]
    pd.DataFrame(rows).to_csv(run / "batches.csv", index=False)


def set_field(text: str, line: int, column: str, value: str) -> str:
    """epochs.csv text with one field (line numbered from 1, the header's) set to ``value``."""
    lines = text.splitlines()
    fields = lines[line - 1].split(",")
    fields[lines[0].split(",").index(column)] = value
    lines[line - 1] = ",".join(fields)
    return "\n".join(lines) + "\n"


def write_finetune_run(
    root: Path,
    *,
    algo_init: str,
    seed: int,
    epochs: int = 10,
    env: str = "slope",
    wind: float = 0.4,
    init: str | None = None,
    targets: int = 3,
    returns=None,
    name: str | None = None,
) -> Path:
    """A fine-tuning run: by default from pre-training run ``runs/<algo_init>-seed<seed>``
    (``init``: another), fine-tuning seed ``seed``, on ``targets`` targets of a goal task whose
    return rises at a speed set by the initialisation; ``returns(epoch, target)`` replaces it."""
    if init is None:
        init = "none" if algo_init == "scratch" else f"/runs/{algo_init}-seed{seed}@75"
    run = root / (name or f"finetune-{algo_init}-seed{seed}")
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "config.yaml").write_text(
        f"env:\n  name: {env}\nseed: {seed}\nwind: {wind}\ninit: {init}\noutput_dir: {run}\n"
    )
    (run / "run.json").write_text(
        json.dumps(
            {
                "status": "finished",
                "epochs_done": epochs,
                "env": env,
                "algo": algo_init,
                "init": init,
                "policy": "markov",
                "seed": seed,
                "wind": wind,
                "config_names": ["south", "north"],
                "config_probs": [0.8, 0.2],
                "free_area": [3.04, 3.04],
                "log_free_area": [SLOPE_LOG_AREA] * 2,
            }
        )
    )
    record_world(run)
    speed = {"hmepol": 1.0, "mepol": 0.3, "scratch": 0.1}[algo_init]
    if returns is None:

        def returns(e: int, t: int) -> float:
            return min(1.0, speed * e / epochs) * (1 - 0.01 * t)

    rows = [
        {
            "epoch": e,
            "target": t,
            "config": c,
            "return": returns(e, t),
            "success_rate": returns(e, t),  # a goal task: the return is the share that arrived
            "init": init,
            "algo_init": algo_init,
            "seed": seed,
            "seconds": 0.5 + seed,
        }
        for e in range(epochs)
        for t in range(targets)
        for c in range(2)
    ]
    pd.DataFrame(rows).to_csv(run / "finetune.csv", index=False)
    return run


# ------------------------------------------------------------------------------------------ stats
def test_mean_ci_matches_hand_computed_t_interval():
    ci = mean_ci([1.0, 2.0, 3.0, 4.0])
    # s = sqrt(5/3) = 1.290994, t_{0.975,3} = 3.182446: 3.182446 * 1.290994 / 2 = 2.054260
    assert ci.mean == pytest.approx(2.5)
    assert ci.half_width == pytest.approx(2.054260, abs=1e-6)
    assert (ci.low, ci.high) == pytest.approx((2.5 - 2.054260, 2.5 + 2.054260), abs=1e-6)


def test_one_seed_has_no_interval():
    ci = mean_ci([3.0])
    assert ci.mean == 3.0 and ci.n == 1 and math.isnan(ci.half_width)
    mean, half, n = curve_ci(np.array([[1.0, 2.0, np.nan], [3.0, np.nan, np.nan]]))
    assert mean[:2] == pytest.approx([2.0, 2.0]) and math.isnan(mean[2])
    assert list(n) == [2, 1, 0]
    # two samples 1, 3: s = sqrt(2), t_{0.975,1} = 12.706205 -> 12.706205 * sqrt(2) / sqrt(2)
    assert half[0] == pytest.approx(12.706205, abs=1e-5)
    assert math.isnan(half[1]) and math.isnan(half[2])


def test_difference_ci_welch_and_paired_by_hand():
    # Welch: a = [1, 2, 3], b = [2, 4, 6, 8]; var_a/3 = 1/3, var_b/4 = (20/3)/4 = 5/3; se^2 = 2
    # df = 4 / ((1/3)^2/2 + (5/3)^2/3) = 4 / (1/18 + 25/27) = 4.0755; t_{0.975,4.0755} = 2.7540
    welch = difference_ci({0: 1, 1: 2, 2: 3}, {0: 2, 1: 4, 2: 6, 3: 8})
    assert welch.method == "Welch t"
    assert welch.diff == pytest.approx(3.0)
    assert welch.half_width == pytest.approx(2.756285 * math.sqrt(2), rel=1e-6)
    # Paired (same seeds): d = [1, 2, 3] -> mean 2, s = 1, t_{0.975,2} = 4.302653 / sqrt(3)
    paired = difference_ci({0: 1, 1: 2, 2: 3}, {0: 2, 1: 4, 2: 6})
    assert paired.method == "paired t"
    assert paired.diff == pytest.approx(2.0)
    assert paired.half_width == pytest.approx(4.302653 / math.sqrt(3), abs=1e-5)


def test_final_value_is_mean_of_last_tenth_of_observed_epochs():
    assert final_value(np.arange(20.0)) == pytest.approx(18.5)  # last 2 of 20
    assert final_value([np.nan, 1.0, np.nan, 3.0]) == pytest.approx(3.0)  # last 1 of 2 observed
    assert math.isnan(final_value([np.nan, np.nan]))


# ---------------------------------------------------------------------------- discovery, groups
def test_groups_split_by_varying_keys_not_seed(tmp_path):
    for algo in ("mepol", "hmepol"):
        for seed in (0, 1):
            write_run(
                tmp_path / "sweep" / "deep",
                algo=algo,
                seed=seed,
                policy="recursive" if algo == "hmepol" else "markov",
            )
    runs, skipped = discover_runs(tmp_path)
    assert len(runs) == 4 and skipped == []
    # algo and the policy that goes with it vary; seed, progress (run-specific) do not count
    assert varying_keys(runs) == ["algo.name", "policy.name"]
    groups = group_runs(runs)
    assert [(g.algo, g.seeds) for g in groups] == [("mepol", [0, 1]), ("hmepol", [0, 1])]
    assert [g.label for g in groups] == ["Mepol", "HMepol"]  # policy is fixed by the algorithm


def test_label_names_key_that_is_not_fixed_by_algorithm(tmp_path):
    write_run(tmp_path, algo="hmepol", policy="recursive", name="a")
    write_run(tmp_path, algo="hmepol", policy="gru", name="b")
    groups = group_runs(discover_runs(tmp_path)[0])
    assert sorted(g.label for g in groups) == ["HMepol (policy=gru)", "HMepol (policy=recursive)"]


def test_labels_name_only_where_a_group_departs_from_the_main_experiment(tmp_path):
    for seed in (0, 1):
        write_run(tmp_path, algo="hmepol", policy="recursive", seed=seed, name=f"main{seed}")
        write_run(tmp_path, algo="hmepol", policy="gru", seed=seed, name=f"gru{seed}")
        write_run(
            tmp_path, algo="hmepol", policy="recursive", seed=seed, name=f"k{seed}",
            extra_config="estimator:\n  k: 10\n",
        )  # fmt: skip
    groups = group_runs(discover_runs(tmp_path)[0])
    assert sorted(g.label for g in groups) == [
        "HMepol", "HMepol (estimator.k=10)", "HMepol (policy=gru)",
    ]  # fmt: skip


def test_a_variant_alone_is_named_by_what_sets_it_apart_from_the_thesis(tmp_path):
    # conf/algo/hmepol.yaml's trust region is the one-step gradient one: runs with the exact one
    # are never plain "HMepol", with or without thesis runs beside them
    def hmepol_run(folder: str, seed: int, trust_region: str) -> None:
        run = write_run(tmp_path / folder, algo="hmepol", policy="recursive", seed=seed)
        config = run / ".hydra" / "config.yaml"
        config.write_text(config.read_text().replace(
            "  lr: 1.0e-05\n", f"  lr: 1.0e-05\n  trust_region: {trust_region}\n"))  # fmt: skip

    for seed in (0, 1):
        hmepol_run("exact", seed, "exact")
    alone = group_runs(discover_runs(tmp_path / "exact")[0])
    assert [g.label for g in alone] == ["HMepol (algo.trust_region=exact)"]
    for seed in (0, 1):
        hmepol_run("thesis", seed, "gradient")
    both = group_runs(discover_runs(tmp_path)[0])
    assert sorted(g.label for g in both) == [
        "HMepol (algo.trust_region=exact)", "HMepol (algo.trust_region=gradient)",
    ]  # fmt: skip
    thesis = group_runs(discover_runs(tmp_path / "thesis")[0])
    assert [g.label for g in thesis] == ["HMepol"]


def test_a_run_continued_for_more_epochs_groups_by_the_epochs_it_was_taken_to(tmp_path):
    write_run(tmp_path, algo="hmepol", seed=0, epochs=40, name="a")
    continued = write_run(tmp_path, algo="hmepol", seed=1, epochs=20, epochs_done=40, name="b")
    meta = json.loads((continued / "run.json").read_text())
    (continued / "run.json").write_text(json.dumps({**meta, "epochs": 40}))  # resume epochs=40
    groups = group_runs(discover_runs(tmp_path)[0])
    assert [(g.label, g.seeds) for g in groups] == [("HMepol", [0, 1])]


def test_wind_interpolation_and_top_level_wind_count_once(tmp_path):
    for wind in (0.05, 0.4):
        write_run(tmp_path, env="slope", algo="mepol", wind=wind)
    runs, _ = discover_runs(tmp_path)
    assert varying_keys(runs) == ["wind"]
    assert [g.wind for g in group_runs(runs)] == [0.05, 0.4]


def test_how_a_run_was_executed_does_not_split_groups(tmp_path):
    # Seed 0 ran inside a population on a GPU, seed 1 alone on a CPU: the same experiment.
    write_run(
        tmp_path,
        seed=0,
        extra_config="seeds: [0, 2]\nvmap: 'on'\ncuda_graphs: true\nmatmul_precision: high\n",
    )
    write_run(
        tmp_path,
        seed=1,
        extra_config="seeds: null\nvmap: 'off'\ncuda_graphs: false\nmatmul_precision: highest\n",
    )
    runs, _ = discover_runs(tmp_path)
    assert varying_keys(runs) == []
    assert [g.seeds for g in group_runs(runs)] == [[0, 1]]


def _skip_warnings(caught) -> list[str]:
    return [str(w.message) for w in caught if issubclass(w.category, SkippedRunWarning)]


def test_duplicate_seed_keeps_the_run_with_most_epochs_and_names_both(tmp_path):
    # Seed 0 twice with the same settings: a copy taken at 20 epochs, and the original resumed
    # to 40. The copy sorts first; the resumed run is the one to keep.
    copy = write_run(tmp_path, seed=0, epochs=20, name="a-copy", last_wall_time=2e9)
    resumed = write_run(tmp_path, seed=0, epochs=20, epochs_done=40, name="b-resumed")
    write_run(tmp_path, seed=1, epochs=20)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        runs, left_out = drop_duplicate_seeds(discover_runs(tmp_path)[0])
    [message] = _skip_warnings(caught)
    assert str(copy) in message and str(resumed) in message
    assert [s.path for s in left_out] == [copy]
    [group] = group_runs(runs)
    assert group.seeds == [0, 1]
    assert next(r for r in group.runs if r.seed == 0).path == resumed
    # The resumed run's curve alone: the mean of its last 4 of 40 points i/39 is 37.5/39.
    assert group.finals()[0] == pytest.approx(37.5 / 39)


def test_duplicate_seed_with_as_many_epochs_keeps_the_later_one(tmp_path):
    earlier = write_run(tmp_path, seed=3, name="a-earlier", last_wall_time=1.7e9)
    later = write_run(tmp_path, seed=3, name="b-later", last_wall_time=1.8e9)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        runs, left_out = drop_duplicate_seeds(discover_runs(tmp_path)[0])
    assert [r.path for r in runs] == [later]
    assert [s.path for s in left_out] == [earlier]
    [message] = _skip_warnings(caught)
    assert str(earlier) in message and str(later) in message


# ------------------------------------------------------------------------- summary differences
def test_summary_difference_equals_hand_computed(tmp_path):
    finals = {"mepol": {0: 1.0, 1: 1.2, 2: 1.1}, "hmepol": {0: 1.5, 1: 1.4, 3: 1.9}}
    for algo, by_seed in finals.items():
        for seed, value in by_seed.items():
            write_run(tmp_path, algo=algo, seed=seed, final=value, epochs=10)
    groups = group_runs(discover_runs(tmp_path)[0])
    # 10 epochs of a linear ramp 0..final: the last 10% is the last epoch, i.e. ``final``.
    summary = final_entropy_table(groups).set_index(["group", "config"])
    assert summary.loc[("Mepol", "average"), "mean_nats"] == pytest.approx(1.1)
    assert summary.loc[("HMepol", "1: north"), "mean_nats"] == pytest.approx(1.6 - 0.1)
    diff = difference_table(groups).set_index("config").loc["average"]
    assert diff["comparison"] == "HMepol − Mepol"
    assert diff["method"] == "Welch t"  # seeds {0,1,2} vs {0,1,3}: not paired
    # a: mean 1.1, var 0.01; b: mean 1.6, var 0.07; se^2 = 0.08/3
    # df = (0.08/3)^2 / ((0.01/3)^2/2 + (0.07/3)^2/2) = 2.56; t_{0.975,2.56} = 3.515420
    se = math.sqrt(0.08 / 3)
    assert diff["diff_nats"] == pytest.approx(0.5)
    assert diff["ci95_high"] - diff["diff_nats"] == pytest.approx(3.515420 * se, rel=1e-6)


def test_summary_difference_carries_the_seeds_it_would_need(tmp_path):
    from hmepol_cli.report.stats import Spread, seeds_for_half_width, seeds_for_power

    finals = {"mepol": {0: 1.0, 1: 1.2, 2: 1.1}, "hmepol": {0: 1.5, 1: 1.4, 3: 1.9}}
    for algo, by_seed in finals.items():
        for seed, value in by_seed.items():
            write_run(tmp_path, algo=algo, seed=seed, final=value, epochs=10)
    diff = difference_table(group_runs(discover_runs(tmp_path)[0])).set_index("config")
    row = diff.loc["average"]
    spread = Spread.welch(0.01, 0.07)  # the two arms' variances, as by hand above
    assert row["seeds_per_arm_hw0.25"] == seeds_for_half_width(spread, 0.25)
    assert row["seeds_per_arm_hw0.3"] == seeds_for_half_width(spread, 0.3)
    assert row["seeds_per_arm_power80_d0.4"] == seeds_for_power(spread, 0.4)
    assert row["seeds_per_arm_hw0.25"] >= row["seeds_per_arm_hw0.3"] >= 2
    assert 0.0 < row["detectable_diff_power80"] < math.inf


# ---------------------------------------------------------------- fine-tuning over its true unit
def test_fine_tuning_interval_is_over_pre_training_runs_not_curves(tmp_path):
    from hmepol_cli.report.summary import finetune_table

    # Two pre-training runs, five targets each, every target of a run at the same return: ten
    # curves, but two independent draws (the same case as test_statistics, through the table).
    for seed, value in ((0, 0.2), (1, 0.6)):
        write_finetune_run(
            tmp_path, algo_init="hmepol", seed=seed, targets=5, returns=lambda e, t, v=value: v
        )
    runs, _ = discover_runs(tmp_path)
    table = finetune_table(runs)
    row = table[table["config"] == 0].iloc[0]
    assert (row["n_pretrain"], row["n_targets"], row["n_curves"], row["n_units"]) == (2, 5, 10, 2)
    assert row["unit"] == "pre-training run" and row["final_return"] == pytest.approx(0.4)
    assert row["ci95_half_width"] == pytest.approx(12.706204736 * 0.2, rel=1e-9)
    # A goal task's return is a share of episodes: the interval stops at 0 and 1.
    assert (row["ci95_low"], row["ci95_high"]) == (0.0, 1.0)


def test_fine_tuning_seeds_of_one_pre_training_run_are_one_unit(tmp_path):
    from hmepol_cli.report.summary import finetune_table

    # Three fine-tunings of one pre-training run (seeds 0-2, its kept checkpoint given two
    # ways): one unit, so no interval; a second pre-training run makes two.
    for seed, init in ((0, "/runs/a@75"), (1, "/runs/a@75"), (2, "/runs/a/checkpoints/last.pt")):
        write_finetune_run(tmp_path, algo_init="mepol", seed=seed, init=init)
    table = finetune_table(discover_runs(tmp_path)[0])
    row = table.iloc[0]
    assert (row["n_units"], row["n_pretrain"], row["n_finetune_seeds"]) == (1, 1, 3)
    assert math.isnan(row["ci95_low"]) and math.isnan(row["ci95_high"])
    write_finetune_run(tmp_path, algo_init="mepol", seed=0, init="/runs/b@75", name="from-b")
    assert finetune_table(discover_runs(tmp_path)[0]).iloc[0]["n_units"] == 2
    # From scratch each fine-tuning run is its own unit.
    for seed in (0, 1, 2):
        write_finetune_run(tmp_path, algo_init="scratch", seed=seed)
    scratch = finetune_table(discover_runs(tmp_path)[0]).query("init == 'from scratch'")
    assert (scratch["n_units"] == 3).all() and (scratch["n_pretrain"] == 0).all()


def test_fine_tuning_reaches_the_mepol_final_return_not_its_last_epoch(tmp_path):
    from hmepol_cli.report.summary import finetune_table

    # Mepol's final return is its mean over the last 10% of epochs (18, 19: 0.925), not its
    # last epoch's 0.95; HMepol's curve e / 19 passes 0.925 at epoch 18 and 0.95 only at 19.
    for algo, slope in (("mepol", 1 / 20), ("hmepol", 1 / 19)):
        for seed in (0, 1):
            write_finetune_run(
                tmp_path, algo_init=algo, seed=seed, epochs=20, targets=1,
                returns=lambda e, t, k=slope: k * e,
            )  # fmt: skip
    table = finetune_table(discover_runs(tmp_path)[0]).set_index(["config", "init"])
    assert table.loc[(0, "Mepol"), "final_return"] == pytest.approx(0.925)
    assert table.loc[(0, "HMepol"), "first_epoch_reaching_mepol_final"] == 18


def test_fine_tuning_differences_are_paired_by_seed_by_hand(tmp_path):
    from hmepol_cli.report.summary import finetune_difference_table

    returns = {"mepol": {0: 0.4, 1: 0.4, 2: 0.2}, "hmepol": {0: 0.9, 1: 0.5, 2: 0.7}}
    for algo, by_seed in returns.items():
        for seed, value in by_seed.items():
            write_finetune_run(
                tmp_path, algo_init=algo, seed=seed, returns=lambda e, t, v=value: v
            )
    row = finetune_difference_table(discover_runs(tmp_path)[0]).iloc[0]
    assert row["comparison"] == "HMepol − Mepol" and row["configs"] == "0 1"
    assert (row["n_pairs"], row["seeds"]) == (3, "0 1 2")
    # d = 0.5, 0.1, 0.5: mean 0.36667, s = 0.23094, t_{0.975,2} = 4.302653, se = s / sqrt(3)
    assert row["diff"] == pytest.approx(0.11 / 0.3)
    assert row["ci95_half_width"] == pytest.approx(4.302653 * 0.23094011 / math.sqrt(3), rel=1e-6)
    # |d| = (0.5, 0.1, 0.5): of the 8 sign assignments, only all + and all - reach |0.3667|.
    assert row["p_sign_flip"] == pytest.approx(0.25)
    assert (row["return_a"], row["return_b"]) == pytest.approx((1.0 / 3, 0.7))


def test_fine_tuning_pairs_by_pre_training_seed_when_one_fine_tuning_seed_serves_all(tmp_path):
    from hmepol_cli.report.summary import finetune_difference_table

    # make finetune-corridor's layout: every pre-trained start fine-tuned with seed 0. The
    # pre-training seed comes from the run's run.json (HMepol's, here 7 and 8, whatever its name
    # says) or, where that folder is gone, from a seed-<n> in its name (Mepol's).
    kept = {}
    for n in (7, 8):
        kept[n] = tmp_path / "pretraining" / f"kept-{n}"
        kept[n].mkdir(parents=True)
        (kept[n] / "run.json").write_text(json.dumps({"seed": n}))
    values = {"hmepol": {7: 0.9, 8: 0.5}, "mepol": {7: 0.4, 8: 0.4}}
    for algo, by_seed in values.items():
        for n, value in by_seed.items():
            init = kept[n] if algo == "hmepol" else f"/gone/experiment-corridor_{algo}_seed-{n}@75"
            write_finetune_run(
                tmp_path / "ft", algo_init=algo, seed=0, init=str(init), name=f"{algo}-{n}",
                returns=lambda e, t, v=value: v,
            )  # fmt: skip
    row = finetune_difference_table(discover_runs(tmp_path / "ft")[0]).iloc[0]
    assert (row["n_pairs"], row["seeds"]) == (2, "7 8")
    assert row["diff"] == pytest.approx(0.3) and row["p_sign_flip"] == pytest.approx(0.5)


def test_fine_tuning_differences_cut_to_the_range_and_pool_only_shared_configs(tmp_path):
    from hmepol_cli.report.summary import finetune_difference_table

    # Seed 0: Mepol 0.0, HMepol 0.9; seed 1: 0.5 and 0.6. HMepol's configuration 1 (1.0, never
    # reached by Mepol, which ran only configuration 0) stays out of the pairs.
    for algo, by_seed in {"mepol": {0: 0.0, 1: 0.5}, "hmepol": {0: 0.9, 1: 0.6}}.items():
        for seed, value in by_seed.items():
            run = write_finetune_run(
                tmp_path, algo_init=algo, seed=seed, returns=lambda e, t, v=value: v
            )
            rows = pd.read_csv(run / "finetune.csv")
            if algo == "mepol":
                rows = rows[rows["config"] == 0]
            else:
                rows.loc[rows["config"] == 1, "return"] = 1.0
            rows.to_csv(run / "finetune.csv", index=False)
    row = finetune_difference_table(discover_runs(tmp_path)[0]).iloc[0]
    assert row["configs"] == "0" and row["diff"] == pytest.approx(0.5)
    # d = 0.9, 0.1: half-width 12.706 * 0.4 = 5.08, cut to the range of a difference, [-1, 1].
    assert row["ci95_half_width"] == pytest.approx(12.706204736 * 0.4, rel=1e-9)
    assert (row["ci95_low"], row["ci95_high"]) == (-1.0, 1.0)


def test_fine_tuning_differences_first_epoch_and_every_pair_of_starts(tmp_path):
    from hmepol_cli.report.summary import finetune_difference_table

    # The default returns: min(1, speed e / 10) (1 - 0.01 t), speeds 1.0, 0.3, 0.1, targets
    # 0-2. Mepol's R: its last epoch, 0.27 * 0.99 = 0.2673; HMepol's mean curve 0.099 e
    # reaches it at epoch 3.
    for algo in ("hmepol", "mepol", "scratch"):
        for seed in (0, 1):
            write_finetune_run(tmp_path, algo_init=algo, seed=seed)
    table = finetune_difference_table(discover_runs(tmp_path)[0]).set_index("comparison")
    assert list(table.index) == ["HMepol − Mepol", "from scratch − Mepol", "from scratch − HMepol"]
    row = table.loc["HMepol − Mepol"]
    assert row["return_a"] == pytest.approx(0.2673)
    assert row["first_epoch_b_reaching_a"] == 3
    # Scratch (0.1 e / 10) never reaches HMepol's 0.891 in 10 epochs.
    assert math.isnan(table.loc["from scratch − HMepol", "first_epoch_b_reaching_a"])


def test_a_reward_task_without_a_success_rate_is_not_bounded(tmp_path):
    from hmepol_cli.report.summary import finetune_table

    for seed in range(3):
        run = write_finetune_run(tmp_path, algo_init="scratch", seed=seed)
        rows = pd.read_csv(run / "finetune.csv")
        rows["return"] = 50.0 * seed + rows["epoch"]  # a world's own reward, far past 1
        rows["success_rate"] = np.nan  # what the runner writes for a Gymnasium world's task
        rows.to_csv(run / "finetune.csv", index=False)
    row = finetune_table(discover_runs(tmp_path)[0]).iloc[0]
    assert row["ci95_high"] > 1.0 and row["ci95_low"] < row["final_return"]
    assert row["ci95_high"] - row["ci95_low"] == pytest.approx(2 * row["ci95_half_width"])


# ---------------------------------------------------------------------------- merged copies
def test_a_run_found_in_two_folders_is_counted_once(tmp_path, capsys):
    first, second = tmp_path / "epoch75", tmp_path / "epoch100"
    for seed in (0, 1):
        write_run(first, algo="mepol", seed=seed)
        write_finetune_run(first, algo_init="scratch", seed=seed)
        write_finetune_run(second, algo_init="hmepol", seed=seed)
    # The same scratch run and the same pre-training run in both folders: copies.
    shutil.copytree(first / "finetune-scratch-seed0", second / "finetune-scratch-seed0")
    shutil.copytree(first / "slope-mepol-wind0.4-seed1", second / "slope-mepol-wind0.4-seed1")
    index = run_report([first, second], tmp_path / "report")
    assert "2 identical copies merged" in capsys.readouterr().out
    finetune = pd.read_csv(tmp_path / "report" / "finetune.csv")
    scratch = finetune[(finetune["init"] == "from scratch") & (finetune["config"] == 0)].iloc[0]
    assert scratch["n_curves"] == 2 * 3 and scratch["n_units"] == 2  # two runs, not three
    summary = pd.read_csv(tmp_path / "report" / "summary.csv")
    assert set(summary["seeds"]) == {"0 1"}
    page = html.unescape(index.read_text())
    assert "Merged runs" in page
    assert "<code>epoch75/finetune-scratch-seed0</code> = <code>epoch100/finetune-scratch" in page


def test_a_run_of_the_same_seed_with_other_rows_is_not_a_copy(tmp_path):
    from hmepol_cli.report.runs import merge_identical_runs

    a = write_finetune_run(tmp_path / "a", algo_init="scratch", seed=0)
    b = write_finetune_run(tmp_path / "b", algo_init="scratch", seed=0)
    c = write_finetune_run(tmp_path / "c", algo_init="scratch", seed=0)
    rows = pd.read_csv(b / "finetune.csv")
    rows.loc[3, "return"] = 0.5
    rows.to_csv(b / "finetune.csv", index=False)
    rows = pd.read_csv(c / "finetune.csv")
    rows["seconds"] = 9.0  # another machine's timings: the same run
    rows.to_csv(c / "finetune.csv", index=False)
    runs = [r for root in "abc" for r in discover_runs(tmp_path / root)[0]]
    kept, merged = merge_identical_runs(runs)
    assert [r.path for r in kept] == [a, b]
    assert [(m.path, m.kept) for m in merged] == [(c, a)]


def test_of_two_copies_the_latest_is_kept(tmp_path):
    from hmepol_cli.report.runs import merge_identical_runs

    # The same numbers made twice: only the timings differ. Kept: the later, as
    # drop_duplicate_seeds would keep it.
    earlier = write_run(tmp_path, seed=3, name="a-earlier", last_wall_time=1.7e9)
    later = write_run(tmp_path, seed=3, name="b-later", last_wall_time=1.8e9)
    kept, merged = merge_identical_runs(discover_runs(tmp_path)[0])
    assert [r.path for r in kept] == [later]
    assert [(m.path, m.kept) for m in merged] == [(earlier, later)]


# ----------------------------------------------------------------------------- the whole report
@pytest.mark.slow  # heavy: make test runs it, make test-fast does not
def test_report_skips_bad_runs_and_still_builds(tmp_path, capsys):
    root = tmp_path / "runs"
    for algo in ("mepol", "alphamepol", "hmepol"):
        for seed in (0, 1):
            write_run(root, algo=algo, seed=seed, final=1.0 + 0.1 * seed)
    write_run(root, algo="hmepol", seed=7, status="running", name="unfinished")
    corrupt = write_run(root, algo="hmepol", seed=8, name="corrupt")
    (corrupt / "epochs.csv").write_bytes(b'epoch,entropy\n0,"1.0\n\x00\x01,zz,\n')
    broken = write_run(root, algo="hmepol", seed=9, name="broken-eval")
    (broken / "eval" / "final.npz").write_bytes(b"not a zip file")
    for init, seed in (("mepol", 0), ("mepol", 1), ("hmepol", 0), ("hmepol", 1), ("scratch", 0)):
        write_finetune_run(root, algo_init=init, seed=seed)

    out = tmp_path / "report"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        index = run_report(root, out)
    reasons = {
        Path(str(w.message).split(": ")[0].removeprefix("skipping run ")).name
        for w in caught
        if issubclass(w.category, SkippedRunWarning)
    }
    assert reasons == {"unfinished", "corrupt", "broken-eval"}
    assert index == out / "index.html" and index.exists()
    assert str(index) in capsys.readouterr().out

    page = html.unescape(index.read_text())
    for name in ("unfinished", "corrupt", "broken-eval"):
        assert name in page
    assert "unfinished (status 'running'" in page
    figures = sorted(p.name for p in (out / "figures").glob("*.png"))
    assert figures == sorted(
        [
            "slope_entropy_epochs.png",
            "slope_entropy_epochs_by_config.png",
            "slope_final_entropy_bars.png",
            "slope_aggregates.png",
            "slope_heatmaps.png",
            "slope_trajectories_mepol.png",
            "slope_trajectories_alpha-mepol.png",
            "slope_trajectories_hmepol.png",
            "slope_finetune_returns.png",
        ]
    )
    for name in figures:
        assert f'src="figures/{name}"' in page
    summary = pd.read_csv(out / "summary.csv")
    assert set(summary["n_seeds"]) == {2}
    assert (
        len(pd.read_csv(out / "differences.csv")) == 3 * 3
    )  # 3 pairs x (average + 2 configurations)
    finetune = pd.read_csv(out / "finetune.csv")
    hm = finetune[(finetune["init"] == "HMepol") & (finetune["config"] == 0)].iloc[0]
    assert hm["n_curves"] == 6 and hm["first_epoch_reaching_mepol_final"] < 9
    assert hm["n_pretrain"] == 2 and hm["n_targets"] == 3
    bounded = finetune[["ci95_low", "ci95_high"]].dropna().to_numpy()
    assert ((bounded >= 0.0) & (bounded <= 1.0)).all()
    # 3 rows of the entropy differences (average + 2 configurations), 1 of fine-tuning's.
    assert (out / "summary.md").read_text().count("HMepol − Mepol") == 4
    paired = pd.read_csv(out / "finetune_differences.csv").set_index("comparison")
    assert paired.loc["HMepol − Mepol", "configs"] == "0 1"
    # Every table says its unit, what its n resolves, and that two seeds are too few.
    assert "The unit of independence is the pre-training run" in page
    assert page.count("What these seeds resolve") == 2 and "What these units resolve" in page
    assert "Fewer than 3 independent units: 9 of 9 rows rest on 2 seeds in an arm" in page


# Configuration 0 drawn every epoch, configuration 1 in even epochs only (of 20).
EVEN_EPOCHS_DRAW_BOTH = {e: (0, 1) if e % 2 == 0 else (0,) for e in range(20)}


@pytest.mark.parametrize(
    ("damage", "reason"),
    [
        (lambda text: text[:-20], "epochs.csv is cut short: its last line (21) stops mid-line"),
        (
            lambda text: text.replace(text.splitlines()[5], text.splitlines()[5][:9]),
            "epochs.csv line 6 does not parse: 2 fields, the header has 12",
        ),
        (
            lambda text: set_field(text, 6, "entropy", "0.2.1"),
            "epochs.csv line 6 does not parse: entropy='0.2.1' is not a number",
        ),
        (lambda text: set_field(text, 6, "entropy", ""), "line 6: entropy=nan is not a finite"),
        (lambda text: set_field(text, 6, "entropy", "inf"), "line 6: entropy=inf is not a finite"),
        (
            lambda text: set_field(text, 7, "entropy_c0", "-inf"),
            "line 7: entropy_c0=-inf is not a finite number",
        ),
        (
            lambda text: set_field(text, 5, "entropy_c1", ""),
            "line 5: entropy_c1=nan in epoch 3, which drew configuration 1",
        ),
    ],
    ids=["last-line-cut", "short-row", "not-a-number", "nan", "inf", "inf-config", "nan-drawn"],
)
@pytest.mark.slow  # heavy: make test runs it, make test-fast does not
def test_report_skips_a_run_with_a_malformed_row_and_says_why(tmp_path, damage, reason):
    root = tmp_path / "runs"
    for seed in (0, 1):
        write_batches(write_run(root, seed=seed), EVEN_EPOCHS_DRAW_BOTH)
    damaged = write_run(root, seed=2, name="damaged")
    # Epoch 3 (line 5) drew configuration 1 here.
    write_batches(damaged, EVEN_EPOCHS_DRAW_BOTH | {3: (0, 1)})
    epochs_csv = damaged / "epochs.csv"
    epochs_csv.write_text(damage(epochs_csv.read_text()))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        index = run_report(root, tmp_path / "report")
    [message] = _skip_warnings(caught)
    assert message.startswith(f"skipping run {damaged}: ") and reason in message
    listed = re.search(r"<code>damaged</code>: ([^<]*)</li>", index.read_text())
    assert listed and reason in html.unescape(listed[1])
    # The rest of the report is built from the two sound runs.
    summary = pd.read_csv(tmp_path / "report" / "summary.csv")
    assert set(summary["seeds"]) == {"0 1"}


def test_a_configuration_not_drawn_in_an_epoch_is_not_malformed(tmp_path):
    run = write_run(tmp_path, epochs=20)
    write_batches(run, EVEN_EPOCHS_DRAW_BOTH)
    text = (run / "epochs.csv").read_text()
    for epoch in range(1, 20, 2):  # line epoch + 2
        text = set_field(text, epoch + 2, "entropy_c1", "")
    (run / "epochs.csv").write_text(text)
    [loaded], skipped = discover_runs(tmp_path)
    assert skipped == []
    # Observed at even epochs only: the last 10% of those 10 values is epoch 18's, 0.9 * 18 / 19.
    assert loaded.final_entropy(1) == pytest.approx(0.9 * 18 / 19)


def test_counts_on_stdout_and_in_the_page_are_the_runs_actually_used(tmp_path, capsys):
    root = tmp_path / "runs"
    for algo in ("mepol", "hmepol"):
        for seed in (0, 1):
            write_run(root, algo=algo, seed=seed)
    # A copy of hmepol seed 1 taken half-way: left out.
    write_run(root, algo="hmepol", seed=1, epochs_done=10, name="hmepol-seed1-copy")
    write_run(root, algo="mepol", seed=5, status="running", name="unfinished")
    write_finetune_run(root, algo_init="mepol", seed=0)
    write_finetune_run(root, algo_init="scratch", seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SkippedRunWarning)
        index = run_report(root, tmp_path / "report")
    # 4 pre-training seeds + 2 fine-tuning runs; 2 groups; the copy and the unfinished run
    # skipped; curves, curves per configuration, bars, aggregates, heatmaps, 2 x trajectories,
    # fine-tuning.
    expected = "6 runs used (2 groups), 2 skipped, 8 figures"
    assert capsys.readouterr().out == f"report: {expected} -> {index}\n"
    page = index.read_text()
    assert expected in page
    assert "(4 pre-training runs in 2 groups, 2 fine-tuning runs)" in page
    assert page.count("<figure>") == 8 == len(list((tmp_path / "report" / "figures").iterdir()))
    assert re.findall(r"<li><code>([^<]*)</code>", page) == ["hmepol-seed1-copy", "unfinished"]


@pytest.mark.slow  # heavy: make test runs it, make test-fast does not
def test_a_new_report_replaces_the_files_of_the_earlier_one_and_nothing_else(tmp_path):
    root, out = tmp_path / "runs", tmp_path / "report"
    for algo in ("mepol", "hmepol"):
        write_run(root, algo=algo, seed=0, name=f"{algo}-0")
    write_finetune_run(root, algo_init="hmepol", seed=0)
    run_report(root, out)
    (out / "notes.txt").write_text("mine")
    (out / "figures" / "sketch.png").write_bytes(b"mine too")
    # The HMepol runs are gone: their trajectories and the fine-tuning figure and table go too.
    shutil.rmtree(root / "hmepol-0")
    shutil.rmtree(root / "finetune-hmepol-seed0")
    index = run_report(root, out)
    report_files = {
        "figures/slope_entropy_epochs.png",
        "figures/slope_entropy_epochs_by_config.png",
        "figures/slope_final_entropy_bars.png",
        "figures/slope_aggregates.png",
        "figures/slope_heatmaps.png",
        "figures/slope_trajectories_mepol.png",
        "index.html",
        "summary.csv",
        "summary.md",  # one group left: no differences.csv
    }
    on_disk = {p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()}
    assert on_disk == report_files | {"report.json", "notes.txt", "figures/sketch.png"}
    assert set(json.loads((out / "report.json").read_text())["files"]) == report_files
    assert "finetune.csv" not in index.read_text()  # no link to a table that is gone


def test_report_refuses_a_folder_it_did_not_write(tmp_path, capsys):
    root, out = tmp_path / "runs", tmp_path / "thesis"
    write_run(root)
    out.mkdir()
    (out / "chapter1.tex").write_text("\\chapter{Introduction}")
    with pytest.raises(SystemExit):
        main(["report", str(root), "--out", str(out)])
    [line] = capsys.readouterr().err.splitlines()
    assert line.startswith("hmepol: error: report folder ") and repr(str(out)) in line
    assert [p.name for p in out.iterdir()] == ["chapter1.tex"]
    # An empty folder is a fine place for a report.
    (out / "chapter1.tex").unlink()
    assert run_report(root, out).exists()
    # A manifest that lists a file outside its folder was not written by a report.
    run_json = next(root.rglob("run.json"))
    (out / "report.json").write_text(json.dumps({"files": [f"../runs/{run_json.parent.name}"]}))
    with pytest.raises(UserError, match="is not a report manifest"):
        run_report(root, out)
    assert run_json.exists()


def test_the_command_prints_a_skipped_run_as_one_line(tmp_path, capsys, monkeypatch):
    root = tmp_path / "runs"
    write_run(root, seed=0)
    unfinished = write_run(root, seed=1, status="running", epochs_done=8, name="unfinished")
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        # Python's own printer, which pytest replaces while it records warnings.
        monkeypatch.setattr(
            warnings,
            "showwarning",
            lambda message, category, filename, lineno, file=None, line=None: sys.stderr.write(
                warnings.formatwarning(message, category, filename, lineno, line)
            ),
        )
        main(["report", str(root), "--out", str(tmp_path / "report")])
    warned = [line for line in capsys.readouterr().err.splitlines() if "warning" in line]
    assert warned == [
        f"hmepol: warning: skipping run {unfinished}: unfinished (status 'running', 4 epochs done)"
    ]


def test_report_refuses_missing_or_empty_root(tmp_path):
    with pytest.raises(UserError, match="does not exist"):
        run_report(tmp_path / "nowhere", tmp_path / "out")
    (tmp_path / "empty").mkdir()
    with pytest.raises(UserError, match="no runs"):
        run_report(tmp_path / "empty", tmp_path / "out")


def test_save_run_plots_writes_heatmap_and_trajectories(tmp_path):
    from hmepol_cli.envs import make_world
    from hmepol_cli.report import save_run_plots

    world = make_world(type("Env", (), {"name": "slope", "wind": 0.0})())
    rng = np.random.default_rng(0)
    positions = {
        c: np.clip(rng.normal(0, 0.5, (5, 21, 2)), -1, 1).astype(np.float32) for c in range(2)
    }
    paths = save_run_plots(world, positions, tmp_path / "eval")
    assert sorted(p.name for p in paths) == ["heatmap.png", "trajectories.png"]
    assert all(p.stat().st_size > 1000 for p in paths)


def _maps_drawn_with(monkeypatch) -> list[object]:
    """The map each map figure (heatmaps, trajectories) of the report is drawn on, in order."""
    from hmepol_cli.report import figures

    maps: list[object] = []

    def recording(draw):
        def record(fig, world_map, *args, **kwargs):
            maps.append(world_map)
            return draw(fig, world_map, *args, **kwargs)

        return record

    monkeypatch.setattr(figures, "heatmap_grid", recording(figures.heatmap_grid))
    monkeypatch.setattr(figures, "trajectory_grid", recording(figures.trajectory_grid))
    return maps


@pytest.mark.parametrize("env", ["slope", "corridor", "multigrid"])
def test_maps_are_drawn_from_the_map_run_json_records(tmp_path, monkeypatch, env):
    maps = _maps_drawn_with(monkeypatch)
    names = make_world(type("Env", (), {"name": env})()).configuration_names
    for seed in (0, 1):
        write_run(tmp_path / "runs", env=env, seed=seed, configuration_names=names,
                  configuration_probs=(1 / len(names),) * len(names))  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("error", MapUnknownWarning)
        run_report(tmp_path / "runs", tmp_path / "report")
    world = make_world(type("Env", (), {"name": env, "wind": 0.4})())
    built = WorldMap.from_json(world.world_map())
    assert maps and all(drawn == built for drawn in maps)  # heatmaps, trajectories
    assert built.arena == (world.arena.x0, world.arena.y0, world.arena.x1, world.arena.y1)
    walls = [np.array([[b.x0, b.y0, b.x1, b.y1] for b in w]).reshape(-1, 4) for w in world.walls]
    for drawn, wall in zip(built.walls, walls, strict=True):
        np.testing.assert_array_equal(np.array(drawn).reshape(-1, 4), wall)


@pytest.mark.parametrize(("env", "wind"), [("nowhere", 0.4), ("corridor", -1.0), ("slope", 0.4)])
def test_a_run_json_without_a_map_is_drawn_without_walls_and_said_once(
    tmp_path, monkeypatch, capsys, env, wind
):
    # An unknown world, one that refuses its config, a run.json made before it held the map.
    maps = _maps_drawn_with(monkeypatch)
    for seed in (0, 1):
        run = write_run(tmp_path / "runs", env=env, wind=wind, seed=seed)
        meta = json.loads((run / "run.json").read_text())
        meta.pop("world_map", None)
        (run / "run.json").write_text(json.dumps(meta))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        index = run_report(tmp_path / "runs", tmp_path / "report")
    unknown = [w for w in caught if issubclass(w.category, MapUnknownWarning)]
    assert len(unknown) == 1 and "2 run(s)" in str(unknown[0].message)
    assert maps and all(world_map is None for world_map in maps)
    assert "2 runs used (1 groups), 0 skipped" in capsys.readouterr().out
    page = index.read_text()
    for name in ("heatmaps", "trajectories_mepol", "entropy_epochs", "final_entropy_bars"):
        assert (tmp_path / "report" / "figures" / f"{env}_{name}.png").is_file()
        assert f'src="figures/{env}_{name}.png"' in page


def test_a_damaged_map_makes_the_run_one_the_report_skips(tmp_path):
    for seed in (0, 1):
        write_run(tmp_path / "runs", seed=seed)
    damaged = tmp_path / "runs" / "slope-mepol-wind0.4-seed1" / "run.json"
    damaged.write_text(json.dumps({**json.loads(damaged.read_text()), "world_map": {"walls": 1}}))
    with pytest.warns(SkippedRunWarning, match="world_map is not a map"):
        runs, skipped = discover_runs(tmp_path / "runs")
    assert [r.seed for r in runs] == [0] and len(skipped) == 1


@pytest.fixture()
def drawn_figures(monkeypatch) -> dict[str, object]:
    """The figures the report saves, by file name, to look at their axes."""
    from hmepol_cli.report import figures

    drawn: dict[str, object] = {}

    def save_and_keep(fig, path):
        drawn[Path(path).name] = fig
        return save(fig, path)

    save = figures.save
    monkeypatch.setattr(figures, "save", save_and_keep)
    return drawn


def _panels(fig) -> list:
    return [ax for ax in fig.axes if ax.get_lines()]


def _line_values(ax) -> np.ndarray:
    values = np.concatenate([np.asarray(line.get_ydata(), float) for line in ax.get_lines()])
    return values[np.isfinite(values)]


def test_every_entropy_panel_shows_its_whole_curve(tmp_path, drawn_figures):
    # Configuration 0 ends at 10 nats, configuration 1 at 1: on one shared scale set by the last
    # panel, the first curve would leave its axes. The two winds differ likewise.
    write_run(tmp_path / "runs", wind=0.05, final=10.0, config_finals=(10.0, 1.0))
    write_run(tmp_path / "runs", wind=0.4, final=1.0, config_finals=(10.0, 1.0))
    run_report(tmp_path / "runs", tmp_path / "report")
    by_config = _panels(drawn_figures["slope_entropy_epochs_by_config.png"])
    assert [ax.get_title() for ax in by_config] == [
        "config 0: south, wind 0.05",
        "config 1: north, wind 0.05",
        "config 0: south, wind 0.4",
        "config 1: north, wind 0.4",
    ]
    average = _panels(drawn_figures["slope_entropy_epochs.png"])
    for ax in by_config + average:
        low, high = ax.get_ylim()
        values = _line_values(ax)
        assert low < values.min() and values.max() < high, ax.get_title()
    for ax in by_config[1::2]:  # configuration 1: its own scale, 0 to log(3.04) = 1.11
        assert ax.get_ylim()[1] < 2.0
    for ax in drawn_figures["slope_final_entropy_bars.png"].axes:
        low, high = ax.get_ylim()
        assert all(low <= bar.get_height() <= high for bar in ax.patches), ax.get_title()


def test_the_entropy_against_wind_shows_its_bound_and_keeps_its_legend_off_the_bars(
    tmp_path, drawn_figures
):
    # Wind 0.4's seeds end just under the bound log(3.04) = 1.11 nats: autoscaled to the
    # error bars, the axes stopped within a hair of the dashed bound, which the frame hid (as
    # in the wind sweep's figure), and a legend inside the axes covered error bars.
    for wind, top in ((0.05, 0.5), (0.4, 1.1)):
        for seed in (0, 1, 2):
            final = top - 0.01 * seed
            write_run(tmp_path / "runs", wind=wind, seed=seed, final=final,
                      config_finals=(final, final))  # fmt: skip
    run_report(tmp_path / "runs", tmp_path / "report")
    fig = drawn_figures["slope_entropy_vs_wind.png"]
    [ax] = fig.axes
    low, high = ax.get_ylim()
    [bound] = [line for line in ax.get_lines() if line.get_linestyle() == "--"]
    assert bound.get_ydata()[0] == pytest.approx(math.log(3.04))
    assert bound.get_ydata()[0] < high - 0.03 * (high - low)
    assert ax.get_legend() is None
    [legend] = fig.legends
    texts = [t.get_text() for t in legend.get_texts()]
    assert texts == ["log(free area) = 1.11 nats", "Mepol (n=3)"]


def test_a_run_of_one_epoch_is_drawn_as_a_point(tmp_path, drawn_figures):
    for seed in (0, 1):
        write_run(tmp_path / "runs", seed=seed, epochs=1)  # entropy 0 at epoch 0
    run_report(tmp_path / "runs", tmp_path / "report")
    for name in ("slope_entropy_epochs.png", "slope_entropy_epochs_by_config.png"):
        for ax in _panels(drawn_figures[name]):
            markers = [
                line
                for line in ax.get_lines()
                if line.get_marker() not in ("None", "", " ") and line.get_markersize() > 0
            ]
            points = [(x, y) for line in markers for x, y in line.get_xydata()]
            assert points == [(0.0, 0.0)], (name, ax.get_title())


def _bands(ax) -> list[np.ndarray]:
    from matplotlib.collections import PolyCollection

    return [
        path.vertices
        for c in ax.collections
        if isinstance(c, PolyCollection)
        for path in c.get_paths()
    ]


def test_under_three_seeds_each_seed_is_drawn_and_no_band(tmp_path, drawn_figures):
    for algo in ("mepol", "hmepol"):
        for seed in (0, 1):
            write_run(tmp_path / "runs", algo=algo, seed=seed, final=1.0 + 0.3 * seed)
    index = run_report(tmp_path / "runs", tmp_path / "report")
    [ax] = _panels(drawn_figures["slope_entropy_epochs.png"])
    assert _bands(ax) == []
    curves = [line for line in ax.get_lines() if len(line.get_xdata()) == 20]
    assert len(curves) == 2 * (2 + 1)  # each group: two seeds' own curves and their mean
    means = [line for line in curves if line.get_label().startswith(("Mepol", "HMepol"))]
    assert len({line.get_color() for line in means}) == 2
    assert [line.get_label() for line in means] == [
        "Mepol (n=2, each seed drawn)", "HMepol (n=2, each seed drawn)",
    ]  # fmt: skip
    bars = drawn_figures["slope_final_entropy_bars.png"].axes[0]
    assert not bars.containers or all(
        type(c).__name__ != "ErrorbarContainer" for c in bars.containers
    )
    assert "thin lines: each seed's own curve" in html.unescape(index.read_text())


def test_from_three_seeds_a_band_is_drawn_inside_the_axes(tmp_path, drawn_figures):
    for seed in range(3):
        write_run(tmp_path / "runs", seed=seed, final=1.0 + 0.5 * seed)
    index = run_report(tmp_path / "runs", tmp_path / "report")
    [ax] = _panels(drawn_figures["slope_entropy_epochs.png"])
    [band] = _bands(ax)
    low, high = ax.get_ylim()
    assert low <= band[:, 1].min() and band[:, 1].max() <= high
    assert len([line for line in ax.get_lines() if len(line.get_xdata()) == 20]) == 1  # mean
    assert "band: Student-t 95% CI over seeds (3 seeds)" in html.unescape(index.read_text())


def test_every_group_has_a_colour_of_its_own():
    from types import SimpleNamespace

    from hmepol_cli.plots import algo_colour
    from hmepol_cli.report.series import series_styles

    def group(algo: str, label: str, **config) -> SimpleNamespace:
        defaults = {"algo.adam_reset": None, "algo.trust_region": "gradient", "policy.bptt": "1"}
        first = SimpleNamespace(wind=0.4, config={**defaults, **config})
        return SimpleNamespace(algo=algo, label=label, env="slope", wind=0.4, first=first)

    groups = [
        group("mepol", "Mepol"),
        group("hmepol", "HMepol (algo.adam_reset=epoch)", **{"algo.adam_reset": "epoch"}),
        group("hmepol", "HMepol (algo.trust_region=exact)", **{"algo.trust_region": "exact"}),
        group("hmepol", "HMepol (bptt=full)", **{"policy.bptt": "full"}),
        group("hmepol", "HMepol"),
    ]
    styles = series_styles(groups)
    assert len({s.colour for s in styles.values()}) == 5
    # The main series keeps its algorithm's colour and a solid line; variants are dashed.
    assert styles["HMepol"].colour == algo_colour("hmepol") and styles["HMepol"].linestyle == "-"
    assert styles["Mepol"].colour == algo_colour("mepol")
    assert all(styles[g.label].linestyle != "-" for g in groups[1:4])


def test_a_fine_tuning_band_stays_inside_the_range_of_a_return(tmp_path, drawn_figures):
    # Three pre-training runs near 1: the t-band would reach past 1.
    for seed, value in enumerate((1.0, 0.9, 0.4)):
        write_finetune_run(
            tmp_path / "runs", algo_init="hmepol", seed=seed, returns=lambda e, t, v=value: v
        )
    run_report(tmp_path / "runs", tmp_path / "report")
    for ax in _panels(drawn_figures["slope_finetune_returns.png"]):
        [band] = _bands(ax)
        assert band[:, 1].min() >= 0.0 and band[:, 1].max() == pytest.approx(1.0)
        assert ax.get_ylim() == pytest.approx((-0.05, 1.05))


def test_figure_names_of_long_labels_stay_short_and_distinct():
    from hmepol_cli.report.figures import slug

    long_a = "Mepol (" + ", ".join(f"algo.key{i}={i}" for i in range(40)) + ")"
    long_b = long_a.replace("key39=39", "key39=40")
    assert len(slug(long_a)) <= 80 and len(slug(long_b)) <= 80
    assert slug(long_a) != slug(long_b)
    assert slug("α-Mepol") == "alpha-mepol"


@pytest.mark.slow  # end to end: runs of the installed command (make test runs it)
def test_exported_runs_rebuild_the_same_summary(tmp_path):
    """docs/results keeps the small files of runs (positions in float16): the report made from
    them gives the summary of the report made from the runs themselves."""
    from hmepol_cli.report.export import export_runs
    from hmepol_cli.run import load_positions

    for algo in ("mepol", "hmepol"):
        for seed in (0, 1):
            run_dir = write_run(tmp_path / "runs", algo=algo, seed=seed, final=1.0 + seed / 10)
            (run_dir / "checkpoints").mkdir()
            (run_dir / "checkpoints" / "last.pt").write_bytes(b"weights")
    with pytest.warns(UserWarning, match="its final policy is not exported"):  # not a checkpoint
        exported = export_runs(tmp_path / "runs", tmp_path / "kept")
    assert len(exported) == 4
    for run_dir in exported:
        assert not (run_dir / "checkpoints").exists()
        positions = np.load(run_dir / "eval" / "final.npz")
        assert all(positions[k].dtype == np.float16 for k in positions.files)
        original = load_positions(
            tmp_path / "runs" / run_dir.relative_to(tmp_path / "kept") / "eval" / "final.npz"
        )
        for c, array in load_positions(run_dir / "eval" / "final.npz").items():
            np.testing.assert_allclose(array, original[c], atol=2e-3)
    run_report(tmp_path / "runs", tmp_path / "report_a")
    run_report(tmp_path / "kept", tmp_path / "report_b")
    a = pd.read_csv(tmp_path / "report_a" / "summary.csv")
    b = pd.read_csv(tmp_path / "report_b" / "summary.csv")
    pd.testing.assert_frame_equal(a, b)


@pytest.mark.slow  # end to end: runs of the installed command (make test runs it)
def test_every_caption_states_its_scale_and_a_smoke_run_says_so(tmp_path):
    small, large = tmp_path / "small", tmp_path / "large"
    write_run(small, seed=0, epochs=15, n_traj=10, horizon=40)
    write_finetune_run(small, algo_init="mepol", seed=0)
    for seed in range(4):
        write_run(large, seed=seed, epochs=120)
    page = html.unescape(run_report(small, tmp_path / "a").read_text())
    assert "Smoke scale, not a result" in page and "1 seed, 15 epochs" in page
    captions = re.findall(r"<figcaption>(.*?)</figcaption>", page, flags=re.S)
    assert captions and all("Scale: " in c for c in captions)
    assert "Scale: 1 seed, 15 epochs of" in page
    page = html.unescape(run_report(large, tmp_path / "b").read_text())
    assert "Smoke scale" not in page
    assert "Scale: 4 seeds, 120 epochs of" in page


# ------------------------------------------------------------------------------- diagnostics
def test_drops_and_the_kl_ratio_of_the_update_before_them_by_hand(tmp_path):
    from hmepol_cli.report.diagnostics import diagnosed, drop_table, pooled_drops

    run = write_run(tmp_path, algo="hmepol", policy="recursive", seed=0, epochs=60)
    epochs = pd.read_csv(run / "epochs.csv")
    # Configuration 1 falls by 2.5 nats at epoch 40 and recovers; a fall at epoch 10 is too early
    # to count (DROP_FROM = 30); configuration 0 falls by 0.9 at epoch 50: not a drop.
    epochs.loc[epochs.epoch == 40, "entropy_c1"] -= 2.5
    epochs.loc[epochs.epoch == 10, "entropy_c1"] -= 3.0
    epochs.loc[epochs.epoch == 50, "entropy_c0"] -= 0.9
    # Both configurations fall by 1.5 at epoch 55: two configurations' drops, one epoch's.
    epochs.loc[epochs.epoch == 55, ["entropy_c0", "entropy_c1"]] -= 1.5
    epochs.to_csv(run / "epochs.csv", index=False)
    # Two steps an epoch, the second accepted: one-step KL 0.01, exact 0.02, except epoch 39's
    # and 54's updates (the ones before the drops): exact 0.5, a ratio of 50.
    rows = []
    for e in range(60):
        rows.append({"epoch": e, "step": 0, "accepted": False, "kl_one_step": 9.0, "kl_exact": 9.0})
        exact = 0.5 if e in (39, 54) else 0.02
        rows.append(
            {"epoch": e, "step": 1, "accepted": True, "kl_one_step": 0.01, "kl_exact": exact}
        )
    pd.DataFrame(rows).to_csv(run / "steps.csv", index=False)
    write_run(tmp_path, algo="mepol", seed=0, epochs=60)  # no steps.csv: compared beside it
    groups = group_runs(discover_runs(tmp_path)[0])
    table = drop_table(diagnosed(groups))
    [hmepol] = [row for row in table.to_dict("records") if row["drops"]]
    assert hmepol["drop_epochs"] == "40 55"
    # 40 is a drop of configuration 1 (2.5 nats less the ramp's step); its recovery at 41 is not.
    # 55 is one epoch with a drop in each configuration.
    assert (hmepol["drops"], hmepol["drops_c0"], hmepol["drops_c1"]) == (2, 1, 2)
    assert hmepol["largest_fall"] == pytest.approx(2.5 - 0.9 / 59)
    assert hmepol["kl_ratio_before_drops"] == pytest.approx(50.0)
    assert hmepol["kl_ratio_other_updates"] == pytest.approx(2.0)
    assert {g.label for g in diagnosed(groups)} == {"Mepol", "HMepol"}
    pooled = pooled_drops(table).set_index("group")
    assert pooled.loc["HMepol", ["runs", "runs_with_drops", "drops", "drops_c1"]].tolist() == [
        1, 1, 2, 2,
    ]  # fmt: skip
    # One run of one with a drop: Wilson's interval [1 / (1 + z^2), 1], not the point 1.
    assert pooled.loc["HMepol", "share_wilson95_high"] == 1.0
    assert pooled.loc["HMepol", "share_wilson95_low"] == pytest.approx(1 / (1 + 1.959964**2))
    assert pooled.loc["Mepol", "drops"] == 0 and pooled.loc["Mepol", "share_wilson95_low"] == 0


def test_a_fine_tuning_legend_names_the_pre_training_epoch_it_started_from():
    from hmepol_cli.report.captions import init_epochs_text

    frame = pd.DataFrame(
        {"algo_init": ["hmepol", "hmepol", "mepol", "scratch"], "init_epoch": [75, 75, 100, None]}
    )
    assert init_epochs_text(frame, "hmepol") == ", from epoch 75"
    assert init_epochs_text(frame, "mepol") == ", from epoch 100"
    assert init_epochs_text(frame, "scratch") == ""
    assert init_epochs_text(frame.drop(columns="init_epoch"), "hmepol") == ""  # older runs


def test_a_block_label_too_long_for_the_figure_gets_smaller_type():
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    from hmepol_cli.plots import _blocks

    fig = Figure(figsize=(6.2, 6))
    _blocks(fig, 2, 1, 2, ["short", "x" * 100])
    short, long = (sub._suptitle for sub in fig.subfigs)
    assert short.get_fontsize() == 10
    assert long.get_fontsize() == pytest.approx(10 * 8.0 * 6.2 / 100)


def test_a_long_block_label_takes_two_lines_before_smaller_type():
    from hmepol_cli.plots import block_title

    label = "HMepol (algo.trust_region=exact): seed 3 (its final entropy is the lower median of 4)"
    text, size = block_title(label, 40.0)  # a 5-inch block: 40 characters of 10-point type
    first, second = text.split("\n")
    assert f"{first} {second}" == label and max(len(first), len(second)) == 44
    assert size == pytest.approx(10 * 40 / 44)  # against 10 * 40 / 85 on one line
    assert block_title("Mepol: seed 2", 40.0) == ("Mepol: seed 2", 10.0)
    text, size = block_title(label, 50.0)  # two lines of at most 50 characters: full size
    assert text.count("\n") == 1 and size == 10.0


def test_category_labels_break_at_parenthesis_and_commas_and_shrink_to_fit():
    from hmepol_cli.plots import category_labels

    labels, size = category_labels(["Mepol", "HMepol (algo.adam_reset=null, epochs=200)"], 6.0)
    assert labels == ["Mepol", "HMepol\n(algo.adam_reset=null,\nepochs=200)"]
    assert size == 8.0  # 3 inches a tick: 48 characters of 8-point type, the widest line is 22
    _, size = category_labels(["x" * 20] * 6, 6.0)
    assert size == pytest.approx(8.0 * 16.0 / 20)  # one inch a tick: 16 characters of 20
    _, size = category_labels(["x" * 400] * 6, 6.0)
    assert size == 5.0


def test_group_labels_read_as_command_line_overrides():
    from hmepol_cli.report.runs import override_text

    assert [override_text(v) for v in (None, True, False, 0.4, "epoch")] == [
        "null", "true", "false", "0.4", "epoch",
    ]  # fmt: skip


def test_an_export_that_fails_midway_leaves_the_kept_files_whole(tmp_path, monkeypatch):
    """A save made while runs go on can be interrupted: a kept table is then its old copy, never
    a prefix of the new one, and no temporary file is left beside it."""
    import hmepol_cli.report.export as export
    import hmepol_cli.run.io as run_io
    from hmepol_cli.errors import StorageError

    run_dir = write_run(tmp_path / "runs", algo="mepol", seed=0, final=1.0)
    export.export_runs(tmp_path / "runs", tmp_path / "kept")
    kept = tmp_path / "kept" / run_dir.relative_to(tmp_path / "runs") / "epochs.csv"
    before = kept.read_bytes()
    (run_dir / "epochs.csv").write_bytes(before + before.splitlines(keepends=True)[-1] * 50)

    real_mkstemp, real_fdopen, opened = run_io.tempfile.mkstemp, run_io.os.fdopen, {}

    def mkstemp(**kwargs):
        fd, name = real_mkstemp(**kwargs)
        opened[fd] = Path(name).name
        return fd, name

    class DiskFullHalfway:  # writes half of what it is given, then the disk is full
        def __init__(self, f):
            self.f = f

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

        def write(self, data):
            self.f.write(data[: len(data) // 2])
            raise OSError(28, "No space left on device")

    def fdopen(fd, mode):
        f = real_fdopen(fd, mode)
        return DiskFullHalfway(f) if opened[fd].startswith(".epochs.csv.") else f

    monkeypatch.setattr(run_io.tempfile, "mkstemp", mkstemp)
    monkeypatch.setattr(run_io.os, "fdopen", fdopen)
    with pytest.raises(StorageError, match="epochs.csv"):
        export.export_runs(tmp_path / "runs", tmp_path / "kept")
    assert kept.read_bytes() == before
    assert not [p for p in kept.parent.iterdir() if p.name.startswith(".")]


@pytest.mark.slow  # heavy: make test runs it, make test-fast does not
def test_report_of_unfinished_runs_cuts_every_run_at_their_common_last_epoch(tmp_path, capsys):
    """`--unfinished` uses a run that stopped early, and compares every run over the epochs all
    of them wrote: the final value is the last 10% of those, computed here by hand."""
    root = tmp_path / "runs"
    for seed in (0, 1):
        write_run(root, algo="mepol", seed=seed, epochs=20, final=1.0 + 0.1 * seed)
    stopped = write_run(root, algo="mepol", seed=2, epochs=20, epochs_done=12, status="interrupted")
    (stopped / "eval" / "final.npz").unlink()  # an interrupted run has no final evaluation

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SkippedRunWarning)
        run_report(root, tmp_path / "finished-only")
    assert pd.read_csv(tmp_path / "finished-only" / "summary.csv").n_seeds.unique().tolist() == [2]

    main(["report", str(root), "--out", str(tmp_path / "report"), "--unfinished"])
    assert "unfinished runs included: slope, wind 0.4 cut at epoch 11" in capsys.readouterr().out
    rows = pd.read_csv(tmp_path / "report" / "summary.csv")
    south = rows[rows.config == "0: south"].iloc[0]
    assert south.n_seeds == 3 and south.final_epochs == "10-11"
    # seed s's configuration 0 ramps linearly to final_s over its epochs; keep epochs 10 and 11
    expected = np.mean(
        [
            (1.0 + 0.1 * s) * np.linspace(0.0, 1.0, 20)[10:12].mean()
            if s < 2
            else 1.0 * np.linspace(0.0, 1.0, 12)[10:12].mean()
            for s in range(3)
        ]
    )
    assert south.mean_nats == pytest.approx(expected, rel=1e-9)
    page = html.unescape((tmp_path / "report" / "index.html").read_text())
    assert "cut at epoch 11" in page


def test_a_figure_names_one_epoch_or_a_range():
    assert epochs_label("8") == "epoch 8"
    assert epochs_label("450-499") == "epochs 450-499"
    assert epochs_label("450-499, 8") == "epochs 450-499, 8"


def test_a_world_without_wind_is_one_setting_when_cut():
    """Runs of a world without wind (NaN however it was read) are cut together, at the last
    epoch all of them wrote, and named by the world alone."""

    def run(done: int, status: str) -> Run:
        table = pd.DataFrame({"epoch": range(done), "entropy": np.zeros(done)})
        meta = {"env": "multigrid", "status": status}  # each run its own NaN object
        return Run(Path(f"r{done}"), {"env.wind": float("nan")}, meta, epochs=table)

    runs = [run(10, "finished"), run(7, "interrupted"), run(9, "interrupted")]
    assert cut_at_common_epochs(runs) == {"multigrid": 6}
    assert [int(r.epochs.epoch.max()) for r in runs] == [6, 6, 6]


@pytest.mark.slow  # heavy: make test runs it, make test-fast does not
def test_report_of_unfinished_runs_cuts_each_wind_on_its_own(tmp_path, capsys):
    """`--unfinished` cuts only the settings that hold an unfinished run, each at the last epoch
    its own runs all wrote: a wind whose arms finished keeps its last 10% of 20 epochs (18-19),
    a wind with a run stopped at 12 epochs compares both arms over epochs 10-11, and a wind
    whose only run stopped at 16 is cut there, not at the other wind's 11 (one stopped at 2
    averages epoch 1 alone, "1" in Fig. 5.10's caption)."""
    root = tmp_path / "runs"
    for algo in ("mepol", "hmepol"):
        policy = "recursive" if algo == "hmepol" else "markov"
        write_run(root, algo=algo, policy=policy, wind=0.05)
        write_run(root, algo=algo, policy=policy, wind=0.15)
    for wind, done in ((0.15, 12), (0.25, 16), (0.35, 2)):
        stopped = write_run(
            root, wind=wind, seed=1, epochs=20, epochs_done=done, status="interrupted"
        )
        (stopped / "eval" / "final.npz").unlink()

    main(["report", str(root), "--out", str(tmp_path / "report"), "--unfinished"])
    out = capsys.readouterr().out
    assert "slope, wind 0.15 at epoch 11; slope, wind 0.25 at epoch 15; slope, wind 0.35 at" in out
    assert "wind 0.05 at" not in out
    rows = pd.read_csv(tmp_path / "report" / "summary.csv")
    south = rows[rows.config == "0: south"]
    windows = {(r.wind, r.group): r.final_epochs for r in south.itertuples()}
    assert windows == {
        (0.05, "Mepol"): "18-19",
        (0.05, "HMepol"): "18-19",
        (0.15, "Mepol"): "10-11",
        (0.15, "HMepol"): "10-11",
        (0.25, "Mepol"): "14-15",
        (0.35, "Mepol"): "1-1",  # the last 10% of 2 epochs
    }
    differences = pd.read_csv(tmp_path / "report" / "differences.csv")
    at_015 = differences[(differences.wind == 0.15) & (differences.config == "0: south")].iloc[0]
    assert (at_015.final_epochs_a, at_015.final_epochs_b) == ("10-11", "10-11")
    # Fig. 5.10 puts the winds on one axis: its caption names each wind's epochs.
    page = html.unescape((tmp_path / "report" / "index.html").read_text())
    assert "(wind 0.05: 18-19; wind 0.15: 10-11; wind 0.25: 14-15; wind 0.35: 1)" in page


def test_a_finished_run_kept_without_final_positions_counts_in_every_table_and_no_map(tmp_path):
    """A study may keep a run's epochs.csv without its eval/final.npz (the export's
    --no-positions): its entropies count, and the maps draw the median of the runs that have
    positions; a damaged eval/final.npz still makes the run unusable."""
    root = tmp_path / "runs"
    for seed in (0, 1, 2):
        write_run(root, algo="mepol", seed=seed, final=1.0 + 0.1 * seed)
    run_report(root, tmp_path / "with-positions")
    (root / "slope-mepol-wind0.4-seed2" / "eval" / "final.npz").unlink()
    runs, skipped = discover_runs(root)
    assert not skipped
    assert {r.seed: r.positions is None for r in runs} == {0: False, 1: False, 2: True}
    (group,) = group_runs(runs)
    assert group.representative().seed == 0  # the lower median of the two seeds with maps
    run_report(root, tmp_path / "report")
    pd.testing.assert_frame_equal(  # the same numbers as with every map
        pd.read_csv(tmp_path / "report" / "summary.csv"),
        pd.read_csv(tmp_path / "with-positions" / "summary.csv"),
    )
    assert pd.read_csv(tmp_path / "report" / "summary.csv").n_seeds.unique().tolist() == [3]
    assert (tmp_path / "report" / "figures" / "slope_heatmaps.png").is_file()
    (root / "slope-mepol-wind0.4-seed1" / "eval" / "final.npz").write_bytes(b"not a zip file")
    with pytest.warns(SkippedRunWarning, match="eval/final.npz is unreadable"):
        skipped = discover_runs(root)[1]
    assert [s.path.name for s in skipped] == ["slope-mepol-wind0.4-seed1"]
