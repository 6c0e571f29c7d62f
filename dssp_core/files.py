"""Atomic file writes and directory swaps (the standard library only; numpy for ``.npy`` files): a reader sees the old
version or the new one.

Each file is written to a temporary file in the same directory, then ``os.replace``d over the target, so
a crash never leaves a half-written file behind under the real name. :func:`replace_dirs` does the same
for directories built beside their targets (a zarr dataset, a checkpoint): the previous version is moved
aside, the new one moved in, the previous one deleted; if a move fails, the previous one is put back.
Files are copied out of a user's folder only by :func:`copy_regular_file` (regular files, no link followed).
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import stat
import tempfile
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path

from dssp_core.errors import DSSPError, OutputError


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


def text_writer(text: str) -> Callable[[str], None]:
    """A ``write(tmp)`` for :func:`atomic_write` that writes ``text`` and syncs it to disk."""

    def write(tmp: str) -> None:
        with open(tmp, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())

    return write


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write(path, text_writer(text))


def atomic_save_npy(path: Path, array) -> None:
    """``np.save`` without pickles (numeric arrays only), atomically."""
    import numpy as np  # only here: the core loads without numpy (the robot commands stop cleanly meanwhile)

    def write(tmp: str) -> None:
        with open(tmp, "wb") as f:
            np.save(f, np.asarray(array), allow_pickle=False)

    atomic_write(path, write)


def _no_link_below(base: Path, path: Path, error: type[DSSPError]) -> None:
    """``base`` is a real folder (not a link) and no folder between it and ``path`` is a link."""
    relative = Path(os.path.relpath(path, base))
    if relative.is_absolute() or ".." in relative.parts:
        raise error(f"{path} is not inside {base}: only a folder's own files are copied")
    folder = Path(base)
    for part in (None, *relative.parts[:-1]):
        folder = folder if part is None else folder / part
        try:
            info = os.lstat(folder)
        except OSError as exc:
            raise error(f"cannot read {folder} ({exc.strerror or exc})") from None
        if stat.S_ISLNK(info.st_mode) or not stat.S_ISDIR(info.st_mode):
            what = "a symbolic link" if stat.S_ISLNK(info.st_mode) else "not a folder"
            raise error(
                f"{folder} is {what}: only a folder's own files are copied (nothing is copied through a "
                f"link); move the files into a real folder"
            )


def copy_regular_file(
    src: str | os.PathLike, dst: str | os.PathLike, *, inside: str | os.PathLike, error: type[DSSPError] = DSSPError
) -> Path:
    """Copy ``src``, a regular file in the folder ``inside``, to the new file ``dst`` (mode and times kept).

    The one way files are copied out of a user's folder: nothing is followed out of it. ``inside`` and every
    folder between it and ``src`` must be real folders, ``src`` a regular file, each checked without following
    links (``src`` is opened with ``O_NOFOLLOW`` and checked on the open descriptor, so a link or a FIFO
    swapped in meanwhile is refused too); ``dst`` must not exist (it is created, never written through a
    link). Anything else is one line, as ``error``; nothing is copied then.
    """
    src, dst = Path(src), Path(dst)
    _no_link_below(Path(inside), src, error)
    try:
        fd = os.open(src, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise error(
                f"{src} is a symbolic link: only a folder's own files are copied; replace the link with the file"
            ) from None
        raise error(f"cannot read {src} ({exc.strerror or exc})") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise error(
                f"{src} is not a regular file (a FIFO, socket or device): only regular files are copied; remove it"
            )
        try:
            out = os.open(
                dst,
                os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC,
                stat.S_IMODE(info.st_mode) | stat.S_IWUSR,
            )
        except OSError as exc:
            raise error(f"cannot write {dst} ({exc.strerror or exc})") from None
        try:
            with os.fdopen(fd, "rb", closefd=False) as reader, os.fdopen(out, "wb", closefd=False) as writer:
                shutil.copyfileobj(reader, writer, 1 << 20)
            os.utime(out, ns=(info.st_atime_ns, info.st_mtime_ns))
        except BaseException:
            os.close(out)
            with contextlib.suppress(OSError):
                os.unlink(dst)
            raise
        os.close(out)
    finally:
        os.close(fd)
    return dst


def sibling_name(path: Path, tag: str) -> Path:
    """A fresh hidden name beside ``path``: ``.NAME.TAG-XXXXXXXX`` (8 hex digits)."""
    path = Path(path)
    return path.with_name(f".{path.name}.{tag}-{uuid.uuid4().hex[:8]}")


def replace_dirs(moves: Sequence[tuple[Path | None, Path]], *, aside: Callable[[Path], Path] | None = None) -> None:
    """Put each finished directory ``new`` in place of its ``target``, all or none: ``[(new, target), ...]``.

    Existing targets are first renamed aside (``aside(target)``, default ``.NAME.old-XXXXXXXX``), then each
    ``new`` is renamed onto its target (``new`` None: the target is only removed); if a rename fails,
    everything is put back. The old directories are deleted only once every new one is in place. Which
    targets may be replaced at all is :mod:`dssp_core.output_guard`'s decision.
    """
    aside = aside or (lambda target: sibling_name(target, "old"))
    moved, placed = [], []
    try:
        for _, target in moves:
            target = Path(target)
            if target.exists() or target.is_symlink():
                old = Path(aside(target))
                os.replace(target, old)
                moved.append((old, target))
        for new, target in moves:
            if new is not None:
                os.replace(new, target)
                placed.append((Path(new), Path(target)))
    except BaseException:
        for new, target in reversed(placed):
            with contextlib.suppress(OSError):
                os.replace(target, new)
        for old, target in reversed(moved):
            with contextlib.suppress(OSError):
                os.replace(old, target)
        raise
    for old, _ in moved:
        shutil.rmtree(old, ignore_errors=True)


def replace_dir(new: Path, target: Path, *, aside: Path | None = None) -> None:
    """:func:`replace_dirs` for one directory; ``aside``: where a previous ``target`` waits until ``new`` is
    in place (default ``.NAME.old-XXXXXXXX``)."""
    replace_dirs([(new, target)], aside=None if aside is None else lambda _: Path(aside))


# ------------------------------------------------------------------------------------------- folders
def check_parent(path: Path, flag: str, error: type[DSSPError]) -> None:
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


LONGEST_SIBLING = ".{name}.partial-XXXXXXXX"
"""The longest name a write puts beside an output (a staging folder; atomic files and locks are shorter)."""


def check_name_lengths(path: str | os.PathLike, flag: str, error: type[DSSPError]) -> None:
    """Refuse, before any work, an output whose names — the folders still to be made, its own, and the longest name
    a write puts beside it (:data:`LONGEST_SIBLING`) — are longer than the file system takes: the write would fail
    only at its end (after a training, a calibration tour)."""
    absolute = Path(os.path.abspath(path))
    folder = absolute.parent
    while True:
        try:
            if folder.is_dir():
                break
        except OSError:  # a name on the way is itself too long
            pass
        if folder.parent == folder:
            return
        folder = folder.parent
    try:
        limit = os.pathconf(folder, "PC_NAME_MAX")
    except (OSError, ValueError):
        return  # the file system does not say: the writes' own errors stand
    names = [*absolute.relative_to(folder).parts[:-1], absolute.name, LONGEST_SIBLING.format(name=absolute.name)]
    too_long = next((name for name in names if len(os.fsencode(name)) > limit), None)
    if too_long is not None:
        shown = str(path) if len(str(path)) <= 80 else str(path)[:80] + "…"
        name = too_long if len(too_long) <= 40 else too_long[:40] + "…"
        raise error(
            f"cannot write {shown}: the name {name!r} is longer than the {limit} bytes "
            f"{folder} takes (with the temporary name the write uses); choose a shorter {flag}"
        )


def make_dirs(path: str | os.PathLike, *, flag: str = "--out", error: type[DSSPError] = OutputError) -> list[Path]:
    """Create the folder ``path`` and its parents; returns the folders created (outermost first).

    A path under a file, or one that cannot be created, is a one-line ``error`` (nothing is left behind).
    """
    path = Path(path).absolute()
    check_parent(path, flag, error)
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
            try:
                folder.mkdir()
            except FileExistsError:  # another process made it meanwhile (two writers beside each other)
                if folder.is_dir() and not folder.is_symlink():
                    continue
                raise
            created.append(folder)
    except OSError as exc:
        remove_created(created)
        raise error(f"cannot write {path} ({exc.strerror or exc}); choose a writable {flag}") from None
    return created


def remove_created(created: list[Path]) -> None:
    """Remove the (still empty) folders a failed write created, innermost first."""
    for folder in reversed(created):
        with contextlib.suppress(OSError):
            folder.rmdir()


# ------------------------------------------------------------------------------------------- metadata
METADATA_LIMIT = 256 << 20
"""Bytes a metadata file (a marker, a zarr group's attributes, a run's config.json) may hold."""

SETTINGS_LIMIT = 16 << 20
"""Bytes a file a user names may hold (settings, poses, a board, extrinsics, a model's manifest): 16 MiB, far above
any real one (a 10,000-pose plan is under 1 MiB)."""


def _kind(mode: int) -> str:
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    if stat.S_ISDIR(mode):
        return "a directory"
    return "not a regular file"


def read_input_bytes(
    path: str | os.PathLike,
    label: str,
    *,
    limit: int = SETTINGS_LIMIT,
    error: type[DSSPError] = DSSPError,
    follow_links: bool = True,
) -> bytes:
    """The bytes of the file a user named, or one line (as ``error``, starting with ``label``) saying why not.

    The one read of such files: it is opened without blocking and checked on the open descriptor, so a FIFO, a
    device (``/dev/zero``), a socket or a directory is refused before a byte is read (a FIFO never blocks the
    command, a device never fills its memory); a file larger than ``limit`` bytes is refused by its size, and
    nothing beyond ``limit + 1`` bytes is ever read (a file that grows meanwhile). A symbolic link the user
    gave is followed: the path came from them, not from a file; ``follow_links=False`` for a file inside a folder
    the user named (a dataset's metadata), where a link is refused.
    """
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC | (0 if follow_links else os.O_NOFOLLOW))
    except FileNotFoundError:
        raise error(f"{label} does not exist; check the path") from None
    except OSError as exc:
        if exc.errno == errno.ELOOP and not follow_links:
            raise error(
                f"{label} is a symbolic link: a folder's own files are read, no link is followed; replace "
                f"the link with the file"
            ) from None
        if exc.errno == errno.ENXIO:  # a socket: it cannot be opened at all
            with contextlib.suppress(OSError):
                raise error(f"{label} is {_kind(os.stat(path).st_mode)}, not a file; give a regular file") from None
        raise error(f"{label} cannot be read ({exc.strerror or exc}); check its permissions") from None
    info = os.fstat(fd)
    if not stat.S_ISREG(info.st_mode):
        os.close(fd)
        raise error(f"{label} is {_kind(info.st_mode)}, not a file; give a regular file")
    with os.fdopen(fd, "rb") as f:
        if info.st_size > limit:
            raise error(
                f"{label} holds {info.st_size} bytes, more than the {limit} such a file may hold; "
                f"check that it is the right file"
            )
        try:
            data = f.read(limit + 1)
        except OSError as exc:
            raise error(f"{label} cannot be read ({exc.strerror or exc}); check the file") from None
    if len(data) > limit:
        raise error(
            f"{label} holds more than the {limit} bytes such a file may hold (it grew while read); "
            f"check that it is the right file"
        )
    return data


def read_regular_text(path: str | os.PathLike, limit: int = METADATA_LIMIT) -> str | None:
    """The text of ``path`` if it is a regular file, read without following a link; None when there is no
    such file (absent, a symbolic link, a FIFO or a device: never opened through, never waited on).
    A file larger than ``limit`` bytes or not UTF-8 raises ValueError."""
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
