"""Policies by name; ``make_policy`` builds one from the ``policy`` config group.

A new policy is a :class:`Policy` subclass with a ``from_config`` class method, one entry in
``POLICIES`` and one ``conf/policy/<name>.yaml``.
"""

from __future__ import annotations

from hmepol_cli.policies.base import Policy
from hmepol_cli.policies.markov import MarkovPolicy
from hmepol_cli.policies.recursive import GRUPolicy, LSTMPolicy, RecursivePolicy, TwoHeadPolicy

POLICIES: dict[str, type[Policy]] = {
    "markov": MarkovPolicy,
    "recursive": RecursivePolicy,
    "twohead": TwoHeadPolicy,
    "gru": GRUPolicy,
    "lstm": LSTMPolicy,
}


def make_policy(cfg, state_dim: int, action_dim: int) -> Policy:
    """Build the policy named by ``cfg.name`` (a PolicyConfig or DictConfig)."""
    try:
        kind = POLICIES[cfg.name]
    except KeyError:
        raise ValueError(
            f"unknown policy {cfg.name!r}; choose one of: {', '.join(POLICIES)}"
        ) from None
    start = dict(
        init_log_std=cfg.init_log_std,
        # Runs saved before these options existed: their weights come from the checkpoint.
        init_weights=getattr(cfg, "init_weights", "xavier"),
        init_mean_scale=getattr(cfg, "init_mean_scale", 0.01),
    )
    return kind.from_config(cfg, state_dim, action_dim, **start)


__all__ = ["POLICIES", "Policy", "make_policy"]
