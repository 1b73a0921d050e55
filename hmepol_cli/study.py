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
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd
import yaml

from hmepol_cli.errors import UserError
from hmepol_cli.report.comparisons import (
    Paired,
    Stage,
    adastop,
    decision_text,
    paired,
    window_metric,
)

PREREGISTRATION = "preregistration.yaml"
LAUNCHERS = ("local", "population", "population_local", "slurm", "population_slurm", "basic")
WARN_HOURS = 3.0  # a stage estimated to need more than this on this machine is announced
POLL_SECONDS = 30.0
KEYS = {"name", "folder", "posthoc", "kept_stages", "launcher", "seeds_per_stage", "stages",
        "alpha", "beta",
        "permutations", "adastop_seed", "epochs", "metric", "half_width", "overrides", "arms",
        "comparisons"}  # fmt: skip


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
    launcher = str(raw.get("launcher", "local"))
    if launcher not in LAUNCHERS:
        raise UserError(f"{where}: launcher={launcher!r}; choose {', '.join(LAUNCHERS)}")
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
        posthoc=bool(raw.get("posthoc", False)), kept_stages=kept,
    )  # fmt: skip


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
            str(info.get("status", "unknown")), pace, table,
        )  # fmt: skip
    return out


def stage_seeds(spec: Spec, stage: int) -> list[int]:
    """The seeds of stage ``stage`` (1-based): n per stage, consecutive from 0."""
    return list(range((stage - 1) * spec.n, stage * spec.n))


@dataclass
class Status:
    spec: Spec
    runs: dict[str, dict[int, RunState]]
    complete_stages: int
    values: dict[str, dict[int, float]]  # per arm, per seed of the complete stages
    decisions: list[Stage]
    differences: dict[tuple[str, str], Paired]

    @property
    def finished(self) -> bool:
        if self.decisions and self.decisions[-1].finished:
            return True
        return self.complete_stages >= self.spec.stages

    def stage_hours(self, stage: int, launcher: str | None = None) -> float:
        """Hours the stage's unfinished epochs need on this machine, at each arm's pace (a
        population trains its members together: the slowest member; otherwise one after the
        other); NaN while no run of the arm has a pace."""
        population = (launcher or self.spec.launcher).startswith("population")
        total = 0.0
        for runs in self.runs.values():
            paces = [r.pace for r in runs.values() if math.isfinite(r.pace)]
            pace = float(pd.Series(paces).median()) if paces else math.nan
            left = [self.spec.epochs - (runs[s].done if s in runs else 0)
                    for s in stage_seeds(self.spec, stage)]  # fmt: skip
            left = [max(0, x) for x in left]
            if not any(left):
                continue
            if not math.isfinite(pace):
                return math.nan
            total += pace * (max(left) if population else sum(left))
        return total / 3600


def status(spec: Spec) -> Status:
    """Where a study stands, from its run directories (reads only)."""
    runs = {name: arm_runs(arm, spec.epochs) for name, arm in spec.arms.items()}
    complete = 0
    for stage in range(1, spec.stages + 1):
        if all(
            s in runs[a] and runs[a][s].complete for a in runs for s in stage_seeds(spec, stage)
        ):
            complete = stage
        else:
            break
    seeds = range(complete * spec.n)
    first, last = spec.window
    values = {
        a: {s: window_metric(runs[a][s].table, spec.columns, first, last,
                             runs[a][s].status == "failed") for s in seeds}
        for a in runs
    }  # fmt: skip
    decisions = []
    if complete:
        decisions = adastop(
            {a: [values[a][s] for s in seeds] for a in runs}, spec.n, spec.stages,
            spec.comparisons, spec.alpha, spec.beta, spec.permutations, spec.adastop_seed,
        )  # fmt: skip
    differences = {(b, a): paired(values[a], values[b], spec.half_width)
                   for b, a in spec.comparisons}  # fmt: skip
    return Status(spec, runs, complete, values, decisions, differences)


def status_lines(st: Status) -> list[str]:
    spec = st.spec
    lines = [f"study {spec.name}: {len(spec.arms)} arms, {spec.n} seeds a stage, at most "
             f"{spec.stages} stages, alpha {spec.alpha:g}, metric: mean of "
             f"{', '.join(spec.columns)} over epochs {spec.window[0]}-{spec.window[1]} of "
             f"{spec.epochs}; runs under {spec.folder}"]  # fmt: skip
    for name, runs in st.runs.items():
        if not runs:
            lines.append(f"  {name}: no runs yet")
            continue
        parts = []
        for s, r in sorted(runs.items()):
            pace = f", {r.pace:.0f} s/epoch" if math.isfinite(r.pace) else ""
            parts.append(f"{s}: {r.done}/{r.epochs}{pace}")
        lines.append(f"  {name}: " + "; ".join(parts))
    lines.append(f"complete stages: {st.complete_stages} of {spec.stages}")
    if not st.finished and not spec.posthoc:
        stage = st.complete_stages + 1
        hours = st.stage_hours(stage)
        left = "unknown until its runs have an epoch" if math.isnan(hours) else f"{hours:.1f} h"
        lines.append(f"stage {stage} still needs {left} on this machine")
    for (b, a), d in st.differences.items():
        if d.n:
            lines.append(f"{b} - {a}: {d.text()}; {d.answer(b, a)}")
    if spec.kept_stages:
        seeds = [s for s in spec.registered_seeds if s < st.complete_stages * spec.n]
        for b, a in spec.comparisons:
            d = paired({s: st.values[a][s] for s in seeds}, {s: st.values[b][s] for s in seeds},
                       spec.half_width)  # fmt: skip
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
        "", *[f"- {line.strip()}" for line in lines[1:]], "",
        "\"equal\" means no difference detected at the last stage, not equivalence "
        "(docs/studies.md).", "",
    ])  # fmt: skip
    out = Path(out_dir) / "study.md"
    out.write_text(text)
    return out


def code_commit() -> str:
    """The commit of the checkout the package runs from ("unknown" outside git)."""
    source = Path(__file__).resolve().parent.parent
    try:
        return subprocess.run(["git", "-C", str(source), "rev-parse", "HEAD"], capture_output=True,
                              text=True, timeout=5, check=True).stdout.strip()  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def preregister(spec: Spec, commit: str) -> Path:
    """Write the pre-registration before the first run; refuse (UserError) once the spec or
    the commit differs from it."""
    path = spec.folder / PREREGISTRATION
    if path.exists():
        written = yaml.safe_load(path.read_text()) or {}
        if written.get("spec") != spec.text:
            raise UserError(f"{spec.path} changed since its pre-registration {path}; a "
                            "pre-registered study runs as written: restore the spec or give a "
                            "new folder")  # fmt: skip
        if written.get("commit") != commit:
            was = str(written.get("commit"))[:12]
            raise UserError(f"the code is at commit {commit[:12]}, not {was} pre-registered in "
                            f"{path}; run the study from that commit")  # fmt: skip
        return path
    spec.folder.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    path.write_text(yaml.safe_dump({"written": stamp, "commit": commit, "spec": spec.text},
                                   sort_keys=False, width=100))  # fmt: skip
    return path


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


def _watch(spec: Spec, stage: int, process: subprocess.Popen, warned: list[bool]) -> int:
    """Wait for one sweep, printing a progress line and, once its first epochs give a pace, a
    warning when the stage needs more than WARN_HOURS."""
    last = ""
    while True:
        try:
            return process.wait(timeout=POLL_SECONDS)
        except subprocess.TimeoutExpired:
            pass
        st = status(spec)
        seeds = stage_seeds(spec, stage)
        done = sum(st.runs[a][s].done for a in st.runs for s in seeds if s in st.runs[a])
        total = spec.epochs * len(seeds) * len(spec.arms)
        hours = st.stage_hours(stage)
        left = f", ~{hours:.1f} h left" if math.isfinite(hours) else ""
        line = f"stage {stage} of {spec.stages}: {done}/{total} epochs{left}"
        if line != last:
            say(line)
            last = line
        if not warned[0] and math.isfinite(hours) and hours > WARN_HOURS:
            warned[0] = True
            print(
                f"hmepol: warning: stage {stage} of {spec.name} needs about {hours:.1f} h on "
                "this machine (estimated from its first epochs)",
                file=sys.stderr,
                flush=True,
            )


def run_study(spec: Spec) -> Status:
    """Run the study to its decision (or to its last stage), resuming whatever is there."""
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
        stage = st.complete_stages + 1
        seeds = stage_seeds(spec, stage)
        say(f"stage {stage} of {spec.stages}: seeds {seeds[0]}-{seeds[-1]} of "
            f"{', '.join(spec.arms)}")  # fmt: skip
        hours = st.stage_hours(stage)
        if math.isfinite(hours) and hours > WARN_HOURS:
            print(f"hmepol: warning: stage {stage} of {spec.name} needs about {hours:.1f} h on "
                  "this machine", file=sys.stderr, flush=True)  # fmt: skip
        warned = [math.isfinite(hours) and hours > WARN_HOURS]
        for arm in spec.arms.values():
            runs = arm_runs(arm, spec.epochs)
            if all(s in runs and runs[s].complete for s in seeds):
                continue
            process = subprocess.Popen(sweep_command(spec, arm, seeds))
            previous = signal.getsignal(signal.SIGTERM)

            def forward(signum, frame, process=process):  # noqa: ANN001, ARG001
                process.send_signal(signum)

            signal.signal(signal.SIGTERM, forward)
            try:
                code = _watch(spec, stage, process, warned)
            except KeyboardInterrupt:
                code = process.wait()
            finally:
                signal.signal(signal.SIGTERM, previous)
            if code:
                raise SystemExit(code)
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
    ns = parser.parse_args(args)
    spec = load_spec(ns.spec)
    if ns.status:
        for line in status_lines(status(spec)):
            print(line)
        return
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    run_study(spec)
