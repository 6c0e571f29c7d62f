"""Outputs written beside their place and put there whole: one writer per output, staging directories,
Ctrl-C held back where a step must not stop half-way (the standard library only).

One writer (:func:`writer_lock`, :class:`WriterLock`): an exclusive ``flock`` on ``.NAME.lock`` beside the
output, so a second command writing the same output is refused with one line instead of interleaving.

Staging (:class:`Staging`, used by :class:`~dssp_core.output_guard.OutputDir` and the dataset writers): a directory is built as a
hidden sibling ``.NAME.tmp-XXXXXXXX`` (``.NAME.partial-XXXXXXXX`` for :class:`OutputDir`) that this
process holds an ``flock`` on while it writes, then renamed onto ``NAME`` (:func:`~dssp_core.files.replace_dirs`: a previous
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

import asyncio
import contextlib
import fcntl
import os
import re
import shutil
import signal
import socket
import stat
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import ClassVar

from dssp_core.errors import DSSPError, OutputError
from dssp_core.files import make_dirs, replace_dirs, sibling_name

__all__ = [
    "WriterLock",
    "writer_lock",
    "writer_lock_path",
    "Staging",
    "sweep_stale",
    "is_staging_name",
    "staging_target",
    "PUT_IN_PLACE",
    "interrupts_deferred",
    "settle_background_writes",
]


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

    :meth:`held_here` says whether this process holds the lock of an output (what a writer that is handed
    the lock by its caller checks).
    """

    _held: ClassVar[set[Path]] = set()
    """The lock files this process holds."""

    def __init__(
        self,
        out: str | os.PathLike,
        *,
        what: str = "output",
        flag: str = "--out",
        error: type[DSSPError] = OutputError,
        doing: str = "written",
    ) -> None:

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
                raise error(
                    f"cannot open the lock file {self.path} ({exc.strerror or exc}): it must be a regular "
                    f"file, not a link; remove it or choose another {flag}"
                ) from None
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
                raise error(
                    f"{Path(out)} is being {holder}: one writer per {what} at a time; wait for "
                    f"it to finish or choose another {flag}"
                ) from None
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
            WriterLock._held.add(self.path)
            return
        raise error(f"could not take the lock {self.path}; try again")

    @property
    def held(self) -> bool:
        return self._fd is not None

    @classmethod
    def held_here(cls, out: str | os.PathLike) -> bool:
        """True while this process holds the lock of the output at ``out``."""
        return writer_lock_path(out) in cls._held

    def release(self) -> None:
        """Remove the lock file (while still holding it) and let go; idempotent."""
        fd, self._fd = self._fd, None
        if fd is None:
            return
        WriterLock._held.discard(self.path)
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
def writer_lock(
    out: str | os.PathLike,
    *,
    what: str,
    flag: str = "--out",
    error: type[DSSPError] = OutputError,
    doing: str = "written",
) -> Iterator[WriterLock]:
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
_STAGED_FOR = re.compile(rf"^\.(.+){_STAGE}$")
_locks: dict[tuple[int, int], int] = {}
"""Staging directories this process holds an ``flock`` on: (device, inode) → open descriptor."""


def is_staging_name(name: str) -> bool:
    """True for the name of a staging directory (``.NAME.tmp-XXXXXXXX``, ``.NAME.partial-XXXXXXXX``, and
    such a name followed by ``.can``)."""
    return bool(_STAGING_NAME.match(name))


def staging_target(path: str | os.PathLike) -> Path | None:
    """The output a staging directory is built for (``.NAME.tmp-XXXXXXXX`` -> ``NAME`` beside it, a nested one
    followed to its outermost output), or None when ``path`` is no staging directory's name."""
    path = Path(path).absolute()
    found = None
    while True:
        match = _STAGED_FOR.match(path.name)
        if not match:
            return found
        path = found = path.with_name(match.group(1))


def _lock_dir(path: Path) -> None:

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
its outputs were complete says so (``dssp_core.cli_runner.run_cli``) instead of claiming it wrote nothing."""


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
            raise self.error(
                f"cannot write to {path.parent} ({exc.strerror or exc}); choose a writable {self.flag}"
            ) from None
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
