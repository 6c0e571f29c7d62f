"""ROS 2 bags (rosbag2: sqlite3 or mcap) -> a DP3 zarr dataset, through the point-cloud pipeline the robot runs.

    dssp-data convert BAGS --out OUT.zarr --extrinsics calib.json [--control-rate 10] [--state-topic /joint_states]
                      [--action-topic /leader/joint_states] [--depth-topic …] [--info-topic …] [--tolerance 0.05]

What a piper_ros user records: the arm's ``sensor_msgs/JointState`` (``/joint_states``; joints named ``joint1`` …
``joint6`` in radians and the gripper ``joint7``, its stroke in metres) and a RealSense's depth image
(``sensor_msgs/Image``, ``16UC1`` millimetres) with its ``sensor_msgs/CameraInfo``. One bag is one episode; BAGS is
one bag folder (``metadata.yaml`` and its storage files) or a folder of bag folders (converted in name order).
Read with the ``rosbags`` library (no ROS install; the ``ros`` extra).

Per bag:
1. every stream's messages are stamped with their header time (the sensor's clock), else the bag's receive time;
2. the control ticks run at ``control_rate_hz`` from the latest first message of the streams to the earliest last
   one; at each tick each stream gives its newest message at or before the tick (as ``dssp-record`` samples);
3. a stream whose newest message is older than ``tolerance`` at any tick is refused — the bag's streams are not
   synchronised, and a faithful step cannot be built (the line says which topic, when, how old);
4. each tick's depth frame -> point cloud (P, C) by :func:`dssp_data.pointcloud.frame_to_cloud` with the
   calibration ``camera_to_base`` (4, 4) and the :class:`~dssp_data.observation.PointCloudConfig`;
   state (7,) = [J1..J6 rad, gripper opening 0..1 = value / ``gripper_open``];
5. the action: with ``action_topic`` the leader's command at each tick (``leader_command``), else the next tick's
   state (``next_state``: the last tick has none and is dropped).

Refused with one line, nothing written: a bag without one of the topics, a depth encoding other than ``16UC1`` /
``mono16``, a camera without intrinsics or with lens distortion, a joint missing from the message, a frame of another
size than its CameraInfo, a bag shorter than two ticks, unsynchronised streams, a bag folder whose files are links.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dssp_core.errors import ConfigError, DatasetError
from dssp_core.output_guard import check_output
from dssp_data.dataset_layout import Episode
from dssp_data.edit import DATA_DATASET, DATA_GENERATORS, write_converted
from dssp_data.observation import ObservationContract, PointCloudConfig, piper_layout
from dssp_data.pointcloud import EmptyCloudError, frame_to_cloud, validate_extrinsics
from dssp_data.pointcloud.depth_frame import DepthFrame, Intrinsics
from dssp_data.recording import ACTION_CONVENTIONS, STATE_CONVENTION

PIPER_JOINTS = ("joint1", "joint2", "joint3", "joint4", "joint5", "joint6", "joint7")
"""piper_ros's joint names: J1..J6, then the gripper."""
PIPER_GRIPPER_OPEN = 0.07
"""The Piper gripper's full stroke in metres: the value of ``joint7`` that is opening 1."""
DEPTH_ENCODINGS = {"16UC1", "mono16"}
TIME_KEYS = ("timestamp", "camera_timestamp", "state_timestamp", "action_timestamp")


@dataclass(frozen=True)
class Rosbag2Settings:
    """How a bag becomes episodes (validated on construction; a bad value is one line naming its flag).

    control_rate_hz: the ticks per second. state_topic / action_topic (None: next_state) / depth_topic / info_topic:
    the topics. joints: the 7 names, J1..J6 then the gripper. gripper_open: the gripper value that is fully open.
    tolerance: s, the oldest a stream's newest message may be at a tick. depth_unit: metres per depth count.
    """

    control_rate_hz: float = 10.0
    state_topic: str = "/joint_states"
    action_topic: str | None = None
    depth_topic: str = "/camera/camera/depth/image_rect_raw"
    info_topic: str = "/camera/camera/depth/camera_info"
    joints: tuple[str, ...] = PIPER_JOINTS
    gripper_open: float = PIPER_GRIPPER_OPEN
    tolerance: float = 0.05
    depth_unit: float = 0.001

    def __post_init__(self) -> None:
        if not (isinstance(self.control_rate_hz, (int, float)) and math.isfinite(self.control_rate_hz)
                and 0.1 <= self.control_rate_hz <= 1000):
            raise ConfigError(f"--control-rate must be in [0.1, 1000] Hz, got {self.control_rate_hz!r}")
        if len(self.joints) != 7 or len(set(self.joints)) != 7 or not all(self.joints):
            raise ConfigError(f"--joints must name 7 different joints (J1..J6, then the gripper), got {','.join(self.joints)}")
        if not (math.isfinite(self.gripper_open) and self.gripper_open > 0):
            raise ConfigError(f"--gripper-open must be a positive number, got {self.gripper_open!r}")
        if not (math.isfinite(self.tolerance) and 0 < self.tolerance <= 10):
            raise ConfigError(f"--tolerance must be in (0, 10] s, got {self.tolerance!r}")
        if not (math.isfinite(self.depth_unit) and 0 < self.depth_unit <= 1):
            raise ConfigError(f"--depth-unit must be in (0, 1] m per count, got {self.depth_unit!r}")
        for name in ("state_topic", "depth_topic", "info_topic", "action_topic"):
            topic = getattr(self, name)
            if topic is not None and not (isinstance(topic, str) and topic.startswith("/")):
                raise ConfigError(f"--{name.replace('_', '-')} must be a topic name starting with /, got {topic!r}")


def _rosbags():
    try:
        from rosbags.rosbag2 import Reader  # optional: the ros extra
        from rosbags.typesys import Stores, get_typestore  # optional: the ros extra
    except ImportError:
        raise ConfigError("reading ROS 2 bags needs the rosbags library: pip install 'dssp[ros]'") from None
    return Reader, get_typestore(Stores.ROS2_HUMBLE)


def is_bag(path: Path) -> bool:
    """A rosbag2 folder: it holds ``metadata.yaml``."""
    return path.is_dir() and (path / "metadata.yaml").is_file()


def find_bags(source: Path) -> list[Path]:
    """The bag folders of ``source`` (one bag, or a folder of bags in name order); refuses links and an empty folder."""
    source = Path(source)
    if source.is_symlink():
        raise DatasetError(f"{source} is a link; give the bag folder itself")
    if is_bag(source):
        return [source]
    if not source.is_dir():
        raise DatasetError(f"{source} is not a ROS 2 bag folder (no metadata.yaml) nor a folder of bags")
    bags = sorted(p for p in source.iterdir() if not p.is_symlink() and is_bag(p))
    if not bags:
        raise DatasetError(f"{source} holds no ROS 2 bag (a folder with metadata.yaml); record with ros2 bag record")
    return bags


def _check_inside(bag: Path) -> None:
    """The bag folder holds no link: the reader opens the files the metadata names inside the folder only, and a link
    there would lead it out."""
    for path in bag.iterdir():
        if path.is_symlink():
            raise DatasetError(f"{bag}: {path.name} is a link or lies outside the bag folder; copy the bag's files in")


@dataclass
class _Stream:
    """One topic's messages in time order: times (s), decoded values, and where each was in the bag (``read``)."""

    topic: str
    times: np.ndarray
    values: list
    read: np.ndarray


def _stamp(msg, received_ns: int) -> float:
    """Header time in seconds, else the bag's receive time."""
    header = getattr(msg, "header", None)
    if header is not None and (header.stamp.sec or header.stamp.nanosec):
        return header.stamp.sec + header.stamp.nanosec * 1e-9
    return received_ns * 1e-9


def _joint_vector(msg, settings: Rosbag2Settings, bag: Path, topic: str) -> np.ndarray:
    names = list(msg.name)
    missing = [j for j in settings.joints if j not in names]
    if missing:
        raise DatasetError(f"{bag}: {topic} has no joint {', '.join(missing)} (it has {', '.join(names) or 'none'}); "
                           "name the joints with --joints J1,..,J6,GRIPPER")
    position = np.asarray(msg.position, dtype=np.float64)
    if len(position) != len(names):
        raise DatasetError(f"{bag}: {topic} gives {len(position)} positions for {len(names)} joint names")
    vector = np.array([position[names.index(j)] for j in settings.joints])
    vector[6] /= settings.gripper_open
    if not np.all(np.isfinite(vector)):
        raise DatasetError(f"{bag}: {topic} holds a NaN or infinite joint position")
    return vector


def _intrinsics(msg, bag: Path, topic: str) -> Intrinsics:
    k = np.asarray(msg.k, dtype=np.float64)
    if k.shape != (9,) or not (k[0] > 0 and k[4] > 0) or not (msg.width > 0 and msg.height > 0):
        raise DatasetError(f"{bag}: {topic} has no usable intrinsics (K = {k.tolist()}, {msg.width}x{msg.height}); "
                           "the clouds need the depth camera's calibration")
    d = np.asarray(msg.d, dtype=np.float64)
    if d.size and np.any(np.abs(d) > 1e-9):
        raise DatasetError(f"{bag}: {topic} has lens distortion ({msg.distortion_model}, D = {d.tolist()}); record the "
                           "rectified depth stream (image_rect_raw), whose distortion is zero")
    return Intrinsics(int(msg.width), int(msg.height), float(k[0]), float(k[4]), float(k[2]), float(k[5]))


def _depth(msg, intrinsics: Intrinsics, bag: Path, topic: str) -> np.ndarray:
    if msg.encoding not in DEPTH_ENCODINGS:
        raise DatasetError(f"{bag}: {topic} is {msg.encoding!r}; depth must be 16UC1 (millimetres) or mono16")
    if (msg.width, msg.height) != (intrinsics.width, intrinsics.height):
        raise DatasetError(f"{bag}: {topic} frames are {msg.width}x{msg.height}, its camera_info says "
                           f"{intrinsics.width}x{intrinsics.height}")
    data = np.frombuffer(bytes(msg.data), dtype=">u2" if msg.is_bigendian else "<u2")
    if msg.step < 2 * msg.width or data.size * 2 != msg.step * msg.height:
        raise DatasetError(f"{bag}: {topic} frame holds {data.size * 2} bytes for {msg.height} rows of {msg.step}")
    rows = data.reshape(msg.height, msg.step // 2)[:, :msg.width]
    return np.ascontiguousarray(rows, dtype=np.uint16)


def _newest(stream: _Stream, ticks: np.ndarray, tolerance: float, bag: Path) -> np.ndarray:
    """Index of each tick's newest message; refuses a tick whose newest message is older than ``tolerance``."""
    index = np.searchsorted(stream.times, ticks, side="right") - 1
    age = ticks - stream.times[index]
    worst = int(np.argmax(age))
    if age[worst] > tolerance:
        raise DatasetError(f"{bag}: the streams are not synchronised: {stream.topic}'s newest message is "
                           f"{age[worst]:.3f} s old at {ticks[worst] - ticks[0]:.3f} s (tolerance {tolerance:g} s); "
                           "record the topics together, or allow more with --tolerance")
    return index


def read_bag(bag: Path, settings: Rosbag2Settings, cloud_config: PointCloudConfig, camera_to_base: np.ndarray):
    """One bag -> (Episode, {"intrinsics": dict, "ticks": n}); see the module's steps."""
    Reader, typestore = _rosbags()
    _check_inside(bag)
    try:
        reader = Reader(bag)
    except Exception as exc:  # rosbags' own errors: a broken metadata.yaml, missing storage files
        raise DatasetError(f"{bag}: not a readable ROS 2 bag ({exc})") from None
    with reader:
        topics = {c.topic: c for c in reader.connections}
        wanted = [settings.state_topic, settings.depth_topic, settings.info_topic] + \
            ([settings.action_topic] if settings.action_topic else [])
        missing = [t for t in wanted if t not in topics]
        if missing:
            raise DatasetError(f"{bag}: no topic {', '.join(missing)} in the bag (it has {', '.join(sorted(topics))}); "
                               "name the topics with --state-topic, --depth-topic, --info-topic, --action-topic")

        def read(topic: str, decode: Callable) -> _Stream:
            connection = topics[topic]
            times, values = [], []
            for _, received, raw in reader.messages(connections=[connection]):
                msg = typestore.deserialize_cdr(raw, connection.msgtype)
                times.append(_stamp(msg, received))
                values.append(decode(msg))
            if not times:
                raise DatasetError(f"{bag}: {topic} holds no message")
            order = np.argsort(times, kind="stable")
            return _Stream(topic, np.asarray(times)[order], [values[i] for i in order], order)

        info = read(settings.info_topic, lambda m: _intrinsics(m, bag, settings.info_topic))
        intrinsics = info.values[0]
        if any(i != intrinsics for i in info.values):
            raise DatasetError(f"{bag}: {settings.info_topic}'s intrinsics change during the bag; convert one setting "
                               "per bag")
        state = read(settings.state_topic, lambda m: _joint_vector(m, settings, bag, settings.state_topic))
        action = read(settings.action_topic, lambda m: _joint_vector(m, settings, bag, settings.action_topic)) \
            if settings.action_topic else None
        depth = read(settings.depth_topic, lambda m: None)  # times only: frames are decoded below, one at a time
        streams = [s for s in (state, action, depth) if s is not None]
        start = max(s.times[0] for s in streams)
        end = min(s.times[-1] for s in streams)
        period = 1.0 / settings.control_rate_hz
        n = int(math.floor((end - start) / period + 1e-9)) + 1 if end >= start else 0
        if n < 2:
            raise DatasetError(f"{bag}: the topics overlap for {max(end - start, 0):.3f} s, less than two ticks at "
                               f"{settings.control_rate_hz:g} Hz")
        ticks = start + period * np.arange(n)
        picks = {s.topic: _newest(s, ticks, settings.tolerance, bag) for s in streams}

        # the frames the ticks use, each decoded and made a cloud as it is read (a bag's depth does not fit in memory)
        needed = {int(depth.read[i]): int(i) for i in picks[depth.topic]}
        cloud_of: dict[int, np.ndarray] = {}
        connection = topics[settings.depth_topic]
        for position, (_, _, raw) in enumerate(reader.messages(connections=[connection])):
            if position not in needed:
                continue
            i = needed[position]
            msg = typestore.deserialize_cdr(raw, connection.msgtype)
            frame = DepthFrame(depth=_depth(msg, intrinsics, bag, settings.depth_topic), depth_unit=settings.depth_unit,
                               intrinsics=intrinsics, timestamp=float(depth.times[i]), frame_number=i)
            try:
                cloud_of[i], _ = frame_to_cloud(frame, cloud_config, camera_to_base)
            except EmptyCloudError as exc:
                raise DatasetError(f"{bag}: the depth frame at {depth.times[i] - ticks[0]:.3f} s has no point in the "
                                   f"workspace ({exc}); check --extrinsics and the crop of --pointcloud") from None
    clouds = [cloud_of[int(i)] for i in picks[depth.topic]]
    states = np.stack([state.values[i] for i in picks[state.topic]])
    times = {"timestamp": ticks, "camera_timestamp": depth.times[picks[depth.topic]],
             "state_timestamp": state.times[picks[state.topic]]}
    if action is not None:
        actions = np.stack([action.values[i] for i in picks[action.topic]])
        times["action_timestamp"] = action.times[picks[action.topic]]
        keep = slice(None)
    else:  # next_state: the action of tick t is the state at t + 1; the last tick has none
        actions, keep = states[1:], slice(0, n - 1)
        times["action_timestamp"] = times["state_timestamp"][1:]
    extras = {key: (np.asarray(v, dtype=np.float64) - ticks[0])[keep] for key, v in times.items()}
    episode = Episode(point_cloud=np.stack(clouds)[keep].astype(np.float32), state=states[keep].astype(np.float32),
                      action=actions.astype(np.float32), extras=extras)
    return episode, {"intrinsics": intrinsics.to_dict(), "ticks": n}


def convert(source: Path, out: Path, settings: Rosbag2Settings, cloud_config: PointCloudConfig,
            camera_to_base: np.ndarray, *, max_episodes: int | None = None, task: str | None = None,
            force: bool = False, progress: Callable | None = None, flag: str = "--out") -> dict:
    """The bags of ``source`` -> a new dataset at ``out`` (one episode per bag), written in a staging folder and
    moved into place at the end; returns {"episodes", "steps", "files", "action_convention"}."""
    camera_to_base = validate_extrinsics(np.asarray(camera_to_base, dtype=np.float64))
    bags = find_bags(source)
    if max_episodes is not None:
        if max_episodes < 1:
            raise DatasetError(f"--episodes must be at least 1, got {max_episodes}")
        bags = bags[:max_episodes]
    out = Path(out)
    check_output(out, force=force, kind=DATA_DATASET, flag=flag, error=DatasetError)
    convention = "leader_command" if settings.action_topic else "next_state"
    episodes, infos = [], []
    for i, bag in enumerate(bags):
        if progress is not None:
            progress(i, len(bags), bag)
        episode, info = read_bag(bag, settings, cloud_config, camera_to_base)
        episodes.append(episode)
        infos.append(info)
    intrinsics = infos[0]["intrinsics"]
    attrs = {
        "generator": DATA_GENERATORS["convert"],
        "source_format": "ROS 2 bag (rosbag2)",
        "source": str(source),
        "converted_from": [b.name for b in bags],
        "control_rate_hz": float(settings.control_rate_hz),
        "action_convention": ACTION_CONVENTIONS[convention],
        "state_convention": STATE_CONVENTION,
        "pointcloud": cloud_config.to_dict(),
        **ObservationContract(state=piper_layout(1), action=piper_layout(1)).attrs(),
        "camera_to_base": camera_to_base.tolist(),
        "camera_intrinsics": intrinsics,
        "camera_depth_unit": float(settings.depth_unit),
        "timestamps": "data/*timestamp: seconds since each episode's first tick (the bag's header stamps)",
        "rosbag2_topics": {"state": settings.state_topic, "action": settings.action_topic,
                           "depth": settings.depth_topic, "camera_info": settings.info_topic,
                           "joints": list(settings.joints), "gripper_open": settings.gripper_open,
                           "tolerance_s": settings.tolerance},
        **({"task": task} if task else {}),
    }
    if any(info["intrinsics"] != intrinsics for info in infos):
        raise DatasetError(f"{source}: the bags' depth cameras have different intrinsics; convert each setting "
                           "into its own dataset")
    steps = write_converted(out, attrs, ((None, e) for e in episodes), extra_keys=TIME_KEYS, force=force, flag=flag)
    return {"episodes": len(bags), "steps": steps, "files": [b.name for b in bags], "action_convention": convention}
