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

Refused with one line, nothing written: a bag without one of the topics or with a topic of another message type, a
depth encoding other than ``16UC1`` / ``mono16``, a camera without intrinsics or with lens distortion
(:class:`~dssp_data.pointcloud.depth_frame.Intrinsics`), a joint missing from the message, a joint value beyond
float32, a frame of another size than its CameraInfo or whose bytes do not make its rows, a bag shorter than two
ticks, unsynchronised streams, a bag folder holding a link or anything but regular files, a folder of bags holding a
link or a folder without ``metadata.yaml`` (never skipped), a ``metadata.yaml`` that is not a small regular file of
plain YAML, and a damaged bag (what a crash of ``ros2 bag record`` leaves: a cut sqlite3 or mcap file).

Memory (the read budget, :func:`dssp_data.bounded.read_budget`): ``metadata.yaml`` is read bounded, without
blocking (:func:`dssp_core.files.read_input_bytes`); the sqlite3 index's message sizes are checked before a message is
read; every compressed message or mcap chunk decodes through :func:`dssp_data.bounded.decompress_frames`, at most the
size it declares, which is checked against the budget first; each message's decoding, the messages kept and the ticks
are checked against the budget before they are allocated. Bags compressed as whole files (``compression_mode:
file``) are refused: their size cannot be bounded before they are decompressed.
"""

from __future__ import annotations

import contextlib
import math
import os
import sqlite3
import urllib.parse
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dssp_core.errors import ConfigError, DatasetError, DSSPError
from dssp_core.files import read_input_bytes
from dssp_core.schema import DEFAULT_CONTROL_RATE_HZ, JSON_MAX_DEPTH, check_rate
from dssp_data.bounded import (
    READ_BUDGET_ENV,
    ChunkTooLarge,
    check_budget,
    decompress_frames,
    human_size,
    read_budget,
    zstd_content_size,
)
from dssp_data.dataset_layout import FLOAT32_MAX, Episode
from dssp_data.edit import DATA_GENERATORS, ConvertedEpisode, check_converted_output, check_data_output, write_converted
from dssp_data.observation import ObservationContract, PointCloudConfig, piper_layout
from dssp_data.pointcloud import EmptyCloudError, frame_to_cloud, validate_extrinsics
from dssp_data.pointcloud.depth_frame import DepthFrame, Intrinsics
from dssp_data.recording import ACTION_CONVENTIONS, STATE_CONVENTION
from dssp_data.replay_buffer_writer import dataset_writer

PIPER_JOINTS = ("joint1", "joint2", "joint3", "joint4", "joint5", "joint6", "joint7")
"""piper_ros's joint names: J1..J6, then the gripper."""
PIPER_GRIPPER_OPEN = 0.07
"""The Piper gripper's full stroke in metres: the value of ``joint7`` that is opening 1."""
DEPTH_ENCODINGS = {"16UC1", "mono16"}
TIME_KEYS = ("timestamp", "camera_timestamp", "state_timestamp", "action_timestamp")
JOINT_STATE, IMAGE, CAMERA_INFO = "sensor_msgs/msg/JointState", "sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo"
METADATA_LIMIT = 4 << 20
"""Bytes a ``metadata.yaml`` may hold (a bag of a thousand topics or storage files writes a few hundred KB)."""
DECODED_FACTOR = 16
"""Bytes in memory per byte of a message while it is decoded and, for a depth frame, made a cloud (the pipeline's
float xyz and masks are about 15 bytes per 2-byte pixel)."""
KEPT_PER_MESSAGE = 256
"""Bytes kept in memory per message of a stream (its time and decoded joint vector or camera)."""
STORAGES = ("sqlite3", "mcap")


@dataclass(frozen=True)
class Rosbag2Settings:
    """How a bag becomes episodes (validated on construction; a bad value is one line naming its flag).

    control_rate_hz: the ticks per second. state_topic / action_topic (None: next_state) / depth_topic / info_topic:
    the topics. joints: the 7 names, J1..J6 then the gripper. gripper_open: the gripper value that is fully open.
    tolerance: s, the oldest a stream's newest message may be at a tick. depth_unit: metres per depth count.
    """

    control_rate_hz: float = DEFAULT_CONTROL_RATE_HZ
    state_topic: str = "/joint_states"
    action_topic: str | None = None
    depth_topic: str = "/camera/camera/depth/image_rect_raw"
    info_topic: str = "/camera/camera/depth/camera_info"
    joints: tuple[str, ...] = PIPER_JOINTS
    gripper_open: float = PIPER_GRIPPER_OPEN
    tolerance: float = 0.05
    depth_unit: float = 0.001

    def __post_init__(self) -> None:
        check_rate(self.control_rate_hz, "--control-rate")
        if len(self.joints) != 7 or len(set(self.joints)) != 7 or not all(self.joints):
            raise ConfigError(
                f"--joints must name 7 different joints (J1..J6, then the gripper), got {','.join(self.joints)}"
            )
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

    def topics(self) -> list[tuple[str, str, str]]:
        """(flag, topic, the message type it must carry) of every topic read."""
        topics = [
            ("--state-topic", self.state_topic, JOINT_STATE),
            ("--depth-topic", self.depth_topic, IMAGE),
            ("--info-topic", self.info_topic, CAMERA_INFO),
        ]
        if self.action_topic:
            topics.append(("--action-topic", self.action_topic, JOINT_STATE))
        return topics


def _rosbags():
    try:
        from rosbags.rosbag2 import Reader  # optional: the ros extra
        from rosbags.typesys import Stores, get_typestore  # optional: the ros extra
    except ImportError:
        raise ConfigError("reading ROS 2 bags needs the rosbags library: pip install 'dssp[ros]'") from None
    return Reader, get_typestore(Stores.ROS2_HUMBLE)


# ------------------------------------------------------------------------------------------- the bag folders
STORAGE_SUFFIXES = (".db3", ".mcap", ".db3.zstd", ".mcap.zstd")


def is_bag(path: Path) -> bool:
    """A rosbag2 folder: it holds ``metadata.yaml`` (whatever it is: it is checked when read)."""
    path = Path(path)
    return path.is_dir() and os.path.lexists(path / "metadata.yaml")


def looks_like_bag(path: Path) -> bool:
    """A rosbag2 folder, or one holding a bag's storage files without its ``metadata.yaml`` (what a crash of
    ``ros2 bag record`` leaves): what ``dssp-data convert`` reads as bags (and refuses, naming what is missing)."""
    path = Path(path)
    if is_bag(path):
        return True
    try:
        return path.is_dir() and any(p.name.endswith(STORAGE_SUFFIXES) for p in path.iterdir())
    except OSError:
        return False


def find_bags(source: Path) -> list[Path]:
    """The bag folders of ``source`` (one bag, or a folder of bags in name order). Anything in a folder of bags that
    is not a bag folder — a link, a folder without ``metadata.yaml`` (a recording cut short), a file — is refused by
    name, never skipped (hidden names aside); so is an empty folder."""
    source = Path(source)
    if source.is_symlink():
        raise DatasetError(f"{source} is a link; give the bag folder itself")
    if is_bag(source):
        return [source]
    if not source.is_dir():
        raise DatasetError(f"{source} is not a ROS 2 bag folder (no metadata.yaml) nor a folder of bags")
    if looks_like_bag(source):
        raise DatasetError(
            f"{source} holds a bag's storage files but no metadata.yaml (ros2 bag record was stopped "
            "before it wrote it?); ros2 bag reindex restores it"
        )
    bags = []
    for path in sorted(source.iterdir()):
        if path.name.startswith("."):
            continue
        if path.is_symlink():
            raise DatasetError(
                f"{path} is a link; a folder of bags is read from its own bag folders only (copy the "
                "bag in, or give it directly)"
            )
        if not path.is_dir():
            raise DatasetError(f"{path} is not a bag folder; a folder of bags holds bag folders only (move it out)")
        if not is_bag(path):
            raise DatasetError(
                f"{path} is a folder without metadata.yaml: not a complete bag (ros2 bag record was "
                f"stopped before it wrote it? ros2 bag reindex restores it); restore it or move it out "
                f"of {source}"
            )
        bags.append(path)
    if not bags:
        raise DatasetError(f"{source} holds no ROS 2 bag (a folder with metadata.yaml); record with ros2 bag record")
    return bags


def _check_inside(bag: Path) -> None:
    """The bag folder holds regular files only: the reader opens the files the metadata names inside the folder, and a
    link there would lead it out, a FIFO would block it."""
    for path in bag.iterdir():
        if path.is_symlink():
            raise DatasetError(f"{bag}: {path.name} is a link or lies outside the bag folder; copy the bag's files in")
        if not path.is_file():
            raise DatasetError(
                f"{bag}: {path.name} is not a regular file; a bag folder holds its metadata.yaml and storage files only"
            )


@dataclass(frozen=True)
class BagMetadata:
    """What a bag's ``metadata.yaml`` says: its storage (sqlite3 or mcap) and files, message compression (None or
    ``"message"``: each message a zstd frame), and {topic: message type}."""

    storage: str
    files: tuple[Path, ...]
    compression: str | None
    topics: dict[str, str]


def _yaml_problem(text: str) -> str | None:
    """What makes ``text`` unfit for the YAML loader (nesting deeper than JSON_MAX_DEPTH, an alias), found on its event
    stream before anything is built (the loader recurses once per level); None if nothing."""
    from ruamel.yaml import YAML  # optional: the ros extra (rosbags needs it)

    depth = 0
    for event in YAML(typ="safe").parse(text):
        kind = type(event).__name__
        if kind in ("MappingStartEvent", "SequenceStartEvent"):
            depth += 1
            if depth > JSON_MAX_DEPTH:
                return f"it nests more than {JSON_MAX_DEPTH} levels deep"
        elif kind in ("MappingEndEvent", "SequenceEndEvent"):
            depth -= 1
        elif kind == "AliasEvent":
            return "it uses a YAML alias (*name), which ros2 bag never writes"
    return None


def read_metadata(bag: Path) -> BagMetadata:
    """``bag/metadata.yaml``, read bounded and without blocking, checked: one DatasetError line otherwise."""
    from ruamel.yaml import YAML  # optional: the ros extra (rosbags needs it)

    where = f"{bag}/metadata.yaml"
    data = read_input_bytes(bag / "metadata.yaml", where, limit=METADATA_LIMIT, error=DatasetError, follow_links=False)
    try:
        text = data.decode()
        problem = _yaml_problem(text)
        values = None if problem else YAML(typ="safe").load(text)
    except UnicodeDecodeError:
        problem = "it is not text"
    except Exception as exc:  # ruamel's parser and scanner errors
        problem = f"it is not valid YAML: {' '.join(str(exc).split())[:200]}"
    if problem:
        raise DatasetError(
            f"{where} is not a bag's metadata ({problem}); a recording cut short? ros2 bag reindex "
            "rebuilds it from the storage files"
        )
    try:
        info = values["rosbag2_bagfile_information"]
        storage = info["storage_identifier"]
        names = info["relative_file_paths"]
        topics = {t["topic_metadata"]["name"]: t["topic_metadata"]["type"] for t in info["topics_with_message_count"]}
        mode = str(info.get("compression_mode") or "").lower()
        fmt = str(info.get("compression_format") or "").lower()
        if not (
            isinstance(names, list)
            and all(isinstance(n, str) and n for n in names)
            and all(isinstance(k, str) and isinstance(v, str) for k, v in topics.items())
        ):
            raise TypeError("relative_file_paths and the topics must be lists of names")
    except (KeyError, TypeError, AttributeError) as exc:
        raise DatasetError(
            f"{where} is not a rosbag2 metadata file ({type(exc).__name__}: {exc}); ros2 bag reindex rebuilds it"
        ) from None
    if storage not in STORAGES:
        raise DatasetError(f"{where}: storage {storage!r} is not read here (only {', '.join(STORAGES)})")
    if mode in ("", "none"):
        compression = None
    elif mode == "message" and fmt == "zstd":
        compression = "message"
    elif mode == "file":
        raise DatasetError(
            f"{where}: the bag is compressed as whole files (compression_mode: file), whose size is not "
            "known before they are decompressed; decompress it first (ros2 bag convert to an "
            "uncompressed bag)"
        )
    else:
        raise DatasetError(f"{where}: compression {mode!r} / {fmt!r} is not read here (none, or zstd messages)")
    files = []
    for name in names:
        path = bag / Path(name).name  # as rosbag2 does: the files lie in the bag folder
        if not path.is_file():
            raise DatasetError(
                f"{where} lists the storage file {name}, which is missing; a recording cut short? "
                "(ros2 bag reindex rebuilds the metadata from the files there)"
            )
        files.append(path)
    return BagMetadata(storage, tuple(files), compression, topics)


def _sqlite_sizes(meta: BagMetadata, bag: Path) -> dict[str, tuple[int, int]]:
    """{topic: (messages, largest message in bytes as stored)} from the sqlite3 files' index, read without
    reading a message."""
    sizes: dict[str, tuple[int, int]] = {}
    for path in meta.files:
        uri = f"file:{urllib.parse.quote(str(path.absolute()))}?mode=ro&immutable=1"
        try:
            with contextlib.closing(sqlite3.connect(uri, uri=True)) as db:
                rows = db.execute(
                    "SELECT topics.name, count(*), max(length(messages.data)) FROM messages "
                    "JOIN topics ON messages.topic_id = topics.id GROUP BY topics.name"
                ).fetchall()
        except sqlite3.Error as exc:
            raise DatasetError(
                f"{bag}: {path.name} is not a readable sqlite3 bag file ({exc}); a recording cut "
                "short? convert the bags that are complete"
            ) from None
        for topic, count, largest in rows:
            before = sizes.get(topic, (0, 0))
            sizes[topic] = (before[0] + int(count), max(before[1], int(largest or 0)))
    return sizes


def _check_message(nbytes: int, bag: Path, topic: str) -> None:
    check_budget(
        nbytes * DECODED_FACTOR,
        f"{bag}: a message of {topic} ({human_size(nbytes)})",
        "convert bags with smaller messages",
    )


@contextlib.contextmanager
def _bounded_decoding(bag: Path) -> Iterator[None]:
    """While a bag is read: rosbags' two decompressors (mcap chunks: ``storage_mcap.DECOMPRESSORS``; zstd messages:
    ``reader.zstd``) decode through :func:`~dssp_data.bounded.decompress_frames` — an mcap chunk to at most the size
    its record declares, checked against the read budget first; a message to at most the size its frame declares,
    checked the same way (a frame that declares none: at most the budget)."""
    from rosbags.rosbag2 import reader as reader_module  # optional: the ros extra
    from rosbags.rosbag2 import storage_mcap  # optional: the ros extra

    def chunk(kind: str | None) -> Callable[[bytes, int], bytes]:
        def decode(data: bytes, size: int) -> bytes:
            check_budget(
                size, f"{bag}: an mcap chunk ({human_size(size)} declared)", "convert bags with smaller chunks"
            )
            if kind is None:
                return data
            try:
                return decompress_frames(kind, data, size)
            except ChunkTooLarge:
                raise DatasetError(
                    f"{bag}: an mcap chunk decodes to more than the {human_size(size)} it declares: a "
                    "damaged or crafted file"
                ) from None

        return decode

    class BoundedZstd:
        @staticmethod
        def decompress(data: bytes) -> bytes:
            declared = _zstd_declared(data)
            if declared is not None:
                check_budget(
                    declared * DECODED_FACTOR,
                    f"{bag}: a compressed message ({human_size(declared)} declared)",
                    "convert bags with smaller messages",
                )
            limit = declared if declared is not None else read_budget() // DECODED_FACTOR
            try:
                return decompress_frames("zstd", data, limit)
            except ChunkTooLarge:
                if declared is not None:
                    raise DatasetError(
                        f"{bag}: a compressed message decodes to more than the {human_size(limit)} it "
                        "declares: a damaged or crafted file"
                    ) from None
                raise DatasetError(
                    f"{bag}: a compressed message decodes to more than {human_size(limit)}, the largest "
                    f"message the read budget of {human_size(read_budget())} ({READ_BUDGET_ENV}) allows "
                    f"(decoding takes {DECODED_FACTOR} times its size): convert bags with smaller "
                    f"messages, or raise {READ_BUDGET_ENV}"
                ) from None

        @staticmethod
        def open(*args, **kwargs):
            raise DatasetError(f"{bag}: files compressed whole are not read here")

    saved = dict(storage_mcap.DECOMPRESSORS), reader_module.zstd
    storage_mcap.DECOMPRESSORS.update({"": chunk(None), "lz4": chunk("lz4"), "zstd": chunk("zstd")})
    reader_module.zstd = BoundedZstd
    try:
        yield
    finally:
        storage_mcap.DECOMPRESSORS.clear()
        storage_mcap.DECOMPRESSORS.update(saved[0])
        reader_module.zstd = saved[1]


def _zstd_declared(data: bytes) -> int | None:
    """The size a zstd frame declares, None when it declares none or is no zstd frame (the decoder says which)."""
    try:
        return zstd_content_size(memoryview(data).cast("B"))
    except ValueError:
        return None


def _unreadable(bag: Path, exc: BaseException) -> DatasetError:
    """A library's error on a damaged bag as one line."""
    if isinstance(exc, MemoryError):
        return DatasetError(
            f"{bag}: reading it ran out of memory; lower DSSP_READ_BUDGET to have such bags refused "
            "before they are read"
        )
    text = " ".join(str(exc).split())[:200] or type(exc).__name__
    return DatasetError(
        f"{bag}: not a readable ROS 2 bag ({text}); a recording cut short? convert the bags that are complete"
    )


# ------------------------------------------------------------------------------------------- messages
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


def _joint_vector(msg, settings: Rosbag2Settings, bag: Path, topic: str, t: float) -> np.ndarray:
    names = list(msg.name)
    missing = [j for j in settings.joints if j not in names]
    if missing:
        raise DatasetError(
            f"{bag}: {topic} has no joint {', '.join(missing)} (it has {', '.join(names) or 'none'}); "
            "name the joints with --joints J1,..,J6,GRIPPER"
        )
    position = np.asarray(msg.position, dtype=np.float64)
    if len(position) != len(names):
        raise DatasetError(f"{bag}: {topic} gives {len(position)} positions for {len(names)} joint names")
    vector = np.array([position[names.index(j)] for j in settings.joints])
    vector[6] /= settings.gripper_open
    bad = np.flatnonzero(~np.isfinite(vector) | (np.abs(vector) > FLOAT32_MAX))
    if bad.size:
        joint = settings.joints[int(bad[0])]
        raise DatasetError(
            f"{bag}: {topic}'s message at {t:.9f} s gives {joint} = {float(position[names.index(joint)])!r}: "
            f"not a finite position within the range of float32 (±{FLOAT32_MAX:.3g}); leave out the bag"
        )
    return vector


def _intrinsics(msg, bag: Path, topic: str) -> Intrinsics:
    k = np.asarray(msg.k, dtype=np.float64)
    if k.shape != (9,):
        raise DatasetError(
            f"{bag}: {topic} has no usable intrinsics (K = {k.tolist()}); the clouds need the depth "
            "camera's calibration"
        )
    try:
        return Intrinsics.rectified(
            int(msg.width), int(msg.height), float(k[0]), float(k[4]), float(k[2]), float(k[5]), msg.d
        )
    except ConfigError as exc:
        raise DatasetError(
            f"{bag}: {topic}: {exc} (K = {k.tolist()}, {msg.width}x{msg.height}, "
            f"{msg.distortion_model}); record the rectified depth stream (image_rect_raw) with its "
            "camera_info"
        ) from None


def _depth(msg, intrinsics: Intrinsics, bag: Path, topic: str, t: float) -> np.ndarray:
    if msg.encoding not in DEPTH_ENCODINGS:
        raise DatasetError(f"{bag}: {topic} is {msg.encoding!r}; depth must be 16UC1 (millimetres) or mono16")
    if (msg.width, msg.height) != (intrinsics.width, intrinsics.height):
        raise DatasetError(
            f"{bag}: {topic} frames are {msg.width}x{msg.height}, its camera_info says "
            f"{intrinsics.width}x{intrinsics.height}"
        )
    size = len(msg.data)
    if msg.step < 2 * msg.width or msg.step % 2 or size != msg.step * msg.height:
        raise DatasetError(
            f"{bag}: {topic}'s frame at {t:.9f} s holds {size} bytes for {msg.height} rows of {msg.step} "
            f"(16-bit pixels: rows of an even number of bytes, at least {2 * msg.width}): a damaged "
            "image; leave out the bag"
        )
    data = np.frombuffer(msg.data, dtype=">u2" if msg.is_bigendian else "<u2")
    rows = data.reshape(msg.height, msg.step // 2)[:, : msg.width]
    return np.ascontiguousarray(rows, dtype=np.uint16)


def _newest(stream: _Stream, ticks: np.ndarray, tolerance: float, bag: Path) -> np.ndarray:
    """Index of each tick's newest message; refuses a tick whose newest message is older than ``tolerance``."""
    index = np.searchsorted(stream.times, ticks, side="right") - 1
    age = ticks - stream.times[index]
    worst = int(np.argmax(age))
    if age[worst] > tolerance:
        raise DatasetError(
            f"{bag}: the streams are not synchronised: {stream.topic}'s newest message is "
            f"{age[worst]:.3f} s old at {ticks[worst] - ticks[0]:.3f} s (tolerance {tolerance:g} s); "
            "record the topics together, or allow more with --tolerance"
        )
    return index


class _Bag:
    """An open bag: its messages by topic, each raw message size checked before it is decoded, every library error
    one line."""

    def __init__(self, reader, typestore, bag: Path):
        self.reader, self.typestore, self.bag = reader, typestore, bag
        self.connections = {c.topic: c for c in reader.connections}

    def messages(self, topic: str) -> Iterator[tuple[int, object]]:
        """(received ns, decoded message) of ``topic``, in the bag's order."""
        connection = self.connections[topic]
        iterator = iter(self.reader.messages(connections=[connection]))
        while True:
            try:
                _, received, raw = next(iterator)
            except StopIteration:
                return
            except DSSPError:
                raise
            except Exception as exc:  # the storage's and rosbags' errors on a damaged file
                raise _unreadable(self.bag, exc) from None
            _check_message(len(raw), self.bag, topic)
            try:
                msg = self.typestore.deserialize_cdr(raw, connection.msgtype)
            except Exception as exc:  # a message whose bytes do not decode as its type
                raise DatasetError(
                    f"{self.bag}: a message of {topic} does not decode as {connection.msgtype} "
                    f"({' '.join(str(exc).split())[:120] or type(exc).__name__}): a damaged bag"
                ) from None
            yield received, msg

    def read(self, topic: str, decode: Callable) -> _Stream:
        """Every message of ``topic``: its time and ``decode(msg, time)``, kept in memory within the read budget."""
        times, values = [], []
        budget = read_budget()
        for received, msg in self.messages(topic):
            t = _stamp(msg, received)
            times.append(t)
            values.append(decode(msg, t))
            if len(times) * KEPT_PER_MESSAGE > budget:
                check_budget(
                    len(times) * KEPT_PER_MESSAGE,
                    f"{self.bag}: the messages of {topic} (more than {len(times)})",
                    "convert shorter bags",
                )
        if not times:
            raise DatasetError(f"{self.bag}: {topic} holds no message")
        order = np.argsort(times, kind="stable")
        return _Stream(topic, np.asarray(times)[order], [values[i] for i in order], order)


def read_bag(bag: Path, settings: Rosbag2Settings, cloud_config: PointCloudConfig, camera_to_base: np.ndarray):
    """One bag -> (Episode, {"intrinsics": dict, "ticks": n}); see the module's steps."""
    Reader, typestore = _rosbags()
    _check_inside(bag)
    meta = read_metadata(bag)
    wanted = settings.topics()
    missing = list(dict.fromkeys(t for _, t, _ in wanted if t not in meta.topics))
    if missing:
        raise DatasetError(
            f"{bag}: no topic {', '.join(missing)} in the bag (it has {', '.join(sorted(meta.topics))}); "
            "name the topics with --state-topic, --depth-topic, --info-topic, --action-topic"
        )
    for flag, topic, msgtype in wanted:
        if meta.topics[topic] != msgtype:
            raise DatasetError(
                f"{bag}: {topic} carries {meta.topics[topic]}, not the {msgtype} {flag} names; name "
                f"a topic of that type with {flag}"
            )
    if meta.storage == "sqlite3":
        sizes = _sqlite_sizes(meta, bag)
        for topic in dict.fromkeys(t for _, t, _ in wanted):
            count, largest = sizes.get(topic, (0, 0))
            if meta.compression is None:  # compressed messages are checked by the size their frames declare
                _check_message(largest, bag, topic)
            if topic != settings.depth_topic:
                check_budget(
                    count * KEPT_PER_MESSAGE, f"{bag}: the {count} messages of {topic}", "convert shorter bags"
                )
    with _bounded_decoding(bag):
        try:
            reader = Reader(bag)
            reader.open()
        except DSSPError:
            raise
        except Exception as exc:  # rosbags' and the storage's errors: a cut or damaged file, broken metadata
            raise _unreadable(bag, exc) from None
        try:
            return _read(_Bag(reader, typestore, bag), settings, cloud_config, camera_to_base)
        finally:
            with contextlib.suppress(Exception):
                reader.close()


def _read(bag: _Bag, settings: Rosbag2Settings, cloud_config: PointCloudConfig, camera_to_base: np.ndarray):
    where = bag.bag
    missing = [t for _, t, _ in settings.topics() if t not in bag.connections]
    if missing:
        raise DatasetError(f"{where}: no topic {', '.join(missing)} in the bag's storage; a damaged bag")
    info = bag.read(settings.info_topic, lambda m, t: _intrinsics(m, where, settings.info_topic))
    intrinsics = info.values[0]
    if any(i != intrinsics for i in info.values):
        raise DatasetError(
            f"{where}: {settings.info_topic}'s intrinsics change during the bag; convert one setting per bag"
        )
    state = bag.read(settings.state_topic, lambda m, t: _joint_vector(m, settings, where, settings.state_topic, t))
    action = (
        bag.read(settings.action_topic, lambda m, t: _joint_vector(m, settings, where, settings.action_topic, t))
        if settings.action_topic
        else None
    )
    depth = bag.read(settings.depth_topic, lambda m, t: None)  # times only: frames are decoded below, one at a time
    streams = [s for s in (state, action, depth) if s is not None]
    start = max(s.times[0] for s in streams)
    end = min(s.times[-1] for s in streams)
    period = 1.0 / settings.control_rate_hz
    n = int(math.floor((end - start) / period + 1e-9)) + 1 if end >= start else 0
    if n < 2:
        raise DatasetError(
            f"{where}: the topics overlap for {max(end - start, 0):.3f} s, less than two ticks at "
            f"{settings.control_rate_hz:g} Hz"
        )
    step_bytes = 2 * cloud_config.n_points * cloud_config.point_dim * 4 + 14 * 4 + 8 * (len(TIME_KEYS) + 4)
    check_budget(
        n * step_bytes,
        f"{where}: {n} ticks at {settings.control_rate_hz:g} Hz ({end - start:.3f} s)",
        "check the bag's header stamps, or convert shorter bags",
    )
    ticks = start + period * np.arange(n)
    picks = {s.topic: _newest(s, ticks, settings.tolerance, where) for s in streams}

    # the frames the ticks use, each decoded and made a cloud as it is read (a bag's depth does not fit in memory)
    needed = {int(depth.read[i]): int(i) for i in picks[depth.topic]}
    cloud_of: dict[int, np.ndarray] = {}
    for position, (_, msg) in enumerate(bag.messages(settings.depth_topic)):
        if position not in needed:
            continue
        i = needed[position]
        t = float(depth.times[i])
        frame = DepthFrame(
            depth=_depth(msg, intrinsics, where, settings.depth_topic, t),
            depth_unit=settings.depth_unit,
            intrinsics=intrinsics,
            timestamp=t,
            frame_number=i,
        )
        try:
            cloud_of[i], _ = frame_to_cloud(frame, cloud_config, camera_to_base)
        except EmptyCloudError as exc:
            raise DatasetError(
                f"{where}: the depth frame at {t - ticks[0]:.3f} s has no point in the workspace "
                f"({exc}); check --extrinsics and the crop of --pointcloud"
            ) from None
    clouds = [cloud_of[int(i)] for i in picks[depth.topic]]
    states = np.stack([state.values[i] for i in picks[state.topic]])
    times = {
        "timestamp": ticks,
        "camera_timestamp": depth.times[picks[depth.topic]],
        "state_timestamp": state.times[picks[state.topic]],
    }
    if action is not None:
        actions = np.stack([action.values[i] for i in picks[action.topic]])
        times["action_timestamp"] = action.times[picks[action.topic]]
        keep = slice(None)
    else:  # next_state: the action of tick t is the state at t + 1; the last tick has none
        actions, keep = states[1:], slice(0, n - 1)
        times["action_timestamp"] = times["state_timestamp"][1:]
    extras = {key: (np.asarray(v, dtype=np.float64) - ticks[0])[keep] for key, v in times.items()}
    episode = Episode(
        point_cloud=np.stack(clouds)[keep].astype(np.float32),
        state=states[keep].astype(np.float32),
        action=actions.astype(np.float32),
        extras=extras,
    )
    return episode, {"intrinsics": intrinsics.to_dict(), "ticks": n}


@dataset_writer(out=None, check=check_converted_output)
def convert(
    source: Path,
    out: Path,
    settings: Rosbag2Settings,
    cloud_config: PointCloudConfig,
    camera_to_base: np.ndarray,
    *,
    max_episodes: int | None = None,
    task: str | None = None,
    force: bool = False,
    progress: Callable | None = None,
    flag: str = "--out",
) -> dict:
    """The bags of ``source`` -> a new dataset at ``out`` (one episode per bag, read one at a time), written in a
    staging folder and moved into place at the end; returns {"episodes", "steps", "files", "action_convention"}.
    It holds ``out``'s writer lock from the start, and ``out`` may not be ``source``, lie inside it or hold it."""
    camera_to_base = validate_extrinsics(np.asarray(camera_to_base, dtype=np.float64))
    out = Path(out)
    check_data_output(out, [source], force, flag)
    bags = find_bags(source)
    if max_episodes is not None:
        if max_episodes < 1:
            raise DatasetError(f"--episodes must be at least 1, got {max_episodes}")
        bags = bags[:max_episodes]
    convention = "leader_command" if settings.action_topic else "next_state"
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
        "camera_depth_unit": float(settings.depth_unit),
        "timestamps": "data/*timestamp: seconds since each episode's first tick (the bag's header stamps)",
        "rosbag2_topics": {
            "state": settings.state_topic,
            "action": settings.action_topic,
            "depth": settings.depth_topic,
            "camera_info": settings.info_topic,
            "joints": list(settings.joints),
            "gripper_open": settings.gripper_open,
            "tolerance_s": settings.tolerance,
        },
        **({"task": task} if task else {}),
    }

    def episodes() -> Iterator[ConvertedEpisode]:
        first = None
        for i, bag in enumerate(bags):
            if progress is not None:
                progress(i, len(bags), bag)
            episode, info = read_bag(bag, settings, cloud_config, camera_to_base)
            if first is None:
                first = info["intrinsics"]
            elif info["intrinsics"] != first:
                raise DatasetError(
                    f"{bag}: its depth camera's intrinsics differ from {bags[0].name}'s; convert each "
                    "setting into its own dataset"
                )
            yield ConvertedEpisode(None, episode, {"camera_intrinsics": first})

    steps = write_converted(out, attrs, episodes(), extra_keys=TIME_KEYS, force=force, flag=flag)
    return {"episodes": len(bags), "steps": steps, "files": [b.name for b in bags], "action_convention": convention}
