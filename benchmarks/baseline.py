"""The straightforward implementation the batched code is measured against.

One environment at a time, one step at a time, in a plain Python loop: NumPy float64 arrays,
the policy's forward pass on a single state per step. It simulates the same worlds as
``hmepol_cli.envs`` (same walls, slope and wind; :func:`check_same_physics` verifies the wall
physics against the batched world) with the same policy weights, so the two do the same work.
"""

from __future__ import annotations

import copy
import time

import numpy as np
import torch
from scipy.special import ndtr, ndtri

from hmepol_cli.envs.base import NavigationWorld
from hmepol_cli.envs.corridor import CorridorWorld
from hmepol_cli.envs.grid import SLOPE_STD, GridWorld
from hmepol_cli.policies.base import Policy
from hmepol_cli.policies.markov import MarkovPolicy
from hmepol_cli.policies.recursive import RecursivePolicy
from tests.reference_edges import slide_path


class PlainWorld:
    """A single agent in one configuration of a world, stepped with NumPy scalars and arrays."""

    def __init__(self, world: NavigationWorld, config: int, rng: np.random.Generator) -> None:
        self.world, self.config, self.rng = world, config, rng
        walls = [(b.x0, b.y0, b.x1, b.y1) for b in world.walls[config]]
        self.walls = np.array(walls, dtype=np.float64).reshape(-1, 4)
        a = world.arena
        self.lo, self.hi = np.array([a.x0, a.y0]), np.array([a.x1, a.y1])
        # Each wall and its mirror images across the edges: a mirrored path touches a wall
        # exactly when its straight, unreflected line touches one of them.
        images = []
        for mx in (None, self.lo[0], self.hi[0]):
            for my in (None, self.lo[1], self.hi[1]):
                w = self.walls.copy()
                if mx is not None:
                    w[:, [0, 2]] = 2 * mx - self.walls[:, [2, 0]]
                if my is not None:
                    w[:, [1, 3]] = 2 * my - self.walls[:, [3, 1]]
                images.append(w)
        self.mirrored_walls = np.concatenate(images)
        if isinstance(world, CorridorWorld):
            field = world.wind_field[config]
            self.wind_boxes = np.array([(b.x0, b.y0, b.x1, b.y1) for b, _ in field])
            self.wind_dirs = np.array([d for _, d in field])
        if isinstance(world, GridWorld):
            slope = world.slopes[config]
            self.slope = slope
            big = 1e9
            r = slope.region
            self.slope_region = (r.x0, r.y0, r.x1, r.y1) if r else (-big, -big, big, big)
            self.slope_cdf = (
                ndtr(-slope.mean / SLOPE_STD),
                ndtr((slope.high - slope.mean) / SLOPE_STD),
            )

    def reset(self) -> np.ndarray:
        s = self.world.start
        while True:
            p = np.array([s.x0, s.y0]) + self.rng.random(2) * np.array([s.x1 - s.x0, s.y1 - s.y0])
            if not self._in_wall(p):
                return p

    def _in_wall(self, p: np.ndarray) -> bool:
        w = self.walls
        return bool(
            ((p[0] >= w[:, 0]) & (p[0] <= w[:, 2]) & (p[1] >= w[:, 1]) & (p[1] <= w[:, 3])).any()
        )

    def force(self, position: np.ndarray) -> np.ndarray:
        x, y = position
        if isinstance(self.world, CorridorWorld):
            r = self.world.room
            if r.x0 <= x <= r.x1 and r.y0 <= y <= r.y1:
                return np.zeros(2)
            b = self.wind_boxes
            holds = (x >= b[:, 0]) & (x <= b[:, 2]) & (y >= b[:, 1]) & (y <= b[:, 3])
            if not holds.any():
                return np.zeros(2)
            return self.world.wind * self.wind_dirs[np.argmax(holds)]
        slope = self.slope
        x0, y0, x1, y1 = self.slope_region
        if slope.mean <= 0 or not (x0 <= x <= x1 and y0 <= y <= y1):
            return np.zeros(2)
        lo, hi = self.slope_cdf
        magnitude = slope.mean + SLOPE_STD * ndtri(lo + self.rng.random() * (hi - lo))
        return min(max(magnitude, 0.0), slope.high) * np.asarray(slope.direction)

    def step(self, position: np.ndarray, action: np.ndarray) -> np.ndarray:
        bound = self.world.max_action
        push = self.rng.random(2)
        return self.move(position, np.clip(action, -bound, bound) + self.force(position), push)

    def move(self, position: np.ndarray, displacement: np.ndarray, push: np.ndarray) -> np.ndarray:
        end, blocked = self.travel(position, displacement)
        if not blocked:
            return end
        back = -np.sign(displacement) * push * self.world.push_back
        end, stuck = self.travel(position, back)
        return position if stuck else end

    def travel(self, p: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, bool]:
        """Where the move p + d ends under the world's edge rule, and whether it hits a wall."""
        if self.world.edge == "mirror":
            too_long = bool((np.abs(d) > self.hi - self.lo).any())
            return self._reflect(p + d), too_long or touches(p, d, self.mirrored_walls)
        points = slide_path(p, d, self.lo, self.hi)
        if points is None:
            return p, True
        pieces = zip(points[:-1], points[1:], strict=True)
        hit = any(touches(a, b - a, self.walls) for a, b in pieces)
        return np.clip(points[-1], self.lo, self.hi), hit

    def _reflect(self, p: np.ndarray) -> np.ndarray:
        out = p.copy()
        for axis in (0, 1):
            lo, hi = self.lo[axis], self.hi[axis]
            if not lo <= p[axis] <= hi:
                r = np.mod(p[axis] - lo, 2 * (hi - lo))
                out[axis] = lo + (2 * (hi - lo) - r if r > hi - lo else r)
        return out


def touches(p: np.ndarray, d: np.ndarray, boxes: np.ndarray) -> bool:
    """Does the segment p + s d, s in [0, 1], touch one of the closed boxes (K, 4)?"""
    enter, leave = np.zeros(len(boxes)), np.ones(len(boxes))
    for axis in (0, 1):
        lo, hi = boxes[:, axis], boxes[:, axis + 2]
        if d[axis] == 0:
            inside = (lo <= p[axis]) & (p[axis] <= hi)
            enter = np.where(inside, enter, np.inf)
            continue
        t1, t2 = (lo - p[axis]) / d[axis], (hi - p[axis]) / d[axis]
        enter = np.maximum(enter, np.minimum(t1, t2))
        leave = np.minimum(leave, np.maximum(t1, t2))
    return bool((enter <= leave).any())


ACTIVATIONS = {torch.nn.ReLU: lambda x: np.maximum(x, 0.0), torch.nn.Tanh: np.tanh}


class PlainPolicy:
    """The same Gaussian policy as a list of float64 NumPy layers, one state at a time."""

    def __init__(self, policy: Policy, rng: np.random.Generator) -> None:
        def layers(net: torch.nn.Sequential) -> list[tuple[np.ndarray, np.ndarray, object]]:
            """(weight (in, out), bias, activation or None) per Linear layer."""
            modules, out = list(net), []
            for i, m in enumerate(modules):
                if isinstance(m, torch.nn.Linear):
                    after = type(modules[i + 1]) if i + 1 < len(modules) else None
                    weight = m.weight.detach().double().numpy().T.copy()
                    out.append((weight, m.bias.detach().double().numpy(), ACTIVATIONS.get(after)))
            return out

        self.rng = rng
        self.std = np.exp(policy.log_std.detach().double().numpy())
        self.history_size = policy.history_size
        if isinstance(policy, MarkovPolicy):
            self.encoder, self.head = None, layers(policy.mean_net)
        elif isinstance(policy, RecursivePolicy):
            self.encoder, self.head = layers(policy.encoder), layers(policy.head)
        else:
            raise ValueError(f"no plain baseline for {type(policy).__name__}")

    @staticmethod
    def _forward(layers, x: np.ndarray) -> np.ndarray:
        for weight, bias, activation in layers:
            x = x @ weight + bias
            if activation is not None:
                x = activation(x)
        return x

    def act(self, state: np.ndarray, history: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
        if self.encoder is not None:
            history = self._forward(self.encoder, np.concatenate((state, history)))
            mean = self._forward(self.head, history)
        else:
            mean = self._forward(self.head, state)
        action = mean + self.std * self.rng.standard_normal(mean.shape)
        z = (action - mean) / self.std
        log_prob = float(np.sum(-0.5 * z * z - np.log(self.std) - 0.5 * np.log(2 * np.pi)))
        return action, log_prob, history


def steps_per_second(
    world: NavigationWorld, policy: Policy, horizon: int, trajectories: int, seed: int = 0
) -> tuple[float, int]:
    """Run ``trajectories`` single-environment episodes of ``horizon`` steps in a plain loop,
    storing states, actions and log-likelihoods as the batched collection does.

    -> (environment steps per second, steps timed).
    """
    rng = np.random.default_rng(seed)
    plain_policy = PlainPolicy(policy, rng)
    probs = np.asarray(world.configuration_probs)
    start = time.perf_counter()
    for _ in range(trajectories):
        env = PlainWorld(world, int(rng.choice(len(probs), p=probs)), rng)
        states = np.empty((horizon + 1, 2))
        actions = np.empty((horizon, 2))
        log_probs = np.empty(horizon)
        states[0] = position = env.reset()
        history = np.zeros(plain_policy.history_size)
        for t in range(horizon):
            actions[t], log_probs[t], history = plain_policy.act(position, history)
            states[t + 1] = position = env.step(position, actions[t])
    seconds = time.perf_counter() - start
    return trajectories * horizon / seconds, trajectories * horizon


def check_same_physics(world: NavigationWorld, samples: int = 2000, seed: int = 0) -> float:
    """Largest difference between the plain and the batched wall physics on random moves from
    free positions (hits, push-backs and reflections among them)."""
    rng = np.random.default_rng(seed)
    a = world.arena
    configurations = rng.integers(0, world.n_configurations, samples)
    plain_worlds = [PlainWorld(world, int(c), rng) for c in configurations]
    positions = np.empty((samples, 2))
    for i, env in enumerate(plain_worlds):
        while True:
            positions[i] = rng.uniform((a.x0, a.y0), (a.x1, a.y1))
            if not env._in_wall(positions[i]):
                break
    displacement = rng.uniform(-0.6, 0.6, size=(samples, 2))
    push = rng.random((samples, 2))
    batched_world = copy.copy(world).to("cpu", torch.float64)  # the caller's world stays as it is
    batched = batched_world.move(
        torch.from_numpy(positions),
        torch.from_numpy(displacement),
        torch.from_numpy(configurations),
        torch.from_numpy(push),
    ).numpy()
    plain = np.stack(
        [
            env.move(p, d, u)
            for env, p, d, u in zip(plain_worlds, positions, displacement, push, strict=True)
        ]
    )
    return float(np.abs(plain - batched).max())
