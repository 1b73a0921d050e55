"""``index.html``: one self-contained page (inline style, images by relative path) with every
figure and its caption, the runs that were used and skipped, and the summary tables."""

from __future__ import annotations

import datetime as dt
import html
import os
from pathlib import Path

import pandas as pd

from hmepol_cli.report.figures import FigureRecord
from hmepol_cli.report.runs import Group, SkippedRun, format_wind
from hmepol_cli.report.summary import ReportCounts, format_number

STYLE = """
body { font-family: system-ui, sans-serif; max-width: 1200px; margin: 2em auto; padding: 0 1em;
       color: #222; line-height: 1.45; }
h1, h2, h3 { font-weight: 600; }
figure { margin: 1.5em 0 2.5em; }
figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-size: 0.92em; color: #444; max-width: 1000px; }
table { border-collapse: collapse; font-size: 0.85em; margin: 0.8em 0 1.5em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: right; }
th { background: #f3f3f3; }
td.text, th.text { text-align: left; }
.thesis { color: #06c; font-weight: 600; }
.warn { color: #a40; }
code { background: #f4f4f4; padding: 0 0.2em; }
"""


def _table(frame: pd.DataFrame, digits: int = 3) -> str:
    if frame.empty:
        return "<p><em>none</em></p>"
    numeric = {c for c in frame.columns if pd.api.types.is_numeric_dtype(frame[c])}

    def cell(column: str, value) -> str:
        number = format_number(column, value, digits)
        return number if number is not None else html.escape(str(value))

    head = "".join(
        f'<th class="{"" if c in numeric else "text"}">{html.escape(str(c))}</th>'
        for c in frame.columns
    )
    body = []
    for row in frame.itertuples(index=False):
        cells = "".join(
            f'<td class="{"" if c in numeric else "text"}">{cell(c, v)}</td>'
            for c, v in zip(frame.columns, row, strict=True)
        )
        body.append(f"<tr>{cells}</tr>")
    return f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>"


def _relative(path: Path, start: Path) -> str:
    return Path(os.path.relpath(path, start)).as_posix()


def write_index(
    out_dir: Path,
    runs_root: Path,
    groups: list[Group],
    skipped: list[SkippedRun],
    figures: list[FigureRecord],
    tables: dict[str, pd.DataFrame],
    table_files: list[Path],
    counts: ReportCounts,
) -> Path:
    """Write ``out_dir/index.html`` (linking ``table_files``) and return its path."""
    out_dir = Path(out_dir)
    e = html.escape
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        "<title>hmepol report</title>",
        f"<style>{STYLE}</style></head><body>",
        "<h1>hmepol report: maximum state-entropy exploration</h1>",
        f"<p>Runs under <code>{e(str(runs_root))}</code>, report built "
        f"{dt.datetime.now().strftime('%Y-%m-%d %H:%M')}: {counts.text()} "
        f"({counts.pretraining_runs} pre-training runs in {counts.groups} groups, "
        f"{counts.finetune_runs} fine-tuning runs).</p>",
        "<p>Entropies are kNN estimates in nats. Curves and bars show the mean over seeds with a "
        "Student-t 95% confidence interval (none with a single seed). "
        "The final entropy of a run is "
        "its mean over the last 10% of epochs. The dashed line log(free area) is the entropy of a "
        "uniform visitation of the free space, the highest any policy can reach.</p>",
        "<h2>Runs</h2>",
    ]
    run_rows = pd.DataFrame(
        [
            {
                "env": g.env,
                "wind": format_wind(g.wind),
                "group": g.label,
                "differs by": ", ".join(f"{k}={v}" for k, v in g.key) or "(all runs alike)",
                "n seeds": len(g.runs),
                "seeds": " ".join(map(str, g.seeds)),
            }
            for g in groups
        ]
    )
    parts.append(_table(run_rows))
    parts.append("<h2>Skipped runs</h2>")
    if skipped:
        parts.append('<ul class="warn">')
        parts += [
            f"<li><code>{e(_relative(s.path, runs_root))}</code>: {e(s.reason)}</li>"
            for s in skipped
        ]
        parts.append("</ul>")
    else:
        parts.append("<p>None.</p>")

    for env in dict.fromkeys(f.env for f in figures):
        parts.append(f"<h2>Environment: {e(env)}</h2>")
        for record in (f for f in figures if f.env == env):
            thesis = (
                f' <span class="thesis">(thesis {e(record.thesis)})</span>' if record.thesis else ""
            )
            parts.append(
                f'<figure><img src="{e(_relative(record.path, out_dir))}" alt="{e(record.title)}">'
                f"<figcaption><strong>{e(record.title)}</strong>{thesis}. {e(record.caption)}"
                "</figcaption></figure>"
            )
    if not figures:
        parts.append("<p>No figures: no usable runs.</p>")

    parts.append("<h2>Summary</h2>")
    parts.append("<h3>Final entropy per group and configuration (nats)</h3>")
    parts.append(_table(tables.get("summary", pd.DataFrame())))
    parts.append("<h3>Differences between algorithms (nats)</h3>")
    parts.append(
        "<p>Final entropy of the later algorithm minus the earlier one (order Mepol, α-Mepol, "
        "HMepol), in the same environment and wind. 95% CI: paired t-interval on per-seed "
        "differences when both groups ran the same seeds, Welch's t-interval otherwise "
        "(column <code>method</code>).</p>"
    )
    parts.append(_table(tables.get("differences", pd.DataFrame())))
    finetune = tables.get("finetune", pd.DataFrame())
    if not finetune.empty:
        parts.append("<h3>Fine-tuning returns</h3>")
        parts.append(
            "<p>Final return: per (seed, target) curve the mean over the last 10% of epochs, then "
            "mean and 95% t-interval over curves. Last column: first epoch at which the mean curve "
            "reaches the final mean return of the Mepol-initialised run.</p>"
        )
        parts.append(_table(finetune))
    links = [e(_relative(path, out_dir)) for path in table_files]
    parts.append(
        "<p>Tables as files: " + ", ".join(f'<a href="{n}">{n}</a>' for n in links) + "</p>"
    )
    parts.append("</body></html>")
    path = out_dir / "index.html"
    path.write_text("\n".join(parts), encoding="utf-8")
    return path
