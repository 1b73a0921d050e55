"""A sweep's jobs and their folders, on Hydra's public override grammar (no private API).

``jobs`` expands ``key=a,b key2=c,d`` into the cartesian product of jobs, as Hydra's basic
sweeper does; ``override_dirname`` names a job's folder as Hydra names it
(``hydra.job.override_dirname``): its overrides, sorted, without the excluded keys.
"""

from __future__ import annotations

import itertools
import logging
import re
from collections.abc import Sequence

from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import Override


def parse(overrides: Sequence[str]) -> list[Override]:
    """Hydra's parsed overrides (HydraException on a malformed one)."""
    return OverridesParser.create().parse_overrides(list(overrides))


def jobs(overrides: Sequence[str]) -> list[list[str]]:
    """Every job a sweep runs: one value of each swept key, in Hydra's order. A key given twice
    keeps its last value, as Hydra does."""
    choices: dict[str, list[str]] = {}
    for override in parse(overrides):
        key = override.get_key_element()
        if override.is_sweep_override():
            choices[key] = [f"{key}={v}" for v in override.sweep_string_iterator()]
        else:
            choices[key] = [f"{key}={override.get_value_element_as_str()}"]
    return [list(job) for job in itertools.product(*choices.values())]


def override_dirname(
    overrides: Sequence[str], exclude_keys: Sequence[str], item_sep: str, kv_sep: str
) -> str:
    """``hydra.job.override_dirname`` of a job with these overrides."""
    lines = sorted(
        o.input_line for o in parse(overrides) if o.key_or_group not in set(exclude_keys)
    )
    return re.sub("=", kv_sep, item_sep.join(lines))


class NoLibraryBanner(logging.Filter):
    """Drops the joblib launcher's banner (``Joblib.Parallel(n_jobs=2, backend=loky, ...) is
    launching N jobs``) from Hydra's log; the sweep's folder and its jobs' overrides stay."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith("Joblib.Parallel(")
