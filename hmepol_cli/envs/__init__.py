"""Environment classes by name; ``make_world`` builds one from the ``env`` config group."""

from __future__ import annotations

from hmepol_cli.envs.base import Box, NavigationWorld
from hmepol_cli.envs.corridor import CorridorWorld
from hmepol_cli.envs.multigrid import MultiGridWorld
from hmepol_cli.envs.slope import SlopeWorld

# name -> world class; a new world is one module, one entry here and one conf/env/<name>.yaml.
ENVIRONMENTS: dict[str, type[NavigationWorld]] = {
    "slope": SlopeWorld,
    "corridor": CorridorWorld,
    "multigrid": MultiGridWorld,
}


def make_world(env_cfg) -> NavigationWorld:
    """Build the world named by ``env_cfg.name`` (an EnvConfig or DictConfig)."""
    try:
        world = ENVIRONMENTS[env_cfg.name]
    except KeyError:
        raise ValueError(
            f"unknown env {env_cfg.name!r}; choose one of: {', '.join(ENVIRONMENTS)}"
        ) from None
    return world.from_config(env_cfg)


# Gymnasium ids (hmepol/Slope-v0, ...) are registered on import; registering twice is a no-op.
from hmepol_cli.envs.gym_api import register_envs  # noqa: E402

register_envs()

__all__ = ["Box", "ENVIRONMENTS", "NavigationWorld", "make_world"]
