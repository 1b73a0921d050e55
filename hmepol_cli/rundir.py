"""The run directory: the one contract between what runs write and what the report reads.

A run directory holds::

    config.yaml          the resolved config the run started with; never rewritten
    run.json             kind (train | finetune), status (running | finished | failed), for a
                         failure its reason, epoch and last finite values; epochs_done; identity
                         (hash of the config); facts of the world; provenance; the owner
    commands.log         one line per invocation: time, host, pid, command line
    epochs.csv           train: one row per epoch
    batches.csv          train: one row per mini-batch (epoch, batch, config, entropy)
    steps.csv            train, with diagnostics: one row per off-policy step tried
    checkpoints/last.pt  train: policy, optimizer and random state (loaded with weights_only=True)
    checkpoints/epoch_<n>.pt  train, every checkpoint.keep_every epochs: the same after n epochs
    eval/<name>.npz      train: positions_c<c>, (n, T + 1, 2) fresh rollouts per configuration
    eval/<name>/*.png    train: heatmaps and trajectory plots
    finetune.csv         finetune: one row per (epoch, configuration, target)
    targets.json         finetune: the target areas
    .lock                while a process writes the directory: its pid, host and start time

Every file is written to a temporary name and renamed into place, so a crash leaves the old file
or the new one, never half of one; it gets the permissions the umask gives a new file. One
process writes a directory at a time (:class:`RunDirectory` holds its lock), and a directory
keeps the config it started with: continuing it with another config is refused.
"""

from __future__ import annotations

import contextlib
import csv
import datetime
import errno
import hashlib
import io
import json
import math
import os
import platform
import shlex
import socket
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch
from omegaconf import DictConfig, OmegaConf

from hmepol_cli.errors import Interrupted, RunDirError, StorageError

CONFIG = "config.yaml"
RUN_INFO = "run.json"
COMMANDS = "commands.log"
EPOCHS_CSV = "epochs.csv"
BATCHES_CSV = "batches.csv"
STEPS_CSV = "steps.csv"
FINETUNE_CSV = "finetune.csv"
TARGETS_JSON = "targets.json"
CHECKPOINT = Path("checkpoints") / "last.pt"


def epoch_checkpoint(epochs: int) -> Path:
    """The checkpoint kept after ``epochs`` epochs (``checkpoint.keep_every``)."""
    return CHECKPOINT.parent / f"epoch_{epochs:04d}.pt"


EVAL_DIR = "eval"
FINAL_EVAL = "final"
LOCK = ".lock"
TEMPORARY_SUFFIX = ".tmp"

# Keys a run may change when it is continued: how long and where it runs, not what it is.
RESUMABLE_KEYS = (
    "epochs",
    "device",
    "progress",
    "threads",
    "eval.every",
    "eval.plot_trajectories",  # how the pictures are drawn
    "eval.plot_every",  # a key of runs made before trajectories were lines
    "vmap",
    "cuda_graphs",
    "resume",
    "skip_finished",
    "seeds",
    "members",
    "chunk_members",
    "env.workers",  # a Gymnasium world's processes: the same episodes with any count
    "diagnostics",  # what is recorded, not what is computed
    "checkpoint",
    "logger",
)


# ------------------------------------------------------------------------------ atomic files
def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


FULL = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``path`` whole or not at all (a temporary file renamed into place); a full disk or
    quota is a StorageError naming the path, and the old file stays as it was."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(
            dir=path.parent, prefix=f".{path.name}.", suffix=TEMPORARY_SUFFIX
        )
    except OSError as error:
        raise _storage_error(path, error) from None
    try:
        os.fchmod(fd, 0o666 & ~_umask())  # mkstemp makes 0600: give what a new file gets
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as error:
        Path(tmp).unlink(missing_ok=True)
        if isinstance(error, OSError) and error.errno in (*FULL, errno.EROFS, errno.EACCES):
            raise _storage_error(path, error) from None
        raise


def _storage_error(path: Path, error: OSError) -> StorageError:
    reason = "no space left on the device" if error.errno in FULL else error.strerror
    return StorageError(f"cannot write {path}: {reason} ({errno.errorcode.get(error.errno, '')})")


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def write_json(path: Path, data: dict[str, Any]) -> None:
    atomic_write_text(path, json.dumps(data, indent=2, sort_keys=True) + "\n")


def read_json(path: Path) -> dict[str, Any]:
    """A JSON file written by hmepol; a damaged one is refused in one line naming it."""
    try:
        data = json.loads(Path(path).read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise RunDirError(
            f"{path} is damaged ({type(error).__name__}: {str(error)[:80]}); a run rewrites its "
            "run.json when it is continued, or delete the run directory"
        ) from None
    if not isinstance(data, dict):
        raise RunDirError(f"{path} is damaged (it holds a {type(data).__name__}, not a record)")
    return data


def write_csv(path: Path, frame: pd.DataFrame) -> None:
    buffer = io.StringIO()
    frame.to_csv(buffer, index=False)
    atomic_write_text(path, buffer.getvalue())


def remove_temporaries(run_dir: Path) -> list[Path]:
    """Delete the temporary files of writes a crash interrupted. -> what was removed"""
    stray = [p for p in Path(run_dir).rglob(f".*{TEMPORARY_SUFFIX}") if p.is_file()]
    for path in stray:
        path.unlink(missing_ok=True)
    return stray


# ------------------------------------------------------------------------------ checkpoints
def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """Save tensors, state dicts and plain Python values atomically."""
    buffer = io.BytesIO()
    torch.save(state, buffer)
    atomic_write_bytes(path, buffer.getvalue())


def load_checkpoint(path: Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Load a checkpoint with ``weights_only=True``: tensors and plain containers, no code.

    A file that is not one (corrupt, truncated, or holding anything but weights) is refused in
    one line that names it."""
    try:
        with warnings.catch_warnings():  # torch's notes on foreign pickles: the refusal says it
            warnings.simplefilter("ignore")
            state = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as error:  # torch raises several unpickling and zip errors
        reason = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise RunDirError(
            f"{path} cannot be loaded as a hmepol checkpoint ({type(error).__name__}: "
            f"{reason[:120]})"
        ) from None
    if not isinstance(state, dict):
        raise RunDirError(f"{path} is not a hmepol checkpoint (it holds a {type(state).__name__})")
    return state


# ------------------------------------------------------------------------------ eval files
def save_positions(path: Path, positions: dict[int, np.ndarray]) -> None:
    """``positions_c{c}``: (n, T + 1, 2) positions of n trajectories in configuration c."""
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **{f"positions_c{c}": p for c, p in positions.items()})
    atomic_write_bytes(path, buffer.getvalue())


def load_positions(path: Path) -> dict[int, np.ndarray]:
    with np.load(path, allow_pickle=False) as data:
        return {
            int(k.removeprefix("positions_c")): np.asarray(data[k], dtype=np.float32)
            for k in data.files
            if k.startswith("positions_c")
        }


# ------------------------------------------------------------------------------ reading runs
def run_config(run_dir: Path) -> DictConfig:
    """The config a run was started with; refuses a folder that is not a run."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise RunDirError(f"run directory {str(run_dir)!r} does not exist or is not a directory")
    if not (run_dir / CONFIG).is_file() or not (run_dir / RUN_INFO).is_file():
        raise RunDirError(
            f"{str(run_dir)!r} is not a hmepol run directory (expected {CONFIG} and {RUN_INFO})"
        )
    return OmegaConf.load(run_dir / CONFIG)


def resolve_checkpoint(path: Path | str) -> tuple[Path, Path]:
    """(run directory, checkpoint file) from a run directory, a checkpoint file, or
    ``<run directory>@<epoch>``: the checkpoint kept after that many epochs."""
    text = str(path)
    run, at, epoch = text.rpartition("@") if "@" in text else (text, "", "")
    path = Path(run)
    if at:
        if not epoch.isdigit():
            raise RunDirError(f"{text!r}: after '@' give a number of epochs, e.g. {run}@100")
        run_config(path)
        checkpoint = path / epoch_checkpoint(int(epoch))
        if not checkpoint.is_file():
            kept = sorted(p.stem.removeprefix("epoch_") for p in (path / CHECKPOINT.parent).glob(
                "epoch_*.pt"))  # fmt: skip
            have = ", ".join(str(int(k)) for k in kept) or "none (run with checkpoint.keep_every=n)"
            raise RunDirError(
                f"{run!r} kept no checkpoint after {int(epoch)} epochs; it has: {have}"
            )
        return path, checkpoint
    if path.is_file():
        run_dir = path.parent.parent if path.parent.name == CHECKPOINT.parent.name else path.parent
        return run_dir, path
    run_config(path)  # a clear error for a folder that is not a run
    checkpoint = path / CHECKPOINT
    if not checkpoint.is_file():
        raise RunDirError(f"run directory {str(path)!r} has no checkpoint yet ({CHECKPOINT})")
    return path, checkpoint


def load_trained_policy(path: Path | str, device: str | torch.device = "cpu"):
    """The policy of a run (directory, checkpoint file, or ``<run>@<epochs>``), the run's
    config and the number of epochs the checkpoint holds.

    -> (Policy on ``device``, DictConfig of the run, epochs)"""
    from hmepol_cli.policies import make_policy

    run_dir, checkpoint = resolve_checkpoint(path)
    cfg = run_config(run_dir)
    state = load_checkpoint(checkpoint, map_location=device)
    try:
        policy = make_policy(cfg.policy, state["state_dim"], state["action_dim"])
        policy.load_state_dict(state["policy"])
    except (KeyError, RuntimeError) as error:
        reason = str(error).splitlines()[0][:120]
        raise RunDirError(
            f"{checkpoint} does not hold the policy its run describes ({reason})"
        ) from None
    return policy.to(device), cfg, int(state.get("epoch", -1))


# ------------------------------------------------------------------------------ identity
def flat_config(cfg: DictConfig | dict) -> dict[str, Any]:
    """{"a.b": value} of a config (resolved), lists as tuples: hashable values, so the report can
    group runs by them (a list of keyword sets, env.configs, as tuples of (key, value) pairs)."""
    container = OmegaConf.to_container(cfg, resolve=True) if OmegaConf.is_config(cfg) else cfg

    def walk(node: Any, prefix: str) -> dict[str, Any]:
        if isinstance(node, dict):
            out: dict[str, Any] = {}
            for key, value in node.items():
                out.update(walk(value, f"{prefix}{key}."))
            return out
        return {prefix[:-1]: hashable_value(node)}

    return walk(container, "")


def hashable_value(value: Any) -> Any:
    """Lists as tuples and dicts as sorted (key, value) tuples, all the way down."""
    if isinstance(value, list | tuple):
        return tuple(hashable_value(v) for v in value)
    if isinstance(value, dict):
        return tuple(sorted((str(k), hashable_value(v)) for k, v in value.items()))
    return value


def identity_of(cfg: DictConfig | dict) -> dict[str, Any]:
    """What a run *is*: its config without the keys a continuation may change."""
    return {
        k: v
        for k, v in flat_config(cfg).items()
        if not any(k == r or k.startswith(f"{r}.") for r in RESUMABLE_KEYS)
    }


def identity_hash(cfg: DictConfig | dict) -> str:
    text = json.dumps(identity_of(cfg), sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def identity_differences(started: DictConfig | dict, now: DictConfig | dict) -> list[str]:
    """``key=<started> (now <now>)`` for every key in which two configs' identities differ.

    A key one config lacks and the other holds as null is no difference: a setting added to
    the schema later (such as the Gymnasium world's env.id) is null where it is not used, so a
    run started before it existed continues."""
    a, b = identity_of(started), identity_of(now)
    return [
        f"{k}={a.get(k, '<absent>')!r} (now {b.get(k, '<absent>')!r})"
        for k in sorted(set(a) | set(b))
        if a.get(k) != b.get(k)  # absent and null read alike
    ]


# ------------------------------------------------------------------------------ provenance
def provenance(device: torch.device | str | None = None) -> dict[str, Any]:
    """Where and with what a run is made: versions, source commit, host, threads, device."""
    import scipy

    from hmepol_cli import __version__

    info: dict[str, Any] = {
        "hmepol": __version__,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "host": socket.gethostname(),
        "threads": torch.get_num_threads(),
        "device": str(device) if device is not None else None,
        "command": " ".join(shlex.quote(a) for a in sys.argv),
    }
    if device is not None and torch.device(device).type == "cuda":
        info["gpu"] = torch.cuda.get_device_name(torch.device(device))
    info.update(_git_state(Path(__file__).resolve().parent.parent))
    return info


def _git_state(source: Path) -> dict[str, Any]:
    """The commit of the checkout the package runs from, and whether it had changes."""
    if not (source / ".git").exists():
        return {}
    try:
        commit = subprocess.run(
            ["git", "-C", str(source), "rev-parse", "HEAD"],
            capture_output=True, text=True, timeout=5, check=True,
        ).stdout.strip()  # fmt: skip
        changes = subprocess.run(
            ["git", "-C", str(source), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True, text=True, timeout=5, check=True,
        ).stdout.strip()  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return {}
    return {"git_commit": commit, "git_dirty": bool(changes)}


def _now() -> str:
    return datetime.datetime.now().astimezone().isoformat(timespec="seconds")


# ------------------------------------------------------------------------------ ownership
def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


class RunLock:
    """The lock file of a run directory: held by the one process that writes it."""

    def __init__(self, run_dir: Path) -> None:
        self.path = Path(run_dir) / LOCK
        self.owner = {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "started": _now(),
        }
        self.held = False

    def acquire(self) -> None:
        """Take the lock; a live holder is refused in one line, a dead one taken over."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        for _ in range(3):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666)
            except FileExistsError:
                self._clear_stale()
                continue
            with os.fdopen(fd, "w") as f:
                json.dump(self.owner, f)
            self.held = True
            return
        raise RunDirError(f"could not take the lock {self.path}; is another process starting?")

    def _clear_stale(self) -> None:
        try:
            holder = json.loads(self.path.read_text())
            pid, host, since = int(holder["pid"]), str(holder["host"]), holder.get("started", "?")
        except (OSError, ValueError, KeyError, TypeError):
            # Unreadable: a holder still writing it (a moment ago) or a crash mid-write.
            if time.time() - self.path.stat().st_mtime < 10:
                time.sleep(1.0)
                return
            warnings.warn(f"taking over the unreadable lock {self.path}", stacklevel=3)
            self.path.unlink(missing_ok=True)
            return
        if host != socket.gethostname():
            raise RunDirError(
                f"{self.path.parent} is held by pid {pid} on host {host} since {since}; if that "
                f"process is gone, delete {self.path}"
            )
        if _process_alive(pid):
            raise RunDirError(
                f"{self.path.parent} is being written by pid {pid} on {host} since {since}; "
                "wait for it to finish or choose another run directory"
            )
        warnings.warn(
            f"taking over {self.path.parent}: its writer (pid {pid}, since {since}) is gone",
            stacklevel=3,
        )
        self.path.unlink(missing_ok=True)

    def holder(self) -> dict[str, Any] | None:
        """Who writes the directory now: the lock's record, when a live process on this host
        (or any process on another host) holds it; None when nobody does."""
        try:
            holder = json.loads(self.path.read_text())
            pid, host = int(holder["pid"]), str(holder["host"])
        except (OSError, ValueError, KeyError, TypeError):
            return None
        if host == socket.gethostname() and not _process_alive(pid):
            return None
        return holder

    def release(self) -> None:
        if not self.held:
            return
        try:
            holder = json.loads(self.path.read_text())
            if int(holder.get("pid", -1)) == os.getpid():
                self.path.unlink()
        except (OSError, ValueError):
            pass
        self.held = False


class RunDirectory:
    """A run directory this process writes: locked, identified, its invocations logged.

    ``open()`` takes the lock, removes the temporaries of interrupted writes, refuses a config
    that differs from the one the run started with, writes config.yaml the first time, and
    records the invocation; ``close()`` releases the lock."""

    def __init__(self, path: Path, cfg: DictConfig, kind: str = "train") -> None:
        self.path, self.cfg, self.kind = Path(path), cfg, kind
        self.lock = RunLock(self.path)

    def open(self, device: torch.device | str | None = None) -> RunDirectory:
        config_file = self.path / CONFIG
        if self.path.exists() and not self.path.is_dir():
            raise RunDirError(f"run directory {str(self.path)!r} exists and is not a directory")
        self.lock.acquire()
        try:
            remove_temporaries(self.path)
            try:
                self.info()
            except RunDirError as damaged:  # its owner rebuilds it: the results are elsewhere
                warnings.warn(f"{damaged}: rewriting it", stacklevel=2)
                (self.path / RUN_INFO).unlink()
            if config_file.is_file():
                differences = identity_differences(OmegaConf.load(config_file), self.cfg)
                if differences:
                    shown = "; ".join(differences[:4]) + ("; ..." if len(differences) > 4 else "")
                    raise RunDirError(
                        f"{self.path} was started with another config: {shown}. Continue it with "
                        "the config it started with, or choose another run directory"
                    )
            else:
                atomic_write_text(config_file, OmegaConf.to_yaml(self.cfg, resolve=True))
            with open(self.path / COMMANDS, "a") as log:
                os.chmod(self.path / COMMANDS, 0o666 & ~_umask())
                log.write(
                    f"{_now()} {socket.gethostname()} pid={os.getpid()} {provenance()['command']}\n"
                )
            self.update(
                kind=self.kind,
                status="running",
                identity=identity_hash(self.cfg),
                owner=self.lock.owner,
                provenance=provenance(device),
                failure=None,
            )
        except BaseException:
            self.lock.release()
            raise
        return self

    def info(self) -> dict[str, Any]:
        path = self.path / RUN_INFO
        return read_json(path) if path.is_file() else {}

    def update(self, **fields: Any) -> dict[str, Any]:
        """Rewrite run.json with ``fields`` changed (one writer: read, change, write)."""
        info = {**self.info(), **fields}
        write_json(self.path / RUN_INFO, info)
        return info

    def fail(self, reason: str, epoch: int | None = None, last: dict | None = None) -> None:
        """Record that the run failed: why, at which epoch, its last finite values."""
        self.update(
            status="failed",
            failure={"reason": reason, "epoch": epoch, "last_finite": last or {}, "at": _now()},
        )

    def interrupt(self, signal_name: str) -> None:
        """Record that the run was stopped by a signal; the next run of the command continues."""
        info = self.info()
        self.update(
            status="interrupted",
            interruption={"signal": signal_name, "epochs_done": info.get("epochs_done", 0),
                          "at": _now()},
        )  # fmt: skip

    def close(self) -> None:
        self.lock.release()

    def __enter__(self) -> RunDirectory:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()


# ------------------------------------------------------------------------------ training CSVs
def row_digest(rows: pd.DataFrame) -> str:
    """A digest of some rows' values, the same whether taken from the rows as written or as
    read back from their CSV (numbers compared as floats, by their exact value)."""

    def canon(value: Any) -> str:
        if isinstance(value, bool | np.bool_):
            return str(bool(value))
        if isinstance(value, int | float | np.number):
            number = float(value)
            return "nan" if math.isnan(number) else repr(number)
        if value is None or (isinstance(value, float) and math.isnan(value)):
            return "nan"
        return str(value)

    columns = [c for c in rows.columns if c != LINE]
    text = "\n".join(
        "|".join(canon(v) for v in row) for row in rows[columns].itertuples(index=False)
    )
    return hashlib.sha256(("|".join(columns) + "\n" + text).encode()).hexdigest()[:16]


LINE = "_line"  # the file line a row was read from (1 = the header), kept out of the files


class RunTables:
    """The CSV files of a run directory (training: epochs.csv, batches.csv and, with
    diagnostics, steps.csv; fine-tuning: finetune.csv), rewritten atomically whenever rows are
    added, so a reader never sees half a file.

    Every row carries an ``epoch``. ``digests`` holds, per table, a digest of each epoch's rows
    as they were written; a checkpoint keeps the digests of the epochs it covers, and on resume
    :meth:`verify` keeps exactly those rows: rows past the checkpoint are dropped, and a row the
    checkpoint covers that is missing, changed, cut, duplicated or unreadable is refused in one
    line naming the file and the line. So every epoch appears exactly once, as it was written."""

    def __init__(self, run_dir: Path, names: Sequence[str], optional: Sequence[str] = ()) -> None:
        """``optional`` tables are written only once they have rows."""
        self.run_dir, self.optional = Path(run_dir), set(optional)
        self.damaged: dict[str, list[tuple[int, str]]] = {}
        self.tables = {name: self._read(name) for name in (*names, *optional)}
        self.digests: dict[str, list[str]] = {name: [] for name in self.tables}

    def __getitem__(self, name: str) -> pd.DataFrame:
        return self.tables[name].drop(columns=[LINE], errors="ignore")

    def _read(self, name: str) -> pd.DataFrame:
        """The rows of a table that can be read, with the line each came from; the lines that
        cannot (a wrong number of fields, an epoch that is not a whole number) in ``damaged``."""
        path = self.run_dir / name
        self.damaged[name] = []
        if not path.is_file():
            return pd.DataFrame()
        try:
            text = path.read_text()
        except UnicodeDecodeError:
            raise RunDirError(f"{path} is not a text file; restore it or start over") from None
        lines = text.splitlines()
        if not lines:
            return pd.DataFrame()
        header = next(csv.reader([lines[0]]))
        epoch = header.index("epoch") if "epoch" in header else None
        good = []
        for number, line in enumerate(lines[1:], start=2):
            fields = next(csv.reader([line]), [])
            if len(fields) != len(header):
                self.damaged[name].append((number, f"{len(fields)} fields for {len(header)}"))
            elif epoch is not None and not fields[epoch].isdigit():
                self.damaged[name].append((number, f"epoch {fields[epoch]!r}"))
            else:
                good.append(number)
        keep = set(good)
        frame = pd.read_csv(path, skiprows=lambda i: i > 0 and i + 1 not in keep)
        frame[LINE] = good
        return frame

    def truncate(self, next_epoch: int) -> None:
        """Keep only epochs < next_epoch (the ones the checkpoint covers)."""
        for name, table in self.tables.items():
            if len(table):
                self.tables[name] = table[table["epoch"] < next_epoch]
            self.digests[name] = self.digests[name][:next_epoch]
        self.damaged = {name: [] for name in self.tables}
        self._flush()

    def verify(self, next_epoch: int, digests: dict[str, list[str]] | None) -> None:
        """Resume at ``next_epoch``: check the rows of the epochs the checkpoint covers against
        its ``digests`` (None: a checkpoint from before they existed: epochs.csv must then hold
        each epoch exactly once), then drop every row past them."""
        for name, table in self.tables.items():
            path = self.run_dir / name
            covered = table[table["epoch"] < next_epoch] if len(table) else table
            last = int(covered[LINE].max()) if len(covered) else 1
            for number, reason in self.damaged.get(name, []):
                if number < last:  # among the rows the checkpoint covers
                    raise RunDirError(
                        f"{path} line {number} cannot be read ({reason}): it is among the "
                        f"rows of the {next_epoch} epochs the checkpoint covers; restore the "
                        "file, or start the run over in a new directory"
                    )
            expected = None if digests is None else digests.get(name)
            if expected is None:
                if name == EPOCHS_CSV and list(covered.get("epoch", [])) != list(range(next_epoch)):
                    raise RunDirError(
                        f"{path} does not hold epochs 0..{next_epoch - 1} exactly once (it has "
                        f"{sorted(set(covered.get('epoch', [])))[:8]}...); restore the file, or "
                        "start the run over in a new directory"
                    )
                continue
            for e in range(next_epoch):
                rows = covered[covered["epoch"] == e] if len(covered) else covered
                if row_digest(rows) == expected[e]:
                    continue
                where = f"line {int(rows[LINE].iloc[0])}" if len(rows) else "no row"
                raise RunDirError(
                    f"{path} {where} (epoch {e}) is not what the run wrote (missing, changed, "
                    f"cut or duplicated); restore the file, or start the run over in a new "
                    "directory"
                )
            self.digests[name] = list(expected[:next_epoch])
        self.truncate(next_epoch)

    def append(self, **rows: pd.DataFrame | None) -> None:
        """Add one epoch's rows to the tables named by the keywords (a table's file name without
        .csv; every table of a training run gets its epoch's digest, empty or not)."""
        for name in self.tables:
            new = rows.get(name.removesuffix(".csv"))
            if name.removesuffix(".csv") not in rows:
                continue
            if new is not None and len(new):
                self.tables[name] = pd.concat([self.tables[name], new], ignore_index=True)
            self.digests[name].append(row_digest(new if new is not None else pd.DataFrame()))
        self._flush()

    def _flush(self) -> None:
        for name, table in self.tables.items():
            if name not in self.optional or len(table) or (self.run_dir / name).exists():
                write_csv(self.run_dir / name, table.drop(columns=[LINE], errors="ignore"))

    @property
    def last_finite(self) -> dict[str, float]:
        """The last row's finite numbers of the first table (what a failure record keeps)."""
        table = self[next(iter(self.tables))]
        if not len(table):
            return {}
        row = table.iloc[-1]
        return {
            k: float(v)
            for k, v in row.items()
            if isinstance(v, int | float | np.number) and math.isfinite(float(v))
        }


def training_tables(run_dir: Path) -> RunTables:
    return RunTables(run_dir, (EPOCHS_CSV, BATCHES_CSV), optional=(STEPS_CSV,))


@contextlib.contextmanager
def writing(
    directories: Sequence[RunDirectory],
    device: torch.device | str | None = None,
    last: Callable[[RunDirectory], dict[str, float]] = lambda directory: {},
) -> Iterator[Sequence[RunDirectory]]:
    """Write run directories (training and fine-tuning alike): open each (lock, config check,
    provenance, status running) and close them all at the end; an exception marks every one
    whose status is still running as failed, with its reason and ``last(directory)``, its last
    finite numbers."""
    opened: list[RunDirectory] = []
    try:
        for directory in directories:  # a refusal here (a lock, a config) changes no status
            directory.open(device)
            opened.append(directory)
    except BaseException:
        for directory in opened:
            directory.close()
        raise
    try:
        yield opened
    except BaseException as error:
        stopped = isinstance(error, Interrupted | KeyboardInterrupt)
        reason = f"{type(error).__name__}: {error}".splitlines()[0][:300]
        for directory in opened:
            try:
                if directory.info().get("status") != "running":
                    continue
                if stopped:
                    directory.interrupt(getattr(error, "name", "SIGINT"))
                else:
                    directory.fail(reason, last=last(directory))
            except (StorageError, RunDirError, OSError):  # a full disk: nothing more to record
                pass
        raise
    finally:
        for directory in opened:
            directory.close()
