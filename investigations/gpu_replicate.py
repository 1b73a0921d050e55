"""The GPU replicate of the corridor's wind sweep (docs/results/gpu_replicate): the analysis its
PREREGISTRATION.md fixes, printed as a table.

E is the last epoch every run completed, rounded down to a multiple of 10; a run's metric is
the mean of entropy_c0 and entropy_c1 over epochs E-49..E (from 0 when E < 49); per wind, HMepol
(exact trust region) - Mepol paired by seed, with the t-interval, the exact sign-flip p, Holm's
adjustment over the four winds and the seeds a +-0.3 interval needs.

    python -m investigations.gpu_replicate [folder]
"""

from __future__ import annotations

import sys
from pathlib import Path

import pandas as pd

from hmepol_cli.report.comparisons import paired, window_metric

FOLDER = Path("docs/results/gpu_replicate")
WINDS = (0.05, 0.15, 0.25, 0.4)
ARMS = {"mepol": "corridor_mepol", "exact": "corridor_hmepol_exact"}
COLUMNS = ("entropy_c0", "entropy_c1")


def load(folder: Path) -> dict[tuple[str, float, int], pd.DataFrame]:
    runs = {}
    for arm, preset in ARMS.items():
        for wind in WINDS:
            for seed in range(8):
                name = f"experiment-{preset}_precision-float32_seed-{seed}_wind-{wind}"
                runs[arm, wind, seed] = pd.read_csv(folder / arm / name / "epochs.csv")
    return runs


def holm(ps: list[float]) -> list[float]:
    order = sorted(range(len(ps)), key=ps.__getitem__)
    adjusted, running = [0.0] * len(ps), 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (len(ps) - rank) * ps[i]))
        adjusted[i] = running
    return adjusted


def main(folder: Path = FOLDER) -> None:
    runs = load(folder)
    last = min(int(frame.epoch.max()) for frame in runs.values())
    end = last - last % 10
    first = max(0, end - 49)
    print(f"E = {end} (every run completed epochs 0..{last}); window: epochs {first}..{end}")
    metric = {key: window_metric(frame, COLUMNS, first, end) for key, frame in runs.items()}
    results = [
        paired(
            {s: metric["mepol", w, s] for s in range(8)},
            {s: metric["exact", w, s] for s in range(8)},
        )
        for w in WINDS
    ]
    print(
        "| wind | Mepol | HMepol exact | exact - Mepol [95% t] | sign-flip p | Holm p "
        "| seeds for +-0.3 |"
    )
    print("|---|---|---|---|---|---|---|")
    for wind, result, p_holm in zip(WINDS, results, holm([r.p for r in results]), strict=True):
        means = [sum(metric[a, wind, s] for s in range(8)) / 8 for a in ("mepol", "exact")]
        print(
            f"| {wind} | {means[0]:.3f} | {means[1]:.3f} | {result.mean:+.3f} "
            f"[{result.low:+.3f}, {result.high:+.3f}] | {result.p:.4f} | {p_holm:.4f} "
            f"| {result.seeds_needed:.0f} |"
        )


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else FOLDER)
