r"""Algorithm 3.1 (Mepol), as Mepol, alpha-Mepol and HMepol run it (thesis 3.3.1, 3.4.2, 4.2.3).

    for epoch = 0, 1, 2, ...                                              Trainer
        draw N trajectories of length T, B per mini-batch, one configuration   epoch()
        particles: the states visited; k nearest neighbours, searched once
        theta' <- theta
        while KL(d_T(theta) || d_T(theta')) <= delta, at most max_off_iters:   off_policy_loop()
            theta' <- theta' + Adam step of lr on grad objective(theta' | theta)
        theta <- theta'                 (the last theta' inside the trust region)

The objective is the mean (Mepol, HMepol) or the CVaR_alpha (alpha-Mepol, eq. 3.3) of the
mini-batches' importance-weighted entropies (eq. 2.7); the KL is eq. 2.8, per mini-batch, averaged
(:class:`hmepol_cli.surrogate.Surrogate`). When a step leaves the trust region the learning
rate is backtracked (``OffPolicySettings.backtracking``):

- ``reference`` (the public Mepol code's ``use_backtracking``, the default): *any* rejected step,
  the first or a later one, returns theta' to the last accepted parameters and is retried at
  lr / factor^j, j = 1 .. tries - 1, until one is accepted or the tries run out; either way the
  epoch ends there (a run that leaves the region after 12 steps makes one smaller 13th step);
- ``first_step`` (this project's rule before it followed the reference): only a rejected *first*
  step is retried, at lr / factor, lr / factor^2, ... (at most ``tries`` times), and the epoch goes
  on at the reduced rate; a later rejection ends the epoch without a smaller step.

What a rejection restores (``restore``): ``parameters`` (the reference: Adam's moments and step
count keep the rejected step's gradient) or ``parameters_and_adam`` (the Adam state too).

A *population* (:mod:`hmepol_cli.population`) runs this for S members at once: every member has
its own learning rate, step count, backtracking and stopping point, and the member masks below
(``searching``, ``accepted``, ``rejected``; shape (S,)) say which members an operation touches.
A single run is a population of one.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from hmepol_cli import estimators
from hmepol_cli.envs import World
from hmepol_cli.population import PolicyPopulation, PopulationAdam, Snapshot
from hmepol_cli.records import EpochStats, StepRecord, UpdateResult
from hmepol_cli.rollout import Rollout, collect, draw_configurations, non_finite_rows
from hmepol_cli.settings import MemberSettings, OffPolicySettings, member_objectives
from hmepol_cli.surrogate import Estimate, Surrogate


# ------------------------------------------------------------------ one epoch
def epoch(
    world: World,
    population: PolicyPopulation,
    optimizer: PopulationAdam,
    settings: OffPolicySettings,
    members: Sequence[int],
    generators: Sequence[torch.Generator],
    graphs: dict | None = None,
) -> list[EpochStats]:
    """One epoch of Algorithm 3.1 for the population's ``members`` (member i acting with
    randomness from ``generators[i]``). -> their stats, in that order.

    A member whose rollout holds a non-finite position, action or history stops before the
    neighbour search: its stats name what broke (``broken``) and it takes no update."""
    s = settings
    t0 = time.perf_counter()
    rows = torch.tensor(list(members), device=world.device)
    configurations = torch.stack(
        [draw_configurations(world, s.trajectories, s.batch_size, g) for g in generators]
    )  # (S', N): one configuration per mini-batch, repeated over its B trajectories
    selection = None if list(members) == list(range(population.size)) else rows
    rollout = collect(world, population, selection, configurations, s.horizon, generators,
                      graphs=graphs)  # fmt: skip
    batch_configurations = configurations[:, :: s.batch_size].cpu().numpy()  # (S', M)
    broken = non_finite_rows(rollout)
    healthy = [i for i in range(len(members)) if i not in broken]
    if broken:
        keep = torch.tensor(healthy, dtype=torch.long, device=world.device)
        rollout, rows = rollout.rows(keep), rows.index_select(0, keep)
    t1 = time.perf_counter()
    stats = iter(_update(world, population, optimizer, settings, rollout, rows, t0, t1)
                 if healthy else [])  # fmt: skip
    out = []
    for i in range(len(members)):
        stat = _broken_stats(broken[i], batch_configurations[i]) if i in broken else next(stats)
        stat.batch_configurations = batch_configurations[i]
        out.append(stat)
    return out


def _update(
    world: World,
    population: PolicyPopulation,
    optimizer: PopulationAdam,
    settings: OffPolicySettings,
    rollout: Rollout,
    members: torch.Tensor,
    t0: float,
    t1: float,
) -> list[EpochStats]:
    """Particles, neighbours, entropies and the off-policy loop of the members of a rollout."""
    s, n = settings, len(members)
    # The entropy is on the world's chosen features of the states (a Gymnasium world's
    # env.features; the whole position in the 2-D worlds).
    features = world.entropy_features(rollout.particles)
    particles = estimators.particles_by_batch(features.flatten(0, 1), s.batch_size)
    # Where episodes end early, the steps after an end produce no particle (as the reference).
    live = None
    if rollout.alive is not None:
        live = rollout.alive.flatten(0, 1).reshape(particles.shape[:2])  # (S' M, P)
    neighbours = s.estimator.search(particles, live)  # (S' M, P, k)
    entropies = s.estimator.entropy(neighbours).view(n, -1)  # (S', M), eq. 2.6
    t2 = time.perf_counter()
    surrogate = Surrogate(population, rollout, neighbours, members, settings)
    updates = off_policy_loop(population, optimizer, surrogate, members, settings)
    t3 = time.perf_counter()
    seconds = {"collect": t1 - t0, "neighbours": t2 - t1, "update": t3 - t2, "epoch": t3 - t0}
    floor = s.estimator.floor_share(neighbours).view(n, -1)
    low, high = world.action_bounds()
    clipped = ((rollout.actions < low) | (rollout.actions > high)).flatten(1)
    host = torch.stack(  # one transfer for every per-member statistic
        [
            _amax_per_member(rollout.histories).double(),
            _amax_per_member(rollout.actions).double(),
            floor.mean(-1).double(),
            member_objectives(entropies, members.tolist(), s).double(),
            rollout.log_std.double().mean(-1),
            clipped.double().mean(-1),
        ]
    ).cpu()
    entropies_host = entropies.double().cpu().numpy()
    stats = []
    for i in range(n):
        history_max, action_max, floor_i, objective_i, log_std, clip_share = host[:, i].tolist()
        stats.append(
            EpochStats(
                entropies=entropies_host[i],
                batch_configurations=np.zeros(0),
                objective=objective_i,
                update=updates[i],
                history_max=history_max,
                action_max=action_max,
                floor_share=floor_i,
                log_std=log_std,
                clip_share=clip_share,
                seconds=seconds,
                broken=list(updates[i].non_finite),
            )
        )
    return stats


# ------------------------------------------------------------------ the off-policy loop
@dataclass
class _Search:
    """One member's place in the off-policy loop: its learning rate and counts, what the last
    step it tried broke, and what its last accepted theta' gave (what the epoch reports)."""

    hyper: MemberSettings
    row: int  # the member's row in the rollout
    lr: float
    entropies: np.ndarray  # (M,) IW entropies at the last accepted theta'
    kl: float = 0.0
    kl_exact: float = math.nan
    off_iters: int = 0
    backtracks: int = 0
    non_finite: list[str] = field(default_factory=list)  # of the last step tried
    stopped: list[str] = field(default_factory=list)  # what no step could mend
    steps: list[StepRecord] = field(default_factory=list)

    def accept(
        self, kl: float, kl_exact: float, entropies: np.ndarray, s: OffPolicySettings
    ) -> bool:
        """The step stays inside the trust region: theta' is the last accepted one now.
        -> whether to step again"""
        self.off_iters += 1
        self.kl, self.kl_exact = kl, kl_exact
        self.entropies = entropies
        done = self.off_iters >= self.hyper.max_off_iters
        if s.backtracking == "reference":
            done |= self.backtracks > 0  # at most one step after backtracking
        return not done

    def revert(self, s: OffPolicySettings) -> bool:
        """The step left the trust region (or broke a number): theta' returns to the last
        accepted one and the learning rate is backtracked. -> whether to try again"""
        if s.backtracking == "reference":  # any rejection: retry at lr0 / factor^j
            retry = self.backtracks < s.backtrack_tries - 1
            if retry:
                self.backtracks += 1
                self.lr = self.hyper.lr / s.backtrack_factor**self.backtracks
        else:  # first_step: only a rejected first step is retried, at a reduced rate
            retry = self.off_iters == 0 and self.backtracks < s.backtrack_tries
            if retry:
                self.lr /= s.backtrack_factor
                self.backtracks += 1
        return retry


def off_policy_loop(
    population: PolicyPopulation,
    optimizer: PopulationAdam,
    surrogate: Surrogate,
    members: torch.Tensor,
    settings: OffPolicySettings,
) -> list[UpdateResult]:
    """The while-loop of Algorithm 3.1 for every member in ``members`` (S',), one batched
    program (:func:`reference_loop` is the same for one member, written as the thesis does;
    tests/test_reference_loop.py holds them equal). -> one result per member, in that order.

    Every iteration steps the members still searching, judges each member's step, and then,
    for all of them at once, *accepts* (records theta' as the last accepted) or *reverts*
    (returns theta' to it). Gradients are each member's own (the members' objectives share no
    parameter)."""
    s, device, size = settings, population.device, population.size
    params = population.params
    if s.adam_reset:
        optimizer.reset(_mask(members.tolist(), size, device))
    # theta' = theta: the IW objective equals the on-policy one and the KL is 0.
    start = surrogate(torch.arange(len(members), device=device))
    grads = _gradients(start.objective, params)
    # A value that is not finite at the sampling policy cannot be stepped away from.
    start_finite = _finite_quantities(start, grads, optimizer, members).tolist()  # (4, S')
    start_entropies = start.entropies.detach().double().cpu().numpy()  # (S', M), per row
    last_accepted = Snapshot(population, optimizer, grads, s.restore == "parameters_and_adam")
    hyper = s.members  # population member -> its own lr, delta, iterations, objective
    threshold = torch.tensor([h.kl_threshold for h in hyper], dtype=torch.float64, device=device)
    searches: dict[int, _Search] = {}
    searching = torch.zeros(size, dtype=torch.bool, device=device)  # members still stepping
    for i, m in enumerate(members.tolist()):
        search = searches[m] = _Search(hyper[m], i, hyper[m].lr, start_entropies[i])
        search.kl_exact = 0.0 if start.kl_exact is not None else math.nan
        broken = [n for n, ok in zip(NON_FINITE, start_finite, strict=True) if not ok[i]]
        search.stopped = [f"{name} at the sampling policy" for name in broken]
        searching[m] = hyper[m].max_off_iters > 0 and not broken
    while bool(searching.any()):
        lr = torch.tensor([searches[m].lr if m in searches else h.lr for m, h in enumerate(hyper)],
                          dtype=torch.float64, device=device)  # fmt: skip
        optimizer.step(grads, lr, searching)  # theta' <- theta' + Adam step
        stepped = searching.nonzero()[:, 0].tolist()
        stepped_members = torch.tensor(stepped, device=device)
        estimate = surrogate(surrogate.rows(stepped))
        new_grads = _gradients(estimate.objective, params)
        finite = _finite_quantities(estimate, new_grads, optimizer, stepped_members)  # (4, R)
        grads = _merge(grads, new_grads, _mask(stepped, size, device))
        limit = threshold.index_select(0, stepped_members).to(estimate.kl.dtype)
        in_region = (estimate.kl <= limit) & finite.all(0)
        # One host sync per iteration: on a GPU the loop waits for the device only here.
        dtype = estimate.kl.dtype
        numbers = [in_region.to(dtype), estimate.kl.detach(), *finite.to(dtype)]
        if s.diagnostics:
            exact = estimate.kl_exact
            numbers += [
                estimate.kl_one_step.detach(),
                torch.full_like(estimate.kl, math.nan) if exact is None else exact,
                estimate.entropies.detach().mean(-1),
                estimate.objective.detach(),
            ]
        host = torch.stack(numbers).tolist()
        flags, kl_values, finite_host, diagnosed = host[0], host[1], host[2:6], host[6:]
        inside = [bool(f) for f in flags]  # KL <= delta, every quantity finite
        for i, m in enumerate(stepped):
            search = searches[m]
            if s.diagnostics:
                search.steps.append(
                    StepRecord(len(search.steps), search.lr, inside[i], kl_values[i],
                               *(row[i] for row in diagnosed))
                )  # fmt: skip
            search.non_finite = [n for n, ok in zip(NON_FINITE, finite_host, strict=True)
                                 if not ok[i]]  # fmt: skip
        accept, revert, broken = (torch.zeros(size, dtype=torch.bool, device=device)
                                  for _ in range(3))  # fmt: skip
        for i, m in enumerate(stepped):
            accept[m], revert[m] = inside[i], not inside[i]
            broken[m] = not inside[i] and bool(searches[m].non_finite)
        # accept: theta' is the last accepted policy now
        last_accepted.take(population, optimizer, grads, accept)
        if any(inside):
            kept = estimate.entropies.detach().double().cpu().numpy()
            for i, m in enumerate(stepped):
                if inside[i]:
                    exact_kl = diagnosed[1][i] if s.diagnostics else searches[m].kl_exact
                    searching[m] = searches[m].accept(kl_values[i], exact_kl, kept[i], s)
        # revert: back to the last accepted theta' (and Adam's state, by the rule or on a NaN)
        last_accepted.restore(population, optimizer, grads, revert, optimizer_mask=broken)
        for i, m in enumerate(stepped):
            if not inside[i]:
                searching[m] = searches[m].revert(s)  # the learning rate backtracked, or stop
    for search in searches.values():  # every step tried broke a number: nothing mends it
        if search.off_iters == 0 and search.non_finite and not search.stopped:
            search.stopped = [f"{name} at every step tried" for name in search.non_finite]
    check = surrogate.full_precision()  # a lowered precision, checked once an epoch
    kl_full, entropy_full = (
        ([math.nan] * len(members),) * 2 if check is None else [c.tolist() for c in check]
    )
    return [
        UpdateResult(
            entropies=search.entropies,
            kl=search.kl,
            off_iters=search.off_iters,
            backtracks=search.backtracks,
            lr=search.lr,
            kl_exact=search.kl_exact if s.diagnostics else math.nan,
            kl_full_precision=kl_full[search.row],
            entropy_iw_full_precision=entropy_full[search.row],
            steps=search.steps,
            non_finite=search.stopped,
        )
        for search in (searches[m] for m in members.tolist())
    ]


def reference_loop(
    population: PolicyPopulation,
    optimizer: PopulationAdam,
    surrogate: Surrogate,
    settings: OffPolicySettings,
) -> UpdateResult:
    """Algorithm 3.1's while-loop for a population of one member, as the thesis writes it, with
    the reference's backtracking and this project's rules (``backtracking``, ``restore``, the
    exact trust region, ``adam_reset``, non-finite values) spelled out one at a time: the
    executable specification :func:`off_policy_loop` is tested equal to, bit for bit on a CPU
    (tests/test_reference_loop.py). Nothing else calls it."""
    s, hyper, params = settings, settings.members[0], population.params
    one = torch.ones(1, dtype=torch.bool, device=population.device)
    if s.adam_reset:
        optimizer.reset(one)
    row = torch.zeros(1, dtype=torch.long, device=population.device)
    estimate = surrogate(row)  # theta' = theta: the on-policy entropy, KL 0
    grads = _gradients(estimate.objective, params)
    kept = Snapshot(population, optimizer, grads, s.restore == "parameters_and_adam")
    result = UpdateResult(estimate.entropies.detach().double().cpu().numpy()[0], 0.0, 0, 0,
                          hyper.lr, 0.0 if estimate.kl_exact is not None else math.nan)  # fmt: skip
    broken = _broken(estimate, grads, optimizer)
    result.non_finite = [f"{name} at the sampling policy" for name in broken]
    steps = hyper.max_off_iters if not broken else 0
    while result.off_iters < steps:
        optimizer.step(grads, torch.tensor([result.lr], dtype=torch.float64), one)
        estimate = surrogate(row)
        grads = _gradients(estimate.objective, params)
        broken = _broken(estimate, grads, optimizer)
        inside = not broken and bool(estimate.kl <= hyper.kl_threshold)  # KL <= delta
        if s.diagnostics:
            result.steps.append(_step_record(len(result.steps), result.lr, inside, estimate))
        if inside:  # accept: theta' is the last accepted policy now
            kept.take(population, optimizer, grads, one)
            result.off_iters += 1
            result.kl = float(estimate.kl.detach())
            result.kl_exact = result.steps[-1].kl_exact if s.diagnostics else result.kl_exact
            result.entropies = estimate.entropies.detach().double().cpu().numpy()[0]
            if s.backtracking == "reference" and result.backtracks > 0:
                break  # one step after backtracking ends the epoch
            continue
        # revert: back to the last accepted theta' (and Adam's state, by the rule or on a NaN)
        kept.restore(population, optimizer, grads, one, optimizer_mask=one if broken else None)
        if s.backtracking == "reference":  # retry at lr0 / factor^j, at most tries - 1 times
            if result.backtracks == s.backtrack_tries - 1:
                break
            result.backtracks += 1
            result.lr = hyper.lr / s.backtrack_factor**result.backtracks
        else:  # first_step: only a rejected first step is retried, at a reduced rate
            if result.off_iters > 0 or result.backtracks == s.backtrack_tries:
                break
            result.backtracks += 1
            result.lr /= s.backtrack_factor
    if result.off_iters == 0 and broken and not result.non_finite:
        result.non_finite = [f"{name} at every step tried" for name in broken]
    if not s.diagnostics:
        result.kl_exact = math.nan
    check = surrogate.full_precision()
    if check is not None:
        result.kl_full_precision, result.entropy_iw_full_precision = (float(c) for c in check)
    return result


def _broken(estimate: Estimate, grads: dict[str, torch.Tensor], optimizer: PopulationAdam):
    """The names of one member's quantities that are not finite (NON_FINITE's order)."""
    member = torch.zeros(1, dtype=torch.long, device=optimizer.steps.device)
    finite = _finite_quantities(estimate, grads, optimizer, member)
    return [name for name, ok in zip(NON_FINITE, finite[:, 0].tolist(), strict=True) if not ok]


def _step_record(step: int, lr: float, accepted: bool, estimate: Estimate) -> StepRecord:
    """steps.csv's row of one member's step (in the estimate's precision, as the loop's)."""
    exact = estimate.kl_exact
    numbers = torch.stack([
        estimate.kl.detach(),
        estimate.kl_one_step.detach(),
        torch.full_like(estimate.kl, math.nan) if exact is None else exact,
        estimate.entropies.detach().mean(-1),
        estimate.objective.detach(),
    ])[:, 0].tolist()  # fmt: skip
    return StepRecord(step, lr, accepted, *numbers)


NON_FINITE = ("objective", "KL", "gradient of the objective", "Adam state")


def _finite_quantities(
    estimate: Estimate,
    grads: dict[str, torch.Tensor],
    optimizer: PopulationAdam,
    members: torch.Tensor,
) -> torch.Tensor:
    """Which of the rows' quantities are finite, in the order of NON_FINITE: the objective,
    the KL, the new gradient and the Adam moments of each row's member. -> (4, R) bool"""

    def per_member(tensors: Sequence[torch.Tensor]) -> torch.Tensor:
        finite = torch.stack([torch.isfinite(t).flatten(1).all(1) for t in tensors]).all(0)
        return finite.index_select(0, members)

    adam = [*optimizer.exp_avg.values(), *optimizer.exp_avg_sq.values()]
    return torch.stack(
        [
            torch.isfinite(estimate.objective.detach()),
            torch.isfinite(estimate.kl.detach()),
            per_member(list(grads.values())),
            per_member(adam),
        ]
    )


def _gradients(value: torch.Tensor, params: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Gradient of -objective of each member (they share no parameter: one backward)."""
    grads = torch.autograd.grad(-value.sum(), list(params.values()), allow_unused=True)
    return {
        k: torch.zeros_like(v) if g is None else g
        for (k, v), g in zip(params.items(), grads, strict=True)
    }


def _mask(members: Sequence[int], size: int, device: torch.device) -> torch.Tensor:
    mask = torch.zeros(size, dtype=torch.bool, device=device)
    mask[list(members)] = True
    return mask


def _merge(
    old: dict[str, torch.Tensor], new: dict[str, torch.Tensor], mask: torch.Tensor
) -> dict[str, torch.Tensor]:
    """new[k] for the members in ``mask`` (S,), old[k] for the others."""
    return {
        k: torch.where(mask.view((-1,) + (1,) * (g.dim() - 1)), new[k], g) for k, g in old.items()
    }


# ------------------------------------------------------------------ rollouts of some members
def _broken_stats(names: list[str], configurations: np.ndarray) -> EpochStats:
    nan = np.full(len(configurations), math.nan)
    return EpochStats(
        entropies=nan,
        batch_configurations=configurations,
        objective=math.nan,
        update=UpdateResult(nan, math.nan, 0, 0, math.nan),
        history_max=math.nan,
        action_max=math.nan,
        broken=names,
    )


def _amax_per_member(values: torch.Tensor) -> torch.Tensor:
    """Largest |value| of each member's slice. (S', ...) -> (S',)"""
    if values.numel() == 0:
        return torch.zeros(values.shape[0], device=values.device, dtype=values.dtype)
    return values.abs().flatten(1).amax(dim=1)
