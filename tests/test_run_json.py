"""What run.json records for the report, which reads it instead of the training code: the rules a
run ran with, its world's map, a fine-tuning's return bounds; written by a real (tiny) training
and fine-tuning, and added to older run.json files by tools/backfill_run_json.py."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import pytest
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra

from hmepol_cli.envs import make_world
from hmepol_cli.plots import WorldMap
from hmepol_cli.report.loading import load_run
from tests.test_trainer import tiny_trainer
from tools.backfill_run_json import main as backfill_main

ROOT = Path(__file__).resolve().parents[1]
TRAINING_KEYS = ("backtracking", "edge", "world_map")
FINETUNE_KEYS = ("return_bounds", "world_map")


def world_map_of(env: str) -> dict:
    """The map the world of ``env`` gives (the walls do not depend on the wind or the edge)."""
    return make_world(SimpleNamespace(name=env, wind=0.4)).world_map()


def finetune_from(run: Path, out: Path) -> Path:
    """A one-epoch fine-tuning of ``run``'s policy on one goal; -> its directory."""
    from hmepol_cli.finetune import finetune

    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="hmepol_cli.conf", version_base="1.3"):
        cfg = compose(
            config_name="finetune",
            overrides=[f"init={run}", "epochs=1", "episodes=2", "horizon=20", "targets=1",
                       "config=0", "progress=false", f"output_dir={out}"],
        )  # fmt: skip
    GlobalHydra.instance().clear()
    return finetune(cfg)


def without(run: Path, keys: tuple[str, ...]) -> dict:
    """Remove ``keys`` from the run's run.json, as a run made before they existed wrote it;
    -> the run.json as it was."""
    meta = json.loads((run / "run.json").read_text())
    (run / "run.json").write_text(
        json.dumps({k: v for k, v in meta.items() if k not in keys}, indent=2, sort_keys=True)
    )
    return meta


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> tuple[Path, Path]:
    """A tiny corridor run with the old rules, and a fine-tuning of a tiny slope run."""
    folder = tmp_path_factory.mktemp("recorded")
    corridor = folder / "corridor"
    trainer = tiny_trainer(corridor, "env=corridor", "epochs=1", "env.edge=mirror",
                           "algo.backtracking=first_step")  # fmt: skip
    trainer.train()
    slope = folder / "slope"
    tiny_trainer(slope, "epochs=1").train()
    return corridor / "run", finetune_from(slope / "run", folder / "ft")


def test_a_training_run_records_its_rules_and_its_worlds_map(trained):
    run, _ = trained
    meta = json.loads((run / "run.json").read_text())
    assert (meta["edge"], meta["backtracking"]) == ("mirror", "first_step")
    assert meta["world_map"] == world_map_of("corridor")
    loaded = load_run(run)
    assert (loaded.config["env.edge"], loaded.config["algo.backtracking"]) == (
        "mirror",
        "first_step",
    )
    world = make_world(SimpleNamespace(name="corridor", wind=0.4))
    drawn = loaded.world_map
    assert drawn == WorldMap.from_json(world.world_map())
    assert drawn.arena == (world.arena.x0, world.arena.y0, world.arena.x1, world.arena.y1)
    assert [len(w) for w in drawn.walls] == [len(w) for w in world.walls]


def test_a_fine_tuning_records_its_return_bounds_and_its_worlds_map(trained):
    _, finetuning = trained
    meta = json.loads((finetuning / "run.json").read_text())
    assert meta["return_bounds"] == [0.0, 1.0]  # a goal task: the share that reached it
    assert meta["world_map"] == world_map_of("slope") and meta["edge"] == "slide"
    assert load_run(finetuning).return_bounds == (0.0, 1.0)


def test_the_backfill_adds_what_the_runs_wrote(trained, tmp_path):
    """A run.json without the keys gets the very values the run wrote, and no other change."""
    copies = []
    for run, keys in zip(trained, (TRAINING_KEYS, FINETUNE_KEYS), strict=True):
        copy = tmp_path / run.parent.name
        shutil.copytree(run, copy)
        copies.append((copy, without(copy, keys)))
    assert backfill_main([str(tmp_path)]) == 0
    for copy, written in copies:
        assert json.loads((copy / "run.json").read_text()) == written


def test_the_backfill_changes_nothing_but_the_keys_it_adds_and_is_idempotent(tmp_path, capsys):
    committed = sorted((ROOT / "docs" / "results" / "quick" / "slope").glob("*seed-0"))[:1]
    committed += sorted((ROOT / "docs" / "results" / "collapse" / "finetune-epoch75").iterdir())[:1]
    for source in committed:
        shutil.copytree(source, tmp_path / source.name)
        without(tmp_path / source.name, (*TRAINING_KEYS, "return_bounds"))
    gym = tmp_path / "gym-run"  # a Gymnasium world has no map and no edge
    gym.mkdir()
    (gym / "config.yaml").write_text(
        "env:\n  name: gym\n  id: hmepol/Slope-v0\nalgo:\n  name: mepol\n"
    )
    (gym / "run.json").write_text(
        json.dumps({"env": "gym", "env_id": "hmepol/Slope-v0", "seed": 0})
    )
    before = {p: json.loads(p.read_text()) for p in tmp_path.rglob("run.json")}
    assert backfill_main([str(tmp_path)]) == 0
    after = {p: json.loads(p.read_text()) for p in tmp_path.rglob("run.json")}
    for path, meta in before.items():
        assert {key: after[path][key] for key in meta} == meta  # no key changed
    for source in committed:  # the committed files were brought up to date by the tool
        assert after[tmp_path / source.name / "run.json"] == json.loads(
            (source / "run.json").read_text()
        )
    assert set(after[gym / "run.json"]) - set(before[gym / "run.json"]) == {
        "backtracking",
        "world_map",
    }
    assert after[gym / "run.json"]["world_map"] is None
    assert after[gym / "run.json"]["backtracking"] == "first_step"  # the config has none
    stamps = {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in after}
    capsys.readouterr()
    assert backfill_main([str(tmp_path)]) == 0
    assert "backfill: 0 run.json files brought up to date" in capsys.readouterr().out
    assert {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in after} == stamps


@pytest.mark.parametrize(
    ("config", "meta", "rules"),
    [
        ({"env.name": "slope"}, {}, {"env.edge": "mirror", "algo.backtracking": "first_step"}),
        (
            {"env.name": "slope", "env.edge": "slide", "algo.backtracking": "reference"},
            {},
            {"env.edge": "slide", "algo.backtracking": "reference"},
        ),
        (
            {"env.name": "corridor", "env.edge": "slide"},
            {"edge": "mirror", "backtracking": "reference"},
            {"env.edge": "mirror", "algo.backtracking": "reference"},
        ),
        ({"env.name": "gym"}, {"env_id": "x"}, {"algo.backtracking": "first_step"}),
        ({"env.name": "slope"}, {"world_map": None}, {"algo.backtracking": "first_step"}),
    ],
)
def test_the_report_reads_the_rules_run_json_records_or_their_absence_meant(config, meta, rules):
    from hmepol_cli.report.rules import saved_rules

    assert saved_rules(config, meta) == rules


def test_the_reports_tables_for_an_older_run_json_are_the_training_codes():
    """What the report assumes of a run.json older than a key is what the training code does."""
    from hmepol_cli.config import AlgoConfig, EnvConfig, backtracking_rule
    from hmepol_cli.envs import ENVIRONMENTS, NavigationWorld
    from hmepol_cli.envs.base import edge_rule
    from hmepol_cli.finetune.task import GoalTask
    from hmepol_cli.report.rules import EDGED_WORLDS, RULE_WITHOUT_SETTING, TODAY
    from hmepol_cli.report.runs import GOAL_TASK_BOUNDS

    assert RULE_WITHOUT_SETTING == {
        "env.edge": edge_rule({}),
        "algo.backtracking": backtracking_rule({}),
    }
    assert TODAY == {"env.edge": EnvConfig.edge, "algo.backtracking": AlgoConfig.backtracking}
    edged = {name for name, world in ENVIRONMENTS.items() if issubclass(world, NavigationWorld)}
    assert set(EDGED_WORLDS) == edged
    assert GOAL_TASK_BOUNDS == GoalTask.return_bounds


@pytest.mark.parametrize("env", ["slope", "corridor", "multigrid"])
def test_walls_drawn_from_run_json_are_the_worlds_own_drawing(env):
    """The report's walls (from the map run.json records) are the patches the world's own
    drawing makes: same rectangles, colours, order and layers, same limits."""
    from matplotlib.figure import Figure

    from hmepol_cli.envs.render import draw_world
    from hmepol_cli.plots import draw_walls

    world = make_world(SimpleNamespace(name=env, wind=0.4))
    recorded = WorldMap.from_json(json.loads(json.dumps(world.world_map())))
    for config in range(world.n_configurations):
        own, drawn = Figure().subplots(), Figure().subplots()
        draw_world(own, world, config, force=False, start=False, zorder=3)
        draw_walls(drawn, recorded, config)

        def patches(ax) -> list[tuple]:
            return [
                (p.get_xy(), p.get_width(), p.get_height(), p.get_facecolor(), p.get_zorder())
                for p in ax.patches
            ]

        assert patches(drawn) == patches(own) and len(own.patches) == len(world.walls[config]) + 1
        assert (drawn.get_xlim(), drawn.get_ylim()) == (own.get_xlim(), own.get_ylim())
