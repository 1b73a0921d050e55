"""Shared fixtures: a float64 slope world and tiny policies of every kind."""

from __future__ import annotations

import pytest
import torch

from hmepol_cli.config import PolicyConfig
from hmepol_cli.envs.slope import SlopeWorld
from hmepol_cli.policies import make_policy

# The tests use tiny tensors; extra threads only contend with the other processes on the box.
torch.set_num_threads(1)


def _tiny_policy(name: str, seed: int = 0, dtype: torch.dtype = torch.float64):
    """A policy of the given kind with 8-unit layers and a 6-dim history, in ``dtype``."""
    torch.manual_seed(seed)
    cfg = PolicyConfig(name=name, hidden=[8], encoder_hidden=[8], history_size=6, init_log_std=-0.5)
    return make_policy(cfg, state_dim=2, action_dim=2).to(dtype)


@pytest.fixture
def tiny_policy():
    """Factory: ``tiny_policy(name, seed=0, dtype=torch.float64)``."""
    return _tiny_policy


@pytest.fixture
def world64() -> SlopeWorld:
    return SlopeWorld().to("cpu", torch.float64)
