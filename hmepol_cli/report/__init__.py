"""``hmepol report``: aggregate finished runs into the thesis figures, tables and one HTML page.

Data path: runs.py (find, load, group) -> stats.py (mean, t-intervals) -> figures.py / plots.py
(PNG) -> summary.py (CSV, Markdown) -> html.py (index.html) -> manifest.py (report.json).
"""

from __future__ import annotations

from pathlib import Path

from hmepol_cli.errors import UserError
from hmepol_cli.plots import save_run_plots
from hmepol_cli.report.figures import make_figures
from hmepol_cli.report.html import write_index
from hmepol_cli.report.manifest import previous_report_files, write_manifest
from hmepol_cli.report.runs import (
    SkippedRunWarning,
    discover_runs,
    drop_duplicate_seeds,
    group_runs,
)
from hmepol_cli.report.summary import ReportCounts, write_summary


def run_report(runs_root: Path, out_dir: Path) -> Path:
    """Build the report of every finished run under ``runs_root`` into ``out_dir``.

    Writes ``out_dir/index.html``, ``out_dir/figures/*.png``, ``summary.csv``,
    ``differences.csv``, ``summary.md`` (and ``finetune.csv`` when there are fine-tuning runs),
    and ``report.json``, the list of those files; returns the path of ``index.html``. The files
    of an earlier report in ``out_dir`` that this one does not write again are deleted; a
    non-empty ``out_dir`` without ``report.json`` is refused. Unusable runs are skipped with a
    warning and listed.
    """
    runs_root, out_dir = Path(runs_root), Path(out_dir)
    if not runs_root.is_dir():
        raise UserError(f"runs root {str(runs_root)!r} does not exist or is not a directory")
    previous = previous_report_files(out_dir)
    runs, skipped = discover_runs(runs_root)
    if not runs and not skipped:
        raise UserError(f"no runs under {str(runs_root)!r} (no directory holds a run.json)")
    runs, duplicates = drop_duplicate_seeds(runs)
    skipped = sorted(skipped + duplicates, key=lambda s: str(s.path))
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
    )
    index = write_index(out_dir, runs_root, groups, skipped, figures, tables, table_files, counts)
    write_manifest(out_dir, [f.path for f in figures] + table_files + [index], previous)
    print(f"report: {counts.text()} -> {index}")
    return index


__all__ = ["SkippedRunWarning", "run_report", "save_run_plots"]
