"""Typed run configs: the schema every composed Hydra config is checked against.

The YAML files in ``conf/`` hold values; these dataclasses hold the types. A wrong type or an
unknown key is refused by OmegaConf before any work starts, and :func:`validate` refuses values
that have the right type but no meaning (k <= 0, alpha outside (0, 1], negative wind).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig, OmegaConf

from hmepol_cli.errors import ConfigError
from hmepol_cli.precision import PRECISIONS, precision_of


@dataclass
class EnvConfig:
    name: str = "slope"  # slope | corridor | multigrid | gym (any Gymnasium id, below)
    # corridor only: force of the wind along the corridor, set with the top-level `wind` (the
    # corridor's env file reads it); null for a world without wind, and in fine-tuning the
    # pre-trained run's wind.
    wind: float | None = None
    # 2-D worlds: what a move past the arena's edge does: slide (the reference's quarter turn
    # into a slide along the edge) | mirror (reflected, this project's rule before)
    edge: str = "slide"
    # gym only (env=gym, or a preset such as env=ant_xy):
    id: str | None = None  # a Gymnasium id, e.g. Ant-v5, MountainCarContinuous-v0
    features: list[int] | None = None  # observation indices the entropy is on (null: all)
    # The class M_1..M_I: one gymnasium.make keyword set per configuration (null: [{}]), drawn
    # with probabilities p_M (null: uniform).
    configs: list[dict[str, Any]] | None = None
    probs: list[float] | None = None
    projection: list[int] | None = None  # two indices heatmaps draw (null: first two features)
    workers: int = 0  # processes stepping the sub-environments (0: this process)


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
    # A step that leaves the trust region is undone and retried at a smaller learning rate
    # (hmepol_cli/mepol.py): "reference" (the public Mepol code: any rejected step is retried
    # at lr / factor^j, j < tries, then the epoch ends) | "first_step" (only a rejected first
    # step is retried, at most `tries` halvings, and the epoch goes on at the reduced rate).
    backtracking: str = "reference"
    lr_backtrack_tries: int = 10
    lr_backtrack_factor: float = 2.0
    # What a rejected step restores: "parameters" (the reference; Adam's moments keep the
    # rejected step's gradient) | "parameters_and_adam".
    backtrack_restore: str = "parameters"
    # Which likelihoods the trust region's KL (eq. 2.8) is computed from: "gradient", those the
    # gradient uses (policy.bptt; the thesis), or "exact", recomputed over the whole history.
    trust_region: str = "gradient"
    # Ours (from the collapse study): "epoch" starts every epoch's off-policy loop with fresh Adam
    # moments and step count; null (the thesis and the reference) keeps one Adam for the run.
    adam_reset: str | None = None


@dataclass
class PolicyConfig:
    name: str = "markov"  # markov | recursive | twohead | gru | lstm
    hidden: list[int] = field(default_factory=lambda: [300, 300])  # Gaussian head MLP
    encoder_hidden: list[int] = field(default_factory=lambda: [300, 300])  # history encoder g
    history_size: int = 100  # length of h'_t
    encoder_activation: str = "relu"  # output of g: relu (thesis) | tanh (bounded history)
    bptt: str | None = "1"  # 1 (thesis) | n (truncated) | full; fine-tuning: null = the run's
    # The reference start for these worlds (docs/worlds.md): std 0.22, about the action bound.
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
    plot_trajectories: int = 5  # lines on each trajectory panel


@dataclass
class AlarmConfig:
    """Bounds past which a run reports that it diverges (log and epochs.csv)."""

    history_bound: float = 1e3  # largest |h'_t| of an epoch's rollout
    action_bound: float = 10.0  # largest |a_t| drawn (50x the action bound)
    stall_epochs: int = 10  # epochs in a row without an accepted off-policy step
    # precision=bf16: the accepted step's KL, recomputed in full precision every epoch, differs
    # from the lowered one by more than this share
    precision_drift: float = 0.01


@dataclass
class WandbConfig:
    project: str = "hmepol"
    entity: str | None = None
    mode: str = "auto"  # auto (online with a key, offline without) | online | offline | disabled


@dataclass
class MlflowConfig:
    tracking_uri: str | None = None  # null: outputs/mlflow.db above the run dir (tracking.py)
    experiment: str = "hmepol"


@dataclass
class LoggerConfig:
    """The ``logger`` group, several at once (logger=[csv,tensorboard]); csv is always on."""

    csv: dict[str, Any] | None = None
    tensorboard: dict[str, Any] | None = None
    wandb: WandbConfig | None = None
    mlflow: MlflowConfig | None = None


@dataclass
class CheckpointConfig:
    # Keep checkpoints/epoch_<n>.pt every keep_every epochs besides last.pt (0: only last.pt);
    # fine-tuning starts from one with init=<run dir>@<n>.
    keep_every: int = 0


@dataclass
class Config:
    env: EnvConfig = field(default_factory=EnvConfig)
    algo: AlgoConfig = field(default_factory=AlgoConfig)
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    alarms: AlarmConfig = field(default_factory=AlarmConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    # steps.csv (every off-policy step: lr, accepted, one-step and exact KL, IW entropy) and
    # epochs.csv's kl_exact; the exact KL costs one full-history pass per step (recursive).
    diagnostics: bool = False
    seed: int = 0
    # A population: runs that differ only in their seed, trained together (one per seed).
    seeds: list[int] | None = None
    # A population of members with their own member-scalar overrides, one string each
    # ("seed=0 wind=0.05"); what hydra/launcher=population writes.
    members: list[str] | None = None
    # Members stepped together in one batched call (0: all on a CPU, as many as fit in the
    # GPU's free memory on a GPU); chunks change no number, only memory and speed.
    chunk_members: int = 0
    device: str = "cpu"  # cpu | cuda | auto
    # float32 | float64 | bf16 (the hidden layers' products in bfloat16; a CPU needs bfloat16
    # units) | tf32 (TF32 products, GPU only) | auto (bf16 where the device has bfloat16
    # arithmetic and it measures faster, else float32); hmepol_cli/precision.py says more
    precision: str = "float32"
    # Who runs the float32 layer products on a CPU: torch | openblas (NumPy's) | auto (the
    # faster at the layer's shape on this machine); default $HMEPOL_BLAS; hmepol_cli/blas.py
    blas: str = "auto"
    vmap: str = "auto"  # population calls: auto (vmap on cuda, a loop on cpu) | on | off
    cuda_graphs: bool = True  # on a GPU, replay each rollout's steps as one captured CUDA graph
    epochs: int = 500
    resume: str | None = None
    wind: float = 0.4
    progress: bool = True
    threads: int = 0  # torch threads; 0 = leave torch's default (sweeps set 1 per job)
    skip_finished: bool = True  # a re-run of a sweep skips a run directory that already finished


@dataclass
class TRPOConfig:
    """TRPO's hyperparameters (Schulman et al. 2015; sb3-contrib's defaults), keys of
    ``hmepol finetune``; :class:`hmepol_cli.finetune.trpo.TRPOSettings` adds the likelihoods'
    bptt. The one place their defaults are written."""

    gamma: float = 0.99
    gae_lambda: float = 0.95
    max_kl: float = 0.01  # delta, the trust region's bound on the mean KL
    cg_iters: int = 10
    damping: float = 0.1  # added to F for the conjugate-gradient solve
    # Share of the episodes in the Fisher-vector products (0.25: a ~3x faster solve); the line
    # search checks the KL on every episode, so the bound holds whatever the share.
    fisher_fraction: float = 1.0
    line_search_steps: int = 10  # tries of the line search, the full step first
    line_search_shrink: float = 0.8  # the step is multiplied by this between tries
    normalize_advantage: bool = True
    value_lr: float = 1e-3
    value_epochs: int = 10
    value_batch: int = 512
    value_hidden: list[int] = field(default_factory=lambda: [64, 64])


@dataclass
class FinetuneConfig(TRPOConfig):
    """``hmepol finetune``: TRPO on sparse goal-reaching tasks (thesis 5.2, Fig. 5.9)."""

    # a run directory or checkpoint of `hmepol train`, <run dir>@<epochs>, or none (scratch)
    init: str = "none"
    # start from a run that is still being trained (its last checkpoint at that moment)
    allow_running: bool = False
    env: EnvConfig | None = None  # null: the init run's world (slope for init=none)
    wind: float | None = None  # corridor wind; null: the init run's (0.4 for init=none)
    policy: PolicyConfig = field(default_factory=PolicyConfig)  # the fresh policy of init=none
    # The task: reward 1 on the step the agent enters the target area; the episode ends there.
    goal: Any = "random"  # random | a list of [x, y] target centres, e.g. [[-0.6,-0.2]]
    targets: int = 5  # random target areas per configuration (thesis: five)
    goal_size: float | None = None  # side of the square target; null: 0.1 x the arena's side
    goal_seed: int = 0  # the random targets; apart from seed, so seeds share their targets
    config: Any = None  # configuration(s) to fine-tune in: an index, a list, or null (each)
    epochs: int = 50
    episodes: int = 20  # episodes per epoch, stepped together
    horizon: int = 400  # T
    seed: int = 0
    device: str = "cpu"  # cpu | cuda | auto
    blas: str = "auto"  # torch | openblas | auto, as in train (default $HMEPOL_BLAS)
    threads: int = 0  # torch threads; 0 = torch's default
    progress: bool = True
    output_dir: str | None = None  # null: Hydra's run directory


# --------------------------------------------------------------------------- the rules
INT_MAX = 2**31 - 1  # every whole number is below this: a seed, a count, an index


@dataclass(frozen=True)
class Rule:
    """What one setting accepts: its kind, a range or the choices, and the worlds or objectives
    it applies to. Every field of the schema has one (tests/test_fuzz_config.py fails on a
    field without), and :func:`check_rules` checks a composed config against them all.

    kind: int | float | bool | text | ints | floats | choice | other (checked further on by
    its own code, which ``bad`` examples exercise)."""

    kind: str
    at_least: float | None = None
    above: float | None = None
    below: float | None = None
    at_most: float | None = None
    choices: Any = None  # a tuple, or a function giving one (a registry)
    null: bool = False  # null is allowed
    nonempty: bool = False  # a list needs an item
    example: str | None = None
    worlds: tuple[str, ...] | None = None  # None: every world
    objectives: tuple[str, ...] | None = None  # None: every objective
    bad: tuple[str, ...] = ()  # kind other: overrides its own check refuses (the fuzz test)

    def allowed(self) -> tuple[str, ...]:
        return tuple(self.choices() if callable(self.choices) else self.choices or ())

    def describe(self) -> str:
        """What the setting takes, in words."""
        if self.kind == "choice":
            text = f"one of: {', '.join(map(str, self.allowed()))}"
        elif self.kind == "other":
            text = self.example or "a value its own check accepts"
        else:
            words = {"int": "a whole number", "float": "a finite number", "bool": "true or false",
                     "text": "text", "ints": "a list of whole numbers",
                     "floats": "a list of finite numbers"}  # fmt: skip
            text = words[self.kind]
            pairs = ((">=", self.at_least), (">", self.above), ("<", self.below),
                     ("<=", self.at_most))  # fmt: skip
            bounds = [f"{op} {_number_text(b)}" for op, b in pairs if b is not None]
            if self.kind in ("int", "ints") and self.below is None and self.at_most is None:
                bounds.append(f"<= {INT_MAX}")
            if bounds:
                text += (" each" if self.kind in ("ints", "floats") else "") + " " + " and ".join(
                    bounds
                )
            if self.nonempty:
                text += ", at least one"
            if self.example:
                text += f", e.g. {self.example}"
        return text + (" (or null)" if self.null else "")


def _number_text(value: float) -> str:
    return str(int(value)) if float(value).is_integer() else f"{value:g}"


def _registry(module: str, name: str):
    def names() -> tuple[str, ...]:
        import importlib

        return tuple(getattr(importlib.import_module(module), name))

    return names


def _choice(*values, null: bool = False, **where) -> Rule:
    return Rule("choice", choices=values, null=null, **where)


def _whole(at_least: int = 0, **more) -> Rule:
    return Rule("int", at_least=at_least, **more)


def _number(**more) -> Rule:
    return Rule("float", **more)


def _text(**more) -> Rule:
    return Rule("text", **more)


FLAG = Rule("bool")
_GYM = {"worlds": ("gym",)}
_BPTT = Rule("other", null=True, example="a whole number >= 1 or 'full'", bad=("zero", "0", "-2"))

# One rule per leaf of the schema, by its dotted key. A new setting adds its line here.
POLICY_RULES: dict[str, Rule] = {
    "name": Rule("choice", choices=_registry("hmepol_cli.policies", "POLICIES")),
    "hidden": Rule("ints", above=0, at_most=100_000, nonempty=True, example="[300,300]"),
    "encoder_hidden": Rule("ints", above=0, at_most=100_000, example="[300,300]"),
    "history_size": _whole(1, at_most=100_000),
    "encoder_activation": _choice("relu", "tanh"),
    "bptt": _BPTT,
    "init_log_std": _number(),
    "init_weights": _choice("xavier", "torch"),
    "init_mean_scale": _number(at_least=0),
}
ENV_RULES: dict[str, Rule] = {
    "name": Rule("choice", choices=_registry("hmepol_cli.envs", "ENVIRONMENTS")),
    "wind": _number(at_least=0, below=12.0, null=True, worlds=("corridor",)),
    "edge": Rule("choice", choices=_registry("hmepol_cli.envs.base", "EDGE_RULES")),
    "id": _text(null=True, **_GYM),
    "features": Rule("ints", at_least=0, null=True, nonempty=True, example="[0,1]", **_GYM),
    "configs": Rule("other", null=True, example="a list of keyword sets, e.g. [{},{gravity:5}]",
                    bad=("3",), **_GYM),  # fmt: skip
    "probs": Rule("floats", at_least=0, null=True, nonempty=True, **_GYM),
    "projection": Rule("ints", at_least=0, null=True, example="[0,1]", **_GYM),
    "workers": _whole(0, at_most=1024, **_GYM),
}
RULES: dict[str, Rule] = {
    **{f"env.{k}": r for k, r in ENV_RULES.items()},
    "algo.name": Rule("choice", choices=_registry("hmepol_cli.algorithms", "ALGORITHMS")),
    "algo.objective": Rule("choice", choices=_registry("hmepol_cli.objectives", "OBJECTIVES")),
    "algo.alpha": _number(above=0, at_most=1, objectives=("cvar",)),
    "algo.trajectories": _whole(1),
    "algo.horizon": _whole(1),
    "algo.batch_size": _whole(1),
    "algo.kl_threshold": _number(above=0),
    "algo.lr": _number(above=0),
    "algo.max_off_iters": _whole(1),
    "algo.backtracking": _choice("reference", "first_step"),
    "algo.lr_backtrack_tries": _whole(0),
    "algo.lr_backtrack_factor": _number(above=1),
    "algo.backtrack_restore": _choice("parameters", "parameters_and_adam"),
    "algo.trust_region": _choice("gradient", "exact"),
    "algo.adam_reset": _choice("epoch", null=True),
    **{f"policy.{k}": r for k, r in POLICY_RULES.items()},
    "estimator.name": Rule("choice", choices=_registry("hmepol_cli.estimators", "ESTIMATORS")),
    "estimator.k": _whole(1),
    "estimator.neighbours": _choice("auto", "kdtree", "torch"),
    "estimator.eps": _number(above=0),
    "eval.every": _whole(0),
    "eval.trajectories": _whole(1),
    "eval.horizon": _whole(1),
    "eval.plot_trajectories": _whole(0),
    "alarms.history_bound": _number(above=0),
    "alarms.action_bound": _number(above=0),
    "alarms.stall_epochs": _whole(1),
    "alarms.precision_drift": _number(above=0),
    "checkpoint.keep_every": _whole(0),
    "logger.csv": Rule("other", null=True, example="a group: logger=[csv,...]", bad=("3",)),
    "logger.tensorboard": Rule("other", null=True, example="a group: logger=[csv,tensorboard]",
                               bad=("3",)),  # fmt: skip
    "logger.wandb.project": _text(),
    "logger.wandb.entity": _text(null=True),
    "logger.wandb.mode": _choice("auto", "online", "offline", "disabled"),
    "logger.mlflow.tracking_uri": _text(null=True),
    "logger.mlflow.experiment": _text(),
    "diagnostics": FLAG,
    "seed": _whole(0),
    "seeds": Rule("ints", at_least=0, at_most=INT_MAX, null=True, nonempty=True,
                  example="seeds=[0,1,2]"),  # fmt: skip
    "members": Rule("other", null=True, example='override strings, e.g. ["seed=0 wind=0.1"]',
                    bad=("3",)),  # fmt: skip
    "chunk_members": _whole(0),
    "device": _choice(*("cpu", "cuda", "auto")),
    "precision": Rule("choice", choices=lambda: (*PRECISIONS, "auto")),
    "blas": _choice("auto", "torch", "openblas"),
    "vmap": _choice("auto", "on", "off"),
    "cuda_graphs": FLAG,
    "epochs": _whole(1),
    "resume": _text(null=True),
    "wind": _number(at_least=0, below=12.0, worlds=("corridor",)),
    "progress": FLAG,
    "threads": _whole(0, at_most=4096),
    "skip_finished": FLAG,
}
FINETUNE_RULES: dict[str, Rule] = {
    "gamma": _number(at_least=0, at_most=1),
    "gae_lambda": _number(at_least=0, at_most=1),
    "max_kl": _number(above=0),
    "cg_iters": _whole(1),
    "damping": _number(at_least=0),
    "fisher_fraction": _number(above=0, at_most=1),
    "line_search_steps": _whole(1),
    "line_search_shrink": _number(above=0, below=1),
    "normalize_advantage": FLAG,
    "value_lr": _number(above=0),
    "value_epochs": _whole(1),
    "value_batch": _whole(1),
    "value_hidden": Rule("ints", above=0, at_most=100_000, nonempty=True, example="[64,64]"),
    "init": _text(example="none, a run directory, or <run dir>@<epochs>"),
    "allow_running": FLAG,
    **{f"env.{k}": r for k, r in ENV_RULES.items()},
    "wind": _number(at_least=0, below=12.0, null=True, worlds=("corridor",)),
    **{f"policy.{k}": r for k, r in POLICY_RULES.items()},
    "goal": Rule("other", example="random or a list of [x, y] centres, e.g. [[-0.6,-0.2]]",
                 bad=("somewhere", "[[5,5]]")),  # fmt: skip
    "targets": _whole(1, at_most=10_000),
    "goal_size": _number(above=0, null=True),
    "goal_seed": _whole(0),
    "config": Rule("other", null=True, example="an index of a configuration, a list, or null",
                   bad=("7",)),  # fmt: skip
    "epochs": _whole(1),
    "episodes": _whole(1),
    "horizon": _whole(1),
    "seed": _whole(0),
    "device": _choice("cpu", "cuda", "auto"),
    "blas": _choice("auto", "torch", "openblas"),
    "threads": _whole(0, at_most=4096),
    "progress": FLAG,
    "output_dir": _text(null=True),
}


def schema_fields(cls: type, prefix: str = "") -> list[str]:
    """Every leaf setting of a schema dataclass, by its dotted key."""
    import dataclasses
    import typing

    keys = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        inner = [t for t in typing.get_args(hints[f.name]) or [hints[f.name]]
                 if dataclasses.is_dataclass(t)]  # fmt: skip
        keys += schema_fields(inner[0], f"{prefix}{f.name}.") if inner else [f"{prefix}{f.name}"]
    return keys


def rules_of(cls: type) -> dict[str, Rule]:
    return FINETUNE_RULES if cls is FinetuneConfig else RULES


def _shown(value: object) -> str:
    if OmegaConf.is_config(value):
        value = OmegaConf.to_container(value)
    return "null" if value is None else repr(value)


def check_value(key: str, value: object, rule: Rule) -> None:
    """One setting against its rule; ConfigError names the value and what is allowed."""

    def refuse() -> None:
        raise ConfigError(f"{key}={_shown(value)} is not allowed: {key} takes {rule.describe()}")

    if value is None:
        if not rule.null and rule.kind != "other":
            refuse()
        return
    if rule.kind == "other":
        return
    if rule.kind == "choice":
        if str(value) not in map(str, rule.allowed()) or isinstance(value, bool):
            refuse()
        return
    if rule.kind == "bool":
        if not isinstance(value, bool):
            refuse()
        return
    if rule.kind == "text":
        if not isinstance(value, str):
            refuse()
        return
    items = list(value) if OmegaConf.is_list(value) or isinstance(value, list) else None
    if rule.kind in ("ints", "floats"):
        if items is None or (rule.nonempty and not items):
            refuse()
    else:
        items = [value]
    whole = rule.kind in ("int", "ints")
    high = rule.at_most if rule.at_most is not None else (INT_MAX if whole else None)
    for item in items:
        if isinstance(item, bool) or not isinstance(item, int | float):
            refuse()
        if whole and not isinstance(item, int):
            refuse()
        if not math.isfinite(item):
            refuse()
        if (
            (rule.at_least is not None and not item >= rule.at_least)
            or (rule.above is not None and not item > rule.above)
            or (rule.below is not None and not item < rule.below)
            or (high is not None and not item <= high)
        ):
            refuse()


def check_rules(cfg: DictConfig, cls: type) -> None:
    """Every setting of a composed config against its rule, in the schema's order."""
    for key in sorted(schema_fields(cls), key=lambda k: k.count(".")):  # wind before env.wind
        rule = rules_of(cls)[key]
        parent = OmegaConf.select(cfg, key.rpartition(".")[0]) if "." in key else cfg
        if parent is None:  # a group left at null (finetune's env, an unused logger)
            continue
        check_value(key, OmegaConf.select(cfg, key, throw_on_missing=False), rule)


def not_applicable(cfg: DictConfig, given: list[str], cls: type = None) -> list[str]:
    """Settings given on the command line that the chosen world or objective does not use."""
    rules = rules_of(cls or Config)
    world = OmegaConf.select(cfg, "env.name")
    objective = OmegaConf.select(cfg, "algo.objective")
    found = []
    for key in dict.fromkeys(given):
        rule = rules.get(key)
        if rule is None:
            continue
        if rule.worlds and world is not None and world not in rule.worlds:
            found.append(f"{key}={_shown(OmegaConf.select(cfg, key))} does not apply to "
                         f"env={world} (only to {', '.join(rule.worlds)})")  # fmt: skip
        elif rule.objectives and objective is not None and objective not in rule.objectives:
            found.append(f"{key}={_shown(OmegaConf.select(cfg, key))} does not apply to "
                         f"algo={cfg.algo.name} (objective {objective}; only to the "
                         f"{', '.join(rule.objectives)} objective)")  # fmt: skip
    return found


def register_configs() -> None:
    ConfigStore.instance().store(name="config_schema", node=Config)
    ConfigStore.instance().store(name="finetune_schema", node=FinetuneConfig)


DEVICES = ("cpu", "cuda", "auto")
NEIGHBOURS = ("auto", "kdtree", "torch")
BACKTRACKING = ("reference", "first_step")


def backtracking_rule(algo_cfg) -> str:
    """The backtracking rule of an ``algo`` config entry; a run started before
    ``algo.backtracking`` existed ran with ``first_step`` and continues with it."""
    value = algo_cfg.get("backtracking") if hasattr(algo_cfg, "get") else None
    return "first_step" if value is None else str(value)


RESTORE = ("parameters", "parameters_and_adam")


def check_device(value: str) -> None:
    """The one check of ``device`` (train, sweep and finetune): a name that means a device,
    and a GPU there when cuda is asked for."""
    import torch

    _one_of("device", value, DEVICES)
    if value == "cuda" and not torch.cuda.is_available():
        raise ConfigError(
            "device='cuda' was asked for but no CUDA GPU is available; use cpu or auto"
        )


def check_precision(value: str, device: str) -> None:
    import torch

    from hmepol_cli import hardware
    from hmepol_cli.precision import bf16_runs_fast_here

    _one_of("precision", value, (*PRECISIONS, "auto"))
    on_cpu = device == "cpu" or (device == "auto" and not torch.cuda.is_available())
    if value != "auto" and PRECISIONS[value].gpu_only and on_cpu:
        raise ConfigError(
            f"precision={value!r} is a GPU precision; on a CPU choose float32, float64, bf16 "
            "or auto"
        )
    if value == "bf16" and on_cpu and not bf16_runs_fast_here("cpu"):
        raise ConfigError(
            "precision='bf16' needs a CPU with bfloat16 units (AVX-512 BF16, AMX or Arm BF16), "
            f"and this one has none: {hardware.describe_cpu()}; its bfloat16 products run on a "
            "slow path (~10x slower than float32): use precision=float32 (or precision=auto)"
        )


def _one_of(key: str, value: object, allowed: tuple[str, ...]) -> None:
    if value not in allowed:
        raise ConfigError(f"{key}={value!r} is not allowed; choose one of: {', '.join(allowed)}")


def _positive(key: str, value: float) -> None:
    if not 0 < value < math.inf:
        raise ConfigError(f"{key}={value!r} must be a finite number > 0")


MAX_WIND = 12.0  # the corridor's side: a stronger wind crosses the whole arena in one step


def check_wind(key: str, value: float | None, allow_none: bool = False) -> None:
    if value is None and allow_none:
        return
    if value is None or not 0 <= value < MAX_WIND:
        raise ConfigError(
            f"{key}={value!r} must be a number >= 0 and < {MAX_WIND:g} (the corridor's side: a "
            "stronger wind crosses the whole arena in one step)"
        )


GYM_KEYS = ("id", "features", "configs", "probs", "projection")


def _check_world_keys(env: DictConfig) -> None:
    """A 2-D world takes none of a Gymnasium world's keys: setting one means nothing there."""
    if env.name == "gym":
        return
    given = [k for k in GYM_KEYS if env.get(k) is not None]
    if env.get("workers"):
        given.append("workers")
    if given:
        raise ConfigError(
            f"{', '.join(f'env.{k}={env.get(k)!r}' for k in given)}: {env.name} takes no "
            f"{'such keys' if len(given) > 1 else 'such key'} (they are for env=gym and its "
            "presets)"
        )


def _check_env_wind(cfg: DictConfig) -> None:
    """The corridor's wind has one key, ``wind``; ``env.wind`` follows it."""
    wind, env_wind = cfg.wind, cfg.env.wind
    if cfg.env.name == "corridor" and env_wind != wind:
        raise ConfigError(
            f"env.wind={env_wind!r} differs from wind={wind!r}: set the corridor's wind with "
            f"wind={env_wind!r} (env.wind follows it)"
        )
    if cfg.env.name != "corridor" and env_wind is not None:
        raise ConfigError(
            f"env.wind={env_wind!r}: {cfg.env.name} has no wind (only the corridor has; set it "
            "with wind=...)"
        )


def parse_bptt(value: str) -> int | None:
    """'full' -> None (whole trajectory), 'n' -> n >= 1."""
    text = str(value).strip().lower()
    if text == "full":
        return None
    if text.isdigit() and int(text) >= 1:
        return int(text)
    raise ConfigError(f"policy.bptt={value!r} is not allowed; use a whole number >= 1 or 'full'")


def validate(cfg: DictConfig) -> None:
    """Refuse values that mean nothing; one line names the value and the rule. Each setting
    against its own rule (:data:`RULES`) first, then the rules that tie settings together."""
    from hmepol_cli.envs import ENVIRONMENTS

    check_rules(cfg, Config)
    check_device(cfg.device)
    check_precision(precision_of(cfg).name, cfg.device)
    if cfg.resume is None:  # a run started before keeps the env.wind it recorded
        _check_env_wind(cfg)
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
    _check_world_keys(cfg.env)
    from hmepol_cli.tracking import check_loggers

    check_loggers(cfg)
    if cfg.seeds is not None and len(set(cfg.seeds)) != len(cfg.seeds):
        raise ConfigError(f"seeds={list(cfg.seeds)} holds a seed twice")
    validate_policy(cfg.policy)
    # Last: a Gymnasium world makes its environments to check their spaces.
    ENVIRONMENTS[cfg.env.name].check_config(cfg.env)


def validate_policy(policy: DictConfig) -> None:
    """The ``policy`` group's values (training and fine-tuning share it)."""
    from hmepol_cli.policies import POLICIES

    _one_of("policy", policy.name, tuple(POLICIES))
    parse_bptt(policy.bptt)
    _one_of("policy.encoder_activation", policy.encoder_activation, ("relu", "tanh"))
    _one_of("policy.init_weights", policy.init_weights, ("xavier", "torch"))
    if not 0 <= policy.init_mean_scale < math.inf:
        raise ConfigError(
            f"policy.init_mean_scale={policy.init_mean_scale!r} must be a finite number >= 0"
        )
    if not math.isfinite(policy.init_log_std):
        raise ConfigError(f"policy.init_log_std={policy.init_log_std!r} must be a finite number")
    if policy.history_size <= 0:
        raise ConfigError(f"policy.history_size={policy.history_size!r} must be > 0")
    for key in ("hidden", "encoder_hidden"):
        sizes = list(policy[key])
        if not all(size > 0 for size in sizes) or (key == "hidden" and not sizes):
            raise ConfigError(f"policy.{key}={sizes!r} must be a list of whole numbers > 0")
