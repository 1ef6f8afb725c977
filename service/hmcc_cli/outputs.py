"""The files a command writes (``-o``, ``--output``, ``--report``): checked, and their missing
folders made, before the command does any work, so a run never ends in a traceback that loses
what it computed (``hmcc colmap``'s report after the database was written).

Refused, with one line ``error: <option>: <path>: <reason>`` and exit 2: a path that is a
folder, one below a file, and one this user cannot write (its folder or the file itself).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

import orjson

__all__ = ["OutputPathError", "checked_output", "prepare_output", "write_report"]


class OutputPathError(ValueError):
    """An output path the command cannot write; ``str()`` is ``<option>: <path>: <reason>``."""

    def __init__(self, option: str, path: Path, reason: str) -> None:
        super().__init__(f"{option}: {path}: {reason}")
        self.option = option
        self.path = path
        self.reason = reason


def prepare_output(value: str | os.PathLike[str], option: str) -> Path:
    """``value`` as a path the command can write: its missing folders are made; raises
    :class:`OutputPathError` (nothing made) when it cannot be written."""
    path = Path(value)
    if path.is_dir():
        raise OutputPathError(option, path, "is a folder; give a file name")
    existing = path.parent
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise OutputPathError(option, path, f"{existing} is a file, not a folder")
    # os.access asks with the real user's rights, as a write would be tried (and it says no
    # on a read-only file system even to root).
    if path.exists():
        if not os.access(path, os.W_OK):
            raise OutputPathError(option, path, "not writable")
    elif not os.access(existing, os.W_OK | os.X_OK):
        raise OutputPathError(option, path, f"{existing} is not writable")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputPathError(option, path, f"cannot make its folder ({e.strerror or e})") from None
    return path


def checked_output(value: str | os.PathLike[str], option: str) -> Path | None:
    """:func:`prepare_output`, or None after printing why not (the caller exits 2)."""
    try:
        return prepare_output(value, option)
    except OutputPathError as e:
        print(f"error: {e}", file=sys.stderr)
        return None


def write_report(path: Path, report: Any) -> int:
    """``report`` as indented JSON at ``path`` (checked by :func:`checked_output` before the
    run): 0, or 1 after printing why it could not be written after all."""
    try:
        path.write_bytes(orjson.dumps(report, option=orjson.OPT_INDENT_2))
    except OSError as e:
        print(f"error: --report: {path}: {e.strerror or e}", file=sys.stderr)
        return 1
    return 0
