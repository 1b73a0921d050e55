"""Grid World with Slope (thesis 5.1, Fig. 5.1): four rooms, a slope south (p=0.8) or north.

The slope pushes only in the bottom half of the arena (y < 0), the half that holds the start
room, as in the public reference implementation of [22]; its magnitude is drawn every step from
N(0.1, 0.01) truncated to [0, 0.2].
"""

from __future__ import annotations

from hmepol_cli.envs.base import Box
from hmepol_cli.envs.grid import FOUR_ROOMS, GridWorld, SlopeSpec

SLOPE_MEAN = 0.1
SLOPE_REGION = Box(-1.0, -1.0, 1.0, 0.0)


class SlopeWorld(GridWorld):
    name = "slope"

    def __init__(self) -> None:
        super().__init__(
            layouts=[FOUR_ROOMS, FOUR_ROOMS],
            slopes=[
                SlopeSpec((0.0, -1.0), SLOPE_MEAN, SLOPE_REGION),
                SlopeSpec((0.0, 1.0), SLOPE_MEAN, SLOPE_REGION),
            ],
            probs=(0.8, 0.2),
            names=("south", "north"),
        )
