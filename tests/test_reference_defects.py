"""The emulation of the reference's three defects (tests/reference_edges.py), on cases
worked out by hand, and where its edge rule must agree with ours."""

from __future__ import annotations

import pytest
import torch

from hmepol_cli.envs.multigrid import MultiGridWorld
from hmepol_cli.envs.slope import SlopeWorld
from tests.reference_edges import DEFECTS, make_variant, reference_edge

HALF = 0.5  # a push-back uniform


def t(*rows: tuple[float, float]) -> torch.Tensor:
    return torch.tensor(rows, dtype=torch.float64)


def move(world, position, displacement, config, push=(HALF, HALF)):
    n = 1
    return world.move(t(position), t(displacement), torch.full((n,), config), t(push))[0]


# ------------------------------------------------------------------ corners
def test_the_north_west_corner_ends_on_the_edge_line_as_in_the_reference():
    # (-0.95, 0.9) + (-0.2, 0.15) reaches the west edge first (at 1/4 of the move) and the north
    # edge second. The reference turns it off the north edge, from the agent's projection on it
    # (-0.95, 1.0): overshoot 0.05 slides west, the -0.2 along the edge comes back south:
    # (-1.0, 0.8). Ours turns it off the west edge, then the north one: (-0.865625, 0.934375).
    open_arena = 7  # multigrid config 7: no slope, no wall near the corners
    ours = MultiGridWorld().to("cpu", torch.float64)
    theirs = make_variant("multigrid", ["corner"])
    assert move(theirs, (-0.95, 0.9), (-0.2, 0.15), open_arena).tolist() == pytest.approx(
        [-1.0, 0.8], abs=1e-12
    )
    assert move(ours, (-0.95, 0.9), (-0.2, 0.15), open_arena).tolist() == pytest.approx(
        [-0.865625, 0.934375], abs=1e-12
    )


def test_the_north_east_corner_differs_too_and_the_southern_ones_agree():
    open_arena = 7
    ours = MultiGridWorld().to("cpu", torch.float64)
    theirs = make_variant("multigrid", ["corner"])
    # The mirror image of the worked example in the north-east corner: the same defect.
    assert move(theirs, (0.95, 0.9), (0.2, 0.15), open_arena).tolist() == pytest.approx(
        [1.0, 0.8], abs=1e-12
    )
    assert move(ours, (0.95, 0.9), (0.2, 0.15), open_arena).tolist() == pytest.approx(
        [0.865625, 0.934375], abs=1e-12
    )
    for sx in (-1.0, 1.0):  # the southern corners: the reference's angle test picks right
        p, d = (sx * 0.95, -0.9), (sx * 0.2, -0.15)
        assert move(theirs, p, d, open_arena).tolist() == pytest.approx(
            [sx * 0.865625, -0.934375], abs=1e-12
        )


def test_the_reference_edge_rule_agrees_with_ours_except_in_the_northern_corners():
    g = torch.Generator().manual_seed(0)
    n = 4000
    # Starts near the corners, so that plenty of moves reach one edge or two.
    signs = torch.where(torch.rand(n, 2, generator=g) < 0.5, -1.0, 1.0).double()
    p = signs * (0.999 - 0.3 * torch.rand(n, 2, generator=g, dtype=torch.float64))
    d = (torch.rand(n, 2, generator=g, dtype=torch.float64) * 2 - 1) * 0.4
    world = MultiGridWorld().to("cpu", torch.float64)
    free = torch.full((1, 1, 4), 1e9, dtype=torch.float64)  # no walls
    ours, _ = world._slide(p, d, free)
    theirs, _ = reference_edge(p, d)
    end = p + d
    north_corner = (end[:, 1] >= 1) & (end[:, 0].abs() >= 1)
    assert north_corner.sum() > 100 and (~north_corner & ((end.abs() >= 1).any(1))).sum() > 500
    same = (ours - theirs).abs().max(dim=1).values < 1e-12
    assert bool(same[~north_corner].all())
    assert not bool(same[north_corner].any())


@pytest.mark.parametrize(
    ("start", "move_", "lands"),
    [  # docs/worlds.md, worked examples of the reference's edge rule
        ((-0.5, 0.95), (0.05, 0.2), (-0.3375, 0.9625)),
        ((-0.5, 0.95), (-0.05, 0.2), (-0.6625, 0.9625)),
        ((-0.5, 0.95), (0.2, 0.2), (-0.3, 0.85)),
        ((-0.5, 0.99), (0.0, 0.2), (-0.5, 0.81)),
        ((0.95, -0.5), (0.2, 0.05), (0.9625, -0.3375)),
        ((-0.95, 0.95), (-0.2, 0.2), (-0.85, 0.85)),
        ((-0.97, 0.9), (-0.2, 0.03), (-0.911175, 0.988825)),  # printed rounded
    ],
)
def test_the_reference_edge_rule_on_the_documented_examples(start, move_, lands):
    end, _ = reference_edge(t(start), t(move_))
    assert end[0].tolist() == pytest.approx(list(lands), abs=1e-12)


# ------------------------------------------------------------------ tunnelling
def test_a_move_tunnels_through_a_thin_wall_when_only_its_end_is_checked():
    # Multigrid config 3 (terraces): the wall of row 2 is 0.2 thick, y in [0.4, 0.6], x in
    # [-1, 0.6]. From (0.1, 0.65) a move of 0.3 south ends free at (0.1, 0.35) beyond it.
    terraces = 3
    ours = MultiGridWorld().to("cpu", torch.float64)
    theirs = make_variant("multigrid", ["tunnel"])
    assert move(theirs, (0.1, 0.65), (0.0, -0.3), terraces).tolist() == pytest.approx(
        [0.1, 0.35], abs=1e-12
    )
    # Ours: the path touches the wall, so the agent is pushed back north by 0.5 x 0.1.
    assert move(ours, (0.1, 0.65), (0.0, -0.3), terraces).tolist() == pytest.approx(
        [0.1, 0.7], abs=1e-12
    )


def test_a_move_cuts_the_corner_of_a_wall_stub_when_only_its_end_is_checked():
    # Slope world: the stub x in [-0.2, 0.2], y in [0.2, 0.4] below the north-west hallway. From
    # the hallway (-0.1, 0.42) to (-0.3, 0.25) in the room below: the path crosses x = -0.2 at
    # y = 0.335, inside the stub; the end point is free.
    ours = SlopeWorld().to("cpu", torch.float64)
    theirs = make_variant("slope", ["tunnel"])
    assert move(theirs, (-0.1, 0.42), (-0.2, -0.17), 0).tolist() == pytest.approx(
        [-0.3, 0.25], abs=1e-12
    )
    assert move(ours, (-0.1, 0.42), (-0.2, -0.17), 0).tolist() == pytest.approx(
        [-0.05, 0.47], abs=1e-12
    )


# ------------------------------------------------------------------ leaving the arena
def test_a_push_back_leaves_the_arena_when_it_is_not_kept_inside():
    # Slope world: (-0.95, 0.25) + (0.05, -0.1) ends in the west wall (x in [-1, -0.6], y in
    # [-0.2, 0.2]); the push-back, against the move, is (-0.9 x 0.1, +0.5 x 0.1).
    ours = SlopeWorld().to("cpu", torch.float64)
    theirs = make_variant("slope", ["leave"])
    push = (0.9, 0.5)
    assert move(theirs, (-0.95, 0.25), (0.05, -0.1), 0, push).tolist() == pytest.approx(
        [-1.04, 0.3], abs=1e-12
    )
    # Ours turns the push-back off the west edge (crossed at y = 0.25 + 0.05 * 5/9): the 0.04
    # beyond slides north, the 0.05 * 4/9 along the edge comes back east.
    assert move(ours, (-0.95, 0.25), (0.05, -0.1), 0, push).tolist() == pytest.approx(
        [-1 + 0.05 * 4 / 9, 0.25 + 0.05 * 5 / 9 + 0.04], abs=1e-12
    )


def test_an_agent_outside_follows_the_reference_edge_rule():
    # From (-1.04, 0.30), 0.04 beyond the west edge, a move (0.02, 0.05) ends at (-1.02, 0.35),
    # still beyond. The reference meets the edge on the move's line, behind the agent, at
    # y = 0.40; the turned remainder (0.05 north -> 0.05 back, 0.02 beyond -> 0.02 along,
    # against the move) ends beyond again at (-1.05, 0.42); turned once more from (-1, 0.40):
    # (-0.98, 0.45).
    theirs = make_variant("slope", ["leave"])
    end, _ = reference_edge(t((-1.04, 0.30)), t((0.02, 0.05)))
    assert end[0].tolist() == pytest.approx([-0.98, 0.45], abs=1e-12)
    assert move(theirs, (-1.04, 0.30), (0.02, 0.05), 0).tolist() == pytest.approx(
        [-0.98, 0.45], abs=1e-12
    )


# ------------------------------------------------------------------ no defect: our world
@pytest.mark.parametrize("name", ["slope", "multigrid"])
def test_without_defects_the_variant_steps_exactly_as_our_world(name):
    world = {"slope": SlopeWorld, "multigrid": MultiGridWorld}[name]().to("cpu", torch.float64)
    plain = make_variant(name, [])
    g = torch.Generator().manual_seed(1)
    n = 2000
    configs = world.sample_configurations(n, g)
    p = world.reset(configs, g)
    for _ in range(5):
        a = 0.3 * torch.randn(n, 2, generator=g, dtype=torch.float64)
        noise = world.draw_noise(n, g)
        q = world.step(p, a, configs, noise=noise)
        assert torch.equal(plain.step(p, a, configs, noise=noise), q)
        p = q


def test_unknown_defects_are_refused():
    with pytest.raises(ValueError, match="unknown defects"):
        make_variant("slope", ["teleport"])
    assert set(DEFECTS) == {"leave", "tunnel", "corner"}
