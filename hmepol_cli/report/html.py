"""``index.html``: one self-contained page (inline style, images by relative path) with every
figure and its caption, the runs that were used and skipped, and the summary tables."""

from __future__ import annotations

import datetime as dt
import html
import os
import re
from pathlib import Path

import pandas as pd

from hmepol_cli.report.figures import FigureRecord
from hmepol_cli.report.rules import old_rules_text
from hmepol_cli.report.runs import Group, MergedRun, SkippedRun, format_wind
from hmepol_cli.report.stats import MIN_UNITS
from hmepol_cli.report.summary import ReportCounts, format_number, table_sections

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
.wide { overflow-x: auto; max-width: 100%; }
.notice { background: #fff4d6; border: 1px solid #e0b84a; padding: 0.6em 1em; }
.resolution { font-size: 0.92em; color: #444; font-style: italic; }
code { background: #f4f4f4; padding: 0 0.2em; }
"""


def _inline_code(text: str) -> str:
    """Plain text with Markdown's `code` spans, as HTML."""
    return re.sub(r"`([^`]+)`", r"<code>\1</code>", html.escape(text))


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
    table = f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>"
    return f'<div class="wide">{table}</div>'  # a wide table scrolls, the page does not


# Below these, a report's runs test the program rather than compare algorithms (the thesis:
# 500 epochs and 8 seeds, 4 in multigrid, tables A.1-A.3).
SMOKE_SEEDS = 3
SMOKE_EPOCHS = 100


def scale_notice(groups: list[Group], finetune_runs: list) -> str:
    """A boxed paragraph when the runs are at smoke scale, naming the groups that are."""
    small = [
        f"{g.env} {g.label}: {len(g.runs)} seed{'s' if len(g.runs) != 1 else ''}, "
        f"{min(len(r.epochs) for r in g.runs)} epochs"
        for g in groups
        if len(g.runs) < SMOKE_SEEDS or min(len(r.epochs) for r in g.runs) < SMOKE_EPOCHS
    ]
    units: dict[str, set[str]] = {}  # per initialisation, its independent units
    for run in finetune_runs:
        units.setdefault(run.algo, set()).add(run.independent_unit)
    fewest = min((len(u) for u in units.values()), default=SMOKE_SEEDS)
    if fewest < SMOKE_SEEDS:
        small.append(
            f"fine-tuning: {fewest} pre-training run{'s' if fewest != 1 else ''} (or runs from "
            "scratch) for an initialisation"
        )
    if not small:
        return ""
    return (
        '<p class="notice"><strong>Smoke scale, not a result.</strong> '
        + html.escape("; ".join(small))
        + f". Under {SMOKE_SEEDS} seeds or {SMOKE_EPOCHS} epochs a report shows that the program "
        "runs end to end; which algorithm is better needs the thesis' scale (500 epochs, 8 "
        "seeds, tables A.1-A.3), or at least RESULTS.md's.</p>"
    )


def rules_notice(groups: list[Group]) -> str:
    """A boxed paragraph when some group ran with rules that are not today's defaults."""
    text = old_rules_text(groups)
    return f'<p class="notice">{html.escape(text)}</p>' if text else ""


def _under_root(path: Path, roots: list[Path]) -> str:
    """A skipped run's path inside the runs folder that holds it."""
    root = next((r for r in roots if Path(path).is_relative_to(r)), roots[0])
    return _relative(path, root)


def _relative(path: Path, start: Path) -> str:
    return Path(os.path.relpath(path, start)).as_posix()


def merged_list(merged: list[MergedRun], roots: list[Path]) -> list[str]:
    """The section on runs found twice: each copy beside the directory kept, both named from
    the folder that holds every runs root (so that two roots' same names read apart)."""
    if not merged:
        return []
    resolved = [Path(r).resolve() for r in roots]
    common = Path(os.path.commonpath(resolved))
    if common in resolved:  # one root, or one inside another: name that root too
        common = common.parent
    e = html.escape

    def name(path: Path) -> str:
        return e(_relative(Path(path).resolve(), common))

    items = [f"<li><code>{name(m.path)}</code> = <code>{name(m.kept)}</code></li>" for m in merged]
    return [
        "<h2>Merged runs</h2>",
        f"<p>{len(merged)} run director{'y holds' if len(merged) == 1 else 'ies hold'} the same "
        "run as another (same config, seed and rows): each run is counted once, from the "
        "directory on the right.</p>",
        "<ul>",
        *items,
        "</ul>",
    ]


def write_index(
    out_dir: Path,
    runs_roots: list[Path],
    groups: list[Group],
    finetune_runs: list,
    skipped: list[SkippedRun],
    merged: list[MergedRun],
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
        f"<p>Runs under {', '.join(f'<code>{e(str(r))}</code>' for r in runs_roots)}, "
        "report built "
        f"{dt.datetime.now().strftime('%Y-%m-%d %H:%M')}: {counts.text()} "
        f"({counts.pretraining_runs} pre-training runs in {counts.groups} groups, "
        f"{counts.finetune_runs} fine-tuning runs).</p>",
        "<p>Entropies are kNN estimates in nats. Every interval is taken over the unit of "
        "independence: the seed (one pre-training run) for entropies, and for fine-tuning the "
        "pre-training run the policy came from, its targets and fine-tuning seeds nested in it. "
        f"Curves and bars show the mean over those units; from {MIN_UNITS} units on with a "
        f"Student-t 95% confidence interval, with fewer each unit's own curve or dot (with two, "
        "t = 12.7 and the band would cover the axis). Intervals of a bounded quantity (a goal "
        "task's return, a share) stay inside its bounds. The final entropy of a run is "
        "its mean over the last 10% of epochs. The dashed line log(free area) is the entropy of a "
        "uniform visitation of the free space, the highest any policy can reach. Beside them, "
        "rliable's aggregates (Agarwal et al., 2021): interquartile mean, mean and probability "
        "of improvement with bootstrap 95% intervals over runs, and performance profiles.</p>",
        scale_notice(groups, finetune_runs),
        rules_notice(groups),
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
            f"<li><code>{e(_under_root(s.path, runs_roots))}</code>: {e(s.reason)}</li>"
            for s in skipped
        ]
        parts.append("</ul>")
    else:
        parts.append("<p>None.</p>")
    parts += merged_list(merged, runs_roots)

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
    for name, title, caption, notice, line in table_sections(tables):
        parts.append(f"<h3>{e(title)}</h3>")
        parts.append(f"<p>{_inline_code(caption)}</p>")
        if notice:
            parts.append(f'<p class="notice"><strong>{_inline_code(notice)}</strong></p>')
        parts.append(_table(tables[name]))
        if line:
            parts.append(f'<p class="resolution">{_inline_code(line)}</p>')
    links = [e(_relative(path, out_dir)) for path in table_files]
    parts.append(
        "<p>Tables as files: " + ", ".join(f'<a href="{n}">{n}</a>' for n in links) + "</p>"
    )
    parts.append("</body></html>")
    path = out_dir / "index.html"
    path.write_text("\n".join(parts), encoding="utf-8")
    return path
