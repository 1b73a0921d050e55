"""Environment classes by name; ``make_world`` builds one from the ``env`` config group."""

from __future__ import annotations

from hmepol_cli.envs.corridor import CorridorWorld
from hmepol_cli.envs.gym_world import GymWorld
from hmepol_cli.envs.multigrid import MultiGridWorld
from hmepol_cli.envs.slope import SlopeWorld
from hmepol_cli.envs.world import World

# name -> world class; a new world is one module, one entry here and one conf/env/<name>.yaml.
# "gym" is any Gymnasium environment (env.id=...); presets such as conf/env/ant_xy.yaml name it.
ENVIRONMENTS: dict[str, type[World]] = {
    "slope": SlopeWorld,
    "corridor": CorridorWorld,
    "multigrid": MultiGridWorld,
    "gym": GymWorld,
}


def make_world(env_cfg) -> World:
    """Build the world named by ``env_cfg.name`` (an EnvConfig or DictConfig)."""
    try:
        world = ENVIRONMENTS[env_cfg.name]
    except KeyError:
        raise ValueError(
            f"unknown env {env_cfg.name!r}; choose one of: {', '.join(ENVIRONMENTS)}"
        ) from None
    return world.from_config(env_cfg)
