"""Copy the small files of runs somewhere they can be kept (docs/results/):

    python -m hmepol_cli.report.export outputs/full docs/results/full

For every run directory under SOURCE (a directory with run.json): config.yaml, run.json,
commands.log (when each invocation started: what shows a study's runs began after its pre-
registration), epochs.csv, finetune.csv and targets.json as they are, steps.csv (diagnostics)
gzipped as steps.csv.gz, and eval/final.npz with its positions stored as float16 (a heatmap bin
is 0.04 wide: float16's 1e-3 resolution on [-6, 6] changes no figure, and halves the file), and
the final policy as policy.pt: the last checkpoint's weights only (no optimizer state, a few MB
at most), which ``hmepol finetune init=<exported run>`` starts from. The resume kit
(checkpoints/last.pt, Adam state included) is copied only with ``--kits``: it lets a run go on
on another machine, and it is what makes a clone heavy. batches.csv and pictures are left out.
``--no-diagnostics`` leaves steps.csv.gz out, ``--no-policy`` the final policy and
``--no-positions`` the final positions (what a study keeps when the repository's size budget has
no room for them: docs/studies.md; such a run is in every curve and table of the report, in no
map); each also removes the copy an earlier export left in DEST, which would describe only part
of the run.
``hmepol
report DEST`` then rebuilds every figure and table from these files alone. Unfinished runs are
copied too (a later export brings them up to date); the report lists them as skipped. Every
file is written whole or not at all, so an export interrupted while runs go on (a periodic save
beside them) never leaves a half-copied table that the report would read.
"""

from __future__ import annotations

import argparse
import gzip
import io
import warnings
from pathlib import Path

import numpy as np

from hmepol_cli.errors import RunDirError
from hmepol_cli.run import (
    CHECKPOINT,
    COMMANDS,
    CONFIG,
    EPOCHS_CSV,
    EVAL_DIR,
    FINAL_EVAL,
    FINAL_POLICY,
    FINETUNE_CSV,
    POLICY_KEYS,
    RUN_INFO,
    STEPS_CSV,
    TARGETS_JSON,
    atomic_write_bytes,
    load_checkpoint,
    load_positions,
    save_checkpoint,
)

KEPT = (CONFIG, RUN_INFO, COMMANDS, EPOCHS_CSV, FINETUNE_CSV, TARGETS_JSON)


def export_runs(
    source: Path,
    dest: Path,
    kits: bool = False,
    *,
    diagnostics: bool = True,
    policy: bool = True,
    positions: bool = True,
) -> list[Path]:
    """Copy the kept files of every run under ``source`` to the same place under ``dest``: its
    diagnostics (steps.csv.gz), final positions and final policy unless told not to (removing an
    earlier export's copy then), and with ``kits`` its resume kit."""
    exported = []
    for marker in sorted(Path(source).rglob(RUN_INFO)):
        run_dir = marker.parent
        target = Path(dest) / run_dir.relative_to(source)
        target.mkdir(parents=True, exist_ok=True)
        for name in KEPT:
            if (run_dir / name).is_file():
                atomic_write_bytes(target / name, (run_dir / name).read_bytes())
        if not diagnostics:
            (target / f"{STEPS_CSV}.gz").unlink(missing_ok=True)
        elif (run_dir / STEPS_CSV).is_file():
            data = gzip.compress((run_dir / STEPS_CSV).read_bytes(), mtime=0)
            atomic_write_bytes(target / f"{STEPS_CSV}.gz", data)
        final = run_dir / EVAL_DIR / f"{FINAL_EVAL}.npz"
        if not positions:
            (target / EVAL_DIR / f"{FINAL_EVAL}.npz").unlink(missing_ok=True)
        elif final.is_file():
            arrays = {
                f"positions_c{c}": p.astype(np.float16) for c, p in load_positions(final).items()
            }
            (target / EVAL_DIR).mkdir(exist_ok=True)
            buffer = io.BytesIO()
            np.savez_compressed(buffer, **arrays)
            atomic_write_bytes(target / EVAL_DIR / f"{FINAL_EVAL}.npz", buffer.getvalue())
        checkpoint = run_dir / CHECKPOINT
        if not policy:
            (target / FINAL_POLICY).unlink(missing_ok=True)
        if checkpoint.is_file() and (policy or kits):
            try:
                state = load_checkpoint(checkpoint)
            except RunDirError as error:
                warnings.warn(f"{error}: its final policy is not exported", stacklevel=2)
                exported.append(target)
                continue
            if policy:
                weights = {k: state[k] for k in POLICY_KEYS if k in state}
                save_checkpoint(target / FINAL_POLICY, weights)
            if kits:
                (target / CHECKPOINT).parent.mkdir(exist_ok=True)
                atomic_write_bytes(target / CHECKPOINT, checkpoint.read_bytes())
        exported.append(target)
    return exported


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m hmepol_cli.report.export", description=__doc__.splitlines()[0]
    )
    parser.add_argument("source", type=Path, help="folder holding run directories")
    parser.add_argument("dest", type=Path, help="where their small files go")
    parser.add_argument("--kits", action="store_true", help="also the resume kits "
                        "(checkpoints/last.pt, Adam state included): only when moving to another "
                        "machine would lose hours of compute")  # fmt: skip
    parser.add_argument("--no-diagnostics", action="store_true",
                        help="leave steps.csv.gz out (and an earlier export's)")  # fmt: skip
    parser.add_argument("--no-policy", action="store_true",
                        help="leave the final policy out (and an earlier export's)")  # fmt: skip
    parser.add_argument("--no-positions", action="store_true",
                        help="leave the final positions (eval/final.npz) out (and an earlier "
                        "export's): the run is then in no map")  # fmt: skip
    args = parser.parse_args(argv)
    runs = export_runs(
        args.source,
        args.dest,
        args.kits,
        diagnostics=not args.no_diagnostics,
        policy=not args.no_policy,
        positions=not args.no_positions,
    )
    print(f"{len(runs)} runs exported to {args.dest}")


if __name__ == "__main__":
    main()
