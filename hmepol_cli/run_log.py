"""What a training run writes as it goes: its config, its status, and per-epoch CSVs.

``epochs.csv``: one row per epoch (entropy, objective, per-configuration entropy, IW entropy after
the update, KL, off-policy iterations, backtracks, learning rate, seconds). ``batches.csv``: one
row per mini-batch (epoch, batch, config, entropy). Both are rewritten atomically every epoch, so
a crash never leaves a half-written row for the report, and rows of an epoch that a checkpoint
does not cover are dropped on resume, so every epoch appears exactly once.
"""

from __future__ import annotations

import io
import math
import time
from pathlib import Path

import pandas as pd
from omegaconf import DictConfig, OmegaConf

from hmepol_cli.checkpoint import RUN_CONFIG, RUN_INFO, atomic_write_text, read_json, write_json
from hmepol_cli.envs.base import NavigationWorld

EPOCHS_CSV = "epochs.csv"
BATCHES_CSV = "batches.csv"


class RunLog:
    def __init__(self, run_dir: Path, cfg: DictConfig, world: NavigationWorld) -> None:
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        config_file = self.run_dir / RUN_CONFIG
        if not config_file.exists():
            atomic_write_text(config_file, OmegaConf.to_yaml(cfg, resolve=True))
        free = [world.free_area(c) for c in range(world.n_configs)]
        info_file = self.run_dir / RUN_INFO
        info = read_json(info_file) if info_file.exists() else {"epochs_done": 0}
        info.update(
            status="running",
            env=cfg.env.name,
            algo=cfg.algo.name,
            policy=cfg.policy.name,
            seed=int(cfg.seed),
            wind=getattr(world, "wind", None),  # only worlds with a wind (corridor) have one
            epochs=int(cfg.epochs),
            config_names=list(world.config_names),
            config_probs=list(world.config_probs),
            free_area=free,
            log_free_area=[math.log(f) for f in free],
        )
        write_json(info_file, info)
        self.info = info
        self.epochs = self._read(EPOCHS_CSV)
        self.batches = self._read(BATCHES_CSV)
        self._started = time.time()

    def _read(self, name: str) -> pd.DataFrame:
        path = self.run_dir / name
        return pd.read_csv(path) if path.exists() else pd.DataFrame()

    def truncate(self, next_epoch: int) -> None:
        """Keep only epochs < next_epoch (the ones the checkpoint covers)."""
        if len(self.epochs):
            self.epochs = self.epochs[self.epochs["epoch"] < next_epoch]
        if len(self.batches):
            self.batches = self.batches[self.batches["epoch"] < next_epoch]
        self._flush(next_epoch)

    def append(self, epoch: int, stats, n_configs: int) -> None:
        u = stats.update
        row = {
            "epoch": epoch,
            "entropy": float(stats.entropies.mean()),
            "objective": stats.objective,
        }
        for c in range(n_configs):
            mask = stats.batch_configs == c
            row[f"entropy_c{c}"] = float(stats.entropies[mask].mean()) if mask.any() else math.nan
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
                "config": stats.batch_configs,
                "entropy": stats.entropies,
            }
        )
        self.epochs = pd.concat([self.epochs, pd.DataFrame([row])], ignore_index=True)
        self.batches = pd.concat([self.batches, batches], ignore_index=True)
        self._flush(epoch + 1)

    def _flush(self, epochs_done: int) -> None:
        for name, frame in ((EPOCHS_CSV, self.epochs), (BATCHES_CSV, self.batches)):
            buffer = io.StringIO()
            frame.to_csv(buffer, index=False)
            atomic_write_text(self.run_dir / name, buffer.getvalue())
        self.info["epochs_done"] = epochs_done
        write_json(self.run_dir / RUN_INFO, self.info)

    def finish(self, epochs: int) -> None:
        self.info.update(status="finished", epochs_done=epochs)
        write_json(self.run_dir / RUN_INFO, self.info)
