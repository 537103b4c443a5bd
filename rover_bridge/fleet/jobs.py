"""Which logs a fleet run reads: files, folders (searched recursively) and glob patterns, each log once.

Each log also gets its folder, the default half of a rover's name (rovers.rover_key): for a log
found under a folder given on the command line, the first folder below it (logs/rover-03/2026-11/a.tlog
given as `logs` -> "rover-03"), or that folder's own name for a log directly in it; for a file or a glob
match, the name of the folder it is in.
"""

from __future__ import annotations

import glob
from dataclasses import dataclass
from pathlib import Path

from rover_bridge.errors import ConfigError

LOG_SUFFIXES = (".tlog", ".bin")


@dataclass(frozen=True, slots=True)
class LogJob:
    path: str  # absolute: what a worker on another machine opens (a shared filesystem)
    folder: str


def is_log(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in LOG_SUFFIXES


def expand(inputs: list[str]) -> list[LogJob]:
    """The logs named by `inputs`, in a stable order (sorted by path); ConfigError lists every input that
    names nothing."""
    jobs: dict[str, LogJob] = {}
    problems = []
    for given in inputs:
        p = Path(given)
        found: list[tuple[Path, str]] = []
        if p.is_dir():
            root = p.resolve()
            for f in sorted(root.rglob("*")):
                if is_log(f):
                    parts = f.relative_to(root).parts
                    found.append((f, parts[0] if len(parts) > 1 else root.name))
        elif p.is_file():
            found.append((p, p.resolve().parent.name))
        else:
            found = [(Path(m), Path(m).resolve().parent.name) for m in sorted(glob.glob(given, recursive=True))
                     if is_log(Path(m))]
        if not found:
            problems.append(f"{given}: no .tlog or .bin log there" if p.exists() or glob.has_magic(given)
                            else f"{given}: no such file or folder")
        for f, folder in found:
            path = str(f.resolve())
            jobs.setdefault(path, LogJob(path, folder))
    if problems:
        raise ConfigError(problems)
    return [jobs[k] for k in sorted(jobs)]
