r"""Grid World with Corridor (thesis 5.2, Fig. 5.4): a room, one looping corridor, and a wind.

The arena is [-6, 6]^2, 36 times the area of the slope world, with the same action bound (0.2).
Config 0 (clockwise wind), one character per 0.5 x 1 cell, top row y in [5, 6]; ``#`` wall,
``.`` room (no wind), arrows the wind (``/`` and ``\`` where it turns a corner)::

           x = -6                   x = 6
           +------------------------+
           |//////>>>\\v##^/>>>\\\\\\|  y in [3, 6]: the ring's top band, cut by wall B (##)
           |//////>>>\\v##^/>>>\\\\\\|
           |//////>>>\\v##^/>>>\\\\\\|
           |^^^^^^###vv##^^###vvvvvv|  y in [2, 3]: stubs WS (vv) and ES (^^)
           |^^^^^^##........##vvvvvv|  y in [-2, 2]: the room; start box [-0.5, 0.5]^2
           |^^^^^^##........##vvvvvv|
           |^^^^^^##........##vvvvvv|
           |^^^^^^##........##vvvvvv|
           |^^^^^^############vvvvvv|  y in [-3, -2]: the room's south wall
           |\\\\\\<<<<<<<<<<<<//////|  y in [-6, -3]: the ring's bottom band
           |\\\\\\<<<<<<<<<<<<//////|
           |\\\\\\<<<<<<<<<<<<//////|
           +------------------------+

- The room's interior is [-2, 2]^2; its walls are 1 thick and fill [-3, 3]^2 around it.
- The ring corridor is everything with |x| or |y| in [3, 6] (width 3).
- Two stubs (1 wide) pierce the room's north wall: the west stub WS at x in [-1.5, -0.5] and the
  east stub ES at x in [0.5, 1.5], both y in [2, 3].
- A wall B at x in [-0.5, 0.5], y in [2, 6] (between the stubs, across the ring's top band)
  cuts the ring, so the corridor is one path: room -> ES -> around the ring -> WS -> room,
  walkable from either entrance to the other.

Free area: 144 - 21 = 123, of which the corridor (ring 105 + stubs 2) is 107, 87 %.

Wind (thesis 5.2): a fixed displacement of magnitude ``wind`` (default 0.4, twice the largest
action) added to the clipped action, in the corridor only, never in the room. Its direction
field is a set of rectangles tiling the corridor, each with a unit direction along the path:
clockwise in config 0 (``clockwise``: up ES, east along the top, down the east band, west along
the bottom, up the west band, east along the top, down WS) and its exact negation in config 1
(``counterclockwise``). The corner squares of the ring (NW, NE, SE, SW) carry the normalised
sum of the incoming and outgoing directions, so both the field and its negation turn the corner
(pushing agents into the arena's edges, which reflect them). The junction columns above the
stubs (WJ, EJ: x in the stub's range, y in [3, 6]) turn the path in two halves: the half beside
wall B blows along the stub, parallel to the wall, the outer half diagonally. Wind never points
into a wall: a wall's push-back reverses both axes of the move, so an agent blown into wall B
would bounce off it forever instead of descending into the stub. p_M = (0.5, 0.5).

Consequence: with wind 0.4 one entrance is downwind in each configuration (WS in clockwise, ES in
counterclockwise): the wind blows into the room there, and an agent pushing in at full force
(0.2) is thrown back and never gets past the entrance (y <= 2.2). The other entrance is upwind:
an agent that steps in is carried out and around the whole loop.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from hmepol_cli.envs.base import Box, NavigationWorld, edge_rule, lattice

ARENA = Box(-6.0, -6.0, 6.0, 6.0)
ROOM = Box(-2.0, -2.0, 2.0, 2.0)  # interior, wind-free
START = Box(-0.5, -0.5, 0.5, 0.5)
WEST_STUB = Box(-1.5, 2.0, -0.5, 3.0)
EAST_STUB = Box(0.5, 2.0, 1.5, 3.0)
DEFAULT_WIND = 0.4  # twice the action bound (thesis 5.2)

WALLS = (
    Box(-3.0, -3.0, 3.0, -2.0),  # room's south wall
    Box(-3.0, -2.0, -2.0, 2.0),  # west wall
    Box(2.0, -2.0, 3.0, 2.0),  # east wall
    Box(-3.0, 2.0, -1.5, 3.0),  # north wall, west of WS
    Box(-0.5, 2.0, 0.5, 6.0),  # north wall between the stubs, continued across the ring (B)
    Box(1.5, 2.0, 3.0, 3.0),  # north wall, east of ES
)

_D = 1.0 / math.sqrt(2.0)
# Clockwise wind field: rectangles tiling the corridor, with the unit direction in each.
# Rectangles are closed and the first one that holds a position decides (they overlap only on
# shared edges, where either direction moves the agent along the path).
CLOCKWISE_FIELD: tuple[tuple[Box, tuple[float, float]], ...] = (
    (WEST_STUB, (0.0, -1.0)),  # down into the room
    (EAST_STUB, (0.0, 1.0)),  # up out of the room
    (Box(-1.5, 3.0, -1.0, 6.0), (_D, -_D)),  # WJ, west half: east and down, towards WS
    (Box(-1.0, 3.0, -0.5, 6.0), (0.0, -1.0)),  # WJ, east half: down along wall B into WS
    (Box(0.5, 3.0, 1.0, 6.0), (0.0, 1.0)),  # EJ, west half: up along wall B from ES
    (Box(1.0, 3.0, 1.5, 6.0), (_D, _D)),  # EJ, east half: up and east, into the top band
    (Box(-3.0, 3.0, -1.5, 6.0), (1.0, 0.0)),  # top band, west part
    (Box(1.5, 3.0, 3.0, 6.0), (1.0, 0.0)),  # top band, east part
    (Box(3.0, 3.0, 6.0, 6.0), (_D, -_D)),  # NE corner
    (Box(3.0, -3.0, 6.0, 3.0), (0.0, -1.0)),  # east band
    (Box(3.0, -6.0, 6.0, -3.0), (-_D, -_D)),  # SE corner
    (Box(-3.0, -6.0, 3.0, -3.0), (-1.0, 0.0)),  # south band
    (Box(-6.0, -6.0, -3.0, -3.0), (-_D, _D)),  # SW corner
    (Box(-6.0, -3.0, -3.0, 3.0), (0.0, 1.0)),  # west band
    (Box(-6.0, 3.0, -3.0, 6.0), (_D, _D)),  # NW corner
)


class CorridorWorld(NavigationWorld):
    """Room plus one looping corridor; wind clockwise (config 0) or counterclockwise (config 1)."""

    name = "corridor"
    arena = ARENA
    start = START
    room = ROOM
    configuration_names = ("clockwise", "counterclockwise")
    configuration_probs = (0.5, 0.5)
    walls = (WALLS, WALLS)
    # One (Box, direction) list per configuration; config 1 is the exact negation of config 0.
    wind_field = (
        CLOCKWISE_FIELD,
        tuple((box, (-dx, -dy)) for box, (dx, dy) in CLOCKWISE_FIELD),
    )

    @classmethod
    def from_config(cls, env_cfg) -> CorridorWorld:
        wind = getattr(env_cfg, "wind", None)
        return cls(wind=DEFAULT_WIND if wind is None else wind, edge=edge_rule(env_cfg))

    def describe(self, config: int) -> str:
        return f"wind {self.wind:g} in the corridor only" if self.wind > 0 else "no wind"

    def facts(self, member: int | None = None) -> dict[str, object]:
        values = getattr(self, "_member_strength_values", None)
        wind = self.wind if member is None or values is None else values[member]
        return {**super().facts(), "wind": wind}

    def arrow_candidates(self, config: int) -> tuple[list[tuple[np.ndarray, np.ndarray]], float]:
        """An arrow every 0.75: one in every stub, four across the ring."""
        if self.wind == 0:
            return [], 0.0
        a, n = self.arena, 16
        points = lattice(a.x0, a.y0, a.x1, a.y1, n)
        at = torch.tensor(points, dtype=self.dtype, device=self.device)
        configurations = torch.full((len(points),), config, dtype=torch.long, device=self.device)
        directions = self.wind_direction(at, configurations).cpu().double().numpy()
        return [(points, directions)], 0.55 * (a.x1 - a.x0) / n

    def __init__(self, wind: float = DEFAULT_WIND, edge: str = "slide") -> None:
        if not 0 <= wind < math.inf:
            raise ValueError(f"wind={wind!r} must be a finite number >= 0")
        self.wind = float(wind)
        super().__init__(edge)

    def _build_tensors(self) -> None:
        super()._build_tensors()
        kw = dict(device=self.device, dtype=self.dtype)
        boxes = [[(b.x0, b.y0, b.x1, b.y1) for b, _ in f] for f in self.wind_field]
        directions = [[d for _, d in f] for f in self.wind_field]
        self._wind_boxes = torch.tensor(boxes, **kw)  # (C, K, 4)
        self._wind_dirs = torch.tensor(directions, **kw)  # (C, K, 2)

    def wind_direction(self, positions: torch.Tensor, configurations: torch.Tensor) -> torch.Tensor:
        """Unit direction of the wind at each position, zero in the room. (N, 2), (N,) -> (N, 2)."""
        boxes = self._wind_boxes[configurations]  # (N, K, 4)
        x, y = positions[:, :1], positions[:, 1:]
        holds = (x >= boxes[..., 0]) & (x <= boxes[..., 2])
        holds &= (y >= boxes[..., 1]) & (y <= boxes[..., 3])
        first = holds.to(positions.dtype).argmax(dim=-1)  # the first rectangle that holds it
        direction = self._wind_dirs[configurations].gather(
            1, first[:, None, None].expand(-1, 1, 2)
        )[:, 0]
        r = self.room
        in_room = (x >= r.x0) & (x <= r.x1) & (y >= r.y0) & (y <= r.y1)
        in_corridor = holds.any(dim=-1, keepdim=True) & ~in_room
        return torch.where(in_corridor, direction, torch.zeros_like(direction))

    def force(
        self,
        positions: torch.Tensor,
        configurations: torch.Tensor,
        noise: torch.Tensor,
        strength: torch.Tensor | None = None,
    ) -> torch.Tensor:
        wind = self.wind if strength is None else strength[:, None]  # a population's winds
        return wind * self.wind_direction(positions, configurations)

    def member_strengths(self, env_cfgs) -> list[float]:
        """Each member's wind."""
        return [DEFAULT_WIND if c.get("wind") is None else float(c.wind) for c in env_cfgs]
