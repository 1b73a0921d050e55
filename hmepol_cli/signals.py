"""SIGTERM and SIGINT as an :class:`~hmepol_cli.errors.Interrupted` exception.

A cluster preempts or ends a job with SIGTERM (SLURM then waits ``KillWait`` seconds before
SIGKILL); a person presses Ctrl-C (SIGINT). Either way the command should stop where it is:
every file a run writes is written to a temporary name and renamed, and a run's checkpoint is
written after its CSV rows, so abandoning the current epoch loses only that epoch, which the
next run of the same command recomputes exactly from the last checkpoint. The handler raises
in the main thread; the run-directory lifecycle (:func:`hmepol_cli.run.writing`) records
the runs as interrupted and releases their locks; the CLI prints one line and exits 128 + the
signal. A second signal while that cleanup runs is ignored.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator

from hmepol_cli.errors import Interrupted

SIGNALS = (signal.SIGTERM, signal.SIGINT)
_state = {"raised": False}


def _raise(signum: int, frame: object) -> None:
    if _state["raised"]:  # already stopping: let the cleanup finish
        return
    _state["raised"] = True
    raise Interrupted(signum)


@contextlib.contextmanager
def preemptible() -> Iterator[None]:
    """SIGTERM and SIGINT raise Interrupted inside this block (in the main thread; elsewhere
    the block changes nothing)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.getsignal(s) for s in SIGNALS}
    _state["raised"] = False
    for s in SIGNALS:
        signal.signal(s, _raise)
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
