"""What the members of a population may differ in: the *member-scalar* keys (issue 23).

A population trains runs as one batched program. Members may differ in any key whose value is
one number per member that changes no tensor's shape: the seed, the corridor's wind, the
learning rate, the KL threshold, the off-policy iterations, the objective and its alpha (Mepol
is alpha-Mepol's objective with alpha = 1: same network, same program) and the algorithm's name.
Everything else (the world, the policy network, N, T, B, k, the device, the precision) shapes
the program, and runs that differ in it cannot be one population.
"""

from __future__ import annotations

from collections.abc import Sequence

from omegaconf import DictConfig

from hmepol_cli.errors import ConfigError
from hmepol_cli.run import RESUMABLE_KEYS, flat_config

MEMBER_KEYS = (
    "seed",
    "wind",
    "env.wind",  # follows wind (the corridor's env file reads it)
    "algo.name",
    "algo.objective",
    "algo.alpha",
    "algo.lr",
    "algo.kl_threshold",
    "algo.max_off_iters",
)
# Keys that say how a population is run, not what its members are.
_HOW = (*RESUMABLE_KEYS, "members", "seeds")


def program_keys(cfg: DictConfig | dict) -> dict[str, object]:
    """The config without its member-scalar keys: what every member of a population shares."""
    return {
        k: v
        for k, v in flat_config(cfg).items()
        if k not in MEMBER_KEYS and not any(k == h or k.startswith(f"{h}.") for h in _HOW)
    }


def program_differences(a: DictConfig | dict, b: DictConfig | dict) -> list[str]:
    """The keys in which two runs differ that forbid them to share a population."""
    pa, pb = program_keys(a), program_keys(b)
    return sorted(k for k in set(pa) | set(pb) if pa.get(k) != pb.get(k))


def check_members(cfgs: Sequence[DictConfig]) -> None:
    """Refuse a population whose members differ in more than member-scalar keys."""
    for cfg in cfgs[1:]:
        differences = program_differences(cfgs[0], cfg)
        if differences:
            raise ConfigError(
                f"the runs of one population may differ only in {', '.join(MEMBER_KEYS)}; "
                f"these differ in {', '.join(differences[:6])}"
            )
