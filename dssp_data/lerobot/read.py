"""A LeRobot v3 dataset -> a new DP3 zarr dataset (pyarrow and JSON; no lerobot, no torch).

    dssp-data convert LEROBOT_ROOT --out OUT.zarr --extrinsics calib.json [--pointcloud FILE] [--depth-key K]
                      [--state-key observation.state] [--action-key action]

Import (:func:`convert`): one DP3 episode per LeRobot episode; each frame's depth becomes the cloud by the robot's
pipeline (:func:`dssp_data.pointcloud.frame_to_cloud`, float32 metres first quantised to ``depth_unit``, 1 mm when
not given); state and action are the two features; ``fps`` is ``control_rate_hz``. Refused with one line and
nothing written: a dataset that is not v3, one without a depth feature or its intrinsics (checked by
:class:`~dssp_data.pointcloud.depth_frame.Intrinsics`), video-encoded depth (lossy), missing or misshapen
state/action, a value beyond float32 (named with its file, episode, key, frame and value), an ``fps`` outside the
control rates, a file path from ``meta/info.json`` that leads outside the root (an absolute path, ``..``, a link) or
whose template asks for other fields or formats, an output that is the root, lies inside it or holds it. Every
parquet file and episode is checked against the read budget before it is read or allocated
(:func:`~dssp_data.lerobot.layout.read_parquet`). The layout and where a depth feature's camera is:
:mod:`dssp_data.lerobot.layout`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dssp_core.errors import ConfigError, DatasetError
from dssp_data import attributes
from dssp_data.bounded import check_budget
from dssp_data.dataset_layout import Episode, as_float32
from dssp_data.edit import DATA_GENERATORS, ConvertedEpisode, check_converted_output, check_data_output, write_converted
from dssp_data.lerobot.layout import (
    EPISODES_DIR,
    INDEX_FEATURES,
    INFO_PATH,
    INTRINSICS_KEYS,
    data_file,
    feature_layout,
    from_numpy,
    named_path,
    numpy_column,
    pyarrow_modules,
    read_info,
    read_parquet,
)
from dssp_data.observation import FRAME_ROBOT_BASE, ObservationContract, PointCloudConfig
from dssp_data.pointcloud import EmptyCloudError, frame_to_cloud, validate_extrinsics
from dssp_data.pointcloud.depth_frame import DepthFrame, Intrinsics
from dssp_data.replay_buffer_writer import dataset_writer

__all__ = ["convert"]

DEFAULT_DEPTH_UNIT = 0.001
"""Metres per count that float32 depth in metres is quantised to when its intrinsics give no ``depth_unit``."""
DEPTH_DTYPES = ("uint16", "float32", "float64")
VECTOR_DTYPES = ("float32", "float64", "float16", "int8", "int16", "int32", "int64", "uint8", "uint16", "uint32")
ACTION_CONVENTION = (
    "lerobot_action: the LeRobot dataset's action feature at this frame (what was commanded to the robot at that frame)"
)
TIME_KEYS = ("timestamp",)


# ------------------------------------------------------------------------------------------- the features
@dataclass(frozen=True)
class DepthFeature:
    """A dataset's depth feature: its key, dtype (uint16 counts or float32 metres), camera and metres per count."""

    key: str
    dtype: str
    intrinsics: Intrinsics
    depth_unit: float


def _feature(features: dict, key: str, flag: str, what: str, root: Path) -> dict:
    if key not in features:
        raise DatasetError(
            f"{root}: no feature {key!r} in {INFO_PATH} (it has {', '.join(features)}); name the "
            f"{what} feature with {flag}"
        )
    return features[key]


def _vector_feature(features: dict, key: str, flag: str, what: str, root: Path) -> int:
    feature = _feature(features, key, flag, what, root)
    if feature["dtype"] not in VECTOR_DTYPES or len(feature["shape"]) != 1:
        raise DatasetError(
            f"{root}: feature {key} is {feature['dtype']} {feature['shape']}; the {what} must be a "
            f"vector of numbers (shape [N]); name another with {flag}"
        )
    return int(feature["shape"][0])


def depth_feature(features: dict, key: str | None, root: Path) -> DepthFeature:
    """The dataset's depth feature ``key`` (None: the one feature named like depth or carrying camera intrinsics),
    checked: its dtype and shape, its ``info.camera_intrinsics``; a DatasetError line otherwise. Shared with the
    LeRobot policy plugin, which builds the same clouds while training."""
    if key is None:
        found = [
            k
            for k, f in features.items()
            if k not in INDEX_FEATURES
            and ("depth" in k.lower() or isinstance(f.get("info"), dict) and "camera_intrinsics" in f["info"])
        ]
        if not found:
            raise DatasetError(
                f"{root}: no depth feature (its features are {', '.join(features)}); the clouds are "
                "made from a uint16 (H, W) depth feature with info.camera_intrinsics: name it with "
                "--depth-key"
            )
        if len(found) > 1:
            raise DatasetError(f"{root}: several depth features ({', '.join(found)}); choose one with --depth-key")
        key = found[0]
    feature = _feature(features, key, "--depth-key", "depth", root)
    dtype, shape = feature["dtype"], feature["shape"]
    if dtype in ("video", "image"):
        raise DatasetError(
            f"{root}: {key} is stored as {dtype}; depth in a {dtype} is not supported (the codecs are "
            "lossy or 8-bit): store it as a uint16 (H, W) array feature"
        )
    if dtype not in DEPTH_DTYPES or not (len(shape) == 2 or len(shape) == 3 and shape[2] == 1):
        raise DatasetError(
            f"{root}: {key} is {dtype} {shape}; depth must be a uint16 (counts) or float32 (metres) "
            "array of shape [H, W]"
        )
    info = feature.get("info")
    camera = info.get("camera_intrinsics") if isinstance(info, dict) else None
    where = f"{root}: {key}'s info.camera_intrinsics"
    if not isinstance(camera, dict):
        raise DatasetError(
            f"{root}: {key} has no camera intrinsics; add info.camera_intrinsics = {{fx, fy, ppx, ppy, "
            f"width, height, depth_unit}} to its entry in {INFO_PATH}"
        )
    unknown = sorted(set(camera) - set(INTRINSICS_KEYS))
    missing = [k for k in INTRINSICS_KEYS[:6] if k not in camera]
    if dtype == "uint16" and "depth_unit" not in camera:
        missing.append("depth_unit")
    if missing or unknown:
        raise DatasetError(
            f"{where} {'lacks ' + ', '.join(missing) if missing else 'has unknown ' + ', '.join(unknown)}"
            f" (it needs {', '.join(INTRINSICS_KEYS)}: pixels, and metres per depth count)"
        )
    try:
        intrinsics = Intrinsics(*(camera[k] for k in ("width", "height", "fx", "fy", "ppx", "ppy")))
    except ConfigError as exc:
        raise DatasetError(f"{where}: {exc}") from None
    if [intrinsics.height, intrinsics.width] != list(shape[:2]):
        raise DatasetError(
            f"{where} says {intrinsics.width}x{intrinsics.height}; the feature's shape is {shape} (height, width)"
        )
    unit = camera.get("depth_unit", DEFAULT_DEPTH_UNIT)
    if isinstance(unit, bool) or not isinstance(unit, (int, float)) or not (math.isfinite(unit) and 0 < unit <= 1):
        raise DatasetError(f"{where}: depth_unit is {unit!r}; it must be metres per count in (0, 1]")
    return DepthFeature(key, dtype, intrinsics, float(unit))


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
    folder = named_path(root, EPISODES_DIR, "the episodes folder", folder=True)
    files = sorted(folder.glob("*/*.parquet"))
    if not files:
        raise DatasetError(f"{root}: {EPISODES_DIR}/ holds no parquet file; not a complete v3 dataset")
    columns = ["episode_index", "length", "data/chunk_index", "data/file_index", "tasks"]
    refs = []
    for path in files:
        path = named_path(root, str(path.relative_to(root)), "the episodes file")
        table = read_parquet(pa, pq, path, columns)
        rows = {c: table.column(c).to_pylist() for c in columns}
        for i in range(table.num_rows):
            values = [rows[c][i] for c in columns[:4]]
            tasks = rows["tasks"][i]
            if not all(isinstance(v, int) and v >= 0 for v in values) or values[1] < 1:
                raise DatasetError(
                    f"{path}: row {i} has an invalid episode_index, length or data file index "
                    f"({dict(zip(columns[:4], values))})"
                )
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


def quantised(depth: np.ndarray, unit: float) -> np.ndarray:
    """Depth in metres -> uint16 counts of ``unit`` (NaN, infinite, negative or out-of-range values: 0, no
    measurement)."""
    with np.errstate(invalid="ignore", over="ignore"):
        counts = np.rint(np.asarray(depth, dtype=np.float64) / unit)
    bad = ~np.isfinite(counts) | (counts < 0) | (counts > 65535)
    counts[bad] = 0
    return counts.astype(np.uint16)


@dataset_writer(out=None, check=check_converted_output)
def convert(
    source: Path,
    out: Path,
    cloud_config: PointCloudConfig,
    camera_to_base: np.ndarray,
    *,
    depth_key: str | None = None,
    state_key: str = "observation.state",
    action_key: str = "action",
    max_episodes: int | None = None,
    task: str | None = None,
    force: bool = False,
    progress: Callable | None = None,
    flag: str = "--out",
) -> dict:
    """The LeRobot v3 dataset at ``source`` -> a new DP3 zarr dataset at ``out`` (one episode per LeRobot episode,
    clouds by the robot's pipeline), written in a staging folder and moved into place at the end; returns
    {"episodes", "steps", "fps", "depth_key", "state_key", "action_key"}. It holds ``out``'s writer lock from the
    start, and ``out`` may not be ``source``, lie inside it or hold it."""
    pa, pc, pq = pyarrow_modules()
    camera_to_base = validate_extrinsics(np.asarray(camera_to_base, dtype=np.float64))
    if cloud_config.use_color:
        raise ConfigError(
            "--pointcloud asks for colour (use_color): the clouds of a LeRobot dataset are made from its "
            "depth feature only; set use_color false"
        )
    root, out = Path(source), Path(out)
    check_data_output(out, [root], force, flag)  # before the input is read: never into it, never over foreign data
    info = read_info(root)
    features = info["features"]
    depth = depth_feature(features, depth_key, root)
    state_dim = _vector_feature(features, state_key, "--state-key", "state", root)
    action_dim = _vector_feature(features, action_key, "--action-key", "action", root)
    refs = _episode_refs(pa, pq, root)
    if max_episodes is not None:
        if max_episodes < 1:
            raise DatasetError(f"--episodes must be at least 1, got {max_episodes}")
        refs = refs[:max_episodes]
    data_files = {(r.chunk, r.file): data_file(root, info.get("data_path"), r.chunk, r.file) for r in refs}

    fps = float(info["fps"])
    action_info = features[action_key].get("info")
    convention = action_info.get("convention") if isinstance(action_info, dict) else None
    if not _is_convention(convention):  # what dssp-data export wrote, else LeRobot's meaning of action
        convention = ACTION_CONVENTION
    contract = ObservationContract(
        pointcloud=cloud_config,
        frame=FRAME_ROBOT_BASE,
        state=feature_layout(features[state_key], state_dim),
        action=feature_layout(features[action_key], action_dim),
    )
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
        "lerobot": {
            "codebase_version": info["codebase_version"],
            "robot_type": info.get("robot_type"),
            "fps": info["fps"],
            "depth": depth.key,
            "state": state_key,
            "action": action_key,
            **({"depth_dtype": depth.dtype} if depth.dtype != "uint16" else {}),
        },
        "episode_tasks": tasks,
        **({"task": task} if task else {"task": tasks[0]} if len(set(tasks)) == 1 else {}),
    }
    columns = ["episode_index", "frame_index", state_key, action_key, depth.key] + (
        ["timestamp"] if "timestamp" in features else []
    )
    shape = tuple(features[depth.key]["shape"])

    def episodes():
        table, loaded = None, None
        for i, ref in enumerate(refs):
            if progress is not None:
                progress(i, len(refs), Path(f"episode_{ref.index:06d}"))
            path = data_files[(ref.chunk, ref.file)]
            if loaded != path:  # one data file in memory at a time
                table, loaded = None, None
                table, loaded = read_parquet(pa, pq, path, columns), path
            yield ConvertedEpisode(
                None,
                _episode(
                    pa,
                    pc,
                    table,
                    ref,
                    path,
                    depth,
                    shape,
                    state_key,
                    state_dim,
                    action_key,
                    action_dim,
                    fps,
                    cloud_config,
                    camera_to_base,
                ),
            )

    steps = write_converted(out, attrs, episodes(), extra_keys=("depth", *TIME_KEYS), force=force, flag=flag)
    return {
        "episodes": len(refs),
        "steps": steps,
        "fps": fps,
        "depth_key": depth.key,
        "state_key": state_key,
        "action_key": action_key,
    }


def _episode(
    pa,
    pc,
    table,
    ref: _EpisodeRef,
    path: Path,
    depth: DepthFeature,
    shape: tuple[int, ...],
    state_key: str,
    state_dim: int,
    action_key: str,
    action_dim: int,
    fps: float,
    cloud_config: PointCloudConfig,
    camera_to_base: np.ndarray,
) -> Episode:
    """One LeRobot episode's rows of ``table`` -> an Episode (clouds by the robot's pipeline)."""
    where = f"{path} (episode {ref.index})"
    pixels = shape[0] * shape[1]
    per_frame = (
        pixels * (2 + 2 + (8 if depth.dtype != "uint16" else 0))
        + 8 * (state_dim + action_dim)
        + 16
        + 2 * cloud_config.n_points * cloud_config.point_dim * 4
    )
    check_budget(
        ref.length * per_frame,
        f"{where}: {ref.length} frames of {shape[1]}x{shape[0]} depth",
        "convert a dataset with shorter episodes",
    )
    episodes = numpy_column(pa, pc, table, "episode_index", (1,), where).reshape(-1)
    rows = np.flatnonzero(episodes == ref.index)
    if rows.size != ref.length:
        raise DatasetError(f"{where}: {rows.size} frames where {EPISODES_DIR}/ says {ref.length}")
    part = table.take(from_numpy(pa, rows))
    order = np.argsort(numpy_column(pa, pc, part, "frame_index", (1,), where).reshape(-1), kind="stable")
    part = part.take(from_numpy(pa, order))
    frames = numpy_column(pa, pc, part, "frame_index", (1,), where).reshape(-1)
    if not np.array_equal(frames, np.arange(ref.length)):
        raise DatasetError(f"{where}: the frame_index values are not 0..{ref.length - 1}, each once")
    remedy = "fix or leave out the episode"
    state = as_float32(
        numpy_column(pa, pc, part, state_key, (state_dim,), where), f"{where}: {state_key}", remedy, "frame"
    )
    action = as_float32(
        numpy_column(pa, pc, part, action_key, (action_dim,), where), f"{where}: {action_key}", remedy, "frame"
    )
    raw = numpy_column(pa, pc, part, depth.key, shape, where).reshape(ref.length, shape[0], shape[1])
    if raw.dtype != np.dtype(depth.dtype):
        raise DatasetError(
            f"{where}: {depth.key} is stored as {raw.dtype}; its feature in {INFO_PATH} says {depth.dtype}"
        )
    counts = raw.astype(np.uint16) if depth.dtype == "uint16" else quantised(raw, depth.depth_unit)
    if "timestamp" in part.column_names:
        times = numpy_column(pa, pc, part, "timestamp", (1,), where).reshape(-1).astype(np.float64)
    else:
        times = np.arange(ref.length) / fps
    clouds = np.empty((ref.length, cloud_config.n_points, cloud_config.point_dim), np.float32)
    for k in range(ref.length):
        frame = DepthFrame(
            depth=counts[k],
            depth_unit=depth.depth_unit,
            intrinsics=depth.intrinsics,
            timestamp=float(times[k]),
            frame_number=k,
        )
        try:
            clouds[k], _ = frame_to_cloud(frame, cloud_config, camera_to_base)
        except EmptyCloudError as exc:
            raise DatasetError(
                f"{where}: the depth frame {k} has no point in the workspace ({exc}); check "
                "--extrinsics and the crop of --pointcloud"
            ) from None
    return Episode(point_cloud=clouds, state=state, action=action, extras={"depth": counts, "timestamp": times})
