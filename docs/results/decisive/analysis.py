"""The pre-registered analysis of the decisive experiment (PREREGISTRATION.md, sections 3-5),
from the small files kept beside this script:

    python docs/results/decisive/analysis.py            # markdown to stdout
    python docs/results/decisive/analysis.py --out docs/results/decisive/analysis.md
    python docs/results/decisive/analysis.py --results RESULTS.md   # its tables, between markers
    python docs/results/decisive/analysis.py --figures docs/results/decisive/figures  # the curves

Corridor: per run M_c = mean of entropy_c<c> over epochs 450-499 and M = (M_0 + M_1) / 2; paired
by seed, HMepol (exact trust region) - Mepol, the 95% Student-t interval and the exact sign-flip
p-value. The answer is *final* only once every pre-registered seed (0-7) of both arms is complete
(500 epochs, or ended early by the algorithm: ``status: failed``, whose metric is then the mean
over its last 50 recorded epochs, reported with and without its pair). Before that the same
numbers are *interim*: over the seeds complete in both arms ("interim (n = 4)" once stage 1 is
done), or, while none is, over the last 50 epochs that every run of the comparison has.
Descriptive: drops (a fall of more than 1 nat in one configuration's entropy from one epoch to
the next, from epoch 30) per arm, and a provenance check of every run (the pre-registered
commit, the faithful rules, float32 on one CPU thread, first row after the pre-registration).
Multigrid: the final entropy as ``hmepol report`` computes it (mean over the last 10% of the
epochs, the epochs without the configuration skipped), average and configuration 0.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import subprocess
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pandas as pd
import yaml
from scipy import stats

HERE = Path(__file__).resolve().parent
BEGIN, END = "<!-- decisive tables: begin -->", "<!-- decisive tables: end -->"
EPOCHS, WINDOW, HALF_WIDTH = 500, 50, 0.3
PRIMARY_SEEDS = tuple(range(8))  # PREREGISTRATION.md section 2: seeds 0-7 (the CPU set)
STAGES = (tuple(range(4)), tuple(range(4, 8)))  # section 2: stage 1, then stage 2
DROP_NATS, DROP_FROM = 1.0, 30  # section 4: a fall of more than 1 nat, from epoch 30
ARMS = {"A": "mepol", "B": "exact", "C": "hmepol"}
NAMES = {"A": "Mepol", "B": "HMepol, exact trust region", "C": "HMepol, one-step (thesis)"}
COMPARISONS = (("B", "A"), ("C", "A"), ("B", "C"))  # (b, a): b - a; B - A is the primary one
# What every run must have been made with (section 2), as config.yaml spells it.
RULES = {("env", "edge"): "slide", ("algo", "backtracking"): "reference",
         ("algo", "backtrack_restore"): "parameters", ("precision",): "float32",
         ("device",): "cpu", ("threads",): 1}  # fmt: skip


@dataclass
class Run:
    """One run directory's small files."""

    name: str
    info: dict
    epochs: pd.DataFrame
    config: dict

    @property
    def seed(self) -> int:
        return int(self.info.get("seed", seed_of(self.name)))

    @property
    def failed(self) -> bool:
        """Ended early by the algorithm itself (non-finite values): its place is kept."""
        return self.info.get("status") == "failed"

    @property
    def done(self) -> int:
        return len(self.epochs)

    def complete(self, epochs: int = EPOCHS) -> bool:
        return self.done >= epochs or self.failed


def runs(folder: Path) -> dict[str, Run]:
    """{run name: Run} of every run in a folder, by name."""
    out = {}
    for table in sorted(folder.glob("*/epochs.csv")):
        config = table.parent / "config.yaml"
        out[table.parent.name] = Run(
            table.parent.name,
            json.loads((table.parent / "run.json").read_text()),
            pd.read_csv(table),
            yaml.safe_load(config.read_text()) if config.exists() else {},
        )
    return out


def seed_of(name: str) -> int:
    return int(name.rsplit("seed-", 1)[1].split("_")[0])


def corridor_metric(epochs: pd.DataFrame, first: int, last: int) -> tuple[float, float, float]:
    """(M, M_0, M_1) over epochs first..last."""
    rows = epochs[(epochs.epoch >= first) & (epochs.epoch <= last)]
    m0, m1 = float(rows.entropy_c0.mean()), float(rows.entropy_c1.mean())
    return (m0 + m1) / 2, m0, m1


def run_metric(run: Run, last: int) -> tuple[float, float, float]:
    """(M, M_0, M_1) over the WINDOW epochs ending at ``last``; a failed run that stopped
    before ``last``: over its last WINDOW recorded epochs (section 2)."""
    end = min(last, int(run.epochs.epoch.max())) if run.failed else last
    return corridor_metric(run.epochs, end - WINDOW + 1, end)


def paired(d: np.ndarray) -> dict[str, float]:
    """Mean, 95% t-interval, exact sign-flip p-value and the seeds a +-0.3 half-width needs."""
    n = len(d)
    mean = float(d.mean()) if n else math.nan
    if n < 2:
        return {"n": n, "mean": mean, "low": math.nan, "high": math.nan, "p": math.nan,
                "seeds_for_0.3": math.nan}  # fmt: skip
    sd = float(d.std(ddof=1))
    half = stats.t.ppf(0.975, n - 1) * sd / math.sqrt(n)
    flips = np.array(list(itertools.product((-1, 1), repeat=n)))
    p = float((np.abs((flips * np.abs(d)).mean(1)) >= abs(mean) - 1e-12).mean())
    need = next(k for k in range(2, 10_000) if stats.t.ppf(0.975, k - 1) * sd / math.sqrt(k)
                <= HALF_WIDTH)  # fmt: skip
    return {"n": n, "mean": mean, "low": mean - half, "high": mean + half, "p": p,
            "seeds_for_0.3": need}  # fmt: skip


def verdict(r: dict[str, float], final: bool) -> str:
    if not final:
        return "interim: not an answer"
    if r["low"] > 0:
        return "ends above"
    if r["high"] < 0:
        return "ends below"
    return f"not resolved at n = {r['n']} (a +-0.3 half-width needs {r['seeds_for_0.3']} seeds)"


@dataclass
class Window:
    """Which seeds a comparison uses, and over which epochs."""

    seeds: list[int]
    last: int  # the window's last epoch (a failed run's own last epoch if earlier)
    final: bool
    label: str


def window(by_seed: dict[str, dict[int, Run]], a: str, b: str) -> Window | None:
    """Section 4: final once every pre-registered seed is complete in both arms; else interim
    over the seeds complete in both (n = 4 after stage 1), or, while none is, over the last
    WINDOW epochs that every run of the seeds common to both arms has."""
    common = sorted(set(by_seed[a]) & set(by_seed[b]))
    complete = [s for s in common if by_seed[a][s].complete() and by_seed[b][s].complete()]
    if complete:
        final = set(PRIMARY_SEEDS) <= set(complete)
        label = "final" if final else f"interim (n = {len(complete)})"
        return Window(
            complete, EPOCHS - 1, final, f"{label}, epochs {EPOCHS - WINDOW}-{EPOCHS - 1}"
        )
    if not common:
        return None
    last = min(by_seed[arm][s].done for arm in (a, b) for s in common) - 1
    if last + 1 < WINDOW:
        return None
    return Window(common, last, False, f"interim (epochs {last - WINDOW + 1}-{last} of {EPOCHS})")


def comparison(lines: list[str], by_seed: dict[str, dict[int, Run]], a: str, b: str) -> None:
    w = window(by_seed, a, b)
    if w is None:
        return
    values = {arm: np.array([run_metric(by_seed[arm][s], w.last) for s in w.seeds])
              for arm in (a, b)}  # fmt: skip
    failed = [s for s in w.seeds if by_seed[a][s].failed or by_seed[b][s].failed]
    lines += [f"#### {NAMES[b]} - {NAMES[a]}: {w.label}, seeds {w.seeds}", "",
              f"| metric | {NAMES[a]} | {NAMES[b]} | difference [95% t-interval] | "
              "sign-flip p | answer |", "|---|---|---|---|---|---|"]  # fmt: skip
    primary = (b, a) == COMPARISONS[0]
    metrics = ("M (both configurations)", "M_0 (clockwise)", "M_1 (counterclockwise)")
    for j, metric in enumerate(metrics):
        r = paired(values[b][:, j] - values[a][:, j])
        answer = verdict(r, w.final) if j == 0 and primary else "secondary"
        if not w.final and answer == "secondary":
            answer = "secondary, interim"
        lines.append(
            f"| {metric} | {values[a][:, j].mean():.3f} | {values[b][:, j].mean():.3f} | "
            f"{r['mean']:+.3f} [{r['low']:+.3f}, {r['high']:+.3f}] | {r['p']:.3g} | {answer} |"
        )
    if failed:
        keep = np.array([s not in failed for s in w.seeds])
        r = paired(values[b][keep, 0] - values[a][keep, 0])
        lines.append(
            f"| M without the pairs of seeds {failed} (a run ended early) | "
            f"{values[a][keep, 0].mean():.3f} | {values[b][keep, 0].mean():.3f} | "
            f"{r['mean']:+.3f} [{r['low']:+.3f}, {r['high']:+.3f}] | {r['p']:.3g} | secondary |"
        )
    if len(w.seeds) >= 2:
        welch = stats.ttest_ind(values[b][:, 0], values[a][:, 0], equal_var=False)
        ci = welch.confidence_interval(0.95)
        lines += ["", f"Welch (unpaired) on M: [{ci.low:+.3f}, {ci.high:+.3f}]."]
    lines.append("")


def drops(run: Run) -> dict[int, int]:
    """{configuration: falls of more than DROP_NATS from one epoch to the next, from DROP_FROM}."""
    t = run.epochs.set_index("epoch").sort_index()
    out = {}
    for c in (0, 1):
        fall = t[f"entropy_c{c}"].diff()
        out[c] = int(((fall < -DROP_NATS) & (t.index >= DROP_FROM)).sum())
    return out


def drops_table(lines: list[str], by_seed: dict[str, dict[int, Run]]) -> None:
    lines += ["Drops (descriptive; section 4): falls of more than 1 nat in one configuration's "
              "entropy from one epoch to the next, from epoch 30, over the epochs each run has.",
              "", "| arm | seed-epochs | drops clockwise / counterclockwise | runs with a drop |",
              "|---|---|---|---|"]  # fmt: skip
    for arm, rs in by_seed.items():
        past = [r for r in rs.values() if r.done > DROP_FROM]  # runs that can have a drop
        counts = [drops(r) for r in past]
        epochs = sum(r.done - DROP_FROM for r in past)
        lines.append(f"| {arm}: {NAMES[arm]} | {epochs} | {sum(c[0] for c in counts)} / "
                     f"{sum(c[1] for c in counts)} | {sum(1 for c in counts if c[0] + c[1])} of "
                     f"{len(counts)} past epoch {DROP_FROM} |")  # fmt: skip
    lines.append("")


def preregistration(root: Path) -> tuple[str, int] | None:
    """(commit, commit time) of the commit that added PREREGISTRATION.md, from git; None without
    the history (no git, or a shallow clone, where that commit may be missing)."""

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True,
                              check=True).stdout.strip()  # fmt: skip

    try:
        if git("rev-parse", "--is-shallow-repository") != "false":
            return None
        out = git("log", "--diff-filter=A", "--format=%H %ct", "--", "PREREGISTRATION.md").split()
    except (OSError, subprocess.CalledProcessError):
        return None
    return (out[-2], int(out[-1])) if len(out) >= 2 else None


def provenance(lines: list[str], every: list[Run], registered: tuple[str, int] | None) -> None:
    """Section 2's conditions, checked on every run; each departure named."""
    if not every:
        return
    bad = []
    for r in every:
        commit = r.info.get("provenance", {}).get("git_commit")
        if registered and commit != registered[0]:
            bad.append(f"{r.name}: commit {commit}, not {registered[0][:7]}")
        for path, want in RULES.items():
            got = r.config
            for key in path:
                got = got.get(key) if isinstance(got, dict) else None
            if got != want:
                bad.append(f"{r.name}: {'.'.join(path)}={got}, not {want}")
        if registered and "wall_time" in r.epochs and len(r.epochs):
            first = float(r.epochs.wall_time.min())
            if first <= registered[1]:
                bad.append(
                    f"{r.name}: a row written at {stamp(first)}, before the "
                    f"pre-registration ({stamp(registered[1])})"
                )
    if bad:
        lines += ["**Provenance: departures from PREREGISTRATION.md section 2:**", ""]
        lines += [f"- {b}" for b in bad] + [""]
        return
    rules = ", ".join(f"{'.'.join(k)}={v}" for k, v in RULES.items())
    text = f"Provenance: all {len(every)} runs were made with {rules}"
    if registered:
        first = min(float(r.epochs.wall_time.min()) for r in every if len(r.epochs))
        text += (
            f", at commit {registered[0][:7]} (the one that added PREREGISTRATION.md, "
            f"{stamp(registered[1])}); their first epoch row was written at {stamp(first)}"
        )
    lines += [text + ".", ""]


def stamp(seconds: float) -> str:
    return datetime.fromtimestamp(seconds, timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")


def corridor(lines: list[str], root: Path = HERE) -> list[Run]:
    arms = {a: runs(root / folder) for a, folder in ARMS.items() if (root / folder).is_dir()}
    by_seed = {a: {r.seed: r for r in rs.values()} for a, rs in arms.items() if rs}
    lines += ["### Corridor, wind 0.4 (PREREGISTRATION.md sections 3-4)", "",
              "| arm | seeds | epochs done per seed | status |", "|---|---|---|---|"]  # fmt: skip
    for a, rs in by_seed.items():
        done = ", ".join(f"{s}: {r.done}" for s, r in sorted(rs.items()))
        status = sorted({r.info["status"] for r in rs.values()})
        lines.append(f"| {a}: {NAMES[a]} | {len(rs)} of {len(PRIMARY_SEEDS)} | {done} | "
                     f"{', '.join(status)} |")  # fmt: skip
    lines.append("")
    for b, a in COMPARISONS:
        if a in by_seed and b in by_seed:
            comparison(lines, by_seed, a, b)
    if by_seed:
        drops_table(lines, by_seed)
    return [r for rs in by_seed.values() for r in rs.values()]


def final_value(values: np.ndarray) -> float:
    x = values[np.isfinite(values)]
    return float(x[-max(1, math.ceil(0.1 * x.size)) :].mean()) if x.size else math.nan


def early(table: pd.DataFrame, epochs: int) -> pd.DataFrame:
    return table[table.epoch < epochs]


def multigrid(lines: list[str], root: Path = HERE) -> list[Run]:
    folder = root / "multigrid"
    if not folder.is_dir():
        return []
    rs = runs(folder)
    by: dict[str, dict[int, Run]] = {"alphamepol": {}, "hmepol": {}}
    for r in rs.values():
        by[r.info["algo"]][r.seed] = r
    lines += ["### Multigrid, quick preset (PREREGISTRATION.md section 5)", ""]
    done = {a: [r.done for r in v.values()] for a, v in by.items()}
    lines.append("Epochs done: " + "; ".join(f"{a} {min(d)}-{max(d)}" for a, d in done.items()
                                            if d) + ".")  # fmt: skip
    lines.append("")
    common = sorted(set(by["alphamepol"]) & set(by["hmepol"]))
    if not common:
        return list(rs.values())
    final = all(r.info["status"] in ("finished", "failed") for v in by.values()
                for r in v.values())  # fmt: skip
    upto = min(min(d) for d in done.values())  # interim: both arms over the same epochs
    if not final:
        lines += [f"Interim, both arms over their first {upto} epochs:", ""]
    lines += ["| metric | alpha-Mepol | HMepol | HMepol - alpha-Mepol [95% t-interval] | answer |",
              "|---|---|---|---|---|"]  # fmt: skip
    finals = {}
    for column, metric in (("entropy", "average"), ("entropy_c0", "configuration 0")):
        a, b = finals[column] = tuple(
            np.array([final_value(early(by[algo][s].epochs, upto)[column].to_numpy(float))
                      for s in common])
            for algo in ("alphamepol", "hmepol")
        )  # fmt: skip
        r = paired(b - a)
        answer = verdict(r, final).replace("ends ", "")
        lines.append(f"| {metric} | {a.mean():.3f} | {b.mean():.3f} | {r['mean']:+.3f} "
                     f"[{r['low']:+.3f}, {r['high']:+.3f}] | {answer} |")  # fmt: skip
    lines += ["", "Per seed (descriptive): final entropies, and the epochs in which the run's "
              "divergence alarm fired (`diverged`: history or action beyond the alarm bounds).",
              "", "| seed | average: alpha-Mepol / HMepol | configuration 0: alpha-Mepol / HMepol "
              "| HMepol epochs diverged |", "|---|---|---|---|"]  # fmt: skip
    for i, s in enumerate(common):
        table = early(by["hmepol"][s].epochs, upto)
        flags = table.get("diverged", pd.Series(False, index=table.index)).astype(bool)
        diverged = table.epoch[flags]
        when = f"{len(diverged)} (from epoch {int(diverged.min())})" if len(diverged) else "0"
        (a, b), (a0, b0) = finals["entropy"], finals["entropy_c0"]
        lines.append(f"| {s} | {a[i]:.3f} / {b[i]:.3f} | {a0[i]:.3f} / {b0[i]:.3f} | {when} |")
    lines.append("")
    return list(rs.values())


def report(root: Path = HERE, registered: tuple[str, int] | None = None) -> str:
    """The markdown of sections 3-5 from the run folders under ``root``."""
    lines: list[str] = []
    every = corridor(lines, root)
    every += multigrid(lines, root)
    provenance(lines, every, registered)
    return "\n".join(lines).strip() + "\n"


COLOURS = {"A": "#1f77b4", "B": "#9467bd", "C": "#2ca02c", "alphamepol": "#d62728",
           "hmepol": "#2ca02c"}  # fmt: skip
MULTIGRID_NAMES = {"alphamepol": "alpha-Mepol", "hmepol": "HMepol"}
BOUND = {"color": "0.3", "ls": "--", "lw": 1}


def mean_groups(by_seed: dict[int, pd.DataFrame]) -> list[list[int]]:
    """The seeds each thick mean is over: all of them once they have the same epochs done;
    while stage 2 runs, one mean per stage (section 2: seeds 0-3, then 4-7), so that the
    finished stage's mean is not cut to the epochs the new one has."""
    if len({len(t) for t in by_seed.values()}) == 1:
        return [sorted(by_seed)]
    groups = [[s for s in sorted(by_seed) if s in stage] for stage in STAGES]
    rest = [s for s in sorted(by_seed) if not any(s in stage for stage in STAGES)]
    return [g for g in (*groups, rest) if g]


def draw_arms(ax, arms: dict[str, dict[int, pd.DataFrame]], column: str, names: dict[str, str],
              colours: dict[str, str]) -> list[str]:  # fmt: skip
    """Each seed's curve (thin) and the mean over the arm's seeds (thick) over the epochs every
    seed of the group has (mean_groups: one group, or one per stage while stage 2 runs, the
    later stage dashed); returns "<arm> <epochs done>" for the title."""
    notes = []
    for arm, by_seed in arms.items():
        if not by_seed:
            continue
        for t in by_seed.values():  # a dot on each epoch where the column has gaps
            ax.plot(t.epoch, t[column], color=colours[arm], lw=0.7, alpha=0.35,
                    marker="." if t[column].isna().any() else None, ms=3)  # fmt: skip
        groups = mean_groups(by_seed)
        for i, seeds in enumerate(groups):
            done = min(len(by_seed[s]) for s in seeds)
            table = pd.concat({s: by_seed[s].set_index("epoch")[column] for s in seeds}, axis=1)
            mean = table.loc[: done - 1].mean(axis=1)  # epochs without the column (NaN) skipped
            which = f"seeds {seeds[0]}-{seeds[-1]}, " if len(groups) > 1 else ""
            ax.plot(mean.index, mean.to_numpy(), color=colours[arm], lw=2,
                    ls="--" if i else "-",
                    label=f"{names[arm]} ({which}n={len(seeds)}; epochs 0-{done - 1})")  # fmt: skip
        notes.append(f"{names[arm]} " + "/".join(
            str(min(len(by_seed[s]) for s in seeds)) for seeds in groups))  # fmt: skip
    return notes


def xlimit(arms: dict[str, dict[int, pd.DataFrame]], epochs: int, final: bool) -> tuple[int, int]:
    """The whole run when final; interim, the epochs done so far (with a margin)."""
    done = max(len(t) for by_seed in arms.values() for t in by_seed.values())
    return (0, epochs if final else min(epochs, math.ceil(done * 1.1) + 1))


def draw_panels(axes, panels, arms, names: dict[str, str], epochs: int, final: bool) -> list[str]:
    """One panel per (column, title, bound line); -> the arms' notes (epochs done)."""
    for ax, (column, title, bound) in zip(axes, panels, strict=True):
        notes = draw_arms(ax, arms, column, names, COLOURS)
        ax.axhline(bound, label=f"log(free area) = {bound:.2f} nats", **BOUND)
        ax.set(title=title, xlabel="epoch", xlim=xlimit(arms, epochs, final))
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("kNN entropy (nats, k = 30)")
    axes[0].legend(loc="lower right", fontsize=8)
    return notes


def save_figure(fig, path: Path, caption: str) -> Path:
    fig.text(0.5, 0.005, caption, ha="center", va="bottom", fontsize=7.5, wrap=True)
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    fig.savefig(path, dpi=110)
    return path


def corridor_state(found: dict[str, dict[str, Run]]) -> str:
    """The corridor figure's state: "final" once every arm has its pre-registered seeds
    complete; "A and B final, C INTERIM" once the primary comparison's two arms have (arm C,
    secondary, may run on); else "INTERIM"."""

    def done(arm: str) -> bool:
        by_seed = {r.seed: r for r in found.get(arm, {}).values()}
        return set(PRIMARY_SEEDS) <= set(by_seed) and all(r.complete() for r in by_seed.values())

    if all(done(arm) for arm in found):
        return "final"
    primary = set(COMPARISONS[0])
    if all(done(arm) for arm in primary):
        later = sorted(set(found) - primary)
        return f"{' and '.join(sorted(primary))} final, {', '.join(later)} INTERIM"
    return "INTERIM"


def figures(out: Path, root: Path = HERE) -> list[Path]:
    """The pre-registered descriptive curves (PREREGISTRATION.md section 4), drawn interim too:
    per arm each seed's curve and the mean over seeds (n = 4 or 8: no band)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    written = []
    found = {a: runs(root / folder) for a, folder in ARMS.items() if (root / folder).is_dir()}
    found = {a: rs for a, rs in found.items() if rs}
    if found:
        arms = {a: {r.seed: r.epochs.assign(m=(r.epochs.entropy_c0 + r.epochs.entropy_c1) / 2)
                    for r in rs.values()} for a, rs in found.items()}  # fmt: skip
        every = [r for rs in found.values() for r in rs.values()]
        bound = every[0].info["log_free_area"][0]
        state = corridor_state(found)
        final = state == "final"
        panels = (("m", "(clockwise + counterclockwise) / 2"),
                  ("entropy_c0", "configuration 0: clockwise"),
                  ("entropy_c1", "configuration 1: counterclockwise"))  # fmt: skip
        fig, axes = plt.subplots(1, 3, figsize=(13, 4.2), sharey=True)
        panels = [(column, title, bound) for column, title in panels]
        notes = draw_panels(axes, panels, arms, NAMES, EPOCHS, final)
        fig.suptitle(f"Decisive experiment, corridor wind 0.4 ({state})\n"
                     f"epochs done of {EPOCHS}: {', '.join(notes)}")  # fmt: skip
        written.append(save_figure(fig, out / "corridor.png",
            "Thick: mean over seeds, over the epochs every one of them has (while stage 2 runs, "
            "one mean per stage, seeds 4-7 dashed); thin: each seed. "
            "No interval drawn. Faithful rules (env.edge=slide, algo.backtracking=reference), "
            "N = 100 x 400 per epoch, commit a95e183. Descriptive (PREREGISTRATION.md section 4): "
            "the answer is the table in RESULTS.md."))  # fmt: skip
        plt.close(fig)
    rs = runs(root / "multigrid") if (root / "multigrid").is_dir() else {}
    if rs:
        by: dict[str, dict[int, pd.DataFrame]] = {"alphamepol": {}, "hmepol": {}}
        for r in rs.values():
            by[r.info["algo"]][r.seed] = r.epochs
        info = next(iter(rs.values())).info
        final = all(r.info["status"] in ("finished", "failed") for r in rs.values())
        epochs = info["epochs"]
        panels = (("entropy", "average over the drawn configurations",
                   float(np.mean(info["log_free_area"]))),
                  ("entropy_c0", f"configuration 0: {info['config_names'][0]}",
                   info["log_free_area"][0]))  # fmt: skip
        fig, axes = plt.subplots(1, 2, figsize=(10, 4.2))
        notes = draw_panels(axes, panels, by, MULTIGRID_NAMES, epochs, final)
        state = "final" if final else "INTERIM"
        fig.suptitle(f"Decisive experiment, multigrid quick preset ({state}; epochs done of "
                     f"{epochs}: {', '.join(notes)})")  # fmt: skip
        written.append(save_figure(fig, out / "multigrid.png",
            "Thick: mean over seeds; thin: each seed; no interval drawn. Configuration 0: only the "
            "epochs that drew it (the mean is over the seeds that did). Faithful rules, "
            "40 trajectories x 400 steps per epoch, commit a95e183."))  # fmt: skip
        plt.close(fig)
    return written


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path)
    parser.add_argument("--results", type=Path, help="a file whose tables between the markers "
                        f"{BEGIN} and {END} are replaced")  # fmt: skip
    parser.add_argument("--figures", type=Path, help="a folder for the curves per arm "
                        "(corridor.png, multigrid.png)")  # fmt: skip
    args = parser.parse_args(argv)
    text = report(HERE, preregistration(HERE))
    if args.out:
        args.out.write_text("# The decisive experiment: analysis as pre-registered\n\n" + text)
    if args.results:
        old = args.results.read_text()
        head, rest = old.split(BEGIN, 1)
        tail = rest.split(END, 1)[1]
        args.results.write_text(f"{head}{BEGIN}\n{text}{END}{tail}")
    if args.figures:
        figures(args.figures)
    print(text)


if __name__ == "__main__":
    main()
