"""Read and write DP3 "ReplayBuffer" zarr datasets.

On-disk layout (as DP3 and RoboTwin write it), with T the total number of steps
over all episodes and E the number of episodes::

    <root>/                     zarr group; its attributes are free-form JSON
        data/point_cloud        (T, P, C) float, C = 3 (xyz) or 6 (xyz + rgb)
        data/state              (T, S) float
        data/action             (T, A) float
        data/<other>            (T, ...) per-step extras, e.g. img, depth, timestamps
        meta/episode_ends       (E,) int64, cumulative exclusive end of each episode

Episode ``i`` covers steps ``episode_ends[i-1]:episode_ends[i]`` (from 0 for
``i = 0``). Both zarr format 2 (what zarr-python 2.x writes: ``.zgroup`` and
``.zarray`` files) and zarr format 3 (``zarr.json``) stores are read. Writing
uses format 2 by default, Blosc zstd level 3 with byte shuffle and chunks of 100
steps along time, like DP3.

Per-step arrays other than point_cloud, state and action ("extras": timestamps,
raw depth images, ...) keep their own dtype. Reading ignores them unless asked
(``ReplayBuffer.load(..., extras=True)``, :class:`ReplayBufferReader`); writing
and appending carry them (:attr:`Episode.extras`), and an append must bring
exactly the extras the dataset holds, so every array keeps one entry per step.

Every problem with a dataset on disk raises :class:`~dssp_core.errors.DatasetError`
with a one-line message that names the key, the problem and what to do.

Appending (:class:`ReplayBufferWriter`) writes the data arrays first and
``meta/episode_ends`` last, and zarr's local store replaces each file
atomically, so a crash in the middle of an append leaves every earlier episode
intact, followed by steps that belong to no episode. :meth:`ReplayBuffer.load`
reports such a tail as an error unless ``allow_incomplete_tail=True``, which
drops exactly those steps and records how many in
:attr:`ReplayBuffer.dropped_tail_steps`. Attributes given with an episode
(``add_episode(episode, attrs=...)``) are written before its data, so after a
crash they may describe one episode more than ``meta/episode_ends`` holds:
readers index such per-episode attributes by episode count.

Chunks. Every read goes through one checked path (:class:`_StoredArray`): before reading a key, the
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
not fetched, and every read (one chunk, one slice, a whole :meth:`ReplayBuffer.load`) whose declared size
is over the read budget (``DSSP_READ_BUDGET``, 4 GiB by default) is refused before anything is allocated.
Before a dataset is opened its folder is walked without following links (:func:`check_dataset_tree`): a
symbolic link, FIFO or device inside it is refused (zarr would read or append through it, outside the
dataset); a writer also refuses a dataset folder that is itself a link.

Empty chunks. zarr 3 does not store a chunk that holds only the fill value (``write_empty_chunks``
off, its default, also when it writes format 2), so a chunk file may be missing from a valid dataset.
Where a missing chunk is lost data, and where it is the fill value:

- zarr format 2 arrays: lost data, an error. zarr-python 2 (DP3, RoboTwin) stores every chunk by default,
  so a missing file there was deleted or never finished (zarr-python 3 with its defaults also leaves chunks
  out of format 2 arrays: such a dataset is refused naming the chunk; rewrite it with
  ``write_empty_chunks=True`` or as format 3);
- arrays this package marked with the attribute ``every_chunk_written`` (its writer stores every chunk,
  ``write_empty_chunks=True``, also when appending, and marks each array it creates): lost data, an error;
- any other zarr 3 array (written by other tools): the fill value, as zarr defines it;
  :meth:`ReplayBufferReader.check_chunks` counts such implicit chunks and ``dssp-data info`` says how many.

Appending to a dataset whose arrays hold every chunk marks them. A ``meta/episode_ends`` chunk left out
because it held only the fill value 0 (``episode_ends = [0]``) reads, in an unmarked zarr 3 array, as
empty episodes, which the episode-end checks refuse as such; in a format 2 array the error says that the
chunk is lost or held only the fill value, and then those episodes are empty.

Shape and chunks. An array whose metadata (``.zarray`` / ``zarr.json``) gives more steps than
``meta/episode_ends`` covers, with no chunk stored behind the extra steps (in an array where a missing
chunk is lost data), is reported as a shape that does not match the stored data, not as the steps of an
interrupted append: :attr:`ReplayBufferReader.unbacked_steps` names them, and the writer's
``repair_incomplete_tail`` (``dssp-data repair``) sets the shape back to the last episode end (nothing
stored is lost).

Attributes are read through :mod:`dssp_data.attributes`: a value of the wrong type (a
``control_rate_hz`` of ``"10"``, ``true`` or ``-10``) raises DatasetError naming the attribute.
"""

from __future__ import annotations

import itertools
import json
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numcodecs
import numpy as np
import zarr
import zarr.codecs
from zarr.abc.store import RangeByteRequest
from zarr.core.buffer import default_buffer_prototype
from zarr.core.sync import sync

from dssp_data import attributes
from dssp_data.bounded import (
    ChunkTooLarge,
    UnboundedCodec,
    blosc_problem as _blosc_problem,
    bounded_pipeline,
    check_budget,
    human_size,
    nbytes_of,
)
from dssp_core.errors import DatasetError
from dssp_core.staging import Staging, WriterLock, is_staging_name

__all__ = ["Episode", "ReplayBuffer", "ReplayBufferReader", "ReplayBufferWriter", "write_replay_buffer", "dataset_lock",
           "check_dataset_tree"]

DATA_KEYS = ("point_cloud", "state", "action")
"""Per-step arrays under ``data/`` that this package reads and writes."""
ENDS_KEY = "meta/episode_ends"
REQUIRED_KEYS = tuple(f"data/{k}" for k in DATA_KEYS) + (ENDS_KEY,)
POINT_DIMS = (3, 6)
"""Allowed point widths C: xyz, or xyz + rgb."""
CHUNK_STEPS = 100
"""Chunk length along time, as DP3 writes."""
ENDS_CHUNK = 1000
EXTRA_CHUNK_BYTES = 16 << 20
"""Upper bound on the size of one chunk of an extra array (e.g. depth images): fewer steps per chunk."""
ZARR_FORMATS = (2, 3)


@dataclass
class Episode:
    """One demonstration.

    Attributes:
        point_cloud: (T, P, C) float32, C = 3 (xyz) or 6 (xyz + rgb).
        state: (T, S) float32, the robot's proprioceptive state.
        action: (T, A) float32, the commanded action at each step.
        extras: other per-step arrays by name, each (T, ...) of any numeric
            or bool dtype (kept as is; NaN allowed), stored as ``data/<name>``.
    """

    point_cloud: np.ndarray
    state: np.ndarray
    action: np.ndarray
    extras: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def n_steps(self) -> int:
        """T, the number of steps."""
        return int(np.shape(self.state)[0])


# --------------------------------------------------------------------------- checks


def _check_data_structure(point_cloud, state, action, where: str, prefix: str = "data/") -> None:
    """Check ranks, widths and dtypes of the three per-step arrays (zarr or numpy)."""
    pc_shape = tuple(np.shape(point_cloud))
    if len(pc_shape) != 3 or pc_shape[2] not in POINT_DIMS or pc_shape[1] == 0:
        raise DatasetError(
            f"{where}: {prefix}point_cloud has shape {pc_shape}; expected (T, P, C) with P >= 1 "
            f"and C = 3 (xyz) or 6 (xyz+rgb): rewrite the point clouds in that layout"
        )
    for name, array, letter in (("state", state, "S"), ("action", action, "A")):
        shape = tuple(np.shape(array))
        if len(shape) != 2 or shape[1] == 0:
            raise DatasetError(
                f"{where}: {prefix}{name} has shape {shape}; expected 2-D (T, {letter}) with {letter} >= 1: "
                f"store one flat vector per step"
            )
    for name, array in zip(DATA_KEYS, (point_cloud, state, action)):
        dtype = np.dtype(array.dtype)
        if not (np.issubdtype(dtype, np.floating) or np.issubdtype(dtype, np.integer)):
            raise DatasetError(
                f"{where}: {prefix}{name} has dtype {dtype}; expected a float array: rewrite it as float32"
            )


def _check_ends_structure(ends, where: str) -> None:
    """Check that episode_ends (zarr or numpy) is a non-empty 1-D integer array."""
    if len(ends.shape) != 1:
        raise DatasetError(
            f"{where}: {ENDS_KEY} has shape {tuple(ends.shape)}; expected 1-D (E,): "
            f"store one cumulative end index per episode"
        )
    if not np.issubdtype(np.dtype(ends.dtype), np.integer):
        raise DatasetError(
            f"{where}: {ENDS_KEY} has dtype {np.dtype(ends.dtype)}; expected an integer array (int64): rewrite it"
        )
    if ends.shape[0] == 0:
        raise DatasetError(f"{where}: {ENDS_KEY} is empty, so the dataset holds no episode: write at least one")


def _check_episode_ends(ends: np.ndarray, where: str) -> None:
    """Check that (E,) int64 ``ends`` is positive and strictly increasing."""
    if ends[0] <= 0:
        problem = "episode 0 is empty" if ends[0] == 0 else "a negative index is out of range"
        raise DatasetError(f"{where}: {ENDS_KEY}[0] = {ends[0]}: {problem}; remove it or fix the episode ends")
    bad = np.flatnonzero(np.diff(ends) <= 0)
    if bad.size:
        k = int(bad[0]) + 1
        raise DatasetError(
            f"{where}: {ENDS_KEY} is not strictly increasing ({ENDS_KEY}[{k - 1}] = {ends[k - 1]}, "
            f"[{k}] = {ends[k]}): episode {k} is empty; remove it or fix the episode ends"
        )


REPAIR_REMEDY = "cut them off with dssp-data repair PATH (or load with allow_incomplete_tail=True)"
SHAPE_REMEDY = "dssp-data repair PATH sets it back to the last episode end (nothing stored is lost)"


def _resolve_length(lengths: Mapping[str, int], last_end: int, allow_incomplete_tail: bool, where: str,
                    remedy: str = REPAIR_REMEDY, unbacked: Mapping[str, tuple[int, int, str]] | None = None,
                    shape_remedy: str = SHAPE_REMEDY) -> tuple[int, int]:
    """Return (number of steps to keep, number of trailing steps dropped).

    ``lengths`` maps each data key to its length along time. Steps after
    ``last_end`` are dropped only when ``allow_incomplete_tail`` is true;
    otherwise the error suggests ``remedy``. ``unbacked``: {key: (first step without a stored chunk,
    length, metadata file)} of arrays whose metadata gives steps that no chunk holds — reported as a
    shape that does not match the data (``shape_remedy``), not as an interrupted write.
    """
    listing = ", ".join(f"{k}: {n}" for k, n in lengths.items())
    shortest, longest = min(lengths.values()), max(lengths.values())
    if shortest >= last_end and longest > last_end:
        tail = longest - last_end
        if allow_incomplete_tail:
            return last_end, tail
        if unbacked:
            key, (start, length, meta) = next(iter(unbacked.items()))
            raise DatasetError(
                f"{where}: {key} has {length} steps in its metadata ({meta}) but no chunk is stored for steps "
                f"{start}..{length - 1}, and the episodes end at step {last_end} ({ENDS_KEY}[-1]): its shape does not "
                f"match the stored data (an edited {meta.rsplit('/', 1)[-1]}, or a write that stopped right after "
                f"growing the array): {shape_remedy}"
            )
        raise DatasetError(
            f"{where}: data has {tail} steps after the last episode end ({ENDS_KEY}[-1] = {last_end}; {listing}) "
            f"(an incomplete episode?): {remedy}, or rewrite the dataset"
        )
    if shortest != longest:
        raise DatasetError(
            f"{where}: data arrays differ in length along time ({listing}); every array under data/ "
            f"needs one entry per step: rewrite the dataset"
        )
    if last_end > longest:
        raise DatasetError(
            f"{where}: {ENDS_KEY}[-1] = {last_end} is out of range: the data arrays hold only {longest} steps "
            f"(data shorter than the episodes claim): fix {ENDS_KEY} or rewrite the dataset"
        )
    return last_end, 0


def _first_bad_steps(values: np.ndarray) -> np.ndarray:
    """Indices of the steps (first axis) of ``values`` that hold NaN or inf."""
    return np.flatnonzero(~np.isfinite(values.reshape(values.shape[0], -1)).all(axis=1))


def _check_finite(key: str, values: np.ndarray, ends: np.ndarray, where: str) -> None:
    """Raise if ``values`` (T, ...) holds NaN or inf; name the first bad step and its episode."""
    bad_steps = _first_bad_steps(values)
    if bad_steps.size:
        step = int(bad_steps[0])
        episode = int(np.searchsorted(ends, step, side="right"))
        raise DatasetError(
            f"{where}: {key} holds NaN or inf at {bad_steps.size} step(s), first at step {step} "
            f"(episode {episode}): fix or remove that episode and rewrite the dataset"
        )


def _check_extra_name(name: str, where: str) -> None:
    """An extra's name is one path component that is not a required key."""
    if not isinstance(name, str) or not name or "/" in name or name.startswith(".") or name in DATA_KEYS:
        raise DatasetError(
            f"{where}: {name!r} cannot name an extra per-step array: use a plain name other than "
            f"{', '.join(DATA_KEYS)}"
        )


def _check_extra_array(name: str, array: np.ndarray, n_steps: int, where: str) -> np.ndarray:
    """Check that an extra is (n_steps, ...) and numeric or bool; return it unchanged."""
    dtype = np.dtype(array.dtype)
    if array.ndim == 0 or array.shape[0] != n_steps:
        raise DatasetError(
            f"{where}: extra {name} has shape {tuple(array.shape)}; expected ({n_steps}, ...) with one entry per step"
        )
    if not (np.issubdtype(dtype, np.number) or dtype == np.bool_):
        raise DatasetError(f"{where}: extra {name} has dtype {dtype}; store numbers or booleans")
    return array


def _layout(extras: Mapping[str, np.ndarray]) -> dict[str, tuple[str, tuple[int, ...]]]:
    """{name: (dtype string, trailing shape)} of extra arrays (numpy or zarr)."""
    return {name: (np.dtype(a.dtype).str, tuple(a.shape[1:])) for name, a in sorted(extras.items())}


def _describe_layout(layout: Mapping[str, tuple[str, tuple[int, ...]]]) -> str:
    if not layout:
        return "none"
    return ", ".join(f"{name} {np.dtype(dt).name}{list(shape) if shape else ''}" for name, (dt, shape) in layout.items())


# --------------------------------------------------------------------------- zarr access


def _describe(exc: Exception) -> str:
    """``Type: message`` of an exception, on one line."""
    return " ".join(f"{type(exc).__name__}: {exc}".split())


def _is_zarr_store(path: Path) -> bool:
    return path.is_dir() and ((path / ".zgroup").is_file() or (path / "zarr.json").is_file())


def check_dataset_tree(path: str | os.PathLike, *, appending: bool = False) -> None:
    """Every entry inside the dataset folder ``path`` must be a real folder or a regular file, checked without
    following links: zarr follows a symbolic link (``data/state`` leading to another folder, a chunk leading to
    another file or to ``/dev/zero``) and would read, or append, through it outside the dataset. A link, a FIFO
    or a device file raises DatasetError naming it. ``appending``: ``path`` itself may not be a link either (a
    writer writes only into a dataset's own folders)."""
    path = Path(path)
    if appending and path.is_symlink():
        raise DatasetError(f"{path} is a symbolic link: appending writes only into a dataset's own folder; give the "
                           f"dataset's real path ({os.path.realpath(path)}) (nothing was written)")
    folders = [path]
    while folders:
        folder = folders.pop()
        try:
            entries = list(os.scandir(folder))
        except OSError as exc:
            raise DatasetError(f"cannot list {folder} ({exc.strerror or exc}): check the dataset's permissions") from None
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
                raise DatasetError(f"{path}: {relative} is not a regular file (a FIFO, socket or device): remove it "
                                   f"from the dataset")


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


def _get_array(group: zarr.Group, key: str, where: str) -> zarr.Array:
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


class _StoredArray:
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
            raise DatasetError(f"{where}: {key} uses a chunk grid this reader does not know ({type(grid).__name__}): "
                               f"rewrite it with regular chunks")
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
                raise DatasetError(f"{self.where}: cannot list the chunks of {self.key} ({_describe(exc)}); "
                                   f"the store may be corrupt: check the disk and restore the dataset from a copy") from exc
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
            also = (f" — or a writer left it out because it held only the fill value {fill}, and then episodes "
                    f"{a}..{b - 1} are empty;" if what.startswith("is missing") else ":")
            return DatasetError(f"{self.where}: {self.key} chunk {c} (episodes {a}..{b - 1}) {what}: the episode "
                                f"boundaries are lost{also} restore the dataset from a copy or rewrite {self.key} "
                                f"(dssp-data repair cannot restore lost data)")
        span = _episode_span(ends, a, b)
        if span is None:
            where = f"steps {a}..{b - 1}"
            remedy = "restore the dataset from a copy or rewrite it"
        else:
            i, j = span
            episodes = f"episode {i}" if i == j else f"episodes {i}..{j}"
            where = f"steps {a}..{b - 1}, {episodes}"
            remedy = (f"re-record or re-convert {episodes}, or leave {'it' if i == j else 'them'} out with "
                      f"dssp-data split {self.where} --train OUT --val OUT --val-ratio R "
                      f"--drop-episodes {i if i == j else f'{i}-{j}'}")
        return DatasetError(f"{self.where}: {self.key} chunk {c} ({where}) {what}: {remedy} "
                            f"(dssp-data repair cannot restore lost data)")

    def _time_chunks(self, start: int, end: int) -> range:
        if end <= start:
            return range(0)
        size = self.chunk_shape[0]
        return range(start // size, (end - 1) // size + 1)

    def missing(self, start: int, end: int) -> list[tuple[int, str]]:
        """(time chunk, store key) of each chunk that steps [start, end) need and the store does not list."""
        stored = self.stored()
        return [(c, key) for c in self._time_chunks(start, end) for key in map(self.store_key, self.coords(c))
                if key not in stored]

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
        check_budget(self.chunk_nbytes, f"{self.where}: one chunk of {self.key} (chunk shape {self.chunk_shape})",
                     f"rewrite it with smaller chunks (its chunk shape is in {self.metadata_file})")
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
            if size is not None and size > 2 * max(self.chunk_nbytes, 8 * (self.chunk_nbytes // self.dtype.itemsize)) + (1 << 16):
                raise self._lost(c, f"is corrupt ({human_size(size)} stored, more than a chunk of "
                                    f"{human_size(self.chunk_nbytes)} takes; {key})", ends)
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
        check_budget(nbytes_of(rows, self.dtype), f"{self.where}: reading {self.key} steps {start}..{end - 1}",
                     f"read fewer steps at a time (its shape is in {self.metadata_file})")
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


def _read(array: zarr.Array, key: str, where: str, end: int | None = None,
          ends: np.ndarray | None = None) -> np.ndarray:
    """Steps [0, end) of ``array`` (all of it if ``end`` is None) through the checked path."""
    return _StoredArray(array, key, where).read(0, int(array.shape[0]) if end is None else end, ends)


def _unbacked(arrays: Mapping[str, zarr.Array], last_end: int, where: str) -> dict[str, tuple[int, int, str]]:
    """{key: (first step without a stored chunk, length, metadata file)} of the data arrays whose metadata
    gives steps after ``last_end`` that no stored chunk holds (see the module docstring)."""
    found = {}
    for key, array in arrays.items():
        if key == ENDS_KEY or int(array.shape[0]) <= last_end:
            continue
        stored = _StoredArray(array, key, where)
        start = stored.unbacked_from(last_end)
        if start is not None:
            found[key] = (start, int(array.shape[0]), stored.metadata_file)
    return found


def _open_required(path: Path, mode: str) -> tuple[zarr.Group, dict[str, zarr.Array], np.ndarray]:
    """Open a dataset, check its structure and episode ends; return (group, arrays, ends (E,) int64)."""
    group = _open_group(path, mode)
    where = str(path)
    arrays = {key: _get_array(group, key, where) for key in REQUIRED_KEYS}
    _check_data_structure(*(arrays[f"data/{k}"] for k in DATA_KEYS), where)
    _check_ends_structure(arrays[ENDS_KEY], where)
    ends = _read(arrays[ENDS_KEY], ENDS_KEY, where).astype(np.int64)
    _check_episode_ends(ends, where)
    return group, arrays, ends


def _extra_arrays(group: zarr.Group, where: str, which: bool | Sequence[str] = True) -> dict[str, zarr.Array]:
    """The per-step arrays under ``data/`` other than point_cloud, state and action (``which``: all if
    True, none if False, else these names, each of which must exist)."""
    if which is False:
        return {}
    try:
        names = sorted(set(group["data"].array_keys()) - set(DATA_KEYS))
    except Exception as exc:
        raise DatasetError(f"{where}: cannot list data/ ({_describe(exc)}); the store may be corrupt: rewrite it") from exc
    if which is not True:
        wanted = list(which)
        missing = [name for name in wanted if name not in names]
        if missing:
            raise DatasetError(f"{where}: missing key data/{missing[0]} (extras here: {', '.join(names) or 'none'})")
        names = wanted
    arrays = {name: _get_array(group, f"data/{name}", where) for name in names}
    for name, array in arrays.items():
        if len(array.shape) == 0:
            raise DatasetError(f"{where}: data/{name} is a scalar, not a per-step array: rewrite the dataset")
    return arrays


def _check_zarr_format(zarr_format: int) -> None:
    if zarr_format not in ZARR_FORMATS:
        raise DatasetError(f"zarr_format = {zarr_format!r} is not supported: use 2 or 3")


def _compressor_kwargs(zarr_format: int) -> dict:
    if zarr_format == 2:
        return {"compressors": numcodecs.Blosc(cname="zstd", clevel=3, shuffle=numcodecs.Blosc.SHUFFLE)}
    return {"compressors": zarr.codecs.BloscCodec(cname="zstd", clevel=3, shuffle="shuffle")}


# --------------------------------------------------------------------------- reading


class ReplayBuffer:
    """A whole DP3 dataset in memory.

    Attributes:
        point_cloud: (T, P, C) float32, all episodes concatenated along time.
        state: (T, S) float32.
        action: (T, A) float32.
        episode_ends: (E,) int64, cumulative exclusive end of each episode.
        attrs: the root group's attributes (JSON).
        dropped_tail_steps: steps after the last episode end that
            ``load(..., allow_incomplete_tail=True)`` dropped (0 otherwise).
        extras: extra per-step arrays by name, (T, ...) each, in their stored
            dtype (empty unless loaded with ``extras``).
        path: where it was loaded from (None for a buffer built in memory).
    """

    def __init__(self, point_cloud: np.ndarray, state: np.ndarray, action: np.ndarray,
                 episode_ends: np.ndarray, attrs: dict | None = None,
                 extras: Mapping[str, np.ndarray] | None = None):
        """Wrap in-memory arrays (shapes as in the class docstring) after validating them.

        Data arrays are converted to float32 and episode_ends to int64;
        ``extras`` (each (T, ...)) keep their dtype.

        Raises:
            DatasetError: the arrays do not form a valid dataset.
        """
        where = "replay buffer"
        point_cloud, state, action, ends = (np.asarray(a) for a in (point_cloud, state, action, episode_ends))
        _check_data_structure(point_cloud, state, action, where)
        _check_ends_structure(ends, where)
        ends = ends.astype(np.int64)
        _check_episode_ends(ends, where)
        lengths = {"data/point_cloud": len(point_cloud), "data/state": len(state), "data/action": len(action)}
        _resolve_length(lengths, int(ends[-1]), False, where)
        values = {}
        for key, array in zip(REQUIRED_KEYS, (point_cloud, state, action)):
            with np.errstate(over="ignore"):
                values[key] = array.astype(np.float32, copy=False)
            _check_finite(key, values[key], ends, where)
        checked_extras = {}
        for name, array in (extras or {}).items():
            _check_extra_name(name, where)
            checked_extras[name] = _check_extra_array(name, np.asarray(array), int(ends[-1]), where)
        self._set(values, ends, attrs, 0, checked_extras)

    def _set(self, values: Mapping[str, np.ndarray], ends: np.ndarray, attrs: dict | None,
             dropped_tail_steps: int, extras: Mapping[str, np.ndarray] | None = None) -> None:
        self.point_cloud = values["data/point_cloud"]
        self.state = values["data/state"]
        self.action = values["data/action"]
        self.episode_ends = ends
        self.attrs = dict(attrs or {})
        self.dropped_tail_steps = int(dropped_tail_steps)
        self.extras = dict(extras or {})
        self.path = None

    @classmethod
    def load(cls, path: str | os.PathLike, *, allow_incomplete_tail: bool = False,
             extras: bool | Sequence[str] = False) -> ReplayBuffer:
        """Read a dataset (zarr format 2 or 3) into memory and validate it.

        Data arrays are converted to float32. Arrays under ``data/`` other than
        point_cloud, state and action are read only when ``extras`` asks.

        Args:
            path: the dataset's root directory.
            allow_incomplete_tail: drop the steps after the last episode end (left
                by an interrupted append) instead of raising; their number is
                stored in :attr:`dropped_tail_steps`. Nothing else is dropped.
            extras: also read these extra per-step arrays (True: all of them)
                into :attr:`extras`, each (T, ...) in its stored dtype.

        Raises:
            DatasetError: the path is not a valid dataset; the message says why.
        """
        path = Path(path)
        where = str(path)
        group, arrays, ends = _open_required(path, "r")
        extra_arrays = _extra_arrays(group, where, extras)
        lengths = {key: arrays[key].shape[0] for key in REQUIRED_KEYS[:3]}
        lengths.update({f"data/{name}": array.shape[0] for name, array in extra_arrays.items()})
        data_arrays = {**arrays, **{f"data/{name}": a for name, a in extra_arrays.items()}}
        n_steps, dropped = _resolve_length(lengths, int(ends[-1]), allow_incomplete_tail, where,
                                           unbacked=_unbacked(data_arrays, int(ends[-1]), where))
        need = sum(n_steps * (nbytes_of(arrays[key].shape[1:], arrays[key].dtype)
                              + (0 if arrays[key].dtype == np.float32 else nbytes_of(arrays[key].shape[1:], np.float32)))
                   for key in REQUIRED_KEYS[:3])
        need += sum(n_steps * nbytes_of(array.shape[1:], array.dtype) for array in extra_arrays.values())
        check_budget(need, f"{where}: loading {n_steps} steps", "read it one episode at a time (ReplayBufferReader)")
        values = {}
        for key in REQUIRED_KEYS[:3]:
            raw = _read(arrays[key], key, where, n_steps, ends)
            with np.errstate(over="ignore"):
                values[key] = raw.astype(np.float32, copy=False)
            _check_finite(key, values[key], ends, where)
        extra_values = {name: _read(array, f"data/{name}", where, n_steps, ends)
                        for name, array in extra_arrays.items()}
        buffer = cls.__new__(cls)
        buffer._set(values, ends, group.attrs.asdict(), dropped, extra_values)
        buffer.path = path
        return buffer

    @property
    def n_episodes(self) -> int:
        """E, the number of episodes."""
        return int(self.episode_ends.shape[0])

    @property
    def n_steps(self) -> int:
        """T, the number of steps over all episodes."""
        return int(self.episode_ends[-1])

    @property
    def n_points(self) -> int:
        """P, points per cloud."""
        return int(self.point_cloud.shape[1])

    @property
    def point_dim(self) -> int:
        """C, values per point: 3 (xyz) or 6 (xyz + rgb)."""
        return int(self.point_cloud.shape[2])

    @property
    def state_dim(self) -> int:
        """S."""
        return int(self.state.shape[1])

    @property
    def action_dim(self) -> int:
        """A."""
        return int(self.action.shape[1])

    @property
    def control_rate_hz(self) -> float | None:
        """``attrs["control_rate_hz"]`` in Hz, or None when absent.

        Raises DatasetError naming the attribute when it is not a number > 0 (``"10"``, ``true``, NaN, -10)."""
        return attributes.control_rate(self.attrs, self.path if self.path is not None else "replay buffer")

    def episode_lengths(self) -> np.ndarray:
        """(E,) int64, the number of steps of each episode."""
        return np.diff(self.episode_ends, prepend=0)

    def episode_range(self, i: int) -> tuple[int, int]:
        """(start, end) step indices of episode ``i`` (negative ``i`` counts from the end)."""
        if not -self.n_episodes <= i < self.n_episodes:
            raise IndexError(f"episode {i} out of range for {self.n_episodes} episodes")
        i %= self.n_episodes
        start = int(self.episode_ends[i - 1]) if i > 0 else 0
        return start, int(self.episode_ends[i])

    def episode(self, i: int) -> Episode:
        """Episode ``i`` as float32 views into this buffer: (T_i, P, C), (T_i, S), (T_i, A), and views
        (T_i, ...) of the loaded extras."""
        start, end = self.episode_range(i)
        return Episode(self.point_cloud[start:end], self.state[start:end], self.action[start:end],
                       {name: array[start:end] for name, array in self.extras.items()})

    def __repr__(self) -> str:
        return (f"ReplayBuffer(n_episodes={self.n_episodes}, n_steps={self.n_steps}, "
                f"point_cloud=({self.n_points}, {self.point_dim}), state_dim={self.state_dim}, "
                f"action_dim={self.action_dim})")


class ReplayBufferReader:
    """A dataset on disk, read one episode (or one slice) at a time: nothing is loaded up front.

    The structure and episode ends are checked on opening, like
    :meth:`ReplayBuffer.load`; values are checked when read, each read through
    the checked path of the module docstring (the chunks it needs must be stored
    and decode). :meth:`check_chunks` checks every chunk without decoding.

    Attributes:
        path: the dataset's root directory.
        zarr_format: 2 or 3.
        attrs: the root group's attributes (JSON).
        episode_ends: (E,) int64.
        dropped_tail_steps: steps after the last episode end that are ignored
            (an interrupted append; only with ``allow_incomplete_tail=True``).
        arrays: {key: (shape, dtype)} of every array under ``data/`` and ``meta/``,
            with shapes as stored (including an ignored tail).
        extra_keys: names of the extra per-step arrays under ``data/``.
        unbacked_steps: {key: (first step, length, metadata file)} of arrays whose metadata gives steps
            after the last episode end that no stored chunk holds (a shape that does not match the data;
            only with ``allow_incomplete_tail=True``, else an error).
    """

    def __init__(self, path: str | os.PathLike, *, allow_incomplete_tail: bool = False):
        self.path = Path(path)
        where = str(self.path)
        group, arrays, ends = _open_required(self.path, "r")
        extras = _extra_arrays(group, where)
        lengths = {key: arrays[key].shape[0] for key in REQUIRED_KEYS[:3]}
        lengths.update({f"data/{name}": array.shape[0] for name, array in extras.items()})
        self._arrays = {**{k: v for k, v in arrays.items()}, **{f"data/{n}": a for n, a in extras.items()}}
        self.unbacked_steps = _unbacked(self._arrays, int(ends[-1]), where)
        n_steps, dropped = _resolve_length(lengths, int(ends[-1]), allow_incomplete_tail, where,
                                           unbacked=self.unbacked_steps)
        self._stored = {key: _StoredArray(array, key, where) for key, array in self._arrays.items()}
        self.zarr_format = group.metadata.zarr_format
        self.attrs = group.attrs.asdict()
        self.episode_ends = ends
        self.dropped_tail_steps = dropped
        self.extra_keys = tuple(sorted(extras))
        self.arrays = {key: (tuple(a.shape), np.dtype(a.dtype)) for key, a in sorted(self._arrays.items())}
        self._n_steps = n_steps

    @property
    def n_episodes(self) -> int:
        """E, the number of episodes."""
        return int(self.episode_ends.shape[0])

    @property
    def n_steps(self) -> int:
        """T, the number of steps that belong to episodes."""
        return self._n_steps

    @property
    def control_rate_hz(self) -> float | None:
        """``attrs["control_rate_hz"]`` in Hz, or None when absent; DatasetError when it is not a number > 0."""
        return attributes.control_rate(self.attrs, self.path)

    def episode_lengths(self) -> np.ndarray:
        """(E,) int64, the number of steps of each episode."""
        return np.diff(self.episode_ends, prepend=0)

    def episode_range(self, i: int) -> tuple[int, int]:
        """(start, end) step indices of episode ``i`` (0 <= i < E)."""
        if not 0 <= i < self.n_episodes:
            raise DatasetError(f"{self.path}: episode {i} is out of range: the dataset holds episodes 0..{self.n_episodes - 1}")
        return (int(self.episode_ends[i - 1]) if i > 0 else 0), int(self.episode_ends[i])

    def read(self, key: str, start: int = 0, end: int | None = None) -> np.ndarray:
        """Steps [start, end) of ``key`` (e.g. ``data/state``) in its stored dtype: (end - start, ...).

        ``end`` defaults to :attr:`n_steps`; negative indices count from the stored length.

        Raises:
            DatasetError: a chunk the steps need is missing or corrupt (the message names the key,
                the chunk, its steps and episodes), or there is no such key.
        """
        if key not in self._arrays:
            raise DatasetError(f"{self.path}: no array {key}")
        length = int(self._arrays[key].shape[0])
        start, end, _ = slice(start, self._n_steps if end is None else end).indices(length)
        return self._stored[key].read(start, max(start, end), self.episode_ends)

    def check_chunks(self, keys: Sequence[str] | None = None, decode: bool = False) -> dict[str, int]:
        """Check every chunk of ``keys`` (default: every array) over the episodes' steps.

        Each must be listed by the store and, for Blosc-compressed arrays, hold a whole Blosc frame
        (header and block offsets that fit the bytes stored; a few kilobytes read per chunk). With
        ``decode``, each chunk is also decoded (the whole dataset is read, one chunk at a time).

        Returns:
            {key: number of chunks not stored} for arrays whose chunks that hold only the fill value may
            be left out (extras without the ``every_chunk_written`` mark); they read as the fill value.

        Raises:
            DatasetError: the first missing or broken chunk (key, chunk, steps, episodes, what to do).
        """
        unstored = {}
        for key in (sorted(self._arrays) if keys is None else keys):
            if key not in self._stored:
                raise DatasetError(f"{self.path}: no array {key}")
            stored = self._stored[key]
            n = stored.probe(0, self.n_episodes if key == ENDS_KEY else self._n_steps, self.episode_ends, decode)
            if n:
                unstored[key] = n
        return unstored

    def episode(self, i: int, extras: bool | Sequence[str] = True, check_finite: bool = True) -> Episode:
        """Episode ``i``: point_cloud, state, action as float32 and the extras asked for (stored dtype).

        Raises DatasetError if ``check_finite`` and the data holds NaN or inf.
        """
        start, end = self.episode_range(i)
        values = []
        for key in DATA_KEYS:
            with np.errstate(over="ignore"):
                array = self.read(f"data/{key}", start, end).astype(np.float32, copy=False)
            if check_finite:
                bad = _first_bad_steps(array)
                if bad.size:
                    raise DatasetError(
                        f"{self.path}: data/{key} holds NaN or inf in episode {i} (step {start + int(bad[0])}): "
                        f"fix or remove that episode"
                    )
            values.append(array)
        names = self.extra_keys if extras is True else () if extras is False else tuple(extras)
        return Episode(*values, extras={name: self.read(f"data/{name}", start, end) for name in names})


# --------------------------------------------------------------------------- writing


def _validated_episode(episode: Episode, where: str,
                       dims: tuple[int, int, int, int] | None = None,
                       layout: Mapping[str, tuple[str, tuple[int, ...]]] | None = None) -> Episode:
    """Return ``episode`` as float32 arrays (extras as given) after checking shapes and values.

    ``dims`` = (P, C, S, A) and ``layout`` = the extras' {name: (dtype, trailing shape)}
    that the episode must match, if given.
    """
    pc, state, action = (np.asarray(getattr(episode, k)) for k in DATA_KEYS)
    _check_data_structure(pc, state, action, where, prefix="")
    lengths = {"point_cloud": pc.shape[0], "state": state.shape[0], "action": action.shape[0]}
    if len(set(lengths.values())) != 1:
        listing = ", ".join(f"{k}: {n}" for k, n in lengths.items())
        raise DatasetError(f"{where}: arrays differ in length along time ({listing}): give one entry per step")
    if state.shape[0] == 0:
        raise DatasetError(f"{where}: the episode is empty (0 steps): leave it out")
    got = (pc.shape[1], pc.shape[2], state.shape[1], action.shape[1])
    if dims is not None and got != dims:
        raise DatasetError(
            f"{where}: (P, C, S, A) = {got} does not match the dataset's {dims}: "
            f"resample the points or write a separate dataset"
        )
    values = []
    for key, array in zip(DATA_KEYS, (pc, state, action)):
        with np.errstate(over="ignore"):
            array = array.astype(np.float32, copy=False)
        bad_steps = _first_bad_steps(array)
        if bad_steps.size:
            raise DatasetError(f"{where}: {key} holds NaN or inf (first at step {bad_steps[0]}): fix the episode")
        values.append(array)
    extras = {}
    for name, array in dict(getattr(episode, "extras", None) or {}).items():
        _check_extra_name(name, where)
        extras[name] = _check_extra_array(name, np.asarray(array), state.shape[0], where)
    if layout is not None and _layout(extras) != dict(layout):
        raise DatasetError(
            f"{where}: extra per-step arrays ({_describe_layout(_layout(extras))}) do not match the dataset's "
            f"({_describe_layout(layout)}): write a separate dataset"
        )
    return Episode(*values, extras=extras)


def _episode_dims(episode: Episode) -> tuple[int, int, int, int]:
    """(P, C, S, A) of an episode."""
    return (episode.point_cloud.shape[1], episode.point_cloud.shape[2],
            episode.state.shape[1], episode.action.shape[1])


def _check_attrs(attrs: dict | None) -> dict:
    attrs = dict(attrs or {})
    try:
        json.dumps(attrs)
    except (TypeError, ValueError) as exc:
        raise DatasetError(f"dataset attributes are not JSON-serialisable ({exc}): use plain numbers, "
                           f"strings, lists and dicts") from exc
    return attrs


def _write_store(path: Path, episodes: Sequence[Episode], attrs: dict, zarr_format: int) -> None:
    """Write validated float32 episodes as a new store at ``path`` (a new or empty directory)."""
    root = zarr.open_group(str(path), mode="w-", zarr_format=zarr_format, attributes=attrs)
    data = root.create_group("data")
    meta = root.create_group("meta")
    # every chunk is stored, also one that holds only the fill value: a missing chunk is then lost data
    codec = {**_compressor_kwargs(zarr_format), "config": WRITE_CONFIG, "attributes": {EVERY_CHUNK_ATTR: True}}
    for key in DATA_KEYS:
        values = np.concatenate([getattr(ep, key) for ep in episodes], axis=0)
        array = data.create_array(key, shape=values.shape, dtype=np.float32,
                                  chunks=(CHUNK_STEPS,) + values.shape[1:], **codec)
        array[...] = values
    for name in sorted(episodes[0].extras):
        values = np.concatenate([ep.extras[name] for ep in episodes], axis=0)
        array = data.create_array(name, shape=values.shape, dtype=values.dtype,
                                  chunks=(_extra_chunk_steps(values),) + values.shape[1:], **codec)
        array[...] = values
    ends = np.cumsum([ep.n_steps for ep in episodes], dtype=np.int64)
    array = meta.create_array("episode_ends", shape=ends.shape, dtype=np.int64, chunks=(ENDS_CHUNK,), **codec)
    array[...] = ends


def _extra_chunk_steps(values: np.ndarray) -> int:
    """Steps per chunk of an extra (T, ...) array: CHUNK_STEPS, fewer for large rows (depth images)."""
    row_bytes = max(1, int(np.prod(values.shape[1:], dtype=np.int64)) * values.dtype.itemsize)
    return int(max(1, min(CHUNK_STEPS, EXTRA_CHUNK_BYTES // row_bytes)))


def _check_replaceable(path: Path) -> None:
    if path.is_symlink() or (path.exists() and not (path.is_dir() and (_is_zarr_store(path) or not any(path.iterdir())))):
        raise DatasetError(
            f"{path} exists and is not a zarr dataset or an empty directory: refusing to replace it; "
            f"choose another path or remove it"
        )


def write_replay_buffer(path: str | os.PathLike, episodes: Sequence[Episode], attrs: dict | None = None,
                        zarr_format: int = 2) -> None:
    """Write ``episodes`` as a complete dataset at ``path``.

    Each episode holds point_cloud (T_i, P, C), state (T_i, S) and action
    (T_i, A); P, C, S and A, and the extras' names, dtypes and trailing shapes,
    must agree over all episodes. The store is written into a temporary sibling
    directory (``.NAME.tmp-XXXXXXXX``, :class:`~dssp_core.staging.Staging`)
    and then renamed onto ``path``; an existing dataset at ``path`` is moved
    aside only once the new one is complete, and deleted after the new one is
    in place. On any failure or interruption (Ctrl-C) the temporary directory
    is removed once zarr's background writes have settled; one left by a killed
    process is removed by the next write to ``path``.

    Args:
        path: directory to create (parents are created too).
        episodes: at least one non-empty episode with finite values.
        attrs: JSON attributes for the root group (e.g. ``control_rate_hz``).
        zarr_format: 2 (default, what zarr-python 2.x and DP3 use) or 3.

    Raises:
        DatasetError: an episode is invalid, ``path`` holds something other
            than a zarr dataset or an empty directory, or cannot be written.
    """
    _check_zarr_format(zarr_format)
    attrs = _check_attrs(attrs)
    if len(episodes) == 0:
        raise DatasetError(f"{path}: no episodes to write: give at least one")
    checked = [_validated_episode(episodes[0], "episode 0")]
    dims, layout = _episode_dims(checked[0]), _layout(checked[0].extras)
    checked += [_validated_episode(ep, f"episode {i}", dims, layout) for i, ep in enumerate(episodes[1:], start=1)]

    path = Path(path)
    _check_replaceable(path)
    with Staging(flag="path", error=DatasetError) as staging:
        tmp = staging.make(staging.reserve(path))
        _write_store(tmp, checked, attrs, zarr_format)
        staging.commit([(tmp, path)])


def dataset_lock(path: str | os.PathLike, *, flag: str = "path", doing: str = "written") -> WriterLock:
    """One writer per dataset: the :class:`~dssp_core.staging.WriterLock` of the dataset at ``path``
    (``.NAME.lock`` beside it, links in the folders above resolved, so that two names for one dataset share
    one lock). Every writer that appends to a dataset or changes it in place holds it
    (:class:`ReplayBufferWriter`, ``dssp-sim collect``, a recording session, ``dssp-data repair``); a second
    one gets one DatasetError line naming the holder (``flag``: the option that names the dataset; ``doing``:
    what this writer does, as the line a second one gets says it)."""
    path = Path(path).absolute()
    return WriterLock(Path(os.path.realpath(path.parent)) / path.name, what="dataset", flag=flag, error=DatasetError,
                      doing=doing)


class ReplayBufferWriter:
    """Append episodes one at a time to a new or existing dataset.

    A new dataset appears on disk, written atomically, with its first episode.
    For an existing one, its structure and episode ends are checked, every chunk
    must be stored with a whole frame and the last chunk of each array (which an
    append rewrites) must decode (other values are not read); episodes are then
    appended: the data arrays (and extras) first, ``meta/episode_ends`` last, so
    an interrupted append leaves every earlier episode readable (see the module
    docstring). Every chunk is stored, also one that holds only the fill value.
    Use as a context manager::

        with ReplayBufferWriter("demo.zarr", attrs={"control_rate_hz": 10.0}) as writer:
            writer.add_episode(episode)

    Args:
        path: dataset directory.
        attrs: JSON attributes merged into the root group's attributes.
        zarr_format: format of a new dataset (2 or 3); an existing dataset
            keeps its own format.
        repair_incomplete_tail: if the existing dataset ends with steps that
            belong to no episode (an interrupted append), cut them off before
            appending instead of raising DatasetError.
        extra_keys: names of the extra per-step arrays every added episode
            brings (:attr:`Episode.extras`); an existing dataset must hold
            exactly these under ``data/`` besides point_cloud, state and action.
        staged: ``path`` is an empty staging directory of the caller's, which
            puts it in place when complete (:class:`~dssp_core.staging.Staging`):
            the first episode is written into it directly instead of beside it.
        lock: hold the dataset's writer lock (:func:`dataset_lock`) until :meth:`close`,
            so that a second writer of the same dataset is refused with one line;
            False when the caller holds it already (a staged writer needs none).

    An existing dataset is checked before anything is written: no symbolic link, FIFO
    or device anywhere in its folder (:func:`check_dataset_tree`), its structure and
    its chunks as above.
    """

    def __init__(self, path: str | os.PathLike, attrs: dict | None = None, zarr_format: int = 2,
                 *, repair_incomplete_tail: bool = False, extra_keys: Sequence[str] = (), staged: bool = False,
                 lock: bool = True):
        _check_zarr_format(zarr_format)
        self.path = Path(path)
        self.staged = staged
        self.zarr_format = zarr_format
        self._attrs = _check_attrs(attrs)
        for name in extra_keys:
            _check_extra_name(name, str(self.path))
        self.extra_keys = tuple(sorted(extra_keys))
        self._closed = False
        self._unmarked: list[str] = []
        self._group: zarr.Group | None = None
        self._arrays: dict[str, zarr.Array] | None = None
        self._dims: tuple[int, int, int, int] | None = None
        self._layout: dict[str, tuple[str, tuple[int, ...]]] | None = None
        self._n_steps = 0
        self._n_episodes = 0
        self.dropped_tail_steps = 0
        """Steps after the last episode end that ``repair_incomplete_tail=True`` cut off."""
        self.unbacked_steps: dict[str, tuple[int, int, str]] = {}
        """Arrays whose metadata gave steps after the last episode end that no stored chunk held
        (``{key: (first such step, length, metadata file)}``); ``repair_incomplete_tail=True`` set them back."""
        self._lock = dataset_lock(self.path) if lock and not staged else None
        try:
            if self.path.is_symlink() or _is_zarr_store(self.path) or (self.path.exists() and not self._is_empty_dir()):
                self._open_existing(repair_incomplete_tail)
        except BaseException:
            self.close()
            raise

    def _is_empty_dir(self) -> bool:
        return self.path.is_dir() and not any(self.path.iterdir())

    def _open_existing(self, repair_incomplete_tail: bool) -> None:
        where = str(self.path)
        group, arrays, ends = _open_required(self.path, "r+")
        extras = _extra_arrays(group, where)
        unexpected = sorted(set(extras) - set(self.extra_keys))
        if unexpected:
            raise DatasetError(
                f"{where}: data/{unexpected[0]} exists: appending would leave it shorter than the other arrays; "
                f"write a new dataset instead"
            )
        missing = sorted(set(self.extra_keys) - set(extras))
        if missing:
            raise DatasetError(
                f"{where}: data/{missing[0]} is missing: the dataset was written without it, so appended "
                f"episodes would not line up; write a new dataset instead"
            )
        arrays.update({f"data/{name}": extras[name] for name in self.extra_keys})
        data_keys = [key for key in arrays if key != ENDS_KEY]
        lengths = {key: arrays[key].shape[0] for key in data_keys}
        self.unbacked_steps = _unbacked(arrays, int(ends[-1]), where)
        n_steps, dropped = _resolve_length(lengths, int(ends[-1]), repair_incomplete_tail, where,
                                           remedy="open the writer with repair_incomplete_tail=True to cut them off",
                                           unbacked=self.unbacked_steps,
                                           shape_remedy="open the writer with repair_incomplete_tail=True to set it "
                                                        "back (nothing stored is lost)")
        # Every chunk of the episodes must be stored and hold a whole frame (lost data is not appended to),
        # and the last one, which the next append reads back and rewrites, must decode.
        arrays = {key: array.with_config(WRITE_CONFIG) for key, array in arrays.items()}
        self._unmarked = []
        for key, array in arrays.items():
            stored = _StoredArray(array, key, where)
            end = int(ends.shape[0]) if key == ENDS_KEY else n_steps
            if stored.probe(0, end, ends) == 0 and not stored.marked:
                self._unmarked.append(key)
            if key != ENDS_KEY:
                stored.read(end - 1, end, ends)
        self.dropped_tail_steps = dropped
        if dropped:
            for key in data_keys:
                if arrays[key].shape[0] != n_steps:
                    arrays[key].resize((n_steps,) + tuple(arrays[key].shape[1:]))
        if self._attrs:
            group.attrs.update(self._attrs)
        self.zarr_format = group.metadata.zarr_format
        self._group = group
        self._arrays = arrays
        self._dims = (arrays["data/point_cloud"].shape[1], arrays["data/point_cloud"].shape[2],
                      arrays["data/state"].shape[1], arrays["data/action"].shape[1])
        self._layout = _layout({name: extras[name] for name in self.extra_keys})
        self._n_steps = n_steps
        self._n_episodes = int(ends.shape[0])

    @property
    def n_episodes(self) -> int:
        """Episodes in the dataset so far."""
        return self._n_episodes

    @property
    def n_steps(self) -> int:
        """Steps in the dataset so far."""
        return self._n_steps

    @property
    def attrs(self) -> dict:
        """The dataset's root attributes as on disk (those given to the writer until the first episode)."""
        if self._group is None:
            return dict(self._attrs)
        return self._group.attrs.asdict()

    def add_episode(self, episode: Episode, attrs: dict | None = None) -> None:
        """Append one episode: point_cloud (T, P, C), state (T, S), action (T, A), and its extras.

        ``attrs`` are merged into the root group's attributes before the
        episode's data is written (with a new dataset: written with it), so
        they may describe the episode; after a crash during the append they
        may describe an episode the dataset does not hold.

        Raises:
            DatasetError: the episode is empty, holds NaN/inf, or does not match
                the dataset's (P, C, S, A) or extras; or the dataset changed underneath.
        """
        if self._closed:
            raise ValueError("ReplayBufferWriter is closed")
        where = f"{self.path}: episode {self._n_episodes}"
        brought = tuple(sorted(getattr(episode, "extras", None) or {}))
        if brought != self.extra_keys:
            raise DatasetError(
                f"{where}: the episode brings extras [{', '.join(brought)}] but the writer was opened for "
                f"[{', '.join(self.extra_keys)}]: pass the same extra_keys"
            )
        episode = _validated_episode(episode, where, self._dims, self._layout)
        attrs = _check_attrs(attrs)
        if self._arrays is None:
            if self.staged and self._is_empty_dir() and is_staging_name(self.path.name):
                _write_store(self.path, [episode], {**self._attrs, **attrs}, self.zarr_format)
            else:
                write_replay_buffer(self.path, [episode], {**self._attrs, **attrs}, self.zarr_format)
            self._group, arrays, _ = _open_required(self.path, "r+")
            arrays.update({f"data/{name}": _get_array(self._group, f"data/{name}", str(self.path))
                           for name in self.extra_keys})
            self._arrays = {key: array.with_config(WRITE_CONFIG) for key, array in arrays.items()}
            self._dims = _episode_dims(episode)
            self._layout = _layout(episode.extras)
        else:
            keys = [key for key in self._arrays if key != ENDS_KEY]
            lengths = [self._arrays[key].shape[0] for key in keys] + [self._arrays[ENDS_KEY].shape[0]]
            if lengths != [self._n_steps] * len(keys) + [self._n_episodes]:
                raise DatasetError(
                    f"{where}: the dataset no longer has the expected {self._n_steps} steps and "
                    f"{self._n_episodes} episodes (an earlier append failed?): reopen the writer with "
                    f"repair_incomplete_tail=True"
                )
            if attrs:
                self._group.attrs.update(attrs)
            for key in DATA_KEYS:
                self._arrays[f"data/{key}"].append(getattr(episode, key), axis=0)
            for name in self.extra_keys:
                self._arrays[f"data/{name}"].append(episode.extras[name], axis=0)
            self._arrays[ENDS_KEY].append(np.array([self._n_steps + episode.n_steps], dtype=np.int64))
            for key in self._unmarked:  # they held every chunk, and every chunk written from now on is stored
                self._arrays[key].attrs[EVERY_CHUNK_ATTR] = True
            self._unmarked = []
        self._n_steps += episode.n_steps
        self._n_episodes += 1

    def close(self) -> None:
        """Stop writing (and let go of the dataset's writer lock); every added episode is already on disk."""
        self._closed = True
        self._arrays = None
        self._group = None
        lock, self._lock = getattr(self, "_lock", None), None
        if lock is not None:
            lock.release()

    def __enter__(self) -> ReplayBufferWriter:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()
