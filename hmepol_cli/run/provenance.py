"""What a run is and where it was made: its identity (the config without the keys a
continuation may change, and its hash), the config flattened to hashable values, and the
provenance run.json records (versions, host, CPU, command, the source's git state)."""

from __future__ import annotations

import datetime
import hashlib
import json
import platform
import shlex
import socket
import subprocess
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from omegaconf import DictConfig, OmegaConf

if TYPE_CHECKING:  # imported by provenance() only: the report reads run directories without it
    import torch

SOURCE = Path(__file__).resolve().parents[2]  # the checkout hmepol_cli/ lies in

# Keys a run may change when it is continued: how long and where it runs, not what it is.
RESUMABLE_KEYS = (
    "epochs",
    "device",
    "blas",  # the same numbers to float32 rounding
    "progress",
    "threads",
    "eval.every",
    "eval.plot_trajectories",  # how the pictures are drawn
    "eval.plot_every",  # a key of runs made before trajectories were lines
    "vmap",
    "cuda_graphs",
    "resume",
    "skip_finished",
    "seeds",
    "members",
    "chunk_members",
    "env.workers",  # a Gymnasium world's processes: the same episodes with any count
    "diagnostics",  # what is recorded, not what is computed
    "checkpoint",
    "logger",
)


def flat_config(cfg: DictConfig | dict) -> dict[str, Any]:
    """{"a.b": value} of a config (resolved), lists as tuples: hashable values, so the report can
    group runs by them (a list of keyword sets, env.configs, as tuples of (key, value) pairs)."""
    container = OmegaConf.to_container(cfg, resolve=True) if OmegaConf.is_config(cfg) else cfg

    def walk(node: Any, prefix: str) -> dict[str, Any]:
        if isinstance(node, dict):
            out: dict[str, Any] = {}
            for key, value in node.items():
                out.update(walk(value, f"{prefix}{key}."))
            return out
        return {prefix[:-1]: hashable_value(node)}

    return walk(container, "")


def hashable_value(value: Any) -> Any:
    """Lists as tuples and dicts as sorted (key, value) tuples, all the way down."""
    if isinstance(value, list | tuple):
        return tuple(hashable_value(v) for v in value)
    if isinstance(value, dict):
        return tuple(sorted((str(k), hashable_value(v)) for k, v in value.items()))
    return value


def identity_of(cfg: DictConfig | dict) -> dict[str, Any]:
    """What a run *is*: its config without the keys a continuation may change."""
    return {
        k: v
        for k, v in flat_config(cfg).items()
        if not any(k == r or k.startswith(f"{r}.") for r in RESUMABLE_KEYS)
    }


def identity_hash(cfg: DictConfig | dict) -> str:
    text = json.dumps(identity_of(cfg), sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def identity_differences(started: DictConfig | dict, now: DictConfig | dict) -> list[str]:
    """``key=<started> (now <now>)`` for every key in which two configs' identities differ.

    A key one config lacks and the other holds as null is no difference: a setting added to
    the schema later (such as the Gymnasium world's env.id) is null where it is not used, so a
    run started before it existed continues."""
    a, b = identity_of(started), identity_of(now)
    return [
        f"{k}={a.get(k, '<absent>')!r} (now {b.get(k, '<absent>')!r})"
        for k in sorted(set(a) | set(b))
        if a.get(k) != b.get(k)  # absent and null read alike
    ]


# ------------------------------------------------------------------------------ provenance
def provenance(device: torch.device | str | None = None) -> dict[str, Any]:
    """Where and with what a run is made: versions, source commit, host, CPU, threads, device."""
    import scipy
    import torch

    from hmepol_cli import __version__, hardware

    info: dict[str, Any] = {
        "hmepol": __version__,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "host": socket.gethostname(),
        "cpu": hardware.cpu_model(),
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "threads": torch.get_num_threads(),
        "device": str(device) if device is not None else None,
        "command": " ".join(shlex.quote(a) for a in sys.argv),
    }
    if device is not None and torch.device(device).type == "cuda":
        info["gpu"] = torch.cuda.get_device_name(torch.device(device))
    info.update(_git_state(SOURCE))
    return info


def _git_state(source: Path) -> dict[str, Any]:
    """The commit of the checkout the package runs from, and whether it had changes."""
    if not (source / ".git").exists():
        return {}
    try:
        commit = subprocess.run(
            ["git", "-C", str(source), "rev-parse", "HEAD"],
            capture_output=True, text=True, timeout=5, check=True,
        ).stdout.strip()  # fmt: skip
        changes = subprocess.run(
            ["git", "-C", str(source), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True, text=True, timeout=5, check=True,
        ).stdout.strip()  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return {}
    return {"git_commit": commit, "git_dirty": bool(changes)}


def timestamp() -> str:
    """Now, as run.json, the lock and commands.log record it (ISO 8601, local time zone)."""
    return datetime.datetime.now().astimezone().isoformat(timespec="seconds")
