"""Write a model directory all at once or not at all.

Files are written into a temporary sibling directory (``.NAME.partial-XXXX`` next to MODEL_DIR) and the
whole directory is renamed into place at the end; on any failure (an error, a failed parity check,
Ctrl-C) the temporary directory — and any parent directories this export created — are removed.

What may already be at MODEL_DIR:
- nothing, or an empty directory: it is (re)placed;
- a previous export (a ``dssp_model.json`` manifest): refused unless ``force``; with ``force`` the old
  directory is moved aside, the new one renamed into place, then the old one deleted;
- anything else (a file, a directory with other content): always refused — export never deletes what it
  did not write.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

from export.errors import ExportError
from export.manifest import is_model_dir


def check_destination(out: Path, force: bool) -> None:
    """Refuse a destination that cannot be (re)placed; see the module docstring for the rules."""
    if out.is_symlink() or (out.exists() and not out.is_dir()):
        raise ExportError(f"{out} exists and is not a directory; choose another -o")
    if not out.exists() or not any(out.iterdir()):
        return
    if not is_model_dir(out):
        raise ExportError(f"{out} exists and is not a DSSP model directory; choose another -o (export never deletes it)")
    if not force:
        raise ExportError(f"{out} already holds an exported model; pass --force to replace it or choose another -o")


class StagedDirectory:
    """A temporary sibling of ``out`` that becomes ``out`` on :meth:`commit`, and vanishes otherwise.

    with StagedDirectory(out, force) as stage:
        write files into stage.path
        stage.commit()
    """

    def __init__(self, out: Path, force: bool = False):
        self.out = Path(out).absolute()
        self.force = force
        self.path: Path | None = None
        self._created_parents: list[Path] = []
        self._committed = False

    def __enter__(self) -> "StagedDirectory":
        check_destination(self.out, self.force)
        parent = self.out.parent
        missing = []
        while not parent.exists():
            missing.append(parent)
            parent = parent.parent
        try:
            for folder in reversed(missing):
                folder.mkdir()
                self._created_parents.append(folder)
            self.path = Path(tempfile.mkdtemp(dir=self.out.parent, prefix=f".{self.out.name}.partial-"))
            os.chmod(self.path, 0o777 & ~_umask())
        except OSError as exc:
            self._cleanup()
            raise ExportError(f"cannot write to {self.out.parent} ({exc.strerror or exc}); choose a writable -o") from None
        return self

    def commit(self) -> Path:
        """Rename the staged directory to ``out`` (replacing a previous export when allowed)."""
        check_destination(self.out, self.force)  # again: something may have appeared meanwhile
        old = None
        if self.out.exists() and any(self.out.iterdir()):
            old = Path(tempfile.mkdtemp(dir=self.out.parent, prefix=f".{self.out.name}.old-"))
            os.rmdir(old)
            self.out.rename(old)
        elif self.out.exists():
            self.out.rmdir()
        self.path.rename(self.out)
        self._committed = True
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
        return self.out

    def _cleanup(self) -> None:
        if self.path is not None and self.path.exists():
            shutil.rmtree(self.path, ignore_errors=True)
        for folder in reversed(self._created_parents):
            try:
                folder.rmdir()
            except OSError:
                break

    def __exit__(self, *exc_info) -> None:
        if not self._committed:
            self._cleanup()


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
