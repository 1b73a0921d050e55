"""The kNN estimators of thesis 2.3.4 (eqs. 2.6-2.8), importance weights, and the objectives.

Statistical tests use fixed seeds; each tolerance is stated beside the test with the spread
measured over independent seeds (mean +- std of the error), so a failure means the estimator
moved, not that the dice were unlucky.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.special import betaln, digamma, gammaln

from hmepol_cli import objectives
from hmepol_cli.estimators import (
    importance_weights,
    iw_entropy,
    kl_divergence,
    knn_entropy,
    nearest_neighbours,
    particles_by_batch,
)
from hmepol_cli.rollout import collect_single, draw_configurations
from tests.conftest import check_gradient_by_central_differences

F64 = torch.float64
METHODS = ("kdtree", "torch")
few = settings(max_examples=30, deadline=None)


def gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


@st.composite
def particle_sets(draw, max_p: int = 80, max_d: int = 4, max_k: int = 10):
    """(M, P, d) float64 Gaussian particles (distinct distances almost surely) and a valid k."""
    m = draw(st.integers(1, 3))
    p = draw(st.integers(3, max_p))
    d = draw(st.integers(1, max_d))
    k = draw(st.integers(1, min(max_k, p - 1)))
    seed = draw(st.integers(0, 2**31 - 1))
    x = np.random.default_rng(seed).normal(size=(m, p, d))
    return torch.from_numpy(x), k


def brute_force(x: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Others by distance, from the full distance matrix: (P, k) indices, (P, k) distances."""
    dist = np.linalg.norm(x[:, None, :] - x[None, :, :], axis=-1)
    np.fill_diagonal(dist, np.inf)
    order = np.argsort(dist, axis=1, kind="stable")[:, :k]
    return order, np.take_along_axis(dist, order, axis=1)


# ------------------------------------------------------------------ neighbour search


@few
@given(particle_sets())
def test_both_neighbour_methods_match_brute_force(case):
    x, k = case
    for method in METHODS:
        nb = nearest_neighbours(x, k, method)
        assert nb.indices.shape == (*x.shape[:2], k) and nb.dim == x.shape[-1]
        for j, batch in enumerate(x.numpy()):
            order, dist = brute_force(batch, k)
            # N_i^k = i itself, then its k - 1 nearest others; R_i = distance to the k-th other.
            assert (nb.indices[j, :, 0] == torch.arange(x.shape[1])).all()
            np.testing.assert_array_equal(nb.indices[j, :, 1:].numpy(), order[:, : k - 1])
            np.testing.assert_allclose(nb.radius[j].numpy(), dist[:, k - 1], rtol=1e-12)


def test_neighbour_methods_agree_in_float32():
    # Measured at 2000 particles in [-1, 1]^2, k = 30: radii differ by <= 1.5e-8 and every
    # neighbour slot agrees (a near-tie may still swap a pair, hence 0.9999).
    x = torch.rand(1, 2000, 2, generator=gen(0)) * 2 - 1
    a, b = (nearest_neighbours(x, 30, method) for method in METHODS)
    assert a.radius.dtype == b.radius.dtype == torch.float32
    torch.testing.assert_close(a.radius, b.radius, atol=1e-7, rtol=0)
    assert (a.indices == b.indices).float().mean() > 0.9999


def test_neighbour_methods_agree_on_coincident_float32_particles():
    # An agent pinned against a wall revisits one position whose coordinates are not round
    # numbers: both searches must find distance 0 (cdist's matrix-product shortcut alone
    # gave up to 5e-4 here, and a different entropy from kdtree).
    x = torch.rand(1, 200, 2, generator=gen(15)) * 2 - 1
    x[0, ::2] = x[0, 1::2]
    a, b = (nearest_neighbours(x, 1, method) for method in METHODS)
    assert (a.radius == 0).all() and (b.radius == 0).all()
    torch.testing.assert_close(knn_entropy(a), knn_entropy(b))


@pytest.mark.parametrize("budget", [300 * 300, 3 * 300 * 300, 1000])
def test_the_torch_search_in_pieces_equals_the_whole_search(budget):
    # A few mini-batches at a time, and a slice of the queries when one is too large: the same
    # neighbours as the search in one piece, and as kdtree's distances.
    from hmepol_cli.estimators import _kdtree_search, _torch_search

    x = torch.rand(7, 300, 2, generator=gen(16), dtype=torch.float64)
    whole, pieces = _torch_search(x, 5), _torch_search(x, 5, budget=budget)
    assert torch.equal(whole[0], pieces[0]) and torch.equal(whole[1], pieces[1])
    torch.testing.assert_close(pieces[1], _kdtree_search(x, 5)[1], rtol=0, atol=1e-15)


def test_bad_k_and_method_are_refused():
    x = torch.zeros(1, 5, 2)
    with pytest.raises(ValueError, match="k=5"):
        nearest_neighbours(x, 5)
    with pytest.raises(ValueError, match="unknown neighbour search"):
        nearest_neighbours(x, 2, method="ball")


# ------------------------------------------------------------------ eq. 2.6


@few
@given(particle_sets())
def test_knn_entropy_is_the_kozachenko_leonenko_formula(case):
    # Eq. 2.6 rewritten: log P - psi(k) + log c_d + d * mean(log R_i), c_d the unit-ball volume;
    # computed here from a brute-force distance matrix, independently of the package.
    x, k = case
    m, p, d = x.shape
    log_unit_ball = (d / 2) * math.log(math.pi) - gammaln(d / 2 + 1)
    expected = [
        math.log(p) - digamma(k) + log_unit_ball + d * np.log(brute_force(b, k)[1][:, -1]).mean()
        for b in x.numpy()
    ]
    got = knn_entropy(nearest_neighbours(x, k))
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize(
    "low, high, tol",
    [
        # log 4. Measured error of the mean of 4 mini-batches: +0.086 +- 0.003 (boundary bias).
        ((-1.0, -1.0), (1.0, 1.0), 0.13),
        # log 1.5; the long thin rectangle has more boundary per area: +0.117 +- 0.006.
        ((0.0, 0.0), (3.0, 0.5), 0.17),
    ],
)
def test_knn_entropy_of_uniform_rectangles(low, high, tol):
    # 4 mini-batches of P = 2000, k = 30 (the thesis' mini-batch size and k).
    low, high = torch.tensor(low, dtype=F64), torch.tensor(high, dtype=F64)
    x = low + (high - low) * torch.rand(4, 2000, 2, generator=gen(1), dtype=F64)
    error = knn_entropy(nearest_neighbours(x, 30)).mean().item() - math.log((high - low).prod())
    # Balls that cross the boundary are partly empty, so the estimate is biased upwards.
    assert 0 < error < tol


def test_knn_entropy_boundary_bias_shrinks_with_more_particles():
    # Uniform on [-1, 1]^2, k = 30. Measured errors: P = 500: 0.167 +- 0.011,
    # P = 2000: 0.086 +- 0.007, P = 20000: 0.026 +- 0.001 (one mini-batch each).
    errors = []
    for p in (500, 2000, 20000):
        x = torch.rand(1, p, 2, generator=gen(p), dtype=F64) * 2 - 1
        errors.append(knn_entropy(nearest_neighbours(x, 30)).item() - math.log(4))
    assert errors[0] > errors[1] > errors[2] > 0
    assert errors[2] < 0.04


@pytest.mark.parametrize(
    "cov, tol",
    [
        # Measured error of the mean of 4 x 20000, k = 4: -0.0045 +- 0.002.
        ([[1.0, 0.6], [0.6, 0.5]], 0.02),
        # Measured: -0.009 +- 0.006.
        ([[1.0, 0.3, 0.1], [0.3, 0.8, -0.2], [0.1, -0.2, 0.4]], 0.03),
    ],
)
def test_knn_entropy_of_gaussians(cov, tol):
    # h = 0.5 log((2 pi e)^d det Sigma). A small k keeps the smoothing bias small, and then the
    # tolerance is tight enough to catch a missing log k - psi(k) (0.13 at k = 4) or an
    # off-by-one neighbour (d/2 log(4/3) = 0.29 in 2-D).
    cov = torch.tensor(cov, dtype=F64)
    d = cov.shape[0]
    x = torch.randn(4, 20000, d, generator=gen(2), dtype=F64) @ torch.linalg.cholesky(cov).T
    truth = 0.5 * math.log((2 * math.pi * math.e) ** d * torch.det(cov).item())
    assert abs(knn_entropy(nearest_neighbours(x, 4)).mean().item() - truth) < tol


# ------------------------------------------------------------------ eqs. 2.7 and 2.8


@few
@given(particle_sets())
def test_iw_entropy_with_uniform_weights_is_eq_2_6(case):
    x, k = case
    nb = nearest_neighbours(x, k)
    uniform = torch.full(x.shape[:2], 1 / x.shape[1], dtype=F64)
    torch.testing.assert_close(iw_entropy(uniform, nb), knn_entropy(nb), rtol=1e-12, atol=1e-12)


@pytest.fixture(scope="module")
def beta_reweighted():
    """Particles uniform on [0, 1]^2 (f), weights f'/f for f' = Beta(2, 2) x Beta(2, 2).

    4 mini-batches of 20000, k = 4.
    """
    x = torch.rand(4, 20000, 2, generator=gen(3), dtype=F64)
    q = 36 * (x * (1 - x)).prod(dim=-1)
    return q / q.sum(dim=-1, keepdim=True), nearest_neighbours(x, 4)


def test_iw_entropy_estimates_the_target_entropy(beta_reweighted):
    # h(Beta(2, 2)) = log B(2, 2) - 2 psi(2) + 2 psi(4); the target's entropy is twice that,
    # -0.250 (the sampling distribution's is 0). Measured error: +0.002 +- 0.002.
    weights, nb = beta_reweighted
    truth = 2 * (betaln(2, 2) - 2 * digamma(2) + 2 * digamma(4))
    assert abs(iw_entropy(weights, nb).mean().item() - truth) < 0.02


def test_kl_estimate_between_known_distributions(beta_reweighted):
    # With w ~ f'/f and particles drawn from f, the terms log((k/P) / W_i) average
    # E_f[log f/f'] = KL(f || f'): the *sampling* distribution against the target one,
    # -E_U[log q] = 4 - 2 log 6 = 0.4165 (the other direction, KL(f' || f) = 0.250, is far
    # outside the tolerance). Measured error: -0.017 +- 0.001 (k = 4, P = 20000).
    weights, nb = beta_reweighted
    truth = 4 - 2 * math.log(6)
    assert abs(kl_divergence(weights, nb).mean().item() - truth) < 0.05


def test_kl_of_a_policy_with_itself_is_zero():
    # Equal policies: every log-ratio is 0, the weights uniform.
    x = torch.rand(3, 500, 2, generator=gen(4), dtype=F64)
    nb = nearest_neighbours(x, 10)
    weights = importance_weights(torch.zeros(30, 50, dtype=F64), batch_size=10)
    assert torch.all(kl_divergence(weights, nb).abs() <= 1e-14)


@few
@given(particle_sets(), st.floats(0.0, 20.0), st.integers(0, 2**31 - 1))
def test_kl_is_eq_2_8_floored_at_zero(case, spread, seed):
    """Eq. 2.8 computed here from scratch (brute-force neighbours: i and its k - 1 nearest
    others, NumPy), then floored at 0 as the public Mepol code does, for any weights."""
    x, k = case
    nb = nearest_neighbours(x, k)
    log_w = spread * torch.randn(x.shape[:2], generator=gen(seed), dtype=F64)
    weights = torch.softmax(log_w, dim=-1)
    kl = kl_divergence(weights, nb)
    points, w = x.numpy(), weights.numpy()
    m, p, _ = points.shape
    for b in range(m):
        distances = np.linalg.norm(points[b][:, None] - points[b][None], axis=-1)
        np.fill_diagonal(distances, np.inf)
        nearest = np.argsort(distances, axis=1, kind="stable")[:, : k - 1]
        w_sum = w[b] + w[b][nearest].sum(axis=1)
        raw = np.mean(np.log((k / p) / np.maximum(w_sum, 1e-30)))
        assert float(kl[b]) == pytest.approx(max(raw, 0.0), rel=1e-9, abs=1e-12)


# ------------------------------------------------------------------ coincident particles


def _pinned_in_corner(dtype):
    # 4 trajectories of 50 steps: three wander, one is stuck in the corner (1, 1) throughout.
    x = torch.rand(1, 200, 2, generator=gen(5), dtype=dtype) * 2 - 1
    x[0, 150:] = 1.0
    return x


def _many_duplicates(dtype):
    x = torch.rand(1, 200, 2, generator=gen(6), dtype=dtype)
    x[0, ::2] = x[0, 1::2]  # every particle has a twin
    x[0, :60] = 0.25  # and 60 share one point
    return x


def _all_equal(dtype):
    return torch.full((2, 100, 2), 0.3, dtype=dtype)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("make", [_all_equal, _pinned_in_corner, _many_duplicates])
def test_coincident_particles_stay_finite(make, method, dtype):
    x = make(dtype)
    m, p, _ = x.shape
    k = 10
    nb = nearest_neighbours(x, k, method)
    # Every row still holds i itself first and k - 1 distinct others.
    assert (nb.indices[..., 0] == torch.arange(p)).all()
    assert (nb.indices[..., 1:] != nb.indices[..., :1]).all()
    assert all(len(set(row.tolist())) == k for row in nb.indices.reshape(-1, k))
    assert torch.isfinite(knn_entropy(nb)).all()

    log_ratios = torch.randn(m * 4, p // 4, generator=gen(7), dtype=dtype).requires_grad_()
    weights = importance_weights(log_ratios, batch_size=4)
    entropy, kl = iw_entropy(weights, nb), kl_divergence(weights, nb)
    assert torch.isfinite(entropy).all() and torch.isfinite(kl).all()
    (entropy.sum() + kl.sum()).backward()
    assert torch.isfinite(log_ratios.grad).all()


@pytest.mark.parametrize("method", METHODS)
def test_all_coincident_particles_hit_the_volume_floor(method):
    # Every R_i = 0, so every V_i is floored at eps:
    # eq. 2.6 = log(P / k) + log(eps) + log k - psi(k).
    eps, k, p = 1e-10, 10, 100
    nb = nearest_neighbours(_all_equal(torch.float32), k, method)
    expected = math.log(p) + math.log(eps) - digamma(k)
    torch.testing.assert_close(knn_entropy(nb, eps), torch.full((2,), expected), rtol=1e-6, atol=0)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_underflowing_weights_keep_gradients_finite(dtype):
    # Log-ratios hundreds of nats apart (a long trajectory's cumulative product) make whole
    # neighbourhoods' weights exactly 0; W log W must still have a finite gradient there.
    x = torch.rand(1, 40, 2, generator=gen(8), dtype=dtype)
    nb = nearest_neighbours(x, 5)
    log_ratios = (300 * torch.randn(4, 10, generator=gen(9), dtype=dtype)).requires_grad_()
    weights = importance_weights(log_ratios, batch_size=4)
    assert (weights == 0).sum() > 30
    entropy, kl = iw_entropy(weights, nb), kl_divergence(weights, nb)
    (entropy.sum() + kl.sum()).backward()
    assert torch.isfinite(entropy).all() and torch.isfinite(kl).all()
    assert torch.isfinite(log_ratios.grad).all()


# ------------------------------------------------------------------ importance weights


def test_importance_weights_by_hand():
    # 4 trajectories of 3 steps, mini-batches of 2. Per-step ratios pi'/pi:
    ratios = torch.tensor(
        [[2.0, 0.5, 1.0], [1.0, 1.0, 4.0], [0.5, 0.5, 2.0], [1.0, 3.0, 1.0]], dtype=F64
    )
    # Particle t's weight is the product of the ratios up to t, normalised over the mini-batch:
    # batch 0: products [2, 1, 1 | 1, 1, 4], sum 10; batch 1: [.5, .25, .5 | 1, 3, 3], sum 8.25.
    expected = torch.tensor(
        [[2, 1, 1, 1, 1, 4], [0.5, 0.25, 0.5, 1, 3, 3]], dtype=F64
    ) / torch.tensor([[10.0], [8.25]], dtype=F64)
    weights = importance_weights(ratios.log(), batch_size=2)
    torch.testing.assert_close(weights, expected, rtol=1e-14, atol=0)


@few
@given(st.integers(1, 4), st.integers(1, 5), st.integers(1, 6), st.floats(0, 50))
def test_importance_weights_sum_to_one_per_mini_batch(batches, batch_size, horizon, spread):
    log_ratios = spread * torch.randn(batches * batch_size, horizon, generator=gen(10), dtype=F64)
    weights = importance_weights(log_ratios, batch_size)
    assert weights.shape == (batches, batch_size * horizon)
    torch.testing.assert_close(weights.sum(dim=-1), torch.ones(batches, dtype=F64))


def test_particles_line_up_with_their_weights():
    # Entry (j, b * T + t) of both is trajectory j * B + b at step t.
    n, t, b = 6, 4, 3
    ids = torch.arange(n * t, dtype=F64).view(n, t)
    particles = particles_by_batch(torch.stack((ids, -ids), dim=-1), b)
    assert particles.shape == (n // b, b * t, 2)
    # A ratio of e at one step of one trajectory raises exactly that trajectory's later particles.
    log_ratios = torch.zeros(n, t, dtype=F64)
    log_ratios[4, 2] = 1.0
    weights = importance_weights(log_ratios, b)
    raised = (weights > weights.min(dim=-1, keepdim=True).values).nonzero().tolist()
    traj_step = [(j * b + i // t, i % t) for j, i in raised]
    assert traj_step == [(4, 2), (4, 3)]
    assert [particles[j, i, 0].item() for j, i in raised] == [4 * t + 2, 4 * t + 3]


# ------------------------------------------------------------------ gradient of eq. 2.7


@pytest.mark.parametrize("name, bptt", [("markov", 1), ("recursive", 1), ("recursive", None)])
def test_iw_entropy_gradient_matches_finite_differences(name, bptt, world64, tiny_policy):
    # float64 throughout; 6 trajectories of 15 steps in the slope world, mini-batches of 3, k = 5.
    policy = tiny_policy(name)
    configurations = draw_configurations(world64, 6, 3, gen(11))
    rollout = collect_single(world64, policy, configurations, horizon=15, generator=gen(12))
    nb = nearest_neighbours(particles_by_batch(rollout.particles, 3), 5)
    with torch.no_grad():  # evaluate away from the sampling policy, so the weights vary
        for param in policy.parameters():
            param.add_(0.1 * torch.randn(param.shape, generator=gen(13), dtype=F64))

    def objective() -> torch.Tensor:
        log_p = policy.log_prob(rollout.inputs, rollout.actions, rollout.histories, bptt)
        weights = importance_weights(log_p - rollout.log_probs, batch_size=3)
        return iw_entropy(weights, nb).mean()

    # float64 central differences, h = 1e-5: measured error <= 3.4e-8 relative and 8.5e-11
    # absolute (gradients from 2e-4 to 55); no ReLU kink is crossed.
    checked = check_gradient_by_central_differences(
        objective, policy, gen(14), rel=1e-6, abs_tol=1e-9
    )
    assert checked >= 3  # not all trivially zero


# ------------------------------------------------------------------ objectives (eq. 3.3)


def test_cvar_by_hand():
    values = torch.tensor([5.0, 1.0, 3.0, 2.0, 4.0])
    assert objectives.cvar(values, 0.4).item() == pytest.approx(1.5)  # lowest 2
    assert objectives.cvar(values, 0.5).item() == pytest.approx(2.0)  # ceil(2.5) = 3 lowest
    assert objectives.cvar(values, 0.01).item() == pytest.approx(1.0)  # at least one
    assert objectives.cvar(values, 1.0).item() == pytest.approx(objectives.mean(values).item())
    # 0.07 * 100 is 7.000000000000001 in floating point: still 7 values, not 8.
    assert objectives.cvar(torch.arange(100.0), 0.07).item() == pytest.approx(3.0)


@few
@given(st.lists(st.floats(-100, 100), min_size=1, max_size=40), st.data())
def test_cvar_is_the_mean_of_the_lowest_ceil_alpha_m(values, data):
    m = len(values)
    count = data.draw(st.integers(1, m))
    # alpha in ((count - 1) / M, count / M]: ceil(alpha * M) = count.
    alpha = (count - data.draw(st.floats(0.0, 0.99))) / m
    x = torch.tensor(values, dtype=F64)
    expected = np.sort(values)[:count].mean()
    assert objectives.cvar(x, alpha).item() == pytest.approx(expected, rel=1e-9, abs=1e-9)


def test_cvar_gradient_reaches_only_the_tail():
    x = torch.tensor([5.0, 1.0, 3.0, 2.0, 4.0], requires_grad=True)
    objectives.cvar(x, 0.4).backward()
    torch.testing.assert_close(x.grad, torch.tensor([0.0, 0.5, 0.0, 0.5, 0.0]))


@pytest.mark.parametrize("alpha", [0.0, -0.5, 1.5])
def test_cvar_refuses_alpha_outside_0_1(alpha):
    with pytest.raises(ValueError, match="alpha"):
        objectives.cvar(torch.ones(4), alpha)


# ------------------------------------------------------------------ particles that do not exist
@st.composite
def partly_live_sets(draw):
    """Particles (M, P, d) with a live mask (M, P) holding more than k live in every mini-batch;
    the dead ones sit on one point (an episode's last state, repeated), as a Gymnasium world
    leaves them."""
    x, k = draw(particle_sets(max_p=60))
    m, p, _ = x.shape
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    live = rng.random((m, p)) < draw(st.floats(0.3, 1.0))
    for j in range(m):  # at least k + 1 live particles
        live[j, rng.permutation(p)[: k + 1]] = True
        x[j, ~live[j]] = x[j, np.flatnonzero(live[j])[0]].clone()
    return x, torch.from_numpy(live), k


@few
@given(partly_live_sets(), st.sampled_from(METHODS))
def test_particles_that_do_not_exist_take_no_part_in_the_estimates(case, method):
    """Each mini-batch's entropy (eq. 2.6), IW entropy (eq. 2.7) and KL (eq. 2.8) with a live
    mask equal the same estimates over its live particles alone, with weights renormalised over
    them; the dead particles get no weight and nobody's neighbour is dead."""
    x, live, k = case
    m, p, _ = x.shape
    nb = nearest_neighbours(x, k, method, live)
    log_ratios = torch.randn(m, p, dtype=F64, generator=gen(k))  # one trajectory a batch
    weights = importance_weights(log_ratios, 1, live)
    log_w = log_ratios.cumsum(-1)
    assert (weights[~live] == 0).all()
    found = live.gather(1, nb.indices.flatten(1)).view(nb.indices.shape)
    assert bool(found[live].all())  # a live particle's neighbours are all live
    entropy, iw, kl = knn_entropy(nb), iw_entropy(weights, nb), kl_divergence(weights, nb)
    for j in range(m):
        alone = x[j][live[j]][None]
        nb_alone = nearest_neighbours(alone, k, method)
        w_alone = torch.softmax(log_w[j][live[j]], dim=-1)[None]
        torch.testing.assert_close(entropy[j], knn_entropy(nb_alone)[0])
        torch.testing.assert_close(iw[j], iw_entropy(w_alone, nb_alone)[0])
        torch.testing.assert_close(kl[j], kl_divergence(w_alone, nb_alone)[0])
        torch.testing.assert_close(weights[j][live[j]], w_alone[0])


def test_a_mini_batch_with_too_few_live_particles_is_refused_in_one_line():
    x = torch.rand(2, 10, 2, dtype=F64, generator=gen(0))
    live = torch.ones(2, 10, dtype=torch.bool)
    live[1, 3:] = False  # 3 live particles, k = 3 needs 4
    with pytest.raises(ValueError, match="only 3 live particles.*k=3"):
        nearest_neighbours(x, 3, "kdtree", live)
