"""Grid World with Slope (thesis 5.1, Fig. 5.1), as in the reference of [22] (docs/worlds.md).

Four rooms; the start area is the north-west corner. A slope acts in the northern half of the
arena (the half that holds the start room), its magnitude drawn every step from N(0.1, 0.01)
truncated to [0, 0.2] and added to the clipped action:

- config 0, p = 0.8, the thesis' favourable "south-facing slope": it pushes south, carrying
  agents away from the start room's outer wall towards the rest of the world;
- config 1, p = 0.2, the unfavourable "north-facing slope": it pushes north, pinning agents
  against the start room's outer (northern) wall.
"""

from __future__ import annotations

from hmepol_cli.envs.grid import FOUR_ROOMS, NORTH, NORTHERN_HALF, SOUTH, GridWorld, SlopeSpec

SLOPE_MEAN = 0.1  # thesis 5.1: N(0.1, 0.01) truncated to [0, 0.2]


class SlopeWorld(GridWorld):
    name = "slope"

    def __init__(self, edge: str = "slide") -> None:
        super().__init__(
            layouts=[FOUR_ROOMS, FOUR_ROOMS],
            slopes=[
                SlopeSpec.centred(SOUTH, SLOPE_MEAN, NORTHERN_HALF),
                SlopeSpec.centred(NORTH, SLOPE_MEAN, NORTHERN_HALF),
            ],
            probs=(0.8, 0.2),
            names=("south slope", "north slope"),
            edge=edge,
        )
