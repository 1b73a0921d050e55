"""Crash-safe run files: atomic writes, checkpoints loaded without executing code.

Every file the report reads is written to a temporary name in the same folder and moved into
place with ``os.replace``, so a crash leaves either the old file or the new one, never half.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

CHECKPOINT = Path("checkpoints") / "last.pt"
RUN_INFO = "run.json"
RUN_CONFIG = (
    "config.yaml"  # the resolved config a run started with (Hydra's .hydra/ may be overwritten)
)


class RunDirError(ValueError):
    """A path given as a run directory is not one; the CLI prints it as one line."""


def atomic_write_bytes(path: Path, data: bytes) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def write_json(path: Path, data: dict[str, Any]) -> None:
    atomic_write_text(path, json.dumps(data, indent=2, sort_keys=True) + "\n")


def read_json(path: Path) -> dict[str, Any]:
    return json.loads(Path(path).read_text())


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """Save tensors, state dicts and plain Python values atomically."""
    import io

    buffer = io.BytesIO()
    torch.save(state, buffer)
    atomic_write_bytes(path, buffer.getvalue())


def load_checkpoint(path: Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Load a checkpoint with ``weights_only=True``: tensors and plain containers, no code."""
    return torch.load(path, map_location=map_location, weights_only=True)


def run_config(run_dir: Path) -> DictConfig:
    """The composed config a run was started with; refuses a folder that is not a run."""
    run_dir = Path(run_dir)
    config_file = run_dir / RUN_CONFIG
    if not run_dir.is_dir():
        raise RunDirError(f"run directory {str(run_dir)!r} does not exist")
    if not config_file.is_file() or not (run_dir / RUN_INFO).is_file():
        raise RunDirError(
            f"{str(run_dir)!r} is not a hmepol run directory (expected {RUN_CONFIG} and {RUN_INFO})"
        )
    return OmegaConf.load(config_file)


def resolve_checkpoint(path: Path) -> tuple[Path, Path]:
    """(run directory, checkpoint file) from either of them."""
    path = Path(path)
    if path.is_file():
        run_dir = path.parent.parent if path.parent.name == "checkpoints" else path.parent
        return run_dir, path
    run_config(path)  # raises a clear error for a folder that is not a run
    ckpt = path / CHECKPOINT
    if not ckpt.is_file():
        raise RunDirError(f"run directory {str(path)!r} has no checkpoint yet ({CHECKPOINT})")
    return path, ckpt


def load_trained_policy(path: Path, device: str | torch.device = "cpu"):
    """The policy of a run (directory or checkpoint file) and the run's config.

    -> (Policy in eval-ready state on ``device``, DictConfig of the run)
    """
    from hmepol_cli.policies import make_policy

    run_dir, ckpt = resolve_checkpoint(path)
    cfg = run_config(run_dir)
    state = load_checkpoint(ckpt, map_location=device)
    policy = make_policy(cfg.policy, state_dim=state["state_dim"], action_dim=state["action_dim"])
    policy.load_state_dict(state["policy"])
    return policy.to(device), cfg
