"""Training runs: a population of members (one run = a population of one) through the epochs of
Algorithm 3.1 (:mod:`hmepol_cli.mepol`), with their run directories, checkpoints and
evaluations. An epoch's statistics leave through one call, :meth:`Trainer.record`: the CSV rows,
the trackers, run.json and the progress bar, after the member's alarms
(:mod:`hmepol_cli.alarms`) have judged them.

Members are runs that differ only in their seed, trained as one batched program
(:mod:`hmepol_cli.population`). Every member has its own run directory, random stream, Adam
state, learning-rate backtracking and trust region; a member whose off-policy loop has stopped
stays where it stopped while the others go on, and a member whose numbers stop being finite
stops there, recorded as failed, while the others go on.
"""

from __future__ import annotations

import logging
import math
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from omegaconf import DictConfig
from tqdm.auto import tqdm

from hmepol_cli import blas, mepol
from hmepol_cli.alarms import MemberAlarms
from hmepol_cli.envs import make_world
from hmepol_cli.errors import RunDirError
from hmepol_cli.evaluation import evaluate_and_save
from hmepol_cli.members import check_members
from hmepol_cli.policies import make_policy
from hmepol_cli.population import PolicyPopulation, PopulationAdam
from hmepol_cli.precision import precision_of
from hmepol_cli.records import EpochStats, epoch_rows
from hmepol_cli.run import (
    CHECKPOINT,
    EVAL_DIR,
    FINAL_EVAL,
    RunDirectory,
    RunTables,
    epoch_checkpoint,
    flat_config,
    load_checkpoint,
    save_checkpoint,
    training_tables,
    writing,
)
from hmepol_cli.seeding import (
    get_device,
    keep_freed_memory,
    make_generator,
    set_random_seed,
)
from hmepol_cli.settings import OffPolicySettings
from hmepol_cli.tracking import MemberTracking, population_group, scalars_of

log = logging.getLogger("hmepol")


@dataclass
class Member:
    """One run of the population: its config, directory, random stream, alarms and files."""

    cfg: DictConfig
    run_dir: Path
    generator: torch.Generator
    directory: RunDirectory
    alarms: MemberAlarms  # when its numbers stop it, and when they warn
    log: RunTables | None = None  # while the directory is open
    start_epoch: int = 0
    failure: str | None = None  # why it stopped, when its numbers stopped making sense
    tracking: MemberTracking | None = None  # TensorBoard, W&B, MLflow (logger=[...])


class Trainer:
    """Trains a population of runs that differ only in member-scalar keys (the seed, the wind,
    the learning rate, ...: :mod:`hmepol_cli.members`); owns their run directories."""

    def __init__(
        self,
        cfgs: DictConfig | list[DictConfig],
        run_dirs: Path | str | list[Path | str],
    ) -> None:
        cfgs = [cfgs] if isinstance(cfgs, DictConfig) else list(cfgs)
        run_dirs = [run_dirs] if isinstance(run_dirs, str | Path) else list(run_dirs)
        if len(cfgs) != len(run_dirs) or not cfgs:
            raise ValueError("one run directory per member config, and at least one member")
        check_members(cfgs)  # they may differ only in member-scalar keys (hmepol_cli/members.py)
        self.cfg = cfg = cfgs[0]  # what the members share: the program
        self.device = get_device(cfg.device)
        self.precision = precision = precision_of(cfg)  # auto: what this machine chose
        self.dtype = precision.dtype
        if self.device.type == "cuda":
            torch.set_float32_matmul_precision(precision.matmul)
        keep_freed_memory()
        self.world = make_world(cfg.env).for_members([c.env for c in cfgs])
        self.world = self.world.to(self.device, self.dtype)
        policies = []
        for member_cfg in cfgs:
            set_random_seed(member_cfg.seed)  # each member's initial weights, as its own run
            policies.append(make_policy(cfg.policy, self.world.state_dim, self.world.action_dim))
        # Who runs the float32 layer products (auto: the faster at an epoch's shape, here)
        self.blas, self.blas_reason = blas.configure(
            str(cfg.get("blas", "auto")),
            self.device.type,
            self.dtype,
            int(cfg.algo.trajectories) * int(cfg.algo.horizon) // int(cfg.algo.batch_size),
            blas.widest_layer(policies[0]),
        )
        vectorize = {"auto": "auto", "on": True, "off": False}[cfg.vmap]
        self.population = PolicyPopulation(policies, vectorize).to(self.device, self.dtype)
        self.optimizer = PopulationAdam(self.population.params)
        self.members = [
            Member(c, Path(d), make_generator(self.device, c.seed), RunDirectory(Path(d), c),
                   MemberAlarms(cfg.alarms, Path(d), c.seed, cfg.algo.lr_backtrack_tries),
                   tracking=MemberTracking(c, Path(d)))
            for c, d in zip(cfgs, run_dirs, strict=True)
        ]  # fmt: skip
        self.settings = OffPolicySettings.from_config(
            cfg, self.population.history_size, cfgs, precision
        )
        # Captured rollouts (CUDA graphs), one per shape: on a GPU the step loop's ~100 small
        # kernels a step cost more in launches than in work.
        self.graphs: dict | None = {} if cfg.cuda_graphs and self.device.type == "cuda" else None

    @property
    def size(self) -> int:
        return len(self.members)

    # ------------------------------------------------------------------ checkpoints
    def save(self, s: int, next_epoch: int) -> None:
        """Member s's checkpoint after ``next_epoch`` epochs; kept apart as well every
        ``checkpoint.keep_every`` epochs (fine-tuning can start from any of them)."""
        member = self.members[s]
        state = {
            "epoch": next_epoch,
            "policy": self.population.member_state_dict(s),
            "optimizer": self.optimizer.member_state_dict(s),
            "generator": member.generator.get_state(),
            "state_dim": self.world.state_dim,
            "action_dim": self.world.action_dim,
            # Digests of each epoch's CSV rows: a resume checks the files against them.
            "tables": {name: list(d) for name, d in member.log.digests.items()},
        }
        save_checkpoint(member.run_dir / CHECKPOINT, state)
        keep_every = int(self.cfg.checkpoint.keep_every)
        if keep_every and next_epoch % keep_every == 0:
            save_checkpoint(member.run_dir / epoch_checkpoint(next_epoch), state)

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
            # The rows the checkpoint covers, checked; the ones it does not cover, dropped.
            member.log.verify(member.start_epoch, state.get("tables"))
            restored.append(s)
        return restored

    # ------------------------------------------------------------------ the run directories
    def record_world(self) -> None:
        """Each member's tables, and what its run.json says about the world and the run."""
        free = [self.world.free_area(c) for c in range(self.world.n_configurations)]
        for s, member in enumerate(self.members):
            member.log = training_tables(member.run_dir)
            member.directory.update(
                env=self.cfg.env.name,
                algo=member.cfg.algo.name,
                policy=self.cfg.policy.name,
                seed=int(member.cfg.seed),
                **{"wind": None, "env_id": None, **self.world.facts(s)},
                epochs=int(self.cfg.epochs),
                precision=self.precision.name,
                blas=self.blas,
                backtracking=self.settings.backtracking,  # the rule it ran with, for the report
                epochs_done=int(member.directory.info().get("epochs_done", 0)),
                config_names=list(self.world.configuration_names),
                config_probs=list(self.world.configuration_probs),
                free_area=free,
                log_free_area=[math.log(f) for f in free],
            )

    def _last_finite(self, directory: RunDirectory) -> dict[str, float]:
        member = next(m for m in self.members if m.directory is directory)
        return {} if member.log is None else member.log.last_finite

    # ------------------------------------------------------------------ the epochs
    def train(self, resume: bool = False) -> list[Path]:
        """Train every member to ``epochs`` (from its checkpoint when ``resume``), evaluate the
        final policies, and leave each directory finished or failed. -> the run directories"""
        directories = [m.directory for m in self.members]
        try:
            with writing(directories, self.device, last=self._last_finite):
                self.record_world()
                if resume:
                    for s in self.restore():
                        member = self.members[s]
                        print(f"hmepol: resuming {member.run_dir} at epoch {member.start_epoch}")
                self.start_tracking()
                self._epochs()
                survivors = [m for m in self.members if m.failure is None]
                if survivors:
                    self.save_evaluation(FINAL_EVAL)
                for member in survivors:
                    member.directory.update(status="finished", epochs_done=int(self.cfg.epochs))
        finally:
            self.close()
        return [m.run_dir for m in self.members]

    def start_tracking(self) -> None:
        """Open each member's tracking runs (continuing the ones its run.json names) and log
        the epochs its CSV holds that a crash kept from them."""
        group = population_group([m.run_dir for m in self.members])
        names = list(self.world.configuration_names)
        for member in self.members:
            if not member.tracking.trackers:
                continue
            info = member.directory.info()
            logged = int(info.get("logged_through", -1))
            provenance = info.get("provenance", {})
            tags = {k: provenance.get(k) for k in ("hmepol", "git_commit", "host", "device")}
            params = {k: v for k, v in flat_config(member.cfg).items() if v is not None}
            state = member.tracking.start(
                member.run_dir.name, group, params, tags, info.get("tracking", {}), logged
            )
            member.tracking.catch_up(member.log["epochs.csv"].to_dict("records"), logged, names)
            member.directory.update(tracking=state, logged_through=member.start_epoch - 1)

    def close(self) -> None:
        """Close the tracking runs; release what the world holds (a Gymnasium world's
        environments and processes)."""
        for member in self.members:
            member.tracking.close()
        self.world.close()

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
            self.record(epoch, due, self.epoch(due), bar)
            done = epoch + 1
            if cfg.eval.every and done % cfg.eval.every == 0 and done < cfg.epochs:
                self.save_evaluation(f"epoch_{done:04d}", epoch)
        bar.close()

    def record(
        self, epoch: int, due: Sequence[int], stats: Sequence[EpochStats], bar: tqdm
    ) -> None:
        """The one way an epoch's statistics leave the trainer. Each member's alarms judge its
        stats: a member they stop is recorded as failed; every other gets its CSV rows, its
        checkpoint, its trackers' scalars and its run.json, then the alarms' warnings. Last, the
        progress bar shows them all."""
        notes = []
        for s, member_stats in zip(due, stats, strict=True):
            member = self.members[s]
            own = {name: p[s] for name, p in self.population.params.items()}
            member.failure = member.alarms.failure(epoch, member_stats, own)
            if member.failure:
                member.directory.fail(member.failure, epoch=epoch, last=member.log.last_finite)
                log.error("%s: %s", member.run_dir, member.failure)
                notes.append(member.alarms.failed_note())
                continue
            diverged = member.alarms.diverged(member_stats)
            epochs, batches, steps = epoch_rows(
                epoch, member_stats, diverged, self.world.n_configurations
            )
            member.log.append(epochs=pd.DataFrame([epochs]), batches=batches, steps=steps)
            self.save(s, epoch + 1)
            member.tracking.scalars(epoch, scalars_of(epochs, self.world.configuration_names))
            member.directory.update(epochs_done=epoch + 1, logged_through=epoch)
            note = member.alarms.warn(epoch, member_stats)
            if note:
                notes.append(note)
        bar.set_postfix(
            H=f"{np.mean([st.entropies.mean() for st in stats]):.3f}",
            KL=f"{max(st.update.kl for st in stats):.3g}",
            it=f"{np.mean([st.update.off_iters for st in stats]):.3g}",
            **({"alarm": ", ".join(notes)} if notes else {}),
        )

    def epoch(self, due: list[int] | None = None) -> list[EpochStats]:
        """One epoch of Algorithm 3.1 (:func:`hmepol_cli.mepol.epoch`) for the members ``due``
        (default: all), ``chunk`` members at a time. -> their stats, in that order."""
        due = list(range(self.size)) if due is None else due
        stats = []
        for start in range(0, len(due), self.chunk):
            part = due[start : start + self.chunk]
            generators = [self.members[s].generator for s in part]
            stats += mepol.epoch(
                self.world, self.population, self.optimizer, self.settings, part, generators,
                graphs=self.graphs,
            )  # fmt: skip
        return stats

    @property
    def chunk(self) -> int:
        """Members stepped together (``chunk_members``; 0: all of them on a CPU, as many as fit
        in the GPU's free memory on a GPU). Members are independent: chunks change no number."""
        if self.cfg.get("chunk_members", 0):
            return int(self.cfg.chunk_members)
        if self.device.type != "cuda":
            return self.size
        if not hasattr(self, "_fitting"):
            free, _ = torch.cuda.mem_get_info(self.device)
            need = self.population.bytes_per_member(
                self.settings.trajectories * self.settings.horizon
            )
            self._fitting = max(1, min(self.size, int(0.8 * free // need)))
        return self._fitting

    # ------------------------------------------------------------------ evaluation
    def save_evaluation(self, name: str, epoch: int | None = None) -> list[Path]:
        """Fresh rollouts of every member's policy in every configuration, saved to eval/ (and
        their heatmaps to the trackers, at ``epoch``)."""
        e = self.cfg.eval
        # Generators of their own, so evaluation never shifts the training streams (exact resume).
        generators = [
            make_generator(self.device, zlib.crc32(f"{m.cfg.seed}/{name}".encode()))
            for m in self.members
        ]
        paths = evaluate_and_save(
            self.world,
            self.population,
            [m.run_dir / EVAL_DIR for m in self.members],
            name,
            e.trajectories,
            e.horizon,
            generators,
            plot_trajectories=e.plot_trajectories,
        )
        step = self.cfg.epochs - 1 if epoch is None else epoch
        for member in self.members:
            member.tracking.image(step, "heatmap", member.run_dir / EVAL_DIR / name / "heatmap.png")
        return paths
