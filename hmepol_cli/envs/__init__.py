"""Environment classes by name; ``make_world`` builds one from the ``env`` config group."""

from __future__ import annotations

from collections.abc import Callable

from hmepol_cli.envs.base import Box, NavigationWorld
from hmepol_cli.envs.corridor import CorridorWorld
from hmepol_cli.envs.multigrid import MultiGridWorld
from hmepol_cli.envs.slope import SlopeWorld

# name -> factory(env_config) ; a new world is one module plus one entry here and one YAML file.
ENVIRONMENTS: dict[str, Callable[..., NavigationWorld]] = {
    "slope": lambda cfg: SlopeWorld(),
    "corridor": lambda cfg: CorridorWorld(wind=cfg.wind),
    "multigrid": lambda cfg: MultiGridWorld(),
}


def make_world(env_cfg) -> NavigationWorld:
    """Build the world named by ``env_cfg.name`` (an EnvConfig or DictConfig)."""
    try:
        factory = ENVIRONMENTS[env_cfg.name]
    except KeyError:
        raise ValueError(
            f"unknown env {env_cfg.name!r}; choose one of: {', '.join(ENVIRONMENTS)}"
        ) from None
    return factory(env_cfg)


# Gymnasium ids (hmepol/Slope-v0, ...) are registered on import; registering twice is a no-op.
from hmepol_cli.envs.gym_api import register_envs  # noqa: E402

register_envs()

__all__ = ["Box", "ENVIRONMENTS", "NavigationWorld", "make_world"]
