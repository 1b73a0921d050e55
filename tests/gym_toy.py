"""A Gymnasium environment small enough to compute by hand, registered as ``hmepol-test/Walk-v0``.

A walker on a line: x_{t+1} = x_t + a_t + drift, with the action bounded to [-0.5, 0.5] (the
environment refuses a larger one: hmepol must clip). The observation is (x, the last move); the
reward is x after the move; the episode terminates once |x| >= ``wall``. The start x_0 is uniform
in [-0.1, 0.1] from the reset seed. ``dim`` pads the observation with zeros (configurations whose
spaces differ).
"""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np

WALK_ID = "hmepol-test/Walk-v0"
MAX_STEP = 0.5


class Walk(gym.Env):
    def __init__(self, drift: float = 0.0, wall: float = math.inf, dim: int = 2) -> None:
        self.drift, self.wall, self.dim = float(drift), float(wall), int(dim)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (self.dim,), np.float64)
        self.action_space = gym.spaces.Box(-MAX_STEP, MAX_STEP, (1,), np.float32)
        self.x, self.move = 0.0, 0.0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x, self.move = float(self.np_random.uniform(-0.1, 0.1)), 0.0
        return self._observation(), {}

    def step(self, action):
        if not self.action_space.contains(np.asarray(action, dtype=np.float32)):
            raise ValueError(f"action {action!r} outside the action space")
        self.move = float(action[0]) + self.drift
        self.x += self.move
        terminated = abs(self.x) >= self.wall
        return self._observation(), self.x, terminated, False, {}

    def _observation(self) -> np.ndarray:
        obs = np.zeros(self.dim)
        obs[:2] = (self.x, self.move)
        return obs


def register_walk() -> None:
    if WALK_ID not in gym.registry:
        gym.register(id=WALK_ID, entry_point=Walk, max_episode_steps=5)


register_walk()
