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


class RunFailure(UserError):
    """A run stopped because its numbers stopped making sense (non-finite values)."""
