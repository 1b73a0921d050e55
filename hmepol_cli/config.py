"""Typed run configuration: the schema every composed Hydra config is checked against.

The YAML files in ``conf/`` hold values; these dataclasses hold the types. A wrong type or an
unknown key is refused by OmegaConf before any work starts, and :func:`validate` refuses values
that have the right type but no meaning (k <= 0, alpha outside (0, 1], negative wind).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig


class ConfigError(ValueError):
    """A user-facing configuration mistake; the CLI prints it as one line."""


@dataclass
class EnvConfig:
    name: str = "slope"
    # corridor only: force of the wind along the corridor (top-level `wind` override).
    wind: float = 0.4


@dataclass
class AlgoConfig:
    name: str = "mepol"
    objective: str = "mean"  # mean (Mepol, HMepol) | cvar (alpha-Mepol, eq. 3.3)
    alpha: float = 1.0  # CVaR level; the lowest alpha fraction of mini-batch entropies
    trajectories: int = 200  # N, trajectories per epoch
    horizon: int = 400  # T
    batch_size: int = 5  # B, trajectories per mini-batch (one configuration each)
    kl_threshold: float = 15.0  # delta, trust region (Algorithm 3.1)
    lr: float = 1e-5
    max_off_iters: int = 30
    # When the first off-policy step already leaves the trust region, the learning rate is
    # divided by lr_backtrack_factor and the step retried, at most lr_backtrack_tries times.
    lr_backtrack_tries: int = 10
    lr_backtrack_factor: float = 2.0
    # Which likelihoods the trust region's KL (eq. 2.8) is computed from: "gradient", those the
    # gradient uses (policy.bptt; the thesis), or "exact", recomputed over the whole history.
    trust_region: str = "gradient"


@dataclass
class PolicyConfig:
    name: str = "markov"  # markov | recursive | twohead | gru | lstm
    hidden: list[int] = field(default_factory=lambda: [300, 300])  # Gaussian head MLP
    encoder_hidden: list[int] = field(default_factory=lambda: [300, 300])  # history encoder g
    history_size: int = 100  # length of h'_t
    encoder_activation: str = "relu"  # output of g: relu (thesis) | tanh (bounded history)
    bptt: str = "1"  # 1 (thesis) | n (truncated) | full (exact likelihoods)
    # The reference start for these worlds (REFERENCE_WORLDS.md): std 0.22, about the action bound.
    init_log_std: float = -1.5
    init_weights: str = "xavier"  # xavier (reference) | torch (torch's default)
    init_mean_scale: float = 0.01  # the mean's output layer is scaled by this: a near-zero start


@dataclass
class EstimatorConfig:
    name: str = "knn"
    k: int = 30
    neighbours: str = "auto"  # auto | kdtree | torch
    eps: float = 1e-10  # floor of the ball volume, so coincident particles stay finite


@dataclass
class EvalConfig:
    every: int = 0  # epochs between evaluations during training (0: only at the end)
    trajectories: int = 100  # heatmap trajectories per configuration
    horizon: int = 400
    plot_trajectories: int = 10
    plot_every: int = 10  # a point every this many steps on trajectory plots


@dataclass
class AlarmConfig:
    """Bounds past which a run reports that it diverges (log and epochs.csv)."""

    history_bound: float = 1e3  # largest |h'_t| of an epoch's rollout
    action_bound: float = 10.0  # largest |a_t| drawn (50x the action bound)


@dataclass
class Config:
    env: EnvConfig = field(default_factory=EnvConfig)
    algo: AlgoConfig = field(default_factory=AlgoConfig)
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    alarms: AlarmConfig = field(default_factory=AlarmConfig)
    seed: int = 0
    # A population: runs that differ only in their seed, trained together (one per seed).
    seeds: list[int] | None = None
    device: str = "cpu"  # cpu | cuda | auto
    dtype: str = "float32"  # float32 | float64
    # float32 matrix products on a GPU: highest (exact float32) | high (TF32, ~3x faster)
    matmul_precision: str = "highest"
    vmap: str = "auto"  # population calls: auto (vmap on cuda, a loop on cpu) | on | off
    cuda_graphs: bool = True  # on a GPU, replay each rollout's steps as one captured CUDA graph
    epochs: int = 20
    resume: str | None = None
    wind: float = 0.4
    progress: bool = True
    threads: int = 0  # torch threads; 0 = leave torch's default (sweeps set 1 per job)
    skip_finished: bool = True  # a re-run of a sweep skips a run directory that already finished


def register_configs() -> None:
    ConfigStore.instance().store(name="config_schema", node=Config)


ALGOS = ("mepol", "alphamepol", "hmepol")
OBJECTIVES = ("mean", "cvar")
POLICIES = ("markov", "recursive", "twohead", "gru", "lstm")
DEVICES = ("cpu", "cuda", "auto")
NEIGHBOURS = ("auto", "kdtree", "torch")
DTYPES = ("float32", "float64")


def _one_of(key: str, value: object, allowed: tuple[str, ...]) -> None:
    if value not in allowed:
        raise ConfigError(f"{key}={value!r} is not allowed; choose one of: {', '.join(allowed)}")


def _positive(key: str, value: float) -> None:
    if not value > 0:
        raise ConfigError(f"{key}={value!r} must be > 0")


def parse_bptt(value: str) -> int | None:
    """'full' -> None (whole trajectory), 'n' -> n >= 1."""
    text = str(value).strip().lower()
    if text == "full":
        return None
    if text.isdigit() and int(text) >= 1:
        return int(text)
    raise ConfigError(f"policy.bptt={value!r} is not allowed; use a whole number >= 1 or 'full'")


def validate(cfg: DictConfig) -> None:
    """Refuse values of the right type that mean nothing; one line names the value and the rule."""
    from hmepol_cli.envs import ENVIRONMENTS

    _one_of("env", cfg.env.name, tuple(ENVIRONMENTS))
    _one_of("algo.name", cfg.algo.name, ALGOS)
    _one_of("algo.objective", cfg.algo.objective, OBJECTIVES)
    _one_of("policy", cfg.policy.name, POLICIES)
    _one_of("device", cfg.device, DEVICES)
    _one_of("dtype", cfg.dtype, DTYPES)
    _one_of("matmul_precision", cfg.matmul_precision, ("highest", "high", "medium"))
    _one_of("vmap", cfg.vmap, ("auto", "on", "off"))
    _one_of("algo.trust_region", cfg.algo.trust_region, ("gradient", "exact"))
    _one_of("estimator.neighbours", cfg.estimator.neighbours, NEIGHBOURS)
    if not 0 < cfg.algo.alpha <= 1:
        raise ConfigError(f"algo.alpha={cfg.algo.alpha!r} must be in (0, 1]")
    if cfg.estimator.k <= 0:
        raise ConfigError(f"estimator.k={cfg.estimator.k!r} must be a whole number > 0")
    for key, value in (("wind", cfg.wind), ("env.wind", cfg.env.wind)):
        if value < 0:
            raise ConfigError(f"{key}={value!r} must be a number >= 0")
    for key in ("trajectories", "horizon", "batch_size", "max_off_iters"):
        _positive(f"algo.{key}", cfg.algo[key])
    for key in ("kl_threshold", "lr"):
        _positive(f"algo.{key}", cfg.algo[key])
    if not cfg.algo.lr_backtrack_factor > 1:
        raise ConfigError(f"algo.lr_backtrack_factor={cfg.algo.lr_backtrack_factor!r} must be > 1")
    if cfg.algo.lr_backtrack_tries < 0:
        raise ConfigError(f"algo.lr_backtrack_tries={cfg.algo.lr_backtrack_tries!r} must be >= 0")
    for key in ("history_bound", "action_bound"):
        _positive(f"alarms.{key}", cfg.alarms[key])
    if cfg.algo.trajectories % cfg.algo.batch_size:
        raise ConfigError(
            f"algo.trajectories={cfg.algo.trajectories} must be a multiple of "
            f"algo.batch_size={cfg.algo.batch_size}"
        )
    if cfg.estimator.k >= cfg.algo.batch_size * cfg.algo.horizon:
        raise ConfigError(
            f"estimator.k={cfg.estimator.k} must be smaller than the particles of a mini-batch "
            f"(batch_size * horizon = {cfg.algo.batch_size * cfg.algo.horizon})"
        )
    if cfg.epochs < 0:
        raise ConfigError(f"epochs={cfg.epochs!r} must be >= 0")
    parse_bptt(cfg.policy.bptt)
    _one_of("policy.encoder_activation", cfg.policy.encoder_activation, ("relu", "tanh"))
    _one_of("policy.init_weights", cfg.policy.init_weights, ("xavier", "torch"))
    if not cfg.policy.init_mean_scale >= 0:
        raise ConfigError(
            f"policy.init_mean_scale={cfg.policy.init_mean_scale!r} must be a number >= 0"
        )
    if cfg.policy.history_size <= 0:
        raise ConfigError(f"policy.history_size={cfg.policy.history_size!r} must be > 0")
