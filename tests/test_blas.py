"""The float32 layer products through OpenBLAS: the same function as torch's to float32 rounding.

Each product is checked against the exact product (float64 of the same float32 inputs) with the
classical bound of a K-term float32 dot product, |fl(x . w) - x . w| <= gamma_K |x| . |w|,
gamma_K = K u / (1 - K u), u = 2^-24 (Higham, Accuracy and Stability of Numerical Algorithms,
eq. 3.5): a bound derived from the shapes, which holds whatever order a library sums in.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from hmepol_cli import blas
from hmepol_cli.config import PolicyConfig
from hmepol_cli.policies import make_policy
from hmepol_cli.policies.base import MLP, HistoryLinear, Linear, OutputLinear
from tests.test_trainer import population, tiny_trainer

U = 2.0**-24
KINDS = ["markov", "recursive", "twohead", "gru", "lstm"]


def gamma(k: int) -> float:
    return k * U / (1 - k * U)


def assert_within_rounding(got: torch.Tensor, exact: torch.Tensor, scale: torch.Tensor, k: int):
    """|got - exact| <= gamma_k * scale (+ the rounding of the result itself), elementwise."""
    error = (got.double() - exact).abs()
    bound = (gamma(k) + U) * scale + 1e-30
    worst = float((error / bound).max().detach())
    assert worst <= 1.0, f"{worst:.2f} times the rounding bound gamma_{k}"


def layer_case(rows: int, inputs: int, outputs: int, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(rows, inputs, generator=gen).requires_grad_(True)
    weight = (torch.randn(outputs, inputs, generator=gen) / inputs**0.5).requires_grad_(True)
    bias = torch.randn(outputs, generator=gen).requires_grad_(True)
    grad = torch.randn(rows, outputs, generator=gen)
    return x, weight, bias, grad


def check_one_layer(rows: int, inputs: int, outputs: int, relu: bool, seed: int = 0):
    """Forward and the three gradients of one layer through OpenBLAS, against the exact ones."""
    x, weight, bias, grad = layer_case(rows, inputs, outputs, seed)
    with blas.using("openblas"):
        y = blas.mlp(x, [blas.Layer(weight, bias, relu)])
        gx, gw, gb = torch.autograd.grad(y, (x, weight, bias), grad)
    x64, w64, b64, g64 = (t.detach().double() for t in (x, weight, bias, grad))
    pre = x64 @ w64.T + b64
    exact = pre.clamp_min(0) if relu else pre
    assert_within_rounding(y, exact, x64.abs() @ w64.abs().T + b64.abs(), inputs + 1)
    # The gradient flows where the float32 pre-activation was positive; compare on rows the
    # float32 and exact signs agree on (a sign flip there is a rounding of the forward pass).
    mask = (y > 0).double() if relu else torch.ones_like(pre)
    g_in = g64 * mask
    assert_within_rounding(gx, g_in @ w64, g_in.abs() @ w64.abs(), outputs)
    assert_within_rounding(gw, g_in.T @ x64, g_in.abs().T @ x64.abs(), rows)
    assert_within_rounding(gb, g_in.sum(0), g_in.abs().sum(0), rows)


@pytest.mark.slow  # heavy: make test runs it, make test-fast does not
def test_a_hidden_layer_at_the_thesis_shape_is_torchs_product_to_float32_rounding():
    check_one_layer(40_000, 300, 300, relu=True)


@settings(max_examples=25, deadline=None)
@given(
    rows=st.integers(1, 3 * blas.BLOCK_ROWS + 7),
    inputs=st.integers(1, 40),
    outputs=st.integers(1, 40),
    relu=st.booleans(),
    seed=st.integers(0, 2**16),
)
def test_every_shape_and_block_split_is_within_the_rounding_bound(
    rows, inputs, outputs, relu, seed
):
    check_one_layer(rows, inputs, outputs, relu, seed)


@settings(max_examples=20, deadline=None)
@given(
    rows=st.integers(1, 2 * blas.BLOCK_ROWS + 3),
    sizes=st.lists(st.integers(1, 24), min_size=2, max_size=5),
    seed=st.integers(0, 2**16),
)
def test_a_stack_equals_its_layers_one_after_the_other_bit_for_bit(rows, sizes, seed):
    """The fused stack (each row block down all layers) computes exactly what its layers do one
    at a time through the same library: outputs and every gradient, bit for bit."""
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(rows, sizes[0], generator=gen).requires_grad_(True)
    layers = [
        blas.Layer(
            torch.randn(o, i, generator=gen).requires_grad_(True),
            torch.randn(o, generator=gen).requires_grad_(True),
            j < len(sizes) - 2,
        )
        for j, (i, o) in enumerate(zip(sizes[:-1], sizes[1:], strict=True))
    ]
    grad = torch.randn(rows, sizes[-1], generator=gen)
    leaves = [x, *(p for la in layers for p in (la.weight, la.bias))]
    with blas.using("openblas"):
        fused = blas.mlp(x, layers)
        fused_grads = torch.autograd.grad(fused, leaves, grad)
        h = x
        for layer in layers:
            h = blas.linear(h, layer.weight, layer.bias)
            h = torch.relu(h) if layer.relu else h
        alone_grads = torch.autograd.grad(h, leaves, grad)
    assert torch.equal(fused, h)
    for a, b in zip(fused_grads, alone_grads, strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("kind", [Linear, OutputLinear, HistoryLinear])
def test_every_layer_kind_runs_its_product_through_the_library(kind, monkeypatch):
    """Each layer class the policies use goes through OpenBLAS when it is selected (counted at
    the autograd function), and gives torch's result to rounding."""
    calls = []
    apply = blas._OpenBLASStack.apply
    monkeypatch.setattr(blas._OpenBLASStack, "apply", lambda *a: calls.append(1) or apply(*a))
    torch.manual_seed(0)
    layer = kind(7, 5)
    x = torch.randn(50, 7)
    with blas.using("openblas"):
        y = layer(x)
    assert calls == [1]
    torch.testing.assert_close(y, torch.nn.functional.linear(x, layer.weight, layer.bias))


def test_a_networks_relu_layers_run_as_one_stack_and_its_tanh_after(monkeypatch):
    depths = []
    apply = blas._OpenBLASStack.apply
    monkeypatch.setattr(
        blas._OpenBLASStack,
        "apply",
        lambda x, relus, *p: depths.append(relus) or apply(x, relus, *p),
    )
    torch.manual_seed(0)
    net = MLP(
        Linear(3, 6), torch.nn.ReLU(), Linear(6, 6), torch.nn.ReLU(), Linear(6, 2), torch.nn.Tanh()
    )
    x = torch.randn(30, 3)
    with blas.using("openblas"):
        y = net(x)
    with blas.using("torch"):
        reference = net(x)
    assert depths == [(True, True, False)]
    torch.testing.assert_close(y, reference)


def test_float64_bf16_autocast_and_vmap_keep_torchs_products():
    torch.manual_seed(0)
    layer = Linear(4, 3)
    x = torch.randn(20, 4)
    with blas.using("openblas"):
        assert blas.fuses(x, layer.weight)
        assert not blas.fuses(x.double(), layer.weight.double())
        with torch.autocast("cpu", dtype=torch.bfloat16):
            assert not blas.fuses(x, layer.weight)
        seen = []
        torch.vmap(lambda row: seen.append(blas.fuses(row, layer.weight)) or row)(x)
        assert seen == [False]
        assert torch.equal(layer.double()(x.double()), x.double() @ layer.weight.T + layer.bias)


def test_auto_keeps_small_products_with_torch():
    x, w = torch.randn(10, 4), torch.randn(3, 4)
    with blas.using("openblas", min_rows=blas.MIN_ROWS):
        assert not blas.fuses(x, w)
        assert blas.fuses(torch.randn(blas.MIN_ROWS, 4), w)


def policy_case(kind: str, bptt, seed: int = 0):
    torch.manual_seed(seed)
    cfg = PolicyConfig(name=kind, hidden=[32, 32], encoder_hidden=[32], history_size=8)
    policy = make_policy(cfg, state_dim=2, action_dim=2)
    gen = torch.Generator().manual_seed(seed)
    n, t = 12, 30
    states = torch.randn(n, t, 2, generator=gen)
    actions = torch.randn(n, t, 2, generator=gen)
    histories = torch.randn(n, t, policy.history_size, generator=gen).abs()
    return policy, (states, actions, histories, bptt)


@pytest.mark.parametrize("bptt", [1, None])
@pytest.mark.parametrize("kind", KINDS)
def test_every_policy_kind_gives_torchs_likelihoods_and_gradients(kind, bptt):
    """A policy's likelihoods and their gradients through OpenBLAS equal float64's to float32
    accuracy, as torch's own float32 ones do (the same tolerance for both)."""
    if kind == "markov" and bptt is None:
        pytest.skip("a Markovian policy has no history")
    policy, args = policy_case(kind, bptt)
    exact_policy = make_policy(
        PolicyConfig(name=kind, hidden=[32, 32], encoder_hidden=[32], history_size=8), 2, 2
    )
    exact_policy.load_state_dict(policy.state_dict())
    exact_policy.double()
    exact = exact_policy.log_prob(*(a.double() if torch.is_tensor(a) else a for a in args))
    exact_grads = torch.autograd.grad(
        exact.sin().sum(), list(exact_policy.parameters()), allow_unused=True
    )
    errors = {}
    for backend in blas.BACKENDS:
        with blas.using(backend):
            log_p = policy.log_prob(*args)
            grads = torch.autograd.grad(
                log_p.sin().sum(), list(policy.parameters()), allow_unused=True
            )
        pairs = [(g, e) for g, e in zip(grads, exact_grads, strict=True) if e is not None]
        errors[backend] = (
            float((log_p.double() - exact).abs().max().detach()),
            max(float(((g.double() - e).abs() / (e.abs().max() + 1e-12)).max()) for g, e in pairs),
        )
    for backend, (value_error, grad_error) in errors.items():
        assert value_error < 1e-4, (backend, errors)
        assert grad_error < 1e-4, (backend, errors)


@pytest.mark.parametrize("bptt", [1, None])
def test_second_derivatives_equal_torchs(bptt):
    """Fine-tuning's Fisher-vector products differentiate a gradient: through OpenBLAS the
    Hessian-vector product equals torch's to float32 rounding, through a whole recursion too."""
    policy, (states, actions, histories, _) = policy_case("recursive", bptt)
    params = list(policy.parameters())
    vector = [torch.randn_like(p) for p in params]

    def hvp(backend):
        with blas.using(backend):
            log_p = policy.log_prob(states, actions, histories, bptt)
            grads = torch.autograd.grad(log_p.sum(), params, create_graph=True)
            dot = sum((g * v).sum() for g, v in zip(grads, vector, strict=True))
            return torch.autograd.grad(dot, params)

    # Through a whole recursion the products cancel: an entry far smaller than its tensor's
    # largest carries that one's rounding, so the absolute tolerance scales with the tensor
    # (on an AMD EPYC family 26, 2 of 320 entries differed by 2.7e-5 at a fixed 1e-5).
    for a, b in zip(hvp("openblas"), hvp("torch"), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4 * float(b.abs().max()))


EPOCH = [
    "env=corridor",
    "algo=mepol",
    "algo.trajectories=20",
    "algo.horizon=100",
    "algo.batch_size=1",
    "algo.max_off_iters=10",
    "algo.kl_threshold=1e9",
    "policy.hidden=[64,64]",
]


def one_epoch(tmp_path, backend: str, *overrides: str):
    trainer = tiny_trainer(tmp_path / backend, *EPOCH, f"blas={backend}", *overrides)
    (stats,) = trainer.epoch()
    blas.select("torch")
    return trainer, stats


@pytest.mark.parametrize("algo", ["mepol", "hmepol"])
def test_an_epoch_through_openblas_matches_torchs_entropy_and_kl(tmp_path, algo):
    _, a = one_epoch(tmp_path, "torch", f"algo={algo}")
    _, b = one_epoch(tmp_path, "openblas", f"algo={algo}")
    assert a.update.off_iters == b.update.off_iters == 10
    assert abs(a.update.kl - b.update.kl) < 1e-5
    # Ten float32 off-policy steps apart in rounding only: within 5e-5 nats (1.03e-5 measured
    # on an AMD EPYC family 26), where a wrong product would be off by tenths.
    assert np.abs(np.asarray(a.update.entropies) - np.asarray(b.update.entropies)).max() < 5e-5


def test_the_same_library_reruns_bit_for_bit(tmp_path):
    _, a = one_epoch(tmp_path / "a", "openblas")
    _, b = one_epoch(tmp_path / "b", "openblas")
    assert a.update.kl == b.update.kl
    assert np.array_equal(a.update.entropies, b.update.entropies)


def test_run_json_records_the_library(tmp_path):
    trainer, _ = one_epoch(tmp_path, "openblas")
    trainer.record_world()
    info = json.loads((tmp_path / "openblas" / "run" / "run.json").read_text())
    assert info["blas"] == "openblas"


def test_a_cpu_population_uses_the_library_and_vmap_keeps_torch(tmp_path):
    """A population's member loop runs through OpenBLAS; with vmap=on torch runs the batched
    products, and both compute the function of the members' own runs to rounding."""
    results = {}
    for vmap in ("off", "on"):
        trainer = population(tmp_path / vmap, (0, 1), *EPOCH, "blas=openblas", f"vmap={vmap}")
        (a, b) = trainer.epoch()
        blas.select("torch")
        results[vmap] = (a.update.kl, b.update.kl)
    np.testing.assert_allclose(results["off"], results["on"], rtol=1e-4, atol=1e-6)


def test_auto_chooses_openblas_only_with_a_margin_and_measures_once(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    timings = {"torch": 1.0, "openblas": 1.0 / (blas.AUTO_MARGIN * 0.99)}
    measured = []

    def fake(rows, width, repeats=5):
        measured.extend(blas.BACKENDS)
        return dict(timings)

    monkeypatch.setattr(blas, "layer_seconds", fake)
    assert blas.resolve("auto", "cpu", torch.float32, 5000, 64)[0] == "torch"
    assert blas.resolve("auto", "cpu", torch.float32, 5000, 64)[0] == "torch"
    assert measured == ["torch", "openblas"]  # the second run read the cache
    timings["openblas"] = 1.0 / (blas.AUTO_MARGIN * 1.01)
    choice, reason = blas.resolve("auto", "cpu", torch.float32, 6000, 64)
    assert choice == "openblas" and "OpenBLAS" in reason
    assert blas.resolve("auto", "cuda", torch.float32, 6000, 64)[0] == "torch"
    assert blas.resolve("openblas", "cpu", torch.float64, 6000, 64)[0] == "torch"


@pytest.mark.parametrize("threads", [1, 2])
def test_auto_times_openblas_with_the_runs_threads(tmp_path, monkeypatch, threads):
    """The timing's OpenBLAS pool is the run's thread count, one thread included: OpenBLAS's
    pool starts with every core, which a 1-thread run never has (a full pool overstated it
    2.37x alone, and two runs timing side by side on 2 cores understated it 0.65x)."""
    from threadpoolctl import threadpool_limits

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    pools = []

    def fake(rows, width, repeats=5):
        pools.append(blas.openblas_info()["num_threads"])
        return {"torch": 1.0, "openblas": 1.0}

    monkeypatch.setattr(blas, "layer_seconds", fake)
    before, torch_threads = blas.openblas_info()["num_threads"], torch.get_num_threads()
    try:
        threadpool_limits(limits=3, user_api="blas")  # a pool wider than the run's, any machine
        torch.set_num_threads(threads)
        blas.resolve("auto", "cpu", torch.float32, 5000, 64)
    finally:
        torch.set_num_threads(torch_threads)
        threadpool_limits(limits=before, user_api="blas")
    assert pools == [threads]


def test_a_cache_timed_with_the_full_pool_is_timed_again(tmp_path, monkeypatch):
    """A machine's cache from before the timing used the run's threads (its key without the
    timing rule) holds a choice timed the old way: it is measured again, not read."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    key = blas._machine_key(5000, 64)
    old_key = key.removeprefix(blas.TIMING + "|")
    assert old_key != key
    cache = tmp_path / "hmepol" / "blas.json"
    cache.parent.mkdir()
    cache.write_text(json.dumps({old_key: {"torch": 1.0, "openblas": 10.0}}))
    monkeypatch.setattr(
        blas, "layer_seconds", lambda rows, width, repeats=5: {"torch": 2.0, "openblas": 1.0}
    )
    assert blas.resolve("auto", "cpu", torch.float32, 5000, 64)[0] == "openblas"


@settings(max_examples=60, deadline=None)
@given(
    repeats=st.integers(2, 6),
    start=st.integers(0, 13),
    length=st.integers(0, 10),
    faster=st.sampled_from(["torch", "openblas"]),
)
def test_auto_times_both_libraries_in_turn_so_a_burst_of_load_cannot_choose(
    repeats, start, length, faster
):
    """Timings alternate between the libraries, so a burst of load (every product 10x slower)
    over up to 2 x repeats - 2 consecutive timings leaves each library a clean one: its best is
    its true time, whichever library is faster and wherever the burst falls. One library's
    timings all in a row would hand a burst of ``repeats`` of them to it alone."""
    length = min(length, 2 * repeats - 2)
    true = {"torch": 1.0, "openblas": 1.0}
    true["torch" if faster == "openblas" else "openblas"] = 1.5
    calls = []

    def timed(backend, x, weight, bias):
        calls.append(backend)
        burst = start <= len(calls) - 1 < start + length
        return true[backend] * (10.0 if burst else 1.0)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(blas, "_product_seconds", timed)
        assert blas.layer_seconds(8, 4, repeats) == true
    assert calls.count("torch") == calls.count("openblas") == repeats + 1


@pytest.mark.parametrize("command", ["train", "finetune"])
def test_an_unknown_library_is_refused_naming_the_choices(tmp_path, command):
    out = subprocess.run(
        [sys.executable, "-m", "hmepol_cli", command, "blas=mkl"],
        cwd=tmp_path, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "blas='mkl'" in out.stderr and "auto, torch, openblas" in out.stderr
    assert list(tmp_path.iterdir()) == []
