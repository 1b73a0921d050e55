"""The ``hmepol`` command: train, sweep, report, finetune, show.

``main`` takes the subcommand from argv, checks every config the command would run before
anything is written (composing it with Hydra's compose API), then hands the arguments to a
``@hydra.main`` app, so single runs, ``--cfg job``, ``-m`` and launchers all keep working
(STYLE.md, Hydra facts). Mistakes of input are one line (exit 2); a run whose numbers stop
making sense is recorded as failed and the command exits 1; anything else is a bug and keeps
its traceback.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import secrets
import sys
import time
import types
import warnings
from pathlib import Path

# OpenMP threads that spin while waiting slow torch down many-fold on a shared or oversubscribed
# machine (a sweep, a laptop); a user who wants spinning sets the variable themselves.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.core.plugins import Plugins
from hydra.errors import HydraException
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf, open_dict
from omegaconf.errors import OmegaConfBaseException

from hmepol_cli import sweeps
from hmepol_cli.config import register_configs, validate
from hmepol_cli.errors import (
    ConfigError,
    Interrupted,
    RunDirError,
    RunFailure,
    StorageError,
    UserError,
)
from hmepol_cli.rundir import RESUMABLE_KEYS, RUN_INFO, read_json, run_config
from hmepol_cli.signals import preemptible
from hydra_plugins.hmepol_population_launcher.population_launcher import PopulationLauncher

log = logging.getLogger("hmepol")

CONFIG_MODULE = "hmepol_cli.conf"
CONFIG_PATH = f"pkg://{CONFIG_MODULE}"
SWEEP_STATUS = "HMEPOL_SWEEP_STATUS"  # a file the jobs of a sweep report their outcome to

USAGE = """usage: hmepol COMMAND [overrides...]

commands:
  train     one run:            hmepol train env=corridor algo=hmepol seed=3
  sweep     a Hydra multirun:   hmepol sweep wind=0.05,0.15,0.25,0.4 seed=0,1,2,3
  report    thesis figures:     hmepol report [RUNS_DIR] [--out DIR]
  finetune  TRPO on a goal:     hmepol finetune init=<run dir> goal=random
  show      draw a world:       hmepol show env=corridor [--out FILE]

`hmepol COMMAND --help` says what a command does and lists its options. Any Hydra override
works with train, sweep and finetune (e.g. --cfg job, hydra/launcher=population).
`hmepol --version` (-V) prints the installed version.
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


def _unique_resolver() -> str:
    """A short random token: two runs started in the same second get different directories."""
    return secrets.token_hex(3)


OmegaConf.register_new_resolver("hmepol_run_dir", _run_dir_resolver, replace=True)
OmegaConf.register_new_resolver("hmepol_job_dir", _job_dir_resolver, replace=True)
OmegaConf.register_new_resolver("hmepol_unique", _unique_resolver, replace=True)
register_configs()
# Hydra scans the hydra_plugins namespace for launchers, which an editable install hides from
# it: register ours by hand (its public API; a no-op when the scan found it).
Plugins.instance().register(PopulationLauncher)


def fail(message: str, code: int = 2) -> None:
    print(f"hmepol: error: {message}", file=sys.stderr)
    raise SystemExit(code)


_PACKAGE_DIR = Path(__file__).resolve().parent
_python_warning_format = warnings.formatwarning


def _one_line_warning(message, category, filename, lineno, line=None) -> str:  # noqa: ANN001
    """Our own warnings (a skipped run, a stale lock taken over) as one line, like our errors;
    everyone else's keep Python's format, with the file and line they came from."""
    if Path(filename).resolve().is_relative_to(_PACKAGE_DIR):
        return f"hmepol: warning: {message}\n"
    return _python_warning_format(message, category, filename, lineno, line)


# --------------------------------------------------------------------------- checking first
def compose(config_name: str, overrides: list[str]) -> DictConfig:
    """The config ``overrides`` compose to (Hydra's own keys left out), or one clear line."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    task = [o for o in overrides if not o.lstrip("+~").startswith("hydra")]
    GlobalHydra.instance().clear()
    try:
        with initialize_config_module(config_module=CONFIG_MODULE, version_base="1.3"):
            return hydra_compose(config_name=config_name, overrides=task)
    except (HydraException, OmegaConfBaseException) as error:
        raise ConfigError(_hydra_message(error, config_name)) from None
    except AssertionError:  # OmegaConf, setting a key below a group left at null
        nested = [o for o in task if "." in o.partition("=")[0]]
        raise ConfigError(
            f"cannot apply {' '.join(nested) or ' '.join(task)}: choose its group first "
            "(e.g. env=corridor, not env.name=corridor)"
        ) from None
    finally:
        GlobalHydra.instance().clear()


def _hydra_message(error: Exception, config_name: str = "config") -> str:
    """Hydra's and OmegaConf's errors, as one line that says what is allowed."""
    text = str(error)
    key = re.search(r"Key '([^']+)' (?:is )?not in", text) or re.search(
        r"Could not override '([^']+)'", text
    )
    if key:
        return _unknown_key(key.group(1), config_name)
    choice = re.search(r"Could not find '([^']+)/([^'/]+)'", text)
    if choice:
        group, name = choice.groups()
        options = _group_options(group)
        listed = f"; choose one of: {', '.join(options)}" if options else ""
        return f"{group}={name!r} is not an option of {group}{listed}"
    merging = re.search(r"Error merging override (\S+?)=(.*)", text)
    if merging:
        name, value = merging.groups()
        kind = _schema_kind(name.lstrip("+~"), config_name)
        return f"{name}={value!r} is not allowed: {name} takes {kind}"
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return lines[0] if lines else type(error).__name__


def _schema(config_name: str):
    from hmepol_cli.config import Config, FinetuneConfig

    return FinetuneConfig if config_name == "finetune" else Config


def _schema_keys(cls, prefix: str = "") -> list[str]:
    """Every dotted key of a schema dataclass."""
    import dataclasses
    import typing

    keys = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        inner = [t for t in typing.get_args(hints[f.name]) or [hints[f.name]]
                 if dataclasses.is_dataclass(t)]  # fmt: skip
        keys.append(f"{prefix}{f.name}")
        if inner:
            keys += _schema_keys(inner[0], f"{prefix}{f.name}.")
    return keys


def _unknown_key(key: str, config_name: str) -> str:
    import difflib

    keys = _schema_keys(_schema(config_name))
    near = difflib.get_close_matches(key, keys, n=3, cutoff=0.6)
    if not near:  # the right name in the wrong place (lr for algo.lr)
        leaves = {k.rpartition(".")[2]: k for k in keys}
        near = [leaves[m] for m in difflib.get_close_matches(key, list(leaves), n=2, cutoff=0.6)]
    hint = f"; did you mean {' or '.join(near)}?" if near else " (--help lists the settings)"
    return f"unknown key {key!r}: not a hmepol setting{hint}"


def _group_options(group: str) -> list[str]:
    """The options of a config group: its YAML files (hydra/launcher: ours and Hydra's)."""
    from importlib.resources import files

    folder = files(CONFIG_MODULE).joinpath(*group.split("/"))
    options = sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".yaml"))
    if group == "hydra/launcher":
        options = sorted({*options, "basic", "joblib", "submitit_local", "submitit_slurm"})
    return options


def _schema_kind(key: str, config_name: str) -> str:
    """What a key of the schema takes, in words."""
    import dataclasses
    import typing

    cls = _schema(config_name)
    *parents, last = key.split(".")
    try:
        for part in parents:
            hint = typing.get_type_hints(cls)[part]
            cls = next(t for t in typing.get_args(hint) or [hint] if dataclasses.is_dataclass(t))
        hint = typing.get_type_hints(cls)[last]
    except (KeyError, StopIteration, TypeError):
        return "another kind of value"
    union = typing.get_origin(hint) in (typing.Union, types.UnionType)
    args = [a for a in typing.get_args(hint) if a is not type(None)] if union else [hint]
    optional = " (or null)" if union and type(None) in typing.get_args(hint) else ""
    base = args[0]
    words = {int: "a whole number", float: "a number", bool: "true or false", str: "text"}
    if typing.get_origin(base) is list:
        (item,) = typing.get_args(base) or (typing.Any,)
        kind = {int: "whole numbers", float: "numbers"}.get(item, "values")
        return f"a list of {kind}, e.g. [300,300]{optional}"
    return words.get(base, "another kind of value") + optional


def _check_known_keys(cfg: DictConfig, schema: DictConfig, prefix: str = "") -> None:
    """Refuse keys the schema does not have (Hydra lets ``+key=value`` add any)."""
    for key in cfg:
        path = f"{prefix}{key}"
        if key not in schema:
            raise ConfigError(_unknown_key(path, "config"))
        node, spec = cfg[key], schema[key]
        if OmegaConf.is_dict(node) and OmegaConf.is_dict(spec):
            _check_known_keys(node, spec, f"{path}.")


def _check_output_dirs(overrides: list[str]) -> None:
    """An output folder given on the command line must be a folder, if it exists; a launcher
    must be one there is."""
    for item in overrides:
        key, _, value = item.partition("=")
        if key == "hydra/launcher" and value not in _group_options("hydra/launcher"):
            options = ", ".join(_group_options("hydra/launcher"))
            raise ConfigError(
                f"hydra/launcher={value!r} is not a launcher; choose one of: {options}"
            )
    for item in overrides:
        key, _, value = item.partition("=")
        if key in ("hydra.run.dir", "hydra.sweep.dir", "output_dir") and value:
            if Path(value).exists() and not Path(value).is_dir():
                raise ConfigError(f"{key}={value!r} is a file, not a folder")


def check_train(overrides: list[str]) -> DictConfig:
    """The config of ``hmepol train overrides``, checked, before Hydra writes anything."""
    from hmepol_cli.config import Config

    _check_output_dirs(overrides)
    resume = next((o.partition("=")[2] for o in overrides if o.startswith("resume=")), None)
    if resume not in (None, "", "null"):
        run_config(Path(resume))  # a clear error for a folder that is not a run
    cfg = compose("config", overrides)
    _check_known_keys(cfg, OmegaConf.structured(Config))
    if cfg.resume is not None:
        cfg = resumed_config(cfg, Path(cfg.resume), overrides)
    validate(cfg)
    return cfg


def check_sweep(overrides: list[str]) -> int:
    """Check the config of every job a sweep would run, before anything is written. -> jobs"""
    _check_output_dirs(overrides)
    task = [o for o in overrides if not o.lstrip("+~").startswith("hydra")]
    try:
        jobs = sweeps.jobs(task)
    except HydraException as error:
        raise ConfigError(_hydra_message(error, "config")) from None
    seen = set()
    for job in jobs:
        key = tuple(job)
        if key not in seen:
            seen.add(key)
            check_train(list(job))
    return len(jobs)


def resumed_config(cfg: DictConfig, run_dir: Path, overrides: list[str]) -> DictConfig:
    """The config a run started with, with the keys a continuation may change taken from the
    command line; any other override is refused (the run keeps what it is)."""
    saved = run_config(run_dir)
    changed = []
    with open_dict(saved):
        for item in overrides:
            key = item.lstrip("+~").partition("=")[0]
            if key.startswith("hydra") or key == "resume":
                continue
            if key in RESUMABLE_KEYS or key.split(".")[0] in RESUMABLE_KEYS:
                OmegaConf.update(saved, key, OmegaConf.select(cfg, key), force_add=True)
            elif OmegaConf.select(cfg, key) != OmegaConf.select(saved, key):
                changed.append(item)  # giving a run the value it already has is no change
        saved.resume = str(run_dir)
    if changed:
        raise ConfigError(
            f"{run_dir} keeps the config it started with; {', '.join(changed)} cannot change on "
            f"resume (only {', '.join(RESUMABLE_KEYS[:5])}, ... can)"
        )
    return saved


# --------------------------------------------------------------------------- train / sweep
def _parallel_jobs() -> int:
    """How many jobs of this sweep run at once (joblib's n_jobs; 1 outside a parallel sweep)."""
    if not HydraConfig.initialized():
        return 1
    hc = HydraConfig.get()
    n_jobs = OmegaConf.select(hc, "launcher.n_jobs") if hc.mode == RunMode.MULTIRUN else None
    if not n_jobs:
        return 1
    return (os.cpu_count() or 1) if n_jobs < 0 else int(n_jobs)


def _set_threads(cfg: DictConfig) -> None:
    if cfg.threads > 0:
        torch.set_num_threads(int(cfg.threads))
        return
    n_jobs = _parallel_jobs()
    if n_jobs > 1:  # joblib reuses workers: set threads inside each job so jobs don't oversubscribe
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // n_jobs))


def say(line: str, stream=None) -> None:
    """One line to stdout in one write: parallel jobs share the stream, and with
    PYTHONUNBUFFERED ``print`` writes the text and its newline apart, so two jobs' lines can
    join into one."""
    stream = sys.stdout if stream is None else stream
    stream.write(line + "\n")
    stream.flush()


def _finished_line(run_dir: Path, seconds: float) -> str:
    """'run written to DIR' with, in a parallel sweep, what a person watching wants to know."""
    if _parallel_jobs() <= 1:
        return f"hmepol: run written to {run_dir}"
    info = read_json(run_dir / RUN_INFO)
    last = _last_row(run_dir / "epochs.csv")
    entropy = f", H={float(last['entropy']):.3f} nats" if "entropy" in last else ""
    minutes, rest = divmod(int(round(seconds)), 60)
    return (
        f"hmepol: job {HydraConfig.get().job.num} finished: {info.get('env')}/{info.get('algo')} "
        f"seed {info.get('seed')}, {info.get('epochs_done')} epochs{entropy}, "
        f"{minutes} min {rest} s -> {run_dir}"
    )


def _last_row(path: Path) -> dict[str, str]:
    try:
        lines = path.read_text().splitlines()
    except OSError:
        return {}
    return dict(zip(lines[0].split(","), lines[-1].split(","), strict=False)) if lines else {}


def _train(cfg: DictConfig) -> list[str]:
    """One run, or a population (``seeds=[...]``, or ``members=[...]`` from the population
    launcher): members that differ only in member-scalar keys (hmepol_cli/members.py)."""
    if cfg.seeds or cfg.members:
        if cfg.resume is not None:
            raise ConfigError("resume= continues one run; give it a member's run directory")
        members = _population_members(cfg)
        if HydraConfig.get().mode == RunMode.MULTIRUN:
            _remove_if_empty(Path(HydraConfig.get().runtime.output_dir))  # the job's own folder
    elif cfg.resume is not None:
        run_dir = Path(cfg.resume)
        members = [(resumed_config(cfg, run_dir, list(HydraConfig.get().overrides.task)), run_dir)]
    else:
        members = [(cfg, Path(HydraConfig.get().runtime.output_dir))]
    return train_runs(members, resume=cfg.resume is not None)


def _population_members(cfg: DictConfig) -> list[tuple[DictConfig, Path]]:
    """Each member's config, and the run directory the same job with the member's own
    overrides instead of ``seeds=[...]`` / ``members=[...]`` would have had: a population
    leaves ordinary runs where the ungrouped sweep would. (A single ``hmepol train
    seeds=[...]`` puts them in ``<run dir>/seed<s>``.)

    ``members``: one string per member, its own overrides separated by spaces
    (``"seed=0 wind=0.05"``), composed with the job's others."""
    from hydra import compose as hydra_compose

    hc = HydraConfig.get()
    common = [o for o in hc.overrides.task if _key(o) not in ("seeds", "members")]
    if cfg.seeds:
        seeds = [int(s) for s in cfg.seeds]
        if len(set(seeds)) != len(seeds):
            raise ConfigError(f"seeds={seeds} holds a seed twice")
        own = [[f"seed={s}"] for s in seeds]
    else:
        own = [str(m).split() for m in cfg.members]
    members = []
    for i, overrides in enumerate(own):
        if cfg.seeds:
            member = cfg.copy()
            with open_dict(member):
                member.seed, member.seeds = int(overrides[0].partition("=")[2]), None
        else:
            member = hydra_compose(config_name="config", overrides=[*common, *overrides])
        if hc.mode == RunMode.MULTIRUN:
            run_dir = Path(str(hc.sweep.dir)) / _member_subdir(hc, [*common, *overrides])
        elif cfg.seeds:
            run_dir = Path(hc.runtime.output_dir) / f"seed{member.seed}"
        else:
            run_dir = Path(hc.runtime.output_dir) / f"member{i}"
        members.append((member, run_dir))
    return members


def _remove_if_empty(folder: Path) -> None:
    """Hydra makes a folder for every job; a population's job writes into its members'."""
    try:
        folder.rmdir()
    except OSError:  # not empty, or not there
        pass


def _key(override: str) -> str:
    return override.lstrip("+~").partition("=")[0]


def _member_subdir(hc: DictConfig, overrides: list[str]) -> str:
    """hydra.sweep.subdir of the job with these overrides (a population member's own job)."""
    naming = hc.job.config.override_dirname
    dirname = sweeps.override_dirname(
        overrides, list(naming.exclude_keys), naming.item_sep, naming.kv_sep
    )
    job = OmegaConf.create({"hydra": OmegaConf.to_container(hc, resolve=False)})
    job.hydra.job.override_dirname = dirname
    return str(job.hydra.sweep.subdir)


def train_runs(members: list[tuple[DictConfig, Path]], resume: bool = False) -> list[str]:
    """Train runs that differ only in their seed as one population (skipping finished ones,
    continuing interrupted ones). -> their run directories; RunFailure if any failed."""
    from hmepol_cli.trainer import Trainer

    todo, resuming = [], resume
    for cfg, run_dir in members:
        validate(cfg)
        info_file = run_dir / RUN_INFO
        if not resume and info_file.exists():
            try:
                info = read_json(info_file)
            except RunDirError:  # damaged: the run rewrites it when it opens its directory
                info = {}
            if (
                cfg.skip_finished
                and info.get("status") == "finished"
                and info.get("epochs_done", 0) >= cfg.epochs
            ):
                say(f"hmepol: {run_dir} already finished ({cfg.epochs} epochs); skipped")
                continue
            resuming = True  # an interrupted (or failed) job continues where it stopped
        todo.append((cfg, run_dir))
    if todo:
        _set_threads(todo[0][0])
        if _parallel_jobs() > 1:  # bars of parallel jobs share one line: a line per job instead
            for cfg, _ in todo:
                cfg.progress = False
        for _, run_dir in todo:
            say(f"hmepol: training into {run_dir}")
        started = time.monotonic()
        trainer = Trainer([c for c, _ in todo], [d for _, d in todo])
        try:
            trainer.train(resume=resuming)
        except Interrupted as error:  # say where each run stopped
            error.runs = [(d, _epochs_done(d)) for _, d in todo]
            raise
        except StorageError as error:
            kept = ", ".join(f"{d} up to epoch {_epochs_done(d)}" for _, d in todo)
            raise StorageError(
                f"{error}: kept {kept} (the last checkpoint); free space and run the same command "
                "again to continue"
            ) from None
        failures = trainer.failures
        for run_dir in (d for _, d in todo if d not in failures):
            say(_finished_line(run_dir, time.monotonic() - started))
        if failures:
            raise RunFailure(
                "; ".join(f"{run_dir}: {reason}" for run_dir, reason in failures.items())
            )
    return [str(d) for _, d in members]


def _epochs_done(run_dir: Path) -> int:
    try:
        return int(read_json(run_dir / RUN_INFO).get("epochs_done", 0))
    except (RunDirError, OSError):
        return 0


def _report_job(outcome: str, cfg: DictConfig, reason: str = "") -> None:
    """Tell the sweep that started this job how it ended (a line in its status file, which
    lies in the sweep's folder, so that a job on another host of a cluster can write it)."""
    path = os.environ.get(SWEEP_STATUS)
    if not path:
        return
    job = " ".join(HydraConfig.get().overrides.task)
    with open(path, "a") as f:
        f.write(json.dumps({"job": job, "outcome": outcome, "reason": reason}) + "\n")


def interrupted_line(error: Interrupted) -> str:
    """What an interrupted command says: where each run stopped, and how to go on."""
    kept = ", ".join(f"{d} up to epoch {n}" for d, n in getattr(error, "runs", [])) or "its runs"
    return f"{error}: kept {kept} (the last checkpoint); run the same command again to continue"


@hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name="config")
def train_app(cfg: DictConfig) -> list[str] | None:
    multirun = HydraConfig.get().mode == RunMode.MULTIRUN
    with preemptible():
        try:
            runs = _train(cfg)
        except UserError as error:
            if multirun:  # the sweep goes on, and ends with a table of its failed jobs
                _report_job("failed", cfg, str(error))
                return None
            fail(str(error), code=1 if isinstance(error, RunFailure | StorageError) else 2)
        except Interrupted as error:
            _report_job("interrupted", cfg, str(error))
            print(f"hmepol: {interrupted_line(error)}", file=sys.stderr, flush=True)
            raise SystemExit(error.exit_code) from None
    _report_job("done", cfg)
    return runs


def _sweep(args: list[str], n_jobs: int = 0) -> None:
    """Run a Hydra multirun; end with a table of the jobs that failed or were interrupted (and
    how many never started), and exit 1 (failed) or 128 + the signal (interrupted)."""
    launcher = (
        [] if any(a.startswith("hydra/launcher=") for a in args) else ["hydra/launcher=local"]
    )
    sweep_dir = next(
        (a.partition("=")[2] for a in args if a.startswith("hydra.sweep.dir=")), "outputs/sweep"
    )
    Path(sweep_dir).mkdir(parents=True, exist_ok=True)
    status = Path(sweep_dir) / f".hmepol-sweep-{secrets.token_hex(4)}.jsonl"
    status.touch()
    os.environ[SWEEP_STATUS] = str(status.resolve())
    sys.argv = ["hmepol", "--multirun", *launcher, *args]
    code = 0
    try:
        with preemptible():
            train_app()
    except SystemExit as exit_:  # a job was interrupted, or Hydra ended the sweep
        code = exit_.code if isinstance(exit_.code, int) else 1
    except Interrupted as error:  # the signal reached this process while it waited for jobs
        code = error.exit_code
    finally:
        lines = [json.loads(line) for line in status.read_text().splitlines() if line]
        status.unlink(missing_ok=True)
        os.environ.pop(SWEEP_STATUS, None)
    for outcome in ("failed", "interrupted"):
        jobs = [job for job in lines if job["outcome"] == outcome]
        if jobs:
            print(f"hmepol: {len(jobs)} of {n_jobs or len(lines)} jobs {outcome}:", file=sys.stderr)
            for job in jobs:
                print(f"  {job['job']}\n      {job['reason']}", file=sys.stderr)
    unstarted = n_jobs - len(lines) if n_jobs and code > 128 else 0
    if unstarted > 0:
        print(f"hmepol: {unstarted} of {n_jobs} jobs did not start", file=sys.stderr)
    if any(job["outcome"] != "done" for job in lines) or unstarted:
        print("hmepol: run the sweep again to retry or continue them", file=sys.stderr)
    if any(job["outcome"] == "failed" for job in lines):
        code = code or 1
    if code:
        raise SystemExit(code)


# --------------------------------------------------------------------------- finetune
@hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name="finetune")
def finetune_app(cfg: DictConfig) -> str | None:
    from hmepol_cli.finetune import finetune

    with preemptible():
        try:
            return str(finetune(cfg))
        except UserError as error:
            fail(str(error))
        except Interrupted as error:
            print(f"hmepol: {error}: the fine-tuning's rows so far are kept; running it again "
                  "starts it over", file=sys.stderr, flush=True)  # fmt: skip
            raise SystemExit(error.exit_code) from None
    return None


# --------------------------------------------------------------------------- report / show
def _report(args: list[str]) -> None:
    import argparse

    from hmepol_cli.report import run_report

    parser = argparse.ArgumentParser(
        prog="hmepol report",
        description="Aggregate finished runs into the thesis' figures and tables: mean and 95% "
        "confidence interval over seeds of every curve and bar of chapter 5, a summary table "
        "with the differences between algorithms, and index.html to read them.",
    )
    parser.add_argument(
        "runs",
        nargs="*",
        default=["outputs"],
        help="folders holding run directories, searched recursively (default: outputs)",
    )
    parser.add_argument(
        "--out", default=None, help="report folder (default: the first RUNS folder's report/)"
    )
    ns = parser.parse_args(args)
    roots = [Path(r) for r in ns.runs]
    for runs in roots:
        if not runs.is_dir():
            fail(f"{str(runs)!r} is not a directory of runs")
    out = Path(ns.out) if ns.out else roots[0] / "report"
    if out.exists() and not out.is_dir():
        fail(f"--out {str(out)!r} is a file; give a folder for the report")
    try:
        index = run_report(roots, out)
    except UserError as error:
        fail(str(error))
    print(f"hmepol: report written to {index}")


def _show(args: list[str]) -> None:
    import argparse

    from hmepol_cli.envs import ENVIRONMENTS, make_world
    from hmepol_cli.envs.render import show_world

    parser = argparse.ArgumentParser(
        prog="hmepol show",
        description="Draw every configuration of a world (north up): walls, start area, the "
        "slope or wind, and each configuration's probability.",
    )
    parser.add_argument("overrides", nargs="*", help="env=NAME [wind=FORCE]")
    parser.add_argument("--out", default=None, help="PNG file (default: outputs/show/<env>.png)")
    ns = parser.parse_args(args)
    values = dict(item.partition("=")[::2] for item in ns.overrides)
    unknown = set(values) - {"env", "wind"}
    if unknown:
        fail(f"unknown option(s) {', '.join(sorted(unknown))}; use env=NAME and wind=FORCE")
    name = values.get("env", "slope")
    # Only the 2-D worlds are maps; a Gymnasium world has no walls to draw.
    maps = [n for n, world in ENVIRONMENTS.items() if world.maps]
    if name not in maps:
        fail(f"env={name!r} cannot be drawn; choose one of: {', '.join(maps)}")
    try:
        wind = float(values.get("wind", 0.4))
    except ValueError:
        fail(f"wind={values['wind']!r} is not a number")
    if not 0 <= wind < float("inf"):
        fail(f"wind={wind!r} must be a finite number >= 0")
    world = make_world(OmegaConf.create({"name": name, "wind": wind, "edge": "slide"}))
    out = Path(ns.out or f"outputs/show/{name}.png")
    show_world(world, out)
    print(f"hmepol: {name} drawn to {out}")


# --------------------------------------------------------------------------- dispatch
def _asks_for_help(args: list[str]) -> bool:
    return any(a in ("--help", "-h", "--hydra-help", "--cfg", "-c", "--info") for a in args)


def package_version() -> str:
    """The installed distribution's version (pyproject.toml's, as pip recorded it)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("hmepol")
    except PackageNotFoundError:
        fail("hmepol is not installed, so it has no version: pip install -e . (or the wheel)")


def main(argv: list[str] | None = None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(USAGE)
        return
    if argv[0] in ("-V", "--version"):
        print(f"hmepol {package_version()}")
        return
    command, rest = argv[0], argv[1:]
    warnings.formatwarning = _one_line_warning
    try:
        if command == "train":
            if not _asks_for_help(rest):
                check_train([a for a in rest if not a.startswith("-")])
            sys.argv = ["hmepol", *rest]
            train_app()
        elif command == "sweep":
            if not _asks_for_help(rest):
                n_jobs = check_sweep([a for a in rest if not a.startswith("-")])
            else:
                n_jobs = 0
            _sweep(rest, n_jobs)
        elif command == "finetune":
            if not _asks_for_help(rest):
                from hmepol_cli.config import FinetuneConfig
                from hmepol_cli.finetune import check_finetune

                overrides = [a for a in rest if not a.startswith("-")]
                _check_output_dirs(overrides)
                cfg = compose("finetune", overrides)
                _check_known_keys(cfg, OmegaConf.structured(FinetuneConfig))
                check_finetune(cfg)
            sys.argv = ["hmepol", *rest]
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
    except UserError as error:
        fail(str(error))


if __name__ == "__main__":
    main()
