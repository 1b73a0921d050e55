"""One place for randomness, devices and the process's allocator."""

from __future__ import annotations

import ctypes
import ctypes.util
import random

import numpy as np
import torch

DTYPES = {"float32": torch.float32, "float64": torch.float64}


def set_random_seed(seed: int) -> None:
    """Seed Python, NumPy and torch (all devices)."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def get_device(name: str = "auto") -> torch.device:
    """'auto' picks cuda when present (``config.check_device`` has checked the name)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def make_generator(device: torch.device, seed: int) -> torch.Generator:
    return torch.Generator(device=device).manual_seed(seed)


def keep_freed_memory() -> None:
    """Let glibc's malloc keep large freed blocks for reuse instead of handing them back.

    An off-policy iteration allocates and frees activations of ~100 MB (80,000 particles x 300
    units). By default glibc serves blocks that large with mmap and unmaps them when freed, so
    every iteration pays the page faults of fresh memory again: an iteration then takes ~1.1-1.5x
    as long (docs/speed.md). Raising the mmap and trim thresholds keeps those pages in the heap.
    Process-wide, idempotent, and a no-op where the C library has no ``mallopt``.
    """
    try:
        mallopt = ctypes.CDLL(ctypes.util.find_library("c")).mallopt
    except (OSError, AttributeError, TypeError):
        return
    m_trim_threshold, m_mmap_threshold = -1, -3  # <malloc.h>
    mallopt(m_mmap_threshold, 1 << 30)
    mallopt(m_trim_threshold, (1 << 31) - 1)
