"""Where commands write: one rule for every output path (the standard library only).

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
studies.sim_study`` resumes its work directory) continue only their own kind (:func:`check_append`,
:func:`claim_dir` with ``resume=True``) and refuse anything else.

Single files (JSON reports, PNG plots; :func:`check_output_file`, :func:`write_output_text`,
:func:`write_output_file`): a new file is written; an existing file is replaced only with ``--force``; a
directory or a symlink at that path is always refused. Files are written to a temporary name beside the
target and renamed over it (:mod:`dssp_core.files`).

Where an output goes: a path under a file, or in a folder that cannot be written, is refused with one
line (:func:`check_output`, :func:`check_output_file`, :func:`make_dirs`); so is an output that is one of
the command's inputs or lies inside one (:func:`check_not_inside`).
How an output is written whole (staging beside it, one writer, Ctrl-C held back during the renames) is
:mod:`dssp_core.staging`. The kinds live beside the commands that write them (``RUN_DIR`` in
``dssp_train.cli.train``, ``DATA_DATASET`` in ``dssp_data.edit``, ``SIM_DATASET`` in ``dssp_sim.collect``,
``RECORDED_DATASET`` in ``hardware.cli.record``, ``RUN_LOG`` in ``hardware.cli.run``, ``MODEL_DIR`` in
``export.output_dir``…).

Every refusal is an :class:`~dssp_core.errors.OutputError`: one line, exit code 2 in the command-line tools.
"""

from __future__ import annotations

import fnmatch
import json
import os
import shutil
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

from dssp_core.errors import DSSPError, OutputError
from dssp_core.files import (
    atomic_write,
    atomic_write_text,
    check_name_lengths,
    check_parent,
    make_dirs,
    read_regular_text,
    remove_created,
    sibling_name,
    text_writer,
)
from dssp_core.staging import Staging, interrupts_deferred

MARKER = ".dssp-output.json"
"""The file a command writes into a directory it creates: which command made it and what it is."""

NEW, OWN = "new", "own"
"""What :func:`check_output` found: nothing (or an empty directory), or a previous output of the kind."""

__all__ = [
    "MARKER",
    "NEW",
    "OWN",
    "OutputKind",
    "check_output",
    "check_append",
    "claim_dir",
    "OutputDir",
    "check_output_file",
    "check_output_files",
    "write_output_text",
    "write_output_file",
    "write_output_figure",
    "check_not_inside",
]


def _entries(path: str | os.PathLike) -> list[str] | None:
    """The names in the real directory ``path``; None for a symlink, a non-directory or an unreadable one."""
    path = Path(path)
    if path.is_symlink() or not path.is_dir():
        return None
    try:
        return os.listdir(path)
    except OSError:
        return None


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
        companion: suffix of a sibling directory that belongs to the output (``".can"``: a dataset's CAN
            logs at ``NAME.can``); it is checked, replaced and kept together with the output.
        companion_entries: glob patterns of the names the command writes into the companion.
    """

    what: str
    command: str
    entries: tuple[str, ...] = ("*",)
    signature: Callable[[Path], bool] | None = None
    marker: bool = True
    companion: str | None = None
    companion_entries: tuple[str, ...] = ()

    def companion_path(self, path: Path) -> Path | None:
        """Where the output at ``path`` keeps its companion directory (None if the kind has none)."""
        path = Path(path)
        return None if self.companion is None else path.with_name(path.name + self.companion)

    def owns_companion(self, path: Path) -> bool:
        """True when ``path`` (the companion directory) holds nothing but names the command writes there."""
        names = _entries(path)
        return names is not None and all(any(fnmatch.fnmatchcase(n, p) for p in self.companion_entries) for n in names)

    def marked(self, path: Path) -> bool:
        """True when ``path``'s marker names this command and kind."""
        try:
            data = json.loads(read_regular_text(Path(path) / MARKER) or "null")
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
        names = _entries(path)
        if names is None:
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
    if not path.exists() and not path.is_symlink():
        return NEW
    names = _entries(path)
    if names is None:
        return "foreign"
    if all(name == MARKER for name in names):
        return NEW
    return OWN if kind.owns(path) else "foreign"


def _foreign_message(path: Path, kind: OutputKind, flag: str) -> str:
    return f"{path} exists and is not {kind.what} made by {kind.command}; choose another {flag} (nothing is deleted)"


def check_output(
    path: str | os.PathLike,
    *,
    force: bool | None,
    kind: OutputKind,
    flag: str = "--out",
    error: type[DSSPError] = OutputError,
) -> str:
    """Whether the command may write ``kind`` at ``path``: returns NEW or OWN (only with ``force``), else raises.

    ``force=None``: the command has no ``--force`` (its previous output is refused without the hint).
    """
    path = Path(path)
    check_name_lengths(path, flag, error)
    found = _found(path, kind)
    if found == "foreign":
        raise error(_foreign_message(path, kind, flag))
    _check_companion(path, kind, found, flag, error)
    if found == NEW:
        check_parent(path, flag, error)
        return NEW
    if force:
        return OWN
    hint = "pass --force to replace it or choose another" if force is not None else "choose another"
    raise error(f"{path} already holds {kind.what} from {kind.command}; {hint} {flag}")


def _check_companion(path: Path, kind: OutputKind, found: str, flag: str, error: type[DSSPError]) -> None:
    """The kind's companion directory (a dataset's ``NAME.can``) must be absent, or belong to its own output."""
    companion = kind.companion_path(path)
    if companion is None or not (companion.exists() or companion.is_symlink()):
        return
    if found == NEW:
        if companion.is_dir() and not companion.is_symlink() and not os.listdir(companion):
            return  # an empty folder: nothing to lose
        raise error(
            f"{companion} exists without {path.name} (it belongs to another dataset?); choose another {flag} "
            f"(nothing is deleted)"
        )
    if not kind.owns_companion(companion):
        raise error(
            f"{companion} holds files {kind.command} does not write; choose another {flag} (nothing is deleted)"
        )


def check_not_inside(
    out: str | os.PathLike,
    inputs: Iterable[str | os.PathLike],
    *,
    flag: str = "--out",
    error: type[DSSPError] = OutputError,
    contains: bool = True,
) -> None:
    """Refuse an output that is one of ``inputs`` or lies inside one (symbolic links resolved).

    ``contains``: also refuse an output that holds an input (replacing the output would delete it).
    """
    target = Path(os.path.realpath(Path(out).absolute()))
    for item in inputs:
        source = Path(os.path.realpath(Path(item).absolute()))
        if target == source:
            raise error(f"{out} is also an input ({item}); choose another {flag} (nothing is written)")
        if source in target.parents:
            raise error(
                f"{out} lies inside the input {item}; writing there would change it: choose another {flag} "
                f"(nothing is written)"
            )
        if contains and target in source.parents:
            raise error(f"{out} holds the input {item}; choose another {flag} (nothing is written)")


def check_append(
    path: str | os.PathLike, *, kind: OutputKind, flag: str = "--out", error: type[DSSPError] = OutputError
) -> str:
    """For commands that add to their output: NEW or OWN (to be continued); anything else raises."""
    path = Path(path)
    check_name_lengths(path, flag, error)
    found = _found(path, kind)
    if found == "foreign":
        raise error(_foreign_message(path, kind, flag))
    if found == NEW:
        check_parent(path, flag, error)
    return found


def claim_dir(
    path: str | os.PathLike,
    *,
    kind: OutputKind,
    flag: str = "--out",
    resume: bool = False,
    error: type[DSSPError] = OutputError,
) -> Path:
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

    ``staged=True`` (default): ``target.path`` is a temporary sibling ``.NAME.partial-XXXXXXXX`` (a
    :class:`Staging` directory) that :meth:`commit` swaps onto ``out`` (:func:`~dssp_core.files.replace_dirs`; a previous
    output is deleted after the swap). ``staged=False``, for outputs that record their own path or are
    watched while they grow (runs, demos): ``target.path`` is ``out`` itself; a previous output (``--force``)
    is first moved aside to ``.NAME.old-XXXX`` and deleted on :meth:`commit`. Without a commit (an error,
    Ctrl-C) what this command created is removed and a previous output is put back — except with
    ``keep_partial``, when an unfinished output that replaced nothing and holds something stays (a training
    run to ``--resume``). Parent directories this command created are removed with it.
    """

    def __init__(
        self,
        out: str | os.PathLike,
        kind: OutputKind,
        *,
        force: bool = False,
        flag: str = "--out",
        staged: bool = True,
        keep_partial: bool = False,
        error: type[DSSPError] = OutputError,
    ):
        self.out = Path(out).absolute()
        self.kind, self.force, self.flag, self.staged = kind, force, flag, staged
        self.keep_partial, self.error = keep_partial, error
        self.path: Path | None = None
        self.found: str | None = None
        self._old: Path | None = None
        self._created: list[Path] = []
        self._staging: Staging | None = None
        self._made_out = False
        self._committed = False

    def check(self) -> str:
        return check_output(self.out, force=self.force, kind=self.kind, flag=self.flag, error=self.error)

    def __enter__(self) -> "OutputDir":
        self.found = self.check()
        try:
            if self.staged:
                self._staging = Staging(flag=self.flag, error=self.error, tag="partial")
                self.path = self._staging.make(self._staging.reserve(self.out))
            else:
                self._created = make_dirs(self.out.parent, flag=self.flag, error=self.error)
                if self.found == OWN:
                    old = sibling_name(self.out, "old")
                    os.replace(self.out, old)
                    self._old = old  # only once it is moved: a rollback puts it back
                self._made_out = not self.out.exists()
                self.out.mkdir(exist_ok=True)
                self.path = self.out
            self.kind.write_marker(self.path)
        except OSError as exc:
            self._rollback()
            raise self.error(
                f"cannot write to {self.out.parent} ({exc.strerror or exc}); choose a writable {self.flag}"
            ) from None
        except BaseException:
            self._rollback()
            raise
        return self

    def commit(self) -> Path:
        """Put the finished output in place (replacing a previous one when allowed); returns ``out``."""
        if self.staged:
            self._staging.commit([(self.path, self.out)], check=self.check)  # again: something may have appeared
        with interrupts_deferred(reraise=not self.staged):  # staged: in place now, a Ctrl-C comes too late
            self._committed = True
            if self._old is not None:
                shutil.rmtree(self._old, ignore_errors=True)
                self._old = None
        return self.out

    def _rollback(self) -> None:
        with interrupts_deferred():
            if self._staging is not None:
                self._staging.discard()
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
        if not (self._committed or (self._staging is not None and self._staging.committed)):  # in place: kept
            self._rollback()


def _empty(path: Path) -> bool:
    try:
        return all(name == MARKER for name in os.listdir(path))
    except OSError:
        return False


# ------------------------------------------------------------------------------------------- single files
def check_output_file(
    path: str | os.PathLike, *, force: bool, flag: str = "--out", error: type[DSSPError] = OutputError
) -> Path:
    """A new file may be written; an existing one only with ``force``; never over a directory or a symlink."""
    path = Path(path)
    check_name_lengths(path, flag, error)
    if path.is_symlink() or (path.exists() and not path.is_file()):
        raise error(f"{path} exists and is not a file; choose another {flag} (nothing is deleted)")
    if path.exists() and not force:
        raise error(f"{path} exists; pass --force to replace it or choose another {flag}")
    check_parent(path, flag, error)
    return path


def write_output_file(
    path: str | os.PathLike,
    write: Callable[[str], None],
    *,
    force: bool,
    flag: str = "--out",
    error: type[DSSPError] = OutputError,
    suffix: str = ".tmp",
) -> Path:
    """Check ``path`` (:func:`check_output_file`), create its parents, and call ``write(tmp)`` atomically.

    ``suffix``: the temporary file's ending, for writers that take the format from the name (``".tmp.gif"``).
    """
    path = check_output_file(path, force=force, flag=flag, error=error)
    created = make_dirs(path.parent, flag=flag, error=error)
    try:
        atomic_write(path, write, suffix=suffix)
    except OSError as exc:
        remove_created(created)
        raise error(f"cannot write {path} ({exc.strerror or exc}); choose a writable {flag}") from None
    return path


def write_output_text(
    path: str | os.PathLike, text: str, *, force: bool, flag: str = "--out", error: type[DSSPError] = OutputError
) -> Path:
    """:func:`write_output_file` for text (JSON, Markdown)."""
    return write_output_file(path, text_writer(text), force=force, flag=flag, error=error)


def write_output_figure(
    path: str | os.PathLike,
    fig,
    *,
    force: bool,
    flag: str = "--out",
    dpi: int = 100,
    error: type[DSSPError] = OutputError,
) -> Path:
    """:func:`write_output_file` for a matplotlib figure (PNG), which is closed afterwards."""
    import matplotlib.pyplot as plt  # optional: matplotlib; the core imports the standard library only

    try:
        return write_output_file(
            path, lambda tmp: fig.savefig(tmp, format="png", dpi=dpi), force=force, flag=flag, error=error
        )
    finally:
        plt.close(fig)


def check_output_files(
    paths: Iterable[str | os.PathLike], *, force: bool, flag: str = "--out", error: type[DSSPError] = OutputError
) -> list[Path]:
    """:func:`check_output_file` for several files at once (all are checked before any is written)."""
    return [check_output_file(p, force=force, flag=flag, error=error) for p in paths]
