"""Write hmepol_cli/report/config_defaults.json: the config values the report holds runs against.

The report imports no training code, so what today's config says is kept beside it as data:

- ``schema``: the schema's defaults (:class:`hmepol_cli.config.Config`), flattened. A run made
  before a key existed takes its default, so old and new runs of the same settings group
  together;
- ``algorithms``: for each conf/algo/<name>.yaml, the flattened config ``algo=<name>``
  composes to (the thesis' settings), which the report names a group's departures from.

tests/test_imports.py checks that the file equals what the config gives; after a change to the
schema or conf/, write it again from the repository root::

    python -m tools.config_defaults
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from hmepol_cli.checks import compose
from hmepol_cli.config import Config, register_configs
from hmepol_cli.report.defaults import DEFAULTS_FILE
from hmepol_cli.run import flat_config

CONF = Path(__file__).resolve().parents[1] / "conf"


def config_defaults() -> dict[str, Any]:
    """{"schema": {key: default}, "algorithms": {name: {key: value}}}, as JSON holds them."""
    register_configs()
    algorithms = {
        path.stem: flat_config(
            OmegaConf.to_container(compose("config", [f"algo={path.stem}"]), resolve=False)
        )
        for path in sorted((CONF / "algo").glob("*.yaml"))
    }
    schema = flat_config(OmegaConf.to_container(OmegaConf.structured(Config)))
    # JSON's lists stand for the flattened config's tuples (read back by hashable_value).
    return json.loads(json.dumps({"schema": schema, "algorithms": algorithms}))


def main() -> None:
    text = json.dumps(config_defaults(), indent=1, sort_keys=True) + "\n"
    DEFAULTS_FILE.write_text(text)
    print(f"wrote {DEFAULTS_FILE}")


if __name__ == "__main__":
    main()
