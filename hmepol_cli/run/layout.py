"""The files of a run directory: the one contract between what runs write and what the report
reads (every module of :mod:`hmepol_cli.run` and the report name them from here).

A run directory holds::

    config.yaml          the resolved config the run started with; never rewritten
    run.json             kind (train | finetune), status (running | finished | failed), for a
                         failure its reason, epoch and last finite values; epochs_done; identity
                         (hash of the config); facts of the world (free areas, edge, world_map);
                         the backtracking rule; a fine-tuning's return_bounds; provenance (the
                         latest invocation's); machines (each machine trained on, from which
                         epoch); the owner. The report reads these instead of the training code
    commands.log         one line per invocation: time, host, pid, command line
    epochs.csv           train: one row per epoch
    batches.csv          train: one row per mini-batch (epoch, batch, config, entropy)
    steps.csv            train, with diagnostics: one row per off-policy step tried
    checkpoints/last.pt  train: policy, optimizer and random state (loaded with weights_only=True)
    checkpoints/epoch_<n>.pt  train, every checkpoint.keep_every epochs: the same after n epochs
    policy.pt            an exported run: its final policy, weights only (no optimizer state)
    eval/<name>.npz      train: positions_c<c>, (n, T + 1, 2) fresh rollouts per configuration
    eval/<name>/*.png    train: heatmaps and trajectory plots
    finetune.csv         finetune: one row per (epoch, configuration, target)
    targets.json         finetune: the target areas

Every file is written to a temporary name and renamed into place (:mod:`hmepol_cli.run.io`), so
a crash leaves the old file or the new one, never half of one; it gets the permissions the umask
gives a new file. One process writes a directory at a time (``RunDirectory`` of
:mod:`hmepol_cli.run.lifecycle` holds its lock, :mod:`hmepol_cli.run.lock`), and a directory
keeps the config it started with: continuing it with another config is refused.
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from hmepol_cli.errors import RunDirError

CONFIG = "config.yaml"
RUN_INFO = "run.json"
COMMANDS = "commands.log"
EPOCHS_CSV = "epochs.csv"
BATCHES_CSV = "batches.csv"
STEPS_CSV = "steps.csv"
FINETUNE_CSV = "finetune.csv"
TARGETS_JSON = "targets.json"
CHECKPOINT = Path("checkpoints") / "last.pt"
FINAL_POLICY = "policy.pt"  # what an export keeps of a checkpoint: the policy's weights
POLICY_KEYS = ("epoch", "policy", "state_dim", "action_dim")


def epoch_checkpoint(epochs: int) -> Path:
    """The checkpoint kept after ``epochs`` epochs (``checkpoint.keep_every``)."""
    return CHECKPOINT.parent / f"epoch_{epochs:04d}.pt"


EVAL_DIR = "eval"
FINAL_EVAL = "final"
LOCK = ".lock"
TEMPORARY_SUFFIX = ".tmp"


def run_config(run_dir: Path) -> DictConfig:
    """The config a run was started with; refuses a folder that is not a run."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise RunDirError(f"run directory {str(run_dir)!r} does not exist or is not a directory")
    if not (run_dir / CONFIG).is_file() or not (run_dir / RUN_INFO).is_file():
        raise RunDirError(
            f"{str(run_dir)!r} is not a hmepol run directory (expected {CONFIG} and {RUN_INFO})"
        )
    return OmegaConf.load(run_dir / CONFIG)
