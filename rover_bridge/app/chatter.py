"""What pymavlink prints while it reads a damaged log, kept off the terminal and counted.

pymavlink reports what it skips in a DataFlash log by printing: its C indexer writes a line per bad byte
("bad header 0x2291 at 0") straight to file descriptor 2 while the log is opened, its Python reader a line
per skipped run ("Skipped 14706 bad bytes in log ...") to sys.stderr, and a few to sys.stdout, as each
message is read. A 200 kB file of noise becomes tens of thousands of lines ahead of the one-line verdict,
and under `fleet` they come from the Dask workers' processes, into the progress bar. The reading accounts
for the bad bytes itself (LogStats), so those lines only repeat it: they are captured where the log is read,
in whichever process reads it, and counted.
"""

from __future__ import annotations

import io
import os
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from types import TracebackType
from typing import TextIO


class Chatter:
    """Counts the lines printed inside `with chatter.python:` (sys.stdout and sys.stderr swapped: cheap enough
    around every message read) and inside `with chatter.everything():` (file descriptors 1 and 2 too, for
    code that writes below Python: a C extension's fprintf)."""

    def __init__(self) -> None:
        self.lines = 0
        self.python = _PythonStreams(self)

    @contextmanager
    def everything(self) -> Iterator[None]:
        for stream in (sys.stdout, sys.stderr):
            stream.flush()  # what was printed before is not ours to capture
        with tempfile.TemporaryFile() as sink:  # a file, not a pipe: a full pipe would block the writer
            saved: list[tuple[int, int]] = []
            try:
                for fd in (1, 2):
                    saved.append((fd, os.dup(fd)))
                    os.dup2(sink.fileno(), fd)
            except OSError:
                pass  # a closed descriptor: nothing can be written to it, so nothing is there to capture
            try:
                with self.python:
                    yield
            finally:
                for fd, copy in saved:
                    os.dup2(copy, fd)
                    os.close(copy)
                sink.seek(0)
                while block := sink.read(1 << 16):
                    self.lines += block.count(b"\n")


class _PythonStreams:
    """sys.stdout and sys.stderr replaced by a line counter while inside (re-entrant for `everything`)."""

    def __init__(self, chatter: Chatter) -> None:
        self._chatter = chatter
        self._saved: list[tuple[TextIO, TextIO]] = []
        self._sink = _Counter(chatter)

    def __enter__(self) -> None:
        self._saved.append((sys.stdout, sys.stderr))
        sys.stdout = sys.stderr = self._sink

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        sys.stdout, sys.stderr = self._saved.pop()


class _Counter(io.StringIO):
    """A text stream that keeps nothing but the number of lines written to it."""

    def __init__(self, chatter: Chatter) -> None:
        super().__init__()
        self._chatter = chatter

    def write(self, text: str) -> int:
        self._chatter.lines += text.count("\n")
        return len(text)
