"""Non-parametric kNN estimators of state entropy and KL divergence (thesis 2.3.4), in nats.

Particles come in mini-batches: ``(M, P, d)``, M mini-batches of P particles of dimension d.
Neighbour sets are searched once per epoch (:func:`nearest_neighbours`) and reused by every
off-policy iteration, since the particles do not move while the policy is updated.

Neighbour convention (public Mepol code): N_i^k holds particle i itself and its k - 1 nearest
other particles, while R_i is the distance to the k-th nearest *other* particle. With uniform
weights w = 1/P, W_i = k/P and eq. 2.7 reduces exactly to eq. 2.6.

Live particles: where an episode ends before T (a Gymnasium world), the steps after its end
produce no state; the reference drops them (its ``real_traj_lengths``). Here a mini-batch keeps
its shape and ``live`` (M, P) marks the particles that exist: the others are no one's neighbour,
have no neighbours, weigh nothing, and P in eqs. 2.6-2.8 is the number of live particles.
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

TINY = 1e-30


@dataclass
class Neighbours:
    """kNN structure of a set of mini-batches of particles."""

    indices: torch.Tensor  # (M, P, k) long: i itself, then its k-1 nearest others (N_i^k)
    radius: torch.Tensor  # (M, P): distance to the k-th nearest other particle (R_i)
    dim: int  # p, the particles' dimension
    # (M, P) bool: the particles that exist (None: all). A particle that does not is listed as
    # its own k neighbours at radius 1, so every term stays finite before it is masked out.
    live: torch.Tensor | None = None

    @property
    def k(self) -> int:
        return self.indices.shape[-1]

    def count(self) -> torch.Tensor | float:
        """P, the live particles of each mini-batch: (M,), or a number when all are live."""
        if self.live is None:
            return float(self.radius.shape[-1])
        return self.live.sum(dim=-1).to(self.radius.dtype)

    def mean(self, values: torch.Tensor) -> torch.Tensor:
        """The mean of per-particle values (M, P) over each mini-batch's live particles. (M,)"""
        if self.live is None:
            return values.mean(dim=-1)
        return torch.where(self.live, values, torch.zeros_like(values)).sum(-1) / self.count()


def nearest_neighbours(
    particles: torch.Tensor, k: int, method: str = "auto", live: torch.Tensor | None = None
) -> Neighbours:
    """Search the k nearest other particles of every particle, within its own mini-batch.

    particles (M, P, d); ``live`` (M, P) bool: only these are searched and found (None: all).
    ``method``: "kdtree" (scipy's cKDTree, one mini-batch per thread), "torch" (pairwise
    distances, chunked; the fast path on a GPU) or "auto" (torch on cuda, kdtree otherwise).
    """
    m, p, d = particles.shape
    if not 0 < k < p:
        raise ValueError(f"k={k} must be in [1, particles per mini-batch - 1 = {p - 1}]")
    if live is not None:
        fewest = int(live.sum(dim=-1).min())
        if fewest <= k:
            raise ValueError(
                f"a mini-batch holds only {fewest} live particles (its episodes ended early) "
                f"and k={k} needs more than k: lower estimator.k or raise algo.batch_size"
            )
    if method == "auto":
        method = "torch" if particles.device.type == "cuda" else "kdtree"
    if method == "kdtree":
        idx, dist = _kdtree_search(particles, k, live)
    elif method == "torch":
        idx, dist = _torch_search(particles, k, live=live)
    else:
        raise ValueError(f"unknown neighbour search {method!r}; choose auto, kdtree or torch")
    if live is not None:  # a particle that does not exist: itself k times, at radius 1
        own = torch.arange(p, device=idx.device).view(1, p, 1).expand_as(idx)
        idx = torch.where(live[..., None], idx, own)
        dist = torch.where(live[..., None], dist, torch.ones_like(dist))
    neighbours = _split_self(idx, dist, k, d)
    neighbours.live = live
    return neighbours


def _kdtree_search(
    particles: torch.Tensor, k: int, live: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    points = particles.detach().to("cpu", torch.float64).numpy()
    idx = np.empty(points.shape[:2] + (k + 1,), dtype=np.int64)
    dist = np.empty(points.shape[:2] + (k + 1,), dtype=np.float64)
    where = None if live is None else [np.flatnonzero(row) for row in live.cpu().numpy()]

    def search(j: int) -> None:
        if where is None:
            dist[j], idx[j] = cKDTree(points[j]).query(points[j], k=k + 1)
            return
        own = where[j]  # the live particles, searched among themselves (the rest: filled later)
        found_dist, found = cKDTree(points[j, own]).query(points[j, own], k=k + 1)
        dist[j], idx[j] = 1.0, 0
        dist[j, own], idx[j, own] = found_dist, own[found]

    # One mini-batch per thread (the query releases the GIL): with small mini-batches this beats
    # cKDTree's own workers, which start their threads anew for every query. As many threads as
    # torch uses, so that a sweep's one-thread jobs stay on one core each.
    with ThreadPoolExecutor(torch.get_num_threads()) as pool:
        list(pool.map(search, range(points.shape[0])))
    device = particles.device
    return torch.from_numpy(idx).to(device), torch.from_numpy(dist).to(device, particles.dtype)


def _torch_search(
    particles: torch.Tensor, k: int, budget: int = 1 << 27, live: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pairwise distances, in pieces of at most ``budget`` entries (0.5 GB in float32): a few
    mini-batches at a time, and a slice of their queries when one mini-batch is too large
    (80,000 particles). Particles that are not ``live`` are never found."""
    x = particles.detach()
    m, p, dim = x.shape
    queries_per_piece = max(1, min(p, budget // p))
    batches_per_piece = max(1, budget // (queries_per_piece * p))
    idx_parts, dist_parts = [], []
    for b0 in range(0, m, batches_per_piece):
        xb = x[b0 : b0 + batches_per_piece]
        idx_rows, dist_rows = [], []
        for q0 in range(0, p, queries_per_piece):
            queries = xb[:, q0 : q0 + queries_per_piece]
            d = torch.cdist(queries, xb)  # (m', q, P)
            if live is not None:
                found = live[b0 : b0 + batches_per_piece, None, :]
                d = d.masked_fill(~found, math.inf)
            _, idx = d.topk(k + 1, dim=-1, largest=False, sorted=True)
            # cdist's matrix-product shortcut leaves ~1e-4 (float32) between coincident
            # particles, where kdtree says 0: recompute the candidates' distances from differences.
            candidates = torch.gather(xb, 1, idx.reshape(len(xb), -1, 1).expand(-1, -1, dim))
            dist = (candidates.view(*idx.shape, dim) - queries[:, :, None]).norm(dim=-1)
            dist, order = dist.sort(dim=-1, stable=True)
            idx_rows.append(idx.gather(-1, order))
            dist_rows.append(dist)
        idx_parts.append(torch.cat(idx_rows, dim=1))
        dist_parts.append(torch.cat(dist_rows, dim=1))
    return torch.cat(idx_parts, dim=0), torch.cat(dist_parts, dim=0)


def _split_self(idx: torch.Tensor, dist: torch.Tensor, k: int, dim: int) -> Neighbours:
    """From the k+1 nearest particles (self usually among them), keep self and k others.

    When particles coincide the search may list a duplicate before i itself, or leave i out;
    then the last candidate is dropped instead, so every row keeps exactly k others.
    """
    m, p, _ = idx.shape
    own = torch.arange(p, device=idx.device).view(1, p, 1)
    is_self = idx == own
    # Column to drop: i itself, or the last one where i is missing (a search lists i at most once).
    drop = torch.where(is_self.any(dim=-1), is_self.to(torch.uint8).argmax(dim=-1), k)
    columns = torch.arange(k, device=idx.device)
    keep = columns + (columns >= drop[..., None])  # (M, P, k): the other columns, in order
    others = idx.gather(-1, keep)
    indices = torch.cat((own.expand(m, p, 1), others[..., : k - 1]), dim=-1)
    return Neighbours(indices=indices, radius=dist.gather(-1, keep[..., k - 1 :])[..., 0], dim=dim)


def log_ball_volume(radius: torch.Tensor, dim: int, eps: float = 1e-10) -> torch.Tensor:
    """log V of the dim-ball of each radius, floored at log(eps).

    The floor keeps coincident particles (an agent pinned in a corner) finite.
    """
    log_unit = (dim / 2) * math.log(math.pi) - math.lgamma(dim / 2 + 1)
    log_v = dim * torch.log(radius.clamp_min(TINY)) + log_unit
    return log_v.clamp_min(math.log(eps))


def floor_share(
    neighbours: Neighbours, eps: float = 1e-10, per_batch: bool = False
) -> torch.Tensor:
    """Share of particles whose ball volume is at the floor eps: where the estimate and its
    gradient are set by eps rather than by the states (coincident particles).

    -> () over all particles, or (M,) per mini-batch."""
    log_unit = (neighbours.dim / 2) * math.log(math.pi) - math.lgamma(neighbours.dim / 2 + 1)
    log_v = neighbours.dim * torch.log(neighbours.radius.clamp_min(TINY)) + log_unit
    at_floor = (log_v <= math.log(eps)).to(torch.float64)
    if per_batch:
        return neighbours.mean(at_floor)
    if neighbours.live is None:
        return at_floor.mean()
    return at_floor[neighbours.live].mean()


def bias_correction(k: int) -> float:
    """log k - psi(k), the bias-correction term of eqs. 2.6 and 2.7."""
    return math.log(k) - float(torch.special.digamma(torch.tensor(float(k), dtype=torch.float64)))


def _log_share(neighbours: Neighbours) -> torch.Tensor | float:
    """log(k / P): a number, or (M, 1) where the mini-batches' live particles differ."""
    p = neighbours.count()
    if isinstance(p, float):
        return math.log(neighbours.k / p)
    return torch.log(neighbours.k / p)[..., None]


def knn_entropy(neighbours: Neighbours, eps: float = 1e-10) -> torch.Tensor:
    """Eq. 2.6, per mini-batch: -(1/P) sum_i log(k / (P V_i)) + log k - psi(k). -> (M,)"""
    log_v = log_ball_volume(neighbours.radius, neighbours.dim, eps)
    return -neighbours.mean(_log_share(neighbours) - log_v) + bias_correction(neighbours.k)


def neighbourhood_weights(weights: torch.Tensor, neighbours: Neighbours) -> torch.Tensor:
    """W_i = sum of w_j over j in N_i^k. weights (M, P) -> (M, P)."""
    m, p, k = neighbours.indices.shape
    gathered = torch.gather(weights, 1, neighbours.indices.reshape(m, p * k)).view(m, p, k)
    return gathered.sum(dim=-1)


def iw_entropy(weights: torch.Tensor, neighbours: Neighbours, eps: float = 1e-10) -> torch.Tensor:
    """Eq. 2.7, per mini-batch: -sum_i (W_i / k) log(W_i / V_i) + log k - psi(k). -> (M,)

    weights (M, P), normalised within each mini-batch. Differentiable in the weights.
    """
    k = neighbours.k
    w_sum = neighbourhood_weights(weights, neighbours)
    log_v = log_ball_volume(neighbours.radius, neighbours.dim, eps)
    # W log W with the log clamped, not xlogy: xlogy's gradient is 0/0 = NaN where a
    # neighbourhood's weights all underflow to 0 (log-ratios hundreds apart after T steps).
    terms = w_sum * (torch.log(w_sum.clamp_min(TINY)) - log_v)
    return -terms.sum(dim=-1) / k + bias_correction(k)


def kl_divergence(weights: torch.Tensor, neighbours: Neighbours) -> torch.Tensor:
    """Eq. 2.8, per mini-batch: (1/P) sum_i log((k/P) / W_i), floored at 0. -> (M,)"""
    w_sum = neighbourhood_weights(weights, neighbours).clamp_min(TINY)
    return neighbours.mean(_log_share(neighbours) - torch.log(w_sum)).clamp_min(0.0)


def importance_weights(
    log_ratios: torch.Tensor, batch_size: int, live: torch.Tensor | None = None
) -> torch.Tensor:
    """Normalised importance weights of the particles of each mini-batch.

    log_ratios (N, T): log pi'(a_t | h_t) - log pi(a_t | h_t) of each step. Particle t of a
    trajectory is the state s_{t+1} reached by its first t+1 actions, so its weight is the product
    of the ratios up to t; weights are normalised over the mini-batch's B trajectories, over its
    ``live`` particles only (N / B, B * T) bool, the others weighing 0 (None: all are live).
    -> (N / B, B * T), in the order of ``particles_by_batch``.
    """
    n, t = log_ratios.shape
    log_w = torch.cumsum(log_ratios, dim=1).reshape(n // batch_size, batch_size * t)
    if live is not None:
        log_w = log_w.masked_fill(~live, -math.inf)
    return torch.softmax(log_w, dim=-1)


def particles_by_batch(states: torch.Tensor, batch_size: int) -> torch.Tensor:
    """(N, T, d) states -> (N / B, B * T, d) particles grouped by mini-batch."""
    n, t, d = states.shape
    return states.reshape(n // batch_size, batch_size * t, d)


class KNNEstimator:
    """The kNN estimators of thesis 2.3.4 with k neighbours, as one object the algorithm talks
    to: the neighbour search (once per epoch), the entropy (eq. 2.6), the IW entropy (eq. 2.7)
    and the KL (eq. 2.8). A new estimator is a class with these methods and an entry in
    ``ESTIMATORS`` (and a ``conf/estimator/<name>.yaml``)."""

    name = "knn"

    def __init__(self, k: int, eps: float = 1e-10, neighbours: str = "auto") -> None:
        self.k, self.eps, self.method = int(k), float(eps), str(neighbours)

    @classmethod
    def from_config(cls, cfg) -> KNNEstimator:
        """The estimator of an ``estimator`` config group entry (k, eps, neighbours)."""
        return cls(cfg.k, cfg.eps, cfg.neighbours)

    def search(self, particles: torch.Tensor, live: torch.Tensor | None = None) -> Neighbours:
        """particles (M, P, d), ``live`` (M, P) bool or None (all) -> their neighbour sets,
        within each mini-batch."""
        return nearest_neighbours(particles, self.k, self.method, live)

    def entropy(self, neighbours: Neighbours) -> torch.Tensor:
        """Eq. 2.6 per mini-batch. -> (M,)"""
        return knn_entropy(neighbours, self.eps)

    def iw_entropy(self, weights: torch.Tensor, neighbours: Neighbours) -> torch.Tensor:
        """Eq. 2.7 per mini-batch, differentiable in the weights (M, P). -> (M,)"""
        return iw_entropy(weights, neighbours, self.eps)

    def kl(self, weights: torch.Tensor, neighbours: Neighbours) -> torch.Tensor:
        """Eq. 2.8 per mini-batch. -> (M,)"""
        return kl_divergence(weights, neighbours)

    def floor_share(self, neighbours: Neighbours) -> torch.Tensor:
        """Share of each mini-batch's particles whose ball volume hit the floor. -> (M,)"""
        return floor_share(neighbours, self.eps, per_batch=True)


# name -> estimator class; the config check, the error messages and make_estimator read it.
ESTIMATORS: dict[str, type[KNNEstimator]] = {"knn": KNNEstimator}


def make_estimator(cfg) -> KNNEstimator:
    """The estimator named by ``cfg.name`` (the ``estimator`` config group)."""
    try:
        kind = ESTIMATORS[cfg.name]
    except KeyError:
        raise ValueError(
            f"unknown estimator {cfg.name!r}; choose one of: {', '.join(ESTIMATORS)}"
        ) from None
    return kind.from_config(cfg)
