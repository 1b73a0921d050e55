"""User errors: mistakes of input that the command reports in one line, never a traceback.

Anything else (a bug) keeps its traceback.
"""

from __future__ import annotations


class UserError(Exception):
    """A mistake in what the user asked for; the CLI prints it as one line and exits 2."""


class ConfigError(UserError, ValueError):
    """A config value that is not allowed: the message names the value and what is allowed."""


class RunDirError(UserError):
    """A run directory that is not one, is locked by another process, or does not match."""


class TableError(RunDirError):
    """A run's CSV table that a reader cannot use: missing, not text, cut short, a row that does
    not parse; the message names the file (and the line)."""


class RunFailure(UserError):
    """A run stopped because its numbers stopped making sense (non-finite values)."""


class StorageError(UserError):
    """A file could not be written (a full disk, a quota, a read-only folder)."""


class Interrupted(BaseException):
    """SIGTERM (a cluster's preemption or time limit) or SIGINT (Ctrl-C) arrived: the command
    stops where it is, records its runs as interrupted, and exits with 128 + the signal.

    A BaseException, like KeyboardInterrupt, so that no ``except Exception`` swallows it."""

    def __init__(self, signum: int) -> None:
        import signal

        self.signum = signum
        self.name = signal.Signals(signum).name
        super().__init__(f"interrupted by {self.name}")

    @property
    def exit_code(self) -> int:
        return 128 + self.signum
