"""``hmepol report``: aggregate finished runs into the thesis figures, tables and one HTML page.

Data path: loading.py (find, load) -> runs.py (merge copies, group) -> stats.py (means and
intervals over the unit of independence, seeds needed), aggregates.py (rliable, bootstrapped over
runs) -> frames.py (the numbers a figure draws) -> figures.py / series.py / plots.py (PNG; the
words in captions.py) -> summary.py (CSV, Markdown; resolution.py's notes) -> html.py
(index.html) -> manifest.py (report.json). docs/statistics.md gives every formula.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from hmepol_cli.errors import UserError
from hmepol_cli.plots import save_run_plots
from hmepol_cli.report.figures import make_figures
from hmepol_cli.report.html import write_index
from hmepol_cli.report.loading import discover_runs
from hmepol_cli.report.manifest import previous_report_files, write_manifest
from hmepol_cli.report.runs import (
    Run,
    SkippedRunWarning,
    drop_duplicate_seeds,
    format_wind,
    group_runs,
    merge_identical_runs,
)
from hmepol_cli.report.summary import ReportCounts, write_summary


def cut_at_common_epochs(runs: list[Run]) -> dict[str, int]:
    """Cut the pre-training runs of every setting the report compares (an env and a wind) that
    holds an unfinished run at the last epoch all of that setting's runs wrote, so that its
    curves and final values compare the same epochs; a setting whose runs all finished keeps
    them whole. Returns the cuts, {"corridor, wind 0.15": epoch}, in env and wind order."""
    settings: dict[tuple[str, float | None], list[Run]] = {}
    for run in runs:
        if run.epochs is not None and len(run.epochs):
            wind = run.wind if np.isfinite(run.wind) else None  # no wind: one key, not NaNs
            settings.setdefault((run.env, wind), []).append(run)
    cuts = {}
    for (env, wind), members in sorted(
        settings.items(), key=lambda item: (item[0][0], -1.0 if item[0][1] is None else item[0][1])
    ):
        if all(r.meta.get("status") == "finished" for r in members):
            continue
        end = min(int(r.epochs.epoch.max()) for r in members)
        for run in members:
            run.epochs = run.epochs[run.epochs.epoch <= end]
        name = env if wind is None else f"{env}, wind {format_wind(wind)}"
        cuts[name] = end
    return cuts


def run_report(runs_roots: Path | Sequence[Path], out_dir: Path, unfinished: bool = False) -> Path:
    """Build the report of every finished run under ``runs_roots`` (one folder or several)
    into ``out_dir``.

    Writes ``out_dir/index.html``, ``out_dir/figures/*.png``, ``summary.csv``,
    ``differences.csv``, ``summary.md`` (and ``finetune.csv``, ``finetune_differences.csv``
    when there are fine-tuning runs; ``study.md``, its decisions stage by stage, for a study's
    folder), and ``report.json``,
    the list of those files; returns the path of ``index.html``. The files
    of an earlier report in ``out_dir`` that this one does not write again are deleted; a
    non-empty ``out_dir`` without ``report.json`` is refused. Unusable runs are skipped with a
    warning and listed; a run found twice (same config, seed and rows) is counted once, and the
    page says which directories were merged.

    ``unfinished``: runs that stopped before their last epoch are used too (an interim report of
    runs still going, a replicate cut short by its time). Every env and wind that holds one has
    its pre-training runs cut at the last epoch all of them wrote, so that the arms compared
    there share their epochs (:func:`cut_at_common_epochs`); the page and the command's last
    line state each cut.
    """
    roots = [runs_roots] if isinstance(runs_roots, str | Path) else list(runs_roots)
    roots = [Path(r) for r in roots]
    out_dir = Path(out_dir)
    for root in roots:
        if not root.is_dir():
            raise UserError(f"runs root {str(root)!r} does not exist or is not a directory")
    previous = previous_report_files(out_dir)
    runs, skipped = [], []
    for root in roots:
        found, unusable = discover_runs(root, unfinished)
        runs, skipped = runs + found, skipped + unusable
    if not runs and not skipped:
        where = ", ".join(repr(str(r)) for r in roots)
        raise UserError(f"no runs under {where} (no directory holds a run.json)")
    runs, merged = merge_identical_runs(runs)
    runs, duplicates = drop_duplicate_seeds(runs)
    skipped = sorted(skipped + duplicates, key=lambda s: str(s.path))
    cuts = cut_at_common_epochs(runs) if unfinished else {}
    groups = group_runs(runs)
    finetune_runs = [r for r in runs if r.finetune is not None]
    out_dir.mkdir(parents=True, exist_ok=True)
    figures = make_figures(groups, finetune_runs, out_dir / "figures")
    tables, table_files = write_summary(groups, finetune_runs, out_dir)
    counts = ReportCounts(
        pretraining_runs=sum(len(g.runs) for g in groups),
        finetune_runs=len(finetune_runs),
        groups=len(groups),
        skipped=len(skipped),
        figures=len(figures),
        merged=len(merged),
        cuts=cuts,
    )
    from hmepol_cli.study import study_report  # a study's folder: its decisions too

    studies = [p for p in (study_report(root, out_dir) for root in roots) if p is not None]
    for study in studies:
        print(study.read_text().rstrip())
    index = write_index(
        out_dir, roots, groups, finetune_runs, skipped, merged, figures, tables, table_files, counts
    )
    write_manifest(out_dir, [f.path for f in figures] + table_files + studies + [index], previous)
    print(f"report: {counts.text()} -> {index}")
    return index


__all__ = ["SkippedRunWarning", "run_report", "save_run_plots"]
