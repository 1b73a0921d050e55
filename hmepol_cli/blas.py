"""Which library runs the float32 layer products on a CPU: torch's own or OpenBLAS (NumPy's).

Most of a CPU epoch is the policy's layer products over all particles (40,000 x 300 @ 300 x
300 in the corridor). torch's x86 wheel runs them through MKL, whose float32 path on AMD CPUs
is shape-sensitive: at the hidden layer's shape it reaches about half of what the same core
does through the OpenBLAS that NumPy links (docs/speed.md has the rates measured per CPU). So
``blas`` chooses who runs them:

- ``torch``: ``torch.nn.functional.linear`` (MKL on x86, whatever the wheel links elsewhere);
- ``openblas``: a layer stack's forward product and both backward products through NumPy's
  ``matmul`` on zero-copy views of the tensors, the rows in blocks of :data:`BLOCK_ROWS` so
  that each block's bias, ReLU and ReLU-backward run while the block is in cache
  (:func:`mlp`); a single layer is a one-layer stack (:func:`linear`);
- ``auto``: times both at the widest layer's shape once per machine, taking turns, and keeps
  torch unless OpenBLAS measured at least :data:`AUTO_MARGIN` times faster (so an Intel CPU
  keeps MKL).

OpenBLAS runs only where it can: float32 tensors on a CPU, outside ``torch.autocast``
(precision=bf16 keeps torch's lowered products) and outside ``torch.vmap`` (a CPU population
run with ``vmap=on``); under ``auto``, on at least :data:`MIN_ROWS` rows only (a rollout's
steps, 100-200 rows, cost less through torch's direct call), while ``openblas`` asked for by
name runs every product it can. Everywhere else, float64 and ``device=cuda``
included, torch runs the product whatever the setting. Second derivatives (fine-tuning's
Fisher-vector products) are taken through torch's operations on the saved inputs.

The two libraries sum a product's terms in different orders: runs made with different
libraries agree to float32 rounding, not bit for bit, just as runs on different CPUs do. With
the same library and the same number of threads a run is bit-identical from one time to the
next. The choice is process-wide (:func:`select`), like torch's own thread count.
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import platform
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F

BACKENDS = ("torch", "openblas")
CHOICES = (*BACKENDS, "auto")
ENV = "HMEPOL_BLAS"  # the default of the ``blas`` setting
AUTO_MARGIN = 1.1  # blas=auto: OpenBLAS only where its products are this many times faster
TIMING = "pool=threads"  # how auto times (in its cache key: a cache timed otherwise is redone)
MIN_ROWS = 1024  # fewer rows (a rollout's steps): torch's call costs less than the detour
BLOCK_ROWS = 1024  # rows of a block in the fused layer stack: 1.2 MB of a 300-wide layer

_current = "torch"
_min_rows = 0


def select(name: str, min_rows: int = 0) -> None:
    """Run the float32 CPU layer products through ``name`` (torch | openblas) from now on;
    products of fewer than ``min_rows`` rows through torch."""
    global _current, _min_rows
    if name not in BACKENDS:
        raise ValueError(f"blas={name!r}: choose one of {', '.join(CHOICES)}")
    _current, _min_rows = name, int(min_rows)


def current() -> str:
    return _current


@contextlib.contextmanager
def using(name: str, min_rows: int = 0) -> Iterator[None]:
    """``select(name, min_rows)`` inside the block, the previous choice after it."""
    before = (_current, _min_rows)
    select(name, min_rows)
    try:
        yield
    finally:
        select(*before)


def limit_openblas_threads(threads: int) -> None:
    """OpenBLAS' pool to ``threads``, so that it and torch's never oversubscribe the cores
    (each runs at its own time; neither should hold more threads than torch is given)."""
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=max(1, int(threads)), user_api="blas")


def openblas_info() -> dict:
    """NumPy's BLAS: library, version, threading, CPU kernel (for bench reports and run.json)."""
    from threadpoolctl import threadpool_info

    for pool in threadpool_info():
        if pool.get("user_api") == "blas" and "numpy" in str(pool.get("filepath", "")):
            keys = ("internal_api", "version", "num_threads", "architecture", "threading_layer")
            return {k: pool.get(k) for k in keys}
    return {}


class Layer(NamedTuple):
    """One layer of a stack: y = x W^T + b, then ReLU if ``relu``."""

    weight: torch.Tensor
    bias: torch.Tensor | None
    relu: bool


def _functorch_wrapped(x: torch.Tensor) -> bool:
    check = getattr(torch._C._functorch, "is_functorch_wrapped_tensor", None)
    return bool(check is not None and check(x))


def fuses(x: torch.Tensor, weight: torch.Tensor) -> bool:
    """Whether OpenBLAS runs this product: it is selected, both are float32 CPU tensors outside
    autocast and vmap, and x has the rows asked for (blas=auto: :data:`MIN_ROWS`)."""
    return (
        _current == "openblas"
        and x.numel() >= _min_rows * x.shape[-1]
        and x.device.type == "cpu"
        and x.dtype == torch.float32
        and weight.dtype == torch.float32
        and not torch.is_autocast_enabled("cpu")
        and not _functorch_wrapped(x)
        and not _functorch_wrapped(weight)
    )


def _torch_stack(x: torch.Tensor, layers: Sequence[Layer]) -> torch.Tensor:
    for layer in layers:
        x = F.linear(x, layer.weight, layer.bias)
        if layer.relu:
            x = torch.relu(x)
    return x


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().numpy()


class _OpenBLASStack(torch.autograd.Function):
    """A stack of linear layers (ReLU where asked) through OpenBLAS, in blocks of rows.

    Forward keeps every layer's output (the next layer's input, and the ReLU's mask) as torch
    does; backward walks each block down the stack while its gradients are in cache, summing
    the weight and bias gradients over the blocks. The products are NumPy's (OpenBLAS), the
    elementwise steps torch's own vectorised kernels, on the same memory."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, relus: tuple[bool, ...], *params: torch.Tensor):
        weights, biases = params[0::2], params[1::2]
        n = x.shape[0]
        outputs = [torch.empty(n, w.shape[0], dtype=x.dtype) for w in weights]
        transposed = [_np(w).T for w in weights]
        biases = [b.detach() for b in biases]
        for start in range(0, n, BLOCK_ROWS):
            rows = slice(start, min(start + BLOCK_ROWS, n))
            h = x[rows]
            for wt, b, relu, out in zip(transposed, biases, relus, outputs, strict=True):
                block = out[rows]
                np.matmul(_np(h), wt, out=block.numpy())
                block.add_(b)
                if relu:
                    block.relu_()
                h = block
        ctx.relus = relus
        ctx.save_for_backward(x, *params, *outputs)
        return outputs[-1]

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        relus = ctx.relus
        depth = len(relus)
        saved = ctx.saved_tensors
        x, params, outputs = saved[0], saved[1 : 1 + 2 * depth], saved[1 + 2 * depth :]
        if torch.is_grad_enabled():  # create_graph: a differentiable backward, through torch
            grad_x, *grads = _differentiable_grads(ctx, x, params, relus, grad)
            return (grad_x, None, *grads)
        weights = [_np(w) for w in params[0::2]]
        need_x = ctx.needs_input_grad[0]
        grad = grad.detach().contiguous()
        n = x.shape[0]
        inputs = [x.detach(), *(o.detach() for o in outputs[:-1])]
        outputs = [o.detach() for o in outputs]
        grad_w = [torch.zeros(w.shape, dtype=grad.dtype) for w in weights]
        grad_b = [torch.zeros(w.shape[0], dtype=grad.dtype) for w in weights]
        products = [torch.empty(w.shape, dtype=grad.dtype) for w in weights]
        grad_x = torch.empty_like(x) if need_x else None
        for start in range(0, n, BLOCK_ROWS):
            rows = slice(start, min(start + BLOCK_ROWS, n))
            g = grad[rows]
            for i in reversed(range(depth)):
                if relus[i]:
                    g = torch.ops.aten.threshold_backward(g, outputs[i][rows], 0)
                np.matmul(_np(g).T, _np(inputs[i][rows]), out=products[i].numpy())
                grad_w[i].add_(products[i])
                grad_b[i].add_(g.sum(0))
                if i > 0:
                    g = torch.from_numpy(_np(g) @ weights[i])
                elif need_x:
                    np.matmul(_np(g), weights[0], out=grad_x[rows].numpy())
        grads = []
        for i in range(depth):
            grads.append(grad_w[i] if ctx.needs_input_grad[2 + 2 * i] else None)
            grads.append(grad_b[i] if ctx.needs_input_grad[3 + 2 * i] else None)
        return (grad_x, None, *grads)


def _differentiable_grads(ctx, x, params, relus, grad):
    """The backward pass as torch operations on the saved inputs, so that it has a graph of its
    own (second derivatives, as in fine-tuning's Fisher-vector products): the forward pass
    recomputed, then the chain rule written out (no nested autograd call, which would walk the
    graph below x again at every layer of a recursion)."""
    weights, biases = params[0::2], params[1::2]
    inputs = [x]
    for weight, bias, relu in zip(weights, biases, relus, strict=True):
        h = F.linear(inputs[-1], weight, bias)
        inputs.append(torch.relu(h) if relu else h)
    grads: list[torch.Tensor | None] = [None] * (2 * len(relus))
    g = grad
    for i in reversed(range(len(relus))):
        if relus[i]:
            g = g * (inputs[i + 1] > 0).to(g.dtype)
        grads[2 * i] = g.transpose(0, 1) @ inputs[i]
        grads[2 * i + 1] = g.sum(0)
        g = g @ weights[i]
    needs = ctx.needs_input_grad
    return [g if needs[0] else None, *(t if needs[2 + j] else None for j, t in enumerate(grads))]


def mlp(x: torch.Tensor, layers: Sequence[Layer]) -> torch.Tensor:
    """``layers`` applied to x (N, d): through OpenBLAS where :func:`fuses`, else through torch.
    Leading dimensions beyond the rows are flattened and restored."""
    if not layers or not fuses(x, layers[0].weight) or any(la.bias is None for la in layers):
        return _torch_stack(x, layers)
    lead = x.shape[:-1]
    rows = x.reshape(-1, x.shape[-1]).contiguous()  # outside the function: keeps its graph
    params = [p for la in layers for p in (la.weight, la.bias)]
    out = _OpenBLASStack.apply(rows, tuple(bool(la.relu) for la in layers), *params)
    return out.reshape(*lead, out.shape[-1])


def linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
    """``F.linear`` through the selected library (a one-layer :func:`mlp`)."""
    return mlp(x, [Layer(weight, bias, False)])


# -- choosing ---------------------------------------------------------------------------------
def layer_seconds(rows: int, width: int, repeats: int = 5) -> dict[str, float]:
    """{library: best-of-``repeats`` seconds} of one hidden layer's forward and backward products
    (rows x width @ width x width, then both gradients) through each library.

    The libraries take turns (torch, OpenBLAS, torch, ...), so that a burst of load from other
    processes slows both rather than one: any burst of up to 2 x ``repeats`` - 2 consecutive
    timings leaves each library one it did not touch. Timed one library after the other, a
    measurement made beside a running study once put OpenBLAS at 0.24x torch's speed at a
    shape where, on the idle machine, it was 1.5x faster; the choice is kept for the machine,
    so one such measurement would have slowed every later run."""
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(rows, width, generator=gen, requires_grad=True)
    weight = torch.randn(width, width, generator=gen, requires_grad=True)
    bias = torch.zeros(width, requires_grad=True)
    best = dict.fromkeys(BACKENDS, float("inf"))
    for turn in range(repeats + 1):
        for backend in BACKENDS:
            seconds = _product_seconds(backend, x, weight, bias)
            if turn:  # the first turn warms each library's buffers up
                best[backend] = min(best[backend], seconds)
    return best


def _product_seconds(
    backend: str, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor
) -> float:
    with using(backend):
        start = time.perf_counter()
        linear(x, weight, bias).sum().backward()
        return time.perf_counter() - start


def _cache_path() -> Path:
    root = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(root) / "hmepol" / "blas.json"


def _machine_key(rows: int, width: int) -> str:
    info = openblas_info()
    return "|".join(
        str(v)
        for v in (
            TIMING,
            platform.processor() or platform.machine(),
            _cpu_model(),
            torch.__version__,
            np.__version__,
            info.get("version"),
            info.get("architecture"),
            torch.get_num_threads(),
            rows,
            width,
        )
    )


@functools.cache
def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def auto_choice(rows: int, width: int) -> tuple[str, dict]:
    """blas=auto: (library, {library: seconds of a layer}) at this layer's shape on this
    machine, measured once and kept in ``~/.cache/hmepol/blas.json`` (per CPU, versions,
    threads and shape)."""
    key = _machine_key(rows, width)
    path = _cache_path()
    try:
        cache = json.loads(path.read_text())
    except (OSError, ValueError):
        cache = {}
    seconds = cache.get(key)
    if not (isinstance(seconds, dict) and set(seconds) == set(BACKENDS)):
        seconds = layer_seconds(rows, width)
        cache[key] = seconds
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".{os.getpid()}.tmp")
            tmp.write_text(json.dumps(cache, indent=1))
            tmp.replace(path)
        except OSError:
            pass  # a read-only home: measure again next time
    fast = seconds["torch"] / seconds["openblas"] >= AUTO_MARGIN
    return ("openblas" if fast else "torch"), seconds


def widest_layer(policy: torch.nn.Module) -> int:
    """The widest hidden layer's width (the product that dominates an epoch)."""
    widths = [m.weight.shape[0] for m in policy.modules() if isinstance(m, torch.nn.Linear)]
    return max(widths, default=1)


def configure(
    name: str, device_type: str, dtype: torch.dtype, rows: int, width: int
) -> tuple[str, str]:
    """Resolve ``name`` for a run (:func:`resolve`), select it, and give OpenBLAS as many
    threads as torch has. -> (library, the line to say as the run starts)"""
    choice, reason = resolve(name, device_type, dtype, rows, width)
    select(choice, MIN_ROWS if name == "auto" else 0)
    if choice == "openblas":
        limit_openblas_threads(torch.get_num_threads())
    return choice, reason


def resolve(
    name: str, device_type: str, dtype: torch.dtype, rows: int, width: int
) -> tuple[str, str]:
    """The library a run of ``dtype`` on ``device_type`` uses, and one line saying why
    (printed as the run starts)."""
    if device_type != "cpu" or dtype != torch.float32:
        kind = "a GPU's" if device_type != "cpu" else str(dtype).removeprefix("torch.")
        return "torch", f"blas: torch ({kind} products are torch's whatever blas says)"
    if name != "auto":
        return name, f"blas={name}"
    # Time both with the run's threads, whatever their number: OpenBLAS's pool starts with every
    # core. On a 2-core Zen 4 EPYC, 1 thread a run, that pool measured OpenBLAS at 2.37x torch
    # alone and 0.64-0.66x with a second run timing beside it (it then kept torch for the
    # machine); with the run's one thread, 1.37-1.39x either way.
    limit_openblas_threads(torch.get_num_threads())
    rows = max(MIN_ROWS, min(int(rows), 40_000))
    choice, seconds = auto_choice(rows, width)
    ratio = seconds["torch"] / seconds["openblas"]
    return choice, (
        f"blas=auto chose {choice}: a {rows} x {width} layer's products ran {ratio:.2f}x as "
        f"fast through OpenBLAS as through torch here (OpenBLAS from {AUTO_MARGIN}x)"
    )
