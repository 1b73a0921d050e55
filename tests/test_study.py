"""``hmepol study``: the statistics of a comparison against hand computations, AdaStop's
decisions on hand-built runs, the pre-registration's refusals, the kept decisive experiment read
by --status, and one tiny study end to end (interrupted, then continued)."""

from __future__ import annotations

import itertools
import json
import math
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from hypothesis import given, settings
from hypothesis.strategies import floats as st_floats
from hypothesis.strategies import integers as st_integers
from scipy import stats

from hmepol_cli.errors import UserError
from hmepol_cli.report.comparisons import paired, sign_flip_p, window_metric
from hmepol_cli.study import load_spec, preregister, status, status_lines, sweep_command
from tests.test_cli import TINY

ROOT = Path(__file__).resolve().parent.parent


def spec_file(folder: Path, n: int, stages: int, epochs: int = 5, **extra: object) -> Path:
    spec = {
        "folder": str(folder / "runs"), "launcher": "population", "seeds_per_stage": n,
        "stages": stages, "alpha": 0.05, "epochs": epochs, "permutations": 2000,
        "metric": {"columns": ["entropy_c0", "entropy_c1"], "epochs": [epochs - 2, epochs - 1]},
        "arms": {"a": {"preset": "demo"}, "b": {"preset": "demo", "overrides": ["algo=hmepol"]}},
        "comparisons": [["b", "a"]],
    }  # fmt: skip
    spec.update(extra)
    path = folder / "spec.yaml"
    path.write_text(yaml.safe_dump(spec))
    return path


def make_run(folder: Path, seed: int, level: float, done: int, epochs: int = 5) -> Path:
    """A run directory with ``done`` epochs whose entropies are ``level`` (+ 0.5 in c1)."""
    run = folder / f"seed-{seed}"
    run.mkdir(parents=True, exist_ok=True)
    status = "finished" if done >= epochs else "interrupted"
    (run / "run.json").write_text(json.dumps({"seed": seed, "status": status, "epochs": epochs}))
    pd.DataFrame({"epoch": range(done), "entropy_c0": [level] * done,
                  "entropy_c1": [level + 0.5] * done, "seconds": [2.0] * done}).to_csv(
        run / "epochs.csv", index=False)  # fmt: skip
    return run


def test_paired_difference_matches_a_hand_computation():
    # d = (1, 2, 3): mean 2, sd 1; t_{0.975, 2} = 4.3027; of the 8 sign flips only (+,+,+) and
    # (-,-,-) reach |mean| >= 2
    r = paired({0: 0.0, 1: 0.0, 2: 0.0}, {0: 1.0, 1: 2.0, 2: 3.0})
    half = 4.302652729911275 / math.sqrt(3)
    assert (r.n, r.mean) == (3, pytest.approx(2.0))
    assert (r.low, r.high) == (pytest.approx(2 - half), pytest.approx(2 + half))
    assert r.p == pytest.approx(2 / 8)
    need = next(k for k in range(2, 1000) if stats.t.ppf(0.975, k - 1) / math.sqrt(k) <= 0.3)
    assert r.seeds_needed == need
    assert r.answer() == f"not resolved at n = 3 (a ±0.3 half-width needs {need} seeds)"
    close = paired({0: 0.0, 1: 0.0, 2: 0.0}, {0: 1.0, 1: 1.1, 2: 0.9})  # [0.75, 1.25]
    assert close.answer("b", "a") == "b ends above a"


def test_sign_flip_p_counts_every_assignment():
    d = np.array([0.5, -0.2, 1.1, 0.3])
    flips = [np.mean(np.array(s) * np.abs(d)) for s in itertools.product((-1, 1), repeat=4)]
    expected = np.mean([abs(m) >= abs(d.mean()) - 1e-12 for m in flips])
    assert sign_flip_p(d) == pytest.approx(expected)


def test_a_failed_run_is_measured_over_its_own_last_epochs():
    table = pd.DataFrame({"epoch": range(6), "x": [0, 1, 2, 3, 4, 5.0]})
    assert window_metric(table, ["x"], 8, 9, failed=True) == pytest.approx(4.5)
    assert window_metric(table, ["x"], 2, 3) == pytest.approx(2.5)


def test_clearly_different_arms_are_decided_after_stage_one(tmp_path):
    spec = load_spec(spec_file(tmp_path, n=4, stages=3))
    rng = np.random.default_rng(0)
    for s in range(4):
        make_run(spec.arms["a"].folder, s, 1.0 + 0.01 * rng.standard_normal(), 5)
        make_run(spec.arms["b"].folder, s, 3.0 + 0.01 * rng.standard_normal(), 5)
    st = status(spec)
    assert st.complete_stages == 1 and len(st.decisions) == 1
    assert st.decisions[0].decisions == {("b", "a"): "larger"} and st.finished
    # the other way round, the other word
    spec = load_spec(spec_file(tmp_path, n=4, stages=3, comparisons=[["a", "b"]]))
    assert status(spec).decisions[0].decisions == {("a", "b"): "smaller"}


def test_identical_arms_are_equal_at_the_last_stage(tmp_path):
    spec = load_spec(spec_file(tmp_path, n=2, stages=2))
    for s in range(4):
        for arm in "ab":
            make_run(spec.arms[arm].folder, s, 1.0 + 0.3 * s, 5)
    st = status(spec)
    assert [d.decisions[("b", "a")] for d in st.decisions] == ["continue", "equal"]
    assert st.finished and st.complete_stages == 2
    assert any("not proof of equivalence" in line for line in status_lines(st))


def test_an_interrupted_stage_continues_with_its_unfinished_seeds(tmp_path):
    spec = load_spec(spec_file(tmp_path, n=2, stages=3))
    for s in range(2):
        for arm in "ab":
            make_run(spec.arms[arm].folder, s, 1.0 + 0.3 * s, 5)
    make_run(spec.arms["a"].folder, 2, 1.0, 5)
    make_run(spec.arms["a"].folder, 3, 1.0, 3)  # interrupted at 3 of 5 epochs
    st = status(spec)
    assert st.complete_stages == 1 and not st.finished
    assert st.runs["a"][3].done == 3 and not st.runs["a"][3].complete
    # stage 2 left: a's seed 3 (2 epochs) and b's seeds 2, 3 (5 each) at 2 s an epoch, a
    # population per arm: 2 x 2 s + 5 x 2 s
    assert st.stage_hours(2) == pytest.approx((2 * 2 + 5 * 2) / 3600)
    command = sweep_command(spec, spec.arms["a"], [2, 3])
    assert "seed=2,3" in command and f"hydra.sweep.dir={spec.arms['a'].folder}" in command
    # Before stage 2 is complete, --status shows each arm's M over its complete seeds: the mean
    # of c0 and c1 over the window, level + 0.25, with its t-interval over the seeds.
    lines = status_lines(st)
    for seeds, levels in (("0 1 2", [1.0, 1.3, 1.0]), ("0 1", [1.0, 1.3])):
        m = np.array(levels) + 0.25
        half = stats.t.ppf(0.975, m.size - 1) * m.std(ddof=1) / np.sqrt(m.size)
        assert (f"    M over its {m.size} complete seeds ({seeds}): {m.mean():.3f} "
                f"[{m.mean() - half:.3f}, {m.mean() + half:.3f}] (95% t), descriptive") in lines
    # Stage 1 is complete: b - a is the comparison's own line, not a descriptive one.
    assert not any("descriptive (the test" in line for line in lines)


def test_status_pairs_the_seeds_two_arms_have_complete_before_their_stage_is(tmp_path):
    """Stage 1 not complete (b's seed 3 still running): b - a over seeds 0-2, paired by hand,
    exact sign-flip p 2/8 (every difference positive), labelled descriptive."""
    spec = load_spec(spec_file(tmp_path, n=4, stages=2))
    for s, (a, b) in enumerate([(1.0, 1.5), (1.1, 1.4), (1.3, 1.9), (1.2, 1.2)]):
        make_run(spec.arms["a"].folder, s, a, 5)
        make_run(spec.arms["b"].folder, s, b, 5 if s < 3 else 2)
    st = status(spec)
    assert st.complete_stages == 0
    d = np.array([0.5, 0.3, 0.6])
    half = stats.t.ppf(0.975, 2) * d.std(ddof=1) / np.sqrt(3)
    line = (f"b - a over the 3 seeds both have complete: {d.mean():+.3f} "
            f"[{d.mean() - half:+.3f}, {d.mean() + half:+.3f}], sign-flip p 0.25 (n = 3), "
            "descriptive (the test is AdaStop's, at the stage's end)")  # fmt: skip
    assert line in status_lines(st)
    make_run(spec.arms["b"].folder, 1, 1.4, 2)  # seed 1 back to running: 2 seeds, 0 and 2
    assert any(x.startswith("b - a over the 2 seeds") for x in status_lines(status(spec)))
    make_run(spec.arms["b"].folder, 2, 1.9, 2)  # one seed left: no interval, no line
    assert not any(x.startswith("b - a") for x in status_lines(status(spec)))


@pytest.mark.slow  # end to end: runs of the installed command (make test runs it)
def test_each_arm_names_the_machines_its_seeds_trained_on(tmp_path):
    """Seeds 0-1 on an EPYC, seed 1 continued on a Xeon from epoch 3, seed 2 wholly on the
    Xeon, seed 3 from before run.json kept machines: one line under the arm, by machine."""
    spec = load_spec(spec_file(tmp_path, n=4, stages=1))
    epyc, xeon = "AMD EPYC 7B13", "Intel(R) Xeon(R) Processor (family 6, model 167)"
    trained = {0: [(0, epyc)], 1: [(0, epyc), (3, xeon)], 2: [(0, xeon)], 3: []}
    for seed, machines in trained.items():
        run = make_run(spec.arms["a"].folder, seed, 1.0, 5)
        info = json.loads((run / "run.json").read_text())
        info["machines"] = [{"from_epoch": e, "cpu": cpu, "device": "cpu"} for e, cpu in machines]
        (run / "run.json").write_text(json.dumps(info))
    make_run(spec.arms["b"].folder, 0, 1.0, 5)  # no record at all: no line
    lines = status_lines(status(spec))
    line = (f"    trained on {epyc}: seeds 0, 1; {xeon}: seeds 1 from epoch 3, 2; "
            "not recorded: seed 3")
    assert line in lines and sum(x.startswith("    trained on") for x in lines) == 1


def test_a_changed_spec_or_commit_is_refused(tmp_path):
    path = spec_file(tmp_path, n=2, stages=2)
    written = preregister(load_spec(path), "c0ffee")
    assert yaml.safe_load(written.read_text())["spec"] == path.read_text()
    preregister(load_spec(path), "c0ffee")  # the same: accepted
    with pytest.raises(UserError, match="commit"):
        preregister(load_spec(path), "beef")
    path.write_text(path.read_text().replace("alpha: 0.05", "alpha: 0.1"))
    with pytest.raises(UserError, match="changed since its pre-registration"):
        preregister(load_spec(path), "c0ffee")
    out = subprocess.run([sys.executable, "-m", "hmepol_cli", "study", str(path)],
                         cwd=tmp_path, capture_output=True, text=True, timeout=120)  # fmt: skip
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1 and "changed since" in out.stderr


@pytest.mark.slow  # end to end: runs of the installed command (make test runs it)
@pytest.mark.parametrize("bad, word", [
    ({"alpha": 2}, "alpha=2.0"), ({"seeds_per_stage": 1}, "seeds_per_stage=1"),
    ({"launcher": "cloud"}, "launcher='cloud'")])  # fmt: skip
def test_a_bad_spec_is_one_line(tmp_path, bad, word):
    path = spec_file(tmp_path, n=2, stages=2)
    path.write_text(yaml.safe_dump({**yaml.safe_load(path.read_text()), **bad}))
    out = subprocess.run([sys.executable, "-m", "hmepol_cli", "study", str(path), "--status"],
                         cwd=tmp_path, capture_output=True, text=True, timeout=120)  # fmt: skip
    assert out.returncode == 2 and word in out.stderr and "Traceback" not in out.stderr


@pytest.mark.slow  # end to end: runs of the installed command (make test runs it)
def test_the_decisive_experiment_reads_as_in_results():
    out = subprocess.run(
        [sys.executable, "-m", "hmepol_cli", "study", "conf/study/decisive_corridor.yaml",
         "--status"], cwd=ROOT, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert out.returncode == 0 and "Traceback" not in out.stderr, out.stderr
    assert "-0.149 [-0.606, +0.309], sign-flip p 0.45 (n = 8)" in out.stdout
    assert "needs 16 seeds" in out.stdout
    assert "post-hoc" in out.stdout and "stage 2 (8 seeds an arm)" in out.stdout


@pytest.mark.slow
def test_a_tiny_study_runs_is_interrupted_and_continues_to_its_decision(tmp_path):
    spec = {
        "folder": str(tmp_path / "study"), "launcher": "population", "seeds_per_stage": 2,
        "stages": 2, "alpha": 0.05, "epochs": 4, "metric": {"columns": ["entropy"]},
        "overrides": [*TINY, "algo.trajectories=20", "algo.horizon=60", "env=slope"],
        "arms": {"mepol": {"preset": "demo", "overrides": ["algo=mepol"]},
                 "fast": {"preset": "demo", "overrides": ["algo=mepol", "algo.lr=1e-2"]}},
    }  # fmt: skip
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(spec))
    command = [sys.executable, "-m", "hmepol_cli", "study", str(path)]
    proc = subprocess.Popen(command, cwd=tmp_path, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)  # fmt: skip
    deadline = time.time() + 240
    tables = lambda: list((tmp_path / "study").glob("*/*/epochs.csv"))  # noqa: E731
    while not any(len(t.read_text().splitlines()) >= 2 for t in tables()):
        assert proc.poll() is None and time.time() < deadline, proc.communicate()
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=240)
    assert proc.returncode == 143 and "Traceback" not in err, err
    # A population writes its members' rows one after the other: one or both may have a row.
    first = min(t for t in tables() if len(t.read_text().splitlines()) >= 2)
    kept = pd.read_csv(first)
    assert (tmp_path / "study" / "preregistration.yaml").exists()

    out = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0 and "Traceback" not in out.stderr, out.stderr
    again = pd.read_csv(first)
    assert len(again) == 4  # continued to the end, its first rows kept as written
    info = json.loads((first.parent / "run.json").read_text())
    assert info["interruption"]["signal"] == "SIGTERM"  # stopped, then resumed, not restarted
    timing = [c for c in kept.columns if c.endswith("seconds") or c == "wall_time"]
    pd.testing.assert_frame_equal(again.iloc[: len(kept)].drop(columns=timing),
                                  kept.drop(columns=timing))  # fmt: skip
    st = status(load_spec(path))
    assert st.complete_stages >= 1 and st.finished
    assert all(r.done == 4 for runs in st.runs.values() for r in runs.values())
    assert "AdaStop, stage" in out.stdout
    # the report of the study's folder: its curves, and its decisions stage by stage
    report = subprocess.run(
        [sys.executable, "-m", "hmepol_cli", "report", str(tmp_path / "study"), "--out",
         str(tmp_path / "report")], cwd=tmp_path, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert report.returncode == 0, report.stderr
    study_md = (tmp_path / "report" / "study.md").read_text()
    stages = [d.number for d in st.decisions]
    assert all(f"AdaStop, stage {k} " in study_md for k in stages)
    # each arm's M nested under the arm's own bullet
    nested = re.findall(r"^- \w+: 0: .*\n  - M over its \d+ complete seeds", study_md, re.M)
    assert len(nested) == 2
    assert "study.md" in json.loads((tmp_path / "report" / "report.json").read_text())["files"]


def test_kept_stages_are_labelled_and_the_registered_seeds_are_compared_alone(tmp_path):
    """A study that continues kept runs: its first stages are read post-hoc and say so, and the
    paired difference of the seeds it pre-registered is given on its own."""
    spec = load_spec(spec_file(tmp_path, n=2, stages=3, kept_stages=2))
    assert list(spec.registered_seeds) == [4, 5]
    for s in range(6):
        make_run(spec.arms["a"].folder, s, 1.0 + 0.3 * s, 5)
        make_run(spec.arms["b"].folder, s, 1.0 + 0.3 * s + (0.5 if s >= 4 else 0.0) + 0.1 * s, 5)
    st = status(spec)
    lines = status_lines(st)
    assert [line for line in lines if "read post-hoc" in line][0].startswith("AdaStop, stage 1")
    assert sum("(kept runs, read post-hoc)" in line for line in lines) == 2
    assert not any("stage 3 (kept" in line for line in lines)
    # seeds 4 and 5 alone: b - a = 0.5 + 0.1 s = 0.9 and 1.0, by hand
    alone = [line for line in lines if "pre-registered stages' seeds alone (4-5)" in line]
    assert len(alone) == 1 and alone[0].split(": ", 1)[1].startswith("+0.950 [")


def test_a_study_does_not_train_its_kept_stages(tmp_path):
    from hmepol_cli.study import run_study

    spec = load_spec(spec_file(tmp_path, n=2, stages=3, kept_stages=2))
    for s in range(3):  # stage 2 lacks seed 3
        for arm in "ab":
            make_run(spec.arms[arm].folder, s, 1.0, 5)
    with pytest.raises(UserError, match=r"stage 2 \(seeds 2-3\) is not complete"):
        run_study(spec)
    assert not (spec.folder / "preregistration.yaml").exists()


@pytest.mark.parametrize("extra, word", [
    ({"kept_stages": 3}, "kept_stages=3"), ({"kept_stages": -1}, "kept_stages=-1"),
    ({"kept_stages": 1, "posthoc": True}, "give one or the other"),
])  # fmt: skip
def test_kept_stages_out_of_range_or_with_posthoc_are_refused(tmp_path, extra, word):
    with pytest.raises(UserError, match=re.escape(word)):
        load_spec(spec_file(tmp_path, n=2, stages=3, **extra))


def test_a_post_hoc_reading_keeps_to_the_stages_its_runs_fill(tmp_path):
    """The decisive experiment's layout: seeds 0-3 read post hoc, then a continuation's seeds
    4-5 and its preregistration.yaml in the same folder. ran_stages: 1 reads seeds 0-1 alone
    (n = 2 a stage) and names no pre-registration; without it the continuation's seeds count."""
    levels = {"a": [1.0, 1.0, 1.0, 1.0, 1.0, 1.0], "b": [1.5, 1.7, 0.0, 0.0, 0.0, 0.0]}
    spec = load_spec(spec_file(tmp_path, n=2, stages=3, posthoc=True, ran_stages=1))
    for arm, values in levels.items():
        for seed, level in enumerate(values):
            make_run(spec.arms[arm].folder, seed, level, 5)
    (spec.folder / "preregistration.yaml").write_text("written: '2030-01-01T00:00:00+00:00'\n")
    st = status(spec)
    assert sorted(st.runs["b"]) == [0, 1] and st.complete_stages == 1
    assert st.differences[("b", "a")].mean == pytest.approx(0.6)  # (0.5 + 0.7) / 2
    assert not any("pre-registration" in line for line in status_lines(st))
    everything = status(load_spec(spec_file(tmp_path, n=2, stages=3, posthoc=True)))
    assert sorted(everything.runs["b"]) == list(range(6)) and everything.complete_stages == 3


@pytest.mark.parametrize("extra, word", [
    ({"ran_stages": 4, "posthoc": True}, "ran_stages=4"),
    ({"ran_stages": 1}, "it needs posthoc: true"),
])  # fmt: skip
def test_ran_stages_out_of_range_or_without_posthoc_are_refused(tmp_path, extra, word):
    with pytest.raises(UserError, match=re.escape(word)):
        load_spec(spec_file(tmp_path, n=2, stages=3, **extra))


def test_sweeps_split_the_stage_and_share_the_time(tmp_path):
    """Seeds per sweep and sweeps at a time: the stage's hours by hand."""
    from hmepol_cli.study import sweep_seeds

    spec = load_spec(spec_file(tmp_path, n=4, stages=2, seeds_per_sweep=3, parallel_sweeps=2))
    assert sweep_seeds(spec, 2) == [[4, 5, 6], [7]]
    for s in range(4):  # stage 1 done at 2 s an epoch
        for arm in "ab":
            make_run(spec.arms[arm].folder, s, 1.0, 5)
    make_run(spec.arms["a"].folder, 4, 1.0, 3)  # 2 epochs left; seeds 5, 6, 7 of a: 5 each
    st = status(spec)
    # sweeps (a population each: its slowest member): a [4,5,6] 5 x 2 s, a [7] 5 x 2, b [4,5,6]
    # 5 x 2, b [7] 5 x 2 = 10 s each; two at a time: max(10, 40 / 2) = 20 s
    assert st.stage_hours(2) == pytest.approx(20 / 3600)
    one = load_spec(spec_file(tmp_path, n=4, stages=2))  # one sweep per arm, one at a time
    assert status(one).stage_hours(2) == pytest.approx(20 / 3600)
    wide = load_spec(spec_file(tmp_path, n=4, stages=2, seeds_per_sweep=1, parallel_sweeps=8))
    assert status(wide).stage_hours(2) == pytest.approx(10 / 3600)  # the longest sweep


@pytest.mark.parametrize("extra, word", [
    ({"parallel_sweeps": 0}, "parallel_sweeps=0"),
    ({"parallel_sweeps": "2"}, "parallel_sweeps='2'"),
    ({"seeds_per_sweep": 3}, "seeds_per_sweep=3"), ({"seeds_per_sweep": 0}, "seeds_per_sweep=0"),
])  # fmt: skip
def test_bad_sweep_layouts_are_refused(tmp_path, extra, word):
    with pytest.raises(UserError, match=re.escape(word)):
        load_spec(spec_file(tmp_path, n=2, stages=2, **extra))


def test_an_amendment_changes_only_how_runs_are_executed(tmp_path):
    from hmepol_cli.study import amend

    path = spec_file(tmp_path, n=2, stages=2, overrides=["wind=0.4", "threads=2"])
    registered = path.read_text()
    with pytest.raises(UserError, match="no pre-registration to amend"):
        amend(load_spec(path), "c0ffee", "why")
    preregister(load_spec(path), "c0ffee")
    spec = load_spec(path)
    make_run(spec.arms["a"].folder, 0, 1.0, 3)
    with pytest.raises(UserError, match="nothing to amend"):
        amend(spec, "c0ffee", "why")
    with pytest.raises(UserError, match="needs its reason"):
        amend(spec, "beef", "  ")
    # the question may not change: alpha, an arm's overrides, a non-execution override
    raw = yaml.safe_load(registered)
    for key, value, named in [
        ("alpha", 0.1, "alpha"), ("overrides", ["wind=0.3", "threads=1"], "overrides"),
        ("arms", {**raw["arms"], "a": {"preset": "demo", "overrides": ["algo.lr=1"]}}, "arms"),
    ]:  # fmt: skip
        path.write_text(yaml.safe_dump({**raw, key: value}))
        with pytest.raises(UserError, match=f"also changes {named}"):
            amend(load_spec(path), "beef", "why")
    # how the runs execute may: threads, the sweep layout, the launcher, the commit
    path.write_text(yaml.safe_dump({**raw, "overrides": ["wind=0.4", "threads=1"],
                                    "seeds_per_sweep": 1, "parallel_sweeps": 2}))  # fmt: skip
    written = amend(load_spec(path), "beef", "two sweeps of one thread; numbers unchanged")
    content = yaml.safe_load(written.read_text())
    assert content["spec"] == registered and content["commit"] == "c0ffee"  # kept as written
    (amendment,) = content["amendments"]
    assert amendment["commit"] == "beef" and amendment["spec"] == path.read_text()
    assert amendment["epochs_done_before"] == {"a": {0: 3}, "b": {}}
    preregister(load_spec(path), "beef")  # the amendment is now in force
    with pytest.raises(UserError, match="at commit c0ffee, not beef"):
        preregister(load_spec(path), "c0ffee")
    path.write_text(registered)
    with pytest.raises(UserError, match="changed since its pre-registration"):
        preregister(load_spec(path), "beef")  # the old spec is no longer the one in force
    path.write_text(amendment["spec"])
    lines = status_lines(status(load_spec(path)))
    assert any("amended" in line and "at commit beef" in line and "numbers unchanged" in line
               for line in lines)  # fmt: skip


@pytest.mark.slow  # end to end: runs of the installed command (make test runs it)
def test_sweeps_side_by_side_give_the_runs_of_one_sweep_per_arm(tmp_path):
    """The same study run as one population per arm, one after the other, and as one seed per
    sweep, two sweeps at a time: every run's epochs.csv is the same but for its timings."""
    tables = {}
    for name, layout in [("one", {}), ("side", {"seeds_per_sweep": 1, "parallel_sweeps": 2})]:
        spec = {
            "folder": str(tmp_path / name), "launcher": "population", "seeds_per_stage": 2,
            "stages": 1, "alpha": 0.05, "epochs": 3, "metric": {"columns": ["entropy"]},
            "overrides": [*TINY, "algo.trajectories=20", "algo.horizon=60", "threads=1"],
            "arms": {"mepol": {"preset": "demo", "overrides": ["algo=mepol"]},
                     "fast": {"preset": "demo", "overrides": ["algo=mepol", "algo.lr=1e-2"]}},
            **layout,
        }  # fmt: skip
        path = tmp_path / f"{name}.yaml"
        path.write_text(yaml.safe_dump(spec))
        out = subprocess.run([sys.executable, "-m", "hmepol_cli", "study", str(path)],
                             cwd=tmp_path, capture_output=True, text=True, timeout=600)  # fmt: skip
        assert out.returncode == 0 and "Traceback" not in out.stderr, out.stderr
        found = sorted((tmp_path / name).glob("*/*/epochs.csv"))
        assert len(found) == 4
        tables[name] = {t.relative_to(tmp_path / name): pd.read_csv(t) for t in found}
    assert tables["one"].keys() == tables["side"].keys()
    for key, table in tables["one"].items():
        timing = [c for c in table.columns if c.endswith("seconds") or c == "wall_time"]
        assert len(table) == 3
        pd.testing.assert_frame_equal(table.drop(columns=timing),
                                      tables["side"][key].drop(columns=timing))  # fmt: skip


@pytest.mark.parametrize("path", sorted((ROOT / "conf" / "study").glob("*.yaml")),
                         ids=lambda p: p.stem)  # fmt: skip
def test_every_study_preset_composes_each_arm_as_its_sweep_will(path):
    """A pre-registered spec must not fail at its first run: each arm's job, with the spec's
    overrides and one seed of its first stage to train, composes and passes the command's
    check (keys and values)."""
    from hmepol_cli.checks import check_train

    spec = load_spec(path)
    seed = spec.kept_stages * spec.n
    for arm in spec.arms.values():
        command = sweep_command(spec, arm, [seed])
        overrides = [o for o in command[command.index("sweep") + 1 :]
                     if not o.startswith("hydra")]  # fmt: skip
        cfg = check_train(overrides)
        assert cfg.epochs == spec.epochs and cfg.seed == seed


def test_sweeps_run_at_most_parallel_sweeps_at_once_and_a_failure_stops_the_others(
    tmp_path, monkeypatch
):
    """The sweeps replaced by small scripts that log when they start and end: never more than
    parallel_sweeps at once, every sweep run once; a sweep that fails ends the others by
    SIGTERM and the study exits with its code, starting nothing more."""
    import hmepol_cli.study as study

    spec = load_spec(spec_file(tmp_path, n=4, stages=1, seeds_per_sweep=1, parallel_sweeps=2))
    log = tmp_path / "log.txt"
    fail = {"seeds": "", "others": 1.0}
    script = (
        "import signal, sys, time\n"
        "log, name, code = sys.argv[1], sys.argv[2], int(sys.argv[3])\n"
        "def stop(*_):\n"
        "    open(log, 'a').write(f'{time.monotonic()} stopped {name}\\n'); sys.exit(143)\n"
        "signal.signal(signal.SIGTERM, stop)\n"
        "open(log, 'a').write(f'{time.monotonic()} start {name}\\n')\n"
        "time.sleep(float(sys.argv[4]))\n"
        "open(log, 'a').write(f'{time.monotonic()} end {name}\\n'); sys.exit(code)\n"
    )

    def fake(spec, arm, seeds):  # noqa: ANN001, ANN202
        name = f"{arm.name}{seeds[0]}"
        code = 3 if name == fail["seeds"] else 0
        seconds = 0.3 if code else fail["others"]
        return [sys.executable, "-c", script, str(log), name, str(code), str(seconds)]

    monkeypatch.setattr(study, "sweep_command", fake)
    monkeypatch.setattr(study, "SWEEP_POLL_SECONDS", 0.05)
    todo = [(arm, seeds) for arm in spec.arms.values() for seeds in study.sweep_seeds(spec, 1)]
    study._run_sweeps(spec, 1, todo, [False])
    events = [line.split() for line in log.read_text().splitlines()]
    assert sorted(e[2] for e in events if e[1] == "start") == sorted(
        f"{a}{s}" for a in "ab" for s in range(4))  # fmt: skip
    level, most = 0, 0
    for _, what, _ in sorted(events, key=lambda e: float(e[0])):
        level += 1 if what == "start" else -1
        most = max(most, level)
    assert most == 2

    log.unlink()
    fail.update(seeds="a1", others=60.0)  # the second sweep fails while the first runs
    with pytest.raises(SystemExit) as stopped:
        study._run_sweeps(spec, 1, todo, [False])
    assert stopped.value.code == 3
    events = [line.split() for line in log.read_text().splitlines()]
    assert [e[1:] for e in events if e[1] != "start"] == [["end", "a1"], ["stopped", "a0"]]
    assert {e[2] for e in events if e[1] == "start"} == {"a0", "a1"}  # nothing more started


def test_an_arm_with_no_run_yet_is_timed_at_a_sibling_arms_pace(tmp_path):
    """A sibling: the same preset, overrides setting the same keys (another wind); an arm of
    another algorithm is not one, so the stage's hours stay unknown until it has a pace."""
    arms = {"a": {"preset": "demo", "overrides": ["wind=0.1"]},
            "a2": {"preset": "demo", "overrides": ["wind=0.2"]},
            "b": {"preset": "demo", "overrides": ["algo=hmepol"]}}  # fmt: skip
    spec = load_spec(spec_file(tmp_path, n=2, stages=2, arms=arms, comparisons=[["b", "a"]]))
    for s in range(2):
        make_run(spec.arms["a"].folder, s, 1.0, 5)  # a's stage 1 done, 2 s an epoch
    st = status(spec)
    seconds = st.epoch_seconds(1)
    assert seconds["a2"][0].tolist() == [2.0] * 5 and seconds["a2"][1] == ["a"]
    assert np.isnan(seconds["b"][0]).all() and seconds["b"][1] == []
    assert math.isnan(st.stage_hours(1))
    assert any("still needs unknown" in line for line in status_lines(st))
    make_run(spec.arms["b"].folder, 0, 1.0, 1)  # b's first epoch: its own pace, 2 s
    st = status(spec)
    # a population per arm, one at a time: a2 5 epochs x 2 s, b max(4, 5) x 2 s
    assert st.stage_hours(1) == pytest.approx(20 / 3600)
    line = next(line for line in status_lines(st) if "still needs" in line)
    assert line.endswith(
        "(epochs an arm's runs have not reached yet timed at a sibling's: a2 at a's)")


def timed(run: Path, seconds: list[float]) -> None:
    """Give a run's epochs.csv these ``seconds``, one an epoch."""
    table = pd.read_csv(run / "epochs.csv")
    table["seconds"] = seconds[: len(table)]
    table.to_csv(run / "epochs.csv", index=False)


def test_what_is_left_is_timed_epoch_by_epoch_at_the_epochs_a_run_has_left(tmp_path):
    """By hand: a sibling whose first 30 epochs cost 10 s and its last 30 cost 2 s times a
    fresh run at 30 x 10 + 30 x 2 = 360 s (a last-epochs pace would say 60 x 2 = 120 s), and a
    run at epoch 45 at its 15 epochs left x 2 s = 30 s; a pause of 1000 s in one epoch is not
    counted; the most recently launched sibling lends; past every run the last epochs' time."""
    arms = {"a": {"preset": "demo", "overrides": ["wind=0.1"]},
            "a2": {"preset": "demo", "overrides": ["wind=0.2"]},
            "a3": {"preset": "demo", "overrides": ["wind=0.3"]}}  # fmt: skip
    spec = load_spec(spec_file(tmp_path, n=2, stages=1, arms=arms, comparisons=[["a2", "a"]],
                               epochs=60))  # fmt: skip

    def runs(arm: str, seconds: list[float], launch: str | None = None) -> None:
        """The arm's stage (seeds 0 and 1, a population) at these epoch times."""
        for seed in (0, 1):
            run = make_run(spec.arms[arm].folder, seed, 1.0, len(seconds), epochs=60)
            timed(run, seconds)
            if launch:
                launched(run, launch)

    steps = [10.0] * 30 + [2.0] * 30
    steps[50] = 1000.0  # a suspended process
    runs("a", steps, "2026-01-02T00:00:00+00:00")
    st = status(spec)
    assert st.stage_hours(1) == pytest.approx(2 * 360 / 3600)  # a2 and a3, one at a time
    seconds = st.epoch_seconds(1)
    assert seconds["a2"][1] == ["a"] and seconds["a2"][0].sum() == pytest.approx(360)

    runs("a2", [3.0] * 45)
    st = status(spec)
    assert st.epoch_seconds(1)["a2"][0][:45].tolist() == [3.0] * 45  # its own where it has them
    # a2's 15 left at a's 2 s, scaled to a2's pace over the 45 epochs both have: 135 s to a's
    # 30 x 10 + 15 x 2 = 330 s; a3's 60 at a's, unscaled (it has no epoch of its own)
    pace = 135 / 330
    assert st.stage_hours(1) == pytest.approx((15 * 2 * pace + 360) / 3600)

    # a3's siblings: a, launched 2026-01-02, and a2, launched later, whose 45 epochs lend first
    runs("a2", [3.0] * 45, "2026-01-03T00:00:00+00:00")
    times, lent = status(spec).epoch_seconds(1)["a3"]
    assert lent == ["a2", "a"] and times.sum() == pytest.approx(45 * 3 + 15 * 2 * pace)

    # past every run: the last 5 epochs' time. a3 alone, at epoch 30 of 60: 30 left x 6 s
    shutil.rmtree(spec.arms["a"].folder)
    shutil.rmtree(spec.arms["a2"].folder)
    runs("a3", [4.0] * 15 + [6.0] * 15)
    # a and a2 now have no run: a3's epochs, 15 x 4 + 15 x 6 + 30 x 6 = 330 s each
    assert status(spec).stage_hours(1) == pytest.approx((30 * 6 + 2 * 330) / 3600)


def test_a_stage_is_timed_at_its_own_runs_before_the_arms_earlier_stages(tmp_path):
    """Stage 2's runs time its epochs before stage 1's (another machine or code, say), which
    time the epochs stage 2 has not reached: by hand, stage 1 at 10 s an epoch, seed 2 at 3 s
    for 5 epochs: seed 3 (fresh) needs 5 x 3 + 55 x 10 = 565 s, seed 2 55 x 10; a population:
    565 s an arm (a median over all three runs would give 600)."""
    spec = load_spec(spec_file(tmp_path, n=2, stages=2, epochs=60))
    for arm in "ab":
        for seed in (0, 1):
            timed(make_run(spec.arms[arm].folder, seed, 1.0, 60, epochs=60), [10.0] * 60)
        timed(make_run(spec.arms[arm].folder, 2, 1.0, 5, epochs=60), [3.0] * 5)
    st = status(spec)
    assert st.complete_stages == 1
    assert st.epoch_seconds(2)["a"][0].sum() == pytest.approx(565)
    assert st.stage_hours(2) == pytest.approx(2 * 565 / 3600)  # two arms, one at a time


def test_a_stage_on_a_faster_machine_is_timed_at_its_own_speed(tmp_path):
    """By hand: stage 1 at 10 s an epoch (another machine), stage 2's seeds at 4 s for their
    first 30 epochs: their 30 left at stage 1's times scaled by 4 / 10, 30 x 4 = 120 s (unscaled
    300); with 20 epochs of their own, too few to compare, stage 1's 10 s as they are."""
    spec = load_spec(spec_file(tmp_path, n=2, stages=2, epochs=60))
    for arm in "ab":
        for seed in (0, 1):
            timed(make_run(spec.arms[arm].folder, seed, 1.0, 60, epochs=60), [10.0] * 60)
        for seed in (2, 3):
            timed(make_run(spec.arms[arm].folder, seed, 1.0, 30, epochs=60), [4.0] * 30)
    times = status(spec).epoch_seconds(2)["a"][0]
    assert times[30:].sum() == pytest.approx(120) and times[:30].tolist() == [4.0] * 30
    assert status(spec).stage_hours(2) == pytest.approx(2 * 120 / 3600)
    for seed in (2, 3):
        timed(make_run(spec.arms["a"].folder, seed, 1.0, 20, epochs=60), [4.0] * 20)
    assert status(spec).epoch_seconds(2)["a"][0][20:].sum() == pytest.approx(400)


def launched(run: Path, *stamps: str) -> None:
    """A run's commands.log, one line per invocation, as a run writes it."""
    (run / "commands.log").write_text("".join(f"{t} host pid=1 hmepol train\n" for t in stamps))


def registered_at(spec_path: Path, stamp: str) -> None:
    spec = load_spec(spec_path)
    spec.folder.mkdir(parents=True, exist_ok=True)
    (spec.folder / "preregistration.yaml").write_text(yaml.safe_dump(
        {"written": stamp, "commit": "c0ffee", "spec": spec_path.read_text()}))  # fmt: skip


def test_status_checks_the_pre_registration_is_older_than_every_run(tmp_path):
    """Each run's first launch (commands.log's first line, before its first row) against the
    pre-registration's time, across time zones; a kept stage's runs are older by design."""
    from hmepol_cli.study import registration_order

    path = spec_file(tmp_path, n=2, stages=2, kept_stages=1)
    spec = load_spec(path)
    assert registration_order(status(spec)) is None  # not registered: nothing to check
    registered_at(path, "2026-12-04T14:28:41Z")
    assert registration_order(status(spec)).endswith(": no run yet")
    kept = make_run(spec.arms["a"].folder, 0, 1.0, 5)
    launched(kept, "2026-11-30T09:00:00+00:00")  # stage 1 is kept: made before, as it should
    runs = {(arm, s): make_run(spec.arms[arm].folder, s, 1.0, 3) for arm in "ab" for s in (2, 3)}
    launched(runs["a", 2], "2026-12-04T15:28:42+01:00", "2026-12-04T10:00:00+00:00")  # 14:28:42Z
    launched(runs["a", 3], "2026-12-04T14:30:00+00:00")
    launched(runs["b", 2], "2026-12-04T09:29:00-05:00")  # 14:29Z
    launched(runs["b", 3], "2026-12-04T16:00:00+00:00")
    line = registration_order(status(spec))
    assert line == (
        "pre-registration written 2026-12-04T14:28:41Z: older than the first launch "
        "of each of its 4 runs (the earliest 2026-12-04T15:28:42+01:00, a seed 2)"
    )
    assert f"  {line}" in status_lines(status(spec))
    launched(runs["b", 2], "2026-12-04T15:28:40+01:00")  # one second before the registration
    launched(runs["a", 3], "2026-12-04T14:30:00")  # no time zone: cannot be placed
    (runs["b", 3] / "commands.log").unlink()
    line = registration_order(status(spec))
    assert line == ("pre-registration written 2026-12-04T14:28:41Z is NOT older than: b seed 2 "
                    "(launched 2026-12-04T15:28:40+01:00); not checked (no commands.log, or no "
                    "time zone on its time): a seed 3, b seed 3")  # fmt: skip


def _four_arms(tmp_path: Path, **extra: object):
    """Arms a, b, c, d; comparisons b - a and d - c (two winds, say)."""
    arms = {name: {"preset": "demo", "overrides": [f"wind=0.{i + 1}"]}
            for i, name in enumerate("abcd")}  # fmt: skip
    return load_spec(spec_file(tmp_path, n=4, stages=3, arms=arms,
                               comparisons=[["b", "a"], ["d", "c"]], **extra))  # fmt: skip


@given(shift=st_floats(0.0, 3.0), other=st_floats(0.0, 3.0), noise=st_integers(0, 10_000))
@settings(max_examples=25, deadline=None)
def test_adastop_needs_no_more_seeds_of_the_arms_it_has_decided(shift, other, noise):
    """AdaStop's decisions are the same whether an arm whose comparisons are all decided has
    the later stages' values or not: the library tests only what is undecided."""
    from hmepol_cli.report.comparisons import adastop, undecided_arms

    rng = np.random.default_rng(noise)
    full = {"a": rng.normal(0, 1, 12), "b": rng.normal(shift, 1, 12),
            "c": rng.normal(0, 1, 12), "d": rng.normal(other, 1, 12)}  # fmt: skip
    pairs = [("b", "a"), ("d", "c")]
    everything = adastop(full, 4, 3, pairs, permutations=500)
    needed = dict.fromkeys(full, 4)  # stage 1 trains every arm
    for stage in everything[:-1]:
        for arm in undecided_arms(stage.decisions):
            needed[arm] = stage.seeds + 4
    trimmed = {arm: values[: needed[arm]] for arm, values in full.items()}
    assert adastop(trimmed, 4, 3, pairs, permutations=500) == everything


def test_a_later_stage_trains_only_the_arms_of_undecided_comparisons(tmp_path, monkeypatch):
    """b - a is clear after stage 1, d - c is not: stage 2 trains c and d alone, is complete
    without a and b, and its hours count only them; --until-stage stops after a stage."""
    from hmepol_cli import study
    from hmepol_cli.study import run_study, stage_arms

    spec = _four_arms(tmp_path)
    level = {"a": lambda s: 1.0 + 0.01 * s, "b": lambda s: 3.0 + 0.01 * s,
             "c": lambda s: 1.0 + 0.3 * (s % 4), "d": lambda s: 1.0 + 0.3 * ((s + 1) % 4)}
    trained = []

    def sweeps(spec, stage, todo, warned):  # noqa: ANN001, ANN202, ARG001
        for arm, seeds in todo:
            trained.append((stage, arm.name))
            for s in seeds:
                make_run(arm.folder, s, level[arm.name](s), 5)

    monkeypatch.setattr(study, "_run_sweeps", sweeps)
    monkeypatch.setattr(study, "code_commit", lambda: "c0ffee")
    st = run_study(spec, until=1)
    assert st.complete_stages == 1 and trained == [(1, a) for a in "abcd"]
    assert st.decisions[0].decisions == {("b", "a"): "larger", ("d", "c"): "continue"}
    assert stage_arms(spec, st.decisions) == ["c", "d"]
    line = next(line for line in status_lines(st) if "still needs" in line)
    assert "still needs 0.0 h on this machine for c, d, the arms of the comparisons" in line
    # stage 2's hours: c's and d's 4 seeds, 5 epochs at 2 s, one population each, one at a time
    assert st.stage_hours(2) == pytest.approx(2 * 5 * 2 / 3600)

    trained.clear()
    st = run_study(spec, until=2)
    assert trained == [(2, "c"), (2, "d")]
    assert st.complete_stages == 2 and set(st.values["a"]) == {0, 1, 2, 3}
    assert set(st.values["c"]) == set(range(8))
    assert not (spec.arms["a"].folder / "seed-4").exists()


def test_until_stage_out_of_range_is_one_line(tmp_path, capsys):
    from hmepol_cli.study import main

    path = spec_file(tmp_path, n=2, stages=2)
    with pytest.raises(UserError, match=r"--until-stage 3: the study .* has stages 1 to 2"):
        main([str(path), "--until-stage", "3"])
