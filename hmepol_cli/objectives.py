"""Objectives over the per-mini-batch entropies of an epoch (thesis 3.3.1, 3.4.2, 4.2.3).

Entropies come as (..., M): M mini-batches, any leading dimensions (one row per member of a
population); the objective reduces the last one.
"""

from __future__ import annotations

import math

import torch


def mean(entropies: torch.Tensor) -> torch.Tensor:
    """Mepol / HMepol: the mean of the mini-batch entropies. (..., M) -> (...)"""
    return entropies.mean(dim=-1)


def cvar(entropies: torch.Tensor, alpha: float) -> torch.Tensor:
    """alpha-Mepol, eq. 3.3: CVaR_alpha, the mean of the lowest ceil(alpha * M) entropies.

    (..., M) -> (...)
    """
    if not 0 < alpha <= 1:
        raise ValueError(f"alpha={alpha!r} must be in (0, 1]")
    count = max(1, math.ceil(alpha * entropies.shape[-1] - 1e-9))
    return torch.topk(entropies, count, dim=-1, largest=False).values.mean(dim=-1)


# name -> objective(entropies, alpha); a new objective is a function and an entry here.
OBJECTIVES = {
    "mean": lambda entropies, alpha: mean(entropies),
    "cvar": cvar,
}


def objective(entropies: torch.Tensor, name: str, alpha: float = 1.0) -> torch.Tensor:
    try:
        return OBJECTIVES[name](entropies, alpha)
    except KeyError:
        raise ValueError(
            f"unknown objective {name!r}; choose one of: {', '.join(OBJECTIVES)}"
        ) from None
