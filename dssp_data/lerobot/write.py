"""A DP3 zarr dataset -> a new LeRobot v3 dataset (pyarrow and JSON; no lerobot, no torch).

    dssp-data export PATH --to lerobot --out DIR [--repo-id local/NAME] [--force]

Export (:func:`export`): the zarr dataset -> the layout of :mod:`dssp_data.lerobot.layout`: ``observation.state``,
``action``, ``observation.pointcloud`` float32 (P, C) and, when the dataset holds the ``depth`` extra and its
camera's attributes, ``observation.depth`` uint16 (H, W) with its intrinsics; ``fps`` is ``control_rate_hz``.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from dssp_core.errors import ConfigError, DatasetError
from dssp_core.output_guard import OutputDir, OutputKind, check_not_inside, check_output
from dssp_data import attributes
from dssp_data.lerobot.layout import (
    CHUNK_FILE,
    CHUNKS_SIZE,
    CODEBASE_VERSION,
    DATA_PATH,
    EPISODES_DIR,
    INDEX_FEATURES,
    INFO_PATH,
    INTRINSICS_KEYS,
    STATS_PATH,
    TASKS_PATH,
    feature_names,
    from_numpy,
    list_array,
    pyarrow_modules,
    text_array,
)
from dssp_data.observation import FRAME_ROBOT_BASE
from dssp_data.replay_buffer import ReplayBufferReader
from dssp_data.replay_buffer_writer import dataset_writer

__all__ = ["export", "LEROBOT_DATASET"]

DATA_FILE_MB = 100
"""A data file is closed before it grows past this (LeRobot's ``data_files_size_in_mb``)."""
VIDEO_FILE_MB = 200
QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)
QUANTILE_VALUES = 2_000_000
"""Quantiles of a feature in one episode are taken from at most this many values, evenly spaced rows."""
ARRAY2D = "datasets.features.features.Array2DExtensionType"
"""How the ``datasets`` library marks a 2-D array column (its extension type; the storage is lists of lists)."""

LEROBOT_DATASET = OutputKind("a LeRobot dataset", "dssp-data export", entries=("meta", "data"))
"""``dssp-data export --to lerobot --out DIR``: the folder holds meta/ and data/ (and the marker)."""


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
        mean += rows[start : start + step].sum(axis=0, dtype=np.float64)
    mean /= rows.shape[0]
    square = np.zeros(rows.shape[1])
    for start in range(0, rows.shape[0], step):
        square += ((rows[start : start + step].astype(np.float64) - mean) ** 2).sum(axis=0)
    stats = {
        "min": rows.min(axis=0),
        "max": rows.max(axis=0),
        "mean": mean,
        "std": np.sqrt(square / rows.shape[0]),
        "count": np.array([frames], dtype=np.int64),
    }
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
    out = {
        "min": np.min(np.stack([s["min"] for s in per_episode]), axis=0),
        "max": np.max(np.stack([s["max"] for s in per_episode]), axis=0),
        "mean": mean,
        "std": np.sqrt(variance),
        "count": total.astype(np.int64),
    }
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
    flat = from_numpy(pa, values)
    if shape == [1]:
        return flat
    if len(shape) == 1:
        return pa.FixedSizeListArray.from_arrays(flat, shape[0])
    rows, cols = shape
    n = values.shape[0]
    return list_array(pa, list_array(pa, flat, n * rows, cols), n, rows)


def _arrow_field(pa, key: str, feature: dict):
    shape, dtype = feature["shape"], pa.from_numpy_dtype(np.dtype(feature["dtype"]))
    if shape == [1]:
        return pa.field(key, dtype)
    if len(shape) == 1:
        return pa.field(key, pa.list_(pa.field("element", dtype), shape[0]))
    kind = pa.list_(pa.field("element", pa.list_(pa.field("element", dtype))))
    return pa.field(
        key,
        kind,
        metadata={
            "ARROW:extension:name": ARRAY2D,
            "ARROW:extension:metadata": json.dumps([list(shape), feature["dtype"]]),
        },
    )


def _features(reader: ReplayBufferReader, path: Path) -> tuple[dict, list[str]]:
    """The LeRobot features of the dataset (and the notes on what is left out)."""
    attrs, notes = reader.attrs, []
    (_, p, c), (_, s), (_, a) = (reader.arrays[f"data/{k}"][0] for k in ("point_cloud", "state", "action"))
    cloud_info = {
        k: v
        for k, v in (
            ("pointcloud", attributes.pointcloud(attrs, path)),
            ("frame", attrs.get("pointcloud_frame", FRAME_ROBOT_BASE) if attrs.get("pointcloud") is not None else None),
            ("camera_to_base", attributes.camera_to_base(attrs, path)),
        )
        if v is not None
    }
    convention = attributes.action_convention(attrs, path)
    features = {
        "observation.state": {"dtype": "float32", "shape": [s], "names": feature_names(attrs.get("state_layout"), s)},
        "action": {
            "dtype": "float32",
            "shape": [a],
            "names": feature_names(attrs.get("action_layout"), a),
            **({"info": {"convention": convention}} if convention else {}),
        },
        "observation.pointcloud": {
            "dtype": "float32",
            "shape": [p, c],
            "names": ["points", "xyz" if c == 3 else "xyzrgb"],
            **({"info": cloud_info} if cloud_info else {}),
        },
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
            raise DatasetError(
                f"{path}: data/depth frames are {shape[2]}x{shape[1]}, its camera_intrinsics say "
                f"{camera['width']}x{camera['height']}"
            )
        else:
            intrinsics = {k: camera[k] for k in INTRINSICS_KEYS[:6]}
            features["observation.depth"] = {
                "dtype": "uint16",
                "shape": list(shape[1:]),
                "names": ["height", "width"],
                "info": {"camera_intrinsics": {**intrinsics, "depth_unit": unit}},
            }
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
    return json.dumps(
        {
            "index_columns": ["__index_level_0__"],
            "column_indexes": [
                {
                    "name": None,
                    "field_name": None,
                    "pandas_type": "unicode",
                    "numpy_type": "object",
                    "metadata": {"encoding": "UTF-8"},
                }
            ],
            "columns": [
                {
                    "name": "task_index",
                    "field_name": "task_index",
                    "pandas_type": "int64",
                    "numpy_type": "int64",
                    "metadata": None,
                },
                {
                    "name": None,
                    "field_name": "__index_level_0__",
                    "pandas_type": "unicode",
                    "numpy_type": "object",
                    "metadata": None,
                },
            ],
            "attributes": {},
            "creator": {"library": "pyarrow", "version": pa.__version__},
        }
    ).encode()


def _next_file(chunk: int, file: int) -> tuple[int, int]:
    return (chunk + 1, 0) if file == CHUNKS_SIZE - 1 else (chunk, file + 1)


def _check_export(arguments: dict) -> None:
    check_not_inside(arguments["out"], [arguments["path"]], flag=arguments["flag"], error=DatasetError)
    check_output(
        arguments["out"], force=arguments["force"], kind=LEROBOT_DATASET, flag=arguments["flag"], error=DatasetError
    )


@dataset_writer(out=None, check=_check_export)
def export(path: Path, out: Path, *, repo_id: str | None = None, force: bool = False, flag: str = "--out") -> dict:
    """The DP3 zarr dataset at ``path`` -> a LeRobot v3 dataset at ``out`` (built beside it and moved into place);
    returns {"episodes", "frames", "fps", "features", "repo_id", "notes"}. It holds ``out``'s writer lock from the
    start; ``out`` is checked before the dataset is read."""
    pa, _, pq = pyarrow_modules()
    path, out = Path(path), Path(out)
    repo_id = _repo_id(repo_id, out)
    _check_export({"out": out, "path": path, "force": force, "flag": flag})
    reader = ReplayBufferReader(path)
    rate = reader.control_rate_hz
    if rate is None:
        raise DatasetError(
            f"{path} has no control_rate_hz attribute; a LeRobot dataset needs its frame rate (fps): "
            "record or convert the dataset with its control rate"
        )
    if abs(rate - round(rate)) > 1e-9:
        raise DatasetError(f"{path}: control_rate_hz is {rate:g}; LeRobot's fps is a whole number of frames per second")
    fps = int(round(rate))
    features, notes = _features(reader, path)
    tasks = _tasks(reader, path)
    task_list = list(dict.fromkeys(tasks))
    task_index = {t: i for i, t in enumerate(task_list)}
    with_depth = "observation.depth" in features
    schema = pa.schema(
        [_arrow_field(pa, k, f) for k, f in features.items()],
        metadata={"huggingface": json.dumps({"info": {"features": {k: _hf_feature(f) for k, f in features.items()}}})},
    )
    episode_rows, episode_stats = [], []
    with OutputDir(out, LEROBOT_DATASET, force=force, flag=flag, error=DatasetError) as target:
        root = target.path
        writer, data_file, chunk, file, file_start, frames = None, None, 0, 0, 0, 0
        try:
            for e in range(reader.n_episodes):
                episode = reader.episode(e, extras=["depth"] if with_depth else False)
                n = episode.n_steps
                values = {
                    "observation.state": episode.state,
                    "action": episode.action,
                    "observation.pointcloud": episode.point_cloud,
                    **({"observation.depth": episode.extras["depth"]} if with_depth else {}),
                    "timestamp": (np.arange(n) / fps).astype(np.float32),
                    "frame_index": np.arange(n, dtype=np.int64),
                    "episode_index": np.full(n, e, dtype=np.int64),
                    "index": np.arange(frames, frames + n, dtype=np.int64),
                    "task_index": np.full(n, task_index[tasks[e]], dtype=np.int64),
                }
                table = pa.Table.from_arrays(
                    [_arrow_column(pa, values[k], f) for k, f in features.items()], schema=schema
                )
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
                episode_rows.append(
                    {
                        "episode_index": e,
                        "tasks": [tasks[e]],
                        "length": n,
                        "data/chunk_index": chunk,
                        "data/file_index": file,
                        "dataset_from_index": frames,
                        "dataset_to_index": frames + n,
                        "stats": stats,
                    }
                )
                frames += n
            if writer is not None:
                writer.close()
                writer = None
            _write_episodes(pa, pq, root, features, episode_rows)
            _write_tasks(pa, pq, root, task_list)
            _write_json(
                root / STATS_PATH,
                {k: {s: v.tolist() for s, v in _aggregate([st[k] for st in episode_stats]).items()} for k in features},
            )
            _write_json(
                root / INFO_PATH,
                {
                    "codebase_version": CODEBASE_VERSION,
                    "robot_type": _robot_type(reader.attrs),
                    "total_episodes": reader.n_episodes,
                    "total_frames": frames,
                    "total_tasks": len(task_list),
                    "chunks_size": CHUNKS_SIZE,
                    "data_files_size_in_mb": DATA_FILE_MB,
                    "video_files_size_in_mb": VIDEO_FILE_MB,
                    "fps": fps,
                    "splits": {"train": f"0:{reader.n_episodes}"},
                    "data_path": DATA_PATH,
                    "video_path": None,
                    "features": features,
                },
            )
        except OSError as exc:
            raise DatasetError(f"cannot write {out} ({exc.strerror or exc}); choose a writable {flag}") from None
        finally:
            if writer is not None:  # an error or Ctrl-C half-way: the staged folder goes, its file is closed first
                writer.close()
        target.commit()
    return {
        "episodes": reader.n_episodes,
        "frames": frames,
        "fps": fps,
        "features": list(features)[:-5],
        "repo_id": repo_id,
        "notes": notes,
    }


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
        return from_numpy(pa, np.asarray(values, dtype=dtype))

    columns = {"episode_index": numbers([r["episode_index"] for r in rows], np.int64)}
    tasks = [t for r in rows for t in r["tasks"]]
    offsets = np.concatenate([[0], np.cumsum([len(r["tasks"]) for r in rows])])
    columns["tasks"] = pa.ListArray.from_arrays(numbers(offsets, np.int32), text_array(pa, tasks))
    for key in ("length", "data/chunk_index", "data/file_index", "dataset_from_index", "dataset_to_index"):
        columns[key] = numbers([r[key] for r in rows], np.int64)
    for feature, spec in features.items():
        whole = np.issubdtype(np.dtype(spec["dtype"]), np.integer)
        for stat_key in rows[0]["stats"][feature]:
            integer = stat_key == "count" or stat_key in ("min", "max") and whole
            values = np.stack([r["stats"][feature][stat_key] for r in rows]).astype(np.int64 if integer else np.float64)
            columns[f"stats/{feature}/{stat_key}"] = list_array(pa, from_numpy(pa, values), n, values.shape[1])
    columns["meta/episodes/chunk_index"] = columns["meta/episodes/file_index"] = numbers(np.zeros(n), np.int64)
    table = pa.Table.from_arrays(list(columns.values()), names=list(columns))
    path = root / EPISODES_DIR / CHUNK_FILE.format(chunk_index=0, file_index=0)
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(table, path, compression="snappy", use_dictionary=True)


def _write_tasks(pa, pq, root: Path, tasks: list[str]) -> None:
    """``meta/tasks.parquet``: task_index with the task texts as the pandas index (what LeRobot looks tasks up by)."""
    schema = pa.schema(
        [pa.field("task_index", pa.int64()), pa.field("__index_level_0__", pa.large_string())],
        metadata={"pandas": _pandas_index_metadata(pa)},
    )
    table = pa.Table.from_arrays(
        [from_numpy(pa, np.arange(len(tasks), dtype=np.int64)), text_array(pa, tasks, large=True)], schema=schema
    )
    pq.write_table(table, root / TASKS_PATH, compression="snappy")
