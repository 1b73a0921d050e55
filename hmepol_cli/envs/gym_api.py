"""The worlds through Gymnasium's API, for RL code outside hmepol.

Registered on ``import hmepol_cli.envs`` (idempotent)::

    hmepol/Slope-v0       hmepol/Corridor-v0 (kwarg wind, default 0.4)       hmepol/MultiGrid-v0

``gymnasium.make(id, horizon=400)`` gives :class:`NavigationEnv`, one numpy environment (what
``gymnasium.utils.env_checker.check_env`` accepts); ``gymnasium.make_vec(id, num_envs=N)``
gives :class:`NavigationVectorEnv`, which steps all N agents together as one batch of tensors
(on ``device``), the way hmepol's own training does.

Both follow the thesis' setting:

- observation: the position (x, y), float32, inside the arena; action: a displacement in
  [-0.2, 0.2]^2 (larger actions are clipped by the world, as in training).
- reward: always 0. Pre-training is reward-free (thesis 2.2): the objective is the entropy of
  the states a whole trajectory visits, which no per-step reward expresses; a downstream task
  adds its own reward with a wrapper.
- episodes never terminate; they are truncated after ``horizon`` steps (T = 400 by default).
- a configuration is drawn from p_M at every reset (thesis 2.1.1); ``options={"config": c}``
  forces one. ``info["config"]`` says which one runs.

Unlike hmepol's training, where the B trajectories of a mini-batch share one configuration
(thesis 4.2.3), each sub-environment of the vector env draws its own configuration.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from hmepol_cli.envs.base import NavigationWorld
from hmepol_cli.envs.corridor import DEFAULT_WIND
from hmepol_cli.envs.registry import make_world

DEFAULT_HORIZON = 400  # T (thesis 5.1)

# Gymnasium id -> (world name, extra default kwargs)
ENV_IDS: dict[str, tuple[str, dict[str, Any]]] = {
    "hmepol/Slope-v0": ("slope", {}),
    "hmepol/Corridor-v0": ("corridor", {"wind": DEFAULT_WIND}),
    "hmepol/MultiGrid-v0": ("multigrid", {}),
}


def register_envs() -> None:
    """Register every id of ``ENV_IDS`` with Gymnasium, skipping those already registered."""
    for env_id, (world, kwargs) in ENV_IDS.items():
        if env_id in gym.registry:
            continue
        gym.register(
            id=env_id,
            entry_point="hmepol_cli.envs.gym_api:NavigationEnv",
            vector_entry_point="hmepol_cli.envs.gym_api:NavigationVectorEnv",
            kwargs={"world": world, **kwargs},
        )


def build_world(world: str, wind: float | None = None, edge: str = "slide") -> NavigationWorld:
    """The world called ``world``; ``wind`` is the corridor's only parameter; ``edge`` the
    arena edge's rule (slide, the reference's, or mirror)."""
    if wind is not None and world != "corridor":
        raise ValueError(f"wind={wind!r} is a parameter of the corridor only, not of {world!r}")
    wind = DEFAULT_WIND if wind is None else wind
    return make_world(SimpleNamespace(name=world, wind=wind, edge=edge))


def _spaces(world: NavigationWorld) -> tuple[gym.spaces.Box, gym.spaces.Box]:
    a = world.arena
    observation = gym.spaces.Box(
        low=np.array([a.x0, a.y0], dtype=np.float32),
        high=np.array([a.x1, a.y1], dtype=np.float32),
        dtype=np.float32,
    )
    bound = world.max_action
    action = gym.spaces.Box(low=-bound, high=bound, shape=(world.action_dim,), dtype=np.float32)
    return observation, action


def _check_config(world: NavigationWorld, config: Any) -> None:
    values = np.atleast_1d(np.asarray(config))
    if values.dtype.kind not in "iu" or values.min() < 0 or values.max() >= world.n_configurations:
        raise ValueError(
            f"options['config']={config!r} is not allowed; use a whole number in "
            f"0..{world.n_configurations - 1} ({', '.join(world.configuration_names)})"
        )


class NavigationEnv(gym.Env[np.ndarray, np.ndarray]):
    """One agent in one world; a configuration drawn from p_M at each reset."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        world: str = "slope",
        horizon: int = DEFAULT_HORIZON,
        wind: float | None = None,
        render_mode: str | None = None,
        edge: str = "slide",
    ) -> None:
        if horizon < 1:
            raise ValueError(f"horizon={horizon!r} must be a whole number >= 1")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode={render_mode!r} is not allowed; use 'rgb_array' or None")
        self.world = build_world(world, wind, edge)
        self.horizon = int(horizon)
        self.render_mode = render_mode
        self.observation_space, self.action_space = _spaces(self.world)
        self._generator = torch.Generator()
        self._position = torch.zeros(1, 2, dtype=self.world.dtype)
        self._config = torch.zeros(1, dtype=torch.long)
        self._t = 0

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        # The slope's noise and the start position come from a torch stream seeded by np_random,
        # so a seeded reset fixes the whole episode.
        self._generator.manual_seed(int(self.np_random.integers(2**62)))
        if options and options.get("config") is not None:
            _check_config(self.world, options["config"])
            config = int(options["config"])
        else:
            config = int(
                self.np_random.choice(self.world.n_configurations, p=self.world.configuration_probs)
            )
        self._config = torch.tensor([config])
        self._position = self.world.reset(self._config, self._generator)
        self._t = 0
        return self._observation(), {"config": config}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        act = torch.as_tensor(
            np.asarray(action, dtype=np.float32).reshape(1, -1), dtype=self.world.dtype
        )
        self._position = self.world.step(self._position, act, self._config, self._generator)
        self._t += 1
        truncated = self._t >= self.horizon
        return self._observation(), 0.0, False, truncated, {"config": int(self._config[0])}

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array":
            return None
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        from hmepol_cli.envs.render import draw_world

        fig = Figure(figsize=(4, 4), dpi=64)
        canvas = FigureCanvasAgg(fig)
        ax = fig.add_axes((0, 0, 1, 1))
        ax.set_axis_off()
        draw_world(ax, self.world, int(self._config[0]))
        x, y = self._position[0].tolist()
        ax.plot([x], [y], "o", color="red", markersize=7, zorder=10)
        canvas.draw()
        return np.asarray(canvas.buffer_rgba())[..., :3].copy()

    def _observation(self) -> np.ndarray:
        return self._position[0].numpy().astype(np.float32, copy=True)


class NavigationVectorEnv(VectorEnv):
    """``num_envs`` agents stepped together as one batch of tensors on ``device``.

    Autoreset is Gymnasium's default ``NEXT_STEP`` mode: the step that truncates an episode
    returns its last observation; the next call to ``step`` ignores that sub-environment's
    action, draws a new configuration and start position, and returns them with reward 0 and
    terminated = truncated = False. All sub-environments start together, so with one horizon
    they also truncate together. ``reset(options={"config": c})`` takes one configuration for
    all, or one per sub-environment; ``options={"reset_mask": m}`` restarts only where the
    boolean (N,) mask is True; ``seed`` is one int for the whole batch (one random stream).
    """

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": []}

    def __init__(
        self,
        num_envs: int = 1,
        world: str = "slope",
        horizon: int = DEFAULT_HORIZON,
        wind: float | None = None,
        device: str = "cpu",
        edge: str = "slide",
    ) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs={num_envs!r} must be a whole number >= 1")
        if horizon < 1:
            raise ValueError(f"horizon={horizon!r} must be a whole number >= 1")
        self.world = build_world(world, wind, edge).to(device)
        self.num_envs = int(num_envs)
        self.horizon = int(horizon)
        self.device = self.world.device
        self.single_observation_space, self.single_action_space = _spaces(self.world)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self._generator = torch.Generator(device=self.device)
        n = self.num_envs
        self._positions = torch.zeros(n, 2, device=self.device, dtype=self.world.dtype)
        self._configs = torch.zeros(n, dtype=torch.long, device=self.device)
        self._t = torch.zeros(n, dtype=torch.long, device=self.device)
        self._autoreset = torch.zeros(n, dtype=torch.bool, device=self.device)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        if seed is not None and not isinstance(seed, (int, np.integer)):
            raise ValueError(f"seed={seed!r} is not allowed; use one int for the whole batch")
        super().reset(seed=seed)
        self._generator.manual_seed(int(self.np_random.integers(2**62)))
        options = options or {}
        mask = options.get("reset_mask")
        mask = (
            torch.ones(self.num_envs, dtype=torch.bool, device=self.device)
            if mask is None
            else torch.as_tensor(np.asarray(mask, dtype=bool), device=self.device)
        )
        configurations = self._draw_configs()
        if options.get("config") is not None:
            _check_config(self.world, options["config"])
            forced = torch.as_tensor(
                np.asarray(options["config"]), dtype=torch.long, device=self.device
            ).reshape(-1)
            if forced.numel() not in (1, self.num_envs):
                raise ValueError(
                    f"options['config'] has {forced.numel()} values; give 1 or "
                    f"num_envs={self.num_envs}"
                )
            configurations = forced.expand(self.num_envs).clone()
        self._start(mask, configurations)
        return self._observations(), self._info()

    def step(
        self, actions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        act = torch.as_tensor(
            np.asarray(actions, dtype=np.float32), device=self.device, dtype=self.world.dtype
        ).reshape(self.num_envs, -1)
        restart = self._autoreset
        self._positions = self.world.step(self._positions, act, self._configs, self._generator)
        self._t += 1
        # Next-step autoreset, with masks rather than a loop: fresh draws for every agent, kept
        # only where the previous step ended an episode (no host synchronisation on the GPU).
        self._start(restart, self._draw_configs())
        truncated = self._t >= self.horizon
        self._autoreset = truncated
        zeros = np.zeros(self.num_envs, dtype=bool)
        return (
            self._observations(),
            np.zeros(self.num_envs),
            zeros,
            truncated.cpu().numpy(),
            self._info(),
        )

    def _draw_configs(self) -> torch.Tensor:
        return self.world.sample_configurations(self.num_envs, self._generator).to(self.device)

    def _start(self, mask: torch.Tensor, configurations: torch.Tensor) -> None:
        """New episodes where ``mask`` (N,) is True: configuration, start position, t = 0."""
        starts = self.world.reset(configurations, self._generator)
        self._configs = torch.where(mask, configurations, self._configs)
        self._positions = torch.where(mask[:, None], starts, self._positions)
        self._t = torch.where(mask, torch.zeros_like(self._t), self._t)
        self._autoreset = self._autoreset & ~mask

    def _observations(self) -> np.ndarray:
        return self._positions.cpu().numpy().astype(np.float32, copy=True)

    def _info(self) -> dict[str, Any]:
        return {"config": self._configs.cpu().numpy(), "_config": np.ones(self.num_envs, bool)}
