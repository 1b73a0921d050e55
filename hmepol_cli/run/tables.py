"""The CSV tables of a run directory: written atomically a whole epoch at a time, each epoch's
rows digested so that a resume keeps exactly the rows its checkpoint covers."""

from __future__ import annotations

import csv
import hashlib
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from hmepol_cli.errors import RunDirError
from hmepol_cli.run.io import write_csv
from hmepol_cli.run.layout import BATCHES_CSV, EPOCHS_CSV, STEPS_CSV


def row_digest(rows: pd.DataFrame) -> str:
    """A digest of some rows' values, the same whether taken from the rows as written or as
    read back from their CSV (numbers compared as floats, by their exact value)."""

    def canon(value: Any) -> str:
        if isinstance(value, bool | np.bool_):
            return str(bool(value))
        if isinstance(value, int | float | np.number):
            number = float(value)
            return "nan" if math.isnan(number) else repr(number)
        if value is None or (isinstance(value, float) and math.isnan(value)):
            return "nan"
        return str(value)

    columns = [c for c in rows.columns if c != LINE]
    text = "\n".join(
        "|".join(canon(v) for v in row) for row in rows[columns].itertuples(index=False)
    )
    return hashlib.sha256(("|".join(columns) + "\n" + text).encode()).hexdigest()[:16]


LINE = "_line"  # the file line a row was read from (1 = the header), kept out of the files


class RunTables:
    """The CSV files of a run directory (training: epochs.csv, batches.csv and, with
    diagnostics, steps.csv; fine-tuning: finetune.csv), rewritten atomically whenever rows are
    added, so a reader never sees half a file.

    Every row carries an ``epoch``. ``digests`` holds, per table, a digest of each epoch's rows
    as they were written; a checkpoint keeps the digests of the epochs it covers, and on resume
    :meth:`verify` keeps exactly those rows: rows past the checkpoint are dropped, and a row the
    checkpoint covers that is missing, changed, cut, duplicated or unreadable is refused in one
    line naming the file and the line. So every epoch appears exactly once, as it was written."""

    def __init__(self, run_dir: Path, names: Sequence[str], optional: Sequence[str] = ()) -> None:
        """``optional`` tables are written only once they have rows."""
        self.run_dir, self.optional = Path(run_dir), set(optional)
        self.damaged: dict[str, list[tuple[int, str]]] = {}
        self.tables = {name: self._read(name) for name in (*names, *optional)}
        self.digests: dict[str, list[str]] = {name: [] for name in self.tables}

    def __getitem__(self, name: str) -> pd.DataFrame:
        return self.tables[name].drop(columns=[LINE], errors="ignore")

    def _read(self, name: str) -> pd.DataFrame:
        """The rows of a table that can be read, with the line each came from; the lines that
        cannot (a wrong number of fields, an epoch that is not a whole number) in ``damaged``."""
        path = self.run_dir / name
        self.damaged[name] = []
        if not path.is_file():
            return pd.DataFrame()
        try:
            text = path.read_text()
        except UnicodeDecodeError:
            raise RunDirError(f"{path} is not a text file; restore it or start over") from None
        lines = text.splitlines()
        if not lines:
            return pd.DataFrame()
        header = next(csv.reader([lines[0]]))
        epoch = header.index("epoch") if "epoch" in header else None
        good = []
        for number, line in enumerate(lines[1:], start=2):
            fields = next(csv.reader([line]), [])
            if len(fields) != len(header):
                self.damaged[name].append((number, f"{len(fields)} fields for {len(header)}"))
            elif epoch is not None and not fields[epoch].isdigit():
                self.damaged[name].append((number, f"epoch {fields[epoch]!r}"))
            else:
                good.append(number)
        keep = set(good)
        frame = pd.read_csv(path, skiprows=lambda i: i > 0 and i + 1 not in keep)
        frame[LINE] = good
        return frame

    def truncate(self, next_epoch: int) -> None:
        """Keep only epochs < next_epoch (the ones the checkpoint covers)."""
        for name, table in self.tables.items():
            if len(table):
                self.tables[name] = table[table["epoch"] < next_epoch]
            self.digests[name] = self.digests[name][:next_epoch]
        self.damaged = {name: [] for name in self.tables}
        self._flush()

    def verify(self, next_epoch: int, digests: dict[str, list[str]] | None) -> None:
        """Resume at ``next_epoch``: check the rows of the epochs the checkpoint covers against
        its ``digests`` (None: a checkpoint from before they existed: epochs.csv must then hold
        each epoch exactly once), then drop every row past them."""
        for name, table in self.tables.items():
            path = self.run_dir / name
            covered = table[table["epoch"] < next_epoch] if len(table) else table
            last = int(covered[LINE].max()) if len(covered) else 1
            for number, reason in self.damaged.get(name, []):
                if number < last:  # among the rows the checkpoint covers
                    raise RunDirError(
                        f"{path} line {number} cannot be read ({reason}): it is among the "
                        f"rows of the {next_epoch} epochs the checkpoint covers; restore the "
                        "file, or start the run over in a new directory"
                    )
            expected = None if digests is None else digests.get(name)
            if expected is None:
                if name == EPOCHS_CSV and list(covered.get("epoch", [])) != list(range(next_epoch)):
                    raise RunDirError(
                        f"{path} does not hold epochs 0..{next_epoch - 1} exactly once (it has "
                        f"{sorted(set(covered.get('epoch', [])))[:8]}...); restore the file, or "
                        "start the run over in a new directory"
                    )
                continue
            for e in range(next_epoch):
                rows = covered[covered["epoch"] == e] if len(covered) else covered
                if row_digest(rows) == expected[e]:
                    continue
                where = f"line {int(rows[LINE].iloc[0])}" if len(rows) else "no row"
                raise RunDirError(
                    f"{path} {where} (epoch {e}) is not what the run wrote (missing, changed, "
                    f"cut or duplicated); restore the file, or start the run over in a new "
                    "directory"
                )
            self.digests[name] = list(expected[:next_epoch])
        self.truncate(next_epoch)

    def append(self, **rows: pd.DataFrame | None) -> None:
        """Add one epoch's rows to the tables named by the keywords (a table's file name without
        .csv; every table of a training run gets its epoch's digest, empty or not)."""
        for name in self.tables:
            new = rows.get(name.removesuffix(".csv"))
            if name.removesuffix(".csv") not in rows:
                continue
            if new is not None and len(new):
                self.tables[name] = pd.concat([self.tables[name], new], ignore_index=True)
            self.digests[name].append(row_digest(new if new is not None else pd.DataFrame()))
        self._flush()

    def _flush(self) -> None:
        for name, table in self.tables.items():
            if name not in self.optional or len(table) or (self.run_dir / name).exists():
                write_csv(self.run_dir / name, table.drop(columns=[LINE], errors="ignore"))

    @property
    def last_finite(self) -> dict[str, float]:
        """The last row's finite numbers of the first table (what a failure record keeps)."""
        table = self[next(iter(self.tables))]
        if not len(table):
            return {}
        row = table.iloc[-1]
        return {
            k: float(v)
            for k, v in row.items()
            if isinstance(v, int | float | np.number) and math.isfinite(float(v))
        }


def training_tables(run_dir: Path) -> RunTables:
    return RunTables(run_dir, (EPOCHS_CSV, BATCHES_CSV), optional=(STEPS_CSV,))
