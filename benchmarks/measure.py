"""Timers, the machine's matrix-multiply throughput, policy FLOPs and the neighbour baseline."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import torch

from hmepol_cli.hardware import describe_cpu


def best_time(fn: Callable[[], object], repeats: int) -> float:
    """Fastest of ``repeats`` calls, in seconds: the least disturbed by other processes."""
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best


def _fastest(fn: Callable[[], object], min_seconds: float) -> float:
    """Fastest call of ``fn`` after a warm-up, repeating for at least ``min_seconds``."""
    fn()
    best, spent = float("inf"), 0.0
    while spent < min_seconds:
        start = time.perf_counter()
        fn()
        seconds = time.perf_counter() - start
        best, spent = min(best, seconds), spent + seconds
    return best


BACKENDS = ("torch", "openblas")  # the libraries a float32 product can run through (blas=)


def _product(backend: str):
    """a @ b through ``backend``: torch.matmul, or NumPy's matmul (OpenBLAS) on the same memory."""
    if backend == "torch":
        return torch.matmul
    if backend == "openblas":
        return lambda a, b: torch.from_numpy(np.matmul(a.numpy(), b.numpy()))
    raise ValueError(f"backend={backend!r}: choose one of {BACKENDS}")


def matmul_flops(size: int = 2048, min_seconds: float = 0.5, backend: str = "torch") -> float:
    """float32 FLOP/s of a (size, size) @ (size, size) product through ``backend``, at its
    thread count."""
    a, b = torch.randn(size, size), torch.randn(size, size)
    product = _product(backend)
    return 2 * size**3 / _fastest(lambda: product(a, b), min_seconds)


def layer_matmul_flops(
    rows: int,
    width: int = 300,
    min_seconds: float = 0.5,
    dtype: torch.dtype = torch.float32,
    backend: str = "torch",
) -> float:
    """FLOP/s (in ``dtype``) of the three matmuls of a hidden (width x width) Linear layer over
    ``rows`` particles, the shapes an off-policy iteration multiplies: forward x W^T, backward
    g W and g^T x, through ``backend`` (openblas: float32 only)."""
    x, g, w = (
        torch.randn(*shape).to(dtype) for shape in ((rows, width), (rows, width), (width, width))
    )
    product = _product(backend)

    def layer() -> None:
        product(x, w.T)
        product(g, w)
        product(g.T, x)

    return 3 * 2 * rows * width * width / _fastest(layer, min_seconds)


def best_rates(rows: int, before: dict | None = None) -> tuple[dict, dict]:
    """float32 FLOP/s per backend at the layer's shapes and at 2048² (the faster of this
    measurement and ``before``'s, taken on the other side of an epoch). -> (layer, square)"""
    before = before or ({}, {})
    layer = {b: max(layer_matmul_flops(rows, backend=b), before[0].get(b, 0.0)) for b in BACKENDS}
    square = {b: max(matmul_flops(backend=b), before[1].get(b, 0.0)) for b in BACKENDS}
    return layer, square


def forward_flops(policy: torch.nn.Module) -> int:
    """FLOPs of one forward pass for one sample: 2 * in * out per Linear layer."""
    return sum(
        2 * layer.in_features * layer.out_features
        for layer in policy.modules()
        if isinstance(layer, torch.nn.Linear)
    )


def brute_force_neighbours(batch: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The straightforward search: all pairwise distances of a mini-batch (P, d), then the k + 1
    smallest of each row, sorted. -> (distances (P, k + 1), indices (P, k + 1))."""
    distances = np.sqrt(((batch[:, None, :] - batch[None, :, :]) ** 2).sum(axis=-1))
    idx = np.argpartition(distances, k, axis=1)[:, : k + 1]
    near = np.take_along_axis(distances, idx, axis=1)
    order = np.argsort(near, axis=1, kind="stable")
    return np.take_along_axis(near, order, axis=1), np.take_along_axis(idx, order, axis=1)


def brute_force_seconds(particles: torch.Tensor, k: int, batches: int) -> tuple[float, int]:
    """Seconds the brute-force search takes for all mini-batches of ``particles`` (M, P, d),
    float64, one thread, timed on the first ``batches`` and extrapolated. -> (seconds, timed)."""
    points = particles.detach().to("cpu", torch.float64).numpy()
    timed = min(batches, points.shape[0])
    start = time.perf_counter()
    for batch in points[:timed]:
        brute_force_neighbours(batch, k)
    return (time.perf_counter() - start) * points.shape[0] / timed, timed


def cpu_name() -> str:
    """The processor: model, torch's vector capability, bfloat16 units, cores (a speed is
    a claim only beside the CPU it was measured on)."""
    return describe_cpu()
