"""The numbers the report's figures draw, shaped apart from the drawing: the entropy bound of a
run, the groups of each wind, the final entropies against the wind, and the fine-tuning returns
as one frame and, per initialisation and configuration, as curves nested in their units.

summary.py's tables read the same frames, so that a figure and its table show one set of numbers.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np
import pandas as pd

from hmepol_cli.algorithms import SCRATCH
from hmepol_cli.report.runs import ALGO_ORDER, Group, Run
from hmepol_cli.report.stats import mean_ci


# ---------------------------------------------------------------------------------- entropy
def average_bound(run: Run) -> float:
    """Highest average entropy: sum_c p_M(c) log(free area of c), the uniform visitation."""
    logs, probs = np.array(run.log_free_area), np.array(run.configuration_probs)
    return float((logs * probs).sum() / probs.sum()) if np.isfinite(logs).all() else math.nan


def config_bound(run: Run, config: int | None) -> float:
    """Highest entropy in one configuration (None: the average over them, weighted by p_M)."""
    return average_bound(run) if config is None else run.log_free_area[config]


def winds_of(groups: list[Group]) -> list[float]:
    """The groups' winds in increasing order, a world without wind (NaN) first."""
    return sorted({g.wind for g in groups}, key=lambda w: np.nan_to_num(w, nan=-1.0))


def at_wind(groups: list[Group], wind: float) -> list[Group]:
    return [g for g in groups if g.wind == wind or (np.isnan(g.wind) and np.isnan(wind))]


def epochs_label(window: str) -> str:
    """ "epochs 450-499", or "epoch 8" for one."""
    return f"epoch {window}" if window.isdigit() else f"epochs {window}"


def final_windows(groups: list[Group], winds: list[float]) -> dict[float, str] | None:
    """The epochs each wind's final values average ("450-499"; several joined by ", "), or None
    when every wind averages the same ones. They differ where ``--unfinished`` cut a wind still
    running, and a figure that puts the winds on one axis must say so."""
    windows = {
        w: ", ".join(dict.fromkeys(g.final_epochs() for g in at_wind(groups, w))) for w in winds
    }
    if len(set(windows.values())) == 1:
        return None
    return {w: re.sub(r"\b(\d+)-\1\b", r"\1", text) for w, text in windows.items()}  # "8-8": "8"


@dataclass(frozen=True)
class WindFinals:
    """The final average entropy of one series at each of its winds, in increasing wind."""

    wind: np.ndarray  # (n_winds,)
    mean: np.ndarray  # (n_winds,): mean over seeds
    half_width: np.ndarray  # (n_winds,): of the Student-t 95% interval (NaN under 2 seeds)
    n: np.ndarray  # (n_winds,): seeds


def wind_finals(groups: list[Group], label: str) -> WindFinals:
    """The groups labelled ``label`` (one per wind) as :class:`WindFinals`."""
    members = [g for g in groups if g.label == label]
    cis = [mean_ci(list(g.finals().values())) for g in members]
    winds = np.array([g.wind for g in members], dtype=float)
    order = np.argsort(winds)
    return WindFinals(
        winds[order],
        np.array([ci.mean for ci in cis], dtype=float)[order],
        np.array([ci.half_width for ci in cis], dtype=float)[order],
        np.array([ci.n for ci in cis], dtype=int)[order],
    )


# ------------------------------------------------------------------------------- fine-tuning
def finetune_frame(runs: list[Run]) -> pd.DataFrame:
    """All fine-tuning returns, one row per (run, seed, target, config, epoch), with the
    independent unit of each (the pre-training run, or the fine-tuning run from scratch) and the
    bounds of its return."""
    frames = []
    for run in runs:
        if run.finetune is None:
            continue
        frame = run.finetune.copy()
        frame["env"] = run.env
        frame["wind"] = run.wind
        frame["run"] = str(run.path)
        frame["pretraining_run"] = run.pretraining_run
        frame["pairing_seed"] = run.pairing_seed
        frame["unit"] = run.independent_unit
        frame["bound_low"], frame["bound_high"] = run.return_bounds
        frames.append(frame)
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def finetune_winds(frame: pd.DataFrame) -> list[tuple[float | None, pd.DataFrame]]:
    """The rows of each wind, in increasing wind; worlds without a wind (slope, multigrid)
    record none (NaN): their rows come last, as wind None."""
    winds = sorted(frame["wind"].dropna().unique())
    parts = [(wind, frame[frame["wind"] == wind]) for wind in winds]
    if frame["wind"].isna().any():
        parts.append((None, frame[frame["wind"].isna()]))
    return parts


def return_range(part: pd.DataFrame) -> tuple[float, float]:
    """The range every run's return can take together (-inf, inf: a world's own reward)."""
    return part["bound_low"].min(), part["bound_high"].max()


@dataclass(frozen=True)
class FinetuneCurves:
    """The return curves of one initialisation in one configuration."""

    epochs: np.ndarray  # (n_epochs,)
    curves: np.ndarray  # (n_curves, n_epochs): one per (run, seed, target)
    units: np.ndarray  # (n_curves,): the independent unit each curve is nested in
    bounds: tuple[float, float]  # of a return: every run's range together

    def unit_curves(self) -> np.ndarray:
        """Each unit's mean curve over its targets and seeds, (n_units, n_epochs)."""
        frame = pd.DataFrame(self.curves)
        return frame.groupby(self.units, sort=False).mean().to_numpy(float)


def finetune_curves(frame: pd.DataFrame) -> dict[tuple[str, int], FinetuneCurves]:
    """(algo_init, config) -> its curves."""
    out = {}
    for (init, config), part in frame.groupby(["algo_init", "config"], sort=False):
        table = part.pivot_table(
            index="epoch", columns=["unit", "run", "seed", "target"], values="return"
        )
        out[(str(init), int(config))] = FinetuneCurves(
            table.index.to_numpy(float),
            table.to_numpy(float).T,
            table.columns.get_level_values("unit").to_numpy(),
            (float(part["bound_low"].min()), float(part["bound_high"].max())),
        )
    return out


def ordered_inits(curves: dict[tuple[str, int], FinetuneCurves]) -> list[str]:
    """The initialisations of ``curves`` in algorithm order, from scratch last (others after)."""
    order = [*ALGO_ORDER, SCRATCH.name]
    return sorted({i for i, _ in curves}, key=lambda i: (order.index(i) if i in order else 9, i))
