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
studies.sim_study`` resumes its work directory) continue only their own kind (:func:`check_append`,
:func:`claim_dir` with ``resume=True``) and refuse anything else.

Single files (JSON reports, PNG plots; :func:`check_output_file`, :func:`write_output_text`,
:func:`write_output_file`): a new file is written; an existing file is replaced only with ``--force``; a
directory or a symlink at that path is always refused. Files are written to a temporary name beside the
target and renamed over it (:mod:`dssp_data.files`).

Where an output goes: a path under a file, or in a folder that cannot be written, is refused with one
line (:func:`check_output`, :func:`check_output_file`, :func:`make_dirs`); so is an output that is one of
the command's inputs or lies inside one (:func:`check_not_inside`).

Staging (:class:`Staging`, used by :class:`OutputDir` and the dataset writers): a directory is built as a
hidden sibling ``.NAME.tmp-XXXXXXXX`` (``.NAME.partial-XXXXXXXX`` for :class:`OutputDir`) that this
process holds an ``flock`` on while it writes, then renamed onto ``NAME`` (:func:`~dssp_data.files.replace_dirs`: a previous
output is moved aside first and deleted only once the new one is in place). On any other exit (an error,
Ctrl-C) the staging directory is removed: zarr's background writes are let finish first
(:func:`settle_background_writes`), and a second Ctrl-C during the clean-up or the final renames is held
back until they are done (:func:`interrupts_deferred`). A process killed outright (SIGKILL) cannot clean
up: the next command that writes the same output removes the staging directories of that name that no
live process holds (:func:`sweep_stale`) — only names of exactly that pattern, never ``.NAME.old-*`` (a
previous output moved aside, possibly the only copy).

Every refusal is an :class:`OutputError`: one line, exit code 2 in the command-line tools.
"""

from __future__ import annotations

import contextlib
import fnmatch
import json
import os
import re
import shutil
import signal
import sys
import threading
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from dssp_data.files import atomic_write, atomic_write_text, replace_dirs, sibling_name, text_writer
from dssp_data.errors import DSSPError

MARKER = ".dssp-output.json"
"""The file a command writes into a directory it creates: which command made it and what it is."""

NEW, OWN = "new", "own"
"""What :func:`check_output` found: nothing (or an empty directory), or a previous output of the kind."""

__all__ = [
    "MARKER", "NEW", "OWN", "OutputError", "OutputKind", "check_output", "check_append", "claim_dir", "OutputDir",
    "check_output_file", "check_output_files", "write_output_text", "write_output_file", "zarr_attrs", "zarr_generator",
    "check_not_inside", "make_dirs", "Staging", "replace_dirs", "sweep_stale", "is_staging_name",
    "interrupts_deferred", "settle_background_writes", "WriterLock", "writer_lock", "writer_lock_path", "read_regular_text",
    "RUN_DIR", "SYNTH_DATASET", "SIM_DATASET", "RECORDED_DATASET", "DATA_DATASET", "DATA_GENERATORS", "RUN_LOG",
]


class OutputError(DSSPError):
    """An output path holds something the command may not replace."""


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


def check_output(path: str | os.PathLike, *, force: bool | None, kind: OutputKind, flag: str = "--out",
                 error: type[DSSPError] = OutputError) -> str:
    """Whether the command may write ``kind`` at ``path``: returns NEW or OWN (only with ``force``), else raises.

    ``force=None``: the command has no ``--force`` (its previous output is refused without the hint).
    """
    path = Path(path)
    found = _found(path, kind)
    if found == "foreign":
        raise error(_foreign_message(path, kind, flag))
    _check_companion(path, kind, found, flag, error)
    if found == NEW:
        _check_parent(path, flag, error)
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
        raise error(f"{companion} exists without {path.name} (it belongs to another dataset?); choose another {flag} "
                    f"(nothing is deleted)")
    if not kind.owns_companion(companion):
        raise error(f"{companion} holds files {kind.command} does not write; choose another {flag} (nothing is deleted)")


def _check_parent(path: Path, flag: str, error: type[DSSPError]) -> None:
    """The nearest existing folder above ``path`` must be a folder this process may write into."""
    path = Path(path).absolute()
    for parent in path.parents:
        if parent.exists() or parent.is_symlink():
            break
    else:
        return
    if not parent.is_dir():
        raise error(f"cannot write {path}: {parent} is a file, not a folder; choose another {flag}")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise error(f"cannot write {path}: {parent} is not writable; choose another {flag}")


def make_dirs(path: str | os.PathLike, *, flag: str = "--out", error: type[DSSPError] = OutputError) -> list[Path]:
    """Create the folder ``path`` and its parents; returns the folders created (outermost first).

    A path under a file, or one that cannot be created, is a one-line ``error`` (nothing is left behind).
    """
    path = Path(path).absolute()
    _check_parent(path, flag, error)
    if path.is_dir():
        return []
    if path.exists() or path.is_symlink():
        raise error(f"cannot write into {path}: it is a file, not a folder; choose another {flag}")
    missing, folder = [], path
    while not (folder.exists() or folder.is_symlink()):
        missing.append(folder)
        folder = folder.parent
    created = []
    try:
        for folder in reversed(missing):
            folder.mkdir()
            created.append(folder)
    except OSError as exc:
        _remove_created(created)
        raise error(f"cannot write {path} ({exc.strerror or exc}); choose a writable {flag}") from None
    return created


def _remove_created(created: list[Path]) -> None:
    """Remove the (still empty) folders a failed write created, innermost first."""
    for folder in reversed(created):
        with contextlib.suppress(OSError):
            folder.rmdir()


def check_not_inside(out: str | os.PathLike, inputs: Iterable[str | os.PathLike], *, flag: str = "--out",
                     error: type[DSSPError] = OutputError, contains: bool = True) -> None:
    """Refuse an output that is one of ``inputs`` or lies inside one (symbolic links resolved).

    ``contains``: also refuse an output that holds an input (replacing the output would delete it).
    """
    target = Path(os.path.realpath(Path(out).absolute()))
    for item in inputs:
        source = Path(os.path.realpath(Path(item).absolute()))
        if target == source:
            raise error(f"{out} is also an input ({item}); choose another {flag} (nothing is written)")
        if source in target.parents:
            raise error(f"{out} lies inside the input {item}; writing there would change it: choose another {flag} "
                        f"(nothing is written)")
        if contains and target in source.parents:
            raise error(f"{out} holds the input {item}; choose another {flag} (nothing is written)")


def check_append(path: str | os.PathLike, *, kind: OutputKind, flag: str = "--out",
                 error: type[DSSPError] = OutputError) -> str:
    """For commands that add to their output: NEW or OWN (to be continued); anything else raises."""
    path = Path(path)
    found = _found(path, kind)
    if found == "foreign":
        raise error(_foreign_message(path, kind, flag))
    if found == NEW:
        _check_parent(path, flag, error)
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

    ``staged=True`` (default): ``target.path`` is a temporary sibling ``.NAME.partial-XXXXXXXX`` (a
    :class:`Staging` directory) that :meth:`commit` swaps onto ``out`` (:func:`replace_dirs`; a previous
    output is deleted after the swap). ``staged=False``, for outputs that record their own path or are
    watched while they grow (runs, demos): ``target.path`` is ``out`` itself; a previous output (``--force``)
    is first moved aside to ``.NAME.old-XXXX`` and deleted on :meth:`commit`. Without a commit (an error,
    Ctrl-C) what this command created is removed and a previous output is put back — except with
    ``keep_partial``, when an unfinished output that replaced nothing and holds something stays (a training
    run to ``--resume``). Parent directories this command created are removed with it.
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
            raise self.error(f"cannot write to {self.out.parent} ({exc.strerror or exc}); choose a writable {self.flag}") from None
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


# -------------------------------------------------------------------------------------- one writer
def writer_lock_path(out: str | os.PathLike) -> Path:
    """The lock file of the output at ``out``: ``.NAME.lock`` beside it, so it outlives the swaps of a
    staged output and covers an output that does not exist yet."""
    out = Path(out).absolute()
    return out.with_name(f".{out.name}.lock")


class WriterLock:
    """One writer per output: an exclusive ``flock`` on :func:`writer_lock_path` (``out``), held until
    :meth:`release` (or the process ends: the system lets go of a dead process's lock).

    A second writer gets one line naming the holder (what it does, pid and host, as the holder wrote them
    into the lock file: ``doing`` is "written" or e.g. "recorded into") and what to do, as ``error``;
    nothing of the first is touched. The lock file is opened without following links and must be a regular
    file (a symlink planted at its name is refused, never followed); it is removed on release, and a lock won
    on a file that was removed or replaced meanwhile is retried on the new one.

        lock = WriterLock(out, what="run directory", flag="--out")
        try: ...write...
        finally: lock.release()
    """

    def __init__(self, out: str | os.PathLike, *, what: str = "output", flag: str = "--out",
                 error: type[DSSPError] = OutputError, doing: str = "written") -> None:
        import fcntl
        import socket
        import stat

        self.path = writer_lock_path(out)
        self._fd: int | None = None
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise error(f"cannot create {self.path.parent} ({exc.strerror or exc}); choose a writable {flag}") from None
        for _ in range(100):
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK, 0o644)
            except OSError as exc:
                raise error(f"cannot open the lock file {self.path} ({exc.strerror or exc}): it must be a regular "
                            f"file, not a link; remove it or choose another {flag}") from None
            info = os.fstat(fd)
            if not stat.S_ISREG(info.st_mode):
                os.close(fd)
                raise error(f"the lock file {self.path} is not a regular file; remove it or choose another {flag}")
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                try:
                    holder = " ".join(os.pread(fd, 200, 0).decode(errors="replace").split()) or "another process"
                finally:
                    os.close(fd)
                if " by " not in holder:  # a lock file that does not say what its holder does
                    holder = f"written by {holder}"
                raise error(f"{Path(out)} is being {holder}: one writer per {what} at a time; wait for "
                            f"it to finish or choose another {flag}") from None
            try:
                now = os.stat(self.path, follow_symlinks=False)
            except OSError:
                now = None
            if now is None or (now.st_dev, now.st_ino) != (info.st_dev, info.st_ino):
                os.close(fd)  # released and removed by its previous holder between our open and flock: again
                continue
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{doing} by pid {os.getpid()} on {socket.gethostname()}\n".encode(), 0)
            self._fd = fd
            return
        raise error(f"could not take the lock {self.path}; try again")

    @property
    def held(self) -> bool:
        return self._fd is not None

    def release(self) -> None:
        """Remove the lock file (while still holding it) and let go; idempotent."""
        fd, self._fd = self._fd, None
        if fd is None:
            return
        try:
            info, now = os.fstat(fd), os.stat(self.path, follow_symlinks=False)
            if (now.st_dev, now.st_ino) == (info.st_dev, info.st_ino):
                os.unlink(self.path)
        except OSError:
            pass
        finally:
            os.close(fd)

    def __enter__(self) -> "WriterLock":
        return self

    def __exit__(self, *exc) -> None:
        self.release()


@contextlib.contextmanager
def writer_lock(out: str | os.PathLike, *, what: str, flag: str = "--out", error: type[DSSPError] = OutputError,
                doing: str = "written") -> Iterator[WriterLock]:
    """Hold the :class:`WriterLock` of ``out`` inside the block (every command's one writer per output).

    The folders above ``out`` that the lock file needs are created first (a path under a file is one line
    naming ``flag``) and removed again at the end if they are still empty.
    """
    created = make_dirs(Path(out).absolute().parent, flag=flag, error=error)
    try:
        lock = WriterLock(out, what=what, flag=flag, error=error, doing=doing)
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


# ------------------------------------------------------------------------------------------- staging
_STAGE = r"\.(?:tmp-[0-9a-f]{8}|partial-[0-9a-f]{8})"
_STAGING_NAME = re.compile(rf"^\..+{_STAGE}(?:\.can)?$")
_locks: dict[tuple[int, int], int] = {}
"""Staging directories this process holds an ``flock`` on: (device, inode) → open descriptor."""


def is_staging_name(name: str) -> bool:
    """True for the name of a staging directory (``.NAME.tmp-XXXXXXXX``, ``.NAME.partial-XXXXXXXX``, and
    such a name followed by ``.can``)."""
    return bool(_STAGING_NAME.match(name))


def _lock_dir(path: Path) -> None:
    import fcntl

    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BaseException:
        os.close(fd)
        raise
    info = os.fstat(fd)
    _locks[(info.st_dev, info.st_ino)] = fd


def _unlock_dir(path: Path) -> None:
    try:
        info = os.stat(path, follow_symlinks=False)
    except OSError:
        return
    fd = _locks.pop((info.st_dev, info.st_ino), None)
    if fd is not None:
        os.close(fd)


def _remove_dir(path: Path) -> None:
    """Remove a staging directory of this process (and let go of its lock)."""
    try:
        info = os.stat(path, follow_symlinks=False)
    except OSError:
        return
    fd = _locks.pop((info.st_dev, info.st_ino), None)
    try:
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
    finally:
        if fd is not None:
            os.close(fd)


def sweep_stale(out: str | os.PathLike) -> list[Path]:
    """Remove the staging directories of ``out`` that a killed process left behind; returns them.

    Only directories beside ``out`` named exactly as :class:`Staging` names them for ``out``
    (``.NAME.tmp-XXXXXXXX``, ``.NAME.partial-XXXXXXXX``, nested ``..NAME.tmp-XXXXXXXX.tmp-XXXXXXXX`` and
    their ``.can`` companions) and that no live process holds (the ``flock`` its writer holds dies with it).
    """
    import fcntl

    out = Path(out).absolute()
    pattern = re.compile(rf"^(\.+){re.escape(out.name)}((?:{_STAGE})+)(\.can)?$")
    try:
        names = os.listdir(out.parent)
    except OSError:
        return []
    removed = []
    for name in names:
        match = pattern.match(name)
        if not match or len(match.group(1)) != len(re.findall(_STAGE, match.group(2))):
            continue
        path = out.parent / name
        try:
            fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW)
        except OSError:  # not a directory, a symbolic link, gone
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:  # a live writer holds it
            os.close(fd)
            continue
        try:
            shutil.rmtree(path, ignore_errors=True)
            removed.append(path)
        finally:
            os.close(fd)
    return removed


PUT_IN_PLACE: list[Path] = []
"""Every output this process has put in place (:meth:`Staging.commit`), in order: a command interrupted after
its outputs were complete says so (``dssp_data.cli_runner.run_cli``) instead of claiming it wrote nothing."""


class Staging:
    """Hidden directories beside their outputs, written by this process and put in place together.

        with Staging(flag="--out", error=DatasetError) as staging:
            tmp = staging.make(staging.reserve(out))   # .OUT.tmp-XXXXXXXX, created and locked
            ... write into tmp ...
            staging.commit([(tmp, out)])

    :meth:`reserve` sweeps the stale staging directories of ``out`` (:func:`sweep_stale`), creates the
    missing parent folders and returns a new staging name beside ``out``; :meth:`make` creates a
    directory there and locks it (a writer that creates the directory itself calls :meth:`hold` on it).
    Leaving the block without :meth:`commit` (an error, Ctrl-C, a kill of the parent) waits for zarr's
    background writes (:func:`settle_background_writes`), removes every reserved name (and its ``.can``
    companion) and the parent folders it created.
    """

    def __init__(self, *, flag: str = "--out", error: type[DSSPError] = OutputError, tag: str = "tmp"):
        self.flag, self.error, self.tag = flag, error, tag
        self.reserved: list[Path] = []
        self._created: list[Path] = []
        self.committed = False

    def reserve(self, out: str | os.PathLike) -> Path:
        out = Path(out).absolute()
        sweep_stale(out)
        self._created += make_dirs(out.parent, flag=self.flag, error=self.error)
        path = sibling_name(out, self.tag)
        self.reserved.append(path)
        return path

    def make(self, path: Path) -> Path:
        """Create the staging directory ``path`` (a reserved name, or its ``.can`` companion) and lock it."""
        try:
            os.mkdir(path)
        except OSError as exc:
            raise self.error(f"cannot write to {path.parent} ({exc.strerror or exc}); choose a writable {self.flag}") from None
        self.hold(path)
        return path

    def hold(self, path: Path) -> None:
        """Lock a staging directory this process created, so that :func:`sweep_stale` leaves it alone."""
        _lock_dir(path)

    def commit(self, moves: Sequence[tuple[Path | None, Path]], check: Callable[[], object] | None = None) -> None:
        """Put the staged outputs in place (:func:`replace_dirs`). ``check`` runs first (nothing appeared
        meanwhile; it raises to refuse). A Ctrl-C before the renames stops the commit (KeyboardInterrupt: nothing
        is put in place); one during the renames comes too late: the outputs are complete, and the command goes
        on as if it had come after (it never reports an interruption with its outputs in place)."""
        with interrupts_deferred(reraise=False) as caught:
            if check is not None:
                check()
            if caught:
                caught.clear()
                raise KeyboardInterrupt
            replace_dirs(moves)
            self.committed = True
            PUT_IN_PLACE.extend(Path(target) for source, target in moves if source is not None)
            for _, target in moves:
                _unlock_dir(Path(target))

    def discard(self) -> None:
        """Remove what this staging wrote (once zarr has settled) and the parent folders it created."""
        settle_background_writes()
        with interrupts_deferred():
            for path in self.reserved:
                for item in (path, path.with_name(path.name + ".can")):
                    _remove_dir(item)
            for folder in reversed(self._created):
                try:
                    folder.rmdir()
                except OSError:
                    break
            self.reserved, self._created = [], []

    def __enter__(self) -> "Staging":
        return self

    def __exit__(self, *exc_info) -> None:
        if not self.committed:
            self.discard()


# ------------------------------------------------------------------------------------------- interruptions
@contextlib.contextmanager
def interrupts_deferred(reraise: bool = True) -> Iterator[list]:
    """Hold back Ctrl-C (SIGINT) inside the block, then act on it (``reraise``: KeyboardInterrupt) at its end.

    For steps that must not stop half-way: renames that put outputs in place, the removal of a staging
    directory. Only in the main thread (elsewhere signals are not delivered); a no-op when SIGINT is ignored.
    The block gets the list of the Ctrl-Cs held back so far (a step can look before it begins).
    """
    if threading.current_thread() is not threading.main_thread():
        yield []
        return
    previous = signal.getsignal(signal.SIGINT)
    if previous in (signal.SIG_IGN, None):
        yield []
        return
    caught: list = []
    signal.signal(signal.SIGINT, lambda signum, frame: caught.append(frame))
    try:
        yield caught
    finally:
        signal.signal(signal.SIGINT, previous)
        if caught and reraise:
            if callable(previous):
                previous(signal.SIGINT, sys._getframe())
            else:
                os.kill(os.getpid(), signal.SIGINT)


def settle_background_writes(timeout: float = 120.0) -> None:
    """Wait until zarr's background event loop has finished what it was doing (at most ``timeout`` s).

    zarr 3 runs every read and write as coroutines on its own thread (and a thread pool); a Ctrl-C reaches
    only the main thread, which stops waiting while the operation goes on writing files. Before a staging
    directory is removed, and before the process exits on Ctrl-C, its work must end (else files reappear
    after the removal, or zarr's pool is shut down under it at exit). A further Ctrl-C meanwhile is ignored.
    """
    module = sys.modules.get("zarr.core.sync")
    loop = (getattr(module, "loop", None) or [None])[0] if module is not None else None
    if loop is None or loop.is_closed() or not loop.is_running():
        return
    import asyncio

    async def idle() -> None:
        me = asyncio.current_task()
        deadline = loop.time() + timeout
        while loop.time() < deadline:
            others = [t for t in asyncio.all_tasks() if t is not me and not t.done()]
            if not others:
                return
            await asyncio.wait(others, timeout=max(0.01, deadline - loop.time()))

    with interrupts_deferred(reraise=False):
        try:
            asyncio.run_coroutine_threadsafe(idle(), loop).result(timeout + 5.0)
        except Exception:  # the loop stopped, or the time is up: nothing more to wait for
            pass


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
    _check_parent(path, flag, error)
    return path


def write_output_file(path: str | os.PathLike, write: Callable[[str], None], *, force: bool, flag: str = "--out",
                      error: type[DSSPError] = OutputError, suffix: str = ".tmp") -> Path:
    """Check ``path`` (:func:`check_output_file`), create its parents, and call ``write(tmp)`` atomically.

    ``suffix``: the temporary file's ending, for writers that take the format from the name (``".tmp.gif"``).
    """
    path = check_output_file(path, force=force, flag=flag, error=error)
    created = make_dirs(path.parent, flag=flag, error=error)
    try:
        atomic_write(path, write, suffix=suffix)
    except OSError as exc:
        _remove_created(created)
        raise error(f"cannot write {path} ({exc.strerror or exc}); choose a writable {flag}") from None
    return path


def write_output_text(path: str | os.PathLike, text: str, *, force: bool, flag: str = "--out",
                      error: type[DSSPError] = OutputError) -> Path:
    """:func:`write_output_file` for text (JSON, Markdown)."""
    return write_output_file(path, text_writer(text), force=force, flag=flag, error=error)


def write_output_figure(path: str | os.PathLike, fig, *, force: bool, flag: str = "--out", dpi: int = 100,
                        error: type[DSSPError] = OutputError) -> Path:
    """:func:`write_output_file` for a matplotlib figure (PNG), which is closed afterwards."""
    import matplotlib.pyplot as plt

    try:
        return write_output_file(path, lambda tmp: fig.savefig(tmp, format="png", dpi=dpi), force=force, flag=flag, error=error)
    finally:
        plt.close(fig)


def check_output_files(paths: Iterable[str | os.PathLike], *, force: bool, flag: str = "--out",
                       error: type[DSSPError] = OutputError) -> list[Path]:
    """:func:`check_output_file` for several files at once (all are checked before any is written)."""
    return [check_output_file(p, force=force, flag=flag, error=error) for p in paths]


# ------------------------------------------------------------------------------------------- known kinds
METADATA_LIMIT = 256 << 20
"""Bytes a metadata file (a marker, a zarr group's attributes, a run's config.json) may hold."""


def read_regular_text(path: str | os.PathLike, limit: int = METADATA_LIMIT) -> str | None:
    """The text of ``path`` if it is a regular file, read without following a link; None when there is no
    such file (absent, a symbolic link, a FIFO or a device: never opened through, never waited on).
    A file larger than ``limit`` bytes or not UTF-8 raises ValueError."""
    import stat

    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError:
        return None
    with os.fdopen(fd, "rb") as f:
        info = os.fstat(f.fileno())
        if not stat.S_ISREG(info.st_mode):
            return None
        data = f.read(limit + 1)
    if len(data) > limit:
        raise ValueError(f"{path} holds more than {limit} bytes")
    return data.decode()


def zarr_attrs(path: str | os.PathLike) -> dict | None:
    """The root attributes of a zarr group at ``path`` (format 2 or 3), read as JSON; None if it is not one.

    Its metadata files are read only as regular files (:func:`read_regular_text`), no link followed: with a
    linked ``.zgroup`` or ``zarr.json`` the folder is not a zarr group, with a linked ``.zattrs`` it has no
    attributes."""
    path = Path(path)
    if read_regular_text(path / ".zgroup") is not None:
        text = read_regular_text(path / ".zattrs")
        attrs = json.loads(text) if text is not None else {}
    elif (text := read_regular_text(path / "zarr.json")) is not None:
        meta = json.loads(text)
        attrs = meta.get("attributes", {}) if isinstance(meta, dict) else None
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
"""The top-level names of a DP3 zarr dataset as :mod:`dssp_data.replay_buffer` writes it."""


def _run_signature(path: Path) -> bool:
    config = json.loads(read_regular_text(path / "config.json") or "null")
    return isinstance(config, dict) and "model" in config and "train" in config


RUN_DIR = OutputKind("a run directory", "dssp-train",
                     entries=("config.json", "model.safetensors", "checkpoint", "log.jsonl", "loss.png", "tensorboard", "wandb"),
                     signature=_run_signature, marker=False)
"""``dssp-train --out``: config.json (a JSON object with ``model`` and ``train``), model.safetensors,
checkpoint/, log.jsonl, loss.png, and the dashboards' tensorboard/ and wandb/ (``--log``) — recognised by its
config.json, no marker added."""

def _made_by(path: Path, generators: Iterable[str]) -> bool:
    """The zarr dataset at ``path`` names one of ``generators`` as its ``generator``, and was not made from
    other datasets by an older ``dssp-data merge``/``split`` (which copied its first input's generator)."""
    attrs = zarr_attrs(path) or {}
    return attrs.get("generator") in tuple(generators) and "merged_from" not in attrs and "split_from" not in attrs


SYNTH_DATASET = OutputKind("a synthetic dataset", "dssp-synth", entries=ZARR_ENTRIES, marker=False,
                           signature=lambda p: _made_by(p, ("dssp_train.data.synthetic",)))
"""``dssp-synth --out``: a zarr dataset whose ``generator`` attribute is ``dssp_train.data.synthetic``."""

DATA_GENERATORS = {"merge": "dssp-data merge", "split": "dssp-data split", "convert": "dssp-data convert"}
"""The ``generator`` attribute each ``dssp-data`` command writes into the datasets it makes."""
_LEGACY_DATA_GENERATORS = ("dssp-data convert (RoboTwin raw HDF5)",)
"""What older versions of ``dssp-data convert`` wrote (merge and split copied their input's generator:
their older outputs are not recognised, so they are never replaced)."""

DATA_DATASET = OutputKind("a dataset", "dssp-data merge, split or convert", entries=ZARR_ENTRIES, marker=False,
                          signature=lambda p: zarr_generator(p) in (*DATA_GENERATORS.values(), *_LEGACY_DATA_GENERATORS),
                          companion=".can", companion_entries=("episode_*.blf",))
"""``dssp-data merge OUT``, ``split --train/--val``, ``convert --out``: a zarr dataset whose ``generator``
attribute is one of :data:`DATA_GENERATORS`, with its CAN logs at ``OUT.can`` (only ``episode_*.blf``)."""

SIM_DATASET = OutputKind("a simulation dataset", "dssp-sim collect", marker=False,
                         signature=lambda p: zarr_generator(p) == "dssp_sim.collect")
"""``dssp-sim collect --out``: a zarr dataset whose ``generator`` attribute is ``dssp_sim.collect`` (appended to)."""

RECORDED_DATASET = OutputKind("a recorded dataset", "dssp-record", marker=False,
                              signature=lambda p: zarr_generator(p) == "dssp-record")
"""``dssp-record --out``: a zarr dataset whose ``generator`` attribute is ``dssp-record`` (appended to)."""

RUN_LOG = OutputKind("an episode log", "dssp-run")
"""``dssp-run --log-dir``: a new directory for one run's log (marked); an existing log is never reused."""
