"""Atomic file writes (numpy and the standard library only): a reader sees the old file or the new one.

Each writes to a temporary file in the same directory, then ``os.replace``s it over the target, so a
crash never leaves a half-written file behind under the real name. :func:`replace_dir` does the same
for a directory built beside its target (a zarr dataset).
"""

from __future__ import annotations

import os
import shutil
import tempfile
import uuid
from pathlib import Path
from typing import Callable

import numpy as np


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write(path: Path, write: Callable[[str], None], suffix: str = ".tmp") -> None:
    """Call ``write(tmp_path)`` and move the result to ``path`` in one step.

    ``suffix`` ends the temporary name (``.NAME.XXXX<suffix>``): writers that pick the format from the
    file name (an animated GIF) need theirs, e.g. ``".tmp.gif"``.
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=suffix)
    os.close(fd)
    try:
        write(tmp)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def atomic_write_text(path: Path, text: str) -> None:
    def write(tmp: str) -> None:
        with open(tmp, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())

    atomic_write(path, write)


def atomic_save_npy(path: Path, array: np.ndarray) -> None:
    """``np.save`` without pickles (numeric arrays only), atomically."""

    def write(tmp: str) -> None:
        with open(tmp, "wb") as f:
            np.save(f, np.asarray(array), allow_pickle=False)

    atomic_write(path, write)


def replace_dir(tmp: Path, out: Path) -> None:
    """Move the finished directory ``tmp`` onto ``out``; an existing ``out`` is removed only after the move.

    The existing ``out`` is first renamed aside (``.NAME.old-XXXX``); if ``tmp`` cannot be moved in, it is
    put back. Which ``out`` may be replaced at all is :mod:`dssp_data.output_guard`'s decision.
    """
    tmp, out = Path(tmp), Path(out)
    if out.exists():
        old = out.with_name(f".{out.name}.old-{uuid.uuid4().hex[:8]}")
        os.replace(out, old)
        try:
            os.replace(tmp, out)
        except BaseException:
            os.replace(old, out)
            raise
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, out)
