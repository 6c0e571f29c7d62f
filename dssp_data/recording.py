"""What a recorded dataset (``dssp-record``) holds beyond DP3's arrays, and :class:`RecordingDataset`,
which appends recorded episodes to it crash-safely.

On disk, next to DP3's ``data/point_cloud`` (T, P, C), ``data/state`` (T, S) and ``data/action`` (T, A)::

    data/timestamp            (T,) float64  s since the episode's first tick: when the step was sampled
    data/camera_timestamp     (T,) float64  s, same origin (negative: before the first step): arrival of the
                                            camera frame the cloud is made from
    data/state_timestamp      (T,) float64  s: arrival of the oldest follower feedback frame in ``state``
    data/action_timestamp     (T,) float64  s: arrival of the oldest leader frame in ``action``
                                            (next-state convention: the next step's state_timestamp)
    data/camera_frame         (T,) int64    the camera's frame number (a repeat means no new frame)
    data/step_problems        (T,) uint8    bit flags, :data:`STEP_PROBLEMS`
    data/depth                (T, H, W) uint16, optional: the raw depth image (metres = value *
                                            camera_depth_unit), to rebuild the clouds with other settings
    meta/episode_ends         (E,) int64

Root attributes: ``control_rate_hz``, ``action_convention`` (:data:`ACTION_CONVENTIONS`),
``state_convention``, ``camera_to_base`` (4x4), ``camera_intrinsics``, ``camera_depth_unit``,
``pointcloud`` (the :class:`~dssp_data.observation.PointCloudConfig`), ``state_layout``, ``action_layout``
(:class:`~dssp_data.observation.VectorLayout`), ``task``, ``generator``;
``recording_sessions`` (one entry per recording session that kept an episode: devices, calibration,
thresholds) and ``episode_info`` (one entry per episode, or null for episodes that were not recorded:
session, start time, measured rate, stream ages, problems, CAN log files). ``episode_info`` is written
before the episode's data, so after a crash it may hold one entry more than there are episodes: read it
with :func:`episode_infos`.

Raw CAN traffic of each kept episode: ``<dataset>.can/episode_000012.can0.blf`` (one per bus), written
as ``...partial-<session>.blf`` while recording and renamed when the episode is kept. ``episode_info``
names them (``can_logs``: {bus: file name}); a name read from a dataset is used only through
:func:`can_log_path`, which refuses anything that does not stay inside that folder.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from dssp_core.errors import ConfigError, DatasetError
from dssp_core.staging import WriterLock
from dssp_data import attributes
from dssp_data.dataset_layout import Episode
from dssp_data.observation import ObservationContract, check_contract
from dssp_data.replay_buffer_writer import DATASET_WRITERS, DatasetWriter, ReplayBufferWriter, dataset_lock

TIME_KEYS = ("timestamp", "camera_timestamp", "state_timestamp", "action_timestamp")
FRAME_KEY = "camera_frame"
FLAGS_KEY = "step_problems"
DEPTH_KEY = "depth"
RECORDED_KEYS = TIME_KEYS + (FRAME_KEY, FLAGS_KEY)
"""Extras every recorded episode carries (``depth`` is optional)."""

STEP_PROBLEMS = {
    "camera_stale": 1,  # the newest frame was older than the camera threshold
    "camera_repeat": 2,  # no new frame since the previous step (a dropped frame)
    "feedback_stale": 4,  # the follower's newest joint/gripper feedback was older than its threshold
    "leader_stale": 8,  # the leader's newest command was older than its threshold
    "late_tick": 16,  # the step was sampled later than half a period after its schedule
    "empty_cloud": 32,  # no point in the crop box: the previous step's cloud was repeated
    "arm_error": 64,  # the follower reported an error or e-stop
}
"""Bit of each per-step problem in ``data/step_problems``."""

PROBLEM_TEXT = {
    "camera_stale": "stale camera",
    "camera_repeat": "dropped camera frames",
    "feedback_stale": "missing follower feedback",
    "leader_stale": "missing leader commands",
    "late_tick": "late ticks",
    "empty_cloud": "empty point clouds",
    "arm_error": "arm error",
    "rate": "control rate off target",
}

ACTION_CONVENTIONS = {
    "leader_command": "leader_command: the leader arm's joint/gripper target at this step (policy units)",
    "next_state": "next_state: the follower's measured state at the next step (RoboTwin's convention; "
    "the last step of each episode is dropped)",
}
STATE_CONVENTION = "follower's measured [J1..J6 rad, gripper opening 0..1] per arm (left, right)"


def problem_names(flags: int) -> list[str]:
    """Names of the problems set in one step's flags."""
    return [name for name, bit in STEP_PROBLEMS.items() if int(flags) & bit]


def convention_name(attrs: Mapping, where=None) -> str | None:
    """The action convention's short name from a dataset's attributes (None if not recorded).

    Raises DatasetError (naming ``where``, the dataset) when ``action_convention`` is not a text."""
    return attributes.convention_name(attrs, where)


def episode_infos(attrs: Mapping, n_episodes: int, where=None) -> list[dict | None]:
    """``attrs["episode_info"]`` aligned with the dataset's ``n_episodes`` episodes.

    Entries beyond the last episode (left by a crash during an append) are dropped; missing ones are None.
    An ``episode_info`` that is not a list of objects (or nulls) raises DatasetError naming ``where``.
    """
    raw = attributes.episode_info(attrs, where) or []
    infos = [dict(entry) if entry is not None else None for entry in raw[:n_episodes]]
    return infos + [None] * (n_episodes - len(infos))


def can_log_dir(dataset: str | os.PathLike) -> Path:
    """Directory of a dataset's CAN logs: ``<dataset>.can`` next to it."""
    dataset = Path(dataset)
    return dataset.with_name(dataset.name + ".can")


def can_log_path(dataset: str | os.PathLike, name, episode: int | None = None) -> Path:
    """The CAN log that a dataset's ``episode_info[episode].can_logs`` names: ``can_log_dir(dataset) / name``.

    The name is read from the dataset, so it must stay inside the dataset's CAN-log folder: a relative
    path without ``..`` that still lies inside the folder with symbolic links resolved, in a folder that is
    not itself a link. Anything else (an absolute path, ``../../etc/passwd``, a link leading out, a linked
    folder) raises DatasetError; nothing is read. Files are copied out of it only as regular files
    (:func:`~dssp_core.files.copy_regular_file`: no link followed).
    """
    folder = can_log_dir(dataset)
    what = f"{dataset}: episode_info[{'?' if episode is None else episode}].can_logs"
    remedy = f"a dataset may only name files in {folder.name}/; fix episode_info or leave the episode out"
    if not isinstance(name, str) or not name.strip() or "\0" in name:
        raise DatasetError(f"{what} names {name!r}, not a file name: {remedy}")
    relative = Path(name)
    if relative.is_absolute() or ".." in relative.parts:
        raise DatasetError(f"{what} names {name!r}, a path outside the CAN-log folder {folder}: {remedy}")
    if folder.is_symlink():
        raise DatasetError(
            f"{what} names {name!r} in {folder}, which is a symbolic link (it may lead anywhere): {remedy}"
        )
    path = folder / relative
    base, real = os.path.realpath(folder), os.path.realpath(path)
    if real == base or os.path.commonpath([base, real]) != base:
        raise DatasetError(
            f"{what} names {name!r}, which leads outside the CAN-log folder {folder} (a symbolic link?): {remedy}"
        )
    return path


def episode_can_logs(dataset: str | os.PathLike, info: Mapping | None, episode: int) -> dict[str, Path]:
    """{bus: path} of the CAN logs an ``episode_info`` entry names, each checked by :func:`can_log_path`
    (the files need not exist)."""
    logs = (info or {}).get("can_logs") or {}
    if not isinstance(logs, Mapping):
        raise DatasetError(
            f"{dataset}: episode_info[{episode}].can_logs is {type(logs).__name__}, not an object "
            f"{{bus: file name}}: fix episode_info or leave the episode out"
        )
    return {str(bus): can_log_path(dataset, name, episode) for bus, name in logs.items()}


def _channel_tag(channel: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in channel) or "bus"


def can_log_name(index: int, channel: str) -> str:
    """File name of episode ``index``'s log of bus ``channel``."""
    return f"episode_{index:06d}.{_channel_tag(channel)}.blf"


def partial_can_log_name(index: int, channel: str, session: str) -> str:
    """File name of that log while the episode is being recorded (session: a unique tag)."""
    return f"episode_{index:06d}.{_channel_tag(channel)}.partial-{session}.blf"


LOCK_NAME = ".recording.lock"
"""The lock file older versions kept in a dataset's CAN-log folder (now the dataset's writer lock,
:func:`~dssp_data.replay_buffer_writer.dataset_lock`, ``.NAME.lock`` beside the dataset; a stale one is ignored)."""


def check_can_log_dir(dataset: str | os.PathLike) -> None:
    """The CAN-log folder of ``dataset``, where a recording session writes, is absent or a real folder holding
    only regular files: a symbolic link there (the folder, or a file in it) would have the logs written, renamed
    or copied through it elsewhere. Anything else raises DatasetError naming it (nothing is written)."""
    folder = can_log_dir(dataset)
    if folder.is_symlink() or (folder.exists() and not folder.is_dir()):
        raise DatasetError(
            f"{folder} is {'a symbolic link' if folder.is_symlink() else 'not a folder'}: a dataset's "
            f"CAN logs are kept in a real folder beside it; move it away (nothing was written)"
        )
    if not folder.exists():
        return
    for entry in os.scandir(folder):
        if entry.is_symlink() or not (entry.is_file(follow_symlinks=False) or entry.is_dir(follow_symlinks=False)):
            kind = "a symbolic link" if entry.is_symlink() else "not a regular file"
            raise DatasetError(
                f"{folder}: {entry.name} is {kind}: a dataset's CAN logs must be its own files; "
                f"move it away (nothing was written)"
            )


def _same_number(a, b) -> bool:
    try:
        return math.isclose(float(a), float(b), rel_tol=1e-9, abs_tol=1e-12)
    except (TypeError, ValueError):
        return False


class RecordingDataset:
    """Appends recorded episodes to a new or existing dataset, one crash-safe append each.

    ``dataset_attrs``: the root attributes a new dataset starts with (rate, conventions, calibration);
    for an existing dataset the ones that decide what the data means (``control_rate_hz``,
    ``action_convention``, ``pointcloud``) must match, else DatasetError. ``session``: this recording
    session's description (devices, calibration, thresholds), stored in ``recording_sessions`` with
    its first kept episode. ``extra_keys``: the per-step extras each episode brings.

    An existing dataset whose last append was interrupted (steps after the last episode end) is
    repaired on opening: :attr:`repaired_steps` says how many steps were cut off.

    The session holds the dataset's writer lock (:func:`~dssp_data.replay_buffer_writer.dataset_lock`) until
    :meth:`close`: a second session, a ``dssp-sim collect`` or a ``dssp-data repair`` of the same dataset is
    refused with one line. The dataset's folder and its CAN-log folder may hold no symbolic link
    (:func:`~dssp_data.zarr_chunks.check_dataset_tree`, :func:`check_can_log_dir`).
    """

    def __init__(
        self,
        path: str | os.PathLike,
        dataset_attrs: dict,
        session: dict,
        extra_keys: Sequence[str],
        lock: WriterLock | None = None,
    ):
        """``lock``: the dataset's writer lock when the caller took it already (``dssp-record`` takes it before
        it opens any device); it is released by :meth:`close` too."""
        self.path = Path(path)
        self.session = dict(session)
        self.session_added = False
        self._lock = lock if lock is not None else dataset_lock(self.path, flag="--out", doing="recorded into")
        try:
            check_can_log_dir(self.path)
            self.writer = ReplayBufferWriter(
                self.path, attrs=None, repair_incomplete_tail=True, extra_keys=extra_keys, lock=False
            )
            self.repaired_steps = self.writer.dropped_tail_steps
            self.new = self.writer.n_episodes == 0  # an existing dataset holds at least one episode
            if self.new:
                self.writer.close()
                self.writer = ReplayBufferWriter(self.path, attrs=dataset_attrs, extra_keys=extra_keys, lock=False)
            else:
                self._check_compatible(self.writer.attrs, dataset_attrs)
        except BaseException:
            self._lock.release()
            raise
        self.calibration_changed = not self.new and self._calibration_differs(self.writer.attrs, dataset_attrs)

    def _check_compatible(self, existing: Mapping, wanted: Mapping) -> None:
        where = str(self.path)
        for message in attributes.attribute_problems(existing, where).values():
            raise DatasetError(message)
        if not _same_number(existing.get("control_rate_hz"), wanted.get("control_rate_hz")):
            raise DatasetError(
                f"{where} was recorded at {existing.get('control_rate_hz')} Hz, this session runs at "
                f"{wanted.get('control_rate_hz')} Hz: record at the dataset's rate (--control-rate) or into a new dataset"
            )
        if convention_name(existing) != convention_name(wanted):
            raise DatasetError(
                f"{where} uses the action convention {convention_name(existing)!r}, this session "
                f"{convention_name(wanted)!r}: use the same --action or a new dataset"
            )
        try:
            check_contract(
                ObservationContract.from_attrs(existing, where),
                ObservationContract.from_attrs(wanted, "this session"),
                trained_by=where,
                given_by="this session",
                remedy="record with the dataset's settings (leave out --pointcloud) or into a new dataset",
            )
        except ConfigError as exc:
            raise DatasetError(str(exc)) from None
        if (existing.get("pointcloud") is None) != (wanted.get("pointcloud") is None):
            raise DatasetError(f"{where} records no point-cloud settings: record into a new dataset")

    @staticmethod
    def _calibration_differs(existing: Mapping, wanted: Mapping) -> bool:
        keys = ("camera_to_base", "camera_intrinsics", "camera_depth_unit")
        return any(existing.get(k) != wanted.get(k) for k in keys)

    @property
    def n_episodes(self) -> int:
        """Episodes in the dataset; also the index the next kept episode gets."""
        return self.writer.n_episodes

    def session_index(self) -> int:
        """Index of this session in ``recording_sessions`` (once its first episode is kept)."""
        sessions = attributes.recording_sessions(self.writer.attrs, self.path)
        existing = len(sessions) if sessions is not None else 0
        return existing - 1 if self.session_added else existing

    def commit(self, episode: Episode, info: dict) -> int:
        """Append ``episode`` (with its extras) and its ``info`` entry; returns the episode's index.

        The attributes (``episode_info``, ``recording_sessions``) are written first, then the data, then
        the episode end: the episode is part of the dataset only once the last write has landed.
        """
        attrs = self.writer.attrs
        index = self.writer.n_episodes
        infos = episode_infos(attrs, index, self.path) + [dict(info, index=index, session=self.session_index())]
        update = {"episode_info": infos}
        if not self.session_added:
            sessions = list(attributes.recording_sessions(attrs, self.path) or [])
            update["recording_sessions"] = sessions + [self.session]
        self.writer.add_episode(episode, attrs=update)
        self.session_added = True
        return index

    def close(self) -> None:
        self.writer.close()
        self._lock.release()


DATASET_WRITERS.append(DatasetWriter(RecordingDataset, (("path", "--out"),)))


def flags_summary(flags: np.ndarray) -> dict[str, dict]:
    """Per problem kind: {"steps": n, "first_step": k} over a (T,) uint8 array of step flags."""
    flags = np.asarray(flags)
    out = {}
    for name, bit in STEP_PROBLEMS.items():
        hit = np.flatnonzero(flags & bit)
        if hit.size:
            out[name] = {"steps": int(hit.size), "first_step": int(hit[0])}
    return out
