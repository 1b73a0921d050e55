"""The config of a continued run (``resume=<run dir>``): the one it started with, beside the
schema of :mod:`hmepol_cli.config`."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig, OmegaConf, open_dict

from hmepol_cli.errors import ConfigError
from hmepol_cli.run import RESUMABLE_KEYS, run_config


def resumed_config(cfg: DictConfig, run_dir: Path, overrides: list[str]) -> DictConfig:
    """The config a run started with, with the keys a continuation may change taken from the
    command line; any other override is refused (the run keeps what it is)."""
    saved = run_config(run_dir)
    changed = []
    with open_dict(saved):
        for item in overrides:
            key = item.lstrip("+~").partition("=")[0]
            if key.startswith("hydra") or key == "resume":
                continue
            if key in RESUMABLE_KEYS or key.split(".")[0] in RESUMABLE_KEYS:
                OmegaConf.update(saved, key, OmegaConf.select(cfg, key), force_add=True)
            elif OmegaConf.select(cfg, key) != OmegaConf.select(saved, key):
                changed.append(item)  # giving a run the value it already has is no change
        saved.resume = str(run_dir)
    if changed:
        raise ConfigError(
            f"{run_dir} keeps the config it started with; {', '.join(changed)} cannot change on "
            f"resume (only {', '.join(RESUMABLE_KEYS[:5])}, ... can)"
        )
    return saved
