"""MultiGrid (thesis 5.3, Fig. 5.11): ten gridworlds on [-1, 1]^2 with different walls and slopes.

Every layout is 10 x 10 blocks of 0.2 (``#`` wall, ``.`` free, first row at the top), keeps the
start box [-1, -0.5]^2 (the bottom-left 3 x 3 blocks) free, and has every free block reachable
from it (4-neighbour moves; ``tests/test_envs.py`` checks both).

Configurations, drawn uniformly (p_M = 1/10 each; the thesis does not give p_M):

====  ==================  ==========  ==============================================
 #    name                slope       layout
====  ==================  ==========  ==============================================
 0    four_rooms_north    north       the slope world's four rooms (thesis Fig. 5.1)
 1    zigzag_south        south       one corridor that zigzags up through the arena
 2    pillars_south       south       open floor with four pillars
 3    spiral_east         east        a spiral corridor inside an outer ring
 4    serpentine_east     east        walls hanging alternately from top and bottom
 5    nine_rooms_east     east        a 3 x 3 grid of rooms joined by doors
 6    blocks_southeast    south-east  three blocks and a bar around open lanes
 7    maze                none        a maze of one-block corridors
 8    halls               none        three long halls joined by narrow doors
 9    open                none        an open square with one central block
====  ==================  ==========  ==============================================

Slopes: config 0 is the slope world's north configuration with a reduced slope: magnitude
~ N(0.077, 0.01) truncated to [0, 0.2], acting only in the bottom half of the arena (y <= 0,
exactly as the slope world). The other slopes have magnitude ~ N(0.1, 0.01) truncated to
[0, 0.2] and act on the whole arena; the south-east direction is normalised, (1, -1) / sqrt(2).
"""

from __future__ import annotations

import math

from hmepol_cli.envs.grid import FOUR_ROOMS, GridWorld, SlopeSpec
from hmepol_cli.envs.slope import SLOPE_REGION

NORTH_SLOPE_MEAN = 0.077  # config 0, thesis 5.3
SLOPE_MEAN = 0.1  # every other sloped configuration

ZIGZAG = [
    "..........",
    "########..",
    "..........",
    "..########",
    "..........",
    "######.###",
    "..........",
    "..........",
    "....###...",
    "..........",
]

PILLARS = [
    "..........",
    ".##....##.",
    ".##....##.",
    "..........",
    "....##....",
    "....##....",
    "..........",
    ".......##.",
    ".......##.",
    "..........",
]

SPIRAL = [
    "..........",
    ".########.",
    ".#......#.",
    ".#.####.#.",
    ".#.#..#.#.",
    ".#.#.##.#.",
    ".#.#....#.",
    "...######.",
    "..........",
    "..........",
]

SERPENTINE = [
    "..#...#...",
    "..#.#.#.#.",
    "..#.#.#.#.",
    "..#.#.#.#.",
    "..#.#.#.#.",
    "..#.#.#.#.",
    "....#...#.",
    "....#...#.",
    "....#...#.",
    "....#...#.",
]

NINE_ROOMS = [
    "...#..#...",
    "......#...",
    "...#......",
    "#.###.##.#",
    "...#..#...",
    "...#......",
    "#.###.##.#",
    "...#..#...",
    "......#...",
    "...#..#...",
]

BLOCKS = [
    "..........",
    ".###..###.",
    ".###..###.",
    ".###..###.",
    "..........",
    "..........",
    "...#..###.",
    "...#..###.",
    "...#..###.",
    "..........",
]

MAZE = [
    "..........",
    ".####.###.",
    ".#......#.",
    ".#.####.#.",
    "...#..#...",
    "##.#.##.##",
    "...#......",
    "...#.####.",
    "...#.#....",
    ".....#..#.",
]

HALLS = [
    "..........",
    "..........",
    "..........",
    "#.####.###",
    "..........",
    "..........",
    "########.#",
    "..........",
    "..........",
    "..........",
]

OPEN = [
    "..........",
    "..........",
    "..........",
    "...####...",
    "...####...",
    "...####...",
    "...####...",
    "..........",
    "..........",
    "..........",
]

NORTH, SOUTH, EAST = (0.0, 1.0), (0.0, -1.0), (1.0, 0.0)
SOUTH_EAST = (1.0 / math.sqrt(2.0), -1.0 / math.sqrt(2.0))
NO_SLOPE = SlopeSpec()

CONFIGS: tuple[tuple[str, list[str], SlopeSpec], ...] = (
    ("four_rooms_north", FOUR_ROOMS, SlopeSpec(NORTH, NORTH_SLOPE_MEAN, SLOPE_REGION)),
    ("zigzag_south", ZIGZAG, SlopeSpec(SOUTH, SLOPE_MEAN)),
    ("pillars_south", PILLARS, SlopeSpec(SOUTH, SLOPE_MEAN)),
    ("spiral_east", SPIRAL, SlopeSpec(EAST, SLOPE_MEAN)),
    ("serpentine_east", SERPENTINE, SlopeSpec(EAST, SLOPE_MEAN)),
    ("nine_rooms_east", NINE_ROOMS, SlopeSpec(EAST, SLOPE_MEAN)),
    ("blocks_southeast", BLOCKS, SlopeSpec(SOUTH_EAST, SLOPE_MEAN)),
    ("maze", MAZE, NO_SLOPE),
    ("halls", HALLS, NO_SLOPE),
    ("open", OPEN, NO_SLOPE),
)


class MultiGridWorld(GridWorld):
    name = "multigrid"

    def __init__(self) -> None:
        super().__init__(
            layouts=[layout for _, layout, _ in CONFIGS],
            slopes=[slope for _, _, slope in CONFIGS],
            probs=tuple(1.0 / len(CONFIGS) for _ in CONFIGS),
            names=tuple(name for name, _, _ in CONFIGS),
        )
