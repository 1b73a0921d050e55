"""Live experiment tracking: TensorBoard, Weights & Biases and MLflow, beside the CSV
files every run writes anyway (``logger=[csv,tensorboard,wandb,mlflow]``).

Every member of a population is a tracking run of its own, named like its run directory and
grouped by its population (a W&B ``group``, an MLflow parent run, one TensorBoard folder per
member under its run directory). Per epoch: every ``epochs.csv`` column as a scalar at step =
epoch, the per-configuration entropies also under ``entropy_by_config/<name>``; the heatmap of
every evaluation as an image; the config as hyperparameters and the provenance as tags. A run
that is continued continues its tracking runs (their ids are kept in run.json): epochs that
reached the CSV but not a tracker before a crash are logged on resume, and none twice.

The packages are an extra (``pip install 'hmepol[tracking]'``). Nothing a tracker does can fail
a run: its first error is one warning, and the tracker is switched off for the rest of the run.
"""

from __future__ import annotations

import hashlib
import importlib.util
import logging
import math
import os
import secrets
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

from hmepol_cli.errors import ConfigError

EXTRA = "pip install 'hmepol[tracking]'"
PACKAGES = {"tensorboard": "tensorboard", "wandb": "wandb", "mlflow": "mlflow"}
TRACKING_DIR = "tensorboard"  # a run directory's TensorBoard folder


def selected(cfg) -> list[str]:
    """The trackers a config asks for (csv is not one: the CSV files are always written)."""
    chosen = cfg.get("logger") or {}
    return [name for name in PACKAGES if chosen.get(name) is not None]


def check_loggers(cfg) -> None:
    """One line for a tracker whose package is missing, before anything is written."""
    for name in selected(cfg):
        if importlib.util.find_spec(PACKAGES[name]) is None:
            raise ConfigError(f"logger={name} needs the {PACKAGES[name]} package: {EXTRA}")


def population_group(run_dirs: Sequence[Path]) -> str | None:
    """A name for the population the runs train in (None for a run alone), the same whenever
    the population is continued."""
    if len(run_dirs) < 2:
        return None
    key = "\n".join(sorted(str(Path(d).resolve()) for d in run_dirs))
    return f"population-{hashlib.sha1(key.encode()).hexdigest()[:8]}"


class Tracker:
    """One tracking backend for one member's run; subclasses log, this class keeps them safe."""

    name = "tracker"
    # What the backend logged may be lost when the process is killed (it writes from another
    # process, asynchronously): on resume every epoch of the CSV is logged again, and the
    # backend keeps the first value it has for a step.
    lossy = False

    def __init__(self, run_dir: Path, settings: dict[str, Any]) -> None:
        self.run_dir, self.settings, self.alive = Path(run_dir), settings, True

    def guard(self, what: str, call, *args, **kwargs):
        """Run a tracker call; its first failure is one warning and the tracker stops."""
        if not self.alive:
            return None
        try:
            return call(*args, **kwargs)
        except Exception as error:  # noqa: BLE001 - a tracker must never fail a run
            self.alive = False
            reason = f"{type(error).__name__}: {error}".splitlines()[0][:160]
            warnings.warn(
                f"{self.run_dir}: logger={self.name} failed to {what} ({reason}); the run goes "
                "on without it",
                stacklevel=2,
            )
            return None

    # -- what every backend implements
    def start(self, name: str, group: str | None, params: dict, tags: dict, state: dict) -> dict:
        """Open (or continue, from ``state``) the tracking run. -> the state to keep in run.json"""
        raise NotImplementedError

    def last_step(self) -> int:
        """The last epoch the tracking run holds (-1: none), where the backend can say."""
        return -1

    def scalars(self, epoch: int, values: dict[str, float]) -> None:
        raise NotImplementedError

    def image(self, epoch: int, tag: str, path: Path) -> None:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError


class TensorBoardTracker(Tracker):
    name = "tensorboard"

    def start(self, name, group, params, tags, state) -> dict:
        from torch.utils.tensorboard import SummaryWriter

        # A continued run drops whatever the folder holds past the last epoch run.json says
        # was logged: those epochs are logged again, once.
        purge = state.get("purge_step")
        self.writer = SummaryWriter(str(self.run_dir / TRACKING_DIR), purge_step=purge)
        if purge is None:
            text = "\n".join(f"{k}: {v}" for k, v in {**tags, **params}.items())
            self.writer.add_text("config", f"```\n{text}\n```", 0)
        return {"folder": TRACKING_DIR}

    def scalars(self, epoch, values) -> None:
        for key, value in values.items():
            self.writer.add_scalar(key, value, epoch)
        self.writer.flush()

    def image(self, epoch, tag, path) -> None:
        import matplotlib.image as mpimg

        picture = mpimg.imread(path)[..., :3]
        self.writer.add_image(tag, picture, epoch, dataformats="HWC")
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()


class WandbTracker(Tracker):
    name = "wandb"
    lossy = True  # wandb-core writes the offline file; a kill loses its buffer

    def start(self, name, group, params, tags, state) -> dict:
        import wandb

        mode = self.settings.get("mode") or "auto"
        if mode == "auto":  # online only with a key; nothing leaves the machine otherwise
            mode = "online" if os.environ.get("WANDB_API_KEY") or _netrc_has_wandb() else "offline"
        run_id = state.get("id") or secrets.token_hex(4)
        self.run = wandb.init(
            project=self.settings.get("project") or "hmepol",
            entity=self.settings.get("entity"),
            name=name,
            group=group,
            id=run_id,
            resume="allow",
            dir=str(self.run_dir),
            mode=mode,
            config=params,
            tags=[f"{k}:{v}"[:64] for k, v in tags.items()],
            settings=wandb.Settings(silent=True, console="off"),
            reinit="create_new",
        )
        return {"id": run_id}

    def scalars(self, epoch, values) -> None:
        self.run.log(values, step=epoch)

    def image(self, epoch, tag, path) -> None:
        import wandb

        self.run.log({tag: wandb.Image(str(path))}, step=epoch)

    def close(self) -> None:
        self.run.finish()


class MlflowTracker(Tracker):
    name = "mlflow"

    def start(self, name, group, params, tags, state) -> dict:
        from mlflow.tracking import MlflowClient

        for quiet in ("mlflow", "alembic"):  # their banners are not the run's output
            logging.getLogger(quiet).setLevel(logging.WARNING)

        uri = self.settings.get("tracking_uri") or default_mlflow_uri(self.run_dir)
        self.client = MlflowClient(uri)
        experiment = self.settings.get("experiment") or "hmepol"
        found = self.client.get_experiment_by_name(experiment)
        if found:  # its artifact root was fixed when it was made
            experiment_id = found.experiment_id
        else:
            experiment_id = self.client.create_experiment(
                experiment, artifact_location=mlflow_artifact_root(uri, self.run_dir)
            )
        parent = state.get("parent")
        if group and parent is None:
            parent = _parent_run(self.client, experiment_id, group)
        run_id = state.get("id")
        if run_id is None:
            run_tags = {"mlflow.runName": name, **{k: str(v) for k, v in tags.items()}}
            if parent:
                run_tags["mlflow.parentRunId"] = parent
            run_id = self.client.create_run(experiment_id, tags=run_tags).info.run_id
            for key, value in list(params.items())[:500]:
                self.client.log_param(run_id, key[:250], str(value)[:500])
        else:
            self.client.update_run(run_id, status="RUNNING")
        self.run_id = run_id
        return {"id": run_id, "parent": parent, "tracking_uri": uri}

    def last_step(self) -> int:
        history = self.client.get_metric_history(self.run_id, "entropy")
        return max((m.step for m in history), default=-1)

    def scalars(self, epoch, values) -> None:
        from mlflow.entities import Metric

        metrics = [Metric(k.replace("/", "."), float(v), 0, epoch) for k, v in values.items()]
        for start in range(0, len(metrics), 900):
            self.client.log_batch(self.run_id, metrics=metrics[start : start + 900])

    def image(self, epoch, tag, path) -> None:
        self.client.log_artifact(self.run_id, str(path), artifact_path=f"{tag}/{epoch:04d}")

    def close(self) -> None:
        self.client.set_terminated(self.run_id)


TRACKERS: dict[str, type[Tracker]] = {
    "tensorboard": TensorBoardTracker,
    "wandb": WandbTracker,
    "mlflow": MlflowTracker,
}


DATABASES = ("sqlite", "postgresql", "mysql", "mssql")  # MLflow's SQLAlchemy stores


def default_store_dir(run_dir: Path) -> Path:
    """Where a run's MLflow store goes when ``tracking_uri`` names none: the nearest folder
    above the run directory called outputs (where every run directory goes by default, so one
    store holds them all), else the folder holding the run directory (a population's members:
    their own). Never the current folder, which may be anywhere."""
    run_dir = Path(run_dir).resolve()
    for folder in run_dir.parents:
        if folder.name == "outputs":
            return folder
    return run_dir.parent


def default_mlflow_uri(run_dir: Path) -> str:
    """A SQLite store, mlflow.db, in :func:`default_store_dir`."""
    store = default_store_dir(run_dir) / "mlflow.db"
    store.parent.mkdir(parents=True, exist_ok=True)
    return f"sqlite:///{store}"


def mlflow_artifact_root(uri: str, run_dir: Path) -> str | None:
    """The artifact root of an experiment made in the store at ``uri``: beside a SQLite file
    (mlflow.db -> mlflow-artifacts/), in the default store's folder for another database; None
    (the store's or the server's own) for a file store or a tracking server. MLflow's default
    for a database is ./mlruns of whatever folder the command ran in."""
    scheme = urlparse(uri).scheme.split("+")[0]
    if scheme not in DATABASES:
        return None
    if scheme == "sqlite":
        # sqlite:///relative.db, sqlite:////absolute.db; sqlite:// is an in-memory store
        path = uri.split("://", 1)[1][1:].split("?", 1)[0]
        if path and path != ":memory:":
            store = Path(path).resolve()
            return (store.parent / f"{store.stem}-artifacts").as_uri()
    return (default_store_dir(run_dir) / "mlflow-artifacts").as_uri()


def _parent_run(client, experiment_id: str, group: str) -> str:
    """The MLflow run that stands for a population: found by its name, or made."""
    runs = client.search_runs(
        [experiment_id], filter_string=f"tags.`mlflow.runName` = '{group}'", max_results=1
    )
    if runs:
        return runs[0].info.run_id
    return client.create_run(experiment_id, tags={"mlflow.runName": group}).info.run_id


def _netrc_has_wandb() -> bool:
    import netrc

    try:
        return netrc.netrc().authenticators("api.wandb.ai") is not None
    except (OSError, netrc.NetrcParseError):
        return False


class MemberTracking:
    """The trackers of one member's run (none when only csv is asked for)."""

    def __init__(self, cfg, run_dir: Path) -> None:
        self.run_dir = Path(run_dir)
        settings = cfg.get("logger") or {}
        self.trackers = [
            TRACKERS[name](run_dir, dict(settings.get(name) or {})) for name in selected(cfg)
        ]

    def start(
        self, name: str, group: str | None, params: dict, tags: dict, kept: dict,
        logged_through: int,
    ) -> dict:  # fmt: skip
        """Open every tracker, continuing the runs ``kept`` in run.json, whose epochs up to
        ``logged_through`` were logged. -> what to keep in run.json now"""
        state = {}
        for tracker in self.trackers:
            before = dict(kept.get(tracker.name) or {})
            if before:
                before["purge_step"] = logged_through + 1
            opened = tracker.guard("start", tracker.start, name, group, params, tags, before)
            state[tracker.name] = {k: v for k, v in (opened or before).items() if k != "purge_step"}
        return state

    def catch_up(self, rows: list[dict], logged_through: int, names: Sequence[str]) -> None:
        """Log the epochs of ``rows`` (epochs.csv, read back) past ``logged_through`` and past
        the last one a tracker says it holds: what a crash between the CSV and the tracker
        left out, each epoch once (a lossy tracker: every epoch again; it keeps a step's first
        value)."""
        for tracker in self.trackers:
            known = tracker.guard("read its last step", tracker.last_step)
            last = -1 if tracker.lossy else max(logged_through, -1 if known is None else known)
            for row in rows:
                if int(row["epoch"]) > last:
                    values = scalars_of(row, names)
                    tracker.guard("log", tracker.scalars, int(row["epoch"]), values)

    def scalars(self, epoch: int, values: dict[str, float]) -> None:
        for tracker in self.trackers:
            tracker.guard("log", tracker.scalars, epoch, values)

    def image(self, epoch: int, tag: str, path: Path) -> None:
        if path.is_file():
            for tracker in self.trackers:
                tracker.guard("log an image", tracker.image, epoch, tag, path)

    def close(self) -> None:
        for tracker in self.trackers:
            tracker.guard("close", tracker.close)


def scalars_of(row: dict, names: Sequence[str] = ()) -> dict[str, float]:
    """An epochs.csv row as the scalars a tracker logs (the epoch is the step); the
    per-configuration entropies also grouped as ``entropy_by_config/<i> <name>``."""
    out = {}
    for key, value in row.items():
        if key == "epoch" or isinstance(value, str):
            continue
        try:
            number = float(value)
        except (TypeError, ValueError):
            continue
        if math.isfinite(number):
            out[key] = number
            if key.startswith("entropy_c") and key[9:].isdigit():
                label = names[int(key[9:])] if int(key[9:]) < len(names) else ""
                out[f"entropy_by_config/{key[9:]} {label}".rstrip()] = number
    return out
