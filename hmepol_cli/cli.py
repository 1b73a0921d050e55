"""The ``hmepol`` command: train, sweep, report, finetune, show.

``main`` takes the subcommand from argv and hands the rest to a ``@hydra.main`` app, so single
runs, ``--cfg job``, ``-m`` and launchers all keep working (STYLE.md, Hydra facts).
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import sys
from pathlib import Path

# OpenMP threads that spin while waiting slow torch down many-fold on a shared or oversubscribed
# machine (a sweep, a laptop); a user who wants spinning sets the variable themselves.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.core.plugins import Plugins
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf, open_dict

from hmepol_cli.checkpoint import RUN_INFO, RunDirError, read_json, run_config
from hmepol_cli.config import ConfigError, register_configs, validate
from hydra_plugins.hmepol_population_launcher.population_launcher import PopulationLauncher

log = logging.getLogger("hmepol")

CONFIG_PATH = "pkg://hmepol_cli.conf"
# Keys a resumed run may change; everything else comes from the run's saved config.
RESUMABLE_KEYS = ("epochs", "device", "progress", "threads", "eval.every")

USAGE = """usage: hmepol COMMAND [overrides...]

commands:
  train     one run:            hmepol train env=corridor algo=hmepol seed=3
  sweep     a Hydra multirun:   hmepol sweep wind=0.05,0.15,0.25,0.4 seed=0,1,2,3
  report    thesis figures:     hmepol report [RUNS_DIR] [--out DIR]
  finetune  TRPO on a goal:     hmepol finetune init=<run dir> goal=random
  show      draw a world:       hmepol show env=corridor [--out FILE]

Any Hydra override works with train, sweep and finetune (e.g. --cfg job, hydra/launcher=slurm).
"""


def _run_dir_resolver(resume: str | None, default: str) -> str:
    return str(resume) if resume else default


def _job_dir_resolver(override_dirname: str) -> str:
    """A sweep job's folder: its overrides, readable, safe to pass back unquoted as an override
    (``init=outputs/sweep/algo-hmepol_seed-0``), and short enough for any filesystem."""
    name = override_dirname.replace("=", "-").replace(",", "_")
    name = re.sub(r"[^A-Za-z0-9._+-]", "", name) or "default"
    if len(name) <= 120:
        return name
    digest = hashlib.sha1(name.encode()).hexdigest()[:10]
    return f"{name[:100]}-{digest}"


OmegaConf.register_new_resolver("hmepol_run_dir", _run_dir_resolver, replace=True)
OmegaConf.register_new_resolver("hmepol_job_dir", _job_dir_resolver, replace=True)
register_configs()
# Hydra scans the hydra_plugins namespace for launchers, which an editable install hides from
# it: register ours by hand (its public API; a no-op when the scan found it).
Plugins.instance().register(PopulationLauncher)


class UserError(Exception):
    """Any mistake of the user's that gets one line, not a traceback."""


def fail(message: str, code: int = 2) -> None:
    print(f"hmepol: error: {message}", file=sys.stderr)
    raise SystemExit(code)


# --------------------------------------------------------------------------- train / sweep
def _set_threads(cfg: DictConfig) -> None:
    if cfg.threads > 0:
        torch.set_num_threads(int(cfg.threads))
        return
    hc = HydraConfig.get()
    n_jobs = OmegaConf.select(hc, "launcher.n_jobs") if hc.mode == RunMode.MULTIRUN else None
    if n_jobs:  # joblib reuses workers: set threads inside each job so jobs don't oversubscribe
        n_jobs = os.cpu_count() if n_jobs < 0 else n_jobs
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // n_jobs))


def _resumed_config(cfg: DictConfig, run_dir: Path) -> DictConfig:
    saved = run_config(run_dir)
    overrides = HydraConfig.get().overrides.task
    with open_dict(saved):
        for item in overrides:
            key, _, value = item.partition("=")
            if key in RESUMABLE_KEYS:
                OmegaConf.update(saved, key, OmegaConf.select(cfg, key))
            elif key not in ("resume",) and not key.startswith("hydra"):
                log.warning("ignoring %s on resume: the run keeps the config it started with", item)
        saved.resume = str(run_dir)
    return saved


def _train(cfg: DictConfig) -> list[str]:
    """One run, or a population (``seeds=[...]``): members that differ only in their seed."""
    if cfg.seeds:
        if cfg.resume is not None:
            raise ConfigError("resume= continues one run; give it a member's run directory")
        members = _population_members(cfg)
    elif cfg.resume is not None:
        members = [(_resumed_config(cfg, Path(cfg.resume)), Path(cfg.resume))]
    else:
        members = [(cfg, Path(HydraConfig.get().runtime.output_dir))]
    return train_runs(members, resume=cfg.resume is not None)


def _population_members(cfg: DictConfig) -> list[tuple[DictConfig, Path]]:
    """Each seed's config, and the run directory the same job with ``seed=<s>`` instead of
    ``seeds=[...]`` would have had: a population leaves ordinary runs where a sweep over seed
    would. (A single ``hmepol train seeds=[...]`` puts them in ``<run dir>/seed<s>``.)"""
    seeds = [int(s) for s in cfg.seeds]
    if len(set(seeds)) != len(seeds):
        raise ConfigError(f"seeds={seeds} holds a seed twice")
    hc = HydraConfig.get()
    members = []
    for seed in seeds:
        member = cfg.copy()
        with open_dict(member):
            member.seed, member.seeds = seed, None
        if hc.mode == RunMode.MULTIRUN:
            run_dir = Path(str(hc.sweep.dir)) / _member_subdir(hc, seed)
        else:
            run_dir = Path(hc.runtime.output_dir) / f"seed{seed}"
        members.append((member, run_dir))
    return members


def _member_subdir(hc: DictConfig, seed: int) -> str:
    """hydra.sweep.subdir of this job with ``seeds=[...]`` replaced by ``seed=<seed>``."""
    from hydra._internal.config_loader_impl import get_overrides_dirname
    from hydra.core.override_parser.overrides_parser import OverridesParser

    lines = [o for o in hc.overrides.task if o.lstrip("+~").partition("=")[0] != "seeds"]
    overrides = OverridesParser.create().parse_overrides([*lines, f"seed={seed}"])
    naming = hc.job.config.override_dirname
    dirname = get_overrides_dirname(
        overrides, list(naming.exclude_keys), naming.item_sep, naming.kv_sep
    )
    job = OmegaConf.create({"hydra": OmegaConf.to_container(hc, resolve=False)})
    job.hydra.job.override_dirname = dirname
    return str(job.hydra.sweep.subdir)


def train_runs(members: list[tuple[DictConfig, Path]], resume: bool = False) -> list[str]:
    """Train runs that differ only in their seed as one population (skipping finished ones,
    continuing interrupted ones). -> their run directories"""
    from hmepol_cli.trainer import Trainer

    todo, resuming = [], resume
    for cfg, run_dir in members:
        validate(cfg)
        info_file = run_dir / RUN_INFO
        if not resume and info_file.exists():
            info = read_json(info_file)
            if (
                cfg.skip_finished
                and info.get("status") == "finished"
                and info.get("epochs_done", 0) >= cfg.epochs
            ):
                print(f"hmepol: {run_dir} already finished ({cfg.epochs} epochs); skipped")
                continue
            resuming = True  # an interrupted sweep job continues where it stopped
        todo.append((cfg, run_dir))
    if todo:
        _set_threads(todo[0][0])
        trainer = Trainer([c for c, _ in todo], [d for _, d in todo])
        if resuming:
            for s in trainer.restore():
                member = trainer.members[s]
                print(f"hmepol: resuming {member.run_dir} at epoch {member.start_epoch}")
        trainer.train()
        for _, run_dir in todo:
            print(f"hmepol: run written to {run_dir}")
    return [str(d) for _, d in members]


@hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name="config")
def train_app(cfg: DictConfig) -> str | None:
    try:
        return _train(cfg)
    except (ConfigError, RunDirError, UserError, ValueError) as error:
        if HydraConfig.get().mode == RunMode.MULTIRUN:
            # A failed job must not stop the others: say why and let the sweep go on.
            log.error("job failed: %s", error)
            print(f"hmepol: error: {error}", file=sys.stderr)
            return None
        fail(str(error))
    return None


# --------------------------------------------------------------------------- finetune
@hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name="finetune")
def finetune_app(cfg: DictConfig) -> str | None:
    from hmepol_cli.finetune import finetune

    try:
        return str(finetune(cfg))
    except (ConfigError, RunDirError, UserError, ValueError) as error:
        fail(str(error))
    return None


# --------------------------------------------------------------------------- report / show
def _report(args: list[str]) -> None:
    import argparse

    from hmepol_cli.report import run_report

    parser = argparse.ArgumentParser(
        prog="hmepol report", description="Thesis figures from finished runs."
    )
    parser.add_argument(
        "runs",
        nargs="?",
        default="outputs",
        help="folder holding run directories (default: outputs)",
    )
    parser.add_argument("--out", default=None, help="report folder (default: RUNS/report)")
    ns = parser.parse_args(args)
    runs = Path(ns.runs)
    out = Path(ns.out) if ns.out else runs / "report"
    try:
        index = run_report(runs, out)
    except ValueError as error:
        fail(str(error))
    print(f"hmepol: report written to {index}")


def _show(args: list[str]) -> None:
    import argparse

    from hmepol_cli.envs import ENVIRONMENTS, make_world
    from hmepol_cli.envs.render import show_world

    parser = argparse.ArgumentParser(
        prog="hmepol show", description="Draw every configuration of a world."
    )
    parser.add_argument("overrides", nargs="*", help="env=NAME [wind=FORCE]")
    parser.add_argument("--out", default=None, help="PNG file (default: outputs/show/<env>.png)")
    ns = parser.parse_args(args)
    values = dict(item.partition("=")[::2] for item in ns.overrides)
    unknown = set(values) - {"env", "wind"}
    if unknown:
        fail(f"unknown option(s) {', '.join(sorted(unknown))}; use env=NAME and wind=FORCE")
    name = values.get("env", "slope")
    if name not in ENVIRONMENTS:
        fail(f"unknown env {name!r}; choose one of: {', '.join(ENVIRONMENTS)}")
    try:
        wind = float(values.get("wind", 0.4))
    except ValueError:
        fail(f"wind={values['wind']!r} is not a number")
    if wind < 0:
        fail(f"wind={wind!r} must be a number >= 0")
    world = make_world(OmegaConf.create({"name": name, "wind": wind}))
    out = Path(ns.out or f"outputs/show/{name}.png")
    show_world(world, out)
    print(f"hmepol: {name} drawn to {out}")


# --------------------------------------------------------------------------- dispatch
def _check_resume(args: list[str]) -> None:
    """Refuse a resume directory that is not a run before Hydra creates anything in it."""
    for item in args:
        if item.startswith("resume="):
            value = item.partition("=")[2]
            if value not in ("", "null"):
                try:
                    run_config(Path(value))
                except RunDirError as error:
                    fail(str(error))


def main(argv: list[str] | None = None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    prog = "hmepol"
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(USAGE)
        return
    command, rest = argv[0], argv[1:]
    if command == "train":
        _check_resume(rest)
        sys.argv = [prog, *rest]
        train_app()
    elif command == "sweep":
        launcher = (
            [] if any(a.startswith("hydra/launcher=") for a in rest) else ["hydra/launcher=local"]
        )
        sys.argv = [prog, "--multirun", *launcher, *rest]
        train_app()
    elif command == "finetune":
        sys.argv = [prog, *rest]
        finetune_app()
    elif command == "report":
        _report(rest)
    elif command == "show":
        _show(rest)
    else:
        fail(
            f"unknown command {command!r}; choose train, sweep, report, finetune or show "
            "(hmepol --help)"
        )


if __name__ == "__main__":
    main()
