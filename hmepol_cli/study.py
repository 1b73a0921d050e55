"""``hmepol study SPEC``: a pre-registered, sequential comparison of arms (AdaStop) run stage by
stage through the project's sweeps, resumable, stopping at a decision.

A spec (YAML; presets in conf/study/, docs/studies.md) names the arms (a preset and overrides
each), the seeds per stage n, the most stages K, alpha, the metric (a window of epochs and the
columns it averages), the comparisons and the Hydra launcher. Before the first run the study
writes ``preregistration.yaml`` (the spec as given and the code's commit) into its folder and
refuses to run once either has changed. Each stage runs its missing seeds with ``hmepol sweep``
(finished runs skipped, interrupted ones resumed from their checkpoints); when a stage is whole,
AdaStop decides, and the study stops or starts the next one. ``--status`` trains nothing.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
import warnings
from collections.abc import Iterable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from hmepol_cli.errors import UserError
from hmepol_cli.report.comparisons import (
    Paired,
    Stage,
    adastop,
    decision_text,
    paired,
    undecided_arms,
    window_metric,
)
from hmepol_cli.report.stats import mean_ci
from hmepol_cli.run.io import atomic_write_text
from hmepol_cli.run.layout import COMMANDS

PREREGISTRATION = "preregistration.yaml"
LAUNCHERS = ("local", "population", "population_local", "slurm", "population_slurm", "basic")
WARN_HOURS = 3.0  # a stage estimated to need more than this on this machine is announced
POLL_SECONDS = 30.0  # between progress lines
SWEEP_POLL_SECONDS = 1.0  # between looks at the running sweeps
KEYS = {"name", "folder", "posthoc", "ran_stages", "kept_stages", "launcher", "seeds_per_stage",
        "stages", "alpha", "beta",
        "permutations", "adastop_seed", "epochs", "metric", "half_width", "overrides", "arms",
        "comparisons", "parallel_sweeps", "seeds_per_sweep"}  # fmt: skip
# How runs are executed, not what they compute: the keys an amendment may change (and the
# overrides that name the threads a run uses). Everything else is the study's question.
EXECUTION_KEYS = ("launcher", "parallel_sweeps", "seeds_per_sweep")
EXECUTION_OVERRIDES = ("threads",)


@dataclass(frozen=True)
class Arm:
    name: str
    preset: str
    overrides: tuple[str, ...]
    folder: Path


@dataclass(frozen=True)
class Spec:
    path: Path
    text: str
    name: str
    folder: Path
    arms: dict[str, Arm]
    n: int
    stages: int
    alpha: float
    beta: float
    permutations: int
    adastop_seed: int
    epochs: int
    columns: tuple[str, ...]
    window: tuple[int, int]
    comparisons: tuple[tuple[str, str], ...]
    launcher: str
    half_width: float = 0.3
    overrides: tuple[str, ...] = ()
    posthoc: bool = False
    kept_stages: int = 0  # stages 1..kept_stages: runs made before the pre-registration
    ran_stages: int = 0  # posthoc: the stages its runs fill; 0: every seed in its folder
    parallel_sweeps: int = 1  # sweeps of a stage that run at the same time
    seeds_per_sweep: int = 0  # seeds one sweep trains (a population's members); 0: the stage's

    @property
    def sweep_size(self) -> int:
        return self.seeds_per_sweep or self.n

    @property
    def registered_seeds(self) -> range:
        """The seeds of the stages this study pre-registered (after its kept stages)."""
        return range(self.kept_stages * self.n, self.stages * self.n)


def _need(spec: dict, key: str, kind: type, where: str):  # noqa: ANN202
    if key not in spec:
        raise UserError(f"{where}: the spec has no {key!r}; docs/studies.md lists what it needs")
    value = spec[key]
    if kind is int and (isinstance(value, bool) or not isinstance(value, int)):
        raise UserError(f"{where}: {key}={value!r} must be a whole number")
    if kind is float and (isinstance(value, bool) or not isinstance(value, int | float)):
        raise UserError(f"{where}: {key}={value!r} must be a number")
    return value


def load_spec(path: str | Path, text: str | None = None, folder: Path | None = None) -> Spec:
    """The spec at ``path`` (or its ``text``; ``folder`` in place of the one it names);
    UserError naming the bad value and what is allowed."""
    path = Path(path)
    where = str(path)
    if text is None:
        try:
            text = path.read_text()
        except OSError:
            raise UserError(f"study spec {where!r} does not exist or cannot be read") from None
    try:
        raw = yaml.safe_load(text)
    except yaml.YAMLError as error:
        line = getattr(getattr(error, "problem_mark", None), "line", None)
        at = f" (line {line + 1})" if line is not None else ""
        raise UserError(f"{where}: not valid YAML{at}") from None
    if not isinstance(raw, dict):
        raise UserError(f"{where}: a study spec is a YAML mapping (docs/studies.md)")
    unknown = sorted(set(raw) - KEYS)
    if unknown:
        raise UserError(f"{where}: unknown key(s) {', '.join(unknown)}; allowed: "
                        f"{', '.join(sorted(KEYS))}")  # fmt: skip
    n = _need(raw, "seeds_per_stage", int, where)
    stages = _need(raw, "stages", int, where)
    alpha = float(_need(raw, "alpha", float, where))
    epochs = _need(raw, "epochs", int, where)
    if n < 2:
        raise UserError(f"{where}: seeds_per_stage={n} must be at least 2")
    if stages < 1:
        raise UserError(f"{where}: stages={stages} must be at least 1")
    if not 0 < alpha < 1:
        raise UserError(f"{where}: alpha={alpha} must lie in (0, 1)")
    if epochs < 1:
        raise UserError(f"{where}: epochs={epochs} must be at least 1")
    kept = raw.get("kept_stages", 0)
    if isinstance(kept, bool) or not isinstance(kept, int) or not 0 <= kept < stages:
        raise UserError(f"{where}: kept_stages={kept!r} must be a whole number from 0 to "
                        f"stages - 1 = {stages - 1}")  # fmt: skip
    if kept and raw.get("posthoc", False):
        raise UserError(f"{where}: kept_stages continues kept runs with pre-registered stages; "
                        "posthoc: true only reads runs: give one or the other")  # fmt: skip
    ran = raw.get("ran_stages", 0)
    if isinstance(ran, bool) or not isinstance(ran, int) or not 0 <= ran <= stages:
        raise UserError(f"{where}: ran_stages={ran!r} must be a whole number from 0 to "
                        f"stages = {stages}")  # fmt: skip
    if ran and not raw.get("posthoc", False):
        raise UserError(f"{where}: ran_stages says which stages a post-hoc reading's runs fill; "
                        "it needs posthoc: true")  # fmt: skip
    launcher = str(raw.get("launcher", "local"))
    if launcher not in LAUNCHERS:
        raise UserError(f"{where}: launcher={launcher!r}; choose {', '.join(LAUNCHERS)}")
    parallel = raw.get("parallel_sweeps", 1)
    if isinstance(parallel, bool) or not isinstance(parallel, int) or parallel < 1:
        raise UserError(f"{where}: parallel_sweeps={parallel!r} must be a whole number >= 1 (the "
                        "sweeps that run at the same time; each uses the threads its overrides "
                        "give)")  # fmt: skip
    per_sweep = raw.get("seeds_per_sweep", n)
    if isinstance(per_sweep, bool) or not isinstance(per_sweep, int) or not 1 <= per_sweep <= n:
        raise UserError(f"{where}: seeds_per_sweep={per_sweep!r} must be a whole number from 1 "
                        f"to seeds_per_stage = {n}")  # fmt: skip
    folder = folder or Path(str(_need(raw, "folder", str, where)))
    arms_raw = _need(raw, "arms", dict, where)
    if not isinstance(arms_raw, dict) or len(arms_raw) < 2:
        raise UserError(f"{where}: arms must map at least two names to a preset each")
    arms = {}
    for name, arm in arms_raw.items():
        if not isinstance(arm, dict) or "preset" not in arm:
            raise UserError(f"{where}: arm {name!r} needs a preset (experiment=...)")
        overrides = arm.get("overrides", []) or []
        if not isinstance(overrides, list):
            raise UserError(f"{where}: arm {name!r}: overrides must be a list of key=value")
        arms[str(name)] = Arm(str(name), str(arm["preset"]), tuple(map(str, overrides)),
                              folder / str(arm.get("folder", name)))  # fmt: skip
    metric = raw.get("metric") or {}
    columns = metric.get("columns", ["entropy"])
    window = metric.get("epochs", [math.floor(0.9 * epochs), epochs - 1])
    if not (isinstance(window, list) and len(window) == 2 and 0 <= window[0] <= window[1] < epochs):
        raise UserError(f"{where}: metric.epochs={window!r} must be [first, last] with "
                        f"0 <= first <= last < epochs={epochs}")  # fmt: skip
    comparisons = raw.get("comparisons") or [
        [b, a] for a, b in zip(arms, list(arms)[1:], strict=False)
    ]
    pairs = []
    for c in comparisons:
        if not (isinstance(c, list) and len(c) == 2 and all(x in arms for x in c) and c[0] != c[1]):
            raise UserError(f"{where}: comparison {c!r} must be [arm, arm] of two different "
                            f"arms among {', '.join(arms)}")  # fmt: skip
        pairs.append((str(c[0]), str(c[1])))
    overrides = raw.get("overrides", []) or []
    return Spec(
        path=path, text=text, name=str(raw.get("name", path.stem)), folder=folder, arms=arms,
        n=n, stages=stages, alpha=alpha, beta=float(raw.get("beta", 0.0)),
        permutations=int(raw.get("permutations", 10_000)),
        adastop_seed=int(raw.get("adastop_seed", 0)), epochs=epochs,
        columns=tuple(map(str, columns)), window=(int(window[0]), int(window[1])),
        comparisons=tuple(pairs), launcher=launcher,
        half_width=float(raw.get("half_width", 0.3)), overrides=tuple(map(str, overrides)),
        posthoc=bool(raw.get("posthoc", False)), kept_stages=kept, parallel_sweeps=parallel,
        seeds_per_sweep=per_sweep, ran_stages=ran,
    )  # fmt: skip


def _question(spec: Spec) -> dict:
    """What a study asks and measures: its spec less the keys that only say how its runs are
    executed (EXECUTION_KEYS, the threads override) and less its comments."""
    raw = dict(yaml.safe_load(spec.text) or {})
    for key in EXECUTION_KEYS:
        raw.pop(key, None)
    raw["overrides"] = [o for o in raw.get("overrides", []) or []
                        if str(o).partition("=")[0] not in EXECUTION_OVERRIDES]  # fmt: skip
    return raw


# ------------------------------------------------------------------------------- the runs
@dataclass
class RunState:
    """One run directory as the study sees it."""

    path: Path
    seed: int
    done: int
    epochs: int
    status: str
    pace: float  # seconds an epoch, over its last epochs (NaN before its first)
    table: pd.DataFrame = field(repr=False)
    machines: list[dict] = field(default_factory=list)  # run.json's: where its epochs were made

    @property
    def complete(self) -> bool:
        return self.done >= self.epochs or self.status == "failed"


def arm_runs(arm: Arm, epochs: int) -> dict[int, RunState]:
    """{seed: run} of the run directories directly under the arm's folder."""
    out = {}
    for info_file in sorted(arm.folder.glob("*/run.json")):
        try:
            info = json.loads(info_file.read_text())
        except (OSError, ValueError):
            continue
        table_file = info_file.parent / "epochs.csv"
        try:
            table = pd.read_csv(table_file) if table_file.exists() else pd.DataFrame()
        except (OSError, pd.errors.EmptyDataError):
            table = pd.DataFrame()
        pace = math.nan
        if "seconds" in table and len(table):
            pace = float(table["seconds"].tail(5).median())
        out[int(info.get("seed", 0))] = RunState(
            info_file.parent, int(info.get("seed", 0)), len(table), epochs,
            str(info.get("status", "unknown")), pace, table, list(info.get("machines") or []),
        )  # fmt: skip
    return out


def machines_line(runs: dict[int, RunState]) -> str | None:
    """Which machines trained an arm's seeds, from each run.json's ``machines``: ``AMD EPYC
    7B13: seeds 0, 1; Intel(R) Xeon(R) Processor (family 6, model 167): seed 1 from epoch 200,
    seed 2; not recorded: seed 3`` (None when no run records one)."""
    by_machine: dict[str, list[str]] = {}
    unrecorded = []
    for seed, run in sorted(runs.items()):
        if not run.machines:
            unrecorded.append(str(seed))
        for machine in run.machines:
            name = machine.get("gpu") or machine.get("cpu") or "an unnamed CPU"
            start = int(machine.get("from_epoch", 0))
            since = f" from epoch {start}" if start else ""
            by_machine.setdefault(name, []).append(f"{seed}{since}")
    if not by_machine:
        return None
    if unrecorded:
        by_machine["not recorded"] = unrecorded
    return "; ".join(
        f"{name}: {'seed' if len(seeds) == 1 else 'seeds'} {', '.join(seeds)}"
        for name, seeds in by_machine.items()
    )


SMOOTH_EPOCHS = 25  # the running median of an arm's epoch times
_NEVER = datetime.min.replace(tzinfo=timezone.utc)  # an arm with no launch on record


def first_launch(run: Path) -> datetime | None:
    """When a run directory was first launched: the time on its commands.log's first line,
    written before the run's first row (None without a log, or without a time zone)."""
    try:
        stamp = (run / COMMANDS).read_text().split("\n", 1)[0].split(" ", 1)[0]
        when = datetime.fromisoformat(stamp)
    except (OSError, ValueError):
        return None
    return when if when.tzinfo is not None else None


def stage_seeds(spec: Spec, stage: int) -> list[int]:
    """The seeds of stage ``stage`` (1-based): n per stage, consecutive from 0."""
    return list(range((stage - 1) * spec.n, stage * spec.n))


def sweep_seeds(spec: Spec, stage: int) -> list[list[int]]:
    """The stage's seeds as the sweeps that train them, ``seeds_per_sweep`` each."""
    seeds = stage_seeds(spec, stage)
    return [seeds[i : i + spec.sweep_size] for i in range(0, len(seeds), spec.sweep_size)]


@dataclass
class Status:
    spec: Spec
    runs: dict[str, dict[int, RunState]]
    complete_stages: int
    values: dict[str, dict[int, float]]  # per arm, per seed of the complete stages
    decisions: list[Stage]
    differences: dict[tuple[str, str], Paired]
    # per arm, per complete run, complete stage or not (descriptive before its stage is)
    metrics: dict[str, dict[int, float]] = field(default_factory=dict)

    @property
    def finished(self) -> bool:
        if self.decisions and self.decisions[-1].finished:
            return True
        return self.complete_stages >= self.spec.stages

    def epoch_seconds(self, stage: int) -> dict[str, tuple[np.ndarray, list[str]]]:
        """Each arm's seconds at each of its epochs, for timing what stage ``stage`` has left,
        and the arms lent from. An epoch takes the median of the newest runs that reached it:
        the arm's runs of this stage, else its runs of other stages, else a sibling's (an arm
        of the same preset whose overrides set the same keys: another wind, say), the most
        recently launched sibling first; the newest are the likeliest to have run on this
        machine, code and layout. Past every run: the median of the last 5 epochs known. Each
        source is a running median over 25 epochs, so that a pause (a suspended process, a
        busy machine) does not count as the cost of the epoch it hit. A later source that
        shares at least 25 epochs with the times already known is scaled to them (by the ratio
        of their sums over those epochs): a stage continued on a faster machine than its
        earlier stages ran on is timed at its own speed. All NaN while neither the arm nor a
        sibling has a run with an epoch.

        Per epoch, not one pace: an arm's epochs need not cost the same (HMepol's exact trust
        region takes more off-policy iterations early on), which an average of a run's recent
        epochs misses: timing a fresh run at a finished sibling's last epochs, say."""
        epochs, seeds = self.spec.epochs, set(stage_seeds(self.spec, stage))
        launched = {name: max((first_launch(r.path) or _NEVER for r in runs.values()),
                              default=_NEVER) for name, runs in self.runs.items()}  # fmt: skip
        out = {}
        for name, arm in self.spec.arms.items():
            runs = self.runs[name]
            siblings = sorted(
                (other for other, o in self.spec.arms.items()
                 if other != name and o.preset == arm.preset
                 and _keys(o.overrides) == _keys(arm.overrides)),
                key=lambda other: launched[other], reverse=True,
            )  # fmt: skip
            sources = [(name, [r for s, r in runs.items() if s in seeds]),
                       (name, [r for s, r in runs.items() if s not in seeds])]  # fmt: skip
            sources += [(other, list(self.runs[other].values())) for other in siblings]
            times, lent = np.full(epochs, np.nan), []
            for source, group in sources:
                known = _median_seconds(group, epochs)
                fill = np.isnan(times) & np.isfinite(known)
                if fill.any():
                    both = np.isfinite(times) & np.isfinite(known)
                    if both.sum() >= SMOOTH_EPOCHS:  # at the pace of the epochs already known
                        known = known * (times[both].sum() / known[both].sum())
                    times[fill] = known[fill]
                    lent += [source] if source != name else []
            known = np.flatnonzero(np.isfinite(times))
            if len(known):
                times[known[-1] + 1 :] = np.median(times[known[-5:]])
            out[name] = (times, lent)
        return out

    def stage_hours(self, stage: int, launcher: str | None = None) -> float:
        """Hours the unfinished epochs of the stage's arms (:func:`stage_arms`) need on this
        machine, each run's from where it stands at its arm's :meth:`epoch_seconds` (a
        population trains its members together: the slowest member; otherwise one after the
        other), its sweeps ``parallel_sweeps`` at a time (the longer of the longest sweep and
        their sum shared out); NaN while an arm with epochs left has no time of its own or a
        sibling's."""
        population = (launcher or self.spec.launcher).startswith("population")
        seconds = self.epoch_seconds(stage)
        sweeps = []
        for name in stage_arms(self.spec, self.decisions[: stage - 1]):
            runs, times = self.runs[name], seconds[name][0]
            for seeds in sweep_seeds(self.spec, stage):
                left = [times[runs[s].done if s in runs else 0 :].sum() for s in seeds]
                if not any(left):
                    continue
                if np.isnan(left).any():
                    return math.nan
                sweeps.append(max(left) if population else sum(left))
        if not sweeps:
            return 0.0
        return float(max(max(sweeps), sum(sweeps) / self.spec.parallel_sweeps) / 3600)

    def borrowed_times(self, stage: int) -> str:
        """Which arms' hours for ``stage`` are partly at a sibling's epochs: '' when none."""
        arms = stage_arms(self.spec, self.decisions[: stage - 1])
        borrowed = [f"{name} at {' and '.join(lent)}'s" for name, (times, lent)
                    in self.epoch_seconds(stage).items() if lent and name in arms]  # fmt: skip
        if not borrowed:
            return ""
        return (" (epochs an arm's runs have not reached yet timed at a sibling's: "
                f"{', '.join(borrowed)})")


def _median_seconds(runs: Iterable[RunState], epochs: int) -> np.ndarray:
    """The median ``seconds`` of ``runs`` at each epoch 0..epochs-1, then a running median over
    :data:`SMOOTH_EPOCHS` epochs; NaN where no run reached."""
    columns = [r.table["seconds"].to_numpy(float)[:epochs] for r in runs if "seconds" in r.table]
    table = np.full((max(len(columns), 1), epochs), np.nan)
    for row, column in zip(table, columns, strict=False):  # no run: one row of NaN
        row[: len(column)] = column
    with warnings.catch_warnings():  # all-NaN at an epoch no run reached: NaN is the answer
        warnings.simplefilter("ignore", RuntimeWarning)
        median = np.nanmedian(table, axis=0)
    smooth = pd.Series(median).rolling(SMOOTH_EPOCHS, center=True, min_periods=1).median()
    return np.where(np.isnan(median), np.nan, smooth.to_numpy())


def _keys(overrides: tuple[str, ...]) -> tuple[str, ...]:
    """The keys an arm's overrides set, in order: ``wind=0.05`` -> ``wind``."""
    return tuple(o.split("=", 1)[0] for o in overrides)


def status(spec: Spec) -> Status:
    """Where a study stands, from its run directories (reads only). A stage is complete when
    the arms it trains have every seed of it: all arms at stage 1, later the arms of the
    comparisons AdaStop left undecided (:func:`stage_arms`)."""
    runs = {name: arm_runs(arm, spec.epochs) for name, arm in spec.arms.items()}
    if spec.ran_stages:  # a continuation's later seeds in the same folder are its own study's
        runs = {name: {s: r for s, r in arm.items() if s < spec.ran_stages * spec.n}
                for name, arm in runs.items()}  # fmt: skip
    metrics = {name: arm_metric(spec, arm) for name, arm in runs.items()}
    values: dict[str, dict[int, float]] = {a: {} for a in runs}
    decisions: list[Stage] = []
    complete = 0
    for stage in range(1, spec.stages + 1):
        arms = stage_arms(spec, decisions)
        seeds = stage_seeds(spec, stage)
        if not arms or not all(s in runs[a] and runs[a][s].complete for a in arms for s in seeds):
            break
        complete = stage
        for a in arms:
            for s in seeds:
                values[a][s] = metrics[a][s]
        decisions = adastop(
            {a: [values[a][s] for s in sorted(values[a])] for a in runs}, spec.n, spec.stages,
            spec.comparisons, spec.alpha, spec.beta, spec.permutations, spec.adastop_seed,
        )  # fmt: skip
        if decisions[-1].finished:
            break
    differences = {(b, a): paired(values[a], values[b], spec.half_width)
                   for b, a in spec.comparisons}  # fmt: skip
    return Status(spec, runs, complete, values, decisions, differences, metrics)


def arm_metric(spec: Spec, runs: dict[int, RunState]) -> dict[int, float]:
    """The study's metric M of each of an arm's complete runs, {seed: M}: what AdaStop will
    read of them, shown before their stage is complete (descriptive: no test reads it)."""
    first, last = spec.window
    return {s: window_metric(r.table, spec.columns, first, last, r.status == "failed")
            for s, r in sorted(runs.items()) if r.complete}  # fmt: skip


def stage_arms(spec: Spec, decisions: list[Stage]) -> list[str]:
    """The arms the next stage trains, after ``decisions`` (AdaStop's, one per complete
    stage): every arm at stage 1; later the arms of the comparisons still undecided, in the
    spec's order (none once AdaStop has finished)."""
    if not decisions:
        return list(spec.arms)
    if decisions[-1].finished:
        return []
    undecided = undecided_arms(decisions[-1].decisions)
    return [a for a in spec.arms if a in undecided]


def registration_order(st: Status) -> str | None:
    """Whether the pre-registration is older than every run it registered (a kept stage's
    runs are older by design): its time against each run's first launch. None for a study
    without ``preregistration.yaml`` (one that reads kept runs only)."""
    path = st.spec.folder / PREREGISTRATION
    if st.spec.posthoc or not path.is_file():  # a post-hoc reading registers nothing: any
        return None  # preregistration.yaml beside its runs is a continuation's
    written, _ = _registration(path)
    try:
        registered = datetime.fromisoformat(str(written.get("written")))
    except ValueError:
        return f"pre-registration {path} has no readable time ('written'); nothing is checked"
    if registered.tzinfo is None:
        return f"pre-registration {path} has no time zone on its time; nothing is checked"
    first = st.spec.registered_seeds.start
    launched = {(arm, seed): first_launch(run.path) for arm, runs in st.runs.items()
                for seed, run in sorted(runs.items()) if seed >= first}  # fmt: skip
    known = {key: when for key, when in launched.items() if when is not None}
    stamp = str(written.get("written"))
    if not launched:
        return f"pre-registration written {stamp}: no run yet"
    early = [f"{arm} seed {seed} (launched {when.isoformat()})"
             for (arm, seed), when in known.items() if when < registered]  # fmt: skip
    unknown = [f"{arm} seed {seed}" for (arm, seed), when in launched.items() if when is None]
    if early:
        line = f"pre-registration written {stamp} is NOT older than: {', '.join(early)}"
    elif known:
        (arm, seed), when = min(known.items(), key=lambda item: item[1])
        line = (
            f"pre-registration written {stamp}: older than the first launch of each of its "
            f"{len(known)} runs (the earliest {when.isoformat()}, {arm} seed {seed})"
        )
    else:
        line = f"pre-registration written {stamp}"
    if unknown:
        line += (f"; not checked (no {COMMANDS}, or no time zone on its time): "
                 f"{', '.join(unknown)}")  # fmt: skip
    return line


def status_lines(st: Status) -> list[str]:
    spec = st.spec
    lines = [f"study {spec.name}: {len(spec.arms)} arms, {spec.n} seeds a stage, at most "
             f"{spec.stages} stages, alpha {spec.alpha:g}, metric: mean of "
             f"{', '.join(spec.columns)} over epochs {spec.window[0]}-{spec.window[1]} of "
             f"{spec.epochs}; runs under {spec.folder}"]  # fmt: skip
    if not spec.posthoc:
        lines += [f"  {line}" for line in amendment_lines(spec.folder / PREREGISTRATION)]
    order = registration_order(st)
    if order is not None:
        lines.append(f"  {order}")
    for name, runs in st.runs.items():
        if not runs:
            lines.append(f"  {name}: no runs yet")
            continue
        parts = []
        for s, r in sorted(runs.items()):
            pace = f", {r.pace:.0f} s/epoch" if math.isfinite(r.pace) else ""
            parts.append(f"{s}: {r.done}/{r.epochs}{pace}")
        lines.append(f"  {name}: " + "; ".join(parts))
        metric = st.metrics[name]
        if metric:
            ci = mean_ci(list(metric.values()))
            spread = f" [{ci.low:.3f}, {ci.high:.3f}] (95% t)" if ci.n > 1 else ""
            seeds = " ".join(str(s) for s in sorted(metric))
            lines.append(f"    M over its {ci.n} complete {'seed' if ci.n == 1 else 'seeds'} "
                         f"({seeds}): {ci.mean:.3f}{spread}, descriptive")  # fmt: skip
        trained_on = machines_line(runs)
        if trained_on:
            lines.append(f"    trained on {trained_on}")
    lines.append(f"complete stages: {st.complete_stages} of {spec.stages}")
    if not st.finished and not spec.posthoc:
        stage = st.complete_stages + 1
        hours = st.stage_hours(stage)
        left = "unknown until its runs have an epoch" if math.isnan(hours) else f"{hours:.1f} h"
        borrowed = "" if math.isnan(hours) else st.borrowed_times(stage)
        arms = stage_arms(spec, st.decisions)
        which = ("" if len(arms) == len(spec.arms)
                 else f" for {', '.join(arms)}, the arms of the comparisons AdaStop left undecided")
        lines.append(f"stage {stage} still needs {left} on this machine{which}{borrowed}")
    for (b, a), d in st.differences.items():
        if d.n:
            lines.append(f"{b} - {a}: {d.text()}; {d.answer(b, a)}")
            continue
        early = paired(st.metrics[a], st.metrics[b], spec.half_width)
        if early.n >= 2:  # both arms have complete seeds before their stage is: descriptive
            lines.append(f"{b} - {a} over the {early.n} seeds both have complete: "
                         f"{early.text()}, descriptive (the test is AdaStop's, at the stage's "
                         "end)")  # fmt: skip
    if spec.kept_stages:
        seeds = [s for s in spec.registered_seeds if s < st.complete_stages * spec.n]
        for b, a in spec.comparisons:
            d = paired({s: v for s, v in st.values[a].items() if s in seeds},
                       {s: v for s, v in st.values[b].items() if s in seeds}, spec.half_width)
            if d.n:
                lines.append(f"{b} - {a}, the pre-registered stages' seeds alone "
                             f"({seeds[0]}-{seeds[-1]}): {d.text()}; {d.answer(b, a)}")  # fmt: skip
    label = "AdaStop"
    if spec.posthoc:
        label += " (post-hoc reading: this experiment was pre-registered without stages)"
    if not st.decisions:
        lines.append(f"{label}: no stage complete yet")
    for stage in st.decisions:
        said = "; ".join(decision_text(a, b, d) for (a, b), d in stage.decisions.items())
        end = ", finished" if stage.finished else ""
        kept = " (kept runs, read post-hoc)" if stage.number <= spec.kept_stages else ""
        lines.append(f"{label}, stage {stage.number}{kept} ({stage.seeds} seeds an arm): "
                     f"{said}{end}")  # fmt: skip
    return lines


# ------------------------------------------------------------------------------ running
def study_report(root: Path, out_dir: Path) -> Path | None:
    """``hmepol report`` of a study's folder (one with a pre-registration): its decisions stage
    by stage and the paired differences, as study.md in ``out_dir``; None for another folder."""
    registered = Path(root) / PREREGISTRATION
    if not registered.is_file():
        return None
    written = yaml.safe_load(registered.read_text()) or {}
    spec = load_spec(registered, str(written.get("spec", "")), folder=Path(root))
    lines = status_lines(status(spec))
    text = "\n".join([
        f"# Study {spec.name}", "",
        f"Pre-registered {written.get('written', '?')} at commit {written.get('commit', '?')}.",
        "", *[_bullet(line) for line in lines[1:]], "",
        "\"equal\" means no difference detected at the last stage, not equivalence "
        "(docs/studies.md).", "",
    ])  # fmt: skip
    out = Path(out_dir) / "study.md"
    out.write_text(text)
    return out


def _bullet(line: str) -> str:
    """A --status line as a Markdown bullet, an arm's own lines (indented 4) nested under it."""
    nested = len(line) - len(line.lstrip(" ")) >= 4
    return f"{'  ' if nested else ''}- {line.strip()}"


def code_commit() -> str:
    """The commit of the checkout the package runs from ("unknown" outside git)."""
    source = Path(__file__).resolve().parent.parent
    try:
        return subprocess.run(["git", "-C", str(source), "rev-parse", "HEAD"], capture_output=True,
                              text=True, timeout=5, check=True).stdout.strip()  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def _registration(path: Path) -> tuple[dict, dict]:
    """(the pre-registration file's content, the registration in force: its last amendment,
    or the pre-registration itself)."""
    written = yaml.safe_load(path.read_text()) or {}
    amendments = written.get("amendments") or []
    return written, (amendments[-1] if amendments else written)


def _write_yaml(path: Path, content: dict) -> None:
    """Replace ``path`` whole (a crash leaves the old file or the new one, never half)."""
    atomic_write_text(path, yaml.safe_dump(content, sort_keys=False, width=100))


def preregister(spec: Spec, commit: str) -> Path:
    """Write the pre-registration before the first run; refuse (UserError) once the spec or
    the commit differs from the registration in force (the last amendment, if any)."""
    path = spec.folder / PREREGISTRATION
    if path.exists():
        _, current = _registration(path)
        if current.get("spec") != spec.text:
            raise UserError(f"{spec.path} changed since its pre-registration {path}; a "
                            "pre-registered study runs as written: restore the spec, give a "
                            "new folder, or (for how its runs are executed only) amend it with "
                            "--amend")  # fmt: skip
        if current.get("commit") != commit:
            was = str(current.get("commit"))[:12]
            raise UserError(f"the code is at commit {commit[:12]}, not {was} pre-registered in "
                            f"{path}; run the study from that commit")  # fmt: skip
        return path
    spec.folder.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    _write_yaml(path, {"written": stamp, "commit": commit, "spec": spec.text})
    return path


def amend(spec: Spec, commit: str, reason: str) -> Path:
    """Record an amendment: the spec as now given and the code's commit, for the runs and
    epochs not yet trained. Only how runs are executed may change (EXECUTION_KEYS, the threads
    override), never the question (arms, presets, seeds, metric, test, epochs); UserError
    otherwise. The epochs each run had reached are written beside it."""
    path = spec.folder / PREREGISTRATION
    if not path.is_file():
        raise UserError(f"{spec.folder} has no pre-registration to amend; run the study first "
                        "(it pre-registers itself before its first run)")  # fmt: skip
    if not reason.strip():
        raise UserError("--amend needs its reason: why the execution changes, and why the "
                        "numbers do not")  # fmt: skip
    written, current = _registration(path)
    before = load_spec(path, str(current.get("spec", "")), folder=spec.folder)
    was, now = _question(before), _question(spec)
    changed = sorted(k for k in set(was) | set(now) if was.get(k) != now.get(k))
    if changed:
        raise UserError(f"an amendment changes only how runs are executed ("
                        f"{', '.join(EXECUTION_KEYS)}, the threads override); {spec.path} "
                        f"also changes {', '.join(changed)}: that is a new study (a new "
                        "folder)")  # fmt: skip
    if current.get("spec") == spec.text and current.get("commit") == commit:
        raise UserError(f"{spec.path} at commit {commit[:12]} is already the registration in "
                        f"force in {path}; nothing to amend")  # fmt: skip
    runs = {name: {seed: run.done for seed, run in sorted(arm_runs(arm, spec.epochs).items())}
            for name, arm in spec.arms.items()}  # fmt: skip
    stamp = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    written.setdefault("amendments", []).append({
        "written": stamp, "commit": commit, "reason": reason.strip(),
        "epochs_done_before": runs, "spec": spec.text,
    })  # fmt: skip
    _write_yaml(path, written)
    return path


def amendment_lines(path: Path) -> list[str]:
    """One line per amendment of a pre-registration, for --status and the report."""
    if not path.is_file():
        return []
    written, _ = _registration(path)
    return [f"amended {a.get('written', '?')} at commit {str(a.get('commit', '?'))[:12]}: "
            f"{a.get('reason', '')}" for a in written.get("amendments") or []]  # fmt: skip


def sweep_command(spec: Spec, arm: Arm, seeds: list[int]) -> list[str]:
    """The ``hmepol sweep`` that runs (or resumes, or skips) these seeds of one arm."""
    return [
        sys.executable, "-m", "hmepol_cli", "sweep", f"experiment={arm.preset}",
        *spec.overrides, *arm.overrides, f"epochs={spec.epochs}",
        f"seed={','.join(map(str, seeds))}", f"hydra.sweep.dir={arm.folder}",
        f"hydra/launcher={spec.launcher}",
    ]  # fmt: skip


def say(line: str) -> None:
    print(f"hmepol study: {line}", flush=True)


def _progress(spec: Spec, stage: int, last: str, warned: list[bool]) -> str:
    """Print the stage's progress line when it changed, and once, when its first epochs give
    a pace, a warning if the stage needs more than WARN_HOURS; the line printed."""
    st = status(spec)
    seeds = stage_seeds(spec, stage)
    arms = stage_arms(spec, st.decisions[: stage - 1])
    done = sum(st.runs[a][s].done for a in arms for s in seeds if s in st.runs[a])
    total = spec.epochs * len(seeds) * len(arms)
    hours = st.stage_hours(stage)
    left = f", ~{hours:.1f} h left" if math.isfinite(hours) else ""
    line = f"stage {stage} of {spec.stages}: {done}/{total} epochs{left}"
    if line != last:
        say(line)
    if not warned[0] and math.isfinite(hours) and hours > WARN_HOURS:
        warned[0] = True
        print(f"hmepol: warning: stage {stage} of {spec.name} needs about {hours:.1f} h on this "
              "machine (estimated from its first epochs)", file=sys.stderr, flush=True)  # fmt: skip
    return line


def _run_sweeps(spec: Spec, stage: int, todo: list[tuple[Arm, list[int]]],
                warned: list[bool]) -> None:  # fmt: skip
    """Run the sweeps in ``todo`` (those whose seeds are all complete are skipped),
    ``parallel_sweeps`` at a time, each its own process. A signal (SIGTERM, Ctrl-C) reaches
    every running sweep, which checkpoints and stops; a sweep that fails stops the others the
    same way, and the study exits with its code."""

    def complete(arm: Arm, seeds: list[int]) -> bool:
        runs = arm_runs(arm, spec.epochs)
        return all(s in runs and runs[s].complete for s in seeds)

    todo = [(arm, seeds) for arm, seeds in todo if not complete(arm, seeds)]
    running: list[subprocess.Popen] = []
    failed = 0

    def forward(signum, frame):  # noqa: ANN001, ARG001
        for process in running:
            if process.poll() is None:
                process.send_signal(signum)

    previous = signal.signal(signal.SIGTERM, forward)
    last, shown = "", time.monotonic()
    try:
        while todo or running:
            while todo and len(running) < spec.parallel_sweeps and not failed:
                arm, seeds = todo.pop(0)
                running.append(subprocess.Popen(sweep_command(spec, arm, seeds)))
            try:
                time.sleep(min(SWEEP_POLL_SECONDS, POLL_SECONDS))
            except KeyboardInterrupt:  # passed on (a sweep ignores a second one)
                forward(signal.SIGINT, None)
                for process in running:
                    process.wait()
                raise SystemExit(130) from None
            for process in [p for p in running if p.poll() is not None]:
                running.remove(process)
                if process.returncode and not failed:
                    failed = process.returncode
                    todo = []
                    forward(signal.SIGTERM, None)
            if time.monotonic() - shown >= POLL_SECONDS:
                last, shown = _progress(spec, stage, last, warned), time.monotonic()
    finally:
        signal.signal(signal.SIGTERM, previous)
    if failed:
        raise SystemExit(failed)


def run_study(spec: Spec, until: int | None = None) -> Status:
    """Run the study to its decision (or to its last stage, or to stage ``until``), resuming
    whatever is there."""
    if spec.posthoc:
        raise UserError(f"{spec.path} reads kept runs (posthoc: true) and trains nothing; use "
                        "hmepol study SPEC --status")  # fmt: skip
    if spec.kept_stages:
        kept = status(spec)
        if kept.complete_stages < spec.kept_stages:
            missing = stage_seeds(spec, kept.complete_stages + 1)
            raise UserError(f"{spec.path}: stages 1-{spec.kept_stages} are kept runs, but stage "
                            f"{kept.complete_stages + 1} (seeds {missing[0]}-{missing[-1]}) is not "
                            f"complete under {spec.folder}; a study does not train its kept "
                            "stages")  # fmt: skip
    preregister(spec, code_commit())
    while True:
        st = status(spec)
        if st.finished:
            for line in status_lines(st):
                say(line)
            return st
        if until is not None and st.complete_stages >= until:
            for line in status_lines(st):
                say(line)
            say(f"stopped after stage {until} (--until-stage {until}); the same command "
                "without it goes on")  # fmt: skip
            return st
        stage = st.complete_stages + 1
        seeds = stage_seeds(spec, stage)
        arms = stage_arms(spec, st.decisions)
        which = ("" if len(arms) == len(spec.arms)
                 else " (the arms of the comparisons AdaStop left undecided)")  # fmt: skip
        say(f"stage {stage} of {spec.stages}: seeds {seeds[0]}-{seeds[-1]} of "
            f"{', '.join(arms)}{which}")  # fmt: skip
        hours = st.stage_hours(stage)
        if math.isfinite(hours) and hours > WARN_HOURS:
            print(f"hmepol: warning: stage {stage} of {spec.name} needs about {hours:.1f} h on "
                  "this machine", file=sys.stderr, flush=True)  # fmt: skip
        warned = [math.isfinite(hours) and hours > WARN_HOURS]
        todo = [(spec.arms[a], seeds) for a in arms for seeds in sweep_seeds(spec, stage)]
        _run_sweeps(spec, stage, todo, warned)
        st = status(spec)
        if st.complete_stages < stage:
            raise UserError(f"stage {stage} is not complete after its sweeps; run the study "
                            "again to continue it")  # fmt: skip
        for line in status_lines(st)[-len(spec.comparisons) :]:
            say(line)


def main(args: list[str]) -> None:
    import argparse

    parser = argparse.ArgumentParser(
        prog="hmepol study",
        description="Run a pre-registered sequential comparison (AdaStop) stage by stage, "
        "resuming what is there; --status says where it stands and trains nothing.",
    )
    parser.add_argument("spec", help="a study spec (YAML; presets in conf/study/)")
    parser.add_argument("--status", action="store_true", help="where the study stands; no training")
    parser.add_argument("--until-stage", type=int, metavar="K",
                        help="stop once stage K is complete (the same command without it goes "
                        "on from there)")  # fmt: skip
    parser.add_argument("--amend", metavar="REASON",
                        help="record the spec as now written and this commit as the study's "
                        "registration for what it has not yet trained; only how runs are "
                        "executed may change (launcher, parallel_sweeps, seeds_per_sweep, "
                        "threads). REASON: why, and why the numbers do not change")  # fmt: skip
    ns = parser.parse_args(args)
    spec = load_spec(ns.spec)
    if ns.status:
        for line in status_lines(status(spec)):
            print(line)
        return
    if ns.amend is not None:
        path = amend(spec, code_commit(), ns.amend)
        print(f"hmepol study: amendment recorded in {path}; run the study from this commit")
        return
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    if ns.until_stage is not None and not 1 <= ns.until_stage <= spec.stages:
        raise UserError(f"--until-stage {ns.until_stage}: the study {spec.name} has stages 1 to "
                        f"{spec.stages}")  # fmt: skip
    run_study(spec, ns.until_stage)
