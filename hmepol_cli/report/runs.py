"""The runs the report is made of, and how they are grouped: a :class:`Run` (one finished run
directory as loading.py read it), copies of one run merged and a seed found twice kept once, and
:class:`Group`s of runs that differ only by seed, each labelled by what sets it apart.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import hashlib
import math
import re
import warnings
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from hmepol_cli.algorithms import ALGORITHMS, SCRATCH
from hmepol_cli.errors import RunDirError
from hmepol_cli.plots import WorldMap
from hmepol_cli.report.defaults import algo_defaults
from hmepol_cli.report.stats import FINAL_FRACTION, UNBOUNDED, final_value
from hmepol_cli.run import CHECKPOINT, read_json

# Config keys that say how a run was executed, not what was run: never a reason to split groups.
RUN_SPECIFIC_KEYS = {
    "seed",
    "resume",
    "progress",
    "threads",
    "skip_finished",
    "checkpoint_every",
    "device",
    # A population (seeds=[...]) and how its members were batched on the device.
    "seeds",
    "members",
    "chunk_members",
    "vmap",
    "cuda_graphs",
    "matmul_precision",
    "eval.every",
    "env.workers",  # processes stepping a Gymnasium world: the same numbers with any count
    "diagnostics",  # what is recorded, not what is computed
    "logger",
    "checkpoint.keep_every",
    # The effective wind is read once (run.json) and stored under the synthetic key "wind".
    "wind",
    "env.wind",
}
RUN_SPECIFIC_PREFIXES = ("hydra", "logger.", "checkpoint.", "eval.plot_")
# Not what a run is, for telling two copies of one run apart: where a fine-tuning wrote, and how
# long each epoch took on its machine.
OUTPUT_KEYS = ("output_dir",)
TIMING_COLUMNS = ("seconds", "wall_time")
SEED_IN_NAME = re.compile(r"(?:^|[_/-])seed[-=](\d+)(?=$|[_@/,-])")

# Short names of the keys that usually vary, for labels and table columns.
SHORT_NAMES = {
    "env.name": "env",
    "algo.name": "algo",
    "policy.name": "policy",
    "policy.bptt": "bptt",
    "algo.alpha": "alpha",
    "algo.objective": "objective",
}
ALGO_ORDER = tuple(ALGORITHMS)
# A goal task's returns (hmepol_cli.finetune.task.GoalTask): the share of episodes that reached
# the target. The bounds of a fine-tuning whose run.json does not record them (made before it
# did) whose rows record a success rate; any other such run's returns are unbounded.
GOAL_TASK_BOUNDS = (0.0, 1.0)


class SkippedRunWarning(UserWarning):
    """A run directory that the report cannot use."""


class MapUnknownWarning(UserWarning):
    """Runs whose run.json does not record their world's map: their maps are drawn without
    walls."""


@dataclass(frozen=True)
class SkippedRun:
    path: Path
    reason: str


@dataclass(frozen=True)
class MergedRun:
    """A run directory that holds the same run as ``kept`` (same config, seed and rows): the run
    is counted once."""

    path: Path
    kept: Path


@dataclass
class Run:
    """One finished run: its flattened config and what it wrote."""

    path: Path
    config: dict[str, Any]  # dotted keys -> leaf values ("algo.name": "hmepol")
    meta: dict[str, Any]  # run.json
    epochs: pd.DataFrame | None = None  # epochs.csv (pre-training runs)
    positions: dict[int, np.ndarray] | None = None  # eval/final.npz, config -> (n, T+1, 2)
    finetune: pd.DataFrame | None = None  # finetune.csv (fine-tuning runs)

    @property
    def seed(self) -> int:
        return int(self.meta.get("seed", self.config.get("seed", 0)))

    @property
    def env(self) -> str:
        env_id = self.meta.get("env_id") or (
            self.config.get("env.id") if self.config.get("env.name") == "gym" else None
        )
        if env_id:  # a Gymnasium world is named by its id, made safe for file names
            return re.sub(r"[^A-Za-z0-9._-]+", "-", str(env_id))
        # run.json names the world actually used (a fine-tuning config may leave it to its init).
        return str(self.meta.get("env") or self.config.get("env.name") or "?")

    @property
    def algo(self) -> str:
        return str(self.meta.get("algo") or self.config.get("algo.name") or "?")

    @property
    def wind(self) -> float:
        if "wind" in self.meta and self.meta["wind"] is None:
            return math.nan  # a world without wind
        for value in (self.meta.get("wind"), self.config.get("env.wind"), self.config.get("wind")):
            try:
                return float(value)
            except (TypeError, ValueError):
                continue
        return math.nan

    @property
    def n_configurations(self) -> int:
        names = self.meta.get("config_names")
        if names:
            return len(names)
        if self.epochs is not None:
            return len([c for c in self.epochs.columns if c.startswith("entropy_c")])
        return len(self.positions or {})

    @property
    def configuration_names(self) -> list[str]:
        names = self.meta.get("config_names") or []
        return [str(n) for n in names] or [f"config {c}" for c in range(self.n_configurations)]

    @property
    def configuration_probs(self) -> list[float]:
        probs = self.meta.get("config_probs")
        if probs and len(probs) == self.n_configurations:
            return [float(p) for p in probs]
        return [1.0 / max(self.n_configurations, 1)] * self.n_configurations

    @property
    def log_free_area(self) -> list[float]:
        logs = self.meta.get("log_free_area")
        if logs and len(logs) == self.n_configurations:
            return [float(v) for v in logs]
        areas = self.meta.get("free_area")
        if areas and len(areas) == self.n_configurations:
            return [math.log(float(a)) for a in areas]
        return [math.nan] * self.n_configurations

    @property
    def is_pretraining(self) -> bool:
        return self.epochs is not None and self.finetune is None

    @property
    def pretraining_run(self) -> str | None:
        """The directory of the pre-training run a fine-tuning started from (its ``init``
        without a kept checkpoint's ``@<epochs>`` or file name); None from scratch."""
        init = str(self.meta.get("init") or self.config.get("init") or "none").strip()
        if self.finetune is None or init.lower() in ("none", "null", "", SCRATCH.name):
            return None
        path = Path(init.partition("@")[0])
        if path.suffix == CHECKPOINT.suffix:  # a checkpoint file: <run>/checkpoints/<name>.pt
            path = path.parent.parent if path.parent.name == CHECKPOINT.parent.name else path.parent
        return str(path)

    @property
    def pretraining_seed(self) -> int | None:
        """The seed of the pre-training run a fine-tuning started from: its run.json's where it
        can be read, else a ``seed-<n>`` or ``seed=<n>`` in its directory's name; None from
        scratch or when neither says."""
        run = self.pretraining_run
        if run is None:
            return None
        with contextlib.suppress(OSError, ValueError, TypeError, RunDirError):
            return int(read_json(Path(run) / "run.json")["seed"])
        found = SEED_IN_NAME.findall(Path(run).name)
        return int(found[-1]) if found else None

    @property
    def pairing_seed(self) -> int:
        """The seed that pairs a fine-tuning with the other starts': the pre-training run's
        where it is known (seeds 0 and 1 of each algorithm fine-tuned with one seed stay two
        pairs), else the fine-tuning seed (from scratch)."""
        seed = self.pretraining_seed
        return self.seed if seed is None else seed

    @property
    def independent_unit(self) -> str:
        """What a fine-tuning run is one independent draw of: the pre-training run its policy
        came from (its targets and fine-tuning seeds are nested in it), or, from scratch, the
        fine-tuning run itself."""
        return self.pretraining_run or str(self.path)

    @property
    def return_bounds(self) -> tuple[float, float]:
        """The range a fine-tuning's returns can take (run.json's ``return_bounds``, null where a
        side is unbounded): a goal task's [0, 1], none for a world's own reward. A run.json
        without it: [0, 1] where the rows record a success rate, else none."""
        recorded = self.meta.get("return_bounds")
        if recorded is not None:
            low, high = recorded
            return (
                -math.inf if low is None else float(low),
                math.inf if high is None else float(high),
            )
        rows = self.finetune
        if rows is not None and "success_rate" in rows:
            if np.isfinite(pd.to_numeric(rows["success_rate"], errors="coerce")).all():
                return GOAL_TASK_BOUNDS
        return UNBOUNDED

    @property
    def world_map(self) -> WorldMap | None:
        """The map run.json records of the run's world (``world_map``); None for a world without
        one, or a run.json made before it recorded the map (:attr:`records_map`)."""
        return WorldMap.from_json(self.meta.get("world_map"))

    @property
    def records_map(self) -> bool:
        """Whether run.json says what the world's map is (null for a world without one)."""
        return "world_map" in self.meta

    def entropy_curve(self, config: int | None = None) -> pd.Series:
        """Entropy per epoch (nats), indexed by epoch: average (None) or one configuration."""
        column = "entropy" if config is None else f"entropy_c{config}"
        if self.epochs is None or column not in self.epochs:
            return pd.Series(dtype=float)
        return pd.Series(self.epochs[column].to_numpy(float), index=self.epochs["epoch"].to_numpy())

    def final_entropy(self, config: int | None = None) -> float:
        """Mean entropy over the last 10% of epochs (nats): average (None) or one configuration."""
        return final_value(self.entropy_curve(config).to_numpy())

    def final_epochs(self, config: int | None = None) -> str:
        """The epochs :meth:`final_entropy` averages, 'first-last' ('' when there are none)."""
        curve = self.entropy_curve(config)
        curve = curve[np.isfinite(curve.to_numpy())]  # the values final_value keeps
        if curve.empty:
            return ""
        k = max(1, math.ceil(FINAL_FRACTION * len(curve)))
        window = curve.index[-k:]
        return f"{int(window[0])}-{int(window[-1])}"

    @property
    def completeness(self) -> tuple[int, int, float]:
        """How far the run got, to choose between two copies of one seed: epochs done (run.json),
        rows in epochs.csv, and the wall_time of its last epoch (the latest wins a tie)."""
        try:
            declared = int(self.meta.get("epochs_done", 0))
        except (TypeError, ValueError):
            declared = 0
        if self.epochs is None:
            return declared, 0, -math.inf
        wall_time = -math.inf
        if "wall_time" in self.epochs:
            last = pd.to_numeric(self.epochs["wall_time"], errors="coerce").iloc[-1]
            wall_time = float(last) if np.isfinite(last) else -math.inf
        return declared, len(self.epochs), wall_time


@dataclass
class Group:
    """Runs that share every varying config key but the seed."""

    key: tuple[tuple[str, Any], ...]  # (dotted key, value) of every key that varies across runs
    runs: list[Run] = field(default_factory=list)
    label: str = ""  # the series name inside its (env, wind) comparison, set by label_groups

    @property
    def first(self) -> Run:
        return self.runs[0]

    @property
    def env(self) -> str:
        return self.first.env

    @property
    def algo(self) -> str:
        return self.first.algo

    @property
    def wind(self) -> float:
        return self.first.wind

    @property
    def seeds(self) -> list[int]:
        return sorted(r.seed for r in self.runs)

    @property
    def n_configurations(self) -> int:
        return self.first.n_configurations

    @property
    def configuration_names(self) -> list[str]:
        return self.first.configuration_names

    def finals(self, config: int | None = None) -> dict[int, float]:
        """Final entropy of every seed, {seed: nats}."""
        return {r.seed: r.final_entropy(config) for r in self.runs}

    def final_epochs(self, config: int | None = None) -> str:
        """The epochs its seeds' finals average: one 'first-last', or each distinct one."""
        return ", ".join(dict.fromkeys(r.final_epochs(config) for r in self.runs))

    def scores(self, config: int | None = None) -> np.ndarray:
        """The score matrix of rliable's aggregates, (n_seeds, n_configurations) in seed order:
        final entropies, a row per run (one column: ``config``'s). A run without a finite score
        in some configuration (never drawn there) is left out, as its row is incomplete."""
        configs = range(self.n_configurations) if config is None else [config]
        finals = [self.finals(c) for c in configs]
        matrix = np.array([[f[s] for f in finals] for s in self.seeds], dtype=float)
        return matrix[np.isfinite(matrix).all(axis=1)].reshape(-1, len(finals))

    def curves(self, config: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Entropy curves of all seeds aligned on epoch: (epochs,), (n_seeds, n_epochs)."""
        table = pd.concat(
            [r.entropy_curve(config).rename(r.seed) for r in self.runs], axis=1
        ).sort_index()
        return table.index.to_numpy(float), table.to_numpy(float).T

    def representative(self) -> Run:
        """The seed whose final average entropy is the median of the group (for maps)."""
        with_eval = [r for r in self.runs if r.positions]
        if not with_eval:
            return self.first
        ordered = sorted(
            with_eval, key=lambda r: (np.nan_to_num(r.final_entropy(), nan=-1e9), r.seed)
        )
        return ordered[(len(ordered) - 1) // 2]


# --------------------------------------------------------------------------------------- grouping
def _is_run_specific(key: str) -> bool:
    return key in RUN_SPECIFIC_KEYS or key.startswith(RUN_SPECIFIC_PREFIXES)


def _values(runs: list[Run], key: str) -> list[Any]:
    return [run.wind if key == "wind" else run.config.get(key) for run in runs]


def varying_keys(runs: list[Run]) -> list[str]:
    """Config keys whose value differs between runs, seeds and run-specific keys excluded.

    ``wind`` (the effective wind force, from run.json) stands for both ``wind`` and ``env.wind``.
    """
    keys = sorted({k for run in runs for k in run.config if not _is_run_specific(k)})
    keys.append("wind")
    out = []
    for key in keys:
        values = {repr(v) for v in _values(runs, key)}
        if len(values) > 1:
            out.append(key)
    return out


def _algo_rank(algo: str) -> tuple[int, str]:
    return (ALGO_ORDER.index(algo) if algo in ALGO_ORDER else len(ALGO_ORDER), algo)


def _settings(run: Run, keys: list[str]) -> tuple[tuple[str, Any], ...]:
    return tuple((k, run.wind if k == "wind" else run.config.get(k)) for k in keys)


def _completeness_text(run: Run) -> str:
    declared, rows, wall_time = run.completeness
    text = f"{declared} epochs done" + (f" ({rows} rows in epochs.csv)" if rows != declared else "")
    if np.isfinite(wall_time):
        ended = dt.datetime.fromtimestamp(wall_time).isoformat(sep=" ", timespec="seconds")
        text += f", last epoch ended {ended}"
    return text


def _fingerprint(run: Run) -> tuple:
    """What makes two directories the same run: kind, config (how it was executed and where it
    wrote aside), effective wind, seed, and the rows it wrote (timings aside)."""
    config = tuple(
        sorted(
            (key, repr(value))
            for key, value in run.config.items()
            if not _is_run_specific(key) and key not in OUTPUT_KEYS
        )
    )
    rows = run.epochs if run.finetune is None else run.finetune
    rows = rows.drop(columns=[c for c in TIMING_COLUMNS if c in rows]).reset_index(drop=True)
    digest = hashlib.sha256(repr(list(rows.columns)).encode())
    digest.update(pd.util.hash_pandas_object(rows, index=False).to_numpy().tobytes())
    kind = "pretraining" if run.finetune is None else "finetune"
    return kind, config, repr(run.wind), run.seed, digest.hexdigest()


def merge_identical_runs(runs: list[Run]) -> tuple[list[Run], list[MergedRun]]:
    """Keep one of the directories that hold the same run (:func:`_fingerprint`): found in two
    input folders (a copy, one run listed twice), it is one draw and is counted once. The one
    kept is the one :func:`drop_duplicate_seeds` would keep (the latest, then path order)."""
    same: dict[tuple, list[Run]] = {}
    for run in sorted(runs, key=lambda r: str(r.path)):
        same.setdefault(_fingerprint(run), []).append(run)
    merged = []
    for copies in same.values():
        kept = max(copies, key=lambda r: r.completeness)
        merged += [MergedRun(r.path, kept.path) for r in copies if r is not kept]
    left_out = {m.path for m in merged}
    return [r for r in runs if r.path not in left_out], merged


def drop_duplicate_seeds(runs: list[Run]) -> tuple[list[Run], list[SkippedRun]]:
    """Keep one pre-training run per (settings, seed): the most complete (``Run.completeness``).

    Two directories with the same settings and seed are the same run twice (a copy, a run made
    again); averaging both would count that seed twice. Each copy left out is skipped with a
    warning naming it and the run kept in its place.
    """
    pretraining = [r for r in runs if r.is_pretraining]
    keys = varying_keys(pretraining)
    copies: dict[tuple, list[Run]] = {}
    for run in sorted(pretraining, key=lambda r: str(r.path)):
        copies.setdefault((_settings(run, keys), run.seed), []).append(run)
    left_out: list[SkippedRun] = []
    for same in copies.values():
        # max keeps the first in path order among equals: the choice does not depend on discovery.
        kept = max(same, key=lambda r: r.completeness)
        for run in same:
            if run is kept:
                continue
            reason = (
                f"same settings and seed {run.seed} as {kept.path}, which is kept "
                f"({_completeness_text(kept)}; this one: {_completeness_text(run)})"
            )
            left_out.append(SkippedRun(run.path, reason))
            warnings.warn(f"skipping run {run.path}: {reason}", SkippedRunWarning, stacklevel=2)
    dropped = {s.path for s in left_out}
    return [r for r in runs if r.path not in dropped], left_out


def group_runs(runs: list[Run]) -> list[Group]:
    """Split pre-training runs into groups that differ only by seed, ordered env, wind, algo.

    Every seed of a group must appear once: pass the runs through :func:`drop_duplicate_seeds`.
    """
    runs = [r for r in runs if r.is_pretraining]
    keys = varying_keys(runs)
    groups: dict[tuple, Group] = {}
    for run in sorted(runs, key=lambda r: str(r.path)):
        key = _settings(run, keys)
        group = groups.setdefault(key, Group(key=key))
        twin = next((r for r in group.runs if r.seed == run.seed), None)
        if twin is not None:
            raise ValueError(
                f"{run.path} and {twin.path} are seed {run.seed} of the same settings "
                "(drop_duplicate_seeds keeps one)"
            )
        group.runs.append(run)
    ordered = sorted(
        groups.values(),
        # Within an algorithm the group with most seeds (the main experiment) comes first.
        key=lambda g: (
            g.env,
            np.nan_to_num(g.wind, nan=-1.0),
            _algo_rank(g.algo),
            -len(g.runs),
            repr(g.key),
        ),
    )
    label_groups(ordered)
    return ordered


def label_groups(groups: list[Group]) -> None:
    """Name each group inside its env: the algorithm, plus the settings in which it departs
    from the algorithm's main experiment ("HMepol (policy=gru)"). A key's main value is the one
    most runs of the algorithm share; where two values tie, every group names its value. Keys
    fixed by the algorithm (HMepol always with the recursive policy, alpha-Mepol always with
    CVaR) are left out of the label. A switch of how the algorithm works (``algo.trust_region``,
    ``policy.bptt``, ...) in which every group departs from the algorithm's own settings (the
    thesis') is named too: the exact trust region alone is "HMepol (algo.trust_region=exact)",
    never plain "HMepol".
    """
    for env in {g.env for g in groups}:
        members = [g for g in groups if g.env == env]
        for algo in {g.algo for g in members}:
            same = [g for g in members if g.algo == algo]
            runs = [g.first for g in same]
            keys = [k for k in varying_keys(runs) if k not in ("env.name", "algo.name", "wind")]
            main = {k: _main_value(same, k) for k in keys}
            shared = [k for k in _switches_departed(same, algo) if k not in keys]
            for group in same:
                parts = [
                    f"{SHORT_NAMES.get(k, k)}={override_text(group.first.config.get(k))}"
                    for k in keys
                    if main[k] is None or repr(group.first.config.get(k)) != main[k]
                ] + [
                    f"{SHORT_NAMES.get(k, k)}={override_text(group.first.config[k])}"
                    for k in shared
                ]
                group.label = algo_label(algo) + (f" ({', '.join(parts)})" if parts else "")


# Keys that say which rules or which network a run had, not which variant of its algorithm.
NOT_SWITCHES = {"algo.name", "policy.name", "algo.backtracking", "algo.backtrack_restore"}


def _switches_departed(groups: list[Group], algo: str) -> list[str]:
    """The algorithm's switches (``algo.*`` and ``policy.*`` keys whose own value is a word,
    true/false or null) in which every run of ``groups`` departs from conf/algo/<algo>.yaml."""
    defaults = algo_defaults(algo) or {}
    runs = [r for g in groups for r in g.runs]
    out = []
    for key, value in defaults.items():
        if key in NOT_SWITCHES or not key.startswith(("algo.", "policy.")):
            continue
        if value is not None and not isinstance(value, str | bool):
            continue
        if all(key in r.config and repr(r.config[key]) != repr(value) for r in runs):
            out.append(key)
    return out


def _main_value(groups: list[Group], key: str) -> str | None:
    """The repr of the value of ``key`` that most of these groups' runs share; None on a tie."""
    counts = Counter(repr(g.first.config.get(key)) for g in groups for _ in g.runs)
    (top, n), *rest = counts.most_common()
    return None if rest and rest[0][1] == n else top


def override_text(value) -> str:
    """A config value as it is written on the command line (``null``, ``true``), so that a
    label reads as the override that makes the group."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    return str(value)


def algo_label(algo: str) -> str:
    known = {**ALGORITHMS, SCRATCH.name: SCRATCH}
    return known[algo].label if algo in known else algo


def format_wind(wind: float) -> str:
    return "n/a" if not np.isfinite(wind) else f"{wind:g}"
