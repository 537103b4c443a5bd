"""The paths a user gives a command (logs, profiles, keys, outputs), checked before any work starts.

Each check returns None, or one line that names the option, the path and what is wrong with it (the shape
of `check_url`), so a command collects every problem at once and raises one ConfigError: exit 2 before a
link opens, a log is read or the rover drives, instead of a traceback after a whole run. What a command
writes is checked without creating or truncating anything: a check that passes leaves no trace.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path


def _may(path: Path, mode: int) -> bool:
    """os.access for the ids that open the file (the effective ones), where the system can tell."""
    return os.access(path, mode, effective_ids=os.access in os.supports_effective_ids)


def _name(path: str | Path, label: str) -> str:
    return f"{label} {path}" if label else str(path)


def input_problem(path: str | Path, label: str = "", what: str = "file") -> str | None:
    """A file to read (`what` names it: "log", "profile"): there, not a folder, readable, not empty."""
    p, name = Path(path), _name(path, label)
    try:
        st = p.stat()
    except (FileNotFoundError, NotADirectoryError):
        return f"{name}: no such {what}"
    except OSError as exc:
        return f"{name}: cannot read the {what} ({exc.strerror or exc})"
    if stat.S_ISDIR(st.st_mode):
        return f"{name}: a folder, not a {what}"
    if not stat.S_ISREG(st.st_mode):
        return None  # a device or a pipe: opening it to look could block or consume it
    try:
        with open(p, "rb"):
            pass
    except OSError as exc:
        return f"{name}: cannot read the {what} ({exc.strerror or exc})"
    if st.st_size == 0:
        return f"{name}: the {what} is empty"
    return None


def output_problem(path: str | Path, label: str = "", make_folders: bool = False) -> str | None:
    """A file to write (created or replaced): not a folder, in a folder that exists (or, with `make_folders`,
    can be made) and that this process may write in."""
    p, name = Path(path), _name(path, label)
    if p.is_dir():
        return f"{name}: a folder: give the name of a file to write"
    parent = p.parent
    if not parent.is_dir():
        return _missing_folder(parent, name, make_folders)
    if p.exists():
        return None if _may(p, os.W_OK) else f"{name}: cannot write the file (permission denied)"
    if not _may(parent, os.W_OK | os.X_OK):
        return f"{name}: cannot create a file in folder {parent} (permission denied)"
    return None


def output_folder_problem(path: str | Path, label: str = "") -> str | None:
    """A folder to write files in, made with its parents when missing."""
    p, name = Path(path), _name(path, label)
    if p.is_dir():
        return None if _may(p, os.W_OK | os.X_OK) else f"{name}: cannot write in the folder (permission denied)"
    if p.exists():
        return f"{name}: a file, not a folder"
    return _missing_folder(p, name, make=True)


def _missing_folder(folder: Path, name: str, make: bool) -> str | None:
    """What stops `folder` (not there) from being made, or from being used at all when `make` is False."""
    ancestor = folder
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        return f"{name}: {ancestor} is a file, not a folder"
    if not make:
        return f"{name}: folder {folder} does not exist"
    if not _may(ancestor, os.W_OK | os.X_OK):
        return f"{name}: cannot create folders in {ancestor} (permission denied)"
    return None
