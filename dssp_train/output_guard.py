"""Where commands write: one rule for every output path (numpy and the standard library only, no torch).

A command never destroys data it did not create. Every command that writes checks its output paths
before any expensive work, with these rules.

Directories (:func:`check_output`, :class:`OutputDir`):

- nothing there, or an empty directory (or one holding only the marker) → written;
- a previous output of the same command, recognised by its *kind* (:class:`OutputKind`): the marker file
  ``.dssp-output.json`` the command wrote into it (``{"command": ..., "output": ...}``), or the kind's own
  signature (a model directory's ``dssp_model.json``, a zarr dataset's ``generator`` attribute, a run
  directory's ``config.json``) — and nothing in it but the names that command writes → refused unless
  ``--force``; with ``--force`` it is replaced all at once (built beside and swapped in, or the old one
  moved aside, see :class:`OutputDir`), the old one deleted only after the new one is complete;
- anything else (a file, a symlink, a directory with anything the command did not write) → always
  refused, ``--force`` or not: nothing is deleted.

Commands that add to what is there (``dssp-sim collect`` appends episodes, ``python -m
dssp_sim.experiment`` resumes its work directory) continue only their own kind (:func:`check_append`,
:func:`claim_dir` with ``resume=True``) and refuse anything else.

Single files (JSON reports, PNG plots; :func:`check_output_file`, :func:`write_output_text`,
:func:`write_output_file`): a new file is written; an existing file is replaced only with ``--force``; a
directory or a symlink at that path is always refused. Files are written to a temporary name beside the
target and renamed over it (:mod:`dssp_train.atomic`).

Every refusal is an :class:`OutputError`: one line, exit code 2 in the command-line tools.
"""

from __future__ import annotations

import fnmatch
import json
import os
import shutil
import tempfile
import uuid
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

from dssp_train.atomic import atomic_write, atomic_write_text, replace_dir
from dssp_train.errors import DSSPError

MARKER = ".dssp-output.json"
"""The file a command writes into a directory it creates: which command made it and what it is."""

NEW, OWN = "new", "own"
"""What :func:`check_output` found: nothing (or an empty directory), or a previous output of the kind."""

__all__ = [
    "MARKER", "NEW", "OWN", "OutputError", "OutputKind", "check_output", "check_append", "claim_dir", "OutputDir",
    "check_output_file", "check_output_files", "write_output_text", "write_output_file", "zarr_attrs", "zarr_generator",
    "RUN_DIR", "SYNTH_DATASET", "SIM_DATASET", "RECORDED_DATASET", "RUN_LOG",
]


class OutputError(DSSPError):
    """An output path holds something the command may not replace."""


@dataclass(frozen=True)
class OutputKind:
    """What a command writes at an output path, and how to recognise it later.

    Args:
        what: the kind with its article, as messages say it ("a run directory").
        command: the command that writes it ("dssp-train").
        entries: glob patterns of the top-level names the command writes there; a directory with any
            other name is not its own (temporary ``.NAME.*`` files of those names are its own too).
        signature: recognises the kind without the marker (outputs of older versions, formats with
            their own header such as zarr datasets and model directories).
        marker: whether the command writes :data:`MARKER` into the directories it creates.
    """

    what: str
    command: str
    entries: tuple[str, ...] = ("*",)
    signature: Callable[[Path], bool] | None = None
    marker: bool = True

    def marked(self, path: Path) -> bool:
        """True when ``path``'s marker names this command and kind."""
        try:
            data = json.loads((Path(path) / MARKER).read_text())
        except (OSError, ValueError):
            return False
        return isinstance(data, dict) and data.get("command") == self.command and data.get("output") == self.what

    def expected(self, name: str) -> bool:
        """True when a top-level entry called ``name`` is one this command writes (or its temporary)."""
        if name == MARKER:
            return True
        for pattern in self.entries:
            if fnmatch.fnmatchcase(name, pattern) or fnmatch.fnmatchcase(name, f".{pattern}.*"):
                return True
        return False

    def owns(self, path: Path) -> bool:
        """True when ``path`` is a directory this command wrote and holds nothing else."""
        path = Path(path)
        if path.is_symlink() or not path.is_dir():
            return False
        try:
            names = os.listdir(path)
        except OSError:
            return False
        if not (self.marked(path) or (self.signature is not None and _safe(self.signature, path))):
            return False
        return all(self.expected(name) for name in names)

    def write_marker(self, path: Path) -> None:
        if self.marker:
            text = json.dumps({"command": self.command, "output": self.what}) + "\n"
            atomic_write_text(Path(path) / MARKER, text)


def _safe(check: Callable[[Path], bool], path: Path) -> bool:
    try:
        return bool(check(path))
    except (OSError, ValueError, TypeError, KeyError):
        return False


def _found(path: Path, kind: OutputKind) -> str:
    """NEW, OWN, or "foreign" (anything that may not be touched)."""
    if path.is_symlink():
        return "foreign"
    if not path.exists():
        return NEW
    if not path.is_dir():
        return "foreign"
    try:
        names = os.listdir(path)
    except OSError:
        return "foreign"
    if all(name == MARKER for name in names):
        return NEW
    return OWN if kind.owns(path) else "foreign"


def _foreign_message(path: Path, kind: OutputKind, flag: str) -> str:
    return f"{path} exists and is not {kind.what} made by {kind.command}; choose another {flag} (nothing is deleted)"


def check_output(path: str | os.PathLike, *, force: bool | None, kind: OutputKind, flag: str = "--out",
                 error: type[DSSPError] = OutputError) -> str:
    """Whether the command may write ``kind`` at ``path``: returns NEW or OWN (only with ``force``), else raises.

    ``force=None``: the command has no ``--force`` (its previous output is refused without the hint).
    """
    path = Path(path)
    found = _found(path, kind)
    if found == NEW:
        return NEW
    if found == OWN:
        if force:
            return OWN
        hint = "pass --force to replace it or choose another" if force is not None else "choose another"
        raise error(f"{path} already holds {kind.what} from {kind.command}; {hint} {flag}")
    raise error(_foreign_message(path, kind, flag))


def check_append(path: str | os.PathLike, *, kind: OutputKind, flag: str = "--out",
                 error: type[DSSPError] = OutputError) -> str:
    """For commands that add to their output: NEW or OWN (to be continued); anything else raises."""
    path = Path(path)
    found = _found(path, kind)
    if found == "foreign":
        raise error(_foreign_message(path, kind, flag))
    return found


def claim_dir(path: str | os.PathLike, *, kind: OutputKind, flag: str = "--out", resume: bool = False,
              error: type[DSSPError] = OutputError) -> Path:
    """Create ``path`` (and its parents) for ``kind`` and write its marker.

    A missing or empty directory is claimed; with ``resume`` a previous output of the kind is continued
    (and marked, if it was recognised by its signature); anything else raises.
    """
    path = Path(path)
    if resume:
        check_append(path, kind=kind, flag=flag, error=error)
    else:
        check_output(path, force=None, kind=kind, flag=flag, error=error)
    try:
        path.mkdir(parents=True, exist_ok=True)
        if not kind.marked(path):
            kind.write_marker(path)
    except OSError as exc:
        raise error(f"cannot write to {path} ({exc.strerror or exc}); choose a writable {flag}") from None
    return path


class OutputDir:
    """A directory written all at once: checked on entry, in place on :meth:`commit`, gone otherwise.

        with OutputDir(out, KIND, force=args.force) as target:
            write files into target.path
            target.commit()

    ``staged=True`` (default): ``target.path`` is a temporary sibling ``.NAME.partial-XXXX`` that
    :meth:`commit` swaps onto ``out`` (:func:`dssp_train.atomic.replace_dir`; a previous output is deleted
    after the swap). ``staged=False``, for outputs that record their own path or are watched while they
    grow (runs, demos): ``target.path`` is ``out`` itself; a previous output (``--force``) is first moved
    aside to ``.NAME.old-XXXX`` and deleted on :meth:`commit`. Without a commit (an error, Ctrl-C) what this
    command created is removed and a previous output is put back — except with ``keep_partial``, when an
    unfinished output that replaced nothing and holds something stays (a training run to ``--resume``).
    Parent directories this command created are removed with it.
    """

    def __init__(self, out: str | os.PathLike, kind: OutputKind, *, force: bool = False, flag: str = "--out",
                 staged: bool = True, keep_partial: bool = False, error: type[DSSPError] = OutputError):
        self.out = Path(out).absolute()
        self.kind, self.force, self.flag, self.staged = kind, force, flag, staged
        self.keep_partial, self.error = keep_partial, error
        self.path: Path | None = None
        self.found: str | None = None
        self._old: Path | None = None
        self._created: list[Path] = []
        self._made_out = False
        self._committed = False

    def check(self) -> str:
        return check_output(self.out, force=self.force, kind=self.kind, flag=self.flag, error=self.error)

    def __enter__(self) -> "OutputDir":
        self.found = self.check()
        missing, parent = [], self.out.parent
        while not parent.exists():
            missing.append(parent)
            parent = parent.parent
        try:
            for folder in reversed(missing):
                folder.mkdir()
                self._created.append(folder)
            if self.staged:
                self.path = Path(tempfile.mkdtemp(dir=self.out.parent, prefix=f".{self.out.name}.partial-"))
                os.chmod(self.path, 0o777 & ~_umask())
            else:
                if self.found == OWN:
                    old = self.out.with_name(f".{self.out.name}.old-{uuid.uuid4().hex[:8]}")
                    os.replace(self.out, old)
                    self._old = old  # only once it is moved: a rollback puts it back
                self._made_out = not self.out.exists()
                self.out.mkdir(exist_ok=True)
                self.path = self.out
            self.kind.write_marker(self.path)
        except OSError as exc:
            self._rollback()
            raise self.error(f"cannot write to {self.out.parent} ({exc.strerror or exc}); choose a writable {self.flag}") from None
        return self

    def commit(self) -> Path:
        """Put the finished output in place (replacing a previous one when allowed); returns ``out``."""
        if self.staged:
            self.check()  # again: something may have appeared meanwhile
            replace_dir(self.path, self.out)
        self._committed = True
        if self._old is not None:
            shutil.rmtree(self._old, ignore_errors=True)
            self._old = None
        return self.out

    def _rollback(self) -> None:
        if self.path is not None and self.staged:
            shutil.rmtree(self.path, ignore_errors=True)
        elif self.path is not None and (self._old is not None or not self.keep_partial or _empty(self.out)):
            if self._made_out or self._old is not None:
                shutil.rmtree(self.out, ignore_errors=True)
            else:  # an empty directory was there: leave it empty
                for entry in self.out.iterdir():
                    if entry.is_dir() and not entry.is_symlink():
                        shutil.rmtree(entry, ignore_errors=True)
                    else:
                        entry.unlink(missing_ok=True)
        if self._old is not None:
            os.replace(self._old, self.out)
            self._old = None
        for folder in reversed(self._created):
            try:
                folder.rmdir()
            except OSError:
                break

    def __exit__(self, *exc_info) -> None:
        if not self._committed:
            self._rollback()


def _empty(path: Path) -> bool:
    try:
        return all(name == MARKER for name in os.listdir(path))
    except OSError:
        return False


# ------------------------------------------------------------------------------------------- single files
def check_output_file(path: str | os.PathLike, *, force: bool, flag: str = "--out",
                      error: type[DSSPError] = OutputError) -> Path:
    """A new file may be written; an existing one only with ``force``; never over a directory or a symlink."""
    path = Path(path)
    if path.is_symlink() or (path.exists() and not path.is_file()):
        raise error(f"{path} exists and is not a file; choose another {flag} (nothing is deleted)")
    if path.exists() and not force:
        raise error(f"{path} exists; pass --force to replace it or choose another {flag}")
    return path


def write_output_file(path: str | os.PathLike, write: Callable[[str], None], *, force: bool, flag: str = "--out",
                      error: type[DSSPError] = OutputError, suffix: str = ".tmp") -> Path:
    """Check ``path`` (:func:`check_output_file`), create its parents, and call ``write(tmp)`` atomically.

    ``suffix``: the temporary file's ending, for writers that take the format from the name (``".tmp.gif"``).
    """
    path = check_output_file(path, force=force, flag=flag, error=error)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(path, write, suffix=suffix)
    except OSError as exc:
        raise error(f"cannot write {path} ({exc.strerror or exc}); choose a writable {flag}") from None
    return path


def write_output_text(path: str | os.PathLike, text: str, *, force: bool, flag: str = "--out",
                      error: type[DSSPError] = OutputError) -> Path:
    """:func:`write_output_file` for text (JSON, Markdown)."""

    def write(tmp: str) -> None:
        with open(tmp, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())

    return write_output_file(path, write, force=force, flag=flag, error=error)


def check_output_files(paths: Iterable[str | os.PathLike], *, force: bool, flag: str = "--out",
                       error: type[DSSPError] = OutputError) -> list[Path]:
    """:func:`check_output_file` for several files at once (all are checked before any is written)."""
    return [check_output_file(p, force=force, flag=flag, error=error) for p in paths]


# ------------------------------------------------------------------------------------------- known kinds
def zarr_attrs(path: str | os.PathLike) -> dict | None:
    """The root attributes of a zarr group at ``path`` (format 2 or 3), read as JSON; None if it is not one."""
    path = Path(path)
    if (path / ".zgroup").is_file():
        attrs_file = path / ".zattrs"
        attrs = json.loads(attrs_file.read_text()) if attrs_file.is_file() else {}
    elif (path / "zarr.json").is_file():
        attrs = json.loads((path / "zarr.json").read_text()).get("attributes", {})
    else:
        return None
    return attrs if isinstance(attrs, dict) else None


def zarr_generator(path: str | os.PathLike) -> str | None:
    """The ``generator`` attribute of a zarr dataset (which program wrote it), or None."""
    try:
        attrs = zarr_attrs(path)
    except (OSError, ValueError):
        return None
    value = (attrs or {}).get("generator")
    return value if isinstance(value, str) else None


ZARR_ENTRIES = (".zgroup", ".zattrs", ".zmetadata", "zarr.json", "data", "meta")
"""The top-level names of a DP3 zarr dataset as :mod:`dssp_train.data.replay_buffer` writes it."""


def _run_signature(path: Path) -> bool:
    config = json.loads((path / "config.json").read_text())
    return isinstance(config, dict) and "model" in config and "train" in config


RUN_DIR = OutputKind("a run directory", "dssp-train",
                     entries=("config.json", "model.safetensors", "checkpoint", "log.jsonl", "loss.png"),
                     signature=_run_signature, marker=False)
"""``dssp-train --out``: config.json (a JSON object with ``model`` and ``train``), model.safetensors,
checkpoint/, log.jsonl, loss.png — recognised by its config.json, no marker added."""

SYNTH_DATASET = OutputKind("a synthetic dataset", "dssp-synth", entries=ZARR_ENTRIES, marker=False,
                           signature=lambda p: zarr_generator(p) == "dssp_train.data.synthetic")
"""``dssp-synth --out``: a zarr dataset whose ``generator`` attribute is ``dssp_train.data.synthetic``."""

SIM_DATASET = OutputKind("a simulation dataset", "dssp-sim collect", marker=False,
                         signature=lambda p: zarr_generator(p) == "dssp_sim.collect")
"""``dssp-sim collect --out``: a zarr dataset whose ``generator`` attribute is ``dssp_sim.collect`` (appended to)."""

RECORDED_DATASET = OutputKind("a recorded dataset", "dssp-record", marker=False,
                              signature=lambda p: zarr_generator(p) == "dssp-record")
"""``dssp-record --out``: a zarr dataset whose ``generator`` attribute is ``dssp-record`` (appended to)."""

RUN_LOG = OutputKind("an episode log", "dssp-run")
"""``dssp-run --log-dir``: a new directory for one run's log (marked); an existing log is never reused."""


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
