"""A population's members: what they may differ in, the *member-scalar* keys, and
each member's config and run directory from a job's ``seeds=[...]`` or ``members=[...]``.

A population trains runs as one batched program. Members may differ in any key whose value is
one number per member that changes no tensor's shape: the seed, the corridor's wind, the
learning rate, the KL threshold, the off-policy iterations, the objective and its alpha (Mepol
is alpha-Mepol's objective with alpha = 1: same network, same program) and the algorithm's name.
Everything else (the world, the policy network, N, T, B, k, the device, the precision) shapes
the program, and runs that differ in it cannot be one population.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf, open_dict

from hmepol_cli import sweeps
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


def population_members(cfg: DictConfig) -> list[tuple[DictConfig, Path]]:
    """Each member's config, and the run directory the same job with the member's own
    overrides instead of ``seeds=[...]`` / ``members=[...]`` would have had: a population
    leaves ordinary runs where the ungrouped sweep would. (A single ``hmepol train
    seeds=[...]`` puts them in ``<run dir>/seed<s>``.)

    ``members``: one string per member, its own overrides separated by spaces
    (``"seed=0 wind=0.05"``), composed with the job's others."""
    from hydra import compose as hydra_compose

    hc = HydraConfig.get()
    common = common_overrides(list(hc.overrides.task))
    members = []
    for i, overrides in enumerate(member_overrides(cfg)):
        member = member_config(cfg, common, overrides, hydra_compose)
        if hc.mode == RunMode.MULTIRUN:
            run_dir = Path(str(hc.sweep.dir)) / _member_subdir(hc, [*common, *overrides])
        elif cfg.seeds:
            run_dir = Path(hc.runtime.output_dir) / f"seed{member.seed}"
        else:
            run_dir = Path(hc.runtime.output_dir) / f"member{i}"
        members.append((member, run_dir))
    return members


def common_overrides(overrides: list[str]) -> list[str]:
    """A population job's overrides that every member shares (all but seeds= and members=)."""
    return [o for o in overrides if _key(o) not in ("seeds", "members")]


def member_overrides(cfg: DictConfig) -> list[list[str]]:
    """Each member's own overrides: ``seed=<s>`` for each of ``seeds=[...]``, or one entry of
    ``members=[...]`` split at its spaces."""
    if cfg.seeds:
        seeds = [int(s) for s in cfg.seeds]
        if len(set(seeds)) != len(seeds):
            raise ConfigError(f"seeds={seeds} holds a seed twice")
        return [[f"seed={s}"] for s in seeds]
    return [str(m).split() for m in cfg.members]


def member_config(
    cfg: DictConfig, common: list[str], own: list[str], compose: Callable[..., DictConfig]
) -> DictConfig:
    """A member's config: the job's with another seed (``seeds=[...]``), or the config
    ``compose`` (Hydra's compose API) makes of the job's common overrides and the member's."""
    if cfg.seeds:
        member = cfg.copy()
        with open_dict(member):
            member.seed, member.seeds = int(own[0].partition("=")[2]), None
        return member
    return compose(config_name="config", overrides=[*common, *own])


def _key(override: str) -> str:
    """The key an override sets (``+a.b=1`` -> ``a.b``)."""
    return override.lstrip("+~").partition("=")[0]


def _member_subdir(hc: DictConfig, overrides: list[str]) -> str:
    """hydra.sweep.subdir of the job with these overrides (a population member's own job)."""
    naming = hc.job.config.override_dirname
    dirname = sweeps.override_dirname(
        overrides, list(naming.exclude_keys), naming.item_sep, naming.kv_sep
    )
    job = OmegaConf.create({"hydra": OmegaConf.to_container(hc, resolve=False)})
    job.hydra.job.override_dirname = dirname
    return str(job.hydra.sweep.subdir)
