"""The trust-region, off-policy loop of Mepol, alpha-Mepol and HMepol (thesis Algorithm 3.1, 4.2.3).

Per epoch: draw N trajectories in mini-batches of B (one configuration each), search neighbours
once, then repeat gradient ascent on the objective over the importance-weighted mini-batch
entropies (eq. 2.7) while the kNN estimate of the KL (eq. 2.8) between the sampling policy and
the updated one stays within delta, at most ``max_off_iters`` times. When the very first step
already leaves the trust region the learning rate is divided by ``backtrack_coeff`` and the step
retried, as Mepol does; a later step that leaves it is undone and ends the epoch.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig
from tqdm.auto import tqdm

from hmepol_cli import estimators
from hmepol_cli.checkpoint import CHECKPOINT, load_checkpoint, save_checkpoint
from hmepol_cli.config import parse_bptt
from hmepol_cli.envs import make_world
from hmepol_cli.evaluation import evaluate_and_save
from hmepol_cli.objectives import objective
from hmepol_cli.policies import make_policy
from hmepol_cli.rollout import Rollout, collect, draw_configs
from hmepol_cli.run_log import RunLog
from hmepol_cli.seeding import DTYPES, get_device, make_generator, set_random_seed


@dataclass
class UpdateResult:
    entropies: torch.Tensor  # (M,) IW entropies of the accepted policy
    kl: float
    off_iters: int
    backtracks: int
    lr: float


@dataclass
class EpochStats:
    entropies: np.ndarray  # (M,) on-policy kNN entropy of each mini-batch (eq. 2.6)
    batch_configs: np.ndarray  # (M,) configuration of each mini-batch
    objective: float
    update: UpdateResult
    history_max: float = 0.0  # largest |h'_t| of the rollout: a diverging recursion shows here
    floor_share: float = 0.0  # share of particles whose ball volume hit the estimator's floor
    seconds: dict[str, float] = field(default_factory=dict)


class Trainer:
    """Trains one policy in one world with one estimator; owns its run directory's files."""

    def __init__(self, cfg: DictConfig, run_dir: Path) -> None:
        self.cfg, self.run_dir = cfg, Path(run_dir)
        self.device = get_device(cfg.device)
        self.dtype = DTYPES[cfg.dtype]
        keep_freed_memory()
        set_random_seed(cfg.seed)
        self.world = make_world(cfg.env).to(self.device, self.dtype)
        self.policy = make_policy(cfg.policy, self.world.state_dim, self.world.action_dim)
        self.policy.to(self.device, self.dtype)
        self.optimizer = torch.optim.Adam(self.policy.parameters(), lr=cfg.algo.lr)
        self.generator = make_generator(self.device, cfg.seed)
        self.bptt = parse_bptt(cfg.policy.bptt)
        self.log = RunLog(self.run_dir, cfg, self.world)
        self.start_epoch = 0

    # ------------------------------------------------------------------ checkpoints
    def save(self, next_epoch: int) -> None:
        save_checkpoint(
            self.run_dir / CHECKPOINT,
            {
                "epoch": next_epoch,
                "policy": self.policy.state_dict(),
                "optimizer": self.optimizer.state_dict(),
                "generator": self.generator.get_state(),
                "state_dim": self.world.state_dim,
                "action_dim": self.world.action_dim,
            },
        )

    def restore(self) -> bool:
        """Continue from the last checkpoint if there is one. -> whether one was loaded."""
        path = self.run_dir / CHECKPOINT
        if not path.is_file():
            return False
        state = load_checkpoint(path, map_location=self.device)
        self.policy.load_state_dict(state["policy"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.generator.set_state(state["generator"].cpu())
        self.start_epoch = int(state["epoch"])
        self.log.truncate(self.start_epoch)  # rows of an epoch the checkpoint does not cover
        return True

    # ------------------------------------------------------------------ Algorithm 3.1
    def train(self) -> Path:
        cfg = self.cfg
        bar = tqdm(
            range(self.start_epoch, cfg.epochs),
            initial=self.start_epoch,
            total=cfg.epochs,
            desc=f"{cfg.env.name}/{cfg.algo.name}",
            disable=not cfg.progress,
            dynamic_ncols=True,
        )
        for epoch in bar:
            stats = self.epoch()
            self.log.append(epoch, stats, self.world.n_configs)
            self.save(epoch + 1)
            bar.set_postfix(
                H=f"{stats.entropies.mean():.3f}",
                KL=f"{stats.update.kl:.3g}",
                it=stats.update.off_iters,
            )
            if cfg.eval.every and (epoch + 1) % cfg.eval.every == 0 and epoch + 1 < cfg.epochs:
                self.evaluate(f"epoch_{epoch + 1:04d}")
        bar.close()
        self.evaluate("final")
        self.log.finish(cfg.epochs)
        return self.run_dir

    def epoch(self) -> EpochStats:
        a = self.cfg.algo
        t0 = time.perf_counter()
        configs = draw_configs(self.world, a.trajectories, a.batch_size, self.generator)
        rollout = collect(self.world, self.policy, configs, a.horizon, self.generator)
        t1 = time.perf_counter()
        particles = estimators.particles_by_batch(rollout.particles, a.batch_size)
        neighbours = estimators.nearest_neighbours(
            particles, self.cfg.estimator.k, self.cfg.estimator.neighbours
        )
        entropies = estimators.knn_entropy(neighbours, self.cfg.estimator.eps)
        t2 = time.perf_counter()
        update = self.trust_region_update(rollout, neighbours)
        t3 = time.perf_counter()
        return EpochStats(
            entropies=entropies.double().cpu().numpy(),
            batch_configs=configs[:: a.batch_size].cpu().numpy(),
            objective=float(objective(entropies, a.objective, a.alpha)),
            update=update,
            history_max=float(rollout.histories.abs().max()) if rollout.histories.numel() else 0.0,
            floor_share=float(estimators.floor_share(neighbours, self.cfg.estimator.eps)),
            seconds={
                "collect": t1 - t0,
                "neighbours": t2 - t1,
                "update": t3 - t2,
                "epoch": t3 - t0,
            },
        )

    def trust_region_update(
        self, rollout: Rollout, neighbours: estimators.Neighbours
    ) -> UpdateResult:
        a, policy, optimizer = self.cfg.algo, self.policy, self.optimizer

        def evaluate(behaviour: torch.Tensor | None = None) -> tuple[torch.Tensor, ...]:
            """-> (IW entropies (M,), KL, objective, target log-likelihoods (N, T))."""
            target = policy.log_prob(rollout.inputs, rollout.actions, rollout.histories, self.bptt)
            behaviour = target.detach() if behaviour is None else behaviour
            weights = estimators.importance_weights(target - behaviour, a.batch_size)
            entropies = estimators.iw_entropy(weights, neighbours, self.cfg.estimator.eps)
            kl = estimators.kl_divergence(weights, neighbours).mean()
            return entropies, kl, objective(entropies, a.objective, a.alpha), target.detach()

        lr = a.lr
        _set_lr(optimizer, lr)
        accepted = _snapshot(policy, optimizer)
        # The sampling policy's likelihoods (same bptt mode) are the behaviour: ratio 1 at start.
        entropies, kl, value, behaviour = evaluate()
        result = UpdateResult(entropies.detach(), 0.0, 0, 0, lr)
        while result.off_iters < a.max_off_iters:
            optimizer.zero_grad(set_to_none=True)
            (-value).backward()
            optimizer.step()
            entropies, kl, value, _ = evaluate(behaviour)
            in_region = (kl <= a.kl_threshold) & torch.isfinite(value)
            # One host sync per iteration: on a GPU the loop waits for the device only here.
            step_kept, kl_value = torch.stack((in_region.to(kl.dtype), kl.detach())).tolist()
            if step_kept:
                accepted = _snapshot(policy, optimizer)
                result = UpdateResult(
                    entropies.detach(), kl_value, result.off_iters + 1, result.backtracks, lr
                )
                continue
            _load_snapshot(policy, optimizer, accepted)
            if result.off_iters > 0 or result.backtracks >= a.backtrack_tries:
                break
            lr /= a.backtrack_coeff  # the first step overshot: backtrack on the learning rate
            _set_lr(optimizer, lr)
            result.backtracks += 1
            result.lr = lr
            entropies, kl, value, _ = evaluate(behaviour)
        _set_lr(optimizer, a.lr)
        return result

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, name: str) -> Path:
        e = self.cfg.eval
        # A generator of its own, so evaluation never shifts the training stream (exact resume).
        generator = make_generator(self.device, zlib.crc32(f"{self.cfg.seed}/{name}".encode()))
        return evaluate_and_save(
            self.world,
            self.policy,
            self.run_dir / "eval",
            name,
            e.trajectories,
            e.horizon,
            generator,
            plot_trajectories=e.plot_trajectories,
            plot_every=e.plot_every,
        )


def _set_lr(optimizer: torch.optim.Optimizer, lr: float) -> None:
    for group in optimizer.param_groups:
        group["lr"] = lr


def _snapshot(policy: torch.nn.Module, optimizer: torch.optim.Optimizer) -> tuple[dict, dict]:
    return _clone(policy.state_dict()), _clone(optimizer.state_dict())


def _load_snapshot(
    policy: torch.nn.Module, optimizer: torch.optim.Optimizer, snap: tuple[dict, dict]
) -> None:
    policy.load_state_dict(snap[0])
    # load_state_dict keeps the given tensors, which Adam then updates in place: hand it a copy.
    optimizer.load_state_dict(_clone(snap[1]))


def _clone(state):
    """A copy of a (nested) state dict with every tensor cloned; cheaper than copy.deepcopy."""
    if isinstance(state, torch.Tensor):
        return state.detach().clone()
    if isinstance(state, dict):
        return {key: _clone(value) for key, value in state.items()}
    if isinstance(state, list):
        return [_clone(value) for value in state]
    return state


def keep_freed_memory() -> None:
    """Let glibc's malloc keep large freed blocks for reuse instead of handing them back.

    An off-policy iteration allocates and frees activations of ~100 MB (80,000 particles x 300
    units). By default glibc serves blocks that large with mmap and unmaps them when freed, so
    every iteration pays the page faults of fresh memory again: an iteration then takes ~1.1-1.5x
    as long (README, Speed). Raising the mmap and trim thresholds keeps those pages in the heap.
    Process-wide, idempotent, and a no-op where the C library has no ``mallopt``.
    """
    try:
        mallopt = ctypes.CDLL(ctypes.util.find_library("c")).mallopt
    except (OSError, AttributeError, TypeError):
        return
    m_trim_threshold, m_mmap_threshold = -1, -3  # <malloc.h>
    mallopt(m_mmap_threshold, 1 << 30)
    mallopt(m_trim_threshold, (1 << 31) - 1)
