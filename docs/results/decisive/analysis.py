"""The pre-registered analysis of the decisive experiment (PREREGISTRATION.md, sections 3-5),
from the small files kept beside this script:

    python docs/results/decisive/analysis.py            # markdown to stdout
    python docs/results/decisive/analysis.py --out docs/results/decisive/analysis.md
    python docs/results/decisive/analysis.py --results RESULTS.md   # its tables, between markers

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


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path)
    parser.add_argument("--results", type=Path, help="a file whose tables between the markers "
                        f"{BEGIN} and {END} are replaced")  # fmt: skip
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
    print(text)


if __name__ == "__main__":
    main()
