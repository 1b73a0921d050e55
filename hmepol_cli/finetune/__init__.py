"""Fine-tuning (thesis 5.2, Fig. 5.9): TRPO on sparse goal-reaching tasks.

``task`` (goal tasks and their targets), ``trpo`` (the solver, importable alone) and ``runner``
(the ``hmepol finetune`` run). The runner's names are re-exported lazily, so that importing the
solver does not import the runner.
"""

from __future__ import annotations

from importlib import import_module

_EXPORTS = {
    "finetune": "hmepol_cli.finetune.runner",
    "check_finetune": "hmepol_cli.finetune.runner",
    "initial_policy": "hmepol_cli.finetune.runner",
    "trpo_settings": "hmepol_cli.finetune.runner",
    "TRPO": "hmepol_cli.finetune.trpo",
    "TRPOSettings": "hmepol_cli.finetune.trpo",
    "GoalTask": "hmepol_cli.finetune.task",
    "make_tasks": "hmepol_cli.finetune.task",
}


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = list(_EXPORTS)
