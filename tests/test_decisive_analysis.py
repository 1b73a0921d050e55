"""The decisive experiment's analysis (docs/results/decisive/analysis.py) does what
PREREGISTRATION.md says, on run folders built by hand whose answers are known: the metric's
window, the paired t-interval and sign-flip p-value against hand-computed values, "final" only
with every pre-registered seed complete, a failed run's last 50 epochs, drops, and the
provenance check; and the kept runs themselves satisfy the provenance the issue asks for."""

from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

ROOT = Path(__file__).resolve().parent.parent
DECISIVE = ROOT / "docs" / "results" / "decisive"
spec = importlib.util.spec_from_file_location("decisive_analysis", DECISIVE / "analysis.py")
analysis = importlib.util.module_from_spec(spec)
sys.modules[spec.name] = analysis  # dataclasses look their module up
spec.loader.exec_module(analysis)

# Arms held constant have no spread: scipy warns on Welch's interval over them.
pytestmark = pytest.mark.filterwarnings("ignore:Precision loss occurred:RuntimeWarning")

REGISTERED = ("a" * 40, 1_000_000)  # (commit, its time): what every hand-built run is made at
T_975_7 = 2.364624251593  # Student t quantile 0.975, 7 degrees of freedom (printed tables)
T_975_3 = 3.182446305284  # ... 3 degrees of freedom
FAITHFUL = {"env": {"edge": "slide"},
            "algo": {"backtracking": "reference", "backtrack_restore": "parameters"},
            "precision": "float32", "device": "cpu", "threads": 1}  # fmt: skip


def make_run(
    folder: Path,
    seed: int,
    c0,
    c1,
    *,
    status: str = "running",
    epochs=None,
    config=None,
    start: float = REGISTERED[1] + 60,
    algo: str = "mepol",
) -> Path:
    """A run folder whose entropy_c0/c1 are the given per-epoch values (scalars: constant)."""
    n = epochs if epochs is not None else len(np.atleast_1d(c0))
    c0 = np.broadcast_to(np.asarray(c0, float), (n,)).copy()
    c1 = np.broadcast_to(np.asarray(c1, float), (n,)).copy()
    run = folder / f"{'' if algo == 'mepol' else algo + '_'}experiment-x_seed-{seed}"
    run.mkdir(parents=True)
    pd.DataFrame({"epoch": np.arange(n), "entropy": (c0 + c1) / 2, "entropy_c0": c0,
                  "entropy_c1": c1, "wall_time": start + np.arange(n)}).to_csv(
        run / "epochs.csv", index=False)  # fmt: skip
    info = {"seed": seed, "status": status, "algo": algo, "epochs": 500,
            "log_free_area": [4.81, 4.81], "config_names": ["clockwise", "counterclockwise"],
            "provenance": {"git_commit": REGISTERED[0]}}  # fmt: skip
    (run / "run.json").write_text(json.dumps(info))
    (run / "config.yaml").write_text(yaml.safe_dump(config if config is not None else FAITHFUL))
    return run


def two_arms(root: Path, base, diff, *, epochs=500, seeds=range(8)):
    """Arm A constant at base[s], arm B at base[s] + diff[s] (both configurations)."""
    for s in seeds:
        done = epochs[s] if isinstance(epochs, dict) else epochs
        status = "finished" if done >= 500 else "running"
        make_run(root / "mepol", s, base[s], base[s], epochs=done, status=status)
        make_run(root / "exact", s, base[s] + diff[s], base[s] + diff[s], epochs=done,
                 status=status)  # fmt: skip


def primary_row(text: str) -> list[str]:
    row = next(line for line in text.splitlines() if line.startswith("| M (both"))
    return [cell.strip() for cell in row.strip("|").split("|")]


def test_final_answer_matches_a_hand_computed_interval(tmp_path):
    base = [3.0 + 0.1 * s for s in range(8)]
    diff = [0.4, 0.6, 0.5, 0.5, 0.45, 0.55, 0.3, 0.7]
    two_arms(tmp_path, base, diff)
    text = analysis.report(tmp_path, REGISTERED)
    d = np.array(diff)
    half = T_975_7 * d.std(ddof=1) / math.sqrt(8)
    cells = primary_row(text)
    assert cells[3] == f"{d.mean():+.3f} [{d.mean() - half:+.3f}, {d.mean() + half:+.3f}]"
    assert float(cells[4]) == pytest.approx(2 / 256, rel=1e-3)  # all 8 signs positive: 2 of 2^8
    assert cells[5] == "ends above"
    assert "final, epochs 450-499, seeds [0, 1, 2, 3, 4, 5, 6, 7]" in text


def test_ends_below_and_not_resolved(tmp_path):
    two_arms(tmp_path / "below", [3.0] * 8, [-0.5, -0.6, -0.4, -0.5, -0.55, -0.45, -0.5, -0.5])
    assert primary_row(analysis.report(tmp_path / "below", REGISTERED))[5] == "ends below"
    spread = [0.9, -0.8, 0.7, -0.9, 0.8, -0.7, 0.1, -0.1]
    two_arms(tmp_path / "open", [3.0] * 8, spread)
    answer = primary_row(analysis.report(tmp_path / "open", REGISTERED))[5]
    sd = np.std(spread, ddof=1)
    need = next(n for n in range(2, 1000)
                if analysis.stats.t.ppf(0.975, n - 1) * sd / math.sqrt(n) <= 0.3)  # fmt: skip
    assert answer == f"not resolved at n = 8 (a +-0.3 half-width needs {need} seeds)"


def test_the_metric_is_the_mean_over_epochs_450_to_499_of_each_configuration(tmp_path):
    epochs = np.arange(500)
    for s in range(8):  # A: 1 before epoch 450, then 2 (c0) and 4 (c1): M = 3
        make_run(tmp_path / "mepol", s, np.where(epochs < 450, 1.0, 2.0),
                 np.where(epochs < 450, 1.0, 4.0), status="finished")  # fmt: skip
        make_run(tmp_path / "exact", s, np.where(epochs < 450, 9.0, 3.0 + 0.01 * s),
                 np.where(epochs < 450, 9.0, 3.0 + 0.01 * s), status="finished")  # fmt: skip
    cells = primary_row(analysis.report(tmp_path, REGISTERED))
    assert cells[1] == "3.000" and cells[2] == f"{3.0 + 0.01 * 3.5:.3f}"
    c0 = next(line for line in analysis.report(tmp_path, REGISTERED).splitlines()
              if line.startswith("| M_0"))  # fmt: skip
    assert c0.split("|")[2].strip() == "2.000"


def test_stage_one_done_is_interim_at_n_4_even_when_its_interval_excludes_zero(tmp_path):
    two_arms(tmp_path, [3.0] * 8, [0.5, 0.6, 0.4, 0.5, 0, 0, 0, 0],
             epochs={s: 500 if s < 4 else 60 for s in range(8)})  # fmt: skip
    text = analysis.report(tmp_path, REGISTERED)
    assert "interim (n = 4), epochs 450-499, seeds [0, 1, 2, 3]" in text
    cells = primary_row(text)
    d = np.array([0.5, 0.6, 0.4, 0.5])
    half = T_975_3 * d.std(ddof=1) / 2
    assert cells[3] == f"{d.mean():+.3f} [{d.mean() - half:+.3f}, {d.mean() + half:+.3f}]"
    assert cells[5] == "interim: not an answer"
    assert "| A: Mepol | 8 of 8 | 0: 500, 1: 500, 2: 500, 3: 500, 4: 60," in text


def test_before_any_seed_is_complete_the_window_is_the_last_50_common_epochs(tmp_path):
    epochs = np.arange(120)
    for s in range(4):
        make_run(tmp_path / "mepol", s, np.where(epochs >= 70, 2.0, 0.0), 2.0)
        make_run(tmp_path / "exact", s, 3.0 + 0.1 * s, 3.0 + 0.1 * s, epochs=120)
    text = analysis.report(tmp_path, REGISTERED)
    assert "interim (epochs 70-119 of 500), seeds [0, 1, 2, 3]" in text
    assert primary_row(text)[1] == "2.000"


def test_a_failed_run_keeps_its_place_with_its_last_50_epochs(tmp_path):
    two_arms(tmp_path, [3.0] * 8, [0.5] * 8, seeds=[s for s in range(8) if s != 2])
    make_run(tmp_path / "mepol", 2, 3.0, 3.0, epochs=500, status="finished")
    values = np.where(np.arange(300) >= 250, 1.0, 8.0)  # ended at epoch 299: M = 1 over 250-299
    make_run(tmp_path / "exact", 2, values, values, status="failed")
    text = analysis.report(tmp_path, REGISTERED)
    assert "final, epochs 450-499" in text
    d = np.array([0.5] * 7 + [-2.0])
    assert primary_row(text)[3].startswith(f"{d.mean():+.3f}")
    row = next(line for line in text.splitlines() if "without the pairs of seeds [2]" in line)
    assert "+0.500" in row


def test_drops_count_falls_of_more_than_one_nat_from_epoch_30(tmp_path):
    c0 = np.full(100, 3.0)
    c0[20:] = 1.0  # a fall of 2 nats at epoch 20: before epoch 30, not counted
    c0[40:] = -0.5  # 1.5 nats at epoch 40: counted
    c0[60:] = -1.4  # 0.9 nats at epoch 60: not a drop
    make_run(tmp_path / "mepol", 0, c0, 3.0)
    make_run(tmp_path / "mepol", 1, 3.0, 3.0, epochs=100)
    make_run(tmp_path / "mepol", 2, 3.0, 3.0, epochs=30)  # not past epoch 30: not counted
    text = analysis.report(tmp_path, REGISTERED)
    assert "| A: Mepol | 140 | 1 / 0 | 1 of 2 past epoch 30 |" in text


def test_provenance_names_every_departure(tmp_path):
    two_arms(tmp_path, [3.0] * 4, [0.1] * 4, epochs=60, seeds=range(4))
    assert "Provenance: all 8 runs were made with env.edge=slide" in analysis.report(
        tmp_path, REGISTERED)  # fmt: skip
    mirror = {**FAITHFUL, "env": {"edge": "mirror"}}
    make_run(tmp_path / "mepol", 4, 3.0, 3.0, epochs=60, config=mirror)
    make_run(tmp_path / "exact", 4, 3.0, 3.0, epochs=60, start=REGISTERED[1] - 5)
    text = analysis.report(tmp_path, REGISTERED)
    assert "departures from PREREGISTRATION.md section 2" in text
    assert "experiment-x_seed-4: env.edge=mirror, not slide" in text
    assert "before the pre-registration" in text


def test_the_kept_runs_postdate_the_preregistration_and_use_the_faithful_rules():
    """PREREGISTRATION.md's commit is older than every epochs.csv row, and every run
    used env.edge=slide and algo.backtracking=reference (needs the git history: CI's clone)."""
    registered = analysis.preregistration(DECISIVE)
    if registered is None:
        pytest.skip("no git history here")
    text = analysis.report(DECISIVE, registered)
    assert "Provenance: all" in text and "departures" not in text


def test_multigrid_finals_average_the_last_10_percent_of_the_epochs_that_drew_the_config(tmp_path):
    """Section 5: average = mean of `entropy` over epochs 90-99; configuration 0 = mean of
    entropy_c0 over the last 10% of the epochs that drew it: here drawn in epochs 0, 2, ..., 78
    and 95 (41 epochs), so the last 5 of them (72-78: 3 nats, 95: 1 nat), mean 2.6, not the
    1 nat of the drawn epochs among the last 10."""
    epochs = np.arange(100)
    drawn = ((epochs < 80) & (epochs % 2 == 0)) | (epochs == 95)
    c0 = np.where(epochs == 95, 1.0, np.where(epochs >= 72, 3.0, -5.0))
    for s in range(4):
        for algo, shift in (("alphamepol", 0.0), ("hmepol", 0.2 + 0.01 * s)):
            values = np.where(drawn, c0, np.nan) + shift
            run = make_run(tmp_path / "multigrid", s, values, 0.0, status="finished", algo=algo)
            table = pd.read_csv(run / "epochs.csv")
            table["entropy"] = np.where(epochs >= 90, 2.0, 7.0) + shift
            table["diverged"] = (epochs >= 60) & (algo == "hmepol") & (s == 1)
            table.to_csv(run / "epochs.csv", index=False)
    text = analysis.report(tmp_path, REGISTERED)
    average = next(line for line in text.splitlines() if line.startswith("| average"))
    config0 = next(line for line in text.splitlines() if line.startswith("| configuration 0"))
    d = np.array([0.20, 0.21, 0.22, 0.23])
    half = T_975_3 * d.std(ddof=1) / 2
    interval = f" {d.mean():+.3f} [{d.mean() - half:+.3f}, {d.mean() + half:+.3f}] "
    assert average.split("|")[1:6] == [" average ", " 2.000 ", " 2.215 ", interval, " above "]
    assert config0.split("|")[2:4] == [" 2.600 ", " 2.815 "]
    assert "| 1 | 2.000 / 2.210 | 2.600 / 2.810 | 40 (from epoch 60) |" in text


def test_while_stage_two_runs_the_figure_keeps_stage_one_s_mean_over_all_its_epochs():
    """A thick mean over every seed of an arm would be cut to the epochs stage 2 has; while
    stage 2 runs there is one mean per stage, each over its own seeds' common epochs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def curve(n, level):
        return pd.DataFrame({"epoch": np.arange(n), "m": level + np.arange(n) / 100})

    by_seed = {s: curve(10, s) for s in range(4)} | {s: curve(3, 10 * s) for s in (4, 5)}
    fig, ax = plt.subplots()
    notes = analysis.draw_arms(ax, {"a": by_seed}, "m", {"a": "arm"}, {"a": "C0"})
    thick = [line for line in ax.lines if line.get_linewidth() == 2]
    plt.close(fig)
    assert [len(line.get_ydata()) for line in thick] == [10, 3]
    np.testing.assert_allclose(thick[0].get_ydata(), 1.5 + np.arange(10) / 100)  # (0+1+2+3)/4
    np.testing.assert_allclose(thick[1].get_ydata(), 45 + np.arange(3) / 100)  # (40+50)/2
    assert [line.get_linestyle() for line in thick] == ["-", "--"]
    assert notes == ["arm 10/3"]
    assert analysis.mean_groups({s: curve(10, s) for s in range(8)}) == [list(range(8))]


def test_the_corridor_figure_is_final_for_the_primary_arms_while_arm_c_runs(tmp_path):
    """Arms A and B with seeds 0-7 at 500 epochs and arm C short: "A and B final, C INTERIM";
    one primary seed short: "INTERIM"; every arm complete: "final"."""

    def arm(folder, done):
        for seed, n in done.items():
            make_run(tmp_path / folder, seed, 4.0, 4.0, epochs=n,
                     status="finished" if n == 500 else "running")  # fmt: skip
        return analysis.runs(tmp_path / folder)

    full = {s: 500 for s in range(8)}
    found = {"A": arm("a", full), "B": arm("b", full), "C": arm("c", {0: 9, 1: 9})}
    assert analysis.corridor_state(found) == "A and B final, C INTERIM"
    found["A"] = arm("a7", full | {7: 499})
    assert analysis.corridor_state(found) == "INTERIM"
    found["A"], found["C"] = arm("a8", full), arm("c8", full)
    assert analysis.corridor_state(found) == "final"
