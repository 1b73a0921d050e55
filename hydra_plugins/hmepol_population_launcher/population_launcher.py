"""A Hydra launcher that turns a sweep's jobs into populations, then hands them to another
launcher.

Jobs whose overrides are equal but for ``seed`` become one job with ``seeds=[...]``, which
hmepol trains as one batched program (a population) that writes one ordinary run directory per
seed, where the ungrouped job would have written it. Every other job goes on unchanged. The
grouped jobs run on the ``inner`` launcher: in this process (basic), in local worker processes
(joblib) or one SLURM job per population (submitit)::

    hmepol sweep experiment=slope_hmepol seed=0,1,2,3,4,5,6,7 hydra/launcher=population
    hmepol sweep ... hydra/launcher=population_slurm hydra.launcher.max_members=4

Hydra finds launchers only in the ``hydra_plugins`` namespace; the grouping is plain Python.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

from hydra.core.plugins import Plugins
from hydra.core.utils import JobReturn
from hydra.plugins.launcher import Launcher
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig, OmegaConf, open_dict

log = logging.getLogger(__name__)


def _key(override: str) -> str:
    return override.lstrip("+~").partition("=")[0]


def group_by_seed(job_overrides: Sequence[Sequence[str]], max_members: int = 0) -> list[list[str]]:
    """Jobs equal but for their ``seed=`` override, as one job ``[..., seeds=[s1,s2,...]]``
    per group (at most ``max_members`` seeds each; 0: no limit). Groups keep the order of
    their first job; a job without a seed, or a group of one, stays as it was."""
    groups: dict[tuple[str, ...], list[Sequence[str]]] = {}
    for overrides in job_overrides:
        rest = tuple(o for o in overrides if _key(o) != "seed")
        if len(rest) == len(overrides):  # no seed to group by
            rest = (*rest, f"#job{len(groups)}")  # a key of its own
        groups.setdefault(rest, []).append(overrides)
    jobs: list[list[str]] = []
    for jobs_of_group in groups.values():
        size = max_members or len(jobs_of_group)
        for start in range(0, len(jobs_of_group), size):
            chunk = jobs_of_group[start : start + size]
            if len(chunk) == 1:
                jobs.append(list(chunk[0]))
                continue
            seeds = [o.partition("=")[2] for job in chunk for o in job if _key(o) == "seed"]
            common = [o for o in chunk[0] if _key(o) != "seed"]
            jobs.append([*common, f"seeds=[{','.join(seeds)}]"])
    return jobs


class PopulationLauncher(Launcher):
    def __init__(self, inner: DictConfig, max_members: int = 0) -> None:
        self.inner_config = inner
        self.max_members = int(max_members)
        self.inner: Launcher | None = None

    def setup(
        self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig
    ) -> None:
        inner_config = config.copy()
        with open_dict(inner_config):
            inner_config.hydra.launcher = OmegaConf.create(
                OmegaConf.to_container(self.inner_config, resolve=False)
            )
        self.inner = Plugins.instance().instantiate_launcher(
            hydra_context=hydra_context, task_function=task_function, config=inner_config
        )

    def launch(
        self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int
    ) -> Sequence[JobReturn]:
        assert self.inner is not None
        jobs = group_by_seed(job_overrides, self.max_members)
        log.info(f"{len(job_overrides)} runs as {len(jobs)} jobs (populations of seeds)")
        return self.inner.launch(jobs, initial_job_idx)
