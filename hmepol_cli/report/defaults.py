"""An algorithm's own settings (conf/algo/<name>.yaml, the thesis'), flattened: what the report
holds a group's runs against when it names what sets them apart."""

from __future__ import annotations

from functools import cache
from typing import Any

from hmepol_cli.errors import ConfigError


@cache
def algo_defaults(algo: str) -> dict[str, Any] | None:
    """The flattened config ``algo=<algo>`` composes to (None where it cannot: an algorithm of
    another checkout)."""
    from omegaconf import OmegaConf

    from hmepol_cli.checks import compose
    from hmepol_cli.config import register_configs
    from hmepol_cli.run import flat_config

    register_configs()
    try:
        cfg = compose("config", [f"algo={algo}"])
    except ConfigError:
        return None
    return flat_config(OmegaConf.to_container(cfg, resolve=False))
