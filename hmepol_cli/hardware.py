"""What the processor can do: its model, its vector instruction set and whether it has bfloat16
units, so that ``precision=bf16`` runs only where it is fast, and every speed names its CPU.

Without bfloat16 instructions (AVX-512 BF16, AMX on x86; BF16 on Arm), torch computes bfloat16
products on a slow path: on an AVX2-only EPYC a (40,000 x 300) @ (300 x 300) product ran at 1
GFLOP/s in bfloat16 against 10 in float32, and a corridor HMepol epoch 5x slower.
"""

from __future__ import annotations

import functools
import os
import platform
import time
from pathlib import Path

import torch

# /proc/cpuinfo flags of bfloat16 arithmetic: x86 (AVX-512 BF16, AMX), Arm (FEAT_BF16)
BFLOAT16_FLAGS = ("avx512_bf16", "amx_bf16", "bf16")
CPUINFO = Path("/proc/cpuinfo")


@functools.cache
def cpu_name() -> str:
    """The processor's model name (Linux), else what the platform module knows."""
    for line in _cpuinfo_lines():
        if line.startswith(("model name", "Model name")):
            return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


@functools.cache
def cpu_model() -> str:
    """The processor's model name with its x86 family and model numbers, which tell apart the
    CPUs a virtual machine names alike: ``Intel(R) Xeon(R) Processor (family 6, model 167)``."""
    fields = dict(
        (key.strip(), value.strip())
        for key, _, value in (line.partition(":") for line in _cpuinfo_lines())
        if key.strip() in ("cpu family", "model")
    )
    if "cpu family" in fields and "model" in fields:
        return f"{cpu_name()} (family {fields['cpu family']}, model {fields['model']})"
    return cpu_name()


@functools.cache
def cpu_flags() -> frozenset[str]:
    """The instruction-set flags the kernel lists (x86 ``flags``, Arm ``Features``); empty
    where there is no /proc/cpuinfo."""
    for line in _cpuinfo_lines():
        if line.startswith(("flags", "Features")):
            return frozenset(line.split(":", 1)[1].split())
    return frozenset()


def _cpuinfo_lines() -> list[str]:
    try:
        return CPUINFO.read_text().splitlines()
    except OSError:
        return []


def bfloat16_units() -> list[str]:
    """The CPU's bfloat16 instruction sets, by flag (empty: none, or none known)."""
    return [flag for flag in BFLOAT16_FLAGS if flag in cpu_flags()]


def describe_cpu() -> str:
    """One line: model, torch's vector capability, bfloat16 units, cores.
    e.g. ``AMD EPYC (torch capability AVX2, no bfloat16 units, 2 cores)``"""
    units = bfloat16_units()
    bf16 = f"bfloat16 units: {', '.join(units)}" if units else "no bfloat16 units"
    capability = torch.backends.cpu.get_cpu_capability()
    return f"{cpu_name()} (torch capability {capability}, {bf16}, {os.cpu_count()} cores)"


@functools.cache
def bf16_speedup(device_type: str = "cpu", rows: int = 4000, width: int = 300) -> float:
    """How many times faster a hidden layer's product, (rows x width) @ (width x width), runs
    under bfloat16 autocast than in float32 on this device (the median of 5 timings each)."""
    device = torch.device(device_type)
    generator = torch.Generator().manual_seed(0)
    x = torch.randn(rows, width, generator=generator).to(device)
    w = torch.randn(width, width, generator=generator).to(device)

    def timed(autocast: bool) -> float:
        times = []
        for _ in range(6):  # the first is a warm-up
            if device.type == "cuda":
                torch.cuda.synchronize()
            start = time.perf_counter()
            with torch.autocast(device.type, dtype=torch.bfloat16, enabled=autocast):
                (x @ w).sum().item()
            times.append(time.perf_counter() - start)
        return sorted(times[1:])[2]

    return timed(False) / timed(True)
