"""The worlds: environment classes by name (:mod:`hmepol_cli.envs.registry`); ``make_world``
builds one from the ``env`` config group."""

from __future__ import annotations

from hmepol_cli.envs.base import Box, NavigationWorld
from hmepol_cli.envs.gym_api import register_envs
from hmepol_cli.envs.gym_world import GymWorld
from hmepol_cli.envs.registry import ENVIRONMENTS, make_world
from hmepol_cli.envs.world import World

# Gymnasium ids (hmepol/Slope-v0, ...) are registered on import; registering twice is a no-op.
register_envs()

__all__ = ["Box", "ENVIRONMENTS", "GymWorld", "NavigationWorld", "World", "make_world"]
