"""A run directory's lifecycle: opened (locked, its config checked, the invocation logged,
status running), updated, and left finished, failed or interrupted; :func:`writing` does it for
training and fine-tuning alike."""

from __future__ import annotations

import contextlib
import os
import socket
import warnings
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from omegaconf import DictConfig, OmegaConf

from hmepol_cli.errors import Interrupted, RunDirError, StorageError
from hmepol_cli.run.io import (
    atomic_write_text,
    read_json,
    remove_temporaries,
    umask,
    write_json,
)
from hmepol_cli.run.layout import COMMANDS, CONFIG, RUN_INFO
from hmepol_cli.run.lock import RunLock
from hmepol_cli.run.provenance import (
    identity_differences,
    identity_hash,
    provenance,
    timestamp,
)

if TYPE_CHECKING:  # a device is only passed on: torch is not needed to read a run directory
    import torch


# What names a machine in run.json's ``machines`` (a new entry when one of them changes)
MACHINE_KEYS = ("host", "cpu", "cpu_capability", "device", "gpu")


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
            made_by = provenance(device)  # once: it asks git for the source's state
            with open(self.path / COMMANDS, "a") as log:
                os.chmod(self.path / COMMANDS, 0o666 & ~umask())
                log.write(
                    f"{timestamp()} {socket.gethostname()} pid={os.getpid()} "
                    f"{made_by['command']}\n"
                )
            self.update(
                kind=self.kind,
                status="running",
                identity=identity_hash(self.cfg),
                owner=self.lock.owner,
                provenance=made_by,
                machines=machines_after(self.info(), made_by),
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
            failure={
                "reason": reason,
                "epoch": epoch,
                "last_finite": last or {},
                "at": timestamp(),
            },
        )

    def interrupt(self, signal_name: str) -> None:
        """Record that the run was stopped by a signal; the next run of the command continues."""
        info = self.info()
        self.update(
            status="interrupted",
            interruption={"signal": signal_name, "epochs_done": info.get("epochs_done", 0),
                          "at": timestamp()},
        )  # fmt: skip

    def close(self) -> None:
        self.lock.release()

    def __enter__(self) -> RunDirectory:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()


def machines_after(info: dict[str, Any], made_by: dict[str, Any]) -> list[dict[str, Any]]:
    """run.json's ``machines``: each machine a run has trained on (host, CPU, device) and the
    epoch it took the run up from, one entry per change of machine. A run continued elsewhere
    keeps the record of where its earlier epochs were made; ``provenance`` holds the latest."""
    machine = {key: made_by.get(key) for key in MACHINE_KEYS}
    machines = list(info.get("machines") or [])
    if machines and {key: machines[-1].get(key) for key in MACHINE_KEYS} == machine:
        return machines
    start = {"from_epoch": int(info.get("epochs_done", 0)), "at": timestamp()}
    return [*machines, {**start, **machine}]


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
