"""Fine-tuning runs (thesis 5.2, Fig. 5.9): TRPO on sparse goal-reaching tasks, from a
pre-trained policy or from scratch; in a Gymnasium world, on the environment's own reward and
termination (one task per configuration).

``finetune(cfg)`` runs one TRPO fine-tuning per (configuration, target): the task fixes the
configuration (``config``, or every configuration of the world in turn) and a target area
(``targets`` random ones, or the ``goal`` centres given). Each one starts from a fresh copy of
the initial policy: the pre-trained policy of ``init`` (a run directory or checkpoint file), or
a new ``policy`` when ``init=none``. Every epoch appends one row per (configuration, target) to
``<output dir>/finetune.csv``, rewritten atomically, with the mean undiscounted return of the
epoch's episodes *before* that epoch's update (so epoch 0 is the initial policy).

:func:`check_finetune` refuses every bad value, the targets included, before anything is
written; :func:`finetune` checks again and runs.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from omegaconf import DictConfig, OmegaConf
from tqdm.auto import tqdm

from hmepol_cli import blas
from hmepol_cli.algorithms import SCRATCH
from hmepol_cli.config import check_device, check_wind, parse_bptt, validate_policy
from hmepol_cli.envs import ENVIRONMENTS, World, make_world
from hmepol_cli.envs.base import edge_rule
from hmepol_cli.errors import ConfigError
from hmepol_cli.finetune.task import (
    GoalTask,
    RewardTask,
    TargetError,
    TaskRollout,
    collect_episodes,
    make_tasks,
    recorded_return_bounds,
)
from hmepol_cli.finetune.trpo import TRPO, TRPOSettings, TRPOStep
from hmepol_cli.policies import Policy, make_policy
from hmepol_cli.run import (
    FINETUNE_CSV,
    TARGETS_JSON,
    RunDirectory,
    RunLock,
    RunTables,
    load_trained_policy,
    resolve_checkpoint,
    write_json,
    writing,
)
from hmepol_cli.seeding import get_device, make_generator, set_random_seed

COLUMNS = [
    "epoch", "target", "config", "return", "success_rate", "kl", "init", "algo_init", "seed",
    "config_name", "episode_length", "accepted", "init_epoch", "seconds",
]  # fmt: skip
SCRATCH_ENV = {"name": "slope", "wind": 0.4, "edge": "slide"}  # init=none's world, if none named


@dataclass
class Plan:
    """Everything a fine-tuning needs, checked: the settings, the start, the world, the tasks."""

    settings: TRPOSettings
    pretrained: Policy | None  # None: a fresh policy per task (init=none)
    env: DictConfig  # name, wind
    init_label: str
    algo_init: str
    world: World
    tasks: dict[int, list[GoalTask] | list[RewardTask]]  # configuration -> its tasks
    init_epoch: int | None = None  # epochs of pre-training the start holds


# --------------------------------------------------------------------------- checks
def _count(cfg: DictConfig, key: str) -> None:
    value = cfg[key]
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise ConfigError(f"{key}={value!r} must be a whole number > 0")


def _in(cfg: DictConfig, key: str, low: float, high: float, closed_low: bool = False) -> None:
    value = cfg[key]
    ok = (low <= value if closed_low else low < value) and value <= high
    if not math.isfinite(value) or not ok:
        bracket = "[" if closed_low else "("
        raise ConfigError(f"{key}={value!r} must be a number in {bracket}{low:g}, {high:g}]")


def trpo_settings(cfg: DictConfig, bptt: int | None) -> TRPOSettings:
    """The TRPO settings of a fine-tuning config; one line names a bad value."""
    for key in ("epochs", "episodes", "horizon", "targets", "cg_iters", "line_search_steps"):
        _count(cfg, key)
    for key in ("value_epochs", "value_batch"):
        _count(cfg, key)
    for key in ("gamma", "gae_lambda", "fisher_fraction"):
        _in(cfg, key, 0.0, 1.0)
    _in(cfg, "line_search_shrink", 0.0, 1.0)
    _in(cfg, "max_kl", 0.0, math.inf)
    _in(cfg, "value_lr", 0.0, math.inf)
    _in(cfg, "damping", 0.0, math.inf, closed_low=True)
    hidden = list(cfg.value_hidden)
    if not hidden or not all(h > 0 for h in hidden):
        raise ConfigError(f"value_hidden={hidden!r} must be a list of whole numbers > 0")
    return TRPOSettings.from_config(cfg, bptt)


def _is_scratch(init: object) -> bool:
    return init is None or str(init).strip().lower() in ("none", "null", "", SCRATCH.name)


@dataclass
class Start:
    """Where a fine-tuning starts: the pre-trained policy (None: a fresh one per task) and what
    its run fixes."""

    policy: Policy | None
    env: DictConfig  # name, wind, edge
    init_label: str  # the checkpoint's path, or none
    algo_init: str  # the pre-training algorithm, or scratch
    bptt: int | None
    init_epoch: int | None = None  # epochs of pre-training the checkpoint holds


def initial_policy(cfg: DictConfig, device: torch.device) -> Start:
    """The start of a fine-tuning: ``init`` is a run directory, a checkpoint file,
    ``<run dir>@<epochs>`` (a checkpoint kept with ``checkpoint.keep_every``) or none.

    A pre-trained run gives its world and its ``policy.bptt``, unless the command changes them
    (``env=...``, ``wind=...``, ``policy.bptt=...``; ``policy.bptt`` null keeps the run's)."""
    named = OmegaConf.to_container(cfg.env, resolve=True) if cfg.get("env") else {}
    override = {k: v for k, v in named.items() if v is not None}
    if cfg.get("wind") is not None:
        override["wind"] = cfg.wind
    chosen_bptt = cfg.policy.bptt
    if _is_scratch(cfg.init):
        env = OmegaConf.create({**SCRATCH_ENV, **override})
        bptt = parse_bptt("1" if chosen_bptt is None else chosen_bptt)
        return Start(None, env, "none", SCRATCH.name, bptt)
    text = str(Path(str(cfg.init)).expanduser())
    if not Path(text.rpartition("@")[0] if "@" in text else text).exists():
        raise ConfigError(
            f"init={str(cfg.init)!r} does not exist; give a run directory, checkpoint file, "
            "<run dir>@<epochs> or none"
        )
    run_dir = Path(text.rpartition("@")[0] if "@" in text else text)
    run_dir = run_dir if run_dir.is_dir() else resolve_checkpoint(run_dir)[0]
    holder = RunLock(run_dir).holder()
    if holder is not None and "@" not in text and not cfg.get("allow_running", False):
        raise ConfigError(
            f"init={str(cfg.init)!r} is still being trained (pid {holder['pid']} on "
            f"{holder['host']} since {holder.get('started', '?')}): wait for it, start from a "
            f"kept checkpoint (init={run_dir}@<epochs>), or give allow_running=true"
        )
    policy, run_cfg, epochs = load_trained_policy(text, device=device)
    run_env = OmegaConf.to_container(run_cfg.env, resolve=True) if "env" in run_cfg else {}
    run_env["edge"] = edge_rule(run_env)  # a run from before env.edge ran with the mirror
    if "name" in override and override["name"] != run_env.get("name"):
        run_env = {"wind": run_env.get("wind")}  # another world: only the wind carries over
    env = OmegaConf.create({**SCRATCH_ENV, **{k: v for k, v in run_env.items() if v is not None},
                            **override})  # fmt: skip
    run_bptt = OmegaConf.select(run_cfg, "policy.bptt", default="1")
    bptt = parse_bptt(run_bptt if chosen_bptt is None else chosen_bptt)
    algo = OmegaConf.select(run_cfg, "algo.name", default="unknown")
    label = str(Path(text.partition("@")[0]).resolve()) + (f"@{epochs}" if "@" in text else "")
    return Start(policy, env, label, str(algo), bptt, epochs)


def _configurations(cfg: DictConfig, world: World) -> list[int]:
    if cfg.config is None:
        return list(range(world.n_configurations))
    values = list(cfg.config) if OmegaConf.is_list(cfg.config) else [cfg.config]
    for c in values:
        if isinstance(c, bool) or not isinstance(c, int) or not 0 <= c < world.n_configurations:
            raise ConfigError(
                f"config={c!r} is not a configuration of {world.name}; "
                f"choose 0..{world.n_configurations - 1}, a list of them, or null (all)"
            )
    return [int(c) for c in values]


def _goal(cfg: DictConfig) -> str | list:
    goal = cfg.goal
    if isinstance(goal, str):
        if goal != "random":
            raise ConfigError(
                f"goal={goal!r} is not allowed; use random or a list of [x, y] centres"
            )
        return goal
    points = OmegaConf.to_container(goal) if OmegaConf.is_config(goal) else goal
    if (
        not isinstance(points, list)
        or not points
        or not all(
            isinstance(p, list | tuple)
            and len(p) == 2
            and all(isinstance(v, int | float) and math.isfinite(v) for v in p)
            for p in points
        )
    ):
        raise ConfigError(f"goal={goal!r} is not allowed; use random or a list of [x, y] centres")
    return points


def check_finetune(cfg: DictConfig) -> Plan:
    """Every value of a fine-tuning config checked, the world built and the targets drawn (a
    target outside the free space refused), before anything is written."""
    check_device(cfg.device)
    device = get_device(cfg.device)
    if _is_scratch(cfg.init):
        fresh = cfg.policy.copy()
        if fresh.bptt is None:
            fresh.bptt = "1"
        validate_policy(fresh)
    start = initial_policy(cfg, device)
    pretrained, env, init_label, algo_init = (
        start.policy,
        start.env,
        start.init_label,
        start.algo_init,
    )
    settings = trpo_settings(cfg, start.bptt)
    if env.name not in ENVIRONMENTS:
        raise ConfigError(
            f"env={env.name!r} is not allowed; choose one of: {', '.join(ENVIRONMENTS)}"
        )
    check_wind("wind", env.get("wind"), allow_none=True)
    if cfg.goal_size is not None and not 0 < cfg.goal_size < math.inf:
        raise ConfigError(f"goal_size={cfg.goal_size!r} must be a number > 0 (or null)")
    world = make_world(env).to(device, torch.float32)
    goal = _goal(cfg)
    if not world.maps:
        # A world without a map (a Gymnasium environment) brings its own task: its reward and
        # termination, per configuration.
        if goal != "random":
            raise ConfigError(
                f"goal={goal!r}: a Gymnasium world ({world.facts()['env_id']}) is fine-tuned on "
                "its own reward; leave goal at random (goal, targets and goal_size are for the "
                "2-D worlds)"
            )
        tasks = {c: [RewardTask(c, int(cfg.horizon))] for c in _configurations(cfg, world)}
        return Plan(
            settings, pretrained, env, init_label, algo_init, world, tasks, start.init_epoch
        )
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
            )  # fmt: skip
            for c in _configurations(cfg, world)
        }
    except TargetError as error:
        raise ConfigError(str(error)) from None
    return Plan(settings, pretrained, env, init_label, algo_init, world, tasks, start.init_epoch)


def _output_dir(cfg: DictConfig) -> Path:
    if cfg.get("output_dir"):
        return Path(cfg.output_dir)
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized():
        return Path(HydraConfig.get().runtime.output_dir)
    raise ConfigError("output_dir=None: give output_dir=<folder> when not running under Hydra")


def _run_seed(seed: int, config: int, target: int) -> int:
    """A stream per (seed, configuration, target): each fine-tuning is reproducible alone."""
    return int(np.random.SeedSequence([seed, config, target]).generate_state(1)[0])


# --------------------------------------------------------------------------- the run
def finetune(cfg: DictConfig) -> Path:
    """Fine-tune with TRPO on every (configuration, target). -> the output directory"""
    plan = check_finetune(cfg)
    device = get_device(cfg.device)
    if cfg.get("threads", 0) and cfg.threads > 0:
        torch.set_num_threads(int(cfg.threads))
    choice, reason = blas.configure(
        str(cfg.get("blas", "auto")),
        device.type,
        torch.float32,
        int(cfg.episodes) * int(cfg.horizon),
        _widest(cfg, plan),
    )
    if cfg.progress and str(cfg.get("blas", "auto")) == "auto":
        print(f"hmepol: {reason}")
    out_dir = _output_dir(cfg)
    directory = RunDirectory(out_dir, cfg, kind="finetune")
    with writing([directory], device):
        directory.update(
            env=plan.env.name,
            wind=plan.env.get("wind") if plan.env.name == "corridor" else None,
            algo=plan.algo_init,
            init=plan.init_label,
            init_epoch=plan.init_epoch,
            seed=int(cfg.seed),
            epochs=int(cfg.epochs),
            blas=choice,
            config_names=list(plan.world.configuration_names),
            config_probs=list(plan.world.configuration_probs),
            return_bounds=recorded_return_bounds(plan.world.maps),
            **{key: plan.world.facts().get(key) for key in ("edge", "world_map")},
        )
        write_json(out_dir / TARGETS_JSON, _targets_info(plan))
        tables = RunTables(out_dir, (FINETUNE_CSV,))
        tables.truncate(0)  # a fine-tuning run again starts over
        rows = _run(cfg, plan, device, tables)
        directory.update(status="finished", epochs_done=int(cfg.epochs))
    print(f"hmepol: fine-tuning returns ({len(rows)} rows) written to {out_dir / FINETUNE_CSV}")
    return out_dir


def _widest(cfg: DictConfig, plan: Plan) -> int:
    """The widest layer of the policy fine-tuned (the pre-trained one, or a fresh one's)."""
    if plan.pretrained is not None:
        return blas.widest_layer(plan.pretrained)
    hidden = [*cfg.policy.get("hidden", []), *cfg.policy.get("encoder_hidden", [])]
    return max((int(h) for h in hidden), default=1)


def _run(cfg: DictConfig, plan: Plan, device: torch.device, tables: RunTables) -> list[dict]:
    rows: list[dict] = []
    total = sum(len(t) for t in plan.tasks.values()) * int(cfg.epochs)
    bar = tqdm(
        total=total,
        desc=f"finetune {plan.env.name}/{plan.algo_init}",
        disable=not cfg.progress,
        dynamic_ncols=True,
    )
    world = plan.world
    for c, tasks in plan.tasks.items():
        for k, task in enumerate(tasks):
            run_seed = _run_seed(int(cfg.seed), c, k)
            set_random_seed(run_seed)
            if plan.pretrained is None:
                policy = make_policy(cfg.policy, world.state_dim, world.action_dim)
            else:
                policy = copy.deepcopy(plan.pretrained)
            policy.to(device, torch.float32)
            generator = make_generator(device, run_seed)
            trpo = TRPO(policy, world, task.horizon, plan.settings, generator)
            for epoch in range(int(cfg.epochs)):
                t0 = time.perf_counter()
                rollout = collect_episodes(world, policy, task, int(cfg.episodes), generator)
                step = trpo.update(rollout)
                row = _row(epoch, k, c, world, rollout, step, plan, int(cfg.seed))
                row["seconds"] = time.perf_counter() - t0
                rows.append(row)
                tables.append(finetune=pd.DataFrame([row], columns=COLUMNS))
                bar.update(1)
                bar.set_postfix(config=c, target=k, R=f"{row['return']:.2f}", KL=f"{step.kl:.3g}")
    bar.close()
    return rows


def _row(
    epoch: int,
    target: int,
    config: int,
    world: World,
    rollout: TaskRollout,
    step: TRPOStep,
    plan: Plan,
    seed: int,
) -> dict:
    return {
        "epoch": epoch,
        "target": target,
        "config": config,
        "return": float(rollout.returns.mean()),
        # A Gymnasium world's own task has no target to reach (NaN).
        "success_rate": (
            math.nan if rollout.success is None else float(rollout.succeeded.float().mean())
        ),
        "kl": step.kl,
        "init": plan.init_label,
        "algo_init": plan.algo_init,
        "seed": seed,
        "config_name": world.configuration_names[config],
        "episode_length": float(rollout.lengths.float().mean()),
        "accepted": step.accepted,
        "init_epoch": math.nan if plan.init_epoch is None else plan.init_epoch,
    }


def _targets_info(plan: Plan) -> dict:
    return {
        "env": OmegaConf.to_container(plan.env, resolve=True),
        "init": plan.init_label,
        "algo_init": plan.algo_init,
        "targets": [
            {
                "config": c,
                "config_name": plan.world.configuration_names[c],
                "target": k,
                "box": (  # no target area in a Gymnasium world's own task
                    None
                    if t.target is None
                    else [t.target.x0, t.target.y0, t.target.x1, t.target.y1]
                ),
            }
            for c, ts in plan.tasks.items()
            for k, t in enumerate(ts)
        ],
    }
