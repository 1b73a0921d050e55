"""The CSV tables of a run directory: written atomically a whole epoch at a time, each epoch's
rows digested so that a resume keeps exactly the rows its checkpoint covers (:class:`RunTables`),
and read back by whoever uses a finished run (:func:`read_table`).

The two reads differ on purpose: the writer's keeps every row it can and locates the damaged
ones (a resume refuses them only where the checkpoint covers them, and drops the rest), while a
reader's refuses the whole table at its first damaged line, which it names.
"""

from __future__ import annotations

import csv
import hashlib
import io
import math
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from hmepol_cli.errors import RunDirError, TableError
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


def _float(text: str) -> float:
    return float(text) if text else math.nan


def exact_floats(frame: pd.DataFrame, path: Path, skiprows: Any = None) -> None:
    """Replace ``frame``'s float columns (read from ``path``) by the exact values their text
    writes: Python's correctly rounded parse of each field. Some pandas releases parse a CSV's
    floats to a neighbouring double (pandas 3.0.6 did so for a third of a sample of doubles
    written by to_csv), which would make rows read back differ from the rows written."""
    floats = [c for c in frame.columns if frame[c].dtype.kind == "f"]
    if not floats or not len(frame):
        return
    text = pd.read_csv(path, skiprows=skiprows, usecols=floats, dtype=str, keep_default_na=False)
    for column in floats:
        frame[column] = np.fromiter(map(_float, text[column]), dtype=np.float64, count=len(text))


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
        skip = lambda i: i > 0 and i + 1 not in keep  # noqa: E731
        frame = pd.read_csv(path, skiprows=skip)
        exact_floats(frame, path, skip)
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


MISSING_FIELDS = ("", "nan", "-nan", "+nan")  # what a CSV writer puts for NaN, any case


def read_table(
    path: Path, required: Sequence[str] = (), numeric: re.Pattern | str | None = None
) -> pd.DataFrame:
    """A table a run wrote (epochs.csv, batches.csv, steps.csv, finetune.csv), indexed by the
    line of the file each row is on (``line``; 1 is the header), for messages.

    Raises :class:`~hmepol_cli.errors.TableError` when the file is missing, empty or cut short,
    its header lacks a ``required`` column or names one twice, a row does not parse, or a column
    whose whole name ``numeric`` matches holds something that is not a number (an empty field
    and ``nan`` are NaN). Other columns become numbers where every field is one, and stay text
    otherwise. Runs rewrite their tables whole and end every row with a line end, so a file
    that stops mid-line was cut (a copy, a full disk), and its last row may hold half a number.
    """
    path = Path(path)
    numeric = re.compile(numeric) if isinstance(numeric, str) else numeric
    if not path.is_file():
        raise TableError(f"{path.name} is missing")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise TableError(f"{path.name} is not UTF-8 text") from None
    except OSError as err:
        raise TableError(f"{path.name} is unreadable ({type(err).__name__})") from None
    if not text.strip():
        raise TableError(f"{path.name} is empty")
    if not text.endswith("\n"):
        last = text.count("\n") + 1
        raise TableError(f"{path.name} is cut short: its last line ({last}) stops mid-line")
    reader = csv.reader(io.StringIO(text))
    try:
        header = next(reader)
    except csv.Error as err:
        raise TableError(f"{path.name} line 1 does not parse ({err})") from None
    if len(set(header)) != len(header):
        raise TableError(f"{path.name} is corrupt (its header names a column twice)")
    missing = [c for c in required if c not in header]
    if missing:
        raise TableError(f"{path.name} is corrupt (missing columns: {', '.join(missing)})")
    rows, lines = [], []
    while True:
        line = reader.line_num + 1
        try:
            row = next(reader)
        except StopIteration:
            break
        except csv.Error as err:
            raise TableError(f"{path.name} line {line} does not parse ({err})") from None
        if not row:  # a blank line
            continue
        if len(row) != len(header):
            raise TableError(
                f"{path.name} line {line} does not parse: {len(row)} fields, "
                f"the header has {len(header)}"
            )
        rows.append(row)
        lines.append(line)
    if not rows:
        raise TableError(f"{path.name} has no rows")
    frame = pd.DataFrame(rows, columns=header, index=pd.Index(lines, name="line"))
    for column in frame.columns:
        fields = frame[column].str.strip()
        blank = fields.str.lower().isin(MISSING_FIELDS)
        numbers = pd.to_numeric(fields.mask(blank), errors="coerce")
        unparsed = numbers.isna() & ~blank
        if not unparsed.any():
            if numbers.dtype.kind == "f":  # each number exactly as written (see exact_floats)
                exact = map(_float, fields.where(~blank, ""))
                numbers = pd.Series(np.fromiter(exact, np.float64, len(fields)), fields.index)
            frame[column] = numbers
        elif numeric is not None and numeric.fullmatch(column):
            line = unparsed.idxmax()
            raise TableError(
                f"{path.name} line {line} does not parse: "
                f"{column}={fields[line][:40]!r} is not a number"
            )
    return frame
