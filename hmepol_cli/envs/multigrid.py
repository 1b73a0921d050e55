"""MultiGrid (thesis 5.3, Fig. 5.11): the ten gridworlds of [22] on [-1, 1]^2, p_M uniform.

Layouts and slopes as the public reference implementation has them (docs/worlds.md), maps
printed north at the top (``#`` wall block of 0.2 x 0.2, ``.`` free). Slopes are added to the
clipped action every step, with magnitudes drawn from truncated normals of sd 0.01:

====  =====================  ===========  ===========  ===============================
 #    layout                 slope        where        magnitude
====  =====================  ===========  ===========  ===============================
 0    four rooms (slope)     north        north half   N(0.077, 0.01) on [0, 0.154]
 1    bars                   east         everywhere   N(0.0625, 0.01) on [0, 0.125]
 2    split halls            south        everywhere   same
 3    terraces               south-east   everywhere   same, added to both axes
 4    blocks                 none
 5    narrow passages        east         everywhere   same
 6    two rooms              south        everywhere   same
 7    two halls, one door    none
 8    stepped maze           none
 9    ring                   east         everywhere   same
====  =====================  ===========  ===========  ===============================

Config 0 is the adversarial one: its slope pushes agents into the start room's outer wall. The
reference draws its magnitudes as fractions of the action bound 0.2: mean 0.2 / 2.6 (the thesis
rounds it to 0.077) up to 0.2 / 1.3, and mean 0.2 / 3.2 = 0.0625 up to 0.2 / 1.6.

Parts of the start area lie in a wall in configurations 3, 4, 5 and 9; agents start uniformly in its
free part (the reference would start some inside the wall).
"""

from __future__ import annotations

from hmepol_cli.envs.base import MAX_ACTION
from hmepol_cli.envs.grid import (
    EAST,
    FOUR_ROOMS,
    NORTH,
    NORTHERN_HALF,
    SOUTH,
    SOUTH_EAST,
    GridWorld,
    SlopeSpec,
)

ADVERSARIAL_MEAN = MAX_ACTION / 2.6  # config 0: 0.0769
SLOPE_MEAN = MAX_ACTION / 3.2  # every other sloped configuration: 0.0625

BARS = [
    "......##..",
    "......##..",
    "......##..",
    "##....##..",
    "##........",
    "##........",
    "##........",
    "##........",
    "########..",
    "########..",
]
SPLIT_HALLS = [
    "....##....",
    "....##....",
    "....##....",
    "..........",
    "....##....",
    "....##....",
    "..........",
    "....##....",
    "....##....",
    "....##....",
]
TERRACES = [
    "..........",
    "..........",
    "########..",
    "##........",
    "##........",
    "######....",
    "######....",
    "####......",
    "####......",
    "####......",
]
BLOCKS = [
    "..........",
    "..........",
    "#.........",
    "#.........",
    "#..####...",
    "#.........",
    "...####...",
    "...####...",
    "...####...",
    "...####...",
]
NARROW_PASSAGES = [
    "..########",
    "..########",
    "..########",
    "..########",
    "..........",
    "..........",
    "..##...###",
    "..##...###",
    "..##...###",
    "..##...###",
]
TWO_ROOMS = [
    ".......###",
    ".......###",
    ".......###",
    ".......###",
    "####..####",
    "####..####",
    ".......###",
    ".......###",
    ".......###",
    "##########",
]
TWO_HALLS = [
    "..........",
    "..........",
    "..........",
    "#####.####",
    "#####.####",
    "#####.####",
    "..........",
    "..........",
    "..........",
    "..........",
]
STEPPED_MAZE = [
    "......####",
    "......####",
    "........##",
    "........##",
    "....##....",
    "....##....",
    "##......##",
    "##......##",
    "####..####",
    "####..####",
]
RING = [
    "..........",
    "..######..",
    "..######..",
    "..##..##..",
    "..........",
    "..........",
    "..##..##..",
    "..######..",
    "..######..",
    "..........",
]

NO_SLOPE = SlopeSpec()
CONFIGS: tuple[tuple[str, list[str], SlopeSpec], ...] = (
    (
        "four rooms, north slope",
        FOUR_ROOMS,
        SlopeSpec.centred(NORTH, ADVERSARIAL_MEAN, NORTHERN_HALF),
    ),
    ("bars, east slope", BARS, SlopeSpec.centred(EAST, SLOPE_MEAN)),
    ("split halls, south slope", SPLIT_HALLS, SlopeSpec.centred(SOUTH, SLOPE_MEAN)),
    ("terraces, south-east slope", TERRACES, SlopeSpec.centred(SOUTH_EAST, SLOPE_MEAN)),
    ("blocks, no slope", BLOCKS, NO_SLOPE),
    ("narrow passages, east slope", NARROW_PASSAGES, SlopeSpec.centred(EAST, SLOPE_MEAN)),
    ("two rooms, south slope", TWO_ROOMS, SlopeSpec.centred(SOUTH, SLOPE_MEAN)),
    ("two halls, no slope", TWO_HALLS, NO_SLOPE),
    ("stepped maze, no slope", STEPPED_MAZE, NO_SLOPE),
    ("ring, east slope", RING, SlopeSpec.centred(EAST, SLOPE_MEAN)),
)


class MultiGridWorld(GridWorld):
    name = "multigrid"

    def __init__(self, edge: str = "slide") -> None:
        super().__init__(
            layouts=[layout for _, layout, _ in CONFIGS],
            slopes=[slope for _, _, slope in CONFIGS],
            probs=tuple(1.0 / len(CONFIGS) for _ in CONFIGS),
            names=tuple(name for name, _, _ in CONFIGS),
            edge=edge,
        )
