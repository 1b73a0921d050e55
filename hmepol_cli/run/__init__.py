"""The run directory: what a run writes and how, one module a job; import from here.

- :mod:`~hmepol_cli.run.layout`: the files of a run directory (the contract) and ``run_config``
- :mod:`~hmepol_cli.run.io`: atomic writes, JSON, CSV, the evaluation archives
- :mod:`~hmepol_cli.run.checkpoint`: checkpoints (``weights_only=True``), a trained policy
- :mod:`~hmepol_cli.run.provenance`: a run's identity and hash, provenance, git state
- :mod:`~hmepol_cli.run.lock`: one writer a directory
- :mod:`~hmepol_cli.run.tables`: the CSV tables, their per-epoch digests, ``read_table``
- :mod:`~hmepol_cli.run.lifecycle`: ``RunDirectory`` and ``writing`` (open, fail, close)
"""

from hmepol_cli.run.checkpoint import (
    load_checkpoint,
    load_trained_policy,
    resolve_checkpoint,
    save_checkpoint,
)
from hmepol_cli.run.io import (
    atomic_write_bytes,
    atomic_write_text,
    load_positions,
    read_json,
    remove_temporaries,
    save_positions,
    write_csv,
    write_json,
)
from hmepol_cli.run.layout import (
    BATCHES_CSV,
    CHECKPOINT,
    COMMANDS,
    CONFIG,
    EPOCHS_CSV,
    EVAL_DIR,
    FINAL_EVAL,
    FINAL_POLICY,
    FINETUNE_CSV,
    LOCK,
    POLICY_KEYS,
    RUN_INFO,
    STEPS_CSV,
    TARGETS_JSON,
    TEMPORARY_SUFFIX,
    epoch_checkpoint,
    run_config,
)
from hmepol_cli.run.lifecycle import RunDirectory, writing
from hmepol_cli.run.lock import RunLock
from hmepol_cli.run.provenance import (
    RESUMABLE_KEYS,
    flat_config,
    hashable_value,
    identity_differences,
    identity_hash,
    identity_of,
    provenance,
)
from hmepol_cli.run.tables import (
    LINE,
    MISSING_FIELDS,
    RunTables,
    read_table,
    row_digest,
    training_tables,
)

__all__ = [
    "BATCHES_CSV",
    "CHECKPOINT",
    "FINAL_POLICY",
    "POLICY_KEYS",
    "COMMANDS",
    "CONFIG",
    "EPOCHS_CSV",
    "EVAL_DIR",
    "FINAL_EVAL",
    "FINETUNE_CSV",
    "LINE",
    "LOCK",
    "MISSING_FIELDS",
    "RESUMABLE_KEYS",
    "RUN_INFO",
    "STEPS_CSV",
    "TARGETS_JSON",
    "TEMPORARY_SUFFIX",
    "RunDirectory",
    "RunLock",
    "RunTables",
    "atomic_write_bytes",
    "atomic_write_text",
    "epoch_checkpoint",
    "flat_config",
    "hashable_value",
    "identity_differences",
    "identity_hash",
    "identity_of",
    "load_checkpoint",
    "load_positions",
    "load_trained_policy",
    "provenance",
    "read_json",
    "read_table",
    "remove_temporaries",
    "resolve_checkpoint",
    "row_digest",
    "run_config",
    "save_checkpoint",
    "save_positions",
    "training_tables",
    "write_csv",
    "write_json",
    "writing",
]
