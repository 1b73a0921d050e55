"""Shared fixtures: a float64 slope world and tiny policies of every kind."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

from hmepol_cli import blas
from hmepol_cli.cli import setup
from hmepol_cli.config import PolicyConfig
from hmepol_cli.envs.slope import SlopeWorld
from hmepol_cli.policies import make_policy

# The tests use tiny tensors; extra threads only contend with the other processes on the box.
torch.set_num_threads(1)
setup()  # the config schema and resolvers: the tests compose configs as hmepol does

# The library of the float32 layer products every test starts with: HMEPOL_BLAS=openblas
# (or torch) runs the whole suite through that one (`make test` with each forced).
SUITE_BLAS = os.environ.get("HMEPOL_BLAS") or "torch"


@pytest.fixture(autouse=True)
def the_suites_blas():
    """Each test starts from the suite's library, whatever a run before it selected."""
    blas.select(SUITE_BLAS if SUITE_BLAS != "auto" else "torch")
    yield


CHECKOUT = Path(__file__).resolve().parent.parent
# What running the suite or the tools may leave in the checkout (all in .gitignore).
LEFT_ALONE = {".git", ".venv", ".pytest_cache", ".hypothesis", ".ruff_cache", "__pycache__"}


def checkout_paths(root: Path = CHECKOUT) -> set[str]:
    """Every file and folder under ``root``, but the caches and virtual environments."""
    found = set()
    for folder, dirs, files in os.walk(root):
        dirs[:] = [
            d for d in dirs
            if d not in LEFT_ALONE and not d.endswith(".egg-info")
            and not (Path(folder) / d / "pyvenv.cfg").exists()
        ]  # fmt: skip
        relative = Path(folder).relative_to(root)
        found.update(str(relative / name) for name in (*dirs, *files))
    return found


@pytest.fixture(scope="session", autouse=True)
def the_checkout_gains_no_files():
    """A test writes only under its temporary folder: whatever appears in the checkout during
    the suite (an mlruns/ or outputs/ of a command run from the checkout) is an error."""
    before = checkout_paths()
    yield
    gained = sorted(checkout_paths() - before)
    assert not gained, (
        f"the test suite left {len(gained)} new path(s) in {CHECKOUT} (a test wrote outside its "
        f"tmp_path, or something else ran there meanwhile): {', '.join(gained[:20])}"
    )


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


def check_gradient_by_central_differences(
    objective, module: torch.nn.Module, generator: torch.Generator, *, rel: float, abs_tol: float
) -> int:
    """Compare autograd's gradient of ``objective()`` with float64 central differences at 3
    random entries of every parameter; -> how many were clearly nonzero.

    The difference is taken with h = 1e-5, and again with h = 1e-6 where the two disagree: a
    ReLU whose pre-activation is within h of 0 at some particle puts a kink inside [-h, h],
    where a central difference is not the derivative (seen: 0.3% off at 1e-5, 1e-9 at 1e-6)."""
    module.zero_grad()
    objective().backward()
    nonzero = 0
    for param in module.parameters():
        flat, grad = param.data.view(-1), param.grad.view(-1)
        for i in torch.randperm(flat.numel(), generator=generator)[:3].tolist():
            for h in (1e-5, 1e-6):
                with torch.no_grad():
                    flat[i] += h
                    up = objective().item()
                    flat[i] -= 2 * h
                    down = objective().item()
                    flat[i] += h
                estimate = pytest.approx((up - down) / (2 * h), rel=rel, abs=abs_tol)
                if grad[i].item() == estimate:
                    break
            assert grad[i].item() == estimate
            nonzero += abs(grad[i].item()) > 1e-5
    return nonzero
