"""A population of S policies of one architecture, trained as one batched program.

Every parameter is one tensor with a leading member dimension ``(S, ...)``; member s is an
ordinary policy whose weights are the slices ``[s]``. A call (act, log-likelihoods) runs
the policy's own code for every member at once:

- ``torch.vmap`` over the members (``torch.func.functional_call`` on the stacked weights):
  one batched matrix product per layer, what fills a GPU;
- or a loop over the members, each an ordinary call on its slice: the same matrix products as
  S separate runs, which is what a CPU does fastest (batched products are ~25% slower there).

Both compute the same function; ``vectorize="auto"`` picks vmap on CUDA and the loop on a CPU,
where a member then equals a run of its own bit for bit. A single run is a population of one.
:class:`PopulationAdam` is Adam with a learning rate and a step count per
member, updating only the members a mask selects, so each member keeps its own trust region.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence

import torch
from torch import nn
from torch.func import functional_call

from hmepol_cli.policies.base import Policy


class _Method(nn.Module):
    """Calls one method of a policy, so ``functional_call`` can swap in a member's weights."""

    def __init__(self, policy: Policy, method: str) -> None:
        super().__init__()
        self.policy, self.method = policy, method

    def forward(self, *args, **kwargs):
        return getattr(self.policy, self.method)(*args, **kwargs)


class PolicyPopulation:
    """S members of one policy architecture with stacked weights ``params[name]: (S, ...)``."""

    def __init__(self, members: Sequence[Policy], vectorize: bool | str = "auto") -> None:
        if not members:
            raise ValueError("a population needs at least one member")
        self.template = copy.deepcopy(members[0]).requires_grad_(False)
        names = [name for name, _ in members[0].named_parameters()]
        self.params: dict[str, torch.Tensor] = {
            name: torch.stack([dict(m.named_parameters())[name].detach() for m in members])
            .clone()
            .requires_grad_(True)
            for name in names
        }
        self.history_size = members[0].history_size
        self.action_dim = members[0].action_dim
        self.vectorize = vectorize
        self._calls = {m: _Method(self.template, m) for m in ("act", "log_prob", "step")}

    # ------------------------------------------------------------------ shape and place
    @property
    def size(self) -> int:
        return next(iter(self.params.values())).shape[0]

    @property
    def device(self) -> torch.device:
        return next(iter(self.params.values())).device

    @property
    def dtype(self) -> torch.dtype:
        return next(iter(self.params.values())).dtype

    def to(self, device: torch.device | str, dtype: torch.dtype) -> PolicyPopulation:
        self.params = {
            k: v.detach().to(device, dtype).requires_grad_(True) for k, v in self.params.items()
        }
        self.template.to(device, dtype)
        return self

    def _vmapped(self, method: str = "log_prob") -> bool:
        """vmap on a GPU; on a CPU a loop over the members, each an ordinary call on its
        slice: the same products as a run of its own, so a member's numbers equal its run's
        bit for bit (batched products round differently: 1 ulp in a rollout's actions, seen
        with small networks). ``vectorize=True`` (vmap=on) batches a CPU's calls too."""
        if self.vectorize == "auto":
            return self.device.type == "cuda"
        return bool(self.vectorize)

    # ------------------------------------------------------------------ calls
    def call(
        self, method: str, members: torch.Tensor | None, *args: torch.Tensor, **kwargs
    ) -> tuple[torch.Tensor, ...] | torch.Tensor:
        """``template.<method>(*args, **kwargs)`` for each selected member, with its weights.

        ``members``: (S',) long indices (None: all S). Every tensor in ``args`` has a leading
        dimension S' (one slice per selected member); so does every output.
        """
        params = (
            self.params
            if members is None
            else {k: v.index_select(0, members) for k, v in self.params.items()}
        )
        module = self._calls[method]
        if self._vmapped(method):

            def one(p, *a):
                return functional_call(module, {f"policy.{k}": v for k, v in p.items()}, a, kwargs)

            return torch.vmap(one, randomness="error")(params, *args)
        n = next(iter(params.values())).shape[0]
        outputs = [
            functional_call(
                module,
                {f"policy.{k}": v[i] for k, v in params.items()},
                tuple(a[i] for a in args),
                kwargs,
            )
            for i in range(n)
        ]
        if isinstance(outputs[0], tuple):
            return tuple(torch.stack(parts) for parts in zip(*outputs, strict=True))
        return torch.stack(outputs)

    def initial_history(self, members: int, n: int) -> torch.Tensor:
        """h'_0 = 0 for n trajectories of each of ``members`` members. (S', n, H)"""
        return torch.zeros(members, n, self.history_size, device=self.device, dtype=self.dtype)

    @torch.no_grad()
    def act(
        self,
        members: torch.Tensor | None,
        states: torch.Tensor,
        history: torch.Tensor,
        noise: torch.Tensor | None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Policy.act of the selected members. (S', N, d), (S', N, H), (S', N, a) | None ->
        actions (S', N, a), log-likelihoods (S', N), h'_t (S', N, H), means (S', N, a)."""
        if noise is None:  # the mean action; a keyword, so vmap does not map over it
            return self.call("act", members, states, history, noise=None)
        return self.call("act", members, states, history, noise)

    def log_prob(
        self,
        members: torch.Tensor | None,
        states: torch.Tensor,
        actions: torch.Tensor,
        histories: torch.Tensor,
        bptt: int | None,
    ) -> torch.Tensor:
        """Policy.log_prob of the selected members. (S', N, T, ...) -> (S', N, T)"""
        return self.call("log_prob", members, states, actions, histories, bptt=bptt)

    def bytes_per_member(self, particles: int) -> int:
        """An estimate of one member's memory in the off-policy loop: every linear layer's
        output over all particles, kept for the backward pass, its gradient, and a lowered copy
        (x 3), plus the weights, their gradients and Adam's moments (x 4)."""
        width = sum(m.out_features for m in self.template.modules() if isinstance(m, nn.Linear))
        weights = sum(v[0].numel() for v in self.params.values())
        itemsize = torch.finfo(self.dtype).bits // 8
        return itemsize * (3 * particles * (width + self.history_size) + 4 * weights)

    # ------------------------------------------------------------------ members as policies
    def member_state_dict(self, s: int) -> dict[str, torch.Tensor]:
        """Member s as an ordinary policy's state dict (what checkpoints hold)."""
        return {k: v[s].detach().clone() for k, v in self.params.items()}

    def load_member_state_dict(self, s: int, state: dict[str, torch.Tensor]) -> None:
        missing = set(self.params) ^ set(state)
        if missing:
            raise KeyError(f"state dict does not match the policy: {sorted(missing)}")
        with torch.no_grad():
            for k, v in self.params.items():
                v[s].copy_(state[k])

    def member(self, s: int) -> Policy:
        """Member s as an ordinary policy module (a copy)."""
        policy = copy.deepcopy(self.template).requires_grad_(True)
        policy.load_state_dict(self.member_state_dict(s))
        return policy


class PopulationAdam:
    """Adam (torch.optim.Adam's update, no weight decay) on stacked parameters, with a learning
    rate and a step count per member, updating only the members ``mask`` selects."""

    def __init__(
        self,
        params: dict[str, torch.Tensor],
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
    ) -> None:
        self.params = params
        self.betas, self.eps = betas, eps
        first = next(iter(params.values()))
        self.steps = torch.zeros(first.shape[0], device=first.device, dtype=torch.float64)
        self.exp_avg = {k: torch.zeros_like(v) for k, v in params.items()}
        self.exp_avg_sq = {k: torch.zeros_like(v) for k, v in params.items()}

    @torch.no_grad()
    def step(self, grads: dict[str, torch.Tensor], lr: torch.Tensor, mask: torch.Tensor) -> None:
        """One Adam step for the members where ``mask`` (S,) is True, at rates ``lr`` (S,)."""
        beta1, beta2 = self.betas
        steps = torch.where(mask, self.steps + 1, self.steps)
        # Members that never stepped keep step 0: guard their bias corrections (masked anyway).
        safe = steps.clamp_min(1)
        step_size = (lr.double() / (1 - beta1**safe)).to(self._dtype)
        correction2_sqrt = (1 - beta2**safe).sqrt().to(self._dtype)
        for k, p in self.params.items():
            shape = (-1,) + (1,) * (p.dim() - 1)
            keep = mask.view(shape)
            g = grads[k]
            m = torch.where(keep, self.exp_avg[k].lerp(g, 1 - beta1), self.exp_avg[k])
            v = torch.where(
                keep, self.exp_avg_sq[k] * beta2 + (1 - beta2) * g * g, self.exp_avg_sq[k]
            )
            denom = v.sqrt() / correction2_sqrt.view(shape) + self.eps
            update = m / denom * step_size.view(shape)
            p.sub_(torch.where(keep, update, torch.zeros_like(update)))
            self.exp_avg[k], self.exp_avg_sq[k] = m, v
        self.steps = steps

    @torch.no_grad()
    def reset(self, mask: torch.Tensor) -> None:
        """Fresh moments and step count for the members where ``mask`` (S,) is True."""
        self.steps = torch.where(mask, torch.zeros_like(self.steps), self.steps)
        for k, p in self.params.items():
            keep = mask.view((-1,) + (1,) * (p.dim() - 1))
            self.exp_avg[k] = torch.where(keep, 0.0, self.exp_avg[k])
            self.exp_avg_sq[k] = torch.where(keep, 0.0, self.exp_avg_sq[k])

    @property
    def _dtype(self) -> torch.dtype:
        return next(iter(self.params.values())).dtype

    # ------------------------------------------------------------------ member state
    def member_state_dict(self, s: int) -> dict[str, object]:
        return {
            "step": self.steps[s].clone(),
            "exp_avg": {k: v[s].clone() for k, v in self.exp_avg.items()},
            "exp_avg_sq": {k: v[s].clone() for k, v in self.exp_avg_sq.items()},
        }

    def load_member_state_dict(self, s: int, state: dict[str, object]) -> None:
        self.steps[s] = state["step"]
        for k in self.exp_avg:
            self.exp_avg[k][s] = state["exp_avg"][k]
            self.exp_avg_sq[k][s] = state["exp_avg_sq"][k]


class Snapshot:
    """Parameters, gradients and Adam state of every member at its last accepted step, to
    return rejected members to. ``with_optimizer``: whether a rejected step's revert restores
    the Adam state too (a step rejected for a non-finite value always does:
    :meth:`restore`'s ``optimizer_mask``)."""

    def __init__(
        self,
        population: PolicyPopulation,
        optimizer: PopulationAdam,
        grads: dict[str, torch.Tensor],
        with_optimizer: bool = True,
    ) -> None:
        self.with_optimizer = with_optimizer
        self.tensors = [
            {k: v.detach().clone() for k, v in live.items()}
            for live in self._kept(population, optimizer, grads)
        ]
        self.steps = optimizer.steps.clone()

    @staticmethod
    def _kept(
        population: PolicyPopulation,
        optimizer: PopulationAdam,
        grads: dict[str, torch.Tensor],
    ) -> list[dict[str, torch.Tensor]]:
        """The tensors a snapshot keeps: weights, the last gradients, Adam's two moments."""
        return [population.params, grads, optimizer.exp_avg, optimizer.exp_avg_sq]

    @torch.no_grad()
    def take(
        self,
        population: PolicyPopulation,
        optimizer: PopulationAdam,
        grads: dict[str, torch.Tensor],
        mask: torch.Tensor,
    ) -> None:
        """Record the current state of the members where ``mask`` is True."""
        for kept, live in zip(self.tensors, self._kept(population, optimizer, grads), strict=True):
            _where_into(kept, mask, live)
        self.steps = torch.where(mask, optimizer.steps, self.steps)

    @torch.no_grad()
    def restore(
        self,
        population: PolicyPopulation,
        optimizer: PopulationAdam,
        grads: dict[str, torch.Tensor],
        mask: torch.Tensor,
        optimizer_mask: torch.Tensor | None = None,
    ) -> None:
        """Return the members where ``mask`` is True to the recorded weights and gradients, and
        their Adam state too if ``with_optimizer``; the members of ``optimizer_mask`` get their
        Adam state back whatever ``with_optimizer`` says."""
        params, last_grads, *adam = self._kept(population, optimizer, grads)
        _where_into(params, mask, self.tensors[0])
        _where_into(last_grads, mask, self.tensors[1])
        adam_mask = mask if self.with_optimizer else torch.zeros_like(mask)
        if optimizer_mask is not None:
            adam_mask = adam_mask | optimizer_mask
        for live, kept in zip(adam, self.tensors[2:], strict=True):
            _where_into(live, adam_mask, kept)
        optimizer.steps = torch.where(adam_mask, self.steps, optimizer.steps)


def _where_into(
    target: dict[str, torch.Tensor], mask: torch.Tensor, source: dict[str, torch.Tensor]
) -> None:
    """target[k][s] = source[k][s] where mask[s], in place (parameters stay the same leaves)."""
    for k, t in target.items():
        keep = mask.view((-1,) + (1,) * (t.dim() - 1))
        t.copy_(torch.where(keep, source[k], t))
