"""Every number RESULTS.md states that is not a row of a report table, recomputed from the small
files kept in docs/results/ (epochs.csv, steps.csv.gz, finetune.csv):

    python docs/results/recompute.py            # prints them, section by section

The report tables (summary.csv, differences.csv, finetune.csv, drops.csv of each report folder)
are `make results`' own; this script checks and adds to them with the same definitions: a run's
final value is the mean over its last 10% of epochs, a window's value is the mean over its
epochs; intervals are Student-t over seeds (the unit of independence; paired by seed for a
difference); `seeds for +-0.3` is the smallest n with t_{0.975, n-1} sd / sqrt(n) <= 0.3 at the
observed sd of the paired differences (for returns, +-0.1 and +-0.2).
"""

from __future__ import annotations

import glob
import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats

HERE = Path(__file__).resolve().parent


def load(pattern: str) -> dict[int, pd.DataFrame]:
    """{seed: epochs.csv} of the run folders matching a pattern under docs/results."""
    out = {}
    for folder in sorted(glob.glob(str(HERE / pattern))):
        info = json.loads((Path(folder) / "run.json").read_text())
        out[info["seed"]] = pd.read_csv(Path(folder) / "epochs.csv")
    return out


def window(t: pd.DataFrame, first: int, last: int, column: str = "entropy") -> float:
    return float(t[(t.epoch >= first) & (t.epoch <= last)][column].mean())


def seeds_for(sd: float, half: float) -> int:
    return next(
        k for k in range(2, 100_000) if stats.t.ppf(0.975, k - 1) * sd / math.sqrt(k) <= half
    )


def interval(x, half: float = 0.3, bounds: tuple[float, float] | None = None, digits=2) -> str:
    x = np.asarray(x, float)
    n, m = len(x), float(x.mean())
    sd = float(x.std(ddof=1))
    h = stats.t.ppf(0.975, n - 1) * sd / math.sqrt(n)
    low, high = m - h, m + h
    if bounds:
        low, high = max(low, bounds[0]), min(high, bounds[1])
    f = f"+.{digits}f"
    return f"{m:{f}} [{low:{f}}, {high:{f}}] (n = {n}; seeds for +-{half}: {seeds_for(sd, half)})"


def last_accepted_ratio(folder: str) -> pd.Series:
    """Per epoch, the last accepted step's exact KL over its one-step KL (steps.csv.gz)."""
    steps = pd.read_csv(Path(folder) / "steps.csv.gz")
    last = steps[steps.accepted].groupby("epoch").tail(1).set_index("epoch")
    return last.kl_exact / last.kl_one_step


def falls(t: pd.DataFrame, threshold: float) -> list[tuple[str, int, float]]:
    """(configuration column, epoch, fall) of every fall above threshold, from epoch 30."""
    t = t.set_index("epoch")
    out = []
    for column in ("entropy_c0", "entropy_c1"):
        fall = -t[column].diff()
        out += [
            (column, int(e), float(f))
            for e, f in fall[(fall > threshold) & (fall.index >= 30)].items()
        ]
    return out


def section(title: str) -> None:
    print(f"\n## {title}")


def collapse() -> None:
    section("Collapse study, N = 100 (docs/results/collapse/n100-*; faithful rules)")
    names = ["gradient", "exact", "adam", "bptt-full", "mepol"]
    v = {name: load(f"collapse/n100-{name}/*") for name in names}
    for name in names:
        for first, last in (
            (0, 9),
            (30, 39),
            (40, 59),
            (60, 89),
            (90, 99),
            (90, 109),
            (110, 149),
            (180, 199),
        ):
            rows = [window(v[name][s], first, last) for s in (0, 1)]
            if np.isnan(rows).any():
                continue
            steps = [window(v[name][s], first, last, "off_iters") for s in (0, 1)]
            clip = [window(v[name][s], first, last, "clip_share") for s in (0, 1)]
            print(
                f"{name:9s} epochs {first:3d}-{last:3d}: entropy {rows[0]:.2f} / {rows[1]:.2f} "
                f"(mean {np.mean(rows):.2f}); off-policy steps {steps[0]:.1f} / {steps[1]:.1f}; "
                f"clip share {clip[0]:.2f} / {clip[1]:.2f}"
            )
        t = v[name][0]
        seconds = [window(t, a, b, "seconds") for a, b in ((0, 9), (0, 99), (150, 199))]
        hours = [float(v[name][s].seconds.sum() / 3600) for s in (0, 1)]
        print(
            f"{name:9s} seconds an epoch (seed 0's table): epochs 0-9 {seconds[0]:.1f}, "
            f"0-99 {seconds[1]:.1f}, 150-199 {seconds[2]:.1f}; hours of epoch time: "
            f"{hours[0]:.2f} / {hours[1]:.2f}; first 100 epochs "
            f"{t[t.epoch < 100].seconds.sum() / 3600:.2f} h"
        )
    logstd = pd.concat([t.log_std for name in names for t in v[name].values()])
    print(f"log-std over all five variants: {logstd.min():.3f} to {logstd.max():.3f}")
    print(
        f"epoch 0: clip share {v['gradient'][0].clip_share[0]:.3f}, largest raw action "
        f"{v['gradient'][0].action_max[0]:.3f}"
    )
    g1 = v["gradient"][1]
    print(
        "one-step seed 1, configuration 0 over epochs 90-109: "
        f"{window(g1, 90, 109, 'entropy_c0'):.2f} at a clip share of "
        f"{window(g1, 90, 109, 'clip_share'):.2f}"
    )
    for name in ("gradient", "exact", "adam", "bptt-full"):
        for s, folder in enumerate(sorted(glob.glob(str(HERE / f"collapse/n100-{name}/*")))):
            r = last_accepted_ratio(folder)
            print(
                f"{name:9s} seed {s}: median KL ratio, epochs 0-9 {r.loc[0:9].median():.2f}, "
                f"30-59 {r.loc[30:59].median():.1f}, 150-159 {r.loc[150:159].median():.1f}, "
                f"150-199 {r.loc[150:199].median():.1f}"
            )
            if name == "gradient":
                big = falls(v[name][s], 2.0)
                ratios = [r.get(e - 1, np.nan) for _, e, _ in big]
                print(
                    f"   falls > 2 nats: {len(big)}, KL ratio of the update before: "
                    f"{min(ratios):.0f} to {max(ratios):.0f}"
                )
    exact = v["exact"]
    print(
        "exact, off-policy steps an epoch over epochs 90-199:",
        [round(window(exact[s], 90, 199, "off_iters"), 1) for s in (0, 1)],
    )

    def w(name, first, last, column="entropy"):
        return np.array([window(v[name][s], first, last, column) for s in (0, 1)])

    print("paired over seeds 0 and 1 (n = 2):")
    for a, b, first, last in (
        ("gradient", "mepol", 40, 59),
        ("gradient", "mepol", 90, 109),
        ("adam", "mepol", 90, 109),
        ("bptt-full", "mepol", 90, 99),
        ("exact", "mepol", 180, 199),
        ("adam", "mepol", 180, 199),
        ("gradient", "mepol", 180, 199),
        ("exact", "gradient", 180, 199),
        ("adam", "gradient", 180, 199),
    ):
        print(
            f"  {a} - {b}, epochs {first}-{last}: {interval(w(a, first, last) - w(b, first, last))}"
        )
    means = [("adam", 90, 109), ("adam", 180, 199), ("mepol", 40, 59), ("mepol", 90, 99),
             ("mepol", 90, 109), ("mepol", 180, 199), ("exact", 40, 59), ("exact", 180, 199),
             ("gradient", 40, 59), ("gradient", 180, 199), ("bptt-full", 90, 99)]  # fmt: skip
    print("means over the two seeds: "
          + "; ".join(f"{n} {a}-{b} {w(n, a, b).mean():.2f}" for n, a, b in means))  # fmt: skip
    # per 10-epoch block: Adam reset - Mepol, mean over the two seeds
    gap = [float((w("adam", b, b + 9) - w("mepol", b, b + 9)).mean()) for b in range(0, 200, 10)]
    print("Adam reset - Mepol by 10-epoch blocks:", " ".join(f"{g:+.2f}" for g in gap))
    for name in ("gradient", "mepol"):
        for s in (0, 1):
            t = v[name][s].set_index("epoch")
            print(
                f"{name} seed {s} at the kept epochs 50 / 75 / 100: entropy "
                + " / ".join(f"{t.entropy[e]:.2f}" for e in (50, 75, 100))
                + "; counterclockwise "
                + " / ".join(f"{t.entropy_c1[e]:.2f}" for e in (50, 75, 100))
            )
    c0 = g1[(g1.epoch >= 80) & (g1.epoch <= 99)].entropy_c0
    print(
        f"one-step seed 1, clockwise over epochs 80-99: from {c0.iloc[0]:.2f} to {c0.min():.2f}, "
        f"mean {c0.mean():.2f}"
    )
    section("Collapse study, N = 20 (docs/results/collapse/n20-*; faithful rules)")
    for folder in sorted(glob.glob(str(HERE / "collapse/n20-gradient/*"))):
        info = json.loads((Path(folder) / "run.json").read_text())
        big = falls(pd.read_csv(Path(folder) / "epochs.csv"), 2.0)
        if big:
            r = last_accepted_ratio(folder)
            ratios = [r.get(e - 1, np.nan) for _, e, _ in big]
            print(
                f"one-step seed {info['seed']}: {len(big)} falls > 2 nats, KL ratios "
                f"{min(ratios):.0f}-{max(ratios):.0f}"
            )


def finetune() -> None:
    section("Fine-tuning (finetune.csv of each run; return in [0, 1]; unit: pre-training run)")
    for folder in ("full/finetune", "collapse/finetune-epoch75", "collapse/finetune-epoch100"):
        rows = []
        for run in sorted(glob.glob(str(HERE / folder / "*"))):
            t = pd.read_csv(Path(run) / "finetune.csv")
            rows.append(t.assign(run=Path(run).name, arm=Path(run).name.split("-")[0]))
        t = pd.concat(rows)
        unit = {
            arm: g[g.epoch >= 45].groupby("run")["return"].mean().to_numpy()
            for arm, g in t.groupby("arm")
        }
        curve = t.groupby(["arm", "epoch"])["return"].mean()
        for arm in ("hmepol", "mepol", "scratch"):
            first = t[(t.arm == arm) & (t.epoch == 0)].groupby("run").success_rate.mean().mean()
            print(
                f"{folder} {arm}: epochs 0 / 9 / 49 {curve[arm][0]:.2f} / {curve[arm][9]:.2f} / "
                f"{curve[arm][49]:.2f}; per run {np.round(unit[arm], 3)}; "
                f"{interval(unit[arm], 0.1, (0, 1), 3)}; first-epoch success {first:.2f}"
            )
        d = unit["hmepol"] - unit["mepol"]
        print(
            f"{folder} HMepol - Mepol, paired by pre-training seed: "
            f"{interval(d, 0.1, (-1, 1), 3)}; seeds for +-0.2: {seeds_for(d.std(ddof=1), 0.2)}"
        )
        if folder.endswith("75"):
            print("  mean curves, epochs 0-15:")
            for arm in ("hmepol", "mepol", "scratch"):
                print(f"  {arm:8s}", " ".join(f"{x:.2f}" for x in curve[arm][:16]))


def old_rules() -> None:
    section("Old rules, full scale corridor (docs/results/full/corridor)")
    h = load("full/corridor/experiment-corridor_hmepol_seed-*")
    m = load("full/corridor/experiment-corridor_mepol_seed-*")
    hm = pd.concat({s: t.set_index("epoch").entropy for s, t in h.items()}, axis=1).mean(axis=1)
    mm = pd.concat({s: t.set_index("epoch").entropy for s, t in m.items()}, axis=1).mean(axis=1)
    peak = int(hm.idxmax())
    print(
        f"HMepol mean peak: epoch {peak}, {hm[peak]:.2f}; Mepol there {mm[peak]:.2f}; Mepol first "
        f">= 3.6 at epoch {int(mm[mm >= 3.6].index[0])}; Mepol max {mm.max():.2f} at epoch "
        f"{int(mm.idxmax())}"
    )
    for first, last in ((40, 59), (90, 109)):
        for column in ("entropy_c0", "entropy_c1"):
            d = [window(h[s], first, last, column) - window(m[s], first, last, column) for s in h]
            print(f"HMepol - Mepol, epochs {first}-{last}, {column}: {interval(d)}")
    print(
        "final (epochs 450-499) per seed: HMepol",
        [round(window(h[s], 450, 499), 2) for s in sorted(h)],
        "Mepol",
        [round(window(m[s], 450, 499), 2) for s in sorted(m)],
    )
    print(
        f"off-policy steps an epoch: HMepol {pd.concat(h.values()).off_iters.mean():.1f}, Mepol "
        f"{pd.concat(m.values()).off_iters.mean():.1f}; HMepol max |h'| "
        f"{pd.concat(h.values()).history_max.max():.1f}; diverged epochs per HMepol seed "
        f"{[int(t.diverged.sum()) for t in h.values()]}; HMepol max floor_share "
        f"{pd.concat(h.values()).floor_share.max():.4f}"
    )
    print(
        f"epoch time (seed 0's seconds column, minutes): Mepol {m[0].seconds.sum() / 60:.1f}, "
        f"HMepol {h[0].seconds.sum() / 60:.1f}"
    )
    section("Old rules, quick slope (docs/results/quick/slope)")
    a = {
        name: load(f"quick/slope/algo-{name}_experiment-quick_slope_seed-*")
        for name in ("mepol", "alphamepol", "hmepol")
    }
    fin = {name: np.array([window(a[name][s], 90, 99) for s in range(4)]) for name in a}
    print("final per seed:", {name: np.round(x, 2).tolist() for name, x in fin.items()})
    print(
        f"HMepol seeds 0-2 mean {fin['hmepol'][:3].mean():.2f}; paired over seeds 0-2: HMepol - "
        f"Mepol {interval(fin['hmepol'][:3] - fin['mepol'][:3])}, HMepol - alpha-Mepol "
        f"{interval(fin['hmepol'][:3] - fin['alphamepol'][:3])}"
    )
    t = a["hmepol"][3].set_index("epoch")
    print(
        f"HMepol seed 3: history_max epoch 72 {t.history_max[72]:.2f}, 93 {t.history_max[93]:.2f}, "
        f"94 {t.history_max[94]:.0f}, 95 {t.history_max[95]:.2g}; epoch 93 {t.off_iters[93]} "
        f"steps, KL {t.kl[93]:.2f}; epoch 94 {t.off_iters[94]} steps, KL {t.kl[94]:.1f}; lr at 95 "
        f"{t.lr[95]:.2g}; diverged epochs {t.index[t.diverged].tolist()}; other seeds' max |h'| "
        f"{[round(float(a['hmepol'][s].history_max.max()), 2) for s in range(3)]}"
    )
    for name in ("mepol", "alphamepol", "hmepol"):
        print(f"{name} epoch time, seed 0: {a[name][0].seconds.sum() / 60:.0f} min")
    mg = load("quick/multigrid/algo-alphamepol*")
    print(f"multigrid alpha-Mepol epoch time, seed 0: {mg[0].seconds.sum() / 60:.0f} min")


def decisive() -> None:
    section("Decisive multigrid alpha-Mepol (docs/results/decisive/multigrid; faithful; finished)")
    t = load("decisive/multigrid/algo-alphamepol*")

    def final(x):
        x = x[np.isfinite(x)]
        return float(x[-max(1, math.ceil(0.1 * x.size)) :].mean())

    for column in ("entropy", "entropy_c0"):
        print(column, interval([final(t[s][column].to_numpy(float)) for s in sorted(t)]))


if __name__ == "__main__":
    collapse()
    finetune()
    old_rules()
    decisive()
