"""RoboTwin's raw HDF5 episodes -> a DP3 zarr dataset, as RoboTwin's ``policy/DP3/scripts/process_data.py`` does.

RoboTwin's collection writes one file per episode, ``<task>/<config>/data/episode<N>.hdf5``, holding
(T steps, 14 values = [left J1..J6, left gripper, right J1..J6, right gripper], joints in radians, grippers
0..1)::

    /joint_action/vector          (T, 14) float     the joint vector at each step
    /joint_action/left_arm        (T, 6), left_gripper (T,), right_arm (T, 6), right_gripper (T,)
    /pointcloud                   (T, N, 6) float   xyz (m) + rgb (0..1); empty when collected without clouds
    /observation/<camera>/...     images and camera matrices (not converted)

Conversion, per episode: ``state[t] = vector[t]`` and ``point_cloud[t] = pointcloud[t]`` for t < T - 1,
``action[t] = vector[t + 1]`` (the next absolute target): T - 1 steps. ``/joint_action/vector`` is used
when present, else it is assembled from the four arm/gripper arrays in that order.

A file that pulls in other files (an external link, external storage, a virtual dataset) is refused
before any data is read, naming the object; each dataset read must fit the read budget
(:mod:`dssp_data.bounded`), and its gzip-compressed chunks are checked to decode within their size.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from dssp_core.errors import DatasetError
from dssp_core.schema import check_rate
from dssp_data.bounded import ChunkTooLarge, check_budget, decompress, human_size, nbytes_of
from dssp_data.dataset_layout import Episode, as_float32
from dssp_data.edit import DATA_GENERATORS, ConvertedEpisode, check_converted_output, check_data_output, write_converted
from dssp_data.recording import ACTION_CONVENTIONS
from dssp_data.replay_buffer_writer import dataset_writer

PARTS = ("left_arm", "left_gripper", "right_arm", "right_gripper")
_NUMBER = re.compile(r"(\d+)")


def _h5py():
    try:
        import h5py  # optional: h5py (the train extra), only for RoboTwin's HDF5 episodes
    except ImportError:
        raise DatasetError("reading RoboTwin's HDF5 episodes needs h5py: pip install h5py") from None
    return h5py


def find_episodes(source: str | os.PathLike) -> list[Path]:
    """The episode files of ``source``: one .hdf5 file, or a directory holding ``episode*.hdf5`` (directly or
    in ``data/``), sorted by episode number."""
    source = Path(source)
    if source.is_file():
        return [source]
    if not source.is_dir():
        raise DatasetError(f"{source} does not exist: give a RoboTwin episode .hdf5 or its task directory")
    for folder in (source, source / "data"):
        files = [p for p in folder.glob("*.hdf5") if p.is_file()] if folder.is_dir() else []
        if files:

            def number(p: Path):
                m = _NUMBER.findall(p.stem)
                return (int(m[-1]) if m else -1, p.name)

            return sorted(files, key=number)
    raise DatasetError(
        f"no .hdf5 episodes in {source} or {source / 'data'}: point to RoboTwin's <task>/<config> directory"
    )


def check_self_contained(f, path: Path) -> None:
    """Refuse an HDF5 file that pulls in other files, before any data is read: an external link (an object
    of another file), a dataset with external storage (its values in other files: the dataset creation
    property ``external``) or a virtual dataset (mapped from other files). The line names the object."""
    h5py = _h5py()
    remedy = "convert only self-contained episode files (copy the data into the file itself)"

    def problem(name: str, link, node) -> str | None:
        if isinstance(link, h5py.ExternalLink):
            return f"/{name} is an external link to {link.filename}:{link.path}, another file"
        if not isinstance(node, h5py.Dataset):
            return None
        if node.is_virtual:
            return f"/{name} is a virtual dataset (its values are mapped from other files)"
        if node.id.get_create_plist().get_external_count() > 0:
            return f"/{name} keeps its values in external files (HDF5 external storage)"
        return None

    found, seen, groups = None, set(), [("", f)]
    try:
        while groups and found is None:  # every link of every group reached by hard links, none followed out
            prefix, group = groups.pop()
            for name in group:
                link = group.get(name, getlink=True)
                node = group.get(name) if isinstance(link, h5py.HardLink) else None  # soft links: checked at the target
                found = problem(prefix + name, link, node)
                if found:
                    break
                if isinstance(node, h5py.Group) and hash(node.id) not in seen:
                    seen.add(hash(node.id))
                    groups.append((f"{prefix}{name}/", node))
    except Exception as exc:  # h5py raises several types for a damaged file
        raise DatasetError(f"{path} is not a readable HDF5 file ({exc})") from None
    if found:
        raise DatasetError(f"{path}: {found}: {remedy}")


_FILTERS = {1: "deflate", 2: "shuffle", 3: "fletcher32"}
"""HDF5 filters whose decoded size is bounded here: deflate (gzip; checked chunk by chunk), and the byte
shuffle and checksum, which do not grow their input."""


def read_array(f, name: str, path: Path, dtype) -> np.ndarray:
    """The HDF5 dataset ``name`` of the open file ``f`` as ``dtype``, read within bounds.

    It must be a numeric dataset; its size (as stored and as ``dtype``) must fit the read budget
    (:func:`~dssp_data.bounded.read_budget`), and each compressed chunk must decode to no more than a
    chunk holds (a deflate bomb is refused before HDF5 decodes it); a filter other than deflate, shuffle
    and fletcher32 is refused by name. Anything else raises DatasetError naming the dataset."""
    h5py = _h5py()
    node = f.get(name)
    if not isinstance(node, h5py.Dataset):
        raise DatasetError(f"{path}: /{name} is not a dataset: not a RoboTwin episode")
    stored = node.dtype
    if not (np.issubdtype(stored, np.number) or stored == np.bool_):
        raise DatasetError(f"{path}: /{name} holds {stored}, not numbers: not a RoboTwin episode")
    need = nbytes_of(node.shape, stored) + (0 if stored == np.dtype(dtype) else nbytes_of(node.shape, dtype))
    check_budget(need, f"{path}: /{name} (shape {node.shape})", "convert smaller episode files")
    plist = node.id.get_create_plist()
    filters = [plist.get_filter(i)[0] for i in range(plist.get_nfilters())]
    for code in filters:
        if code not in _FILTERS:
            raise DatasetError(
                f"{path}: /{name} is compressed with the HDF5 filter {code}, whose decoded size this "
                f"reader cannot bound: re-save the episode uncompressed or with gzip"
            )
    if filters.count(1) > 1:
        raise DatasetError(
            f"{path}: /{name} is compressed twice with deflate: re-save the episode uncompressed or with gzip"
        )
    if 1 in filters and node.chunks is not None:
        chunk_nbytes = nbytes_of(node.chunks, stored)
        check_budget(
            chunk_nbytes,
            f"{path}: one chunk of /{name} (chunk shape {node.chunks})",
            "re-save the episode with smaller chunks",
        )
        deflate_bit = 1 << filters.index(1)
        for i in range(node.id.get_num_chunks()):
            info = node.id.get_chunk_info(i)
            if info.filter_mask & deflate_bit:
                continue  # stored without deflate: as large as it is on disk
            if info.size > 2 * chunk_nbytes + (1 << 16):
                raise DatasetError(
                    f"{path}: /{name} chunk {info.chunk_offset} is corrupt ({human_size(info.size)} "
                    f"stored, more than a chunk of {human_size(chunk_nbytes)} takes): re-save the episode"
                )
            _, raw = node.id.read_direct_chunk(info.chunk_offset)
            try:
                decompress("zlib", raw, chunk_nbytes)
            except ChunkTooLarge as exc:
                raise DatasetError(
                    f"{path}: /{name} chunk {info.chunk_offset} is corrupt ({exc}): re-save or leave out the episode"
                ) from None
            except Exception as exc:
                raise DatasetError(
                    f"{path}: /{name} chunk {info.chunk_offset} is corrupt (it does not decode: "
                    f"{exc}): re-save or leave out the episode"
                ) from None
    try:
        values = np.asarray(node[()])
    except Exception as exc:  # h5py raises OSError and others for damaged data
        raise DatasetError(f"{path}: /{name} cannot be read ({exc}): re-save or leave out the episode") from None
    if np.dtype(dtype) == np.float32:  # a value beyond float32 is refused by name, never cast to inf
        return as_float32(values, f"{path}: /{name}", "fix or leave out the episode")
    return values.astype(dtype)


def read_episode(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """(vector (T, D) float64, pointcloud (T, N, C) float32) of one RoboTwin episode file.

    The file is first checked to be self-contained (:func:`check_self_contained`); each dataset is read
    within bounds (:func:`read_array`)."""
    h5py = _h5py()
    path = Path(path)
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise DatasetError(f"{path} is not a readable HDF5 file ({exc})") from None
    with f:
        check_self_contained(f, path)
        if "joint_action/vector" in f:
            vector = read_array(f, "joint_action/vector", path, np.float64)
        elif all(f"joint_action/{k}" in f for k in PARTS):
            parts = [read_array(f, f"joint_action/{k}", path, np.float64) for k in PARTS]
            parts = [p.reshape(len(p), -1) for p in parts]
            vector = np.concatenate(parts, axis=1)
        else:
            raise DatasetError(
                f"{path}: no /joint_action/vector (nor left_arm, left_gripper, right_arm, right_gripper): "
                f"not a RoboTwin episode"
            )
        if "pointcloud" not in f:
            raise DatasetError(f"{path}: no /pointcloud: collect with data_type.pointcloud enabled in the task config")
        cloud = read_array(f, "pointcloud", path, np.float32)
    if vector.ndim != 2 or vector.shape[0] == 0:
        raise DatasetError(f"{path}: /joint_action/vector has shape {vector.shape}; expected (T, D)")
    if cloud.size == 0 or cloud.ndim != 3:
        raise DatasetError(
            f"{path}: /pointcloud is empty or not (T, N, C) (shape {cloud.shape}): the episode was "
            f"collected without point clouds (data_type.pointcloud)"
        )
    if cloud.shape[0] != vector.shape[0]:
        raise DatasetError(f"{path}: /pointcloud has {cloud.shape[0]} steps but the joint vector {vector.shape[0]}")
    if cloud.shape[2] not in (3, 6):
        raise DatasetError(
            f"{path}: /pointcloud points have {cloud.shape[2]} values; expected 3 (xyz) or 6 (xyz + rgb)"
        )
    return vector, cloud


def to_episode(vector: np.ndarray, cloud: np.ndarray, xyz_only: bool = False) -> Episode:
    """RoboTwin's convention: state = vector[:-1], action = vector[1:], point_cloud = cloud[:-1]."""
    if len(vector) < 2:
        raise DatasetError("an episode needs at least 2 steps (the action is the next step's joint vector)")
    points = cloud[:-1, :, :3] if xyz_only else cloud[:-1]
    vector = as_float32(vector, "/joint_action/vector", "fix or leave out the episode")
    return Episode(point_cloud=points, state=vector[:-1], action=vector[1:])


@dataset_writer(out=None, check=check_converted_output)
def convert(
    source: str | os.PathLike,
    out: str | os.PathLike,
    *,
    max_episodes: int | None = None,
    xyz_only: bool = False,
    control_rate_hz: float | None = None,
    task: str | None = None,
    force: bool = False,
    progress=None,
    flag: str = "--out",
) -> dict:
    """Convert RoboTwin episodes from ``source`` into the DP3 dataset ``out`` (written whole, then renamed).

    ``out`` must be new, or a dataset ``dssp-data`` made (replaced only with ``force``); anything else is
    refused and nothing is deleted (:data:`~dssp_data.edit.DATA_DATASET`). The dataset is
    written into a staging directory beside ``out``, removed on an error or Ctrl-C. Its ``generator``
    attribute is ``dssp-data convert``. Returns {"episodes": n, "steps": n, "files": [names]}.
    ``progress(i, n, path)`` is called per file. It holds ``out``'s writer lock from the start
    (:func:`~dssp_data.replay_buffer_writer.dataset_writer`), and ``out`` may not be ``source``, lie inside it or
    hold it (:func:`~dssp_data.edit.check_data_output`).
    """
    if control_rate_hz is not None:
        check_rate(control_rate_hz, "--control-rate")
    out = Path(out)
    check_data_output(out, [source], force, flag)  # before the input is read: never into it, never over foreign data
    files = find_episodes(source)
    if max_episodes is not None:
        if max_episodes < 1:
            raise DatasetError(f"--episodes must be at least 1, got {max_episodes}")
        files = files[:max_episodes]
    attrs = {
        "generator": DATA_GENERATORS["convert"],
        "source_format": "RoboTwin raw HDF5",
        "source": str(source),
        "action_convention": ACTION_CONVENTIONS["next_state"],
        "state_convention": "RoboTwin joint vector [left J1..J6 rad, left gripper 0..1, right J1..J6, right gripper]",
        "converted_from": [p.name for p in files],
    }
    if control_rate_hz is not None:
        attrs["control_rate_hz"] = float(control_rate_hz)
    if task:
        attrs["task"] = task

    def episodes():
        for i, path in enumerate(files):
            if progress is not None:
                progress(i, len(files), path)
            vector, cloud = read_episode(path)
            try:
                episode = to_episode(vector, cloud, xyz_only)
            except DatasetError as exc:
                raise DatasetError(f"{path}: {exc}") from None
            yield ConvertedEpisode(str(path), episode)

    steps = write_converted(out, attrs, episodes(), force=force, flag=flag)
    return {"episodes": len(files), "steps": steps, "files": [p.name for p in files]}
