"""Checked access to a dataset's zarr arrays, chunk by chunk: what every read of :mod:`dssp_data.replay_buffer` and
every append of :mod:`dssp_data.replay_buffer_writer` goes through.

Chunks. Every read goes through one checked path (:class:`StoredArray`): before reading a key, the
chunks the read needs are looked up in the store's listing (zarr 2 names them ``data/action/3.0``,
zarr 3 ``data/action/c/3/0``; the array's metadata says which); then each chunk's bytes are fetched,
a Blosc frame is checked against the bytes actually stored (its header's size and block offsets), and
the whole chunk is decoded with the array's codecs. A slice is never decompressed in part: zarr 2's
partial decompression (``partial_decompress``) calls c-blosc's ``blosc_getitem``, which is given no
buffer length and follows the offsets in the frame's header, so a truncated chunk file makes it read
past the end of the buffer and kill the process (SIGSEGV); old c-blosc did the same when decompressing
a whole chunk (numcodecs issue 228). Checking the header against the bytes actually stored before any
decoder sees them keeps that out of reach whatever the installed versions. A chunk that is missing,
truncated or does not decode raises :class:`~dssp_core.errors.DatasetError` naming the key, the chunk, its steps
and episodes, and what to do. Blosc frames carry no checksum: bytes overwritten inside a frame whose
header still fits decode to wrong values that only the NaN/inf checks may notice.

Bounds (:mod:`dssp_data.bounded`). A chunk is decoded by the array's codecs with every decompressing stage
bounded by the chunk's shape x dtype (a decompression bomb is a corrupt chunk, named as above; a codec whose
output cannot be bounded is refused by name), a stored chunk file larger than any encoding of a chunk is
not fetched, and every read (one chunk, one slice, a whole :meth:`~dssp_data.replay_buffer.ReplayBuffer.load`) whose declared size
is over the read budget (``DSSP_READ_BUDGET``, 4 GiB by default) is refused before anything is allocated.
Before a dataset is opened its folder is walked without following links (:func:`check_dataset_tree`): a
symbolic link, FIFO or device inside it is refused (zarr would read or append through it, outside the
dataset); a writer also refuses a dataset folder that is itself a link.

Empty chunks. zarr 3 does not store a chunk that holds only the fill value (``write_empty_chunks``
off, its default, also when it writes format 2), so a chunk file may be missing from a valid dataset.
Where a missing chunk is lost data, and where it is the fill value:

Appending to a dataset whose arrays hold every chunk marks them. A ``meta/episode_ends`` chunk left out
because it held only the fill value 0 (``episode_ends = [0]``) reads, in an unmarked zarr 3 array, as
empty episodes, which the episode-end checks refuse as such; in a format 2 array the error says that the
chunk is lost or held only the fill value, and then those episodes are empty.

Shape and chunks. An array whose metadata (``.zarray`` / ``zarr.json``) gives more steps than
``meta/episode_ends`` covers, with no chunk stored behind the extra steps (in an array where a missing
chunk is lost data), is reported as a shape that does not match the stored data, not as the steps of an
interrupted append: :attr:`~dssp_data.replay_buffer.ReplayBufferReader.unbacked_steps` names them, and the writer's
``repair_incomplete_tail`` (``dssp-data repair``) sets the shape back to the last episode end (nothing
stored is lost).
"""

from __future__ import annotations

import itertools
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path

import numcodecs
import numpy as np
import zarr
import zarr.codecs
from zarr.abc.store import RangeByteRequest
from zarr.core.buffer import default_buffer_prototype
from zarr.core.sync import sync

from dssp_core.errors import DatasetError
from dssp_data.bounded import (
    ChunkTooLarge,
    UnboundedCodec,
    bounded_pipeline,
    check_budget,
    human_size,
    nbytes_of,
)
from dssp_data.bounded import (
    blosc_problem as _blosc_problem,
)
from dssp_data.dataset_layout import (
    DATA_KEYS,
    ENDS_KEY,
    REQUIRED_KEYS,
    ZARR_FORMATS,
    check_data_structure,
    check_ends_structure,
    check_episode_ends,
)

__all__ = ["check_dataset_tree", "EVERY_CHUNK_ATTR", "StoredArray"]


# --------------------------------------------------------------------------- zarr access


def _describe(exc: Exception) -> str:
    """``Type: message`` of an exception, on one line."""
    return " ".join(f"{type(exc).__name__}: {exc}".split())


def is_zarr_store(path: Path) -> bool:
    return path.is_dir() and ((path / ".zgroup").is_file() or (path / "zarr.json").is_file())


def check_dataset_tree(path: str | os.PathLike, *, appending: bool = False) -> None:
    """Every entry inside the dataset folder ``path`` must be a real folder or a regular file, checked without
    following links: zarr follows a symbolic link (``data/state`` leading to another folder, a chunk leading to
    another file or to ``/dev/zero``) and would read, or append, through it outside the dataset. A link, a FIFO
    or a device file raises DatasetError naming it. ``appending``: ``path`` itself may not be a link either (a
    writer writes only into a dataset's own folders)."""
    path = Path(path)
    if appending and path.is_symlink():
        raise DatasetError(
            f"{path} is a symbolic link: appending writes only into a dataset's own folder; give the "
            f"dataset's real path ({os.path.realpath(path)}) (nothing was written)"
        )
    folders = [path]
    while folders:
        folder = folders.pop()
        try:
            entries = list(os.scandir(folder))
        except OSError as exc:
            raise DatasetError(
                f"cannot list {folder} ({exc.strerror or exc}): check the dataset's permissions"
            ) from None
        for entry in entries:
            relative = os.path.relpath(entry.path, path)
            if entry.is_symlink():
                raise DatasetError(
                    f"{path}: {relative} is a symbolic link: a dataset's files and folders must be its own (zarr "
                    f"would {'write' if appending else 'read'} through the link, outside the dataset); replace it with "
                    f"the real {'folder' if os.path.isdir(entry.path) else 'file'} (nothing was {'written' if appending else 'read'})"
                )
            if entry.is_dir(follow_symlinks=False):
                folders.append(Path(entry.path))
            elif not entry.is_file(follow_symlinks=False):
                raise DatasetError(
                    f"{path}: {relative} is not a regular file (a FIFO, socket or device): remove it from the dataset"
                )


def _open_group(path: Path, mode: str) -> zarr.Group:
    if not path.exists():
        raise DatasetError(f"dataset {path} does not exist: check the path")
    if not path.is_dir():
        raise DatasetError(f"{path} is a file, not a zarr dataset directory: point to the dataset's .zarr directory")
    check_dataset_tree(path, appending=mode != "r")
    try:
        # Consolidated metadata (.zmetadata) is ignored: appends do not update it.
        return zarr.open_group(str(path), mode=mode, use_consolidated=False)
    except Exception as exc:  # zarr raises several unrelated types here
        raise DatasetError(
            f"{path} is not a zarr group (no readable .zgroup or zarr.json: {type(exc).__name__}): "
            f"point to the root directory of a DP3 zarr dataset"
        ) from exc


def get_array(group: zarr.Group, key: str, where: str) -> zarr.Array:
    try:
        node = group[key]
    except KeyError:
        hint = "was it written completely?"
        if key.startswith("data/") and DATA_KEYS[0] in group:
            hint = "this looks like the data/ group itself: point to the dataset root"
        raise DatasetError(
            f"{where}: missing key {key} (a DP3 dataset needs {', '.join(REQUIRED_KEYS)}); {hint}"
        ) from None
    except Exception as exc:
        raise DatasetError(
            f"{where}: cannot open {key} ({_describe(exc)}); the store may be corrupt: rewrite it"
        ) from exc
    if not isinstance(node, zarr.Array):
        raise DatasetError(f"{where}: {key} is a group, expected an array: rewrite the dataset")
    return node


# --------------------------------------------------------------------------- chunks

EVERY_CHUNK_ATTR = "every_chunk_written"
"""Array attribute set by this package's writer: every chunk the array covers is stored, also those that
hold only the fill value, so a missing chunk file is lost data (see the module docstring)."""
WRITE_CONFIG = {"write_empty_chunks": True}
"""zarr array config for writing: store every chunk."""
_BLOSC_NAMES = ("blosc", "numcodecs.blosc")
_PROBE_BYTES = 1 << 16
"""Bytes fetched to check a Blosc frame's header and block offsets without reading the whole chunk."""


async def _collect(iterator) -> list:
    return [item async for item in iterator]


def _episode_span(ends: np.ndarray | None, start: int, end: int) -> tuple[int, int] | None:
    """(first, last) episode that holds any of the steps [start, end), or None."""
    if ends is None or end <= start or start >= int(ends[-1]):
        return None
    first = int(np.searchsorted(ends, start, side="right"))
    last = min(int(np.searchsorted(ends, end - 1, side="right")), len(ends) - 1)
    return first, last


class StoredArray:
    """One array of a dataset on disk, read through the checked path (see the module docstring).

    The chunk grid is the array's (a shard per store key for sharded zarr 3 arrays); chunks are
    indexed along time (axis 0); a read of steps [start, end) needs every chunk of the time chunks it
    touches. ``strict``: a missing chunk is lost data (zarr format 2, arrays this package marked);
    otherwise (unmarked zarr 3 arrays) it reads as the fill value.
    """

    def __init__(self, array: zarr.Array, key: str, where: str):
        self.array, self.key, self.where = array, key, where
        metadata = array.metadata
        grid = getattr(metadata, "chunk_grid", None)
        chunk_shape = getattr(grid, "chunk_shape", None)
        if chunk_shape is None or len(chunk_shape) != len(array.shape) or min(chunk_shape, default=1) < 1:
            raise DatasetError(
                f"{where}: {key} uses a chunk grid this reader does not know ({type(grid).__name__}): "
                f"rewrite it with regular chunks"
            )
        self.chunk_shape = tuple(int(n) for n in chunk_shape)
        self.grid = tuple(-(-int(n) // c) for n, c in zip(array.shape, self.chunk_shape))
        self.dtype = np.dtype(array.dtype)
        self.marked = array.attrs.get(EVERY_CHUNK_ATTR) is True
        self.zarr_format = int(array.metadata.zarr_format)
        self.strict = self.zarr_format == 2 or self.marked
        self.chunk_nbytes = nbytes_of(self.chunk_shape, self.dtype)
        self.blosc, self.expected_nbytes = self._frame_format()
        self._stored: frozenset[str] | None = None
        self._pipeline = None

    def _frame_format(self) -> tuple[bool, int | None]:
        """(chunks are stored as Blosc frames, decoded bytes of one chunk if known)."""
        metadata = self.array.metadata
        whole = self.chunk_nbytes
        if metadata.zarr_format == 2:
            compressor = getattr(metadata, "compressor", None)
            is_blosc = getattr(compressor, "codec_id", None) == "blosc"
            return is_blosc, (whole if is_blosc and not metadata.filters else None)
        names = [c.get("name") if isinstance(c, dict) else None for c in metadata.to_dict().get("codecs", [])]
        if not names or names[-1] not in _BLOSC_NAMES:
            return False, None
        plain = len(names) >= 2 and names[-2] == "bytes" and all(n == "transpose" for n in names[:-2])
        return True, (whole if plain else None)

    # ---- where a chunk is, and what its loss means
    def store_key(self, coords: tuple[int, ...]) -> str:
        """The chunk's key in the store, e.g. ``data/action/3.0`` (zarr 2) or ``data/action/c/3/0`` (zarr 3)."""
        return f"{self.array.path}/{self.array.metadata.encode_chunk_key(coords)}"

    def coords(self, c: int):
        """Grid coordinates of every chunk of time chunk ``c``."""
        return itertools.product([c], *(range(n) for n in self.grid[1:]))

    def stored(self) -> frozenset[str]:
        """The keys the store lists under this array (listed once)."""
        if self._stored is None:
            try:
                self._stored = frozenset(sync(_collect(self.array.store.list_prefix(self.array.path))))
            except Exception as exc:
                raise DatasetError(
                    f"{self.where}: cannot list the chunks of {self.key} ({_describe(exc)}); "
                    f"the store may be corrupt: check the disk and restore the dataset from a copy"
                ) from exc
        return self._stored

    def _steps(self, c: int) -> tuple[int, int]:
        size = self.chunk_shape[0]
        return c * size, min((c + 1) * size, int(self.array.shape[0]))

    @property
    def metadata_file(self) -> str:
        """Where the array's metadata is stored: ``data/state/.zarray`` or ``data/state/zarr.json``."""
        return f"{self.key}/{'.zarray' if self.zarr_format == 2 else 'zarr.json'}"

    def unbacked_from(self, last_end: int) -> int | None:
        """The first step after ``last_end`` from which no chunk is stored up to the array's length, or None
        (every step is backed by a stored chunk, the array holds no step after ``last_end``, or a missing
        chunk here reads as the fill value)."""
        length = int(self.array.shape[0])
        if not self.strict or length <= last_end:
            return None
        sentinels = [str(918273645000 + axis) for axis in range(len(self.chunk_shape))]
        pattern = re.escape(self.store_key(tuple(int(v) for v in sentinels)))
        for value in sentinels:
            pattern = pattern.replace(value, r"(\d+)", 1)
        indices = [int(m.group(1)) for m in map(re.compile(f"^{pattern}$").match, self.stored()) if m]
        size = self.chunk_shape[0]
        top = max((c for c in indices if c >= last_end // size), default=None)
        backed = last_end if top is None else max(last_end, min(length, (top + 1) * size))
        return backed if backed < length else None

    def _lost(self, c: int, what: str, ends: np.ndarray | None) -> DatasetError:
        a, b = self._steps(c)
        if self.key == ENDS_KEY:
            fill = self.array.fill_value
            also = (
                f" — or a writer left it out because it held only the fill value {fill}, and then episodes "
                f"{a}..{b - 1} are empty;"
                if what.startswith("is missing")
                else ":"
            )
            return DatasetError(
                f"{self.where}: {self.key} chunk {c} (episodes {a}..{b - 1}) {what}: the episode "
                f"boundaries are lost{also} restore the dataset from a copy or rewrite {self.key} "
                f"(dssp-data repair cannot restore lost data)"
            )
        span = _episode_span(ends, a, b)
        if span is None:
            where = f"steps {a}..{b - 1}"
            remedy = "restore the dataset from a copy or rewrite it"
        else:
            i, j = span
            episodes = f"episode {i}" if i == j else f"episodes {i}..{j}"
            where = f"steps {a}..{b - 1}, {episodes}"
            remedy = (
                f"re-record or re-convert {episodes}, or leave {'it' if i == j else 'them'} out with "
                f"dssp-data split {self.where} --train OUT --val OUT --val-ratio R "
                f"--drop-episodes {i if i == j else f'{i}-{j}'}"
            )
        return DatasetError(
            f"{self.where}: {self.key} chunk {c} ({where}) {what}: {remedy} (dssp-data repair cannot restore lost data)"
        )

    def _time_chunks(self, start: int, end: int) -> range:
        if end <= start:
            return range(0)
        size = self.chunk_shape[0]
        return range(start // size, (end - 1) // size + 1)

    def missing(self, start: int, end: int) -> list[tuple[int, str]]:
        """(time chunk, store key) of each chunk that steps [start, end) need and the store does not list."""
        stored = self.stored()
        return [
            (c, key)
            for c in self._time_chunks(start, end)
            for key in map(self.store_key, self.coords(c))
            if key not in stored
        ]

    def check_present(self, start: int, end: int, ends: np.ndarray | None) -> int:
        """Raise DatasetError for the first chunk of steps [start, end) that is not stored, if ``strict``;
        return the number of chunks not stored (read as the fill value) otherwise."""
        missing = self.missing(start, end)
        if missing and self.strict:
            c, key = missing[0]
            raise self._lost(c, f"is missing (no {key} in the store)", ends)
        return len(missing)

    def probe(self, start: int, end: int, ends: np.ndarray | None, decode: bool = False) -> int:
        """:meth:`check_present`, then check each stored chunk of steps [start, end): its Blosc frame
        against its size without decoding it (a few kilobytes read per chunk), or, with ``decode``, by
        decoding it (one time chunk in memory at a time)."""
        n_missing = self.check_present(start, end, ends)
        if decode:
            size = self.chunk_shape[0]
            for c in self._time_chunks(start, end):
                self.read(max(start, c * size), min(end, (c + 1) * size), ends)
            return n_missing
        if not self.blosc:
            return n_missing
        stored = self.stored()
        for c in self._time_chunks(start, end):
            for key in map(self.store_key, self.coords(c)):
                if key not in stored:
                    continue
                try:
                    problem = self._stored_frame_problem(key)
                except Exception as exc:  # the store raises OSError and others
                    raise self._lost(c, f"cannot be read ({_describe(exc)}; {key})", ends) from exc
                if problem:
                    raise self._lost(c, f"is corrupt ({problem}; {key})", ends)
        return n_missing

    def _stored_frame_problem(self, key: str) -> str | None:
        """:func:`_blosc_problem` of the stored chunk ``key``, reading only its header and block table."""
        store, prototype = self.array.store, default_buffer_prototype()
        size = int(sync(store.getsize(key)))

        def read(a: int, b: int) -> np.ndarray:
            got = sync(store.get(key, prototype=prototype, byte_range=RangeByteRequest(a, b)))
            if got is None:
                raise FileNotFoundError(key)
            return got.as_numpy_array()

        head = read(0, min(size, _PROBE_BYTES))
        return _blosc_problem(lambda a, b: head[a:b] if b <= head.size else read(a, b), size, self.expected_nbytes)

    # ---- reading
    def _bounded_pipeline(self):
        """The array's codecs with every decompressing stage bounded by a chunk's size (built once)."""
        if self._pipeline is None:
            try:
                self._pipeline = bounded_pipeline(self.array, self.chunk_shape, self.dtype)
            except UnboundedCodec as exc:
                raise DatasetError(
                    f"{self.where}: {self.key} is stored with the codec {exc}, whose decoded size this reader cannot "
                    f"bound (it reads blosc, zstd, lz4, zlib, gzip, bz2 and lzma, checksums and numeric filters): "
                    f"rewrite the array with zarr's default compressor"
                ) from None
        return self._pipeline

    def _decode(self, c: int, coords: tuple[int, ...], ends: np.ndarray | None) -> np.ndarray:
        """The whole chunk at ``coords`` (its full chunk shape), checked and decoded within its size
        (:mod:`dssp_data.bounded`: no decoding stage may produce more than a chunk holds)."""
        check_budget(
            self.chunk_nbytes,
            f"{self.where}: one chunk of {self.key} (chunk shape {self.chunk_shape})",
            f"rewrite it with smaller chunks (its chunk shape is in {self.metadata_file})",
        )
        key = self.store_key(coords)
        prototype = default_buffer_prototype()
        pipeline = self._bounded_pipeline()
        try:
            try:
                size = int(sync(self.array.store.getsize(key)))
            except FileNotFoundError:
                size = None
            # compressed data is at most a little larger than what it decodes to (at most 8 bytes per element
            # in any stage): never fetch more than twice that
            if size is not None and size > 2 * max(
                self.chunk_nbytes, 8 * (self.chunk_nbytes // self.dtype.itemsize)
            ) + (1 << 16):
                raise self._lost(
                    c,
                    f"is corrupt ({human_size(size)} stored, more than a chunk of "
                    f"{human_size(self.chunk_nbytes)} takes; {key})",
                    ends,
                )
            buffer = None if size is None else sync(self.array.store.get(key, prototype=prototype))
        except DatasetError:
            raise
        except Exception as exc:  # the store raises OSError and others
            raise self._lost(c, f"cannot be read ({_describe(exc)}; {key})", ends) from exc
        if buffer is None:
            if self.strict:
                raise self._lost(c, f"is missing (no {key} in the store)", ends)
            fill = self.array.fill_value
            return np.full(self.chunk_shape, 0 if fill is None else fill, dtype=self.dtype)
        raw = buffer.as_numpy_array()
        problem = _blosc_problem(lambda a, b: raw[a:b], raw.size, self.expected_nbytes) if self.blosc else None
        if problem:
            raise self._lost(c, f"is corrupt ({problem}; {key})", ends)
        try:  # the whole chunk, by the array's own codecs, each decompressing stage bounded
            spec = self.array.metadata.get_chunk_spec(coords, self.array.async_array.config, prototype)
            (decoded,) = sync(pipeline.decode([(buffer, spec)]))
        except ChunkTooLarge as exc:
            raise self._lost(c, f"is corrupt ({exc}; {key})", ends) from None
        except Exception as exc:  # each codec raises its own types
            raise self._lost(c, f"is corrupt (it does not decode: {_describe(exc)}; {key})", ends) from exc
        values = None if decoded is None else decoded.as_numpy_array()
        if values is None or values.shape != self.chunk_shape:
            got = "nothing" if values is None else f"shape {values.shape}"
            raise self._lost(c, f"is corrupt (it decodes to {got}, expected {self.chunk_shape}; {key})", ends)
        return values

    def read(self, start: int, end: int, ends: np.ndarray | None = None) -> np.ndarray:
        """Steps [start, end) (0 <= start, end <= length) in the stored dtype, chunk by whole chunk.

        A read larger than the read budget (:func:`~dssp_data.bounded.read_budget`) is refused before
        anything is allocated."""
        shape = tuple(int(n) for n in self.array.shape)
        start, end = max(0, start), min(end, shape[0])
        rows = (max(0, end - start),) + shape[1:]
        check_budget(
            nbytes_of(rows, self.dtype),
            f"{self.where}: reading {self.key} steps {start}..{end - 1}",
            f"read fewer steps at a time (its shape is in {self.metadata_file})",
        )
        out = np.empty(rows, dtype=self.dtype)
        self.check_present(start, end, ends)
        size = self.chunk_shape[0]
        for c in self._time_chunks(start, end):
            lo, hi = max(start, c * size), min(end, (c + 1) * size)
            for coords in self.coords(c):
                chunk = self._decode(c, coords, ends)
                src, dst = [slice(lo - c * size, hi - c * size)], [slice(lo - start, hi - start)]
                for axis in range(1, len(shape)):
                    a = coords[axis] * self.chunk_shape[axis]
                    b = min(a + self.chunk_shape[axis], shape[axis])
                    src.append(slice(0, b - a))
                    dst.append(slice(a, b))
                out[tuple(dst)] = chunk[tuple(src)]
        return out


def read_checked(
    array: zarr.Array, key: str, where: str, end: int | None = None, ends: np.ndarray | None = None
) -> np.ndarray:
    """Steps [0, end) of ``array`` (all of it if ``end`` is None) through the checked path."""
    return StoredArray(array, key, where).read(0, int(array.shape[0]) if end is None else end, ends)


def find_unbacked(arrays: Mapping[str, zarr.Array], last_end: int, where: str) -> dict[str, tuple[int, int, str]]:
    """{key: (first step without a stored chunk, length, metadata file)} of the data arrays whose metadata
    gives steps after ``last_end`` that no stored chunk holds (see the module docstring)."""
    found = {}
    for key, array in arrays.items():
        if key == ENDS_KEY or int(array.shape[0]) <= last_end:
            continue
        stored = StoredArray(array, key, where)
        start = stored.unbacked_from(last_end)
        if start is not None:
            found[key] = (start, int(array.shape[0]), stored.metadata_file)
    return found


def open_required(path: Path, mode: str) -> tuple[zarr.Group, dict[str, zarr.Array], np.ndarray]:
    """Open a dataset, check its structure and episode ends; return (group, arrays, ends (E,) int64)."""
    group = _open_group(path, mode)
    where = str(path)
    arrays = {key: get_array(group, key, where) for key in REQUIRED_KEYS}
    check_data_structure(*(arrays[f"data/{k}"] for k in DATA_KEYS), where)
    check_ends_structure(arrays[ENDS_KEY], where)
    ends = read_checked(arrays[ENDS_KEY], ENDS_KEY, where).astype(np.int64)
    check_episode_ends(ends, where)
    return group, arrays, ends


def open_extra_arrays(group: zarr.Group, where: str, which: bool | Sequence[str] = True) -> dict[str, zarr.Array]:
    """The per-step arrays under ``data/`` other than point_cloud, state and action (``which``: all if
    True, none if False, else these names, each of which must exist)."""
    if which is False:
        return {}
    try:
        names = sorted(set(group["data"].array_keys()) - set(DATA_KEYS))
    except Exception as exc:
        raise DatasetError(
            f"{where}: cannot list data/ ({_describe(exc)}); the store may be corrupt: rewrite it"
        ) from exc
    if which is not True:
        wanted = list(which)
        missing = [name for name in wanted if name not in names]
        if missing:
            raise DatasetError(f"{where}: missing key data/{missing[0]} (extras here: {', '.join(names) or 'none'})")
        names = wanted
    arrays = {name: get_array(group, f"data/{name}", where) for name in names}
    for name, array in arrays.items():
        if len(array.shape) == 0:
            raise DatasetError(f"{where}: data/{name} is a scalar, not a per-step array: rewrite the dataset")
    return arrays


def check_zarr_format(zarr_format: int) -> None:
    if zarr_format not in ZARR_FORMATS:
        raise DatasetError(f"zarr_format = {zarr_format!r} is not supported: use 2 or 3")


def compressor_kwargs(zarr_format: int) -> dict:
    if zarr_format == 2:
        return {"compressors": numcodecs.Blosc(cname="zstd", clevel=3, shuffle=numcodecs.Blosc.SHUFFLE)}
    return {"compressors": zarr.codecs.BloscCodec(cname="zstd", clevel=3, shuffle="shuffle")}
