"""LeRobot v3 datasets <-> DP3 zarr datasets, read and written with pyarrow and JSON (no lerobot, no torch).

    dssp-data convert LEROBOT_ROOT --out OUT.zarr --extrinsics calib.json [--pointcloud FILE] [--depth-key K]
                      [--state-key observation.state] [--action-key action]
    dssp-data export PATH --to lerobot --out DIR [--repo-id local/NAME] [--force]

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
count). That is where :func:`export` writes them, and where a user adds them to a dataset recorded elsewhere.

Import (:func:`convert`): one DP3 episode per LeRobot episode; each frame's depth becomes the cloud by the robot's
pipeline (:func:`dssp_data.pointcloud.frame_to_cloud`, float32 metres first quantised to ``depth_unit``, 1 mm when
not given); state and action are the two features; ``fps`` is ``control_rate_hz``. Refused with one line and
nothing written: a dataset that is not v3, one without a depth feature or its intrinsics, video-encoded depth
(lossy), missing or misshapen state/action, a file path from ``meta/info.json`` that leads outside the root (an
absolute path, ``..``, a link).

Export (:func:`export`): the zarr dataset -> the layout above: ``observation.state``, ``action``,
``observation.pointcloud`` float32 (P, C) and, when the dataset holds the ``depth`` extra and its camera's
attributes, ``observation.depth`` uint16 (H, W) with its intrinsics; ``fps`` is ``control_rate_hz``.
"""

from __future__ import annotations

import json
import math
import os
import re
import stat
import string
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dssp_core.errors import ConfigError, DatasetError
from dssp_core.output_guard import OutputDir, OutputKind, check_not_inside, check_output
from dssp_core.staging import Staging, settle_background_writes
from dssp_data import attributes
from dssp_data.dataset_layout import Episode
from dssp_data.edit import DATA_DATASET, DATA_GENERATORS
from dssp_data.observation import FRAME_ROBOT_BASE, ObservationContract, PointCloudConfig, VectorLayout
from dssp_data.pointcloud import EmptyCloudError, frame_to_cloud, validate_extrinsics
from dssp_data.pointcloud.depth_frame import DepthFrame, Intrinsics
from dssp_data.recording import can_log_dir
from dssp_data.replay_buffer import ReplayBufferReader
from dssp_data.replay_buffer_writer import ReplayBufferWriter

__all__ = ["is_lerobot_root", "convert", "export", "LEROBOT_DATASET", "CODEBASE_VERSION"]

CODEBASE_VERSION = "v3.0"
"""What :func:`export` writes (LeRobot 0.4's format)."""
INFO_PATH = "meta/info.json"
TASKS_PATH = "meta/tasks.parquet"
STATS_PATH = "meta/stats.json"
EPISODES_DIR = "meta/episodes"
CHUNK_FILE = "chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
DATA_PATH = "data/" + CHUNK_FILE
CHUNKS_SIZE = 1000
"""Files per chunk folder."""
DATA_FILE_MB = 100
"""A data file is closed before it grows past this (LeRobot's ``data_files_size_in_mb``)."""
VIDEO_FILE_MB = 200
INDEX_FEATURES = ("timestamp", "frame_index", "episode_index", "index", "task_index")
"""The per-frame columns every LeRobot dataset holds after its own features."""
QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)
QUANTILE_VALUES = 2_000_000
"""Quantiles of a feature in one episode are taken from at most this many values, evenly spaced rows."""
DEFAULT_DEPTH_UNIT = 0.001
"""Metres per count that float32 depth in metres is quantised to when its intrinsics give no ``depth_unit``."""
INTRINSICS_KEYS = ("fx", "fy", "ppx", "ppy", "width", "height", "depth_unit")
DEPTH_DTYPES = ("uint16", "float32", "float64")
VECTOR_DTYPES = ("float32", "float64", "float16", "int8", "int16", "int32", "int64", "uint8", "uint16", "uint32")
ACTION_CONVENTION = ("lerobot_action: the LeRobot dataset's action feature at this frame (what was commanded to the "
                     "robot at that frame)")
TIME_KEYS = ("timestamp",)
ARRAY2D = "datasets.features.features.Array2DExtensionType"
"""How the ``datasets`` library marks a 2-D array column (its extension type; the storage is lists of lists)."""

LEROBOT_DATASET = OutputKind("a LeRobot dataset", "dssp-data export", entries=("meta", "data"))
"""``dssp-data export --to lerobot --out DIR``: the folder holds meta/ and data/ (and the marker)."""


def _pyarrow():
    try:
        import pyarrow as pa  # optional: the lerobot extra
        import pyarrow.compute as pc  # optional: the lerobot extra
        import pyarrow.parquet as pq  # optional: the lerobot extra
    except ImportError:
        raise ConfigError("LeRobot datasets are parquet files: reading and writing them needs pyarrow "
                          "(pip install 'dssp[lerobot]')") from None
    return pa, pc, pq


# ------------------------------------------------------------------------------------------- files of a root
def is_lerobot_root(path: Path) -> bool:
    """A LeRobot dataset's root: a folder holding ``meta/info.json``."""
    path = Path(path)
    return path.is_dir() and (path / INFO_PATH).is_file()


def _relative(root: Path, rel: str, what: str, folder: bool = False) -> Path:
    """``root / rel`` for a path named by the dataset (a template or a listing): relative, no ``..``, and no link
    anywhere on the way (each part checked without following it); a regular file (``folder``: a folder)."""
    parts = Path(rel).parts
    if not rel or Path(rel).is_absolute() or ".." in parts or "\\" in rel:
        raise DatasetError(f"{root}: {what} {rel!r} leads outside the dataset's folder; a LeRobot dataset names its "
                           "files relative to its root")
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
            raise DatasetError(f"{root}: {'/'.join(parts[:i + 1])} is a link; a LeRobot dataset is read from its own "
                               "files only (download it with --local-dir, not as the hub cache's links)")
        file = i == len(parts) - 1 and not folder
        if file and not stat.S_ISREG(info.st_mode) or not file and not stat.S_ISDIR(info.st_mode):
            raise DatasetError(f"{root}: {'/'.join(parts[:i + 1])} is not a {'file' if file else 'folder'}")
    return path


def _open_regular(path: Path):
    """The file at ``path`` opened for reading without following a link."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
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
    """``meta/info.json`` of a v3 dataset, checked: a JSON object with ``codebase_version`` v3.x, ``fps`` > 0 and
    ``features``; anything else is one line."""
    root = _check_root(root)
    path = _relative(root, INFO_PATH, "its info file")
    with _open_regular(path) as f:
        raw = f.read(64 << 20)
    try:
        info = json.loads(raw)
    except (ValueError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path} is not valid JSON ({exc})") from None
    if not isinstance(info, dict):
        raise DatasetError(f"{path} must hold a JSON object")
    version = info.get("codebase_version")
    if not (isinstance(version, str) and re.fullmatch(r"v3(\.\d+)*", version)):
        raise DatasetError(f"{root} is a LeRobot dataset of codebase_version {version!r}; only v3 datasets are read "
                           "(convert an older one with lerobot's convert_dataset_v21_to_v30 first)")
    fps = info.get("fps")
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not (math.isfinite(fps) and 0 < fps <= 1000):
        raise DatasetError(f"{path}: fps must be a frame rate in (0, 1000] Hz, got {fps!r}")
    features = info.get("features")
    if not (isinstance(features, dict) and all(isinstance(f, dict) for f in features.values())):
        raise DatasetError(f"{path}: features must be an object of feature objects")
    for key, feature in features.items():
        shape = feature.get("shape")
        if not (isinstance(shape, list) and shape and all(isinstance(n, int) and not isinstance(n, bool) and n > 0
                                                          for n in shape)):
            raise DatasetError(f"{path}: feature {key}'s shape must be a list of positive integers, got {shape!r}")
        if not isinstance(feature.get("dtype"), str):
            raise DatasetError(f"{path}: feature {key} has no dtype")
    return info


def _data_path(root: Path, template, chunk: int, file: int) -> Path:
    """The data file of (chunk, file) by the dataset's ``data_path`` template, which may name only those two."""
    if not isinstance(template, str):
        raise DatasetError(f"{root}: data_path in {INFO_PATH} must be a text template, got {template!r}")
    try:
        fields = {name for _, name, _, _ in string.Formatter().parse(template) if name is not None}
        if not fields <= {"chunk_index", "file_index"}:
            raise ValueError(f"it names {sorted(fields)}")
        rel = template.format(chunk_index=chunk, file_index=file)
    except (ValueError, IndexError, KeyError) as exc:
        raise DatasetError(f"{root}: data_path {template!r} in {INFO_PATH} is not a template of chunk_index and "
                           f"file_index ({exc})") from None
    return _relative(root, rel, "the data file")


def _read_parquet(pa, pq, path: Path, columns: Sequence[str]):
    """The ``columns`` of the parquet file at ``path`` (opened without following a link)."""
    with _open_regular(path) as f:
        try:
            return pq.ParquetFile(f).read(columns=list(columns))
        except (OSError, ValueError, KeyError, TypeError, pa.ArrowException) as exc:
            raise DatasetError(f"{path}: not a readable parquet file with the columns {', '.join(columns)} "
                               f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None


# ------------------------------------------------------------------------------------------- columns
def _column(pa, pc, table, name: str, shape: tuple[int, ...], where: str) -> np.ndarray:
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
            raise DatasetError(f"{where}: {name} is {table.schema.field(name).type}, not an array of shape "
                               f"{list(shape)}")
        lengths = _to_numpy(pa, pc.list_value_length(values))
        if lengths.size and not np.all(lengths == dim):
            bad = int(np.argmax(lengths != dim))
            raise DatasetError(f"{where}: {name} has {int(lengths[bad])} values where its shape {list(shape)} says "
                               f"{dim} (row {bad}{', axis ' + str(depth) if len(shape) > 1 else ''})")
        values = values.flatten()
    if values.null_count:
        raise DatasetError(f"{where}: {name} holds empty (null) values")
    try:
        array = _to_numpy(pa, values)
    except (pa.ArrowException, TypeError) as exc:
        raise DatasetError(f"{where}: {name} is not numeric ({exc})") from None
    return array.reshape((n, *shape))


def _is_list(pa, kind) -> bool:
    return pa.types.is_list(kind) or pa.types.is_large_list(kind) or pa.types.is_fixed_size_list(kind)


# Arrays go between numpy and arrow through their buffers: pyarrow's own conversions (pa.array, to_numpy) load
# pandas when it is installed, which the dataset package has no use for.
def _to_numpy(pa, array) -> np.ndarray:
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


def _from_numpy(pa, values: np.ndarray):
    """A flat arrow array of ``values``' numbers."""
    values = np.ascontiguousarray(values).reshape(-1)
    return pa.Array.from_buffers(pa.from_numpy_dtype(values.dtype), len(values), [None, pa.py_buffer(values)])


def _lists(pa, values, rows: int, length: int):
    """Variable-size lists of ``length`` values each (the arrow type ``datasets`` writes for 2-D arrays)."""
    return pa.ListArray.from_arrays(_from_numpy(pa, np.arange(0, rows * length + 1, length, dtype=np.int32)), values)


def _texts(pa, texts: Sequence[str], large: bool = False):
    """An arrow string array (``large``: 64-bit offsets)."""
    data = [t.encode() for t in texts]
    offsets = np.zeros(len(data) + 1, np.int64 if large else np.int32)
    offsets[1:] = np.cumsum([len(d) for d in data], dtype=np.int64)
    return pa.Array.from_buffers(pa.large_string() if large else pa.string(), len(data),
                                 [None, _from_numpy(pa, offsets).buffers()[1], pa.py_buffer(b"".join(data))])


# ------------------------------------------------------------------------------------------- the features
@dataclass(frozen=True)
class _Depth:
    key: str
    dtype: str
    intrinsics: Intrinsics
    depth_unit: float


def _feature(features: dict, key: str, flag: str, what: str, root: Path) -> dict:
    if key not in features:
        raise DatasetError(f"{root}: no feature {key!r} in {INFO_PATH} (it has {', '.join(features)}); name the "
                           f"{what} feature with {flag}")
    return features[key]


def _vector_feature(features: dict, key: str, flag: str, what: str, root: Path) -> int:
    feature = _feature(features, key, flag, what, root)
    if feature["dtype"] not in VECTOR_DTYPES or len(feature["shape"]) != 1:
        raise DatasetError(f"{root}: feature {key} is {feature['dtype']} {feature['shape']}; the {what} must be a "
                           f"vector of numbers (shape [N]); name another with {flag}")
    return int(feature["shape"][0])


def _depth_feature(features: dict, key: str | None, root: Path) -> _Depth:
    if key is None:
        found = [k for k, f in features.items() if k not in INDEX_FEATURES and (
            "depth" in k.lower() or isinstance(f.get("info"), dict) and "camera_intrinsics" in f["info"])]
        if not found:
            raise DatasetError(f"{root}: no depth feature (its features are {', '.join(features)}); the clouds are "
                               "made from a uint16 (H, W) depth feature with info.camera_intrinsics: name it with "
                               "--depth-key")
        if len(found) > 1:
            raise DatasetError(f"{root}: several depth features ({', '.join(found)}); choose one with --depth-key")
        key = found[0]
    feature = _feature(features, key, "--depth-key", "depth", root)
    dtype, shape = feature["dtype"], feature["shape"]
    if dtype in ("video", "image"):
        raise DatasetError(f"{root}: {key} is stored as {dtype}; depth in a {dtype} is not supported (the codecs are "
                           "lossy or 8-bit): store it as a uint16 (H, W) array feature")
    if dtype not in DEPTH_DTYPES or not (len(shape) == 2 or len(shape) == 3 and shape[2] == 1):
        raise DatasetError(f"{root}: {key} is {dtype} {shape}; depth must be a uint16 (counts) or float32 (metres) "
                           "array of shape [H, W]")
    info = feature.get("info")
    camera = info.get("camera_intrinsics") if isinstance(info, dict) else None
    where = f"{root}: {key}'s info.camera_intrinsics"
    if not isinstance(camera, dict):
        raise DatasetError(f"{root}: {key} has no camera intrinsics; add info.camera_intrinsics = {{fx, fy, ppx, ppy, "
                           f"width, height, depth_unit}} to its entry in {INFO_PATH}")
    unknown = sorted(set(camera) - set(INTRINSICS_KEYS))
    missing = [k for k in INTRINSICS_KEYS[:6] if k not in camera]
    if dtype == "uint16" and "depth_unit" not in camera:
        missing.append("depth_unit")
    if missing or unknown:
        raise DatasetError(f"{where} {'lacks ' + ', '.join(missing) if missing else 'has unknown ' + ', '.join(unknown)}"
                           f" (it needs {', '.join(INTRINSICS_KEYS)}: pixels, and metres per depth count)")
    numbers = {k: camera[k] for k in INTRINSICS_KEYS if k in camera}
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in numbers.values()):
        raise DatasetError(f"{where} must hold finite numbers, got {camera}")
    width, height = camera["width"], camera["height"]
    if not (isinstance(width, int) and isinstance(height, int) and [height, width] == list(shape[:2])):
        raise DatasetError(f"{where} says {width}x{height}; the feature's shape is {shape} (height, width)")
    if not (camera["fx"] > 0 and camera["fy"] > 0):
        raise DatasetError(f"{where}: fx and fy must be positive, got {camera['fx']}, {camera['fy']}")
    unit = float(camera.get("depth_unit", DEFAULT_DEPTH_UNIT))
    if not 0 < unit <= 1:
        raise DatasetError(f"{where}: depth_unit must be metres per count in (0, 1], got {unit}")
    intrinsics = Intrinsics(width, height, float(camera["fx"]), float(camera["fy"]), float(camera["ppx"]),
                            float(camera["ppy"]))
    return _Depth(key, dtype, intrinsics, unit)


def _layout(feature: dict, dim: int) -> VectorLayout | None:
    """The vector's layout from the feature's names: ``arm<i> <channel>`` blocks (what :func:`export` writes for
    several arms), else one arm with the names as channels; None when the names do not give one per value."""
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
            if arms > 1 and dim == arms * per and all(
                    m.group(1) == str(i // per) and m.group(2) == channels[i % per] for i, m in enumerate(blocks)):
                return VectorLayout(arms=arms, channels=tuple(channels))
        return VectorLayout(arms=1, channels=tuple(names))
    except ConfigError:
        return None


def _layout_names(layout: dict | None, dim: int) -> list[str] | None:
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


# ------------------------------------------------------------------------------------------- import
@dataclass
class _EpisodeRef:
    index: int
    length: int
    chunk: int
    file: int
    tasks: list[str]


def _episode_refs(pa, pq, root: Path) -> list[_EpisodeRef]:
    """Every episode's row of ``meta/episodes/*/*.parquet``, in episode order (0..E-1, each once)."""
    folder = _relative(root, EPISODES_DIR, "the episodes folder", folder=True)
    files = sorted(folder.glob("*/*.parquet"))
    if not files:
        raise DatasetError(f"{root}: {EPISODES_DIR}/ holds no parquet file; not a complete v3 dataset")
    columns = ["episode_index", "length", "data/chunk_index", "data/file_index", "tasks"]
    refs = []
    for path in files:
        path = _relative(root, str(path.relative_to(root)), "the episodes file")
        table = _read_parquet(pa, pq, path, columns)
        rows = {c: table.column(c).to_pylist() for c in columns}
        for i in range(table.num_rows):
            values = [rows[c][i] for c in columns[:4]]
            tasks = rows["tasks"][i]
            if not all(isinstance(v, int) and v >= 0 for v in values) or values[1] < 1:
                raise DatasetError(f"{path}: row {i} has an invalid episode_index, length or data file index "
                                   f"({dict(zip(columns[:4], values))})")
            if not (isinstance(tasks, list) and all(isinstance(t, str) for t in tasks)):
                raise DatasetError(f"{path}: row {i}'s tasks must be a list of texts")
            refs.append(_EpisodeRef(*values, tasks=tasks))
    refs.sort(key=lambda r: r.index)
    if [r.index for r in refs] != list(range(len(refs))):
        raise DatasetError(f"{root}: the episodes in {EPISODES_DIR}/ are not numbered 0..{len(refs) - 1} each once")
    return refs


def _is_convention(value) -> bool:
    try:
        return isinstance(value, str) and attributes.action_convention({"action_convention": value}) is not None
    except DatasetError:
        return False


def _quantised(depth: np.ndarray, unit: float) -> np.ndarray:
    """Depth in metres -> uint16 counts of ``unit`` (NaN, infinite, negative or out-of-range values: 0, no
    measurement)."""
    with np.errstate(invalid="ignore", over="ignore"):
        counts = np.rint(np.asarray(depth, dtype=np.float64) / unit)
    bad = ~np.isfinite(counts) | (counts < 0) | (counts > 65535)
    counts[bad] = 0
    return counts.astype(np.uint16)


def convert(source: Path, out: Path, cloud_config: PointCloudConfig, camera_to_base: np.ndarray, *,
            depth_key: str | None = None, state_key: str = "observation.state", action_key: str = "action",
            max_episodes: int | None = None, task: str | None = None, force: bool = False,
            progress: Callable | None = None, flag: str = "--out") -> dict:
    """The LeRobot v3 dataset at ``source`` -> a new DP3 zarr dataset at ``out`` (one episode per LeRobot episode,
    clouds by the robot's pipeline), written in a staging folder and moved into place at the end; returns
    {"episodes", "steps", "fps", "depth_key", "state_key", "action_key"}."""
    pa, pc, pq = _pyarrow()
    camera_to_base = validate_extrinsics(np.asarray(camera_to_base, dtype=np.float64))
    if cloud_config.use_color:
        raise ConfigError("--pointcloud asks for colour (use_color): the clouds of a LeRobot dataset are made from its "
                          "depth feature only; set use_color false")
    root = Path(source)
    info = read_info(root)
    features = info["features"]
    depth = _depth_feature(features, depth_key, root)
    state_dim = _vector_feature(features, state_key, "--state-key", "state", root)
    action_dim = _vector_feature(features, action_key, "--action-key", "action", root)
    refs = _episode_refs(pa, pq, root)
    if max_episodes is not None:
        if max_episodes < 1:
            raise DatasetError(f"--episodes must be at least 1, got {max_episodes}")
        refs = refs[:max_episodes]
    out = Path(out)
    check_not_inside(out, [root], flag=flag, error=DatasetError)
    check_output(out, force=force, kind=DATA_DATASET, flag=flag, error=DatasetError)
    data_files = {(r.chunk, r.file): _data_path(root, info.get("data_path"), r.chunk, r.file) for r in refs}

    fps = float(info["fps"])
    action_info = features[action_key].get("info")
    convention = action_info.get("convention") if isinstance(action_info, dict) else None
    if not _is_convention(convention):  # what dssp-data export wrote, else LeRobot's meaning of action
        convention = ACTION_CONVENTION
    contract = ObservationContract(pointcloud=cloud_config, frame=FRAME_ROBOT_BASE,
                                   state=_layout(features[state_key], state_dim),
                                   action=_layout(features[action_key], action_dim))
    tasks = [r.tasks[0] if len(r.tasks) == 1 else "; ".join(r.tasks) for r in refs]
    attrs = {
        "generator": DATA_GENERATORS["convert"],
        "source_format": f"LeRobot dataset {info['codebase_version']}",
        "source": str(root),
        "control_rate_hz": fps,
        "action_convention": convention,
        **contract.attrs(),
        "camera_to_base": camera_to_base.tolist(),
        "camera_intrinsics": depth.intrinsics.to_dict(),
        "camera_depth_unit": depth.depth_unit,
        "timestamps": "data/timestamp: the LeRobot frames' timestamp (s since each episode's start)",
        "lerobot": {"codebase_version": info["codebase_version"], "robot_type": info.get("robot_type"),
                    "fps": info["fps"], "depth": depth.key, "state": state_key, "action": action_key,
                    **({"depth_dtype": depth.dtype} if depth.dtype != "uint16" else {})},
        "episode_tasks": tasks,
        **({"task": task} if task else {"task": tasks[0]} if len(set(tasks)) == 1 else {}),
    }
    columns = ["episode_index", "frame_index", state_key, action_key, depth.key] + \
        (["timestamp"] if "timestamp" in features else [])
    shape = tuple(features[depth.key]["shape"])
    steps = 0
    try:
        with Staging(flag=flag, error=DatasetError) as staging:
            tmp = staging.make(staging.reserve(out))
            with ReplayBufferWriter(tmp, attrs=attrs, staged=True, extra_keys=("depth", *TIME_KEYS)) as writer:
                table, loaded = None, None
                for i, ref in enumerate(refs):
                    if progress is not None:
                        progress(i, len(refs), Path(f"episode_{ref.index:06d}"))
                    path = data_files[(ref.chunk, ref.file)]
                    if loaded != path:  # one data file in memory at a time
                        table, loaded = None, None
                        table, loaded = _read_parquet(pa, pq, path, columns), path
                    episode = _episode(pa, pc, table, ref, path, depth, shape, state_key, state_dim, action_key,
                                       action_dim, fps, cloud_config, camera_to_base)
                    writer.add_episode(episode)
                    steps += episode.n_steps
            staging.commit([(tmp, out), (None, can_log_dir(out))],  # the output checked again first
                           check=lambda: check_output(out, force=force, kind=DATA_DATASET, flag=flag, error=DatasetError))
    finally:
        settle_background_writes()
    return {"episodes": len(refs), "steps": steps, "fps": fps, "depth_key": depth.key, "state_key": state_key,
            "action_key": action_key}


def _episode(pa, pc, table, ref: _EpisodeRef, path: Path, depth: _Depth, shape: tuple[int, ...], state_key: str,
             state_dim: int, action_key: str, action_dim: int, fps: float, cloud_config: PointCloudConfig,
             camera_to_base: np.ndarray) -> Episode:
    """One LeRobot episode's rows of ``table`` -> an Episode (clouds by the robot's pipeline)."""
    where = f"{path} (episode {ref.index})"
    episodes = _column(pa, pc, table, "episode_index", (1,), where).reshape(-1)
    rows = np.flatnonzero(episodes == ref.index)
    if rows.size != ref.length:
        raise DatasetError(f"{where}: {rows.size} frames where {EPISODES_DIR}/ says {ref.length}")
    part = table.take(_from_numpy(pa, rows))
    order = np.argsort(_column(pa, pc, part, "frame_index", (1,), where).reshape(-1), kind="stable")
    part = part.take(_from_numpy(pa, order))
    frames = _column(pa, pc, part, "frame_index", (1,), where).reshape(-1)
    if not np.array_equal(frames, np.arange(ref.length)):
        raise DatasetError(f"{where}: the frame_index values are not 0..{ref.length - 1}, each once")
    state = _column(pa, pc, part, state_key, (state_dim,), where).astype(np.float32)
    action = _column(pa, pc, part, action_key, (action_dim,), where).astype(np.float32)
    raw = _column(pa, pc, part, depth.key, shape, where).reshape(ref.length, shape[0], shape[1])
    if raw.dtype != np.dtype(depth.dtype):
        raise DatasetError(f"{where}: {depth.key} is stored as {raw.dtype}; its feature in {INFO_PATH} says {depth.dtype}")
    counts = raw.astype(np.uint16) if depth.dtype == "uint16" else _quantised(raw, depth.depth_unit)
    if "timestamp" in part.column_names:
        times = _column(pa, pc, part, "timestamp", (1,), where).reshape(-1).astype(np.float64)
    else:
        times = np.arange(ref.length) / fps
    for name, values in ((state_key, state), (action_key, action)):
        bad = np.flatnonzero(~np.all(np.isfinite(values), axis=1))
        if bad.size:
            raise DatasetError(f"{where}: {name} holds NaN or infinity at frame {int(bad[0])}")
    clouds = np.empty((ref.length, cloud_config.n_points, cloud_config.point_dim), np.float32)
    for k in range(ref.length):
        frame = DepthFrame(depth=counts[k], depth_unit=depth.depth_unit, intrinsics=depth.intrinsics,
                           timestamp=float(times[k]), frame_number=k)
        try:
            clouds[k], _ = frame_to_cloud(frame, cloud_config, camera_to_base)
        except EmptyCloudError as exc:
            raise DatasetError(f"{where}: the depth frame {k} has no point in the workspace ({exc}); check "
                               "--extrinsics and the crop of --pointcloud") from None
    return Episode(point_cloud=clouds, state=state, action=action, extras={"depth": counts, "timestamp": times})


# ------------------------------------------------------------------------------------------- statistics
def _stats(values: np.ndarray) -> dict[str, np.ndarray]:
    """LeRobot's per-episode statistics of one feature: over every axis but the last (a scalar feature: one
    value), min and max in the feature's dtype, mean and std (population) in float64, count = frames, quantiles
    q01 .. q99 (from at most :data:`QUANTILE_VALUES` values, evenly spaced rows)."""
    frames = values.shape[0]
    rows = values.reshape(-1, 1) if values.ndim == 1 else values.reshape(-1, values.shape[-1])
    mean = np.zeros(rows.shape[1])
    step = max(1, (8 << 20) // max(1, rows.shape[1]))
    for start in range(0, rows.shape[0], step):
        mean += rows[start:start + step].sum(axis=0, dtype=np.float64)
    mean /= rows.shape[0]
    square = np.zeros(rows.shape[1])
    for start in range(0, rows.shape[0], step):
        square += ((rows[start:start + step].astype(np.float64) - mean) ** 2).sum(axis=0)
    stats = {"min": rows.min(axis=0), "max": rows.max(axis=0), "mean": mean, "std": np.sqrt(square / rows.shape[0]),
             "count": np.array([frames], dtype=np.int64)}
    keep = max(1, QUANTILE_VALUES // rows.shape[1])
    sample = rows if rows.shape[0] <= keep else rows[np.linspace(0, rows.shape[0] - 1, keep).round().astype(np.int64)]
    quantiles = np.quantile(sample.astype(np.float64), QUANTILES, axis=0)
    for q, value in zip(QUANTILES, quantiles):
        stats[f"q{round(q * 100):02d}"] = value
    return stats


def _aggregate(per_episode: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """The dataset's statistics from the episodes' as LeRobot aggregates them: min of mins, max of maxes, the
    count-weighted mean, the pooled variance, count-weighted quantiles."""
    counts = np.stack([s["count"] for s in per_episode]).astype(np.float64)  # (E, 1)
    total = counts.sum(axis=0)
    means = np.stack([s["mean"] for s in per_episode])
    mean = (means * counts).sum(axis=0) / total
    variance = ((np.stack([s["std"] for s in per_episode]) ** 2 + (means - mean) ** 2) * counts).sum(axis=0) / total
    out = {"min": np.min(np.stack([s["min"] for s in per_episode]), axis=0),
           "max": np.max(np.stack([s["max"] for s in per_episode]), axis=0),
           "mean": mean, "std": np.sqrt(variance), "count": total.astype(np.int64)}
    for key in per_episode[0]:
        if key.startswith("q"):
            out[key] = (np.stack([s[key] for s in per_episode]) * counts).sum(axis=0) / total
    return out


# ------------------------------------------------------------------------------------------- export
def _repo_id(repo_id: str | None, out: Path) -> str:
    if repo_id is None:
        name = re.sub(r"[^A-Za-z0-9._-]", "_", Path(out).name) or "dataset"
        return f"local/{name}"
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*/[A-Za-z0-9][A-Za-z0-9._-]*", repo_id):
        raise ConfigError(f"--repo-id must be OWNER/NAME (letters, digits, '.', '_', '-'), got {repo_id!r}")
    return repo_id


def _hf_feature(feature: dict) -> dict:
    """How the ``datasets`` library describes a feature's column (the data files' ``huggingface`` metadata)."""
    shape, dtype = feature["shape"], feature["dtype"]
    if shape == [1]:
        return {"dtype": dtype, "_type": "Value"}
    if len(shape) == 1:
        return {"feature": {"dtype": dtype, "_type": "Value"}, "length": shape[0], "_type": "List"}
    return {"shape": list(shape), "dtype": dtype, "_type": "Array2D"}


def _arrow_column(pa, values: np.ndarray, feature: dict):
    """(T, ...) values -> the column LeRobot writes: plain values, fixed-size lists, or lists of lists (2-D)."""
    shape = feature["shape"]
    flat = _from_numpy(pa, values)
    if shape == [1]:
        return flat
    if len(shape) == 1:
        return pa.FixedSizeListArray.from_arrays(flat, shape[0])
    rows, cols = shape
    n = values.shape[0]
    return _lists(pa, _lists(pa, flat, n * rows, cols), n, rows)


def _arrow_field(pa, key: str, feature: dict):
    shape, dtype = feature["shape"], pa.from_numpy_dtype(np.dtype(feature["dtype"]))
    if shape == [1]:
        return pa.field(key, dtype)
    if len(shape) == 1:
        return pa.field(key, pa.list_(pa.field("element", dtype), shape[0]))
    kind = pa.list_(pa.field("element", pa.list_(pa.field("element", dtype))))
    return pa.field(key, kind, metadata={"ARROW:extension:name": ARRAY2D,
                                         "ARROW:extension:metadata": json.dumps([list(shape), feature["dtype"]])})


def _features(reader: ReplayBufferReader, path: Path) -> tuple[dict, list[str]]:
    """The LeRobot features of the dataset (and the notes on what is left out)."""
    attrs, notes = reader.attrs, []
    (_, p, c), (_, s), (_, a) = (reader.arrays[f"data/{k}"][0] for k in ("point_cloud", "state", "action"))
    cloud_info = {k: v for k, v in (("pointcloud", attributes.pointcloud(attrs, path)),
                                    ("frame", attrs.get("pointcloud_frame", FRAME_ROBOT_BASE)
                                     if attrs.get("pointcloud") is not None else None),
                                    ("camera_to_base", attributes.camera_to_base(attrs, path))) if v is not None}
    convention = attributes.action_convention(attrs, path)
    features = {
        "observation.state": {"dtype": "float32", "shape": [s], "names": _layout_names(attrs.get("state_layout"), s)},
        "action": {"dtype": "float32", "shape": [a], "names": _layout_names(attrs.get("action_layout"), a),
                   **({"info": {"convention": convention}} if convention else {})},
        "observation.pointcloud": {"dtype": "float32", "shape": [p, c],
                                   "names": ["points", "xyz" if c == 3 else "xyzrgb"],
                                   **({"info": cloud_info} if cloud_info else {})},
    }
    if "depth" in reader.extra_keys:
        shape, dtype = reader.arrays["data/depth"]
        camera = attributes.camera_intrinsics(attrs, path)
        unit = attributes.depth_unit(attrs, path)
        if dtype != np.uint16 or len(shape) != 3:
            notes.append(f"data/depth is {dtype} {list(shape[1:])}, not uint16 (H, W): left out")
        elif camera is None or unit is None or any(k not in camera for k in INTRINSICS_KEYS[:6]):
            notes.append("data/depth left out: the dataset has no camera_intrinsics and camera_depth_unit attributes")
        elif [camera["height"], camera["width"]] != list(shape[1:]):
            raise DatasetError(f"{path}: data/depth frames are {shape[2]}x{shape[1]}, its camera_intrinsics say "
                               f"{camera['width']}x{camera['height']}")
        else:
            intrinsics = {k: camera[k] for k in INTRINSICS_KEYS[:6]}
            features["observation.depth"] = {"dtype": "uint16", "shape": list(shape[1:]), "names": ["height", "width"],
                                             "info": {"camera_intrinsics": {**intrinsics, "depth_unit": unit}}}
    for key in INDEX_FEATURES:
        features[key] = {"dtype": "float32" if key == "timestamp" else "int64", "shape": [1], "names": None}
    return features, notes


def _tasks(reader: ReplayBufferReader, path: Path) -> list[str]:
    """Each episode's task: ``episode_tasks`` (a list of texts, one per episode), else ``task``, else the dataset's
    name."""
    attrs, n = reader.attrs, reader.n_episodes
    per_episode = attrs.get("episode_tasks")
    if isinstance(per_episode, list) and len(per_episode) >= n and all(isinstance(t, str) and t for t in per_episode):
        return per_episode[:n]
    task = attrs.get("task")
    return [task if isinstance(task, str) and task else Path(path).name.removesuffix(".zarr")] * n


def _pandas_index_metadata(pa) -> bytes:
    """The metadata pandas reads a parquet file's index from: ``tasks.parquet`` is a pandas frame indexed by task."""
    return json.dumps({
        "index_columns": ["__index_level_0__"],
        "column_indexes": [{"name": None, "field_name": None, "pandas_type": "unicode", "numpy_type": "object",
                            "metadata": {"encoding": "UTF-8"}}],
        "columns": [{"name": "task_index", "field_name": "task_index", "pandas_type": "int64", "numpy_type": "int64",
                     "metadata": None},
                    {"name": None, "field_name": "__index_level_0__", "pandas_type": "unicode", "numpy_type": "object",
                     "metadata": None}],
        "attributes": {}, "creator": {"library": "pyarrow", "version": pa.__version__}}).encode()


def _next_file(chunk: int, file: int) -> tuple[int, int]:
    return (chunk + 1, 0) if file == CHUNKS_SIZE - 1 else (chunk, file + 1)


def export(path: Path, out: Path, *, repo_id: str | None = None, force: bool = False, flag: str = "--out") -> dict:
    """The DP3 zarr dataset at ``path`` -> a LeRobot v3 dataset at ``out`` (built beside it and moved into place);
    returns {"episodes", "frames", "fps", "features", "repo_id", "notes"}."""
    pa, _, pq = _pyarrow()
    path, out = Path(path), Path(out)
    repo_id = _repo_id(repo_id, out)
    reader = ReplayBufferReader(path)
    rate = reader.control_rate_hz
    if rate is None:
        raise DatasetError(f"{path} has no control_rate_hz attribute; a LeRobot dataset needs its frame rate (fps): "
                           "record or convert the dataset with its control rate")
    if abs(rate - round(rate)) > 1e-9:
        raise DatasetError(f"{path}: control_rate_hz is {rate:g}; LeRobot's fps is a whole number of frames per second")
    fps = int(round(rate))
    check_not_inside(out, [path], flag=flag, error=DatasetError)
    features, notes = _features(reader, path)
    tasks = _tasks(reader, path)
    task_list = list(dict.fromkeys(tasks))
    task_index = {t: i for i, t in enumerate(task_list)}
    with_depth = "observation.depth" in features
    schema = pa.schema([_arrow_field(pa, k, f) for k, f in features.items()],
                       metadata={"huggingface": json.dumps({"info": {"features": {
                           k: _hf_feature(f) for k, f in features.items()}}})})
    episode_rows, episode_stats = [], []
    with OutputDir(out, LEROBOT_DATASET, force=force, flag=flag, error=DatasetError) as target:
        root = target.path
        writer, data_file, chunk, file, file_start, frames = None, None, 0, 0, 0, 0
        try:
            for e in range(reader.n_episodes):
                episode = reader.episode(e, extras=["depth"] if with_depth else False)
                n = episode.n_steps
                values = {"observation.state": episode.state, "action": episode.action,
                          "observation.pointcloud": episode.point_cloud,
                          **({"observation.depth": episode.extras["depth"]} if with_depth else {}),
                          "timestamp": (np.arange(n) / fps).astype(np.float32),
                          "frame_index": np.arange(n, dtype=np.int64),
                          "episode_index": np.full(n, e, dtype=np.int64),
                          "index": np.arange(frames, frames + n, dtype=np.int64),
                          "task_index": np.full(n, task_index[tasks[e]], dtype=np.int64)}
                table = pa.Table.from_arrays([_arrow_column(pa, values[k], f) for k, f in features.items()],
                                             schema=schema)
                if writer is not None:  # LeRobot's rule: a new file when this episode would take it past the size
                    size = data_file.stat().st_size / (1 << 20)
                    if size + size / (frames - file_start) * n >= DATA_FILE_MB:
                        writer.close()
                        writer, (chunk, file), file_start = None, _next_file(chunk, file), frames
                if writer is None:
                    data_file = root / DATA_PATH.format(chunk_index=chunk, file_index=file)
                    data_file.parent.mkdir(parents=True, exist_ok=True)
                    writer = pq.ParquetWriter(data_file, schema, compression="snappy", use_dictionary=True)
                writer.write_table(table)
                stats = {k: _stats(values[k]) for k in features}
                episode_stats.append(stats)
                episode_rows.append({"episode_index": e, "tasks": [tasks[e]], "length": n, "data/chunk_index": chunk,
                                     "data/file_index": file, "dataset_from_index": frames,
                                     "dataset_to_index": frames + n, "stats": stats})
                frames += n
            if writer is not None:
                writer.close()
                writer = None
            _write_episodes(pa, pq, root, features, episode_rows)
            _write_tasks(pa, pq, root, task_list)
            _write_json(root / STATS_PATH, {k: {s: v.tolist() for s, v in _aggregate([st[k] for st in episode_stats])
                                                .items()} for k in features})
            _write_json(root / INFO_PATH, {
                "codebase_version": CODEBASE_VERSION, "robot_type": _robot_type(reader.attrs),
                "total_episodes": reader.n_episodes,
                "total_frames": frames, "total_tasks": len(task_list), "chunks_size": CHUNKS_SIZE,
                "data_files_size_in_mb": DATA_FILE_MB, "video_files_size_in_mb": VIDEO_FILE_MB, "fps": fps,
                "splits": {"train": f"0:{reader.n_episodes}"}, "data_path": DATA_PATH, "video_path": None,
                "features": features})
        except OSError as exc:
            raise DatasetError(f"cannot write {out} ({exc.strerror or exc}); choose a writable {flag}") from None
        finally:
            if writer is not None:  # an error or Ctrl-C half-way: the staged folder goes, its file is closed first
                writer.close()
        target.commit()
    return {"episodes": reader.n_episodes, "frames": frames, "fps": fps, "features": list(features)[:-5],
            "repo_id": repo_id, "notes": notes}


def _robot_type(attrs: dict) -> str | None:
    """The robot type a converted LeRobot dataset recorded (its ``lerobot`` attribute), else none."""
    source = attrs.get("lerobot")
    value = source.get("robot_type") if isinstance(source, dict) else None
    return value if isinstance(value, str) else None


def _write_json(path: Path, value) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(value, indent=4, ensure_ascii=False))


def _write_episodes(pa, pq, root: Path, features: dict, rows: list[dict]) -> None:
    """``meta/episodes/chunk-000/file-000.parquet``: one row per episode, the columns in LeRobot's order and types."""
    n = len(rows)

    def numbers(values, dtype):
        return _from_numpy(pa, np.asarray(values, dtype=dtype))

    columns = {"episode_index": numbers([r["episode_index"] for r in rows], np.int64)}
    tasks = [t for r in rows for t in r["tasks"]]
    offsets = np.concatenate([[0], np.cumsum([len(r["tasks"]) for r in rows])])
    columns["tasks"] = pa.ListArray.from_arrays(numbers(offsets, np.int32), _texts(pa, tasks))
    for key in ("length", "data/chunk_index", "data/file_index", "dataset_from_index", "dataset_to_index"):
        columns[key] = numbers([r[key] for r in rows], np.int64)
    for feature, spec in features.items():
        whole = np.issubdtype(np.dtype(spec["dtype"]), np.integer)
        for stat_key in rows[0]["stats"][feature]:
            integer = stat_key == "count" or stat_key in ("min", "max") and whole
            values = np.stack([r["stats"][feature][stat_key] for r in rows]).astype(np.int64 if integer else np.float64)
            columns[f"stats/{feature}/{stat_key}"] = _lists(pa, _from_numpy(pa, values), n, values.shape[1])
    columns["meta/episodes/chunk_index"] = columns["meta/episodes/file_index"] = numbers(np.zeros(n), np.int64)
    table = pa.Table.from_arrays(list(columns.values()), names=list(columns))
    path = root / EPISODES_DIR / CHUNK_FILE.format(chunk_index=0, file_index=0)
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(table, path, compression="snappy", use_dictionary=True)


def _write_tasks(pa, pq, root: Path, tasks: list[str]) -> None:
    """``meta/tasks.parquet``: task_index with the task texts as the pandas index (what LeRobot looks tasks up by)."""
    schema = pa.schema([pa.field("task_index", pa.int64()), pa.field("__index_level_0__", pa.large_string())],
                       metadata={"pandas": _pandas_index_metadata(pa)})
    table = pa.Table.from_arrays([_from_numpy(pa, np.arange(len(tasks), dtype=np.int64)), _texts(pa, tasks, large=True)],
                                 schema=schema)
    pq.write_table(table, root / TASKS_PATH, compression="snappy")
