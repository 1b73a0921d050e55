"""The report folder's manifest: ``report.json`` lists the files one report wrote.

A report replaces the one before it in the same folder: figures whose names no longer arise (a
group gone, a wind dropped) must not stay beside the new ones. Only files an earlier report
listed are ever deleted, so a folder that holds anything else (the user's notes, another tool's
output) is never emptied; a folder with files but no manifest is refused before anything is
written.
"""

from __future__ import annotations

import json
from pathlib import Path, PurePosixPath

from hmepol_cli.errors import UserError
from hmepol_cli.run import write_json

MANIFEST = "report.json"


def _is_inside(name: str) -> bool:
    """A relative path that stays inside the folder (no root, no '..')."""
    path = PurePosixPath(name)
    return bool(name) and not path.is_absolute() and ".." not in path.parts


def previous_report_files(out_dir: Path) -> set[str]:
    """Files (relative to ``out_dir``) that the earlier report in ``out_dir`` wrote.

    Raises ValueError (one line naming the folder) when ``out_dir`` is not a folder, or holds
    files but no manifest, or a manifest this module did not write: none of those is safe to
    write a report into.
    """
    out_dir = Path(out_dir)
    if not out_dir.exists():
        return set()
    if not out_dir.is_dir():
        raise UserError(f"report folder {str(out_dir)!r} is a file; --out must name a folder")
    manifest = out_dir / MANIFEST
    if not manifest.exists():
        if any(out_dir.iterdir()):
            raise UserError(
                f"report folder {str(out_dir)!r} is not empty and holds no {MANIFEST} (the list "
                "of files an earlier report wrote, which a new report replaces): choose a new or "
                "empty folder for --out"
            )
        return set()
    try:
        files = json.loads(manifest.read_text())["files"]
    except (OSError, ValueError, KeyError, TypeError):
        files = None
    if not isinstance(files, list) or not all(isinstance(f, str) and _is_inside(f) for f in files):
        raise UserError(
            f"{str(manifest)!r} is not a report manifest (a list of files inside "
            f"{str(out_dir)!r}): remove it, or choose a new or empty folder for --out"
        )
    return set(files)


def write_manifest(out_dir: Path, written: list[Path], previous: set[str]) -> None:
    """List ``written`` (paths inside ``out_dir``) in the manifest, then delete the files of the
    previous report that this one did not write again."""
    out_dir = Path(out_dir)
    files = sorted({Path(p).relative_to(out_dir).as_posix() for p in written})
    write_json(out_dir / MANIFEST, {"written_by": "hmepol report", "files": files})
    root = out_dir.resolve()
    for name in sorted(previous - set(files) - {MANIFEST}):
        stale = out_dir / name
        # A listed folder swapped for a link must not lead the deletion outside the report.
        if stale.parent.resolve().is_relative_to(root) and (stale.is_file() or stale.is_symlink()):
            stale.unlink()
