"""The trust-region, off-policy loop of Mepol, alpha-Mepol and HMepol (thesis Algorithm 3.1, 4.2.3).

Per epoch: draw N trajectories in mini-batches of B (one configuration each), search neighbours
once, then repeat gradient ascent on the objective over the importance-weighted mini-batch
entropies (eq. 2.7) while the kNN estimate of the KL (eq. 2.8) between the sampling policy and
the updated one stays within delta, at most ``max_off_iters`` times. When the very first step
already leaves the trust region the learning rate is divided by ``lr_backtrack_factor`` and the
step retried, as Mepol does; a later step that leaves it is undone and ends the epoch.

The trainer runs a *population*: runs that differ only in their seed, as one batched program
(:mod:`hmepol_cli.population`). Every member has its own run directory, random stream, Adam
state, learning-rate backtracking and trust region; a member whose off-policy loop has stopped
stays where it stopped while the others go on. A single run is a population of one.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import math
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from omegaconf import DictConfig
from tqdm.auto import tqdm

from hmepol_cli import estimators
from hmepol_cli.config import parse_bptt
from hmepol_cli.envs import make_world
from hmepol_cli.errors import RunDirError
from hmepol_cli.evaluation import evaluate_and_save
from hmepol_cli.objectives import objective
from hmepol_cli.policies import make_policy
from hmepol_cli.population import PolicyPopulation, PopulationAdam, Snapshot
from hmepol_cli.rollout import Rollout, collect, draw_configurations
from hmepol_cli.rundir import (
    CHECKPOINT,
    EVAL_DIR,
    FINAL_EVAL,
    EpochLog,
    RunDirectory,
    load_checkpoint,
    save_checkpoint,
)
from hmepol_cli.seeding import DTYPES, get_device, make_generator, set_random_seed

log = logging.getLogger("hmepol")


@dataclass
class UpdateResult:
    """One member's off-policy loop in one epoch."""

    entropies: np.ndarray  # (M,) IW entropies of the accepted policy
    kl: float  # KL of the accepted policy (the one the trust region judged by)
    off_iters: int
    backtracks: int
    lr: float


@dataclass
class EpochStats:
    """One member's epoch."""

    entropies: np.ndarray  # (M,) on-policy kNN entropy of each mini-batch (eq. 2.6)
    batch_configurations: np.ndarray  # (M,) configuration of each mini-batch
    objective: float
    update: UpdateResult
    history_max: float = 0.0  # largest |h'_t| of the rollout: a diverging recursion shows here
    action_max: float = 0.0  # largest |a_t| drawn (before clipping): diverging means show here
    floor_share: float = 0.0  # share of particles whose ball volume hit the estimator's floor
    diverged: bool = False  # |h'| or |a| past the alarm bounds
    seconds: dict[str, float] = field(default_factory=dict)
    broken: list[str] = field(default_factory=list)  # non-finite in the rollout: the member stops


@dataclass
class Member:
    """One run of the population: its config, directory, random stream and files."""

    cfg: DictConfig
    run_dir: Path
    generator: torch.Generator
    directory: RunDirectory
    log: EpochLog | None = None  # while the directory is open
    start_epoch: int = 0
    failure: str | None = None  # why it stopped, when its numbers stopped making sense
    stalled_for: int = 0  # consecutive epochs in which no off-policy step was accepted


class Trainer:
    """Trains a population of runs that differ only in their seed; owns their run directories."""

    def __init__(
        self,
        cfgs: DictConfig | list[DictConfig],
        run_dirs: Path | str | list[Path | str],
    ) -> None:
        cfgs = [cfgs] if isinstance(cfgs, DictConfig) else list(cfgs)
        run_dirs = [run_dirs] if isinstance(run_dirs, str | Path) else list(run_dirs)
        if len(cfgs) != len(run_dirs) or not cfgs:
            raise ValueError("one run directory per member config, and at least one member")
        self.cfg = cfg = cfgs[0]  # what the members share: everything but the seed
        self.device = get_device(cfg.device)
        self.dtype = DTYPES[cfg.dtype]
        if self.device.type == "cuda":
            torch.set_float32_matmul_precision(cfg.matmul_precision)
        keep_freed_memory()
        self.world = make_world(cfg.env).to(self.device, self.dtype)
        policies = []
        for member_cfg in cfgs:
            set_random_seed(member_cfg.seed)  # each member's initial weights, as its own run
            policies.append(make_policy(cfg.policy, self.world.state_dim, self.world.action_dim))
        vectorize = {"auto": "auto", "on": True, "off": False}[cfg.vmap]
        self.population = PolicyPopulation(policies, vectorize).to(self.device, self.dtype)
        self.optimizer = PopulationAdam(self.population.params)
        self.members = [
            Member(c, Path(d), make_generator(self.device, c.seed), RunDirectory(Path(d), c))
            for c, d in zip(cfgs, run_dirs, strict=True)
        ]
        self.bptt = parse_bptt(cfg.policy.bptt)
        # Captured rollouts (CUDA graphs), one per shape: on a GPU the step loop's ~100 small
        # kernels a step cost more in launches than in work.
        self.graphs: dict | None = {} if cfg.cuda_graphs and self.device.type == "cuda" else None
        self.exact_kl = cfg.algo.trust_region == "exact" and self.population.history_size > 0

    @property
    def size(self) -> int:
        return len(self.members)

    # ------------------------------------------------------------------ checkpoints
    def save(self, s: int, next_epoch: int) -> None:
        member = self.members[s]
        save_checkpoint(
            member.run_dir / CHECKPOINT,
            {
                "epoch": next_epoch,
                "policy": self.population.member_state_dict(s),
                "optimizer": self.optimizer.member_state_dict(s),
                "generator": member.generator.get_state(),
                "state_dim": self.world.state_dim,
                "action_dim": self.world.action_dim,
            },
        )

    def restore(self) -> list[int]:
        """Continue every member from its last checkpoint, if it has one (directories open).

        -> the members that were restored."""
        restored = []
        for s, member in enumerate(self.members):
            path = member.run_dir / CHECKPOINT
            if not path.is_file():
                member.log.truncate(0)  # rows written before a first checkpoint are not kept
                continue
            state = load_checkpoint(path, map_location=self.device)
            try:
                self.population.load_member_state_dict(s, state["policy"])
                self.optimizer.load_member_state_dict(s, state["optimizer"])
                member.generator.set_state(state["generator"].cpu())
                member.start_epoch = int(state["epoch"])
            except (KeyError, TypeError, RuntimeError) as error:
                raise RunDirError(
                    f"{path} does not match the run's policy and optimizer "
                    f"({str(error).splitlines()[0][:100]}); it cannot be resumed"
                ) from None
            member.log.truncate(member.start_epoch)  # rows the checkpoint does not cover
            restored.append(s)
        return restored

    # ------------------------------------------------------------------ the run directories
    def open(self) -> None:
        """Lock every member's directory, check its config, record the world's facts."""
        opened = []
        try:
            for member in self.members:
                member.directory.open(self.device)
                opened.append(member)
                member.log = EpochLog(member.run_dir)
                free = [self.world.free_area(c) for c in range(self.world.n_configurations)]
                member.directory.update(
                    env=self.cfg.env.name,
                    algo=self.cfg.algo.name,
                    policy=self.cfg.policy.name,
                    seed=int(member.cfg.seed),
                    wind=getattr(self.world, "wind", None),  # worlds with a wind (corridor)
                    env_id=getattr(self.world, "env_id", None),  # a Gymnasium world's id
                    epochs=int(self.cfg.epochs),
                    epochs_done=int(member.directory.info().get("epochs_done", 0)),
                    config_names=list(self.world.configuration_names),
                    config_probs=list(self.world.configuration_probs),
                    free_area=free,
                    log_free_area=[math.log(f) for f in free],
                )
        except BaseException:
            for member in opened:
                member.directory.close()
            raise

    def close(self) -> None:
        for member in self.members:
            member.directory.close()
        self.world.close()  # a Gymnasium world's environments and worker processes

    # ------------------------------------------------------------------ Algorithm 3.1
    def train(self, resume: bool = False) -> list[Path]:
        """Train every member to ``epochs`` (from its checkpoint when ``resume``), evaluate the
        final policies, and leave each directory finished or failed. -> the run directories"""
        self.open()
        try:
            if resume:
                for s in self.restore():
                    member = self.members[s]
                    print(f"hmepol: resuming {member.run_dir} at epoch {member.start_epoch}")
            self._epochs()
            survivors = [m for m in self.members if m.failure is None]
            if survivors:
                self.save_evaluation(FINAL_EVAL)
            for member in survivors:
                member.directory.update(status="finished", epochs_done=int(self.cfg.epochs))
        except BaseException as error:
            reason = f"{type(error).__name__}: {error}".splitlines()[0][:300]
            if isinstance(error, KeyboardInterrupt):
                reason = "interrupted (KeyboardInterrupt)"
            for member in self.members:
                if member.failure is None and member.log is not None:
                    member.directory.fail(reason, last=member.log.last_finite)
            raise
        finally:
            self.close()
        return [m.run_dir for m in self.members]

    @property
    def failures(self) -> dict[Path, str]:
        """Members that stopped because their numbers stopped making sense: run dir -> why."""
        return {m.run_dir: m.failure for m in self.members if m.failure is not None}

    def _epochs(self) -> None:
        cfg = self.cfg
        first = min(m.start_epoch for m in self.members)
        label = f"{cfg.env.name}/{cfg.algo.name}" + (f" x{self.size}" if self.size > 1 else "")
        bar = tqdm(
            range(first, cfg.epochs),
            initial=first,
            total=cfg.epochs,
            desc=label,
            disable=not cfg.progress,
            dynamic_ncols=True,
        )
        for epoch in bar:
            # Members restored at a later epoch (a crash between two members' checkpoints)
            # sit out the epochs they already have; failed members stay where they stopped.
            due = [
                s
                for s, m in enumerate(self.members)
                if m.start_epoch <= epoch and m.failure is None
            ]
            if not due:
                break
            stats = self.epoch(due)
            notes = []
            for s, member_stats in zip(due, stats, strict=True):
                note = self._record(s, epoch, member_stats)
                if note:
                    notes.append(note)
            bar.set_postfix(
                H=f"{np.mean([st.entropies.mean() for st in stats]):.3f}",
                KL=f"{max(st.update.kl for st in stats):.3g}",
                it=f"{np.mean([st.update.off_iters for st in stats]):.3g}",
                **({"alarm": ", ".join(notes)} if notes else {}),
            )
            done = epoch + 1
            if cfg.eval.every and done % cfg.eval.every == 0 and done < cfg.epochs:
                self.save_evaluation(f"epoch_{done:04d}")
        bar.close()

    def _record(self, s: int, epoch: int, stats: EpochStats) -> str | None:
        """Write member s's epoch, or stop it if a number is not finite. -> a note for the bar"""
        member, alarms = self.members[s], self.cfg.alarms
        broken = stats.broken or self._non_finite(s, stats)
        if broken:
            member.failure = (
                f"non-finite {', '.join(broken)} at epoch {epoch}: the run stopped there"
            )
            member.directory.fail(member.failure, epoch=epoch, last=member.log.last_finite)
            log.error("%s: %s", member.run_dir, member.failure)
            return f"seed {member.cfg.seed} failed"
        member.log.append(*_epoch_rows(epoch, stats, self.world.n_configurations))
        self.save(s, epoch + 1)
        member.directory.update(epochs_done=epoch + 1)
        if stats.diverged:
            self._warn_divergence(s, epoch, stats)
        member.stalled_for = member.stalled_for + 1 if stats.update.off_iters == 0 else 0
        if member.stalled_for >= alarms.stall_epochs:
            log.warning(
                "%s: no off-policy step accepted for %d epochs (to epoch %d): the trust region "
                "rejects every step even after %d learning-rate halvings",
                member.run_dir,
                member.stalled_for,
                epoch,
                self.cfg.algo.lr_backtrack_tries,
            )
            return f"seed {member.cfg.seed} stalled"
        return "diverging" if stats.diverged else None

    def _non_finite(self, s: int, stats: EpochStats) -> list[str]:
        """The quantities of member s's epoch that are not finite, by name."""
        params = self.population.params
        checks = {
            "entropy": bool(np.isfinite(stats.entropies).all()),
            "KL": math.isfinite(stats.update.kl),
            "history": math.isfinite(stats.history_max),
            "actions": math.isfinite(stats.action_max),
            "log-std": bool(torch.isfinite(params["log_std"][s]).all()),
            "policy weights": all(bool(torch.isfinite(v[s]).all()) for v in params.values()),
        }
        return [name for name, ok in checks.items() if not ok]

    def epoch(self, due: list[int] | None = None) -> list[EpochStats]:
        """One epoch of the members ``due`` (default: all). -> their stats, in that order.

        A member whose rollout holds a non-finite position, action or history stops here:
        its stats name what broke (``broken``) and it takes no update."""
        a = self.cfg.algo
        due = list(range(self.size)) if due is None else due
        members = torch.tensor(due, device=self.device)
        generators = [self.members[s].generator for s in due]
        t0 = time.perf_counter()
        configurations = torch.stack(
            [draw_configurations(self.world, a.trajectories, a.batch_size, g) for g in generators]
        )  # (S', N)
        selection = None if len(due) == self.size else members
        rollout = collect(
            self.world,
            self.population,
            selection,
            configurations,
            a.horizon,
            generators,
            graphs=self.graphs,
        )
        configs_host = configurations[:, :: a.batch_size].cpu().numpy()
        broken = _broken_rows(rollout)
        if broken:
            healthy = [i for i in range(len(due)) if i not in broken]
            rows = torch.tensor(healthy, dtype=torch.long, device=self.device)
            rollout = _rollout_rows(rollout, rows)
            members = members.index_select(0, rows)
        t1 = time.perf_counter()
        stats = self._epoch_of(rollout, members, t0, t1) if len(members) else []
        by_row = iter(stats)
        out = []
        for i in range(len(due)):
            if i in broken:
                out.append(_broken_stats(broken[i], configs_host[i]))
            else:
                stat = next(by_row)
                stat.batch_configurations = configs_host[i]
                out.append(stat)
        return out

    def _epoch_of(
        self, rollout: Rollout, members: torch.Tensor, t0: float, t1: float
    ) -> list[EpochStats]:
        """Neighbours, entropies and the update of the members of a rollout."""
        a, e = self.cfg.algo, self.cfg.estimator
        n = len(members)
        # The entropy is on the world's chosen features of the states (a Gymnasium world's
        # env.features; the whole position in the 2-D worlds).
        features = self.world.entropy_features(rollout.particles)
        particles = estimators.particles_by_batch(features.flatten(0, 1), a.batch_size)
        neighbours = estimators.nearest_neighbours(particles, e.k, e.neighbours)  # (S' M, P, k)
        entropies = estimators.knn_entropy(neighbours, e.eps).view(n, -1)  # (S', M)
        t2 = time.perf_counter()
        updates = self.trust_region_update(members, rollout, neighbours)
        t3 = time.perf_counter()
        seconds = {"collect": t1 - t0, "neighbours": t2 - t1, "update": t3 - t2, "epoch": t3 - t0}
        # One transfer for every per-member statistic.
        alarms = self.cfg.alarms
        history_max = _amax_per_member(rollout.histories)
        action_max = _amax_per_member(rollout.actions)
        floor = estimators.floor_share(neighbours, e.eps, per_batch=True).view(n, -1)
        objectives = objective(entropies, a.objective, a.alpha)
        host = torch.stack(
            [
                history_max.double(),
                action_max.double(),
                floor.mean(-1).double(),
                objectives.double(),
            ]
        ).cpu()
        entropies_host = entropies.double().cpu().numpy()
        stats = []
        for i in range(n):
            h_max, a_max, floor_i, objective_i = host[:, i].tolist()
            stats.append(
                EpochStats(
                    entropies=entropies_host[i],
                    batch_configurations=np.zeros(0),
                    objective=objective_i,
                    update=updates[i],
                    history_max=h_max,
                    action_max=a_max,
                    floor_share=floor_i,
                    diverged=h_max > alarms.history_bound or a_max > alarms.action_bound,
                    seconds=seconds,
                )
            )
        return stats

    def trust_region_update(
        self, members: torch.Tensor, rollout: Rollout, neighbours: estimators.Neighbours
    ) -> list[UpdateResult]:
        """The off-policy loop of every member in ``members`` (S',), as one batched program.

        Each member keeps its own learning rate, backtracks and stopping point; gradients are
        those of each member's own objective (the members' objectives share no parameters).
        """
        a, eps = self.cfg.algo, self.cfg.estimator.eps
        population, optimizer = self.population, self.optimizer
        params = population.params
        n_sel = len(members)
        m_batches = neighbours.radius.shape[0] // n_sel
        row_of = {int(s): i for i, s in enumerate(members.tolist())}  # member -> row of rollout

        def estimate(rows: torch.Tensor, behaviour: torch.Tensor | None = None):
            """The objective of the members in rollout rows ``rows``.

            -> (IW entropies (R, M), KL (R,), objective (R,), likelihoods (R, N, T))."""
            inputs = rollout.inputs.index_select(0, rows)
            actions = rollout.actions.index_select(0, rows)
            histories = rollout.histories.index_select(0, rows)
            who = members.index_select(0, rows)
            alive = None if rollout.alive is None else rollout.alive.index_select(0, rows)
            target = population.log_prob(who, inputs, actions, histories, self.bptt)
            behaviour = target.detach() if behaviour is None else behaviour.index_select(0, rows)
            nb = _select_batches(neighbours, rows, m_batches)
            weights = estimators.importance_weights(
                _live(target - behaviour, alive).flatten(0, 1), a.batch_size
            )
            entropies = estimators.iw_entropy(weights, nb, eps).view(len(rows), -1)
            if self.exact_kl:
                # The guard the one-step likelihoods lack: the KL of the same step computed from
                # likelihoods over the whole history, against the exact sampling likelihoods.
                with torch.no_grad():
                    exact = population.log_prob(who, inputs, actions, histories, None)
                    sampling = rollout.log_probs.index_select(0, rows)
                    exact_w = estimators.importance_weights(
                        _live(exact - sampling, alive).flatten(0, 1), a.batch_size
                    )
                    kl = estimators.kl_divergence(exact_w, nb).view(len(rows), -1).mean(-1)
            else:
                kl = estimators.kl_divergence(weights, nb).view(len(rows), -1).mean(-1)
            return entropies, kl, objective(entropies, a.objective, a.alpha), target.detach()

        def gradients(value: torch.Tensor) -> dict[str, torch.Tensor]:
            """Gradient of -objective of each member (they share no parameter: one backward)."""
            grads = torch.autograd.grad(-value.sum(), list(params.values()), allow_unused=True)
            return {
                k: torch.zeros_like(v) if g is None else g
                for (k, v), g in zip(params.items(), grads, strict=True)
            }

        size = population.size
        in_epoch = torch.zeros(size, dtype=torch.bool, device=self.device)
        in_epoch[members] = True
        lr = torch.full((size,), float(a.lr), dtype=torch.float64, device=self.device)
        off_iters, backtracks = [0] * size, [0] * size
        all_rows = torch.arange(n_sel, device=self.device)
        entropies, kl, value, behaviour = estimate(all_rows)
        grads = gradients(value)
        result_entropies = entropies.detach().double().cpu().numpy()
        result_kl = [0.0] * n_sel
        snapshot = Snapshot(population, optimizer, grads)
        active = in_epoch & (a.max_off_iters > 0)
        while bool(active.any()):
            optimizer.step(grads, lr, active)
            stepped = active.nonzero()[:, 0]
            rows = torch.tensor([row_of[int(s)] for s in stepped.tolist()], device=self.device)
            entropies, kl, value, _ = estimate(rows, behaviour)
            new_grads = gradients(value)
            stepped_mask = torch.zeros(size, dtype=torch.bool, device=self.device)
            stepped_mask[stepped] = True
            grads = {
                k: torch.where(stepped_mask.view((-1,) + (1,) * (g.dim() - 1)), new_grads[k], g)
                for k, g in grads.items()
            }
            in_region = (kl <= a.kl_threshold) & torch.isfinite(value)
            # One host sync per iteration: on a GPU the loop waits for the device only here.
            flags, kl_values = torch.stack((in_region.to(kl.dtype), kl.detach())).tolist()
            accepted = torch.zeros(size, dtype=torch.bool, device=self.device)
            rejected = torch.zeros(size, dtype=torch.bool, device=self.device)
            accepted_rows = []
            for i, s in enumerate(stepped.tolist()):
                if flags[i]:
                    accepted[s] = True
                    off_iters[s] += 1
                    result_kl[row_of[s]] = kl_values[i]
                    accepted_rows.append((i, row_of[s]))
                    if off_iters[s] >= a.max_off_iters:
                        active[s] = False
                    continue
                rejected[s] = True
                if off_iters[s] > 0 or backtracks[s] >= a.lr_backtrack_tries:
                    active[s] = False
                else:  # the first step overshot: backtrack on the learning rate
                    lr[s] /= a.lr_backtrack_factor
                    backtracks[s] += 1
            if accepted_rows:
                kept = entropies.detach().double().cpu().numpy()
                for i, row in accepted_rows:
                    result_entropies[row] = kept[i]
            snapshot.take(population, optimizer, grads, accepted)
            snapshot.restore(population, optimizer, grads, rejected)
        lr_host = lr.tolist()
        return [
            UpdateResult(
                entropies=result_entropies[row_of[s]],
                kl=result_kl[row_of[s]],
                off_iters=off_iters[s],
                backtracks=backtracks[s],
                lr=lr_host[s],
            )
            for s in members.tolist()
        ]

    # ------------------------------------------------------------------ evaluation
    def save_evaluation(self, name: str) -> list[Path]:
        """Fresh rollouts of every member's policy in every configuration, saved to eval/."""
        e = self.cfg.eval
        # Generators of their own, so evaluation never shifts the training streams (exact resume).
        generators = [
            make_generator(self.device, zlib.crc32(f"{m.cfg.seed}/{name}".encode()))
            for m in self.members
        ]
        return evaluate_and_save(
            self.world,
            self.population,
            [m.run_dir / EVAL_DIR for m in self.members],
            name,
            e.trajectories,
            e.horizon,
            generators,
            plot_trajectories=e.plot_trajectories,
            plot_every=e.plot_every,
        )

    def _warn_divergence(self, s: int, epoch: int, stats: EpochStats) -> None:
        alarms = self.cfg.alarms
        log.warning(
            "%s: epoch %d: the policy is diverging: max |h'| = %.3g (alarms.history_bound = %g), "
            "max |a| = %.3g (alarms.action_bound = %g)",
            self.members[s].run_dir,
            epoch,
            stats.history_max,
            alarms.history_bound,
            stats.action_max,
            alarms.action_bound,
        )


def _epoch_rows(epoch: int, stats: EpochStats, n_configurations: int) -> tuple[dict, pd.DataFrame]:
    """One member's epoch as its epochs.csv row and batches.csv rows."""
    u = stats.update
    row = {"epoch": epoch, "entropy": float(stats.entropies.mean()), "objective": stats.objective}
    for c in range(n_configurations):
        drawn = stats.batch_configurations == c
        row[f"entropy_c{c}"] = float(stats.entropies[drawn].mean()) if drawn.any() else math.nan
    row.update(
        entropy_iw=float(u.entropies.mean()),
        kl=u.kl,
        off_iters=u.off_iters,
        backtracks=u.backtracks,
        lr=u.lr,
        history_max=stats.history_max,
        action_max=stats.action_max,
        diverged=stats.diverged,
        floor_share=stats.floor_share,
        seconds=stats.seconds["epoch"],
        collect_seconds=stats.seconds["collect"],
        neighbours_seconds=stats.seconds["neighbours"],
        update_seconds=stats.seconds["update"],
        wall_time=time.time(),
    )
    batches = pd.DataFrame(
        {
            "epoch": epoch,
            "batch": range(len(stats.entropies)),
            "config": stats.batch_configurations,
            "entropy": stats.entropies,
        }
    )
    return row, batches


def _broken_rows(rollout: Rollout) -> dict[int, list[str]]:
    """Rows (members) of a rollout holding non-finite positions, actions or histories, with
    their names. One transfer."""
    checks = {"positions": rollout.states, "actions": rollout.actions, "history": rollout.histories}
    finite = torch.stack(
        [
            torch.isfinite(v).flatten(1).all(dim=1)
            if v.numel()
            else torch.ones(v.shape[0], dtype=torch.bool, device=v.device)
            for v in checks.values()
        ]
    ).cpu()  # (3, S')
    names = list(checks)
    return {
        i: [names[j] for j in range(len(names)) if not finite[j, i]]
        for i in range(finite.shape[1])
        if not finite[:, i].all()
    }


def _rollout_rows(rollout: Rollout, rows: torch.Tensor) -> Rollout:
    """The members of a rollout in ``rows``."""
    return Rollout(
        **{
            k: v.index_select(0, rows) if isinstance(v, torch.Tensor) else v
            for k, v in vars(rollout).items()
        }
    )


def _broken_stats(names: list[str], configurations: np.ndarray) -> EpochStats:
    nan = np.full(len(configurations), math.nan)
    return EpochStats(
        entropies=nan,
        batch_configurations=configurations,
        objective=math.nan,
        update=UpdateResult(nan, math.nan, 0, 0, math.nan),
        history_max=math.nan,
        action_max=math.nan,
        broken=names,
    )


def _live(log_ratios: torch.Tensor, alive: torch.Tensor | None) -> torch.Tensor:
    """Log-ratios of the actions that moved the state: an action drawn after the environment
    ended its episode (Gymnasium worlds) changes no particle, so it counts in no weight.
    (S', N, T), alive (S', N, T) bool or None (every step counts)."""
    if alive is None:
        return log_ratios
    return torch.where(alive, log_ratios, torch.zeros_like(log_ratios))


def _amax_per_member(values: torch.Tensor) -> torch.Tensor:
    """Largest |value| of each member's slice. (S', ...) -> (S',)"""
    if values.numel() == 0:
        return torch.zeros(values.shape[0], device=values.device, dtype=values.dtype)
    return values.abs().flatten(1).amax(dim=1)


def _select_batches(
    neighbours: estimators.Neighbours, rows: torch.Tensor, m_batches: int
) -> estimators.Neighbours:
    """The mini-batches of some members: neighbours of (S' M) mini-batches -> (R M)."""
    if len(rows) * m_batches == neighbours.radius.shape[0]:
        return neighbours
    idx = neighbours.indices.view(-1, m_batches, *neighbours.indices.shape[1:])
    radius = neighbours.radius.view(-1, m_batches, neighbours.radius.shape[-1])
    return estimators.Neighbours(
        indices=idx.index_select(0, rows).flatten(0, 1),
        radius=radius.index_select(0, rows).flatten(0, 1),
        dim=neighbours.dim,
    )


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
