"""ROS 2 bags as piper_ros and realsense2_camera users record them, written by the ``rosbags`` library's own writer:
``/joint_states`` (joint1..joint7, the gripper in metres), the depth of :data:`conftest.CAMERA` as a RealSense-style
16UC1 topic and its CameraInfo, each stream at its own rate and phase."""

from __future__ import annotations

import numpy as np
from conftest import CAMERA
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

TS = get_typestore(Stores.ROS2_HUMBLE)
JointState = TS.types["sensor_msgs/msg/JointState"]
Image = TS.types["sensor_msgs/msg/Image"]
CameraInfo = TS.types["sensor_msgs/msg/CameraInfo"]
Header = TS.types["std_msgs/msg/Header"]
Time = TS.types["builtin_interfaces/msg/Time"]
RegionOfInterest = TS.types["sensor_msgs/msg/RegionOfInterest"]

T0 = 1_700_000_000.0  # the bag's clock: header stamps in seconds since the epoch


def header(t: float, frame: str = "camera_depth_optical_frame"):
    """A message header stamped ``t`` (seconds since the epoch) in ``frame``."""
    sec = int(t)
    return Header(stamp=Time(sec=sec, nanosec=int(round((t - sec) * 1e9))), frame_id=frame)


def joints(t: float) -> np.ndarray:
    """The arm's trajectory: J1..J6 rad and the gripper stroke in metres (piper_ros's joint7)."""
    s = t - T0
    return np.array([0.3 * np.sin(s), 1.0 + 0.1 * s, -0.8, 0.05 * s, 0.3, -0.2, 0.035 + 0.03 * np.sin(2 * s)])


def depth_image(t: float) -> np.ndarray:
    """The depth image :data:`conftest.CAMERA` takes at ``t`` on the bag's clock."""
    depth, _ = CAMERA.render(t - T0)
    return depth


def write_bag(
    path,
    seconds=1.5,
    *,
    joint_hz=100.0,
    depth_hz=30.0,
    phase=0.004,
    info=True,
    leader=False,
    encoding="16UC1",
    distortion=(0.0,) * 5,
    depth_gap=None,
    storage="sqlite3",
    compression=None,
    joints_of=joints,
    k_of=None,
    image_bytes=None,
):
    """A bag like piper_ros + realsense2_camera record; ``depth_gap`` (start, end) s: no depth frame in between;
    ``storage`` sqlite3 or mcap, ``compression`` None, "message" (each message zstd) or "storage" (mcap's zstd
    chunks); ``joints_of(t)``: the joint positions at t; ``k_of(k)``: the CameraInfo's K from the camera's;
    ``image_bytes(data)``: a depth image's bytes from the camera's."""
    intr = CAMERA.intrinsics
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3)
    if compression is not None:
        writer.set_compression(CompressionMode[compression.upper()], CompressionFormat.ZSTD)
    with writer:
        conns = {
            "/joint_states": writer.add_connection("/joint_states", JointState.__msgtype__, typestore=TS),
            "/camera/camera/depth/image_rect_raw": writer.add_connection(
                "/camera/camera/depth/image_rect_raw", Image.__msgtype__, typestore=TS
            ),
        }
        if info:
            conns["info"] = writer.add_connection(
                "/camera/camera/depth/camera_info", CameraInfo.__msgtype__, typestore=TS
            )
        if leader:
            conns["leader"] = writer.add_connection("/leader/joint_states", JointState.__msgtype__, typestore=TS)
        events = []
        for k in range(int(seconds * joint_hz) + 1):
            events.append((T0 + k / joint_hz, "joints"))
        for k in range(int(seconds * depth_hz) + 1):
            t = T0 + phase + k / depth_hz
            if depth_gap and depth_gap[0] <= t - T0 < depth_gap[1]:
                continue
            events.append((t, "depth"))
        for t, kind in sorted(events):
            ns = int(round((t + 0.002) * 1e9))  # received a little after the sensor's stamp
            if kind == "joints":
                names = [f"joint{i}" for i in range(1, 8)]
                msg = JointState(
                    header=header(t, "base_link"),
                    name=names,
                    position=joints_of(t),
                    velocity=np.zeros(0),
                    effort=np.zeros(0),
                )
                writer.write(conns["/joint_states"], ns, TS.serialize_cdr(msg, JointState.__msgtype__))
                if leader:
                    ahead = JointState(
                        header=header(t, "base_link"),
                        name=names,
                        position=joints(t + 0.1),
                        velocity=np.zeros(0),
                        effort=np.zeros(0),
                    )
                    writer.write(conns["leader"], ns, TS.serialize_cdr(ahead, JointState.__msgtype__))
                continue
            depth = depth_image(t)
            data = depth.astype("<u2").tobytes() if encoding != "32FC1" else (depth * 0.00025).astype("<f4").tobytes()
            data = data if image_bytes is None else image_bytes(data)
            image = Image(
                header=header(t),
                height=intr.height,
                width=intr.width,
                encoding=encoding,
                is_bigendian=0,
                step=len(data) // intr.height,
                data=np.frombuffer(data, dtype=np.uint8),
            )
            writer.write(conns["/camera/camera/depth/image_rect_raw"], ns, TS.serialize_cdr(image, Image.__msgtype__))
            if info:
                k = np.array([intr.fx, 0, intr.ppx, 0, intr.fy, intr.ppy, 0, 0, 1], dtype=np.float64)
                k = k if k_of is None else k_of(k)
                camera_info = CameraInfo(
                    header=header(t),
                    height=intr.height,
                    width=intr.width,
                    distortion_model="plumb_bob",
                    d=np.array(distortion, dtype=np.float64),
                    k=k,
                    r=np.eye(3).reshape(9),
                    p=np.zeros(12),
                    binning_x=0,
                    binning_y=0,
                    roi=RegionOfInterest(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
                )
                writer.write(conns["info"], ns, TS.serialize_cdr(camera_info, CameraInfo.__msgtype__))
    return path
