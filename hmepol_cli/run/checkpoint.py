"""Checkpoints: saved atomically, loaded with ``weights_only=True`` (tensors and plain
containers, no code), found from a run directory, a file or ``<run>@<epochs>``, and the trained
policy a checkpoint holds."""

from __future__ import annotations

import io
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hmepol_cli.errors import RunDirError
from hmepol_cli.run.io import atomic_write_bytes
from hmepol_cli.run.layout import CHECKPOINT, FINAL_POLICY, epoch_checkpoint, run_config

if TYPE_CHECKING:  # torch is imported where a checkpoint is written or read: the report,
    import torch  # which imports this package for the run directory's contract, needs none


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """Save tensors, state dicts and plain Python values atomically."""
    import torch

    buffer = io.BytesIO()
    torch.save(state, buffer)
    atomic_write_bytes(path, buffer.getvalue())


def load_checkpoint(path: Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Load a checkpoint with ``weights_only=True``: tensors and plain containers, no code.

    A file that is not one (corrupt, truncated, or holding anything but weights) is refused in
    one line that names it."""
    import torch

    try:
        with warnings.catch_warnings():  # torch's notes on foreign pickles: the refusal says it
            warnings.simplefilter("ignore")
            state = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as error:  # torch raises several unpickling and zip errors
        reason = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise RunDirError(
            f"{path} cannot be loaded as a hmepol checkpoint ({type(error).__name__}: "
            f"{reason[:120]})"
        ) from None
    if not isinstance(state, dict):
        raise RunDirError(f"{path} is not a hmepol checkpoint (it holds a {type(state).__name__})")
    return state


def resolve_checkpoint(path: Path | str) -> tuple[Path, Path]:
    """(run directory, checkpoint file) from a run directory, a checkpoint file, or
    ``<run directory>@<epoch>``: the checkpoint kept after that many epochs. An exported run
    without its checkpoints gives its final policy (policy.pt)."""
    text = str(path)
    run, at, epoch = text.rpartition("@") if "@" in text else (text, "", "")
    path = Path(run)
    if at:
        if not epoch.isdigit():
            raise RunDirError(f"{text!r}: after '@' give a number of epochs, e.g. {run}@100")
        run_config(path)
        checkpoint = path / epoch_checkpoint(int(epoch))
        if not checkpoint.is_file():
            kept = sorted(p.stem.removeprefix("epoch_") for p in (path / CHECKPOINT.parent).glob(
                "epoch_*.pt"))  # fmt: skip
            have = ", ".join(str(int(k)) for k in kept) or "none (run with checkpoint.keep_every=n)"
            raise RunDirError(
                f"{run!r} kept no checkpoint after {int(epoch)} epochs; it has: {have}"
            )
        return path, checkpoint
    if path.is_file():
        run_dir = path.parent.parent if path.parent.name == CHECKPOINT.parent.name else path.parent
        return run_dir, path
    run_config(path)  # a clear error for a folder that is not a run
    checkpoint = path / CHECKPOINT
    if not checkpoint.is_file() and (path / FINAL_POLICY).is_file():
        return path, path / FINAL_POLICY
    if not checkpoint.is_file():
        raise RunDirError(f"run directory {str(path)!r} has no checkpoint yet ({CHECKPOINT})")
    return path, checkpoint


def load_trained_policy(path: Path | str, device: str | torch.device = "cpu"):
    """The policy of a run (directory, checkpoint file, or ``<run>@<epochs>``), the run's
    config and the number of epochs the checkpoint holds.

    -> (Policy on ``device``, DictConfig of the run, epochs)"""
    from hmepol_cli.policies import make_policy

    run_dir, checkpoint = resolve_checkpoint(path)
    cfg = run_config(run_dir)
    state = load_checkpoint(checkpoint, map_location=device)
    try:
        policy = make_policy(cfg.policy, state["state_dim"], state["action_dim"])
        policy.load_state_dict(state["policy"])
    except (KeyError, RuntimeError) as error:
        reason = str(error).splitlines()[0][:120]
        raise RunDirError(
            f"{checkpoint} does not hold the policy its run describes ({reason})"
        ) from None
    return policy.to(device), cfg, int(state.get("epoch", -1))
