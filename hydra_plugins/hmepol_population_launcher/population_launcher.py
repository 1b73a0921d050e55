"""A Hydra launcher that turns a sweep's jobs into populations, then hands them to another
launcher.

Jobs whose configs differ only in member-scalar keys (the seed, the corridor's wind, the
learning rate, the KL threshold, the off-policy iterations, the objective and alpha, the
algorithm's name: ``hmepol_cli.members``) become one job with ``members=[...]``, which hmepol
trains as one batched program (a population) that writes one ordinary run directory per
member, where the ungrouped job would have written it. Jobs that differ in anything else go
to populations of their own. The grouped jobs run on the ``inner`` launcher: in this process
(basic), in local worker processes (submitit local) or one SLURM job per population::

    hmepol sweep experiment=slope_hmepol seed=0,1,2,3,4,5,6,7 hydra/launcher=population
    hmepol sweep env=corridor algo=mepol wind=0.05,0.4 seed=0,1 hydra/launcher=population
    hmepol sweep ... hydra/launcher=population_slurm hydra.launcher.max_members=16

Hydra finds launchers only in the ``hydra_plugins`` namespace; the grouping is plain Python.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence

from hydra.core.plugins import Plugins
from hydra.core.utils import JobReturn
from hydra.plugins.launcher import Launcher
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig, OmegaConf, open_dict

log = logging.getLogger(__name__)


def _key(override: str) -> str:
    return override.lstrip("+~").partition("=")[0]


def group_jobs(
    job_overrides: Sequence[Sequence[str]],
    program: Callable[[Sequence[str]], dict],
    max_members: int = 0,
) -> tuple[list[list[str]], str]:
    """Jobs whose ``program(overrides)`` (their config without member-scalar keys) is equal,
    as one job ``[<shared overrides>, members=["<own overrides>", ...]]`` per group (at most
    ``max_members`` members each; 0: no limit). Groups keep the order of their first job; a
    group of one stays the job it was. -> (jobs, one line saying how they were grouped)"""
    groups: list[tuple[dict, list[Sequence[str]]]] = []
    for overrides in job_overrides:
        key = program(overrides)
        for known, jobs in groups:
            if known == key:
                jobs.append(overrides)
                break
        else:
            groups.append((key, [overrides]))
    out: list[list[str]] = []
    sizes = []
    for _, jobs_of_group in groups:
        size = max_members or len(jobs_of_group)
        for start in range(0, len(jobs_of_group), size):
            chunk = jobs_of_group[start : start + size]
            sizes.append(len(chunk))
            if len(chunk) == 1:
                out.append(list(chunk[0]))
                continue
            shared = [o for o in chunk[0] if all(o in job for job in chunk)]
            own = [" ".join(o for o in job if o not in shared) for job in chunk]
            if any('"' in o for o in own):
                raise ValueError(f"a member's overrides hold a double quote: {own}")
            quoted = ",".join(f'"{o}"' for o in own)
            out.append([*shared, f"members=[{quoted}]"])
    return out, _summary(len(job_overrides), sizes, groups)


def _summary(n_jobs: int, sizes: list[int], groups: list[tuple[dict, list]]) -> str:
    line = (
        f"{n_jobs} runs as {len(sizes)} job{'s' if len(sizes) != 1 else ''} "
        f"(populations of {', '.join(str(s) for s in sizes)} members)"
    )
    if len(groups) > 1:
        first = groups[0][0]
        reasons = []
        for key, _ in groups[1:]:
            differ = sorted(k for k in set(first) | set(key) if first.get(k) != key.get(k))
            reasons.append(", ".join(differ[:3]) + (", ..." if len(differ) > 3 else ""))
        line += "; not one population: they differ in " + "; ".join(reasons)
    return line


class PopulationLauncher(Launcher):
    def __init__(self, inner: DictConfig, max_members: int = 0, dry_run: bool = False) -> None:
        self.inner_config = inner
        self.max_members = int(max_members)
        self.dry_run = bool(dry_run)
        self.inner: Launcher | None = None
        self.hydra_context: HydraContext | None = None
        self.config: DictConfig | None = None

    def setup(
        self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig
    ) -> None:
        self.hydra_context, self.config = hydra_context, config
        inner_config = config.copy()
        with open_dict(inner_config):
            inner_config.hydra.launcher = OmegaConf.create(
                OmegaConf.to_container(self.inner_config, resolve=False)
            )
        self.inner = Plugins.instance().instantiate_launcher(
            hydra_context=hydra_context, task_function=task_function, config=inner_config
        )

    def _program(self, overrides: Sequence[str]) -> dict:
        """A job's config without its member-scalar keys (composed as Hydra composes it)."""
        from hmepol_cli.members import program_keys

        cfg = self.hydra_context.config_loader.load_sweep_config(self.config, list(overrides))
        with open_dict(cfg):
            cfg.pop("hydra", None)
        return program_keys(cfg)

    def launch(
        self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int
    ) -> Sequence[JobReturn]:
        assert self.inner is not None
        jobs, summary = group_jobs(job_overrides, self._program, self.max_members)
        print(f"hmepol: {summary}", flush=True)
        if self.dry_run:  # the plan only: each population job's overrides, nothing run
            for job in jobs:
                print("  " + " ".join(job), flush=True)
            return []
        return self.inner.launch(jobs, initial_job_idx)
