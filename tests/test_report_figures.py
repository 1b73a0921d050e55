"""What the report's figures say, read from matplotlib's objects and the captions:
a series' colour is a function of what it is, legends count what they should, captions name
the seed a map shows and the old rules a run was made with."""

from __future__ import annotations

import html
import json
from pathlib import Path

import pandas as pd
import pytest

from hmepol_cli.algorithms import ALGORITHMS
from hmepol_cli.config import backtracking_rule
from hmepol_cli.report import run_report
from hmepol_cli.report.loading import discover_runs
from hmepol_cli.report.runs import group_runs
from hmepol_cli.report.series import series_styles
from tests import test_report
from tests.test_report import (
    record_world,
    set_field,
    write_batches,
    write_finetune_run,
    write_run,
)

drawn_figures = test_report.drawn_figures  # the fixture: the figures the report saves

RULES = "  edge: slide\n"  # with algo's backtracking: reference, today's rules


def variant_run(
    root: Path, seed: int, *, algo: str = "hmepol", epochs: int = 20, **algo_keys: str
) -> Path:
    """A run of ``algo`` at today's rules with ``algo_keys`` in its algo section."""
    name = "-".join([algo, *(f"{k}-{v}" for k, v in algo_keys.items()), f"seed{seed}"])
    run = write_run(root, algo=algo, seed=seed, name=name, epochs=epochs)
    config = run / ".hydra" / "config.yaml"
    keys = "".join(f"  {k}: {v}\n" for k, v in {"backtracking": "reference", **algo_keys}.items())
    text = (
        config.read_text().replace("algo:\n", f"algo:\n{keys}").replace("env:\n", f"env:\n{RULES}")
    )
    config.write_text(text)
    meta = json.loads((run / "run.json").read_text())
    rules = {key: value for key, value in meta.items() if key not in ("edge", "backtracking")}
    (run / "run.json").write_text(json.dumps(rules))
    record_world(run)  # the rules its config now says
    return run


def styles_of(root: Path) -> dict:
    runs, _ = discover_runs(root)
    return series_styles(group_runs(runs))


def test_a_variant_keeps_its_colour_whatever_else_the_report_holds(tmp_path):
    # Report one: the thesis' HMepol and the exact trust region; report two adds a variant that
    # sorts before it. The exact variant's colour may not depend on what is beside it.
    for seed in (0, 1, 2):
        variant_run(tmp_path / "one", seed)
        variant_run(tmp_path / "two", seed)
    for seed in (0, 1):
        variant_run(tmp_path / "one", seed, trust_region="exact")
        variant_run(tmp_path / "two", seed, trust_region="exact")
        variant_run(tmp_path / "two", seed, adam_reset="epoch")
    one, two = styles_of(tmp_path / "one"), styles_of(tmp_path / "two")
    exact = "HMepol (algo.trust_region=exact)"
    assert one[exact].colour == two[exact].colour
    # The thesis' HMepol: its algorithm's colour, and a label that says which one it is.
    assert one["HMepol"].colour == two["HMepol"].colour == ALGORITHMS["hmepol"].colour
    assert one["HMepol"].label == two["HMepol"].label == "HMepol (thesis settings)"
    colours = [style.colour for style in two.values()]
    assert len(set(colours)) == len(colours)  # distinct in one figure


def test_colours_do_not_depend_on_the_groups_order(tmp_path):
    for seed in (0, 1):
        variant_run(tmp_path, seed, trust_region="exact")
        variant_run(tmp_path, seed, adam_reset="epoch")
        variant_run(tmp_path, seed, algo="mepol")
    runs, _ = discover_runs(tmp_path)
    groups = group_runs(runs)
    forward = series_styles(groups)
    backward = series_styles(groups[::-1])
    assert {k: s.colour for k, s in forward.items()} == {k: s.colour for k, s in backward.items()}
    assert forward["Mepol"].colour == ALGORITHMS["mepol"].colour
    assert forward["Mepol"].label == "Mepol"  # no variants of Mepol: nothing to tell apart


def test_of_two_tied_groups_the_one_at_the_algorithms_settings_is_the_thesis_one(tmp_path):
    for seed in (0, 1):
        variant_run(tmp_path, seed, trust_region="exact")
        variant_run(tmp_path, seed, trust_region="gradient")
    styles = styles_of(tmp_path)
    gradient = styles["HMepol (algo.trust_region=gradient)"]
    assert gradient.label == "HMepol (thesis settings: algo.trust_region=gradient)"
    assert gradient.colour == ALGORITHMS["hmepol"].colour
    assert styles["HMepol (algo.trust_region=exact)"].label == "HMepol (algo.trust_region=exact)"


def test_the_figures_name_the_thesis_series_in_their_legends(tmp_path, drawn_figures):
    for seed in (0, 1, 2):
        variant_run(tmp_path / "runs", seed)
    for seed in (0, 1):
        variant_run(tmp_path / "runs", seed, trust_region="exact")
    run_report(tmp_path / "runs", tmp_path / "report")
    [legend] = drawn_figures["slope_entropy_epochs.png"].legends
    texts = [t.get_text() for t in legend.get_texts()]
    assert "HMepol (thesis settings) (n=3)" in texts


def write_steps(run: Path, ratio: float) -> None:
    """steps.csv of a run made with diagnostics=true: one accepted step an epoch."""
    epochs = len(pd.read_csv(run / "epochs.csv"))
    pd.DataFrame(
        {
            "epoch": range(epochs),
            "accepted": True,
            "kl_one_step": 0.1,
            "kl_exact": 0.1 * ratio,
        }
    ).to_csv(run / "steps.csv", index=False)


def _report_record(out: Path, name: str) -> str:
    """The caption index.html gives the figure ``name``."""
    page = html.unescape((out / "index.html").read_text())
    start = page.index(f"figures/{name}")
    return page[start : page.index("</figcaption>", start)]


@pytest.mark.slow  # end to end: runs of the installed command (make test runs it)
def test_the_diagnostics_figure_is_readable_and_says_what_it_lacks(
    tmp_path, drawn_figures, monkeypatch
):
    import hmepol_cli.plots

    save = hmepol_cli.plots.save

    def save_and_keep(fig, path):  # draw_diagnostics saves through plots.save
        drawn_figures[Path(path).name] = fig
        return save(fig, path)

    monkeypatch.setattr(hmepol_cli.plots, "save", save_and_keep)
    for seed in (0, 1, 2):
        write_steps(variant_run(tmp_path / "runs", seed, epochs=40), 3.0)
    for seed in (0, 1):
        variant_run(tmp_path / "runs", seed, epochs=40, trust_region="exact")  # no steps.csv
        variant_run(tmp_path / "runs", seed, epochs=40, algo="mepol")  # no steps.csv
    run_report(tmp_path / "runs", tmp_path / "report")
    ratio_ax, drops_ax, scatter_ax, _ = drawn_figures["slope_diagnostics.png"].axes
    assert min(t.get_fontsize() for t in drops_ax.get_yticklabels()) >= 8
    assert "negative: a fall" in scatter_ax.get_ylabel()
    assert [t.get_text() for t in ratio_ax.get_legend().get_texts()] == [
        "HMepol (thesis settings) (median of n=3)"
    ]
    caption = _report_record(tmp_path / "report", "slope_diagnostics.png")
    assert "Mepol and HMepol (algo.trust_region=exact) have no steps.csv" in caption


def test_a_sampled_configuration_has_one_bound_entry_and_says_n_varies(tmp_path, drawn_figures):
    for seed in (0, 1, 2):
        run = write_run(tmp_path / "runs", seed=seed, configuration_names=("a", "b"))
        # Seed 1 draws configuration b at odd epochs, the others at even ones.
        write_batches(run, {e: (0, 1) if (e + seed) % 2 == 0 else (0,) for e in range(20)})
        text = (run / "epochs.csv").read_text()
        for epoch in range(1 - seed % 2, 20, 2):
            text = set_field(text, epoch + 2, "entropy_c1", "")
        (run / "epochs.csv").write_text(text)
    run_report(tmp_path / "runs", tmp_path / "report")
    [legend] = drawn_figures["slope_entropy_epochs_by_config.png"].legends
    texts = [t.get_text() for t in legend.get_texts()]
    assert texts == ["Mepol (n≤3 per epoch)", "log(free area) of the configuration"]
    caption = _report_record(tmp_path / "report", "slope_entropy_epochs_by_config.png")
    assert "Configurations are sampled each epoch" in caption


def test_one_sampled_seed_is_n_1_not_at_most_1(tmp_path, drawn_figures):
    run = write_run(tmp_path / "runs", seed=0, configuration_names=("a", "b"))
    write_batches(run, {e: (0, 1) if e % 2 == 0 else (0,) for e in range(20)})
    text = (run / "epochs.csv").read_text()
    for epoch in range(1, 20, 2):
        text = set_field(text, epoch + 2, "entropy_c1", "")
    (run / "epochs.csv").write_text(text)
    run_report(tmp_path / "runs", tmp_path / "report")
    [legend] = drawn_figures["slope_entropy_epochs_by_config.png"].legends
    assert [t.get_text() for t in legend.get_texts()][0] == "Mepol (n=1, no CI)"


def test_fine_tuning_legend_says_what_n_counts(tmp_path, drawn_figures):
    for seed in (0, 1):
        write_run(tmp_path / "runs", algo="hmepol", seed=seed, name=f"hmepol-seed{seed}")
        write_finetune_run(tmp_path / "runs", algo_init="hmepol", seed=seed)
        write_finetune_run(tmp_path / "runs", algo_init="scratch", seed=seed)
    run_report(tmp_path / "runs", tmp_path / "report")
    [legend] = drawn_figures["slope_finetune_returns.png"].legends
    texts = [t.get_text() for t in legend.get_texts()]
    assert any(t.startswith("HMepol init") and "(n=2 pre-training runs)" in t for t in texts)
    assert "TRPO from scratch (n=2 fine-tuning runs)" in texts
    caption = _report_record(tmp_path / "report", "slope_finetune_returns.png")
    assert "thin lines: each unit's own curve (a pre-training run's" in caption


def test_heatmaps_say_which_seed_and_what_white_is(tmp_path):
    for seed, final in enumerate((1.0, 3.0, 2.0, 4.0)):
        write_run(tmp_path / "runs", seed=seed, final=final)
    run_report(tmp_path / "runs", tmp_path / "report")
    caption = _report_record(tmp_path / "report", "slope_heatmaps.png")
    # Final entropies 1, 3, 2, 4: the lower of the middle two is seed 2's.
    assert "Mepol: seed 2 (its final entropy is the lower median of 4)" in caption
    assert "White: bins that no state of these trajectories fell in" in caption


def test_runs_made_with_the_old_rules_say_so(tmp_path):
    for seed in (0, 1):
        write_run(tmp_path / "old", seed=seed)  # no env.edge, no algo.backtracking
        variant_run(tmp_path / "new", seed, algo="mepol")
    runs, _ = discover_runs(tmp_path / "old")
    assert {(r.config["env.edge"], r.config["algo.backtracking"]) for r in runs} == {
        ("mirror", "first_step")
    }
    run_report(tmp_path / "old", tmp_path / "report-old")
    line = "Made with the old rules (env.edge=mirror, algo.backtracking=first_step)"
    assert line in html.unescape((tmp_path / "report-old" / "index.html").read_text())
    assert line in _report_record(tmp_path / "report-old", "slope_entropy_epochs.png")
    assert line in _report_record(tmp_path / "report-old", "slope_trajectories_mepol.png")
    run_report(tmp_path / "new", tmp_path / "report-new")
    assert "old rules" not in (tmp_path / "report-new" / "index.html").read_text()


@pytest.mark.parametrize(
    ("saved", "rule"), [({}, "first_step"), ({"backtracking": "reference"}, "reference")]
)
def test_a_config_older_than_backtracking_ran_with_first_step(saved, rule):
    assert backtracking_rule(saved) == rule


def test_a_series_with_other_seed_counts_in_other_panels_has_one_legend_entry():
    """Mepol with 4 seeds at one wind and 8 at another is one series: one entry, "n=4–8", in
    its first place; a series drawn seed by seed (n=2) or with one count keeps its label."""
    from matplotlib.figure import Figure

    from hmepol_cli.report.series import figure_legend

    fig = Figure()
    left, right = fig.subplots(1, 2)
    left.plot([0, 1], label="Mepol (n=4)")
    left.plot([0, 1], label="HMepol (n=4)")
    left.plot([0, 1], label="α-Mepol (n=2, each seed drawn)")
    right.plot([0, 1], label="Mepol (n=8)")
    right.plot([0, 1], label="HMepol (n=4)")
    right.plot([0, 1], label="Mepol (exact) (n=3)")
    figure_legend(fig, [left, right])
    shown = [text.get_text() for text in fig.legends[0].get_texts()]
    assert shown == ["Mepol (n=4–8)", "HMepol (n=4)", "α-Mepol (n=2, each seed drawn)",
                     "Mepol (exact) (n=3)"]  # fmt: skip
