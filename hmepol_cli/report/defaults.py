"""Today's config as data: the schema's defaults, and each algorithm's own settings
(conf/algo/<name>.yaml, the thesis'), flattened; what the report holds a run's config against.

The report imports no training code, so these are read from config_defaults.json, written by
``python -m tools.config_defaults`` from the schema and conf/ (a test checks that they agree).
"""

from __future__ import annotations

import json
from functools import cache
from pathlib import Path
from typing import Any

from hmepol_cli.run import hashable_value

DEFAULTS_FILE = Path(__file__).with_name("config_defaults.json")


@cache
def _defaults() -> dict[str, dict[str, Any]]:
    return json.loads(DEFAULTS_FILE.read_text())


def _flat(values: dict[str, Any]) -> dict[str, Any]:
    """A flattened config as :func:`hmepol_cli.run.flat_config` gives it: lists as tuples."""
    return {key: hashable_value(value) for key, value in values.items()}


def schema_defaults() -> dict[str, Any]:
    """The schema's default of every key (a run made before a key existed ran with it, the
    rules aside: :mod:`hmepol_cli.report.rules`)."""
    return _flat(_defaults()["schema"])


def algo_defaults(algo: str) -> dict[str, Any] | None:
    """The flattened config ``algo=<algo>`` composes to (None for an algorithm this checkout
    does not have)."""
    settings = _defaults()["algorithms"].get(algo)
    return None if settings is None else _flat(settings)
