"""The algorithms by name: what the config accepts and how the report labels and orders them.

An algorithm is a ``conf/algo/<name>.yaml`` (its hyperparameters: the objective over the
mini-batch entropies, the policy it picks) plus one entry here. All three share the trust-region
loop of :mod:`hmepol_cli.mepol`.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Algorithm:
    name: str  # the key of conf/algo/<name>.yaml
    label: str  # in figures and tables
    colour: str  # one colour per algorithm in every figure


ALGORITHMS: dict[str, Algorithm] = {
    a.name: a
    for a in (
        Algorithm("mepol", "Mepol", "#1f77b4"),  # thesis 3.3.1
        Algorithm("alphamepol", "α-Mepol", "#d62728"),  # thesis 3.4.2
        Algorithm("hmepol", "HMepol", "#2ca02c"),  # thesis 4.2
    )
}
SCRATCH = Algorithm("scratch", "from scratch", "#7f7f7f")  # fine-tuning from no run
