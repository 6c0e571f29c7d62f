"""The LeRobot v3 layout both directions share: its paths, ``meta/info.json`` read and checked, the files of a
root opened without following links, and columns between numpy and arrow through their buffers (pyarrow only,
loaded when first needed).

The layout LeRobot 0.4 writes (``codebase_version`` ``"v3.0"``), under the dataset's root:

- ``meta/info.json``: ``codebase_version``, ``fps``, ``features`` (``{key: {dtype, shape, names, info?}}``), the
  ``data_path`` template of the data files, totals, ``chunks_size``, ``splits``;
- ``meta/tasks.parquet``: ``task_index`` with the task texts as the (pandas) index;
- ``meta/episodes/chunk-CCC/file-FFF.parquet``: one row per episode: ``episode_index``, ``tasks``, ``length``,
  ``data/chunk_index``, ``data/file_index``, ``dataset_from_index``, ``dataset_to_index``, the episode's
  ``stats/<feature>/<stat>``, ``meta/episodes/chunk_index``, ``meta/episodes/file_index``;
- ``meta/stats.json``: every feature's ``min``, ``max``, ``mean``, ``std``, ``count``, ``q01`` … ``q99``;
- ``data/chunk-CCC/file-FFF.parquet``: one row per frame (one row group per episode): the features, then
  ``timestamp``, ``frame_index``, ``episode_index``, ``index``, ``task_index``;
- ``videos/…``: video features (mp4), never read here.

Depth and its camera: a depth feature is an array feature of dtype ``uint16`` (raw counts) or ``float32`` (metres),
shape ``(H, W)``, whose entry in ``meta/info.json`` holds the camera in
``info.camera_intrinsics = {fx, fy, ppx, ppy, width, height, depth_unit}`` (pixels; ``depth_unit``: metres per
count). That is where :func:`dssp_data.lerobot.write.export` writes them, and where a user adds them to a dataset
recorded elsewhere.

A vector feature's ``names`` give its layout: ``arm<i> <channel>`` blocks for several arms, else one arm with the
names as channels (:func:`feature_names` writes them, :func:`feature_layout` reads them back).
"""

from __future__ import annotations

import os
import re
import stat
import string
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from dssp_core.errors import ConfigError, DatasetError
from dssp_core.schema import check_rate, read_json
from dssp_data.bounded import check_budget, human_size
from dssp_data.observation import VectorLayout

__all__ = [
    "CODEBASE_VERSION",
    "INFO_PATH",
    "TASKS_PATH",
    "STATS_PATH",
    "EPISODES_DIR",
    "CHUNK_FILE",
    "DATA_PATH",
    "CHUNKS_SIZE",
    "INDEX_FEATURES",
    "INTRINSICS_KEYS",
    "pyarrow_modules",
    "is_lerobot_root",
    "named_path",
    "open_regular",
    "read_info",
    "data_file",
    "read_parquet",
    "decoded_size",
    "numpy_column",
    "to_numpy",
    "from_numpy",
    "list_array",
    "text_array",
    "feature_layout",
    "feature_names",
]

CODEBASE_VERSION = "v3.0"
"""What :func:`dssp_data.lerobot.write.export` writes (LeRobot 0.4's format)."""
INFO_PATH = "meta/info.json"
TASKS_PATH = "meta/tasks.parquet"
STATS_PATH = "meta/stats.json"
EPISODES_DIR = "meta/episodes"
CHUNK_FILE = "chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
DATA_PATH = "data/" + CHUNK_FILE
CHUNKS_SIZE = 1000
"""Files per chunk folder."""
INDEX_FEATURES = ("timestamp", "frame_index", "episode_index", "index", "task_index")
"""The per-frame columns every LeRobot dataset holds after its own features."""
INTRINSICS_KEYS = ("fx", "fy", "ppx", "ppy", "width", "height", "depth_unit")
INFO_LIMIT = 16 << 20
"""Bytes ``meta/info.json`` may hold (a dataset of a hundred features writes a few tens of KB)."""
TEMPLATE_LIMIT = 1024
"""Characters a file path template of ``meta/info.json`` may have."""


def pyarrow_modules():
    """``pyarrow``, ``pyarrow.compute`` and ``pyarrow.parquet``; without them, one line saying how to install them."""
    try:
        import pyarrow as pa  # optional: the lerobot extra
        import pyarrow.compute as pc  # optional: the lerobot extra
        import pyarrow.parquet as pq  # optional: the lerobot extra
    except ImportError:
        raise ConfigError(
            "LeRobot datasets are parquet files: reading and writing them needs pyarrow (pip install 'dssp[lerobot]')"
        ) from None
    return pa, pc, pq


# ------------------------------------------------------------------------------------------- files of a root
def is_lerobot_root(path: Path) -> bool:
    """A LeRobot dataset's root: a folder holding ``meta/info.json`` (whatever it is: it is checked when read)."""
    path = Path(path)
    return path.is_dir() and os.path.lexists(path / INFO_PATH)


def named_path(root: Path, rel: str, what: str, folder: bool = False) -> Path:
    """``root / rel`` for a path named by the dataset (a template or a listing): relative, no ``..``, and no link
    anywhere on the way (each part checked without following it); a regular file (``folder``: a folder)."""
    parts = Path(rel).parts
    if not rel or Path(rel).is_absolute() or ".." in parts or "\\" in rel:
        raise DatasetError(
            f"{root}: {what} {rel!r} leads outside the dataset's folder; a LeRobot dataset names its "
            "files relative to its root"
        )
    path = root
    for i, part in enumerate(parts):
        path = path / part
        try:
            info = os.lstat(path)
        except FileNotFoundError:
            raise DatasetError(f"{root}: {what} {rel} does not exist; the dataset is incomplete") from None
        except OSError as exc:
            raise DatasetError(f"cannot read {path} ({exc.strerror or exc})") from None
        if stat.S_ISLNK(info.st_mode):
            raise DatasetError(
                f"{root}: {'/'.join(parts[: i + 1])} is a link; a LeRobot dataset is read from its own "
                "files only (download it with --local-dir, not as the hub cache's links)"
            )
        file = i == len(parts) - 1 and not folder
        if file and not stat.S_ISREG(info.st_mode) or not file and not stat.S_ISDIR(info.st_mode):
            raise DatasetError(f"{root}: {'/'.join(parts[: i + 1])} is not a {'file' if file else 'folder'}")
    return path


def open_regular(path: Path):
    """The file at ``path`` opened for reading without following a link and without blocking (a FIFO swapped in
    is refused, never waited on)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK)
    except OSError as exc:
        raise DatasetError(f"cannot read {path} ({exc.strerror or exc})") from None
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise DatasetError(f"{path} is not a regular file")
    return os.fdopen(fd, "rb")


def _check_root(root: Path) -> Path:
    root = Path(root)
    if root.is_symlink():
        raise DatasetError(f"{root} is a link; give the LeRobot dataset's folder itself")
    if not is_lerobot_root(root):
        raise DatasetError(f"{root} is not a LeRobot dataset (no {INFO_PATH})")
    return root


def read_info(root: Path) -> dict:
    """``meta/info.json`` of a v3 dataset, checked: a JSON object (at most :data:`INFO_LIMIT` bytes, no key twice,
    nested at most :data:`~dssp_core.schema.JSON_MAX_DEPTH` deep) with ``codebase_version`` v3.x, ``fps`` a control
    rate (:func:`~dssp_core.schema.check_rate`) and ``features``; anything else is one line."""
    root = _check_root(root)
    path = named_path(root, INFO_PATH, "its info file")
    info = read_json(path, str(path), error=DatasetError, limit=INFO_LIMIT, follow_links=False)
    if not isinstance(info, dict):
        raise DatasetError(f"{path} must hold a JSON object")
    version = info.get("codebase_version")
    if not (isinstance(version, str) and re.fullmatch(r"v3(\.\d+)*", version)):
        raise DatasetError(
            f"{root} is a LeRobot dataset of codebase_version {_shown(version)}; only v3 datasets are "
            "read (convert an older one with lerobot's convert_dataset_v21_to_v30 first)"
        )
    try:
        check_rate(info.get("fps"), "fps")
    except ConfigError as exc:
        raise DatasetError(f"{path}: {exc} (the frame rate, the dataset's control rate)") from None
    features = info.get("features")
    if not (isinstance(features, dict) and all(isinstance(f, dict) for f in features.values())):
        raise DatasetError(f"{path}: features must be an object of feature objects")
    for key, feature in features.items():
        shape = feature.get("shape")
        if not (
            isinstance(shape, list)
            and shape
            and all(isinstance(n, int) and not isinstance(n, bool) and n > 0 for n in shape)
        ):
            raise DatasetError(
                f"{path}: feature {key}'s shape must be a list of positive integers, got {_shown(shape)}"
            )
        if not isinstance(feature.get("dtype"), str):
            raise DatasetError(f"{path}: feature {key} has no dtype")
    return info


def _shown(value, limit: int = 80) -> str:
    """``value`` for a message, cut to ``limit`` characters (a value from a file may be any size)."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 5] + " ...'"


_FIELDS = ("chunk_index", "file_index")
_FIELD_SPEC = re.compile(r"(0?[1-9])?d?")
"""The formats a data_path template may give its fields: an integer, zero-padded to at most 9 digits (``03d``)."""


def data_file(root: Path, template, chunk: int, file: int) -> Path:
    """The data file of (chunk, file) by the dataset's ``data_path`` template: text with ``{chunk_index}`` and
    ``{file_index}`` fields, each formatted at most as an integer padded to 9 digits (``{chunk_index:03d}``); any
    other field, conversion or format (a width that would fill memory) is refused before anything is formatted."""
    problem = None
    if not isinstance(template, str) or len(template) > TEMPLATE_LIMIT:
        problem = f"a text of at most {TEMPLATE_LIMIT} characters"
    else:
        parts = []
        try:
            parsed = list(string.Formatter().parse(template))
        except ValueError as exc:
            parsed, problem = [], f"a template ({exc})"
        for literal, name, spec, conversion in parsed:
            parts.append(literal)
            if name is None:
                continue
            if name not in _FIELDS or conversion or not _FIELD_SPEC.fullmatch(spec or ""):
                problem = "a template whose fields are {chunk_index} and {file_index}, formatted at most as :09d"
                break
            parts.append(format(chunk if name == "chunk_index" else file, spec or ""))
    if problem:
        raise DatasetError(
            f"{root}: data_path {_shown(template)} in {INFO_PATH} is not {problem}; LeRobot writes {DATA_PATH!r}"
        )
    return named_path(root, "".join(parts), "the data file")


def read_parquet(pa, pq, path: Path, columns: Sequence[str]):
    """The ``columns`` of the parquet file at ``path`` (opened without following a link), their decoded size as the
    file's metadata declares it (:func:`decoded_size`) checked against the read budget before anything is read."""
    with open_regular(path) as f:
        try:
            parquet = pq.ParquetFile(f)
            need = decoded_size(parquet.metadata, columns)
        except (OSError, ValueError, KeyError, TypeError, pa.ArrowException) as exc:
            raise DatasetError(f"{path}: not a readable parquet file ({_first_line(exc)})") from None
        check_budget(
            2 * need,
            f"{path}: the columns {', '.join(columns)} ({human_size(need)} decoded)",
            "convert a dataset with smaller data files",
        )
        try:
            return parquet.read(columns=list(columns))
        except (MemoryError, pa.ArrowMemoryError):
            raise DatasetError(
                f"{path}: reading it ran out of memory although its metadata declares "
                f"{human_size(need)}: a damaged or crafted file"
            ) from None
        except (OSError, ValueError, KeyError, TypeError, pa.ArrowException) as exc:
            raise DatasetError(
                f"{path}: not a readable parquet file with the columns {', '.join(columns)} ({_first_line(exc)})"
            ) from None


def _first_line(exc: BaseException) -> str:
    return str(exc).splitlines()[0][:200] if str(exc) else type(exc).__name__


_WIDTHS = {"BOOLEAN": 1, "INT32": 4, "INT64": 8, "INT96": 12, "FLOAT": 4, "DOUBLE": 8}
_LIST_PARTS = {"list", "element", "item", "array", "bag"}


def decoded_size(metadata, columns: Sequence[str]) -> int:
    """Bytes the ``columns`` of a parquet file take decoded, from its metadata, before anything is read: per value of
    every row group's column chunks its width (and 4 bytes of offsets and levels); strings at most their stored
    bytes, or every value the whole dictionary when dictionary-encoded."""
    total = 0
    for g in range(metadata.num_row_groups):
        group = metadata.row_group(g)
        for c in range(group.num_columns):
            chunk = group.column(c)
            path = chunk.path_in_schema
            if not any(
                path == name or path.startswith(name + ".") and set(path[len(name) + 1 :].split(".")) <= _LIST_PARTS
                for name in columns
            ):
                continue
            values, stored = int(chunk.num_values), int(chunk.total_uncompressed_size)
            width = _WIDTHS.get(chunk.physical_type)
            if width is not None:
                total += values * (width + 4)
            else:  # BYTE_ARRAY, FIXED_LEN_BYTE_ARRAY
                total += values * (4 + (stored if chunk.has_dictionary_page else 0)) + stored
    return total


# ------------------------------------------------------------------------------------------- columns
def numpy_column(pa, pc, table, name: str, shape: tuple[int, ...], where: str) -> np.ndarray:
    """A column of ``table`` as an (n, *shape) array: fixed or variable lists nested len(shape) deep (or plain
    values for shape (1,)), every row exactly ``shape``, no null."""
    if name not in table.column_names:
        raise DatasetError(f"{where}: no column {name!r} in the data file")
    values = table.column(name).combine_chunks()
    n = len(values)
    if isinstance(values.type, pa.ExtensionType):
        values = values.storage
    if shape == (1,) and not _is_list(pa, values.type):
        dims: tuple[int, ...] = ()
    else:
        dims = shape
    for depth, dim in enumerate(dims):
        if values.null_count:
            raise DatasetError(f"{where}: {name} holds empty (null) values")
        if not _is_list(pa, values.type):
            raise DatasetError(
                f"{where}: {name} is {table.schema.field(name).type}, not an array of shape {list(shape)}"
            )
        lengths = to_numpy(pa, pc.list_value_length(values))
        if lengths.size and not np.all(lengths == dim):
            bad = int(np.argmax(lengths != dim))
            raise DatasetError(
                f"{where}: {name} has {int(lengths[bad])} values where its shape {list(shape)} says "
                f"{dim} (row {bad}{', axis ' + str(depth) if len(shape) > 1 else ''})"
            )
        values = values.flatten()
    if values.null_count:
        raise DatasetError(f"{where}: {name} holds empty (null) values")
    try:
        array = to_numpy(pa, values)
    except (pa.ArrowException, TypeError) as exc:
        raise DatasetError(f"{where}: {name} is not numeric ({exc})") from None
    return array.reshape((n, *shape))


def _is_list(pa, kind) -> bool:
    return pa.types.is_list(kind) or pa.types.is_large_list(kind) or pa.types.is_fixed_size_list(kind)


# Arrays go between numpy and arrow through their buffers: pyarrow's own conversions (pa.array, Array.to_numpy) load
# pandas when it is installed, which the dataset package has no use for.
def to_numpy(pa, array) -> np.ndarray:
    """The values of a numeric arrow array without nulls (a read-only view of its buffer)."""
    if isinstance(array, pa.ChunkedArray):
        array = array.combine_chunks()
    kind = array.type
    if not (pa.types.is_integer(kind) or pa.types.is_floating(kind)) or array.null_count:
        raise TypeError(f"{kind}{' with nulls' if array.null_count else ''} is not an array of numbers")
    dtype = np.dtype(kind.to_pandas_dtype())
    if len(array) == 0:
        return np.empty(0, dtype)
    return np.frombuffer(array.buffers()[1], dtype=dtype, count=len(array), offset=array.offset * dtype.itemsize)


def from_numpy(pa, values: np.ndarray):
    """A flat arrow array of ``values``' numbers."""
    values = np.ascontiguousarray(values).reshape(-1)
    return pa.Array.from_buffers(pa.from_numpy_dtype(values.dtype), len(values), [None, pa.py_buffer(values)])


def list_array(pa, values, rows: int, length: int):
    """Variable-size lists of ``length`` values each (the arrow type ``datasets`` writes for 2-D arrays)."""
    return pa.ListArray.from_arrays(from_numpy(pa, np.arange(0, rows * length + 1, length, dtype=np.int32)), values)


def text_array(pa, texts: Sequence[str], large: bool = False):
    """An arrow string array (``large``: 64-bit offsets)."""
    data = [t.encode() for t in texts]
    offsets = np.zeros(len(data) + 1, np.int64 if large else np.int32)
    offsets[1:] = np.cumsum([len(d) for d in data], dtype=np.int64)
    return pa.Array.from_buffers(
        pa.large_string() if large else pa.string(),
        len(data),
        [None, from_numpy(pa, offsets).buffers()[1], pa.py_buffer(b"".join(data))],
    )


# ------------------------------------------------------------------------------------------- the features' names
def feature_layout(feature: dict, dim: int) -> VectorLayout | None:
    """The vector's layout from the feature's names: ``arm<i> <channel>`` blocks (what
    :func:`dssp_data.lerobot.write.export` writes for several arms), else one arm with the names as channels; None
    when the names do not give one per value."""
    names = feature.get("names")
    if isinstance(names, dict) and len(names) == 1:  # {"motors": [...]} as some LeRobot datasets write it
        names = next(iter(names.values()))
    if not (isinstance(names, list) and len(names) == dim and all(isinstance(n, str) and n for n in names)):
        return None
    blocks = [re.fullmatch(r"arm(\d+) (.+)", n) for n in names]
    try:
        if all(blocks):
            arms = len({m.group(1) for m in blocks})
            per = dim // arms
            channels = [m.group(2) for m in blocks[:per]]
            if (
                arms > 1
                and dim == arms * per
                and all(m.group(1) == str(i // per) and m.group(2) == channels[i % per] for i, m in enumerate(blocks))
            ):
                return VectorLayout(arms=arms, channels=tuple(channels))
        return VectorLayout(arms=1, channels=tuple(names))
    except ConfigError:
        return None


def feature_names(layout: dict | None, dim: int) -> list[str] | None:
    """The feature names of a vector with ``layout`` (the dataset's state_layout / action_layout attribute)."""
    try:
        layout = VectorLayout.from_dict(layout) if isinstance(layout, dict) else None
    except ConfigError:
        return None
    if layout is None or layout.dim != dim:
        return None
    if layout.arms == 1:
        return list(layout.channels)
    return [f"arm{a} {c}" for a in range(layout.arms) for c in layout.channels]
