"""The pre-registered analysis of the decisive experiment (PREREGISTRATION.md, sections 3-5),
from the small files kept beside this script:

    python docs/results/decisive/analysis.py            # markdown to stdout
    python docs/results/decisive/analysis.py --out docs/results/decisive/analysis.md
    python docs/results/decisive/analysis.py --results RESULTS.md   # its tables, between markers
    python docs/results/decisive/analysis.py --figures docs/results/decisive/figures  # the curves

Corridor: per run M_c = mean of entropy_c<c> over epochs 450-499 and M = (M_0 + M_1) / 2; paired
by seed, HMepol (exact trust region) - Mepol, the 95% Student-t interval and the exact sign-flip
p-value. Until every run has 500 epochs the same is computed *interim*, over the last 50 epochs
that every run of the comparison has (the same window for both arms), and labelled so.
Multigrid: the final entropy as ``hmepol report`` computes it (mean over the last 10% of the
epochs, the epochs without the configuration skipped), average and configuration 0.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats

HERE = Path(__file__).resolve().parent
BEGIN, END = "<!-- decisive tables: begin -->", "<!-- decisive tables: end -->"
EPOCHS, WINDOW, HALF_WIDTH = 500, 50, 0.3
ARMS = {"A": "mepol", "B": "exact", "C": "hmepol"}
NAMES = {"A": "Mepol", "B": "HMepol, exact trust region", "C": "HMepol, one-step (thesis)"}


def runs(folder: Path) -> dict[str, pd.DataFrame]:
    """{run name: epochs.csv} of every run in a folder, by seed."""
    out = {}
    for table in sorted(folder.glob("*/epochs.csv")):
        info = json.loads((table.parent / "run.json").read_text())
        out[table.parent.name] = (info, pd.read_csv(table))
    return out


def seed_of(name: str) -> int:
    return int(name.rsplit("seed-", 1)[1].split("_")[0])


def corridor_metric(epochs: pd.DataFrame, first: int, last: int) -> tuple[float, float, float]:
    """(M, M_0, M_1) over epochs first..last."""
    rows = epochs[(epochs.epoch >= first) & (epochs.epoch <= last)]
    m0, m1 = float(rows.entropy_c0.mean()), float(rows.entropy_c1.mean())
    return (m0 + m1) / 2, m0, m1


def paired(d: np.ndarray) -> dict[str, float]:
    """Mean, 95% t-interval, exact sign-flip p-value and the seeds a +-0.3 half-width needs."""
    n = len(d)
    mean = float(d.mean())
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


def corridor(lines: list[str]) -> None:
    arms = {a: runs(HERE / folder) for a, folder in ARMS.items() if (HERE / folder).is_dir()}
    lines += ["### Corridor, wind 0.4 (PREREGISTRATION.md sections 3-4)", "",
              "| arm | seeds | epochs done (min-max) | status |", "|---|---|---|---|"]  # fmt: skip
    for a, rs in arms.items():
        done = [len(t) for _, t in rs.values()]
        status = sorted({i["status"] for i, _ in rs.values()})
        seeds = ",".join(str(seed_of(n)) for n in rs)
        lines.append(f"| {a}: {NAMES[a]} | {seeds} | {min(done)}-{max(done)} | "
                     f"{', '.join(status)} |")  # fmt: skip
    lines.append("")
    for b, a in (("B", "A"), ("C", "A"), ("B", "C")):
        if a not in arms or b not in arms:
            continue
        common = sorted({seed_of(n) for n in arms[a]} & {seed_of(n) for n in arms[b]})
        by_seed = {arm: {seed_of(n): t for n, (_, t) in arms[arm].items()} for arm in (a, b)}
        done = min(len(by_seed[arm][s]) for arm in (a, b) for s in common)
        final = done >= EPOCHS
        last = (EPOCHS if final else done) - 1
        first = last - WINDOW + 1
        if first < 0:
            continue
        values = {arm: np.array([corridor_metric(by_seed[arm][s], first, last) for s in common])
                  for arm in (a, b)}  # fmt: skip
        label = "final" if final else f"interim (epochs {first}-{last} of {EPOCHS})"
        lines += [f"#### {NAMES[b]} - {NAMES[a]}: {label}, seeds {common}", "",
                  "| metric | " + f"{NAMES[a]} | {NAMES[b]} | difference [95% t-interval] | "
                  "sign-flip p | answer |", "|---|---|---|---|---|---|"]  # fmt: skip
        for j, metric in enumerate(("M (both configurations)", "M_0 (clockwise)",
                                    "M_1 (counterclockwise)")):  # fmt: skip
            r = paired(values[b][:, j] - values[a][:, j])
            answer = verdict(r, final) if j == 0 else "secondary"
            lines.append(
                f"| {metric} | {values[a][:, j].mean():.3f} | {values[b][:, j].mean():.3f} | "
                f"{r['mean']:+.3f} [{r['low']:+.3f}, {r['high']:+.3f}] | {r['p']:.3g} | {answer} |"
            )
        w = stats.ttest_ind(values[b][:, 0], values[a][:, 0], equal_var=False)
        ci = w.confidence_interval(0.95)
        lines += ["", f"Welch (unpaired) on M: [{ci.low:+.3f}, {ci.high:+.3f}].", ""]


def final_value(values: np.ndarray) -> float:
    x = values[np.isfinite(values)]
    return float(x[-max(1, math.ceil(0.1 * x.size)):].mean()) if x.size else math.nan


def early(table: pd.DataFrame, epochs: int) -> pd.DataFrame:
    return table[table.epoch < epochs]


def multigrid(lines: list[str]) -> None:
    folder = HERE / "multigrid"
    if not folder.is_dir():
        return
    rs = runs(folder)
    by = {"alphamepol": {}, "hmepol": {}}
    for name, (info, table) in rs.items():
        by[info["algo"]][seed_of(name)] = (info, table)
    lines += ["### Multigrid, quick preset (PREREGISTRATION.md section 5)", ""]
    done = {a: [len(t) for _, t in v.values()] for a, v in by.items()}
    lines.append("Epochs done: " + "; ".join(f"{a} {min(d)}-{max(d)}" for a, d in done.items()
                                            if d) + ".")  # fmt: skip
    lines.append("")
    common = sorted(set(by["alphamepol"]) & set(by["hmepol"]))
    if not common:
        return
    final = all(i["status"] == "finished" for v in by.values() for i, _ in v.values())
    upto = min(min(d) for d in done.values())  # interim: both arms over the same epochs
    if not final:
        lines += [f"Interim, both arms over their first {upto} epochs:", ""]
    lines += ["| metric | alpha-Mepol | HMepol | HMepol - alpha-Mepol [95% t-interval] | answer |",
              "|---|---|---|---|---|"]  # fmt: skip
    for column, metric in (("entropy", "average"), ("entropy_c0", "configuration 0")):
        a, b = (
            np.array([final_value(early(by[algo][s][1], upto)[column].to_numpy(float))
                      for s in common])
            for algo in ("alphamepol", "hmepol")
        )  # fmt: skip
        r = paired(b - a)
        lines.append(f"| {metric} | {a.mean():.3f} | {b.mean():.3f} | {r['mean']:+.3f} "
                     f"[{r['low']:+.3f}, {r['high']:+.3f}] | {verdict(r, final)} |")  # fmt: skip
    lines.append("")


COLOURS = {"A": "#1f77b4", "B": "#9467bd", "C": "#2ca02c", "alphamepol": "#d62728",
           "hmepol": "#2ca02c"}  # fmt: skip
MULTIGRID_NAMES = {"alphamepol": "alpha-Mepol", "hmepol": "HMepol"}
BOUND = {"color": "0.3", "ls": "--", "lw": 1}


def draw_arms(ax, arms: dict[str, dict[int, pd.DataFrame]], column: str, names: dict[str, str],
              colours: dict[str, str]) -> list[str]:  # fmt: skip
    """Each seed's curve (thin) and the mean over the arm's seeds (thick) over the epochs every
    seed of the arm has; returns "<arm> <epochs done>" for the title."""
    notes = []
    for arm, by_seed in arms.items():
        if not by_seed:
            continue
        done = min(len(t) for t in by_seed.values())
        for t in by_seed.values():  # a dot on each epoch where the column has gaps
            ax.plot(t.epoch, t[column], color=colours[arm], lw=0.7, alpha=0.35,
                    marker="." if t[column].isna().any() else None, ms=3)  # fmt: skip
        table = pd.concat({s: t.set_index("epoch")[column] for s, t in by_seed.items()}, axis=1)
        mean = table.loc[: done - 1].mean(axis=1)  # epochs without the column (NaN) skipped
        ax.plot(mean.index, mean.to_numpy(), color=colours[arm], lw=2,
                label=f"{names[arm]} (n={len(by_seed)}; epochs 0-{done - 1})")  # fmt: skip
        notes.append(f"{names[arm]} {done}")
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


def figures(out: Path) -> list[Path]:
    """The pre-registered descriptive curves (PREREGISTRATION.md section 4), drawn interim too:
    per arm each seed's curve and the mean over seeds (n = 4 or 8: no band)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    written = []
    found = {a: runs(HERE / folder) for a, folder in ARMS.items() if (HERE / folder).is_dir()}
    if found:
        arms = {a: {seed_of(n): t.assign(m=(t.entropy_c0 + t.entropy_c1) / 2)
                    for n, (_, t) in rs.items()} for a, rs in found.items()}  # fmt: skip
        infos = [info for rs in found.values() for info, _ in rs.values()]
        bound = infos[0]["log_free_area"][0]
        final = all(i["status"] == "finished" for i in infos)
        panels = (("m", "(clockwise + counterclockwise) / 2"),
                  ("entropy_c0", "configuration 0: clockwise"),
                  ("entropy_c1", "configuration 1: counterclockwise"))  # fmt: skip
        fig, axes = plt.subplots(1, 3, figsize=(13, 4.2), sharey=True)
        panels = [(column, title, bound) for column, title in panels]
        notes = draw_panels(axes, panels, arms, NAMES, EPOCHS, final)
        fig.suptitle(f"Decisive experiment, corridor wind 0.4 ({'final' if final else 'INTERIM'}; "
                     f"epochs done of {EPOCHS}: {', '.join(notes)})")  # fmt: skip
        written.append(save_figure(fig, out / "corridor_interim.png",
            "Thick: mean over seeds, over the epochs every seed of the arm has; thin: each seed. "
            "No interval drawn. Faithful rules (env.edge=slide, algo.backtracking=reference), "
            "N = 100 x 400 per epoch, commit a95e183. Descriptive (PREREGISTRATION.md section 4): "
            "the answer is the table in RESULTS.md."))  # fmt: skip
        plt.close(fig)
    folder = HERE / "multigrid"
    if folder.is_dir():
        rs = runs(folder)
        by = {"alphamepol": {}, "hmepol": {}}
        for name, (info, table) in rs.items():
            by[info["algo"]][seed_of(name)] = table
        info = next(iter(rs.values()))[0]
        final = all(i["status"] == "finished" for i, _ in rs.values())
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
        written.append(save_figure(fig, out / "multigrid_interim.png",
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
                        "(corridor_interim.png, multigrid_interim.png)")  # fmt: skip
    args = parser.parse_args(argv)
    lines: list[str] = []
    corridor(lines)
    multigrid(lines)
    text = "\n".join(lines).strip() + "\n"
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
