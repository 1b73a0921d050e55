"""The worlds: solid walls, reachable layouts, forces as specified, Gymnasium API."""

from __future__ import annotations

import copy
import warnings
from collections import deque
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from omegaconf import OmegaConf

from hmepol_cli.envs import ENVIRONMENTS, make_world
from hmepol_cli.envs.base import EDGE_RULES, Box, NavigationWorld
from hmepol_cli.envs.corridor import EAST_STUB, ROOM, WEST_STUB, CorridorWorld
from hmepol_cli.envs.grid import GridWorld
from hmepol_cli.envs.gym_api import ENV_IDS, NavigationEnv, NavigationVectorEnv, register_envs
from hmepol_cli.envs.multigrid import MultiGridWorld
from hmepol_cli.envs.render import draw_world, force_arrows, show_world
from hmepol_cli.envs.slope import SlopeWorld
from tests.reference_edges import edge_distance, slide_path

CONF_ENV = Path(__file__).resolve().parents[1] / "conf" / "env"
WORLDS: dict[str, NavigationWorld] = {
    "slope": SlopeWorld(),
    "corridor": CorridorWorld(wind=0.4),
    "multigrid": MultiGridWorld(),
}
WORLD_CONFIGS = [(name, c) for name, w in WORLDS.items() for c in range(w.n_configurations)]
MIRRORED: dict[str, NavigationWorld] = {
    "slope": SlopeWorld(edge="mirror"),
    "corridor": CorridorWorld(wind=0.4, edge="mirror"),
    "multigrid": MultiGridWorld(edge="mirror"),
}


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def free_positions(world: NavigationWorld, config: int, n: int, g: torch.Generator) -> torch.Tensor:
    """n positions uniform over the free space of one configuration (rejection sampling). (n, 2)"""
    a = world.arena
    out = []
    while sum(len(p) for p in out) < n:
        u = torch.rand(4 * n, 2, generator=g)
        p = torch.stack((a.x0 + u[:, 0] * (a.x1 - a.x0), a.y0 + u[:, 1] * (a.y1 - a.y0)), 1)
        out.append(p[~world.inside_wall(p, torch.full((len(p),), config))])
    return torch.cat(out)[:n]


def near_walls(world: NavigationWorld, config: int, n: int, g: torch.Generator) -> torch.Tensor:
    """Free positions a hair (1e-4) outside wall faces and corners: the hardest starts. (<=n, 2)"""
    walls = torch.tensor([(b.x0, b.y0, b.x1, b.y1) for b in world.walls[config]])
    pick = walls[torch.randint(len(walls), (n,), generator=g)]
    u = torch.rand(n, 2, generator=g)
    # A point of the box's boundary, pushed out along its outward normal(s).
    x = pick[:, 0] + u[:, 0] * (pick[:, 2] - pick[:, 0])
    y = pick[:, 1] + u[:, 1] * (pick[:, 3] - pick[:, 1])
    side = torch.randint(4, (n,), generator=g)
    x = torch.where(side == 0, pick[:, 0] - 1e-4, torch.where(side == 1, pick[:, 2] + 1e-4, x))
    y = torch.where(side == 2, pick[:, 1] - 1e-4, torch.where(side == 3, pick[:, 3] + 1e-4, y))
    p = torch.stack((x, y), 1)
    ok = ~world.inside_wall(p, torch.full((n,), config)) & inside_arena(world, p)
    return p[ok]


def inside_arena(world: NavigationWorld, positions: torch.Tensor) -> torch.Tensor:
    a = world.arena
    x, y = positions[:, 0], positions[:, 1]
    return (x >= a.x0) & (x <= a.x1) & (y >= a.y0) & (y <= a.y1)


def fold(v: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Mirror coordinates beyond [lo, hi] back inside, as often as needed (not base.py's code)."""
    span = hi - lo
    r = np.mod(v - lo, 2 * span)
    return lo + np.where(r > span, 2 * span - r, r)


def fold_xy(world: NavigationWorld, points: np.ndarray) -> np.ndarray:
    a = world.arena
    return np.stack((fold(points[..., 0], a.x0, a.x1), fold(points[..., 1], a.y0, a.y1)), -1)


def in_wall_interior(world: NavigationWorld, config: int, points: np.ndarray, margin=0.0):
    """True where a point lies more than ``margin`` inside a wall. points (..., 2) -> (...)"""
    inside = np.zeros(points.shape[:-1], dtype=bool)
    x, y = points[..., 0], points[..., 1]
    for b in world.walls[config]:
        inside |= (
            (x > b.x0 + margin) & (x < b.x1 - margin) & (y > b.y0 + margin) & (y < b.y1 - margin)
        )
    return inside


def path_samples(world, start: np.ndarray, delta: np.ndarray, n: int = 2001) -> np.ndarray:
    """Points along start + t * delta, t in [0, 1], reflected into the arena. -> (N, n, 2)"""
    t = np.linspace(0.0, 1.0, n)[None, :, None]
    return fold_xy(world, start[:, None, :] + t * delta[:, None, :])


def expected_moves(world, p: np.ndarray, d: np.ndarray):
    """Where each move ends under the world's edge rule if nothing blocks it, and points along
    its path, from implementations that are not base.py's (tests/reference_edges.py's scalar slide,
    fold above). -> (ends (N, 2), samples (N, n, 2), resolved (N,) bool)"""
    if world.edge == "mirror":
        return fold_xy(world, p + d), path_samples(world, p, d), np.ones(len(p), dtype=bool)
    a = world.arena
    lo, hi = np.array([a.x0, a.y0]), np.array([a.x1, a.y1])
    ends, samples, resolved = [], [], []
    for start, delta in zip(p, d, strict=True):
        points = slide_path(start, delta, lo, hi)
        resolved.append(points is not None)
        points = points or [start, start]
        pieces = list(zip(points[:-1], points[1:], strict=True))
        t = np.linspace(0.0, 1.0, 2001 // len(pieces))[:, None]
        samples.append(np.concatenate([u + t * (v - u) for u, v in pieces]))
        ends.append(points[-1])
    n = min(len(x) for x in samples)
    return np.array(ends), np.stack([x[:n] for x in samples]), np.array(resolved)


# ---------------------------------------------------------------- solid walls, any move size
@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    which=st.sampled_from(WORLD_CONFIGS),
    edge=st.sampled_from(EDGE_RULES),
    seed=st.integers(0, 2**31 - 1),
    log_scale=st.floats(-3.0, 1.0),  # moves from 0.001 to 10 times the arena's side
)
def test_a_move_lands_free_and_never_passes_through_a_wall(which, edge, seed, log_scale):
    """Whatever the displacement, under either edge rule: the agent ends in the arena, outside
    every wall; a move whose path (turned or mirrored off the edges) enters a wall does not
    happen; one whose path stays clear does; a blocked move goes back against its direction by
    at most max_action / 2 per axis, or nowhere."""
    name, config = which
    world = (WORLDS if edge == "slide" else MIRRORED)[name]
    g = _gen(seed)
    span = world.arena.x1 - world.arena.x0
    positions = torch.cat(
        [free_positions(world, config, 64, g), near_walls(world, config, 64, g)]
    ).double()
    n = len(positions)
    configurations = torch.full((n,), config)
    displacement = torch.randn(n, 2, generator=g, dtype=torch.float64) * span * 10.0**log_scale
    displacement[::4, 0] = 0.0  # a quarter of the moves along one axis only
    displacement[1::4, 1] = 0.0
    push = torch.rand(n, 2, generator=g, dtype=torch.float64)
    world64 = copy.copy(world).to("cpu", torch.float64)
    new = world64.move(positions, displacement, configurations, push)

    assert not world64.inside_wall(new, configurations).any()
    assert inside_arena(world64, new).all()
    p, d, end = positions.numpy(), displacement.numpy(), new.numpy()
    target, samples, resolved = expected_moves(world, p, d)
    moved = np.isclose(end, target, atol=1e-9).all(axis=1) & resolved
    enters = in_wall_interior(world, config, samples).any(axis=1)
    assert not (moved & enters).any(), "a move passed through a wall"
    # Paths that stay clear of every wall by a margin are never blocked. The margin exceeds the
    # gap between a path's samples, so that a path grazing a wall's corner between two samples
    # is not taken for a clear one (a corridor move of 13.5 grazed a corner by 1.2e-4).
    gap = np.linalg.norm(np.diff(samples, axis=1), axis=-1).max(axis=1)[:, None]
    clear = ~in_wall_interior(world, config, samples, margin=-(gap + 1e-3)).any(axis=1)
    clear &= resolved
    if edge == "mirror":
        clear &= (np.abs(d) <= span).all(axis=1)
    assert moved[clear].all(), "a move with a clear path was blocked"
    # A blocked move: stays, or steps back against the move by at most push_back per axis.
    back = ~moved & ~(end == p).all(axis=1)
    a = world.arena
    away_from_edges = (p[:, 0] > a.x0 + 0.1) & (p[:, 0] < a.x1 - 0.1)
    away_from_edges &= (p[:, 1] > a.y0 + 0.1) & (p[:, 1] < a.y1 - 0.1)
    step = (end - p)[back & away_from_edges]
    expected = -np.sign(d) * push.numpy() * world.push_back
    assert np.allclose(step, expected[back & away_from_edges], atol=1e-9)


def test_a_step_displaces_by_the_clipped_action_plus_the_force_in_open_space():
    world = WORLDS["multigrid"]
    positions = torch.tensor([[0.5, 0.8]])  # config 7 ("two halls"): no wall nearby, no slope
    new = world.step(positions, torch.tensor([[5.0, -0.05]]), torch.tensor([7]))
    assert torch.allclose(new, torch.tensor([[0.7, 0.75]]))


# docs/worlds.md's worked examples (multigrid config 7: open floor, no slope): from, move,
# where the reference lands, where a mirror would. The last one slides into the north-west
# corner and is turned twice; the page rounds it to 4 decimals, worked out by hand: the move
# crosses x = -1 at 0.15 of its length, at (-1, 0.9045); its rest (-0.17, 0.0255) becomes
# (0.0255, 0.17), which crosses y = 1 at 0.0955 / 0.17 of its length, at (-0.985675, 1); that
# rest (0.011175, 0.0745) becomes (0.0745, -0.011175): (-0.911175, 0.988825).
WORKED_EXAMPLES = [
    ((-0.5, 0.95), (0.05, 0.2), (-0.3375, 0.9625), (-0.45, 0.85)),
    ((-0.5, 0.95), (-0.05, 0.2), (-0.6625, 0.9625), (-0.55, 0.85)),
    ((-0.5, 0.95), (0.2, 0.2), (-0.3, 0.85), (-0.3, 0.85)),
    ((-0.5, 0.99), (0.0, 0.2), (-0.5, 0.81), (-0.5, 0.81)),
    ((0.95, -0.5), (0.2, 0.05), (0.9625, -0.3375), (0.85, -0.45)),
    ((-0.95, 0.95), (-0.2, 0.2), (-0.85, 0.85), (-0.85, 0.85)),
    ((-0.97, 0.9), (-0.2, 0.03), (-0.911175, 0.988825), (-0.83, 0.93)),
]


@pytest.mark.parametrize("edge, column", [("slide", 2), ("mirror", 3)])
def test_the_edge_rules_reproduce_the_reference_pages_worked_examples(edge, column):
    world = MultiGridWorld(edge=edge).to("cpu", torch.float64)
    rows = torch.tensor([[*r[0], *r[1], *r[column]] for r in WORKED_EXAMPLES], dtype=torch.float64)
    configurations = torch.full((len(rows),), 7)
    actions = rows[:, 2:4]
    noise = torch.zeros(len(rows), world.noise_size, dtype=torch.float64)  # push-back unused
    new = world.step(rows[:, :2], actions, configurations, noise=noise)
    torch.testing.assert_close(new, rows[:, 4:], rtol=0, atol=1e-9)
    # The page's own rounded figures for the corner case.
    if edge == "slide":
        assert new[-1].tolist() == pytest.approx([-0.9112, 0.9888], abs=5e-5)


def test_the_slide_keeps_agents_pushed_into_an_edge_as_close_as_the_reference_does():
    """docs/worlds.md: agents pushed steadily into an edge stay about 0.04 from it on
    average under the reference's rule, about 0.09 under a mirror."""
    slide = edge_distance(MultiGridWorld().to("cpu", torch.float64))
    mirror = edge_distance(MultiGridWorld(edge="mirror").to("cpu", torch.float64))
    assert slide == pytest.approx(0.04, abs=0.01)
    assert mirror == pytest.approx(0.09, abs=0.01)


def test_a_wall_pushes_the_agent_back_by_the_uniform_noise():
    world = copy.copy(WORLDS["slope"]).to("cpu", torch.float64)
    # In the north-west room, west of the central wall (x in [-0.2, 0.2], y in [0.6, 1]).
    positions = torch.tensor([[-0.3, 0.7], [-0.3, 0.7]], dtype=torch.float64)
    # Noise: push-back x, push-back y, slope quantile (0.5: the median magnitude, 0.1).
    noise = torch.tensor([[0.5, 0.25, 0.5], [0.0, 1.0, 0.5]], dtype=torch.float64)
    actions = torch.tensor([[0.2, 0.05], [0.2, 0.05]], dtype=torch.float64)
    new = world.step(positions, actions, torch.tensor([0, 0]), noise=noise)
    # Displacement (0.2, 0.05 - 0.1) ends in the wall: back by (-0.5, +0.25) x 0.1, (0, +1) x 0.1.
    expected = torch.tensor([[-0.35, 0.725], [-0.3, 0.8]], dtype=torch.float64)
    assert torch.allclose(new, expected)


def test_a_push_back_into_a_wall_leaves_the_agent_where_it_was():
    world = WORLDS["slope"]
    # In the one-block door at x in [-0.6, -0.4], y in [-0.2, 0.2], next to its west side.
    positions = torch.tensor([[-0.58, 0.0]], dtype=torch.float64)
    world64 = copy.copy(world).to("cpu", torch.float64)
    # South-east into the door's east side; the push-back (west) would enter its west side.
    new = world64.move(
        positions,
        torch.tensor([[0.3, -0.05]], dtype=torch.float64),
        torch.tensor([1]),
        torch.tensor([[0.9, 0.1]], dtype=torch.float64),
    )
    assert torch.equal(new, positions)


# ---------------------------------------------------------------- layouts
# The reference implementation's layouts, verbatim: '#' wall, '.' free; first row north, first
# column west (docs/worlds.md).
REFERENCE_LAYOUTS = """
config 0          config 1          config 2          config 3          config 4
....##....        ......##..        ....##....        ..........        ..........
....##....        ......##..        ....##....        ..........        ..........
..........        ......##..        ....##....        ########..        #.........
....##....        ##....##..        ..........        ##........        #.........
##.####.##        ##........        ....##....        ##........        #..####...
##.####.##        ##........        ....##....        ######....        #.........
....##....        ##........        ..........        ######....        ...####...
..........        ##........        ....##....        ####......        ...####...
....##....        ########..        ....##....        ####......        ...####...
....##....        ########..        ....##....        ####......        ...####...

config 5          config 6          config 7          config 8          config 9
..########        .......###        ..........        ......####        ..........
..########        .......###        ..........        ......####        ..######..
..########        .......###        ..........        ........##        ..######..
..########        .......###        #####.####        ........##        ..##..##..
..........        ####..####        #####.####        ....##....        ..........
..........        ####..####        #####.####        ....##....        ..........
..##...###        .......###        ..........        ##......##        ..##..##..
..##...###        .......###        ..........        ##......##        ..######..
..##...###        .......###        ..........        ####..####        ..######..
..##...###        ##########        ..........        ####..####        ..........
"""


def reference_layouts() -> dict[int, list[str]]:
    lines = [line for line in REFERENCE_LAYOUTS.splitlines() if line.strip()]
    grids: dict[int, list[str]] = {}
    for block in (lines[:11], lines[11:]):
        ids = [int(word) for word in block[0].split()[1::2]]
        for row in block[1:]:
            for config, cells in zip(ids, row.split(), strict=True):
                grids.setdefault(config, []).append(cells)
    return grids


def cell_grid(world: NavigationWorld, config: int) -> list[str]:
    """The world's walls read back as a 10 x 10 map, first row north: a '#' where the cell's
    centre lies in a wall."""
    rows = []
    for r in range(10):
        y = 1 - 0.2 * r - 0.1
        rows.append(
            "".join(
                "#" if any(b.contains(-1 + 0.2 * c + 0.1, y) for b in world.walls[config]) else "."
                for c in range(10)
            )
        )
    return rows


@pytest.mark.parametrize("config", range(10))
def test_multigrid_layouts_equal_the_reference_cell_by_cell(config):
    assert cell_grid(WORLDS["multigrid"], config) == reference_layouts()[config]
    # The walls are exactly the '#' cells: free area = 0.04 per free cell.
    cells = sum(row.count(".") for row in reference_layouts()[config])
    assert WORLDS["multigrid"].free_area(config) == pytest.approx(0.04 * cells, abs=1e-6)


def test_the_slope_world_has_the_layout_of_multigrid_config_0():
    assert cell_grid(WORLDS["slope"], 0) == cell_grid(WORLDS["slope"], 1)
    assert cell_grid(WORLDS["slope"], 0) == reference_layouts()[0]


def start_cells(world: NavigationWorld) -> set[tuple[int, int]]:
    """(row, col) of the cells the start area overlaps."""
    s = world.start
    return {
        (r, c)
        for r in range(10)
        for c in range(10)
        if -1 + 0.2 * c < s.x1
        and -1 + 0.2 * (c + 1) > s.x0
        and 1 - 0.2 * (r + 1) < s.y1
        and 1 - 0.2 * r > s.y0
    }


@pytest.mark.parametrize("config", range(10))
def test_every_free_cell_is_reachable_from_the_start_area(config):
    rows = reference_layouts()[config]
    start = {(r, c) for r, c in start_cells(WORLDS["multigrid"]) if rows[r][c] == "."}
    assert start, "the start area has free cells"
    seen, todo = set(start), deque(start)
    while todo:
        r, c = todo.popleft()
        for rr, cc in ((r + 1, c), (r - 1, c), (r, c + 1), (r, c - 1)):
            if 0 <= rr < 10 and 0 <= cc < 10 and rows[rr][cc] == "." and (rr, cc) not in seen:
                seen.add((rr, cc))
                todo.append((rr, cc))
    free = {(r, c) for r in range(10) for c in range(10) if rows[r][c] == "."}
    assert free - seen == set(), f"cells {sorted(free - seen)} cannot be reached"


def test_the_start_area_is_the_north_west_corner():
    for name in ("slope", "multigrid"):
        s = WORLDS[name].start
        assert (s.x0, s.y0, s.x1, s.y1) == (-1.0, 0.5, -0.5, 1.0)


@pytest.mark.parametrize("name", list(WORLDS))
def test_agents_start_uniformly_in_the_free_part_of_the_start_area(name):
    world = WORLDS[name]
    s = world.start
    for c in range(world.n_configurations):
        configurations = torch.full((4000,), c)
        starts = world.reset(configurations, _gen(c))
        assert not world.inside_wall(starts, configurations).any()
        assert ((starts[:, 0] >= s.x0) & (starts[:, 0] <= s.x1)).all()
        assert ((starts[:, 1] >= s.y0) & (starts[:, 1] <= s.y1)).all()
    if name == "multigrid":
        # Config 5's wall covers the start area's eastern strip x in [-0.6, -0.5].
        starts = world.reset(torch.full((4000,), 5), _gen(0))
        assert starts[:, 0].max() < -0.6
        assert starts[:, 0].mean() == pytest.approx(-0.8, abs=0.01)


# ---------------------------------------------------------------- areas
def test_free_areas():
    slope = WORLDS["slope"]
    # 28 wall blocks of 0.2 x 0.2 in FOUR_ROOMS: 4 - 28 * 0.04 = 2.88.
    assert slope.free_area(0) == pytest.approx(2.88, abs=1e-6)
    assert slope.free_area(1) == pytest.approx(2.88, abs=1e-6)
    for c, rows in enumerate(WORLDS["multigrid"].layouts):
        cells = sum(r.count(".") for r in rows)
        assert WORLDS["multigrid"].free_area(c) == pytest.approx(0.04 * cells, abs=1e-6)
    corridor = WORLDS["corridor"]
    assert corridor.arena.area == 36 * slope.arena.area
    assert corridor.free_area() == pytest.approx(144 - 21, abs=0.1)


def test_the_corridor_is_most_of_the_corridor_worlds_free_space():
    world = WORLDS["corridor"]
    mask = world.free_mask(0, resolution=600)
    centres = np.linspace(-6, 6, 601)
    centres = (centres[:-1] + centres[1:]) / 2
    gx, gy = np.meshgrid(centres, centres)
    in_room = (np.abs(gx) <= 2) & (np.abs(gy) <= 2)
    share = (mask & ~in_room).sum() / mask.sum()
    assert share == pytest.approx(107 / 123, abs=0.01)
    assert share > 0.8


# ---------------------------------------------------------------- slopes
# docs/worlds.md: (direction, magnitude mean, upper truncation, north half only).
NORTH_HALF_ONLY = True
REFERENCE_SLOPES = {
    ("slope", 0): ((0.0, -1.0), 0.1, 0.2, NORTH_HALF_ONLY),
    ("slope", 1): ((0.0, 1.0), 0.1, 0.2, NORTH_HALF_ONLY),
    ("multigrid", 0): ((0.0, 1.0), 0.077, 0.154, NORTH_HALF_ONLY),
    **{("multigrid", c): ((0.0, -1.0), 0.0625, 0.125, False) for c in (2, 6)},
    **{("multigrid", c): ((1.0, 0.0), 0.0625, 0.125, False) for c in (1, 5, 9)},
    ("multigrid", 3): ((1.0, -1.0), 0.0625, 0.125, False),  # added to both axes
    **{("multigrid", c): (None, 0.0, 0.0, False) for c in (4, 7, 8)},
}


@pytest.mark.parametrize("name, config", sorted(REFERENCE_SLOPES))
def test_slopes_have_the_reference_direction_region_and_magnitude(name, config):
    direction, mean, high, north_only = REFERENCE_SLOPES[(name, config)]
    world = WORLDS[name]
    n = 40000
    g = _gen(config)
    positions = free_positions(world, config, n, g)
    configurations = torch.full((n,), config)
    noise = torch.rand(n, world.force_noise, generator=g)
    force = world.force(positions, configurations, noise).double()
    if direction is None:
        assert (force == 0).all()
        return
    north = positions[:, 1] >= 0
    acting = north if north_only else torch.ones(n, dtype=torch.bool)
    assert (force[~acting] == 0).all(), "the slope acts outside its region"
    unit = torch.tensor(direction, dtype=torch.float64)
    magnitude = force[acting] @ unit / (unit @ unit)
    assert torch.allclose(force[acting], magnitude[:, None] * unit, atol=1e-6)
    # Truncated normal N(mean, 0.01) on [0, high]: the truncation lies >= 6 sd out, so the
    # mean and sd are those of the normal; 5-sigma bands for the sample statistics.
    m = len(magnitude)
    assert magnitude.mean().item() == pytest.approx(mean, abs=max(5 * 0.01 / m**0.5, 1e-3))
    assert magnitude.std().item() == pytest.approx(0.01, abs=5 * 0.01 / (2 * m) ** 0.5)
    assert magnitude.min() >= 0 and magnitude.max() <= high + 1e-7
    assert len(torch.unique(magnitude)) > m // 2, "a fresh draw per agent and step"


def test_truncated_magnitudes_stay_in_range_at_the_extreme_quantiles():
    world = WORLDS["multigrid"]
    configurations = torch.arange(10).repeat_interleave(3)
    noise = torch.tensor([0.0, 0.5, 1.0 - 2**-24]).repeat(10)
    magnitude = world.slope_magnitude(configurations, noise)
    high = torch.tensor([s.high for s in world.slopes], dtype=torch.float64)[configurations]
    assert (magnitude >= 0).all() and (magnitude <= high).all() and magnitude.isfinite().all()


def zero_mean_rollout(world, config: int, std: float = 0.22, n: int = 100, steps: int = 400):
    """Positions s_1..s_T of n agents whose actions are N(0, std^2) per axis. (n * steps, 2)"""
    g = _gen(config)
    configurations = torch.full((n,), config)
    positions = world.reset(configurations, g)
    visited = []
    for _ in range(steps):
        positions = world.step(positions, torch.randn(n, 2, generator=g) * std, configurations, g)
        visited.append(positions)
    return torch.cat(visited)


def test_the_frequent_slope_carries_agents_away_and_the_rare_one_pins_them():
    """docs/worlds.md: under a zero-mean policy of std 0.22, config 0 (p = 0.8) spends
    ~90% of the steps in the southern half, config 1 (p = 0.2) stays in the northern half."""
    world = WORLDS["slope"]
    assert world.configuration_probs == (0.8, 0.2)
    favourable = zero_mean_rollout(world, 0)
    unfavourable = zero_mean_rollout(world, 1)
    assert (favourable[:, 1] < 0).double().mean() >= 0.80
    assert (unfavourable[:, 1] < 0).double().mean() <= 0.05
    # The rare slope holds agents against the start room's outer (northern) wall: the reference
    # measured about a quarter of the steps within 0.05 of it.
    x, y = unfavourable[:, 0], unfavourable[:, 1]
    assert ((y >= 0.95) & (x <= -0.2)).double().mean() == pytest.approx(0.25, abs=0.06)
    assert (favourable[:, 1] > 0.9).double().mean() < 0.01


def test_multigrid_config_0_pins_agents_against_the_outer_wall():
    adversarial = zero_mean_rollout(WORLDS["multigrid"], 0)
    assert (adversarial[:, 1] < 0).double().mean() <= 0.05


def coinciding_share(positions: torch.Tensor) -> float:
    return 1.0 - len(torch.unique(positions, dim=0)) / len(positions)


WALL, EDGE = 0.0, 0.01  # sd of the noise added to the action (see below)
DRIVES = [  # (world, config, action, noise): straight into a wall, an edge or a corner
    ("slope", 0, (0.2, 0.0), WALL),  # east, into the central wall
    ("slope", 1, (0.2, 0.2), WALL),  # north-east, into the central wall's corner
    ("slope", 1, (0.0, 0.2), EDGE),  # north, with the north slope, into the northern edge
    ("slope", 0, (-0.2, 0.2), EDGE),  # into the arena's north-west corner
    ("multigrid", 5, (0.2, 0.0), WALL),  # east with the east slope, into the big block
    ("multigrid", 3, (0.0, -0.2), WALL),  # south with the south-east slope, onto the terrace
    ("multigrid", 0, (0.0, 0.2), EDGE),  # north with the adversarial slope
    ("corridor", 0, (0.2, 0.0), WALL),  # east, into the room's east wall
    ("corridor", 1, (0.2, 0.2), WALL),  # into the room's north-east corner
]


@pytest.mark.parametrize("edge", EDGE_RULES)
@pytest.mark.parametrize("name, config, action, noise", DRIVES)
@pytest.mark.slow  # heavy: make test runs it, make test-fast does not
def test_agents_driven_into_walls_edges_and_corners_do_not_pile_up(
    name, config, action, noise, edge
):
    """100 agents, 400 steps of one action: fewer than 0.1% of the positions coincide with
    another one, under either edge rule. The push-back off a wall is random; the turn off an
    edge is not, so there the action carries the slightest policy noise (sd 0.01; see the next
    test)."""
    world = (WORLDS if edge == "slide" else MIRRORED)[name]
    g = _gen(1)
    n = 100
    configurations = torch.full((n,), config)
    positions = world.reset(configurations, g)
    visited = []
    for _ in range(400):
        actions = torch.tensor(action) + noise * torch.randn(n, 2, generator=g)
        positions = world.step(positions, actions, configurations, g)
        visited.append(positions)
    assert coinciding_share(torch.cat(visited)) < 0.001


def test_an_exactly_constant_action_against_an_edge_cycles():
    """What the noise above guards against: both edge rules are deterministic, and a move
    exactly normal to the edge comes straight back, so an agent pushing into an edge with
    exactly the same action every step returns to the same two points
    (x -> 2 * edge - x - d -> x). No Gaussian policy acts like this."""
    world = WORLDS["multigrid"]
    positions = torch.tensor([[0.95, 0.7]])  # config 7: open floor by the eastern edge
    path = [positions]
    for _ in range(4):
        path.append(world.step(path[-1], torch.tensor([[0.2, 0.0]]), torch.tensor([7])))
    assert torch.allclose(path[1], path[3]) and torch.allclose(path[2], path[4])


@pytest.mark.parametrize("name", list(WORLDS))
def test_configurations_are_drawn_from_p_m(name):
    world = WORLDS[name]
    n = 100_000
    counts = torch.bincount(
        world.sample_configurations(n, _gen(1)), minlength=world.n_configurations
    )
    p = np.asarray(world.configuration_probs)
    assert p.sum() == pytest.approx(1.0)
    tolerance = 5 * np.sqrt(p * (1 - p) / n)
    assert (np.abs(counts.numpy() / n - p) < tolerance).all(), counts


# ---------------------------------------------------------------- corridor wind
def _corridor_run(
    world: CorridorWorld, config: int, stub: Box, steps: int, push: int, seed: int = 0
) -> torch.Tensor:
    """Agents starting in the room just below ``stub``; they push north at full force for ``push``
    steps (all steps when push < 0), wiggling sideways at random around the stub's axis; after
    that their actions are uniform in [-0.2, 0.2]^2.

    Returns the paths, (steps + 1, N, 2).
    """
    g = _gen(seed)
    n = 128
    x = stub.x0 + 0.01 + (stub.x1 - stub.x0 - 0.02) * torch.rand(n, generator=g)
    y = ROOM.y1 - 0.5 * torch.rand(n, generator=g)
    positions = torch.stack((x, y), 1)
    configurations = torch.full((n,), config)
    path = [positions]
    for t in range(steps):
        wiggle = (torch.rand(n, generator=g) - 0.5) * 0.4
        centre = (stub.x0 + stub.x1) / 2
        actions = torch.stack(
            ((centre - positions[:, 0] + wiggle).clamp(-0.2, 0.2), torch.zeros(n)), 1
        )
        if push < 0 or t < push:
            actions[:, 1] = 0.2
        else:
            actions = (torch.rand(n, 2, generator=g) - 0.5) * 0.4
        positions = world.step(positions, actions, configurations, g)
        path.append(positions)
    return torch.stack(path)


@pytest.mark.parametrize("config, downwind", [(0, WEST_STUB), (1, EAST_STUB)])
@pytest.mark.slow  # heavy: make test runs it, make test-fast does not
def test_pushing_into_the_downwind_entrance_never_gets_past_it(config, downwind):
    world = CorridorWorld(wind=0.4)
    path = _corridor_run(world, config, downwind, steps=300, push=-1)
    # One action (0.2) past the room's edge at most, then the wind (0.4) throws it back.
    assert path[..., 1].max() <= ROOM.y1 + 0.2 + 1e-5
    assert path[..., 1].max() > ROOM.y1, "the agents did reach the entrance"
    # With a weak wind the same agents walk through the same entrance.
    weak = _corridor_run(CorridorWorld(wind=0.1), config, downwind, steps=300, push=-1)
    assert (weak[..., 1].max(dim=0).values > 3.0).all()


@pytest.mark.parametrize(
    "config, upwind, other", [(0, EAST_STUB, WEST_STUB), (1, WEST_STUB, EAST_STUB)]
)
def test_entering_upwind_the_wind_carries_the_agent_around_the_whole_corridor(
    config, upwind, other
):
    world = CorridorWorld(wind=0.4)
    path = _corridor_run(world, config, upwind, steps=300, push=3)  # 3 steps in, then random
    x, y = path[..., 0], path[..., 1]
    for band in (y > 3, y < -3, x > 3, x < -3):  # every side of the ring
        assert band.any(dim=0).all()
    travelled = (path[1:] - path[:-1]).norm(dim=-1).sum(dim=0)
    assert travelled.min() > 30  # the loop is about 36 long
    # Out through one entrance, back towards the room through the other.
    in_other = (x >= other.x0) & (x <= other.x1) & (y >= other.y0) & (y <= other.y1)
    assert in_other.any(dim=0).all()


def test_no_wind_in_the_room_in_either_configuration():
    world = WORLDS["corridor"]
    edge = torch.linspace(ROOM.x0, ROOM.x1, 81)
    gx, gy = torch.meshgrid(edge, edge, indexing="xy")
    room = torch.stack((gx.ravel(), gy.ravel()), 1)  # the closed room, edges included
    for c in (0, 1):
        assert (world.force(room, torch.full((len(room),), c), None) == 0).all()


def test_the_wind_blows_at_full_force_everywhere_in_the_corridor():
    world = CorridorWorld(wind=0.25)
    positions = free_positions(world, 0, 20000, _gen(2))
    x, y = positions[:, 0], positions[:, 1]
    corridor = ~((x.abs() <= 2) & (y.abs() <= 2))
    for c in (0, 1):
        force = world.force(positions[corridor], torch.full((int(corridor.sum()),), c), None)
        assert torch.allclose(force.norm(dim=1), torch.tensor(0.25), atol=1e-6)


def test_the_wind_negates_between_configurations_and_config_0_is_clockwise():
    world = WORLDS["corridor"]
    a = world.arena
    u = torch.rand(20000, 2, generator=_gen(3))
    positions = torch.stack((a.x0 + 12 * u[:, 0], a.y0 + 12 * u[:, 1]), 1)
    n = len(positions)
    clockwise = world.force(positions, torch.zeros(n, dtype=torch.long), None)
    counter = world.force(positions, torch.ones(n, dtype=torch.long), None)
    assert torch.equal(clockwise, -counter)
    x, y = positions[:, 0], positions[:, 1]
    ring = (x.abs() >= 3) | (y.abs() >= 3)
    ring &= ~world.inside_wall(positions, torch.zeros(n, dtype=torch.long))
    ring &= ~((x.abs() <= 1.5) & (y >= 3))  # the junctions above the stubs turn towards them
    # Angular momentum about the centre, x * F_y - y * F_x, < 0 means clockwise.
    spin = x * clockwise[:, 1] - y * clockwise[:, 0]
    assert (spin[ring] < 0).all()
    assert world.configuration_names == ("clockwise", "counterclockwise")
    assert world.configuration_probs == (0.5, 0.5)


# ---------------------------------------------------------------- Hydra config group
@pytest.mark.parametrize("path", sorted(CONF_ENV.glob("*.yaml")), ids=lambda p: p.stem)
def test_env_config_files_name_a_world_and_hold_only_schema_keys(path):
    """A built-in world's file is named after it; a Gymnasium preset (ant_xy, mountaincar)
    names the gym world and an id, and builds (MuJoCo presets where MuJoCo is installed)."""
    from hmepol_cli.config import EnvConfig

    cfg = OmegaConf.load(path)
    assert cfg.name in ENVIRONMENTS
    if cfg.name != "gym":
        assert set(cfg) <= {"name", "wind"} and cfg.name == path.stem
    assert set(cfg) <= set(OmegaConf.structured(EnvConfig))
    if cfg.name == "corridor":
        assert OmegaConf.to_container(cfg)["wind"] == "${wind}"
    if cfg.name == "gym" and cfg.id is None:
        assert path.stem == "gym"  # the bare entry: env=gym env.id=...
        return
    if cfg.name == "gym" and gym.spec(cfg.id).entry_point.startswith("gymnasium.envs.mujoco"):
        pytest.importorskip("mujoco")
    merged = OmegaConf.merge({"wind": 0.15}, {"env": cfg})
    world = make_world(merged.env)
    assert world.name == cfg.name
    if isinstance(world, CorridorWorld):
        assert world.wind == 0.15


def test_env_config_group_covers_every_world():
    stems = {p.stem for p in CONF_ENV.glob("*.yaml")}
    assert set(ENVIRONMENTS) <= stems
    presets = {p.stem for p in CONF_ENV.glob("*.yaml") if p.stem not in ENVIRONMENTS}
    assert {OmegaConf.load(CONF_ENV / f"{p}.yaml").name for p in presets} == {"gym"}


# ---------------------------------------------------------------- Gymnasium API
@pytest.mark.parametrize("env_id", list(ENV_IDS))
def test_gymnasium_check_env_passes(env_id):
    from gymnasium.utils.env_checker import check_env

    env = gym.make(env_id)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the checker reports most problems as warnings
        check_env(env.unwrapped)
    env.close()


def test_single_env_semantics():
    register_envs()  # again: idempotent
    env = gym.make("hmepol/Corridor-v0", horizon=5, wind=0.05)
    world = env.unwrapped.world
    assert isinstance(world, CorridorWorld) and world.wind == 0.05
    obs, info = env.reset(seed=0, options={"config": 1})
    assert info["config"] == 1 and env.observation_space.contains(obs)
    for t in range(5):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert reward == 0.0 and not terminated and truncated == (t == 4) and info["config"] == 1
    with pytest.raises(ValueError, match="config"):
        env.reset(options={"config": 2})
    with pytest.raises(ValueError, match="wind"):
        gym.make("hmepol/Slope-v0", wind=0.1)
    frame = gym.make("hmepol/Slope-v0", render_mode="rgb_array")
    frame.reset(seed=0)
    image = frame.render()
    assert image.shape == (256, 256, 3) and image.dtype == np.uint8 and image.std() > 0


def test_single_env_draws_configurations_from_p_m():
    env = NavigationEnv("slope")
    env.reset(seed=0)
    draws = np.array([env.reset()[1]["config"] for _ in range(2000)])
    assert abs((draws == 0).mean() - 0.8) < 0.045  # 5 sigma


def test_make_vec_steps_a_batch_and_autoresets_on_the_next_step():
    env = gym.make_vec("hmepol/MultiGrid-v0", num_envs=16, horizon=3)
    assert isinstance(env.unwrapped, NavigationVectorEnv)
    assert env.metadata["autoreset_mode"] == gym.vector.AutoresetMode.NEXT_STEP
    obs, info = env.reset(seed=3, options={"config": 4})
    assert obs.shape == (16, 2) and obs.dtype == np.float32 and (info["config"] == 4).all()
    env.action_space.seed(0)
    for t in range(3):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert env.observation_space.contains(obs)
        assert (reward == 0).all() and not terminated.any() and truncated.all() == (t == 2)
        assert (info["config"] == 4).all()
    # The step after truncation ignores the actions and starts new episodes from p_M.
    obs, reward, terminated, truncated, info = env.step(np.full((16, 2), 0.2, np.float32))
    assert not truncated.any() and (reward == 0).all()
    start = MultiGridWorld.start
    assert ((obs >= [start.x0, start.y0]) & (obs <= [start.x1, start.y1])).all()
    assert len(set(info["config"].tolist())) > 1
    # Same seed, same actions: same episode.
    again = gym.make_vec("hmepol/MultiGrid-v0", num_envs=16, horizon=3)
    first = env.reset(seed=11)[0], env.step(np.full((16, 2), 0.1, np.float32))[0]
    second = again.reset(seed=11)[0], again.step(np.full((16, 2), 0.1, np.float32))[0]
    assert all(np.array_equal(a, b) for a, b in zip(first, second, strict=True))
    env.close()


def test_make_vec_passes_the_wind_and_steps_like_the_world():
    env = gym.make_vec("hmepol/Corridor-v0", num_envs=4, wind=0.25)
    world = env.unwrapped.world
    assert isinstance(world, CorridorWorld) and world.wind == 0.25
    obs, _ = env.reset(seed=0, options={"config": [0, 1, 0, 1]})
    # Teleport the batch into the ring's east band: the wind goes south (0) or north (1).
    env.unwrapped._positions = torch.tensor([[4.5, 0.0]] * 4)
    obs, *_ = env.step(np.zeros((4, 2), np.float32))
    assert np.allclose(obs[:, 1], [-0.25, 0.25, -0.25, 0.25], atol=1e-6)
    sync = gym.make_vec("hmepol/Slope-v0", num_envs=2, vectorization_mode="sync")
    assert sync.reset(seed=0)[0].shape == (2, 2)


# ---------------------------------------------------------------- pictures
def test_force_arrows_show_the_force_and_never_sit_on_a_wall():
    for name, c in WORLD_CONFIGS:
        world = WORLDS[name]
        points, directions, length = force_arrows(world, c)
        has_force = not (isinstance(world, GridWorld) and world.slopes[c].mean == 0)
        assert (len(points) > 0) == has_force, (name, c)
        for offset in (-length / 2, 0.0, length / 2):
            ends = torch.tensor(points + offset * directions, dtype=torch.float32)
            assert not world.inside_wall(ends, torch.full((len(ends),), c)).any()


def test_show_world_saves_one_panel_per_configuration(tmp_path):
    import matplotlib.image as mpimg
    from matplotlib.figure import Figure

    ax = Figure().subplots()
    draw_world(ax, WORLDS["multigrid"], 7)
    assert len(ax.patches) == len(WORLDS["multigrid"].walls[7]) + 2  # walls, start, arena
    path = show_world(WORLDS["corridor"], tmp_path / "corridor.png")
    image = mpimg.imread(path)
    assert image.shape[1] > 1.4 * image.shape[0]  # two panels side by side


# ---------------------------------------------------------------- estimator on the worlds
@pytest.mark.parametrize("name, batch_size", [("slope", 5), ("multigrid", 5), ("corridor", 1)])
@pytest.mark.slow  # heavy: make test runs it, make test-fast does not
def test_no_ball_volume_hits_the_floor_on_the_initial_policy(name, batch_size):
    """The thesis' mini-batches (B x T particles, k = 30) of the default initial policy: no
    particle's ball volume is at the estimator's floor (coincident particles would be)."""
    from hmepol_cli import estimators
    from hmepol_cli.config import PolicyConfig
    from hmepol_cli.policies import make_policy
    from hmepol_cli.rollout import collect_single

    world = WORLDS[name]
    torch.manual_seed(0)
    policy = make_policy(PolicyConfig(), world.state_dim, world.action_dim)
    configurations = torch.arange(world.n_configurations).repeat_interleave(batch_size).repeat(2)
    rollout = collect_single(world, policy, configurations, 400, _gen(0))
    particles = estimators.particles_by_batch(rollout.particles, batch_size)
    neighbours = estimators.nearest_neighbours(particles, 30)
    assert float(estimators.floor_share(neighbours, 1e-10)) == 0.0
    # The column would see the floor: the same particles with every agent pinned to one point.
    pinned = estimators.nearest_neighbours(torch.zeros_like(particles), 30)
    assert float(estimators.floor_share(pinned, 1e-10)) == 1.0


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    env=st.sampled_from(["corridor", "slope", "multigrid"]),
    dtype=st.sampled_from([torch.float32, torch.float64]),
    seed=st.integers(0, 2**31 - 1),
    scale=st.sampled_from([0.0, 1e-3, 0.05, 0.3, 2.0, 20.0]),
    still=st.floats(0.0, 1.0),
)
def test_the_slide_that_skips_its_still_rounds_is_the_full_slide_bit_for_bit(
    env, dtype, seed, scale, still
):
    """Once no agent moves, the slide finishes its rounds in closed form on a CPU: the ends
    (their bits, zeros' signs included) and the blocked flags are those of all the rounds."""
    world = make_world(OmegaConf.create({"name": env, "wind": 0.25 if env == "corridor" else None}))
    world = world.to("cpu", dtype)
    g = torch.Generator().manual_seed(seed)
    n = 64
    lo, hi = world._arena_lo, world._arena_hi
    p = lo + (hi - lo) * torch.rand(n, 2, generator=g, dtype=dtype)
    side = torch.randint(0, 6, (n,), generator=g)
    p[side == 0, 0], p[side == 1, 1] = lo[0], hi[1]  # on an edge
    p[side == 2] = -0.0
    d = torch.randn(n, 2, generator=g, dtype=dtype) * scale
    d[torch.rand(n, generator=g) < still] = -0.0  # standing agents, -0.0 among them
    configurations = torch.randint(0, world.n_configurations, (n,), generator=g)
    walls = (
        world._obstacles.index_select(0, configurations)
        if world._shared_obstacles is None
        else world._shared_obstacles
    )
    fast = world._slide(p, d, walls, stop_when_still=True)
    full = world._slide(p, d, walls, stop_when_still=False)
    bits = torch.int64 if dtype == torch.float64 else torch.int32
    assert torch.equal(fast[0].view(bits), full[0].view(bits))
    assert torch.equal(fast[1], full[1])
