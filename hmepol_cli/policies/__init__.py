"""Policies by name; ``make_policy`` builds one from the ``policy`` config group."""

from __future__ import annotations

from hmepol_cli.policies.base import Policy
from hmepol_cli.policies.markov import MarkovPolicy
from hmepol_cli.policies.recursive import GRUPolicy, LSTMPolicy, RecursivePolicy, TwoHeadPolicy


def make_policy(cfg, state_dim: int, action_dim: int) -> Policy:
    """Build the policy named by ``cfg.name`` (a PolicyConfig or DictConfig)."""
    hidden = list(cfg.hidden)
    # Runs saved before the option existed used the thesis' ReLU encoder output.
    encoder_activation = getattr(cfg, "encoder_activation", "relu")
    common = dict(
        state_dim=state_dim,
        action_dim=action_dim,
        init_log_std=cfg.init_log_std,
        # Runs saved before these options existed: their weights come from the checkpoint.
        init_weights=getattr(cfg, "init_weights", "xavier"),
        init_mean_scale=getattr(cfg, "init_mean_scale", 0.01),
    )
    if cfg.name == "markov":
        return MarkovPolicy(hidden=hidden, **common)
    if cfg.name == "recursive":
        return RecursivePolicy(
            hidden=hidden,
            encoder_hidden=list(cfg.encoder_hidden),
            history_size=cfg.history_size,
            encoder_activation=encoder_activation,
            **common,
        )
    if cfg.name == "twohead":
        return TwoHeadPolicy(
            hidden=hidden,
            history_size=cfg.history_size,
            encoder_activation=encoder_activation,
            **common,
        )
    if cfg.name == "gru":
        return GRUPolicy(hidden=hidden, history_size=cfg.history_size, **common)
    if cfg.name == "lstm":
        return LSTMPolicy(hidden=hidden, history_size=cfg.history_size, **common)
    raise ValueError(f"unknown policy {cfg.name!r}; choose markov, recursive, twohead, gru or lstm")


__all__ = ["Policy", "make_policy"]
