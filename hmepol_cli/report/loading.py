"""Find run directories and load what the trainer wrote, as :class:`~hmepol_cli.report.runs.Run`s.

A run directory is any directory holding ``run.json`` (:mod:`hmepol_cli.run` is the
contract): config.yaml, run.json (status, epochs_done, env, algo, policy, seed, wind, config
names/probs, free areas, the edge and backtracking rules, the world's map, a fine-tuning's return
bounds), epochs.csv, batches.csv (which configurations an epoch drew, where its
entropy_c<c> must be a number), eval/final.npz (the final positions, for maps; a run kept
without them is still used for every curve and table) and, for fine-tuning runs, finetune.csv.

Runs that cannot be used (unfinished, missing or corrupt files, a row cut short or not a number)
are skipped with a warning and listed, with the reason, in the report; the rest of the report is
still built.
"""

from __future__ import annotations

import json
import re
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from hmepol_cli.errors import TableError
from hmepol_cli.plots import WorldMap
from hmepol_cli.report.defaults import schema_defaults
from hmepol_cli.report.rules import saved_rules
from hmepol_cli.report.runs import MapUnknownWarning, Run, SkippedRun, SkippedRunWarning
from hmepol_cli.run import (
    BATCHES_CSV,
    CONFIG,
    EPOCHS_CSV,
    EVAL_DIR,
    FINAL_EVAL,
    FINETUNE_CSV,
    RUN_INFO,
    flat_config,
    load_positions,
)
from hmepol_cli.run import read_table as run_read_table

REQUIRED_EPOCH_COLUMNS = ("epoch", "entropy")
REQUIRED_FINETUNE_COLUMNS = ("epoch", "target", "config", "return", "algo_init", "seed")
# The columns the report reads as numbers: a field that is not one makes the run unusable.
NUMERIC_EPOCH_COLUMNS = re.compile(r"epoch|entropy(_c\d+)?")
NUMERIC_FINETUNE_COLUMNS = re.compile(r"epoch|config|return|seed")
CONFIG_ENTROPY = re.compile(r"entropy_c(\d+)")  # entropy in configuration c (group 1)


class RunError(Exception):
    """Why one run directory cannot be used (one line)."""


def load_config(path: Path) -> dict[str, Any]:
    """Flattened ``.hydra/config.yaml``; interpolations are resolved where they can be."""
    from omegaconf import OmegaConf

    cfg = OmegaConf.load(path)
    try:
        container = OmegaConf.to_container(cfg, resolve=True)
    except Exception:
        # e.g. ${hydra:...} needs a running Hydra app: keep those values as written.
        container = OmegaConf.to_container(cfg, resolve=False)
    if not isinstance(container, dict):
        raise RunError(f"{path.name} is not a mapping")
    return flat_config(container)


def read_table(path: Path, required: tuple[str, ...], numeric: re.Pattern) -> pd.DataFrame:
    """A table the run wrote, read by the run package's one reader (:func:`hmepol_cli.run.
    read_table`); a table it cannot use makes the run one the report skips (RunError)."""
    try:
        return run_read_table(path, required, numeric)
    except TableError as err:
        raise RunError(str(err)) from None


def _require_finite(frame: pd.DataFrame, columns: tuple[str, ...], name: str) -> None:
    for column in columns:
        values = frame[column].to_numpy(float)
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            line = frame.index[bad[0]]
            raise RunError(f"{name} line {line}: {column}={values[bad[0]]} is not a finite number")


def _drawn_configurations(path: Path) -> set[tuple[float, int]] | None:
    """(epoch, configuration) of every mini-batch in batches.csv; None when there is no file."""
    if not path.exists():
        return None
    batches = read_table(path, ("epoch", "config"), re.compile("epoch|config"))
    _require_finite(batches, ("epoch", "config"), path.name)
    return set(zip(batches["epoch"].astype(float), batches["config"].astype(int), strict=True))


def check_entropies(epochs: pd.DataFrame, drawn: set[tuple[float, int]] | None) -> None:
    """Raise :class:`RunError` naming the line of epochs.csv where an epoch or its entropy is
    not finite, or a configuration's entropy is not finite in an epoch that drew it.

    ``entropy_c<c>`` is empty (NaN) in an epoch that drew no mini-batch of configuration c.
    ``drawn`` holds the (epoch, configuration) pairs that were drawn (batches.csv); without it
    only an infinite ``entropy_c<c>`` is known to be wrong.
    """
    _require_finite(epochs, ("epoch", "entropy"), EPOCHS_CSV)
    epoch = epochs["epoch"].to_numpy(float)
    for column in epochs.columns:
        match = CONFIG_ENTROPY.fullmatch(column)
        if match is None:
            continue
        config = int(match[1])
        values = epochs[column].to_numpy(float)
        wrong = np.isinf(values)
        if drawn is not None:
            was_drawn = np.array([(e, config) in drawn for e in epoch])
            wrong |= np.isnan(values) & was_drawn
        bad = np.flatnonzero(wrong)
        if bad.size:
            i = bad[0]
            why = (
                f"in epoch {epoch[i]:g}, which drew configuration {config}"
                if np.isnan(values[i])
                else "is not a finite number"
            )
            raise RunError(f"{EPOCHS_CSV} line {epochs.index[i]}: {column}={values[i]} {why}")


def _read_positions(path: Path, n_configurations: int) -> dict[int, np.ndarray]:
    try:
        positions = load_positions(path)
    except Exception as err:  # numpy raises several errors for a damaged archive
        raise RunError(f"eval/final.npz is unreadable ({type(err).__name__})") from None
    if not positions:
        raise RunError("eval/final.npz holds no positions_c<c> arrays")
    for c, array in positions.items():
        if array.ndim != 3 or array.shape[-1] != 2:
            raise RunError(
                f"eval/final.npz positions_c{c} has shape {array.shape}, not (n, T+1, 2)"
            )
    if n_configurations and sorted(positions) != list(range(n_configurations)):
        raise RunError(
            f"eval/final.npz holds configurations {sorted(positions)}, "
            f"expected 0..{n_configurations - 1}"
        )
    return positions


def load_run(path: Path, unfinished: bool = False) -> Run:
    """Load one run directory; raise :class:`RunError` saying why it cannot be used.

    ``unfinished``: a pre-training run that stopped before its last epoch (interrupted, still
    running) is used with the epochs it wrote; otherwise it is refused."""
    path = Path(path)
    try:
        meta = json.loads((path / RUN_INFO).read_text())
    except (OSError, ValueError) as err:
        raise RunError(f"run.json is unreadable ({type(err).__name__})") from None
    if not isinstance(meta, dict):
        raise RunError("run.json is not a JSON object")
    status = meta.get("status")
    if status != "finished" and not (unfinished and (path / EPOCHS_CSV).is_file()):
        raise RunError(
            f"unfinished (status {status!r}, {meta.get('epochs_done', '?')} epochs done)"
        )
    # The run's own resolved copy first (runs before it existed: Hydra's .hydra/config.yaml).
    config_path = path / CONFIG
    if not config_path.is_file():
        config_path = path / ".hydra" / "config.yaml"
    if config_path.is_file():
        try:
            config = load_config(config_path)
        except RunError:
            raise
        except Exception as err:
            raise RunError(f"{config_path.name} is unreadable ({type(err).__name__})") from None
    else:  # fall back on what run.json says
        config = {
            "env.name": meta.get("env"),
            "algo.name": meta.get("algo"),
            "policy.name": meta.get("policy"),
            "seed": meta.get("seed"),
        }
    if isinstance(meta.get("epochs"), int):
        # A run continued with `resume=<run> epochs=N` keeps the config.yaml it started with;
        # run.json holds the epochs it was taken to.
        config = {**config, "epochs": meta["epochs"]}
    if not (path / FINETUNE_CSV).exists():
        # Keys added to the schema after a run was made take their defaults, so old and new runs
        # of the same settings group together; but the rules a run older than their keys ran
        # with are the ones run.json records (or their absence meant), not today's defaults.
        config = {**schema_defaults(), **config, **saved_rules(config, meta)}
    run = Run(path=path, config=config, meta=meta)
    try:
        WorldMap.from_json(meta.get("world_map"))  # a map that cannot be drawn: not usable
    except (KeyError, TypeError, ValueError) as err:
        raise RunError(f"run.json's world_map is not a map ({type(err).__name__})") from None
    if (path / FINETUNE_CSV).exists():
        # A fine-tuning run is reported only through its returns.
        run.finetune = read_table(
            path / FINETUNE_CSV, REQUIRED_FINETUNE_COLUMNS, NUMERIC_FINETUNE_COLUMNS
        )
        _require_finite(run.finetune, ("epoch",), FINETUNE_CSV)
        return run
    epochs = read_table(path / EPOCHS_CSV, REQUIRED_EPOCH_COLUMNS, NUMERIC_EPOCH_COLUMNS)
    check_entropies(epochs, _drawn_configurations(path / BATCHES_CSV))
    run.epochs = epochs.sort_values("epoch")
    final_eval = path / EVAL_DIR / f"{FINAL_EVAL}.npz"
    # An unfinished run has no final evaluation, and a kept run may leave it out (the export's
    # --no-positions): either is drawn in no map. One that is there must be whole.
    if final_eval.exists():
        run.positions = _read_positions(final_eval, run.n_configurations)
    return run


def discover_runs(root: Path, unfinished: bool = False) -> tuple[list[Run], list[SkippedRun]]:
    """Every run directory under ``root`` (any depth), loaded; the unusable ones with a reason.
    ``unfinished``: as in :func:`load_run`."""
    root = Path(root)
    runs: list[Run] = []
    skipped: list[SkippedRun] = []
    for marker in sorted(root.rglob(RUN_INFO)):
        try:
            runs.append(load_run(marker.parent, unfinished))
        except RunError as err:
            skipped.append(SkippedRun(marker.parent, str(err)))
            warnings.warn(f"skipping run {marker.parent}: {err}", SkippedRunWarning, stacklevel=2)
    unknown = [run.path for run in runs if run.is_pretraining and not run.records_map]
    if unknown:
        warnings.warn(
            f"{len(unknown)} run(s) (the first: {unknown[0]}) have a run.json that does not record "
            "their world's map (world_map): their maps are drawn without walls; "
            "tools/backfill_run_json.py adds it",
            MapUnknownWarning,
            stacklevel=2,
        )
    return runs, skipped
