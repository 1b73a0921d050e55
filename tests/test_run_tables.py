"""A run's CSV tables read back by a reader (:func:`hmepol_cli.run.read_table`): what the writer
wrote, with the line each row came from, and every kind of damage refused in one line that
names the file and the line."""

from __future__ import annotations

import math
import re

import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hmepol_cli.errors import RunDirError, TableError
from hmepol_cli.run import EPOCHS_CSV, RunTables, read_table

NUMERIC = re.compile(r"epoch|entropy(_c\d+)?")


def written(tmp_path, epochs: int = 3):
    """epochs.csv as RunTables writes it: numbers, a NaN, a flag and a text column."""
    tables = RunTables(tmp_path, (EPOCHS_CSV,))
    for e in range(epochs):
        row = {
            "epoch": e,
            "entropy": 1.0 / (e + 1),
            "entropy_c0": math.nan if e == 1 else 0.1 * e,
            "diverged": e == 2,
            "note": f"epoch {e}",
        }
        tables.append(epochs=pd.DataFrame([row]))
    return tmp_path / EPOCHS_CSV


def test_a_table_reads_back_as_written_indexed_by_its_lines(tmp_path):
    frame = read_table(written(tmp_path), ("epoch", "entropy"), NUMERIC)
    assert list(frame.index) == [2, 3, 4] and frame.index.name == "line"
    assert list(frame["epoch"]) == [0, 1, 2]
    assert list(frame["entropy"]) == [1.0, 0.5, 1.0 / 3.0]  # exact: the writer's repr
    assert np.isnan(frame["entropy_c0"][3]) and frame["entropy_c0"][4] == pytest.approx(0.2)
    assert frame["note"].tolist() == ["epoch 0", "epoch 1", "epoch 2"]  # text stays text
    assert frame["diverged"].tolist() == ["False", "False", "True"]


def test_numeric_may_be_given_as_text_and_nan_fields_of_any_case_are_nan(tmp_path):
    path = tmp_path / "batches.csv"
    path.write_text("epoch,config,entropy\n0,0,NaN\n0,1,-nan\n1,0,\n")
    frame = read_table(path, ("epoch",), "epoch|config|entropy")
    assert frame["entropy"].isna().all() and frame["config"].tolist() == [0, 1, 0]


def replace_line(text: str, number: int, line: str) -> str:
    lines = text.splitlines(keepends=True)
    lines[number - 1] = line
    return "".join(lines)


DAMAGE = [
    (lambda text: text[:-5], "epochs.csv is cut short: its last line (4) stops mid-line"),
    (lambda text: replace_line(text, 3, "1,0.5\n"), "epochs.csv line 3 does not parse: 2 fields"),
    (
        lambda text: replace_line(text, 3, "1,0.5.1,,False,x\n"),
        "epochs.csv line 3 does not parse: entropy='0.5.1' is not a number",
    ),
    (
        lambda text: replace_line(text, 4, "two,0.3,,True,x\n"),
        "epochs.csv line 4 does not parse: epoch='two' is not a number",
    ),
    (lambda text: text.replace("entropy_c0", "entropy", 1), "header names a column twice"),
    (lambda text: text.replace("entropy,", "H,", 1), "missing columns: entropy"),
    (lambda text: text.splitlines(keepends=True)[0], "epochs.csv has no rows"),
    (lambda text: " \n", "epochs.csv is empty"),
    (lambda text: replace_line(text, 3, '1,"0.5\n'), "epochs.csv line 3 does not parse"),
]


@pytest.mark.parametrize(("damage", "message"), DAMAGE)
def test_a_damaged_table_is_refused_in_one_line_naming_the_file_and_line(tmp_path, damage, message):
    path = written(tmp_path)
    path.write_text(damage(path.read_text()))
    with pytest.raises(TableError, match=re.escape(message)) as refused:
        read_table(path, ("epoch", "entropy"), NUMERIC)
    assert "\n" not in str(refused.value)


def test_a_table_that_is_not_text_or_missing_is_refused(tmp_path):
    with pytest.raises(TableError, match="epochs.csv is missing"):
        read_table(tmp_path / EPOCHS_CSV)
    (tmp_path / EPOCHS_CSV).write_bytes(b"epoch\n\xff\xfe\n")
    with pytest.raises(TableError, match="epochs.csv is not UTF-8 text"):
        read_table(tmp_path / EPOCHS_CSV)


def test_a_column_outside_numeric_may_hold_text(tmp_path):
    path = written(tmp_path)
    path.write_text(replace_line(path.read_text(), 3, "1,0.5,n/a,False,x\n"))
    frame = read_table(path, ("epoch",), NUMERIC.pattern.replace("(_c\\d+)?", ""))
    assert frame["entropy_c0"].tolist() == ["0.0", "n/a", "0.2"]
    assert issubclass(TableError, RunDirError)  # a user's error: one line, exit 2


def _inexact(monkeypatch):
    """Make pandas parse CSV floats one double up, as some releases' parsers do (pandas 3.0.6
    read a third of a sample of to_csv's doubles as a neighbouring double)."""
    read_csv, to_numeric = pd.read_csv, pd.to_numeric

    def up(frame):
        for column in frame.columns:
            if frame[column].dtype.kind == "f":
                with np.errstate(over="ignore"):  # the largest double goes up to inf
                    frame[column] = np.nextafter(frame[column].to_numpy(), np.inf)
        return frame

    def inexact_read_csv(*args, **kwargs):
        frame = read_csv(*args, **kwargs)
        return frame if kwargs.get("dtype") is str else up(frame)

    def inexact_to_numeric(*args, **kwargs):
        numbers = to_numeric(*args, **kwargs)
        if getattr(numbers, "dtype", None) is not None and numbers.dtype.kind == "f":
            with np.errstate(over="ignore"):
                up_one = np.nextafter(numbers.to_numpy(), np.inf)
            numbers = pd.Series(up_one, index=numbers.index)
        return numbers

    monkeypatch.setattr(pd, "read_csv", inexact_read_csv)
    monkeypatch.setattr(pd, "to_numeric", inexact_to_numeric)


FLOATS = st.floats(allow_nan=True, allow_infinity=False, width=64)


@settings(max_examples=60, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])  # fmt: skip
@given(values=st.lists(st.tuples(FLOATS, FLOATS), min_size=1, max_size=6), inexact=st.booleans())
def test_rows_read_back_are_the_rows_written_whatever_the_csv_parser_rounds(
    tmp_path_factory, monkeypatch, values, inexact
):
    """Any doubles a run writes come back bit for bit, to the resume's digest check and to the
    report's reader, even from a pandas whose CSV parser rounds to a neighbouring double."""
    run = tmp_path_factory.mktemp("run")
    tables = RunTables(run, (EPOCHS_CSV,))
    for e, (a, b) in enumerate(values):
        tables.append(epochs=pd.DataFrame([{"epoch": e, "entropy": a, "kl": b}]))
    digests = {EPOCHS_CSV: list(tables.digests[EPOCHS_CSV])}
    with monkeypatch.context() as patch:
        if inexact:
            _inexact(patch)
        again = RunTables(run, (EPOCHS_CSV,))
        again.verify(len(values), digests)  # refuses (RunDirError) if a row came back changed
        frame = read_table(run / EPOCHS_CSV, ("epoch",), NUMERIC)
    for column, k in (("entropy", 0), ("kl", 1)):
        want = np.array([v[k] for v in values], dtype=np.float64)
        for got in (again[EPOCHS_CSV][column].to_numpy(np.float64), frame[column].to_numpy()):
            assert np.array_equal(np.isnan(got), np.isnan(want))
            bits = lambda x: x[~np.isnan(x)].view(np.int64)  # noqa: E731
            assert np.array_equal(bits(got), bits(want))  # -0.0 and 0.0 told apart
