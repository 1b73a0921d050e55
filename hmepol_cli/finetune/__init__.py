"""Fine-tuning (thesis 5.2, Fig. 5.9): TRPO on sparse goal-reaching tasks, from a pre-trained
policy or from scratch.

``finetune(cfg)`` runs one TRPO fine-tuning per (configuration, target): the task fixes the
configuration (``config``, or every configuration of the world in turn) and a target area
(``targets`` random ones, or the ``goal`` centres given). Each one starts from a fresh copy of
the initial policy: the pre-trained policy of ``init`` (a run directory or checkpoint file), or
a new ``policy`` when ``init=none``. Every epoch appends one row per (configuration, target) to
``<output_dir>/finetune.csv``, rewritten atomically, with the mean undiscounted return of the
epoch's episodes *before* that epoch's update (so epoch 0 is the initial policy).
"""

from __future__ import annotations

import copy
import io
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from omegaconf import DictConfig, OmegaConf
from tqdm.auto import tqdm

from hmepol_cli.checkpoint import RUN_INFO, atomic_write_text, load_trained_policy, write_json
from hmepol_cli.config import ConfigError
from hmepol_cli.envs import ENVIRONMENTS, NavigationWorld, make_world
from hmepol_cli.finetune.task import GoalTask, TargetError, make_tasks
from hmepol_cli.finetune.trpo import TRPO, GoalRollout, TRPOSettings, UpdateStats, collect_goal
from hmepol_cli.policies import Policy, make_policy
from hmepol_cli.seeding import get_device, make_generator, set_random_seed

FINETUNE_CSV = "finetune.csv"
TARGETS_JSON = "targets.json"
COLUMNS = [
    "epoch", "target", "config", "return", "success_rate", "kl", "init", "algo_init", "seed",
    "config_name", "episode_length", "accepted", "seconds",
]  # fmt: skip
SCRATCH = "scratch"
DEFAULT_ENV = {"name": "slope", "wind": 0.4}  # the env of a scratch run that names none


# --------------------------------------------------------------------------- settings
def _positive(cfg: DictConfig, key: str, integer: bool = False) -> None:
    value = cfg[key]
    ok = isinstance(value, int) if integer else isinstance(value, (int, float))
    if isinstance(value, bool) or not ok or not value > 0:
        kind = "a whole number" if integer else "a number"
        raise ConfigError(f"{key}={value!r} must be {kind} > 0")


def parse_bptt(value: object) -> int | None:
    """1 (default, thesis) | n | 'full' -> None."""
    text = str(value).strip().lower()
    if text in ("full", "none", "null"):
        return None
    if text.isdigit() and int(text) >= 1:
        return int(text)
    raise ConfigError(f"bptt={value!r} is not allowed; use a whole number >= 1 or 'full'")


def trpo_settings(cfg: DictConfig) -> TRPOSettings:
    """Check every fine-tuning key that needs no world; one-line errors name the bad value."""
    for key in (
        "epochs",
        "episodes",
        "horizon",
        "targets",
        "cg_iters",
        "backtrack_iters",
        "value_epochs",
        "value_batch",
    ):
        _positive(cfg, key, integer=True)
    for key in ("max_kl", "value_lr"):
        _positive(cfg, key)
    for key in ("gamma", "gae_lambda", "backtrack_coeff", "fisher_fraction"):
        value = cfg[key]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value <= 1:
            raise ConfigError(f"{key}={value!r} must be a number in (0, 1]")
    if (
        isinstance(cfg.damping, bool)
        or not isinstance(cfg.damping, (int, float))
        or cfg.damping < 0
    ):
        raise ConfigError(f"damping={cfg.damping!r} must be a number >= 0")
    if cfg.device not in ("cpu", "cuda", "auto"):
        raise ConfigError(f"device={cfg.device!r} is not allowed; choose one of: cpu, cuda, auto")
    goal = cfg.goal
    if isinstance(goal, str):
        if goal != "random":
            raise ConfigError(
                f"goal={goal!r} is not allowed; use 'random' or a list of [x, y] centres"
            )
    else:
        points = OmegaConf.to_container(goal) if OmegaConf.is_config(goal) else goal
        if not points or not all(
            isinstance(p, (list, tuple))
            and len(p) == 2
            and all(isinstance(v, (int, float)) for v in p)
            for p in points
        ):
            raise ConfigError(
                f"goal={goal!r} is not allowed; use 'random' or a list of [x, y] centres"
            )
    if cfg.goal_size is not None and not (
        isinstance(cfg.goal_size, (int, float)) and cfg.goal_size > 0
    ):
        raise ConfigError(
            f"goal_size={cfg.goal_size!r} must be a number > 0 (or null: 0.1 x arena side)"
        )
    hidden = list(cfg.value_hidden)
    if not all(isinstance(h, int) and h > 0 for h in hidden):
        raise ConfigError(f"value_hidden={hidden!r} must be a list of whole numbers > 0")
    return TRPOSettings(
        gamma=float(cfg.gamma),
        gae_lambda=float(cfg.gae_lambda),
        max_kl=float(cfg.max_kl),
        cg_iters=int(cfg.cg_iters),
        damping=float(cfg.damping),
        backtrack_iters=int(cfg.backtrack_iters),
        backtrack_coeff=float(cfg.backtrack_coeff),
        value_lr=float(cfg.value_lr),
        value_epochs=int(cfg.value_epochs),
        value_batch=int(cfg.value_batch),
        value_hidden=tuple(hidden),
        normalize_advantage=bool(cfg.normalize_advantage),
        bptt=parse_bptt(cfg.bptt),
        fisher_fraction=float(cfg.fisher_fraction),
    )


def _is_scratch(init: object) -> bool:
    return init is None or str(init).strip().lower() in ("none", "null", "", SCRATCH)


def initial_policy(
    cfg: DictConfig, device: torch.device
) -> tuple[Policy | None, DictConfig, str, str]:
    """(pre-trained policy or None for scratch, env config, init label, algo_init)."""
    override = {k: v for k, v in (cfg.get("env") or {}).items() if v is not None}
    if _is_scratch(cfg.init):
        env = OmegaConf.create({**DEFAULT_ENV, **override})
        return None, env, "none", SCRATCH
    init_path = Path(str(cfg.init)).expanduser()
    if not init_path.exists():
        raise ConfigError(
            f"init={str(cfg.init)!r} does not exist; give a run directory, checkpoint file or none"
        )
    policy, run_cfg = load_trained_policy(init_path, device=device)
    run_env = (
        OmegaConf.to_container(run_cfg.env, resolve=True) if "env" in run_cfg else dict(DEFAULT_ENV)
    )
    if "name" in override and override["name"] != run_env.get("name"):
        run_env = {
            "wind": run_env.get("wind", DEFAULT_ENV["wind"])
        }  # another world: keep only the wind
    env = OmegaConf.create({**DEFAULT_ENV, **run_env, **override})
    algo = OmegaConf.select(run_cfg, "algo.name", default="unknown")
    return policy, env, str(init_path.resolve()), str(algo)


def _output_dir(cfg: DictConfig) -> Path:
    if cfg.get("output_dir"):
        return Path(cfg.output_dir)
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized():
        return Path(HydraConfig.get().runtime.output_dir)
    raise ConfigError("output_dir=None: give output_dir=<folder> when not running under Hydra")


def _configs(cfg: DictConfig, world: NavigationWorld) -> list[int]:
    if cfg.config is None:
        return list(range(world.n_configs))
    values = cfg.config if OmegaConf.is_list(cfg.config) else [cfg.config]
    for c in values:
        if isinstance(c, bool) or not isinstance(c, int) or not 0 <= c < world.n_configs:
            raise ConfigError(
                f"config={c!r} is not a configuration of {world.name}; "
                f"choose 0..{world.n_configs - 1} or null (all)"
            )
    return [int(c) for c in values]


def _run_seed(seed: int, config: int, target: int) -> int:
    """A stream per (seed, configuration, target): each fine-tuning is reproducible alone."""
    return int(np.random.SeedSequence([seed, config, target]).generate_state(1)[0])


# --------------------------------------------------------------------------- the run
def finetune(cfg: DictConfig) -> Path:
    """Fine-tune with TRPO on every (configuration, target); -> the output directory."""
    settings = trpo_settings(cfg)
    device = get_device(cfg.device)
    if cfg.get("threads", 0) and cfg.threads > 0:
        torch.set_num_threads(int(cfg.threads))
    pretrained, env_cfg, init_label, algo_init = initial_policy(cfg, device)
    if env_cfg.name not in ENVIRONMENTS:
        raise ConfigError(
            f"env.name={env_cfg.name!r} is not allowed; choose one of: {', '.join(ENVIRONMENTS)}"
        )
    if env_cfg.get("wind") is not None and env_cfg.wind < 0:
        raise ConfigError(f"env.wind={env_cfg.wind!r} must be a number >= 0")
    if pretrained is None and cfg.get("policy") is None:
        raise ConfigError(
            "policy=None: init=none trains a fresh policy; choose policy=markov or recursive"
        )
    world = make_world(env_cfg).to(device, torch.float32)
    configs = _configs(cfg, world)
    goal = cfg.goal if isinstance(cfg.goal, str) else OmegaConf.to_container(cfg.goal)
    try:
        tasks = {
            c: make_tasks(
                world,
                c,
                int(cfg.horizon),
                goal,
                int(cfg.targets),
                int(cfg.goal_seed),
                cfg.goal_size,
            )
            for c in configs
        }
    except TargetError as error:
        raise ConfigError(str(error)) from None

    out_dir = _output_dir(cfg)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / TARGETS_JSON, _targets_info(world, tasks, env_cfg, init_label, algo_init))
    info = {
        "kind": "finetune",
        "status": "running",
        "env": env_cfg.name,
        "wind": float(env_cfg.get("wind") or 0.0),
        "algo": algo_init,
        "init": init_label,
        "seed": int(cfg.seed),
        "epochs": int(cfg.epochs),
        "config_names": list(world.config_names),
        "config_probs": list(world.config_probs),
    }
    write_json(out_dir / RUN_INFO, info)
    csv_path = out_dir / FINETUNE_CSV
    rows: list[dict] = []
    total = sum(len(t) for t in tasks.values()) * int(cfg.epochs)
    bar = tqdm(
        total=total,
        desc=f"finetune {env_cfg.name}/{algo_init}",
        disable=not cfg.progress,
        dynamic_ncols=True,
    )
    for c in configs:
        for k, task in enumerate(tasks[c]):
            run_seed = _run_seed(int(cfg.seed), c, k)
            set_random_seed(run_seed)
            if pretrained is None:
                policy = make_policy(cfg.policy, world.state_dim, world.action_dim)
            else:
                policy = copy.deepcopy(pretrained)
            policy.to(device, torch.float32)
            generator = make_generator(device, run_seed)
            trpo = TRPO(policy, world, task.horizon, settings, generator)
            for epoch in range(int(cfg.epochs)):
                t0 = time.perf_counter()
                rollout = collect_goal(world, policy, task, int(cfg.episodes), generator)
                stats = trpo.update(rollout)
                row = _row(epoch, k, c, world, rollout, stats, init_label, algo_init, int(cfg.seed))
                row["seconds"] = time.perf_counter() - t0
                rows.append(row)
                _write_csv(csv_path, rows)
                bar.update(1)
                bar.set_postfix(config=c, target=k, R=f"{row['return']:.2f}", KL=f"{stats.kl:.3g}")
    bar.close()
    write_json(out_dir / RUN_INFO, {**info, "status": "finished"})
    print(f"hmepol: fine-tuning returns written to {csv_path}")
    return out_dir


def _row(
    epoch: int,
    target: int,
    config: int,
    world: NavigationWorld,
    rollout: GoalRollout,
    stats: UpdateStats,
    init: str,
    algo_init: str,
    seed: int,
) -> dict:
    return {
        "epoch": epoch,
        "target": target,
        "config": config,
        "return": float(rollout.returns.mean()),
        "success_rate": float(rollout.succeeded.float().mean()),
        "kl": stats.kl,
        "init": init,
        "algo_init": algo_init,
        "seed": seed,
        "config_name": world.config_names[config],
        "episode_length": float(rollout.lengths.float().mean()),
        "accepted": stats.accepted,
    }


def _write_csv(path: Path, rows: list[dict]) -> None:
    buffer = io.StringIO()
    pd.DataFrame(rows, columns=COLUMNS).to_csv(buffer, index=False)
    atomic_write_text(path, buffer.getvalue())


def _targets_info(
    world: NavigationWorld,
    tasks: dict[int, list[GoalTask]],
    env_cfg: DictConfig,
    init: str,
    algo_init: str,
) -> dict:
    return {
        "env": OmegaConf.to_container(env_cfg, resolve=True),
        "init": init,
        "algo_init": algo_init,
        "targets": [
            {
                "config": c,
                "config_name": world.config_names[c],
                "target": k,
                "box": [t.target.x0, t.target.y0, t.target.x1, t.target.y1],
            }
            for c, ts in tasks.items()
            for k, t in enumerate(ts)
        ],
    }


__all__ = [
    "FINETUNE_CSV",
    "GoalTask",
    "TRPO",
    "TRPOSettings",
    "collect_goal",
    "finetune",
    "initial_policy",
    "make_tasks",
    "trpo_settings",
]
