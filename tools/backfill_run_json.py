"""Add to run.json files made before they recorded them the keys the report reads instead of
the training code: the rules a run ran with, its world's map, a fine-tuning's return bounds.

The values are computed with the training code, the way a run computes them from its own saved
config (config.yaml, or Hydra's .hydra/config.yaml in runs older than it):

- ``backtracking`` (pre-training): the backtracking rule of the run's ``algo`` entry
  (:func:`hmepol_cli.config.backtracking_rule`: a config without the setting ran with
  ``first_step``);
- ``edge`` (pre-training, 2-D worlds): the world's edge rule (:func:`hmepol_cli.envs.base.
  edge_rule`: a config without the setting ran with ``mirror``);
- ``world_map``: the arena, start area and walls pictures draw (null for a Gymnasium world);
- ``free_area`` and ``log_free_area`` (pre-training, where missing): the world's free area;
- ``return_bounds`` (fine-tuning): the bounds of its task's returns.

A key run.json already holds is never changed, and a file that needs nothing is not rewritten,
so running the tool again changes nothing. Files are written atomically
(:func:`hmepol_cli.run.write_json`). From the repository root::

    python -m tools.backfill_run_json docs/results
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from hmepol_cli.config import backtracking_rule
from hmepol_cli.envs import ENVIRONMENTS, NavigationWorld, make_world
from hmepol_cli.errors import RunDirError
from hmepol_cli.finetune.task import recorded_return_bounds
from hmepol_cli.run import CONFIG, FINETUNE_CSV, RUN_INFO, read_json, write_json


class BackfillError(Exception):
    """Why one run.json cannot be brought up to date (one line)."""


def saved_config(run_dir: Path) -> DictConfig | None:
    """The config the run saved, interpolations resolved where they can be (a ``${hydra:...}``
    needs a running Hydra app); None when it saved none (some fine-tuning runs)."""
    for path in (run_dir / CONFIG, run_dir / ".hydra" / "config.yaml"):
        if path.is_file():
            cfg = OmegaConf.load(path)
            try:
                return OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
            except Exception:  # OmegaConf raises several errors for an unresolvable value
                return OmegaConf.create(OmegaConf.to_container(cfg, resolve=False))
    return None


def _env_entry(meta: dict[str, Any], cfg: DictConfig | None) -> DictConfig:
    """The run's ``env`` entry, with the world and wind run.json says it actually used."""
    saved = cfg.get("env") if cfg is not None else None  # a fine-tuning may leave it to its start
    env = dict(OmegaConf.to_container(saved)) if saved is not None else {}
    env["name"] = meta.get("env") or env.get("name")
    if meta.get("wind") is not None:
        env["wind"] = meta["wind"]
    return OmegaConf.create(env)


def missing_keys(run_dir: Path) -> dict[str, Any]:
    """The keys the run's run.json lacks, with the values the run would have recorded."""
    meta = read_json(run_dir / RUN_INFO)
    cfg = saved_config(run_dir)
    finetune = meta.get("kind") == "finetune" or (run_dir / FINETUNE_CSV).exists()
    env = _env_entry(meta, cfg)
    world_class = ENVIRONMENTS.get(str(env.name))
    if world_class is None:
        raise BackfillError(f"env {env.name!r} is not a world of this checkout")
    added: dict[str, Any] = {}
    if finetune:
        added["return_bounds"] = recorded_return_bounds(world_class.maps)
    elif cfg is None:
        raise BackfillError("it saved no config (config.yaml, .hydra/config.yaml)")
    else:
        added["backtracking"] = backtracking_rule(cfg.algo if "algo" in cfg else {})
    if not issubclass(world_class, NavigationWorld):
        added["world_map"] = None  # a Gymnasium world: pictures project its observations
    else:
        world = make_world(env)
        added["world_map"] = world.world_map()
        if not finetune:  # a fine-tuning's edge rule is its start's, which it may not record
            added["edge"] = world.facts()["edge"]
        if not finetune and "free_area" not in meta:
            free = [world.free_area(c) for c in range(world.n_configurations)]
            added |= {"free_area": free, "log_free_area": [math.log(f) for f in free]}
    return {key: value for key, value in added.items() if key not in meta}


def backfill(run_dir: Path) -> list[str]:
    """Add the keys run.json lacks (atomically; other keys as they are). -> the keys added"""
    added = missing_keys(run_dir)
    if added:
        write_json(run_dir / RUN_INFO, {**read_json(run_dir / RUN_INFO), **added})
    return sorted(added)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("roots", nargs="+", type=Path, help="folders searched for run.json")
    args = parser.parse_args(argv)
    changed = failed = 0
    for marker in sorted(m for root in args.roots for m in root.rglob(RUN_INFO)):
        try:
            added = backfill(marker.parent)
        except (BackfillError, RunDirError, ValueError) as error:  # a world refuses its config
            print(f"{marker.parent}: not brought up to date: {error}", file=sys.stderr)
            failed += 1
            continue
        if added:
            print(f"{marker.parent}: added {', '.join(added)}")
            changed += 1
    print(f"backfill: {changed} run.json files brought up to date, {failed} left as they were")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
