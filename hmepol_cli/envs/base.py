"""Batched continuous 2-D navigation worlds: the common physics of slope, corridor and multigrid.

A world is a *class* of configurations M_1..M_I (thesis 2.1.1) that share the arena, the state
space (position (x, y)) and the action space (a displacement clipped to [-0.2, 0.2] per axis).
Configurations differ by their walls and by an external force (a slope, a wind) that is added to
the clipped action. Every method works on a whole batch of agents at once, as tensors, on the
device the world was moved to.

Walls and edges follow the public reference implementation of the thesis' worlds ([22];
docs/worlds.md), which keeps agents from piling up on identical points (kNN distances of 0):

- **arena edge** (``edge="slide"``, the reference): the part of a move beyond an edge is turned
  by a quarter turn. From the point where the move crosses the edge, the remainder's outward
  part n and its part along the edge t become a slide of |n| along the edge, in the direction
  of t, and a step of |t| back inside (t = 0: straight back by |n|). A remainder that leaves
  the arena again (near a corner) is turned again from its new crossing point; a point exactly
  on the edge counts as beyond it. ``edge="mirror"`` (this project's rule before it followed
  the reference) mirrors the part beyond the edge back inside instead;
- **wall**: a move that would end inside a wall instead moves the agent *back* from where it
  was, against the sign of the move on each axis, by an independent uniform amount in
  [0, max_action / 2] per axis (that move follows the same edge rule); if that point is in a
  wall too, the agent stays where it was.

The reference checks only a move's end point; here a move whose path (each straight piece of
it, after the edge's turns or mirrors) touches a wall counts as hitting it, so no move tunnels
through a wall, whatever its size. Walls are closed rectangles: an agent never ends on or inside
one, and never outside the arena (a move whose turns off the edges do not end within
``EDGE_ROUNDS`` rounds, which takes a move several times the arena's size, counts as blocked).

Randomness: a step consumes ``noise_size`` uniform numbers per agent (the push-back's two, then
the force's), passed in as ``noise`` or drawn from ``generator``; the rollout draws a whole
epoch's worth at once, so a run's random stream does not depend on how it is batched.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from hmepol_cli.envs.world import Transition, action_noise

MAX_ACTION = 0.2  # per-axis action bound of every world (thesis 5.1)
PUSH_BACK_NOISE = 2  # uniforms per agent and step for the push-back (one per axis)
START_CANDIDATES = 16  # start positions drawn per agent; the first free one is taken
FAR_AWAY = 1e9  # where the padding rectangles of the wall table lie
EDGE_RULES = ("slide", "mirror")  # the reference's quarter turn | a mirror (before)
EDGE_ROUNDS = 4  # turns off the edges one move may take (a corner takes two)


@dataclass(frozen=True)
class Box:
    """Axis-aligned rectangle [x0, x1] x [y0, y1]."""

    x0: float
    y0: float
    x1: float
    y1: float

    @property
    def area(self) -> float:
        return (self.x1 - self.x0) * (self.y1 - self.y0)

    def contains(self, x: float, y: float) -> bool:
        return self.x0 <= x <= self.x1 and self.y0 <= y <= self.y1


class NavigationWorld:
    """A class of 2-D navigation configurations, stepped in batches.

    Subclasses set ``name``, ``arena``, ``start``, ``configuration_names``,
    ``configuration_probs`` and
    ``walls`` (one tuple of :class:`Box` per configuration), and, for a force, ``force_noise``
    (uniforms it needs per agent and step) and :meth:`force`.
    """

    name: str = "world"
    maps = True  # walls on an arena: pictures draw it, fine-tuning draws goals in free space
    episodes_end = False  # every trajectory runs T steps
    capturable = True  # a step is tensor operations only
    projection = (0, 1)  # the state indices pictures draw: the position
    state_dim: int = 2
    action_dim: int = 2
    max_action: float = MAX_ACTION
    force_noise: int = 0
    arena: Box
    start: Box
    configuration_names: tuple[str, ...]
    configuration_probs: tuple[float, ...]
    walls: tuple[tuple[Box, ...], ...]

    def __init__(self, edge: str = "slide") -> None:
        if edge not in EDGE_RULES:
            raise ValueError(f"edge={edge!r}; choose one of {', '.join(EDGE_RULES)}")
        self.edge = edge
        self.device = torch.device("cpu")
        self.dtype = torch.float32
        self._build_tensors()

    # ------------------------------------------------------------------ set-up
    @property
    def n_configurations(self) -> int:
        return len(self.configuration_probs)

    @property
    def noise_size(self) -> int:
        """Uniform numbers one agent consumes per step."""
        return PUSH_BACK_NOISE + self.force_noise

    @property
    def push_back(self) -> float:
        """Largest push-back per axis after hitting a wall (reference: max_action / 2)."""
        return self.max_action / 2

    @classmethod
    def from_config(cls, env_cfg) -> NavigationWorld:
        """The world of an ``env`` config group entry (name, edge, and wind for the corridor)."""
        return cls(edge=edge_rule(env_cfg))

    @classmethod
    def check_config(cls, env_cfg) -> None:
        """Refuse a bad ``env`` entry before anything is written (the built-in worlds' keys are
        checked by :func:`hmepol_cli.config.validate`)."""

    def close(self) -> None:
        """Release what the world holds outside tensors (nothing, for these worlds)."""

    def facts(self, member: int | None = None) -> dict[str, object]:
        """What run.json records about the world (of a population's ``member``) beyond its
        configurations: the edge rule, and the map pictures draw (:meth:`world_map`)."""
        return {"edge": self.edge, "world_map": self.world_map()}

    def world_map(self) -> dict[str, list]:
        """The arena, the start area and each configuration's walls as [x0, y0, x1, y1] lists:
        what a picture draws (:class:`hmepol_cli.plots.WorldMap`), so the report draws the world
        from run.json without building it."""

        def corners(box: Box) -> list[float]:
            return [float(box.x0), float(box.y0), float(box.x1), float(box.y1)]

        return {
            "arena": corners(self.arena),
            "start": corners(self.start),
            "walls": [[corners(b) for b in walls] for walls in self.walls],
        }

    # ------------------------------------------------------------------ states
    def entropy_features(self, states: torch.Tensor) -> torch.Tensor:
        """The part of states the entropy is computed on: the whole position. (..., 2)"""
        return states

    def plane(self, states: torch.Tensor) -> torch.Tensor:
        """The 2-D coordinates heatmaps draw: the position itself. (..., 2)"""
        return states

    def action_bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Where actions are clipped, per dimension: (low (a,), high (a,))."""
        high = torch.full((self.action_dim,), self.max_action, device=self.device, dtype=self.dtype)
        return -high, high

    def state_bounds(self) -> tuple[list[float], list[float]]:
        """Lower and upper bound of each state index: the arena."""
        a = self.arena
        return [a.x0, a.y0], [a.x1, a.y1]

    # ------------------------------------------------------------------ how it looks
    def describe(self, config: int) -> str:
        """One line on the force of a configuration (no force: empty)."""
        return ""

    def force_region(self, config: int) -> Box | None:
        """The part of the arena the force acts on, shaded in pictures (None: none shaded)."""
        return None

    def arrow_candidates(self, config: int) -> tuple[list[tuple[np.ndarray, np.ndarray]], float]:
        """Lattices of arrows showing the force: [(centres (M, 2), directions (M, 2))] and the
        arrows' length; the picture keeps those that touch no wall."""
        return [], 0.0

    def to(self, device: torch.device | str, dtype: torch.dtype = torch.float32) -> NavigationWorld:
        self.device, self.dtype = torch.device(device), dtype
        self._build_tensors()
        return self

    def _build_tensors(self) -> None:
        kw = dict(device=self.device, dtype=self.dtype)
        most = max(1, max(len(w) for w in self.walls))
        # Padding rectangles lie far outside the arena, beyond the reach of any move.
        table = np.full((self.n_configurations, most, 4), FAR_AWAY)
        for c, boxes in enumerate(self.walls):
            for i, b in enumerate(boxes):
                table[c, i] = (b.x0, b.y0, b.x1, b.y1)
        self._walls = torch.tensor(table, **kw)  # (C, W, 4)
        if self.edge == "mirror":  # a mirrored path is a straight line among mirrored walls
            table = _with_mirror_images(table, self.arena)  # (C, 9W, 4)
        self._obstacles = torch.tensor(table, **kw)
        # Configurations that share their walls (slope, corridor) need no per-agent gather.
        shared = len(set(self.walls)) == 1
        self._shared_obstacles = self._obstacles[:1] if shared else None
        self._probs = torch.tensor(
            self.configuration_probs, device=self.device, dtype=torch.float64
        )
        self._arena_lo = torch.tensor([self.arena.x0, self.arena.y0], **kw)
        self._arena_hi = torch.tensor([self.arena.x1, self.arena.y1], **kw)
        self._start_lo = torch.tensor([self.start.x0, self.start.y0], **kw)
        self._start_hi = torch.tensor([self.start.x1, self.start.y1], **kw)
        self._start_fallback = torch.tensor(
            [self._free_start_point(c) for c in range(self.n_configurations)], **kw
        )
        values = getattr(self, "_member_strength_values", None)
        self._member_strength = None if values is None else torch.tensor(values, **kw)

    def _free_start_point(self, config: int) -> tuple[float, float]:
        """A free point of the start area, for the (astronomically rare) agent whose candidates
        all fell in a wall."""
        s = self.start
        for gx in np.linspace(0.05, 0.95, 19):
            for gy in np.linspace(0.05, 0.95, 19):
                x, y = s.x0 + gx * (s.x1 - s.x0), s.y0 + gy * (s.y1 - s.y0)
                if not any(b.contains(x, y) for b in self.walls[config]):
                    return (x, y)
        raise ValueError(f"{self.name} config {config}: the start area lies inside walls")

    # ------------------------------------------------------------------ dynamics
    def sample_configurations(
        self, n: int, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """Draw n configuration indices from p_M. (n,) long."""
        return torch.multinomial(self._probs, n, replacement=True, generator=generator)

    def reset(
        self, configurations: torch.Tensor, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """Initial positions, uniform over the free part of the start area.

        configurations (N,) -> (N, 2)

        A fixed number of candidates per agent (the first free one is taken), so the random
        stream advances by the same amount whatever the walls.
        """
        n = configurations.shape[0]
        u = torch.rand(
            n, START_CANDIDATES, 2, device=self.device, dtype=self.dtype, generator=generator
        )
        candidates = self._start_lo + u * (self._start_hi - self._start_lo)  # (N, K, 2)
        free = ~self.inside_wall(
            candidates.reshape(-1, 2), configurations.repeat_interleave(START_CANDIDATES)
        ).view(n, START_CANDIDATES)
        first = free.to(torch.uint8).argmax(dim=1)
        chosen = candidates[torch.arange(n, device=self.device), first]
        return torch.where(
            free.any(dim=1, keepdim=True), chosen, self._start_fallback[configurations]
        )

    def begin(
        self,
        configurations: torch.Tensor,
        horizon: int,
        generators: Sequence[torch.Generator],
        members: torch.Tensor | None = None,
    ) -> tuple[NavigationEpisodes, torch.Tensor]:
        """S' x N episodes in ``configurations`` (S', N) for the population's ``members`` (S',)
        (None: all). Member i draws from generators[i], in this order: its start positions,
        its action noise (N, T, a), its world noise (N, T, k) (the push-back's and the force's
        uniforms of every step)."""
        n = configurations.shape[1]
        starts, actions, noise = [], [], []
        for i, generator in enumerate(generators):
            starts.append(self.reset(configurations[i], generator))
            actions.append(action_noise(n, horizon, self, generator))
            noise.append(
                torch.rand(n, horizon, self.noise_size, device=self.device, dtype=self.dtype,
                           generator=generator)
            )  # fmt: skip
        strength = None
        if self._member_strength is not None:  # members with forces of their own (winds)
            rows = self._member_strength if members is None else self._member_strength[members]
            strength = rows.repeat_interleave(n)
        episodes = NavigationEpisodes(
            self, torch.stack(starts), configurations.flatten(), torch.stack(noise).flatten(0, 1),
            strength,
        )  # fmt: skip
        return episodes, torch.stack(actions)

    def for_members(self, env_cfgs: Sequence) -> NavigationWorld:
        """The world of a population whose members' ``env`` entries are ``env_cfgs``: they must
        be the same world; a world with a force of its own per member (the corridor's wind)
        overrides :meth:`member_strengths`."""
        strengths = self.member_strengths(env_cfgs)
        if strengths is not None and len(set(strengths)) > 1:
            self._member_strength_values = tuple(float(v) for v in strengths)
        else:
            self._member_strength_values = None
        self._build_tensors()
        return self

    def member_strengths(self, env_cfgs: Sequence) -> list[float] | None:
        """Each member's force strength (None: the world's own, for every member)."""
        return None

    def force(
        self,
        positions: torch.Tensor,
        configurations: torch.Tensor,
        noise: torch.Tensor,
        strength: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """External displacement (slope, wind) at each position, added to the clipped action.

        positions (N, 2), configurations (N,), noise (N, force_noise) uniform in [0, 1),
        strength (N,) each agent's own strength of the force (None: the world's) -> (N, 2).
        """
        return torch.zeros_like(positions)

    def draw_noise(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """The uniforms one step of n agents consumes. (n, noise_size)"""
        return torch.rand(
            n, self.noise_size, device=self.device, dtype=self.dtype, generator=generator
        )

    def step(
        self,
        positions: torch.Tensor,
        actions: torch.Tensor,
        configurations: torch.Tensor,
        generator: torch.Generator | None = None,
        *,
        noise: torch.Tensor | None = None,
        strength: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Next positions: clipped action plus the configuration's force, off edges and walls.

        positions (N, 2), actions (N, 2), configurations (N,), noise (N, noise_size) -> (N, 2).
        """
        if noise is None:
            noise = self.draw_noise(positions.shape[0], generator)
        displacement = actions.clamp(-self.max_action, self.max_action)
        force = self.force(positions, configurations, noise[:, PUSH_BACK_NOISE:], strength)
        displacement = displacement + force
        return self.move(positions, displacement, configurations, noise[:, :PUSH_BACK_NOISE])

    def move(
        self,
        positions: torch.Tensor,
        displacement: torch.Tensor,
        configurations: torch.Tensor,
        push_noise: torch.Tensor,
    ) -> torch.Tensor:
        """Apply a displacement with the arena's edge rule and the reference's wall push-back.

        positions (N, 2), displacement (N, 2), configurations (N,), push_noise (N, 2) in [0, 1).
        """
        if self._shared_obstacles is None:
            obstacles = self._obstacles.index_select(0, configurations)  # (N, W, 4)
        else:
            obstacles = self._shared_obstacles  # (1, W, 4)
        moved, hit = self._travel(positions, displacement, obstacles)
        back = -torch.sign(displacement) * push_noise * self.push_back
        pushed, stuck = self._travel(positions, back, obstacles)
        fallback = torch.where(stuck[:, None], positions, pushed)
        return torch.where(hit[:, None], fallback, moved)

    def _travel(
        self, positions: torch.Tensor, displacement: torch.Tensor, obstacles: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Where a move ends under the edge rule, and whether its path touches a wall.

        -> (end (N, 2), blocked (N,) bool)"""
        if self.edge == "mirror":
            return self._reflect(positions + displacement), self._mirror_blocked(
                positions, displacement, obstacles
            )
        return self._slide(positions, displacement, obstacles)

    def _slide(
        self,
        positions: torch.Tensor,
        displacement: torch.Tensor,
        walls: torch.Tensor,
        stop_when_still: bool = True,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The reference's edge rule: the part of a move beyond an edge, turned a quarter turn
        (a slide along the edge, then back inside), round after round; each straight piece of
        the path is tested against the walls. -> (end (N, 2), blocked (N,) bool)

        ``stop_when_still`` (not on a GPU, whose rollouts are captured graphs without
        data-dependent branches): once no agent moves at the start of a round, that round and
        the later ones are done in closed form (a standing point tested against the walls; the
        position plus a zero piece); the result is the same, bit for bit, zeros' signs included
        (tested against all ``EDGE_ROUNDS`` rounds)."""
        lo, hi = self._arena_lo, self._arena_hi
        p, d = positions, displacement
        blocked = torch.zeros(p.shape[0], dtype=torch.bool, device=p.device)
        inf = torch.full_like(p, float("inf"))
        stop_when_still = stop_when_still and p.device.type != "cuda"
        for round_ in range(EDGE_ROUNDS):
            if stop_when_still and not bool(d.any()):
                # This round in closed form (no crossing: piece = d * 1 = d), then the later
                # ones: each adds a piece of +0.0 (once is enough) and tests the same point.
                blocked |= _segment_touches_box(p, d, walls)
                p = p + d
                if round_ + 1 < EDGE_ROUNDS:
                    p = p + torch.zeros_like(p)
                d = torch.zeros_like(d)
                break
            # Fraction of d at which the path reaches each axis' edge ahead of it; a point on
            # the edge counts as beyond it (fraction 0).
            safe = torch.where(d == 0, torch.ones_like(d), d)
            ahead = torch.where(d > 0, hi, lo)
            reach = torch.where(d != 0, ((ahead - p) / safe).clamp_min(0.0), inf)  # (N, 2)
            fraction, axis = reach.min(dim=1)
            crosses = fraction <= 1
            piece = d * torch.where(crosses, fraction, torch.ones_like(fraction))[:, None]
            blocked |= _segment_touches_box(p, piece, walls)
            on_axis = F.one_hot(axis, 2).bool() & crosses[:, None]
            p = torch.where(on_axis, ahead, p + piece)  # the crossing point sits on the edge
            rest = d - piece
            outward = rest.gather(1, axis[:, None])[:, 0].abs()  # |n|
            along = rest.gather(1, (1 - axis)[:, None])[:, 0]  # t
            inward = -torch.sign(d.gather(1, axis[:, None])[:, 0])
            back = torch.where(along == 0, outward, along.abs()) * inward  # |t| (t = 0: |n|)
            slide = torch.sign(along) * outward  # |n| in the direction of t
            turned = torch.where(on_axis, back[:, None], slide[:, None])
            d = torch.where(crosses[:, None], turned, torch.zeros_like(d))
        blocked |= (d != 0).any(dim=1)  # still turning after EDGE_ROUNDS rounds: a huge move
        return torch.minimum(torch.maximum(p, lo), hi), blocked

    def _reflect(self, positions: torch.Tensor) -> torch.Tensor:
        """Mirror the part of a move beyond an arena edge back inside. (N, 2) -> (N, 2)"""
        lo, hi = self._arena_lo, self._arena_hi
        span = hi - lo
        folded = torch.remainder(positions - lo, 2 * span)
        folded = lo + torch.where(folded > span, 2 * span - folded, folded)
        inside = (positions >= lo) & (positions <= hi)
        return torch.where(inside, positions, folded)

    def _mirror_blocked(
        self, positions: torch.Tensor, displacement: torch.Tensor, obstacles: torch.Tensor
    ) -> torch.Tensor:
        """True where the mirrored move touches a wall. (N,)

        The path reflected off the edges is the straight segment ``positions + t * displacement``
        (t in [0, 1]) among the walls' mirror images, so one slab test covers it. A move longer
        than the arena on an axis would be reflected more than once: it counts as blocked.
        """
        too_long = (displacement.abs() > self._arena_hi - self._arena_lo).any(dim=-1)
        return _segment_touches_box(positions, displacement, obstacles) | too_long

    # ------------------------------------------------------------------ geometry
    def inside_wall(self, positions: torch.Tensor, configurations: torch.Tensor) -> torch.Tensor:
        """True where a position lies in (or on the boundary of) one of its configuration's
        walls. positions (N, 2), configurations (N,) -> (N,)"""
        walls = self._walls[configurations]
        x, y = positions[:, :1], positions[:, 1:]
        inside = (
            (x >= walls[..., 0])
            & (x <= walls[..., 2])
            & (y >= walls[..., 1])
            & (y <= walls[..., 3])
        )
        return inside.any(dim=-1)

    def free_mask(self, config: int, resolution: int = 1000) -> np.ndarray:
        """Raster of free space, (resolution, resolution) bool, row 0 at y0 (bottom, south)."""
        a = self.arena
        xs = np.linspace(a.x0, a.x1, resolution + 1)
        ys = np.linspace(a.y0, a.y1, resolution + 1)
        cx, cy = (xs[:-1] + xs[1:]) / 2, (ys[:-1] + ys[1:]) / 2
        gx, gy = np.meshgrid(cx, cy)
        free = np.ones_like(gx, dtype=bool)
        for b in self.walls[config]:
            free &= ~((gx > b.x0) & (gx < b.x1) & (gy > b.y0) & (gy < b.y1))
        return free

    def free_area(self, config: int | None = None) -> float:
        """Area of free space of one configuration (or of the least free one when None).

        log(free area) is the entropy of the uniform distribution over free space: the
        highest entropy any visitation can reach.
        """
        if config is None:
            return min(self.free_area(c) for c in range(self.n_configurations))
        mask = self.free_mask(config)
        return float(mask.mean()) * self.arena.area


@dataclass
class NavigationEpisodes:
    """S' x N episodes of a 2-D world, with every step's world noise drawn up front."""

    world: NavigationWorld
    start: torch.Tensor  # (S', N, 2): s_0
    configurations: torch.Tensor  # (S' N,)
    noise: torch.Tensor  # (S' N, T, k): the uniforms each step consumes
    strength: torch.Tensor | None = None  # (S' N,): each agent's force (members' winds)

    def step(self, t: int, states: torch.Tensor, actions: torch.Tensor) -> Transition:
        s, n = states.shape[:2]
        moved = self.world.step(
            states.flatten(0, 1), actions.flatten(0, 1), self.configurations,
            noise=self.noise[:, t], strength=self.strength,
        )  # fmt: skip
        return Transition(moved.view(s, n, -1))


def edge_rule(env_cfg) -> str:
    """The edge rule of an ``env`` config entry; a run started before ``env.edge`` existed ran
    with the mirror and continues with it."""
    value = env_cfg.get("edge") if hasattr(env_cfg, "get") else getattr(env_cfg, "edge", None)
    return "mirror" if value is None else str(value)


def lattice(x0: float, y0: float, x1: float, y1: float, n: int) -> np.ndarray:
    """Centres of an n x n grid of cells over the rectangle, (n * n, 2)."""
    xs = x0 + (np.arange(n) + 0.5) * (x1 - x0) / n
    ys = y0 + (np.arange(n) + 0.5) * (y1 - y0) / n
    gx, gy = np.meshgrid(xs, ys)
    return np.stack([gx.ravel(), gy.ravel()], axis=1)


def _with_mirror_images(walls: np.ndarray, arena: Box) -> np.ndarray:
    """Each wall and its mirror images across the arena edges and corners: (C, W, 4) -> (C, 9W, 4).

    A path reflected off an edge touches a wall exactly when its unreflected straight line
    touches that wall's mirror image across the edge.
    """
    x0, y0, x1, y1 = (walls[..., i] for i in range(4))
    xs = [(x0, x1), (2 * arena.x0 - x1, 2 * arena.x0 - x0), (2 * arena.x1 - x1, 2 * arena.x1 - x0)]
    ys = [(y0, y1), (2 * arena.y0 - y1, 2 * arena.y0 - y0), (2 * arena.y1 - y1, 2 * arena.y1 - y0)]
    padding = x0 == FAR_AWAY  # stays far away
    images = []
    for ax0, ax1 in xs:
        for ay0, ay1 in ys:
            box = np.stack([ax0, ay0, ax1, ay1], axis=-1)
            box[padding] = FAR_AWAY
            images.append(box)
    return np.concatenate(images, axis=1)


def _segment_touches_box(
    start: torch.Tensor, delta: torch.Tensor, boxes: torch.Tensor
) -> torch.Tensor:
    """Slab test: does the segment start + t * delta, t in [0, 1], touch a closed box?

    start, delta (N, 2); boxes (N, K, 4) or (1, K, 4) as (x0, y0, x1, y1). -> (N,) bool
    """
    enter = torch.zeros((), dtype=start.dtype, device=start.device)
    leave = torch.ones((), dtype=start.dtype, device=start.device)
    for axis in (0, 1):
        p = start[:, axis : axis + 1]
        d = delta[:, axis : axis + 1]
        lo, hi = boxes[..., axis], boxes[..., axis + 2]
        moving = d != 0
        safe = torch.where(moving, d, torch.ones_like(d))
        t_lo, t_hi = (lo - p) / safe, (hi - p) / safe
        first, last = torch.minimum(t_lo, t_hi), torch.maximum(t_lo, t_hi)
        # Not moving on this axis: the segment is inside the slab for every t, or never.
        within = (p >= lo) & (p <= hi)
        inf = torch.full_like(first, float("inf"))
        first = torch.where(moving, first, torch.where(within, -inf, inf))
        last = torch.where(moving, last, torch.where(within, inf, -inf))
        enter = torch.maximum(enter, first)
        leave = torch.minimum(leave, last)
    return (enter <= leave).any(dim=-1)
