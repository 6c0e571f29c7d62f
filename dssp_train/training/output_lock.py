"""One writer per output of training and export: dssp-train's and dssp-distill's run directory, export's
model directory (no torch here: the lock is taken before anything expensive is imported or read).

:func:`writer_lock` holds :class:`dssp_data.output_guard.WriterLock` on the output while the command writes
it; a second writer of the same output gets one line naming the holder (exit code 2) and touches nothing.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

from dssp_data.errors import DSSPError
from dssp_data.output_guard import OutputError, WriterLock, make_dirs


@contextlib.contextmanager
def writer_lock(out: str | os.PathLike, *, what: str, flag: str = "--out",
                error: type[DSSPError] = OutputError) -> Iterator[WriterLock]:
    """Hold the writer lock of ``out`` (``.NAME.lock`` beside it) inside the block.

    The folders above ``out`` that the lock file needs are created first (a path under a file is one line
    naming ``flag``) and removed again at the end if they are still empty.
    """
    created = make_dirs(Path(out).absolute().parent, flag=flag, error=error)
    try:
        lock = WriterLock(out, what=what, flag=flag, error=error)
        try:
            yield lock
        finally:
            lock.release()
    finally:
        for folder in reversed(created):
            try:
                folder.rmdir()
            except OSError:  # it holds the output (or anything else): kept
                break
