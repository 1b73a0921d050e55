"""Policies (thesis 4.2): the history recursion, stored-trajectory likelihoods, and how far
back-propagation through the recursion reaches (one step, n steps, the whole trajectory).

Everything runs on tiny float64 policies (8-unit layers, 6-dim history) in the slope world, so
likelihoods recomputed from stored trajectories must match the recorded ones to rounding.
"""

from __future__ import annotations

import pytest
import torch
from scipy.stats import norm

from hmepol_cli.config import PolicyConfig
from hmepol_cli.envs.slope import SlopeWorld
from hmepol_cli.policies import make_policy
from hmepol_cli.policies.markov import MarkovPolicy
from hmepol_cli.rollout import Rollout, collect_single, draw_configurations
from tests.conftest import check_gradient_by_central_differences

F64 = torch.float64
ALL = ("markov", "recursive", "twohead", "gru", "lstm")
RECURRENT = ("recursive", "twohead", "gru", "lstm")
N, T = 6, 12  # trajectories, horizon


def gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def roll(world, policy, seed: int = 0, n: int = N, horizon: int = T) -> Rollout:
    configurations = draw_configurations(world, n, batch_size=2, generator=gen(seed))
    return collect_single(world, policy, configurations, horizon, generator=gen(seed + 1))


def jiggle(policy, scale: float = 0.3, seed: int = 99):
    """Move every parameter by N(0, scale^2): away from the near-zero initial action mean, or
    away from the sampling policy."""
    g = gen(seed)
    with torch.no_grad():
        for param in policy.parameters():
            param.add_(scale * torch.randn(param.shape, generator=g, dtype=param.dtype))
    return policy


def assert_same_rollout(a: Rollout, b: Rollout, **tol):
    for field in ("states", "actions", "histories", "log_probs", "configurations"):
        torch.testing.assert_close(getattr(a, field), getattr(b, field), **tol)


# ------------------------------------------------------------------ the history recursion


@pytest.mark.parametrize("name", ALL)
def test_histories_start_at_zero_and_follow_the_recursion(name, world64, tiny_policy):
    policy = jiggle(tiny_policy(name))
    r = roll(world64, policy)
    assert r.histories.shape == (N, T, policy.history_size)
    assert (r.histories[:, 0] == 0).all()  # h'_{-1} = 0: the first step reads a zero history
    # Stored histories are h'_{t-1} = g(s_{t-1}, h'_{t-2}), replayed here from zero.
    history = torch.zeros(N, policy.history_size, dtype=F64)
    with torch.no_grad():
        for t in range(T):
            torch.testing.assert_close(r.histories[:, t], history, rtol=1e-12, atol=1e-12)
            _, history = policy.step(r.inputs[:, t], history)
    if policy.history_size:
        assert r.histories[:, 1:].abs().sum() > 0


@pytest.mark.parametrize("name", RECURRENT)
def test_consecutive_collects_do_not_leak_history(name, world64, tiny_policy):
    policy = jiggle(tiny_policy(name))
    first = roll(world64, policy, seed=0)
    roll(world64, policy, seed=5)  # a different batch in between
    again = roll(world64, policy, seed=0)
    assert_same_rollout(first, again, rtol=0, atol=0)


# ------------------------------------------------------------------ stored-trajectory likelihoods


@pytest.mark.parametrize("bptt", [1, 2, 5, None, 50])
@pytest.mark.parametrize("name", ALL)
def test_log_prob_under_sampling_parameters_is_the_recorded_one(name, bptt, world64, tiny_policy):
    # bptt = 1 reads the stored h'_{t-1}, n from the stored h'_{t-n}, None (and n >= T) replays
    # from h'_0 = 0: all three must give back what the rollout recorded, to float64 rounding.
    policy = jiggle(tiny_policy(name))
    r = roll(world64, policy)
    assert r.states.shape == (N, T + 1, 2) and r.actions.shape == (N, T, 2)
    with torch.no_grad():
        log_p = policy.log_prob(r.inputs, r.actions, r.histories, bptt)
    assert log_p.shape == (N, T)
    torch.testing.assert_close(log_p, r.log_probs, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("bptt", [1, 3, None])
@pytest.mark.parametrize("name", ALL)
def test_log_prob_in_float32(name, bptt, tiny_policy):
    # The default dtype: the same identity to float32 rounding (measured <= 9.5e-7).
    policy = jiggle(tiny_policy(name, dtype=torch.float32))
    r = roll(SlopeWorld(), policy)
    with torch.no_grad():
        log_p = policy.log_prob(r.inputs, r.actions, r.histories, bptt)
    assert log_p.dtype == torch.float32
    torch.testing.assert_close(log_p, r.log_probs, rtol=1e-5, atol=1e-5)


def test_make_policy_builds_every_kind_and_refuses_others():
    for name in ALL:
        cfg = PolicyConfig(name=name, hidden=[4], encoder_hidden=[4], history_size=3)
        policy = make_policy(cfg, state_dim=2, action_dim=2)
        assert policy.history_size == {"markov": 0, "lstm": 6}.get(name, 3)
    with pytest.raises(ValueError, match="unknown policy 'rnn'"):
        make_policy(PolicyConfig(name="rnn"), state_dim=2, action_dim=2)


# ------------------------------------------------------------------ how far gradients reach


def input_gradients(policy, r: Rollout, bptt, t0: int):
    """d log pi(a_t0 | h_t0) / d (s_t, stored h'_{t-1}), summed in size per step t. -> (T,), (T,)"""
    states = r.inputs.clone().requires_grad_()
    histories = r.histories.clone().requires_grad_()
    policy.log_prob(states, r.actions, histories, bptt)[:, t0].sum().backward()
    per_step = lambda g: torch.zeros(T, dtype=F64) if g is None else g.abs().sum(dim=(0, 2))  # noqa: E731
    return per_step(states.grad), per_step(histories.grad)


@pytest.mark.parametrize("name", RECURRENT)
def test_gradient_reach_through_the_recursion(name, world64, tiny_policy):
    policy = jiggle(tiny_policy(name))
    r = roll(world64, policy)
    t0, steps = 8, torch.arange(T)

    # One step: only s_t0 and the stored h'_{t0-1} carry gradient.
    ds, dh = input_gradients(policy, r, 1, t0)
    assert ds[t0] > 0 and dh[t0] > 0
    assert (ds[steps != t0] == 0).all() and (dh[steps != t0] == 0).all()

    # n = 3 steps: s_{t0-2} .. s_t0, from the stored h'_{t0-3} (histories[:, t0 - 2]).
    ds, dh = input_gradients(policy, r, 3, t0)
    reached = (steps > t0 - 3) & (steps <= t0)
    assert (ds[reached] > 0).all() and (ds[~reached] == 0).all()
    assert dh[t0 - 2] > 0 and (dh[steps != t0 - 2] == 0).all()

    # Whole trajectory: every s_t with t <= t0 (nothing later); stored histories are not read.
    ds, dh = input_gradients(policy, r, None, t0)
    assert (ds[: t0 + 1] > 0).all() and (ds[t0 + 1 :] == 0).all()
    assert (dh == 0).all()


@pytest.mark.parametrize("name", RECURRENT)
def test_one_step_parameter_gradient_comes_from_step_t_alone(name, world64, tiny_policy):
    # With bptt = 1, d log pi(a_t | h_t) / d theta is that of one step of the network on
    # (s_t, stored h'_{t-1}); with the whole trajectory it differs (the recursion adds terms).
    policy = jiggle(tiny_policy(name))
    r = roll(world64, policy)
    t0 = 7

    def grads(fn):
        policy.zero_grad()
        fn().backward()
        # (the two-head policy's history head gets no gradient at all from one step)
        return torch.cat(
            [
                torch.zeros(p.numel(), dtype=F64) if p.grad is None else p.grad.flatten()
                for p in policy.parameters()
            ]
        )

    one_step = grads(lambda: policy.log_prob(r.inputs, r.actions, r.histories, 1)[:, t0].sum())
    direct = grads(
        lambda: policy.gaussian_log_prob(
            policy.step(r.inputs[:, t0], r.histories[:, t0])[0], r.actions[:, t0]
        ).sum()
    )
    full = grads(lambda: policy.log_prob(r.inputs, r.actions, r.histories, None)[:, t0].sum())
    torch.testing.assert_close(one_step, direct, rtol=1e-10, atol=1e-12)
    assert (full - one_step).abs().max() > 1e-6


# ------------------------------------------------------------------ a history-blind encoder


def test_history_blind_recursive_policy_is_markovian(world64, tiny_policy):
    # Zero the history columns of the encoder's first layer: h'_t then depends on s_t alone, so
    # the policy is the Markovian MLP s -> encoder -> head. Copy those layers into a
    # MarkovPolicy with hidden (8, 6, 8): same sampled trajectories, same likelihoods, and
    # every bptt mode gives the same likelihoods.
    recursive = jiggle(tiny_policy("recursive"))
    with torch.no_grad():
        recursive.encoder[0].weight[:, 2:] = 0.0
    markov = MarkovPolicy(state_dim=2, action_dim=2, hidden=[8, 6, 8], init_log_std=0.0).double()
    layers = [recursive.encoder[0], recursive.encoder[2], recursive.head[0], recursive.head[2]]
    with torch.no_grad():
        for target, source in zip(markov.mean_net[::2], layers, strict=True):
            target.weight.copy_(source.weight[:, : target.in_features])
            target.bias.copy_(source.bias)
        markov.log_std.copy_(recursive.log_std)

    a, b = roll(world64, recursive), roll(world64, markov)
    for field in ("states", "actions", "log_probs"):
        torch.testing.assert_close(getattr(a, field), getattr(b, field), rtol=1e-12, atol=1e-12)
    assert a.histories.abs().sum() > 0  # the recursive policy does carry a history
    with torch.no_grad():
        markov_lp = markov.log_prob(b.inputs, b.actions, b.histories)
        for bptt in (1, 3, None):
            lp = recursive.log_prob(a.inputs, a.actions, a.histories, bptt)
            torch.testing.assert_close(lp, markov_lp, rtol=1e-12, atol=1e-12)


# ------------------------------------------------------------------ finite differences


@pytest.mark.parametrize("bptt", [1, 3, None])
@pytest.mark.parametrize("name", ["recursive", "gru", "lstm"])
def test_log_prob_gradient_matches_finite_differences(name, bptt, world64, tiny_policy):
    policy = tiny_policy(name)
    r = roll(world64, policy)
    jiggle(policy, scale=0.1)  # evaluate away from the sampling parameters
    coeffs = torch.randn(N, T, generator=gen(3), dtype=F64)

    def objective() -> torch.Tensor:
        return (coeffs * policy.log_prob(r.inputs, r.actions, r.histories, bptt)).sum()

    # float64 central differences with h = 1e-5: measured |error| <= 2.6e-10 over the 9 cases
    # (gradients ~1e-4 .. 1e-2); h = 1e-6 is rounding-limited (~3e-9).
    nonzero = check_gradient_by_central_differences(
        objective, policy, gen(4), rel=1e-5, abs_tol=1e-8
    )
    assert nonzero >= 5


# ------------------------------------------------------------------ the Gaussian head


@pytest.mark.parametrize("name", ["markov", "gru"])
def test_act_samples_the_gaussian_it_scores(name, tiny_policy):
    # 20000 draws at one (state, history). Sample mean within 4 standard errors of the
    # network's mean (4 * 0.61 / sqrt(20000) = 0.017; measured 1.6), sample std within 2% of
    # exp(log_std) (standard error 0.5%; measured 0.2%). The recorded log-likelihood is
    # scipy's Gaussian log-density.
    policy = jiggle(tiny_policy(name))
    n = 20000
    states = torch.tensor([[-0.7, -0.8]], dtype=F64).expand(n, 2)
    history = torch.full((n, policy.history_size), 0.1, dtype=F64)
    noise = torch.randn(n, 2, generator=gen(6), dtype=F64)
    actions, log_p, _, means = policy.act(states, history, noise)
    mean, _ = policy.step(states[:1], history[:1])
    torch.testing.assert_close(means, mean.detach().expand(n, 2))  # the mean act reports
    std = policy.log_std.exp().detach()
    assert ((actions.mean(0) - mean[0]).abs() < 4 * std / n**0.5).all()
    torch.testing.assert_close(actions.std(0), std, rtol=0.02, atol=0)
    expected = norm.logpdf(actions.numpy(), mean.detach().numpy(), std.numpy()).sum(-1)
    torch.testing.assert_close(log_p, torch.from_numpy(expected), rtol=1e-12, atol=1e-12)
    deterministic, _, _, _ = policy.act(states[:1], history[:1], None)
    torch.testing.assert_close(deterministic, mean.detach())


def test_tanh_encoder_keeps_the_history_bounded_where_relu_can_grow_without_bound():
    """h'_t = g(s_t, h'_{t-1}): with an expansive last layer a ReLU output grows geometrically."""
    from hmepol_cli.policies.recursive import RecursivePolicy

    torch.manual_seed(0)
    states = torch.rand(8, 2) * 2 - 1
    sizes = dict(
        state_dim=2, action_dim=2, hidden=[16], encoder_hidden=[], history_size=6, init_log_std=-0.5
    )
    for activation in ("relu", "tanh"):
        policy = RecursivePolicy(encoder_activation=activation, **sizes)
        with torch.no_grad():  # an expansive recursion: identity x 2 on the history inputs
            layer = policy.encoder[0]
            layer.weight.zero_()
            layer.weight[:, 2:] = 2 * torch.eye(6)
            layer.bias.fill_(0.1)
        history = policy.initial_history(8)
        for _ in range(60):
            _, history = policy.step(states, history)
        if activation == "relu":
            assert history.max() > 1e15
        else:
            assert history.abs().max() <= 1.0


@pytest.mark.parametrize("name", ["markov", "recursive", "twohead", "gru", "lstm"])
def test_the_default_policy_starts_as_the_reference_does(name):
    """docs/worlds.md: log-std -1.5 (std 0.22), Xavier-uniform linear layers, near-zero
    mean actions."""
    from hmepol_cli.config import PolicyConfig
    from hmepol_cli.policies import make_policy

    torch.manual_seed(0)
    policy = make_policy(PolicyConfig(name=name), state_dim=2, action_dim=2)
    assert torch.equal(policy.log_std.detach(), torch.full((2,), -1.5))
    linears = [m for m in policy.modules() if isinstance(m, torch.nn.Linear)]
    mean_layer = linears[-1] if name != "twohead" else policy.mean_head[-1]
    for layer in linears:
        bound = (6 / (layer.in_features + layer.out_features)) ** 0.5
        scale = 0.01 if layer is mean_layer else 1.0
        assert layer.weight.abs().max() <= scale * bound
        # Xavier-uniform fills its range: the largest weight is near the bound.
        assert layer.weight.abs().max() > 0.9 * scale * bound
    states = torch.rand(500, 2) * 2 - 1
    history = policy.initial_history(500)
    for _ in range(20):  # along a recursion too
        mean, history = policy.step(states, history)
        assert mean.abs().max() < 0.02
