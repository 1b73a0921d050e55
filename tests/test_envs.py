"""The worlds (SPEC 2): solid walls, reachable layouts, forces as specified, Gymnasium API."""

from __future__ import annotations

import math
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
from hmepol_cli.envs.base import Box, NavigationWorld
from hmepol_cli.envs.corridor import EAST_STUB, ROOM, WEST_STUB, CorridorWorld
from hmepol_cli.envs.grid import FOUR_ROOMS, GridWorld
from hmepol_cli.envs.gym_api import ENV_IDS, NavigationEnv, NavigationVectorEnv, register_envs
from hmepol_cli.envs.multigrid import CONFIGS, MultiGridWorld
from hmepol_cli.envs.render import draw_world, force_arrows, show_world
from hmepol_cli.envs.slope import SlopeWorld

CONF_ENV = Path(__file__).resolve().parents[1] / "conf" / "env"
WORLDS: dict[str, NavigationWorld] = {
    "slope": SlopeWorld(),
    "corridor": CorridorWorld(wind=0.4),
    "multigrid": MultiGridWorld(),
}
WORLD_CONFIGS = [(name, c) for name, w in WORLDS.items() for c in range(w.n_configs)]


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


def on_wall_faces(world: NavigationWorld, config: int, n: int, g: torch.Generator) -> torch.Tensor:
    """Valid positions lying exactly on wall faces and corners (the hardest starts). (<=n, 2)"""
    walls = torch.tensor([(b.x0, b.y0, b.x1, b.y1) for b in world.walls[config]])
    pick = walls[torch.randint(len(walls), (n,), generator=g)]
    u = torch.rand(n, generator=g)
    side = torch.randint(4, (n,), generator=g)
    x = torch.where(
        side == 0,
        pick[:, 0],
        torch.where(side == 1, pick[:, 2], pick[:, 0] + u * (pick[:, 2] - pick[:, 0])),
    )
    y = torch.where(
        side == 2,
        pick[:, 1],
        torch.where(side == 3, pick[:, 3], pick[:, 1] + u * (pick[:, 3] - pick[:, 1])),
    )
    p = torch.stack((x, y), 1)
    configs = torch.full((n,), config)
    # A point on the seam of two touching walls is inside the wall, not on its face: keep only
    # points with free space just outside the face they were put on.
    normal = torch.tensor([[-1.0, 0.0], [1.0, 0.0], [0.0, -1.0], [0.0, 1.0]])[side]
    outside = p + 1e-5 * normal
    beside = ~world.inside_wall(outside, configs) & world.inside_arena(outside)
    ok = ~world.inside_wall(p, configs) & world.inside_arena(p)
    return p[ok & beside]


def segment_crosses_wall(
    world: NavigationWorld, config: int, start: np.ndarray, end: np.ndarray
) -> np.ndarray:
    """True where the axis-separated move start -> (end_x, start_y) -> end enters a wall's interior.

    start, end (N, 2) -> (N,). The world moves along x first, then along y (base.py).
    """
    hit = np.zeros(len(start), dtype=bool)
    for b in world.walls[config]:
        lo_x, hi_x = np.minimum(start[:, 0], end[:, 0]), np.maximum(start[:, 0], end[:, 0])
        hit |= (start[:, 1] > b.y0) & (start[:, 1] < b.y1) & (hi_x > b.x0) & (lo_x < b.x1)
        lo_y, hi_y = np.minimum(start[:, 1], end[:, 1]), np.maximum(start[:, 1], end[:, 1])
        hit |= (end[:, 0] > b.x0) & (end[:, 0] < b.x1) & (hi_y > b.y0) & (lo_y < b.y1)
    return hit


# ---------------------------------------------------------------- solid walls, any action size
@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    which=st.sampled_from(WORLD_CONFIGS),
    seed=st.integers(0, 2**31 - 1),
    log_scale=st.floats(-3.0, 3.0),  # actions from 0.001 to 1000 times the arena's unit
    steps=st.integers(1, 12),
)
def test_walls_are_never_crossed_and_the_arena_never_left(which, seed, log_scale, steps):
    name, config = which
    world = WORLDS[name]
    g = _gen(seed)
    span = world.arena.x1 - world.arena.x0
    positions = torch.cat(
        [free_positions(world, config, 96, g), on_wall_faces(world, config, 96, g)]
    )
    configs = torch.full((len(positions),), config)
    for _ in range(steps):
        actions = torch.randn(len(positions), 2, generator=g) * span * 10.0**log_scale / 10
        # A quarter of the agents move along one axis only: slides along faces and seams.
        actions[::4, 0] = 0.0
        actions[1::4, 1] = 0.0
        new = world.step(positions, actions, configs, g)
        assert not world.inside_wall(new, configs).any()
        assert world.inside_arena(new).all()
        crossed = segment_crosses_wall(world, config, positions.numpy(), new.numpy())
        assert not crossed.any(), positions[torch.from_numpy(crossed)][:3]
        positions = new


def test_a_step_displaces_by_the_clipped_action_plus_the_force_in_open_space():
    world = WORLDS["multigrid"]
    positions = torch.tensor([[0.5, 0.8]])  # config 9 ("open"): no wall nearby, no slope
    new = world.step(positions, torch.tensor([[5.0, -0.05]]), torch.tensor([9]))
    assert torch.allclose(new, torch.tensor([[0.7, 0.75]]))


# ---------------------------------------------------------------- layouts
def grid_cells(rows: list[str], box: Box) -> set[tuple[int, int]]:
    """(row, col) of the 10 x 10 cells of [-1, 1]^2 that overlap the box's interior."""
    size = 2.0 / len(rows)
    return {
        (r, c)
        for r in range(len(rows))
        for c in range(len(rows[0]))
        if -1 + c * size < box.x1
        and -1 + (c + 1) * size > box.x0
        and 1 - (r + 1) * size < box.y1
        and 1 - r * size > box.y0
    }


@pytest.mark.parametrize("name, rows", [(n, r) for n, r, _ in CONFIGS])
def test_every_free_cell_of_every_multigrid_layout_is_reachable_from_the_start(name, rows):
    assert len(rows) == 10 and all(len(r) == 10 and set(r) <= set(".#") for r in rows), name
    start = grid_cells(rows, MultiGridWorld.start)
    assert all(rows[r][c] == "." for r, c in start), f"{name}: the start area holds a wall"
    seen, todo = set(start), deque(start)
    while todo:
        r, c = todo.popleft()
        for rr, cc in ((r + 1, c), (r - 1, c), (r, c + 1), (r, c - 1)):
            if 0 <= rr < 10 and 0 <= cc < 10 and rows[rr][cc] == "." and (rr, cc) not in seen:
                seen.add((rr, cc))
                todo.append((rr, cc))
    free = {(r, c) for r in range(10) for c in range(10) if rows[r][c] == "."}
    assert free - seen == set(), f"{name}: cells {sorted(free - seen)} cannot be reached"


def test_multigrid_configurations_are_as_the_thesis_lists():
    world = WORLDS["multigrid"]
    assert world.n_configs == 10 and len(set(world.config_names)) == 10
    assert world.layouts[0] == FOUR_ROOMS
    assert len({tuple(rows) for rows in world.layouts}) == 10, "layouts must differ"
    assert world.slopes[0].direction == (0.0, 1.0) and world.slopes[0].mean == 0.077
    assert world.slopes[0].region == WORLDS["slope"].slopes[1].region
    directions = [tuple(np.round(s.direction, 6)) for s in world.slopes[1:] if s.mean > 0]
    d = round(1 / math.sqrt(2), 6)
    assert sorted(directions) == sorted([(0.0, -1.0)] * 2 + [(1.0, 0.0)] * 3 + [(d, -d)])
    assert sum(s.mean == 0 for s in world.slopes) == 3
    assert all(s.mean == 0.1 and s.region is None for s in world.slopes[1:] if s.mean > 0)
    assert world.config_probs == pytest.approx([0.1] * 10)


@pytest.mark.parametrize("name", list(WORLDS))
def test_the_start_box_is_free_in_every_configuration(name):
    world = WORLDS[name]
    s = world.start
    for c in range(world.n_configs):
        for b in world.walls[c]:
            overlap = min(s.x1, b.x1) > max(s.x0, b.x0) and min(s.y1, b.y1) > max(s.y0, b.y0)
            assert not overlap, (world.config_names[c], b)
    starts = world.reset(torch.arange(world.n_configs).repeat(200), _gen(0))
    assert ((starts[:, 0] >= s.x0) & (starts[:, 0] <= s.x1)).all()
    assert ((starts[:, 1] >= s.y0) & (starts[:, 1] <= s.y1)).all()


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
@pytest.mark.parametrize("name, config", [wc for wc in WORLD_CONFIGS if wc[0] != "corridor"])
def test_slope_force_distribution_and_region(name, config):
    world: GridWorld = WORLDS[name]
    slope = world.slopes[config]
    g = _gen(config)
    n = 20000
    positions = free_positions(world, config, n, g)
    force = world.force(positions, torch.full((n,), config), g).double()
    region = slope.region or world.arena
    x, y = positions[:, 0], positions[:, 1]
    inside = (x >= region.x0) & (x <= region.x1) & (y >= region.y0) & (y <= region.y1)
    assert (force[~inside] == 0).all(), "the slope acts outside its region"
    if slope.mean == 0:
        assert (force == 0).all()
        return
    assert inside.sum() > 5000
    direction = torch.tensor(slope.direction, dtype=torch.float64)
    magnitude = force[inside] @ direction
    # The force is parallel to the slope's direction ...
    assert torch.allclose(force[inside], magnitude[:, None] * direction, atol=1e-6)
    # ... its magnitude ~ N(mean, 0.01) truncated to [0, 0.2].
    expected = 0.077 if (name, config) == ("multigrid", 0) else 0.1
    assert magnitude.mean().item() == pytest.approx(expected, abs=5e-4)
    assert magnitude.std().item() == pytest.approx(0.01, abs=5e-4)
    assert magnitude.min() >= 0 and magnitude.max() <= 0.2
    assert len(torch.unique(magnitude)) > n // 4, "a fresh draw per agent and step"


def test_slope_world_slopes_south_and_north_in_the_bottom_half():
    world = WORLDS["slope"]
    assert world.config_names == ("south", "north") and world.config_probs == (0.8, 0.2)
    assert world.slopes[0].direction == (0.0, -1.0) and world.slopes[1].direction == (0.0, 1.0)
    below, above = torch.tensor([[0.7, -0.3]]), torch.tensor([[0.7, 0.6]])
    for c, sign in ((0, -1), (1, 1)):
        assert sign * world.force(below, torch.tensor([c]), None)[0, 1] > 0.05
        assert (world.force(above, torch.tensor([c]), None) == 0).all()


@pytest.mark.parametrize("name", list(WORLDS))
def test_configurations_are_drawn_from_p_m(name):
    world = WORLDS[name]
    n = 100_000
    counts = torch.bincount(world.sample_configs(n, _gen(1)), minlength=world.n_configs)
    p = np.asarray(world.config_probs)
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
    configs = torch.full((n,), config)
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
        positions = world.step(positions, actions, configs, g)
        path.append(positions)
    return torch.stack(path)


@pytest.mark.parametrize("config, downwind", [(0, WEST_STUB), (1, EAST_STUB)])
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
    path = _corridor_run(world, config, upwind, steps=150, push=3)  # 3 steps in, then random
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
    # Angular momentum about the centre, x * F_y - y * F_x, < 0 means clockwise.
    spin = x * clockwise[:, 1] - y * clockwise[:, 0]
    assert (spin[ring] < 0).all()
    assert world.config_names == ("clockwise", "counterclockwise")
    assert world.config_probs == (0.5, 0.5)


# ---------------------------------------------------------------- Hydra config group
@pytest.mark.parametrize("path", sorted(CONF_ENV.glob("*.yaml")), ids=lambda p: p.stem)
def test_env_config_files_name_a_world_and_hold_only_schema_keys(path):
    cfg = OmegaConf.load(path)
    assert set(cfg) <= {"name", "wind"}
    assert cfg.name == path.stem and cfg.name in ENVIRONMENTS
    if cfg.name == "corridor":
        assert OmegaConf.to_container(cfg)["wind"] == "${wind}"
    merged = OmegaConf.merge({"wind": 0.15}, {"env": cfg})
    world = make_world(merged.env)
    assert world.name == path.stem
    if isinstance(world, CorridorWorld):
        assert world.wind == 0.15


def test_env_config_group_covers_every_world():
    assert {p.stem for p in CONF_ENV.glob("*.yaml")} == set(ENVIRONMENTS)


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
