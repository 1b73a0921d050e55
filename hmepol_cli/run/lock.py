"""The lock of a run directory: one process writes it at a time; the lock of a process that is
gone is taken over with a warning."""

from __future__ import annotations

import json
import os
import socket
import time
import warnings
from pathlib import Path
from typing import Any

from hmepol_cli.errors import RunDirError
from hmepol_cli.run.layout import LOCK
from hmepol_cli.run.provenance import timestamp


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
            "started": timestamp(),
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
