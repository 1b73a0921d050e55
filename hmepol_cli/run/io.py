"""Files written whole or not at all: atomic writes, JSON, CSV and the evaluation archives.

Each write goes to a temporary file in the same folder, is flushed to the disk and renamed into
place, so a crash leaves the old file or the new one; a full disk or a quota is one line naming
the file (:class:`~hmepol_cli.errors.StorageError`) and the old file stays as it was.
"""

from __future__ import annotations

import errno
import io
import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from hmepol_cli.errors import RunDirError, StorageError
from hmepol_cli.run.layout import TEMPORARY_SUFFIX


def umask() -> int:
    """The process's umask (reading it means setting it: set back at once)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


FULL = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``path`` whole or not at all (a temporary file renamed into place); a full disk or
    quota is a StorageError naming the path, and the old file stays as it was."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(
            dir=path.parent, prefix=f".{path.name}.", suffix=TEMPORARY_SUFFIX
        )
    except OSError as error:
        raise _storage_error(path, error) from None
    try:
        os.fchmod(fd, 0o666 & ~umask())  # mkstemp makes 0600: give what a new file gets
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as error:
        Path(tmp).unlink(missing_ok=True)
        if isinstance(error, OSError) and error.errno in (*FULL, errno.EROFS, errno.EACCES):
            raise _storage_error(path, error) from None
        raise


def _storage_error(path: Path, error: OSError) -> StorageError:
    reason = "no space left on the device" if error.errno in FULL else error.strerror
    return StorageError(f"cannot write {path}: {reason} ({errno.errorcode.get(error.errno, '')})")


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def write_json(path: Path, data: dict[str, Any]) -> None:
    atomic_write_text(path, json.dumps(data, indent=2, sort_keys=True) + "\n")


def read_json(path: Path) -> dict[str, Any]:
    """A JSON file written by hmepol; a damaged one is refused in one line naming it."""
    try:
        data = json.loads(Path(path).read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise RunDirError(
            f"{path} is damaged ({type(error).__name__}: {str(error)[:80]}); a run rewrites its "
            "run.json when it is continued, or delete the run directory"
        ) from None
    if not isinstance(data, dict):
        raise RunDirError(f"{path} is damaged (it holds a {type(data).__name__}, not a record)")
    return data


def write_csv(path: Path, frame: pd.DataFrame) -> None:
    buffer = io.StringIO()
    frame.to_csv(buffer, index=False)
    atomic_write_text(path, buffer.getvalue())


def remove_temporaries(run_dir: Path) -> list[Path]:
    """Delete the temporary files of writes a crash interrupted. -> what was removed"""
    stray = [p for p in Path(run_dir).rglob(f".*{TEMPORARY_SUFFIX}") if p.is_file()]
    for path in stray:
        path.unlink(missing_ok=True)
    return stray


def save_positions(path: Path, positions: dict[int, np.ndarray]) -> None:
    """``positions_c{c}``: (n, T + 1, 2) positions of n trajectories in configuration c."""
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **{f"positions_c{c}": p for c, p in positions.items()})
    atomic_write_bytes(path, buffer.getvalue())


def load_positions(path: Path) -> dict[int, np.ndarray]:
    with np.load(path, allow_pickle=False) as data:
        return {
            int(k.removeprefix("positions_c")): np.asarray(data[k], dtype=np.float32)
            for k in data.files
            if k.startswith("positions_c")
        }
