"""The ``hmepol`` command: train, sweep, report, finetune, show.

``main`` takes the subcommand from argv and checks every config the command would run before
anything is written (:mod:`hmepol_cli.checks`, with Hydra's compose API). ``train`` composes its
config once, checks it and runs it as Hydra's job (:func:`run_train`); a sweep checks every job,
then hands the arguments to the ``@hydra.main`` app, whose launcher composes each job it runs
(as do ``--cfg job``, ``--help`` and Hydra's other flags). Mistakes of input are one line (exit
2); a run whose numbers stop making sense is recorded as failed and the command exits 1;
anything else is a bug and keeps its traceback.
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
import warnings
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.core.plugins import Plugins
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf, open_dict

from hmepol_cli.checks import (
    CONFIG_MODULE,
    check_config,
    check_finetune_overrides,
    check_output_dirs,
    check_sweep,
    check_train,
    compose,
    compose_here,
    override_value,
    unquote,
)
from hmepol_cli.config import register_configs, validate
from hmepol_cli.errors import (
    ConfigError,
    Interrupted,
    RunDirError,
    RunFailure,
    StorageError,
    UserError,
)
from hmepol_cli.members import population_members
from hmepol_cli.precision import auto_reason, device_type
from hmepol_cli.resume import resumed_config
from hmepol_cli.run import RUN_INFO, read_json
from hmepol_cli.signals import preemptible
from hydra_plugins.hmepol_population_launcher.population_launcher import PopulationLauncher

log = logging.getLogger("hmepol")

CONFIG_PATH = f"pkg://{CONFIG_MODULE}"
SWEEP_STATUS = "HMEPOL_SWEEP_STATUS"  # a file the jobs of a sweep report their outcome to

USAGE = """usage: hmepol COMMAND [overrides...]

commands:
  train     one run:            hmepol train env=corridor algo=hmepol seed=3
  sweep     a Hydra multirun:   hmepol sweep wind=0.05,0.15,0.25,0.4 seed=0,1,2,3
  report    thesis figures:     hmepol report [RUNS_DIR] [--out DIR]
  finetune  TRPO on a goal:     hmepol finetune init=<run dir> goal=random
  show      draw a world:       hmepol show env=corridor [--out FILE]
  study     a staged comparison: hmepol study conf/study/decisive_corridor.yaml [--status]

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


def setup() -> None:
    """What composing hmepol's configs needs: its resolvers, the schema in Hydra's config
    store and the population launcher. ``main`` calls it; so does anything else that composes
    (tests, benchmarks). Importing this module does none of it. Safe to call twice."""
    OmegaConf.register_new_resolver("hmepol_run_dir", _run_dir_resolver, replace=True)
    OmegaConf.register_new_resolver("hmepol_job_dir", _job_dir_resolver, replace=True)
    OmegaConf.register_new_resolver("hmepol_unique", _unique_resolver, replace=True)
    register_configs()
    # Hydra scans the hydra_plugins namespace for launchers, which an editable install hides
    # from it: register ours by hand (its public API; a no-op when the scan found it).
    Plugins.instance().register(PopulationLauncher)


def fail(message: str, code: int = 2) -> None:
    print(f"hmepol: error: {message}", file=sys.stderr)
    raise SystemExit(code)


DEBUG_ENV = "HYDRA_FULL_ERROR"  # =1 (or --debug): an unexpected error keeps its traceback


def debugging() -> bool:
    return os.environ.get(DEBUG_ENV) == "1"


def unexpected_line(error: BaseException) -> str:
    """An exception no check foresaw, as one line; its traceback goes to a log file, whose
    path the line gives (a temporary folder's, so nothing is left in the user's folders)."""
    import tempfile
    import traceback

    stamp = time.strftime("%Y%m%d-%H%M%S")
    path = Path(tempfile.gettempdir()) / f"hmepol-error-{stamp}-{os.getpid()}.log"
    text = "".join(traceback.format_exception(type(error), error, error.__traceback__))
    try:
        path.write_text(f"hmepol {' '.join(sys.argv[1:])}\n{text}")
        where = f"the traceback is in {path}"
    except OSError:
        where = "the traceback could not be written"
    first = (str(error).strip().splitlines() or [""])[0][:200]
    return (
        f"unexpected {type(error).__name__}{': ' + first if first else ''} (a bug in hmepol; "
        f"{where}; {DEBUG_ENV}=1 or --debug prints it)"
    )


def guard_unexpected(error: Exception) -> None:
    """The top-level guard of every command: an unexpected exception is one line and exit 1,
    or, when debugging, its traceback."""
    if debugging():
        raise error
    fail(unexpected_line(error), code=1)


_PACKAGE_DIR = Path(__file__).resolve().parent
_python_warning_format = warnings.formatwarning


def _one_line_warning(message, category, filename, lineno, line=None) -> str:  # noqa: ANN001
    """Our own warnings (a skipped run, a stale lock taken over) as one line, like our errors;
    everyone else's keep Python's format, with the file and line they came from."""
    if Path(filename).resolve().is_relative_to(_PACKAGE_DIR):
        return f"hmepol: warning: {message}\n"
    return _python_warning_format(message, category, filename, lineno, line)


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
        members = population_members(cfg)
        if HydraConfig.get().mode == RunMode.MULTIRUN:
            _remove_if_empty(Path(HydraConfig.get().runtime.output_dir))  # the job's own folder
    elif cfg.resume is not None:
        run_dir = Path(cfg.resume)
        members = [(resumed_config(cfg, run_dir, list(HydraConfig.get().overrides.task)), run_dir)]
    else:
        members = [(cfg, Path(HydraConfig.get().runtime.output_dir))]
    return train_runs(members, resume=cfg.resume is not None)


def _remove_if_empty(folder: Path) -> None:
    """Hydra makes a folder for every job; a population's job writes into its members'."""
    try:
        folder.rmdir()
    except OSError:  # not empty, or not there
        pass


def train_runs(members: list[tuple[DictConfig, Path]], resume: bool = False) -> list[str]:
    """Train runs that differ only in member-scalar keys as one population (skipping finished
    ones, continuing interrupted ones). The configs are valid ones: the command checked them
    (:func:`hmepol_cli.checks.check_train`) before anything was written. -> their run
    directories; RunFailure if any failed."""
    from hmepol_cli.trainer import Trainer

    todo, resuming = [], resume
    for cfg, run_dir in members:  # validated by the command's check, before anything was written
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
        if todo[0][0].get("precision") == "auto":
            say(f"hmepol: {auto_reason(device_type(str(todo[0][0].device)))}")
        started = time.monotonic()
        trainer = Trainer([c for c, _ in todo], [d for _, d in todo])
        if str(todo[0][0].get("blas", "auto")) == "auto":
            say(f"hmepol: {trainer.blas_reason}")
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


def train_job(cfg: DictConfig) -> list[str] | None:
    """A Hydra job of ``hmepol train`` or of a sweep: its runs, and what happened to them as one
    line (a sweep's failed or interrupted jobs are reported to it instead)."""
    multirun = HydraConfig.get().mode == RunMode.MULTIRUN
    with preemptible():
        try:
            runs = _train(cfg)
        except UserError as error:
            if multirun:  # the sweep goes on, and ends with a table of its failed jobs
                _report_job("failed", cfg, str(error))
                return None
            fail(str(error), code=1 if isinstance(error, RunFailure | StorageError) else 2)
        except Exception as error:  # a bug: one line and a log file, or the traceback
            if multirun and not debugging():
                _report_job("failed", cfg, unexpected_line(error))
                return None
            guard_unexpected(error)
        except Interrupted as error:
            _report_job("interrupted", cfg, str(error))
            print(f"hmepol: {interrupted_line(error)}", file=sys.stderr, flush=True)
            raise SystemExit(error.exit_code) from None
    _report_job("done", cfg)
    return runs


# Hydra's own command line: sweeps (each job composed by its launcher), --cfg, --help, -m.
train_app = hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name="config")(train_job)


def run_train(overrides: list[str]) -> None:
    """``hmepol train overrides``: the config composed once, with Hydra's own node, checked
    before anything is written, then run as Hydra's job in the folder it names (what
    ``@hydra.main`` does, without composing it again)."""
    from hydra import initialize_config_module
    from hydra._internal.callbacks import Callbacks  # Hydra 1.3 (pinned below 1.4)
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.utils import run_job
    from hydra.types import HydraContext

    check_output_dirs(overrides)
    GlobalHydra.instance().clear()
    try:
        with initialize_config_module(CONFIG_MODULE, version_base="1.3", job_name="cli"):
            config = compose_here("config", overrides, with_hydra=True)
            task = OmegaConf.masked_copy(config, [k for k in config if k != "hydra"])
            check_config(task, overrides, compose_here)
            with open_dict(config):
                config.hydra.mode = RunMode.RUN
            context = HydraContext(
                config_loader=GlobalHydra.instance().config_loader(), callbacks=Callbacks(config)
            )
            job = run_job(train_job, config, "hydra.run.dir", None, context)
            job.return_value  # noqa: B018  (re-raises what the job raised)
    finally:
        GlobalHydra.instance().clear()


def _sweep(args: list[str], n_jobs: int = 0) -> None:
    """Run a Hydra multirun; end with a table of the jobs that failed or were interrupted (and
    how many never started), and exit 1 (failed) or 128 + the signal (interrupted)."""
    launcher = (
        [] if any(a.startswith("hydra/launcher=") for a in args) else ["hydra/launcher=local"]
    )
    sweep_dir = next(
        (override_value(a) for a in args if a.startswith("hydra.sweep.dir=")), "outputs/sweep"
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
        except Exception as error:  # a bug: one line and a log file, or the traceback
            guard_unexpected(error)
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
    parser.add_argument(
        "--unfinished",
        action="store_true",
        help="use runs that stopped before their last epoch too (runs still going, a replicate "
        "cut short); each env and wind holding one is then cut at the last epoch all of its "
        "runs wrote",
    )
    ns = parser.parse_args(args)
    roots = [Path(unquote(r)) for r in ns.runs]  # a path quoted as for Hydra reads the same
    for runs in roots:
        if not runs.is_dir():
            fail(f"{str(runs)!r} is not a directory of runs")
    out = Path(unquote(ns.out)) if ns.out else roots[0] / "report"
    if out.exists() and not out.is_dir():
        fail(f"--out {str(out)!r} is a file; give a folder for the report")
    try:
        index = run_report(roots, out, unfinished=ns.unfinished)
    except UserError as error:
        fail(str(error))
    print(f"hmepol: report written to {index}")


def _show(args: list[str]) -> None:
    import argparse

    from hmepol_cli.envs import make_world
    from hmepol_cli.envs.render import show_world

    parser = argparse.ArgumentParser(
        prog="hmepol show",
        description="Draw every configuration of a world with its probability: a 2-D world's "
        "map (north up: walls, start area, the slope or wind), or, for a Gymnasium world, where "
        "episodes of uniformly random actions take its state (the two env.projection indices).",
    )
    parser.add_argument(
        "overrides", nargs="*", help="env=NAME [env.KEY=VALUE ...] [wind=FORCE], as for train"
    )
    parser.add_argument("--out", default=None, help="PNG file (default: outputs/show/<env>.png)")
    ns = parser.parse_args(args)
    keys = [item.lstrip("+~").partition("=")[0] for item in ns.overrides]
    unknown = {k for k in keys if k not in ("env", "wind") and not k.startswith("env.")}
    if unknown:
        fail(
            f"unknown option(s) {', '.join(sorted(unknown))}; use env=NAME, env.KEY=VALUE and "
            "wind=FORCE"
        )
    values = dict(item.partition("=")[::2] for item in ns.overrides)
    if "wind" in values:
        try:
            wind = float(values["wind"])
        except ValueError:
            fail(f"wind={values['wind']!r} is not a number")
        if not 0 <= wind < float("inf"):
            fail(f"wind={wind!r} must be a finite number >= 0")
    cfg = compose("config", ns.overrides)  # the world a run with these overrides would have
    validate(cfg)
    world = make_world(cfg.env)
    name = values.get("env", cfg.env.name)
    if cfg.env.get("id"):
        name += "-" + re.sub(r"[^A-Za-z0-9._-]", "_", str(cfg.env.id))
    out = Path(ns.out or f"outputs/show/{name}.png")
    try:
        show_world(world, out)
    finally:
        world.close()
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
    if "--debug" in argv:  # the traceback of an unexpected error, Hydra's included
        argv = [a for a in argv if a != "--debug"]
        os.environ[DEBUG_ENV] = "1"
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(USAGE)
        return
    if argv[0] in ("-V", "--version"):
        print(f"hmepol {package_version()}")
        return
    command, rest = argv[0], argv[1:]
    warnings.formatwarning = _one_line_warning
    setup()
    try:
        if command == "train":
            if any(a.startswith("-") for a in rest):  # Hydra's own flags: its command line
                if not _asks_for_help(rest):
                    check_train([a for a in rest if not a.startswith("-")])
                sys.argv = ["hmepol", *rest]
                train_app()
            else:
                run_train(rest)
        elif command == "sweep":
            if not _asks_for_help(rest):
                n_jobs = check_sweep([a for a in rest if not a.startswith("-")])
            else:
                n_jobs = 0
            _sweep(rest, n_jobs)
        elif command == "finetune":
            if not _asks_for_help(rest):
                check_finetune_overrides([a for a in rest if not a.startswith("-")])
            sys.argv = ["hmepol", *rest]
            finetune_app()
        elif command == "report":
            _report(rest)
        elif command == "show":
            _show(rest)
        elif command == "study":
            from hmepol_cli.study import main as study

            study(rest)
        else:
            fail(
                f"unknown command {command!r}; choose train, sweep, report, finetune, show or "
                "study "
                "(hmepol --help)"
            )
    except UserError as error:
        fail(str(error))
    except Exception as error:  # a bug: one line and a log file, or the traceback
        guard_unexpected(error)


if __name__ == "__main__":  # `python -m hmepol_cli` also sets the OpenMP wait policy first
    main()
