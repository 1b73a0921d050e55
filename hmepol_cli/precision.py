"""Where lower precision is used, and where it is not.

An epoch's cost is the off-policy loop's forward and backward passes over all particles, and
those are the hidden layers' (300, 300) matrix products. ``precision`` chooses how they run:

- ``float32`` (default): everything in float32, exact float32 products on a GPU;
- ``float64``: everything in float64 (the public reference's precision);
- ``bf16``: the hidden layers' products, forward and backward, in bfloat16 (float32
  accumulation) through ``torch.autocast``, on a CPU with bfloat16 units (AVX-512 BF16, AMX;
  a CPU without them is refused: :mod:`hmepol_cli.hardware`) or a GPU; weights,
  particles, Adam's state and the layer that gives the action mean stay float32
  (:class:`hmepol_cli.policies.base.OutputLinear`), so the likelihoods, the cumulative
  log-ratios, the importance weights, the KL and the kNN volumes are computed from float32
  numbers; the layers whose output is the history h'_t (an encoder's last layer, a GRU's or
  LSTM's gates; ``HistoryLinear``) stay float32 when the likelihoods run the recursion over
  several steps (``policy.bptt`` > 1 and the exact KL), where rounding would accumulate, and are
  lowered at ``bptt = 1``, where h'_t is computed once from the stored h'_{t-1}. Rollouts act
  in float32;
- ``tf32``: float32 storage, TF32 matrix products on a GPU (``torch.set_float32_matmul_precision
  ("high")``); a GPU precision only;
- ``auto``: bf16 where the device has bfloat16 units and a hidden layer's product measured at
  least ``AUTO_MARGIN`` times faster in bf16 than in float32, float32 everywhere else. The
  choice is the machine's: a run resumed on another machine may continue in the other one.

Whatever the precision, the likelihoods the sampling policy is compared with are computed the
same way as the target's (:class:`hmepol_cli.surrogate.Surrogate`), so that at theta' = theta the
log-ratios, and both KLs, are exactly 0.
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
from dataclasses import dataclass

import torch

from hmepol_cli import hardware

AUTO_MARGIN = 1.3  # precision=auto: bf16 only where its products are this many times faster

_LOWERED_HISTORY = contextvars.ContextVar("lowered_history", default=False)


def lowered_history() -> bool:
    """Whether layers that output the history may run in the lower precision now (bptt = 1)."""
    return _LOWERED_HISTORY.get()


@dataclass(frozen=True)
class Precision:
    name: str
    dtype: torch.dtype  # weights, particles, optimizer state
    autocast: torch.dtype | None = None  # the hidden layers' products in the off-policy loop
    matmul: str = "highest"  # torch.set_float32_matmul_precision on a GPU
    gpu_only: bool = False

    @contextlib.contextmanager
    def products(self, device: torch.device, bptt: int | None = None):
        """The context the off-policy loop's likelihoods are computed in; ``bptt`` = 1: the
        history layers are hidden layers too (h'_t computed once, from the stored h'_{t-1})."""
        if self.autocast is None:
            yield
            return
        token = _LOWERED_HISTORY.set(bptt == 1)
        try:
            with torch.autocast(device.type, dtype=self.autocast):
                yield
        finally:
            _LOWERED_HISTORY.reset(token)


PRECISIONS: dict[str, Precision] = {
    p.name: p
    for p in (
        Precision("float32", torch.float32),
        Precision("float64", torch.float64),
        Precision("bf16", torch.float32, autocast=torch.bfloat16),
        Precision("tf32", torch.float32, matmul="high", gpu_only=True),
    )
}


def precision_of(cfg) -> Precision:
    """The precision of a run's config (``auto`` resolved on this machine); a run started before
    ``precision`` existed said it with ``dtype`` (float32 | float64) and ``matmul_precision``
    (high: TF32)."""
    name = cfg.get("precision")
    if name is None:
        name = str(cfg.get("dtype", "float32"))
        if name == "float32" and cfg.get("matmul_precision", "highest") != "highest":
            name = "tf32"
    if name == "auto":
        return auto_precision(device_type(str(cfg.get("device", "cpu"))))
    return PRECISIONS[str(name)]


def device_type(device: str) -> str:
    return "cuda" if device == "cuda" or (device == "auto" and torch.cuda.is_available()) else "cpu"


def bf16_runs_fast_here(device_type: str) -> bool:
    """Whether the device has bfloat16 arithmetic (a CPU's units, a GPU's support)."""
    if device_type == "cuda":
        return torch.cuda.is_bf16_supported()
    return bool(hardware.bfloat16_units())


@functools.cache
def auto_precision(device_type: str) -> Precision:
    """precision=auto on this device: bf16 where it has bfloat16 arithmetic and the product of
    a hidden layer measured at least AUTO_MARGIN times faster, else float32."""
    if not bf16_runs_fast_here(device_type):
        return PRECISIONS["float32"]
    return PRECISIONS["bf16" if hardware.bf16_speedup(device_type) >= AUTO_MARGIN else "float32"]


def auto_reason(device_type: str) -> str:
    """What precision=auto chose on this device and why, in one line (a run says it as it
    starts; run.json keeps the choice)."""
    chosen = auto_precision(device_type).name
    if not bf16_runs_fast_here(device_type):
        return f"precision=auto chose {chosen}: this {device_type} has no bfloat16 arithmetic"
    speedup = hardware.bf16_speedup(device_type)
    return (
        f"precision=auto chose {chosen}: a hidden layer's bf16 products measured {speedup:.2f}x "
        f"float32's here (bf16 from {AUTO_MARGIN}x)"
    )
