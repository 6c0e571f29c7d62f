"""Encode and decode the AgileX Piper CAN frames the driver and the simulator use.

Every frame is classic CAN with an 11-bit ID and 8 data bytes; multi-byte fields are big-endian.
The dataclasses hold SI units (radians, metres, N·m, rad/s, A, V, °C); the wire holds integers in
0.001 degree (joints; 0.1 degree for the joint limits of 0x473), 0.001 mm (gripper stroke), 0.001 N·m
(gripper effort), 0.001 rad/s, 0.001 A, 0.1 V. ``to_frame()`` range-checks every field (ValueError for NaN/inf
or a value that does not fit its integer field); ``Decoder.decode`` turns any ``can.Message`` into one of these or
None.

Frames (fb = arm -> host, cmd = host -> arm):

- 0x150 cmd ``MotionCtrl1``: u8 emergency stop (1 stop, 2 resume/reset), u8 trajectory ctrl, u8 drag-teach
- 0x151 cmd ``MotionCtrl2``: u8 ctrl_mode (1 = CAN command), u8 move_mode (1 = joint), u8 speed %, u8 mit_mode,
  u8 residence time, u8 installation position
- 0x155..0x157 cmd ``JointCtrl``: int32 pairs (J1,J2) (J3,J4) (J5,J6) in 0.001 degree
- 0x159 cmd ``GripperCtrl``: int32 stroke 0.001 mm, u16 effort 0.001 N·m (0..5000), u8 code, u8 set_zero (0xAE)
- 0x471 cmd ``MotorEnable``: u8 motor (1..6 joint; 7 or 0xFF all, see MOTOR_ALL), u8 flag (1 off, 2 on)
- 0x472 cmd ``MotorLimitQuery``: u8 motor (1..6), u8 content (1 angle limits and max speed, answered by 0x473;
  2 max acceleration)
- 0x473 fb ``MotorLimitFeedback``: u8 motor, int16 max angle 0.1 degree, int16 min angle 0.1 degree, u16 max joint
  speed 0.001 rad/s (the limits the motor's firmware enforces; piper-sdk's ArmMsgFeedbackCurrentMotorAngleLimitMaxSpd)
- 0x2A1 fb ``ArmStatusFeedback``: u8 ctrl_mode, arm_status, mode_feed, teach_status, motion_status,
  trajectory_num, u16 error code (high byte: joint-limit bits J1..J6, low byte: communication bits J1..J6)
- 0x2A5..0x2A7 fb ``JointFeedback``: int32 pairs in 0.001 degree
- 0x2A8 fb ``GripperFeedback``: int32 stroke 0.001 mm, int16 effort 0.001 N·m, u8 status (bit 6 enabled)
- 0x251..0x256 fb ``MotorHighSpeed``: int16 speed 0.001 rad/s, int16 current 0.001 A, int32 position (raw)
- 0x261..0x266 fb ``MotorLowSpeed``: u16 voltage 0.1 V, int16 driver °C, int8 motor °C, u8 status
  (bit 6 driver enabled), u16 bus current 0.001 A
"""

from __future__ import annotations

import math
import struct
from collections import Counter
from dataclasses import dataclass
from typing import ClassVar, Union

import can
import numpy as np

# ---- IDs --------------------------------------------------------------------------------------------
MOTION_CTRL_1 = 0x150
MOTION_CTRL_2 = 0x151
JOINT_CTRL_IDS = (0x155, 0x156, 0x157)
GRIPPER_CTRL = 0x159
MOTOR_ENABLE = 0x471
MOTOR_LIMIT_QUERY = 0x472
MOTOR_LIMIT_FEEDBACK = 0x473
ARM_STATUS = 0x2A1
JOINT_FEEDBACK_IDS = (0x2A5, 0x2A6, 0x2A7)
GRIPPER_FEEDBACK = 0x2A8
HIGH_SPEED_IDS = tuple(range(0x251, 0x257))
LOW_SPEED_IDS = tuple(range(0x261, 0x267))

# ---- constants ----------------------------------------------------------------------------------------
# 0x150 byte 0: the SDK's EmergencyStop calls 2 "resume", and its ResetPiper sends the same 2, documented as a
# reset after which the motors are unpowered (the arm drops). The simulator models the reset.
ESTOP_NONE, ESTOP_STOP, ESTOP_RESUME = 0x00, 0x01, 0x02
CTRL_MODE_STANDBY, CTRL_MODE_CAN = 0x00, 0x01
MOVE_MODE_P, MOVE_MODE_J, MOVE_MODE_L, MOVE_MODE_C, MOVE_MODE_MIT = 0, 1, 2, 3, 4
GRIPPER_DISABLE, GRIPPER_ENABLE, GRIPPER_DISABLE_CLEAR, GRIPPER_ENABLE_CLEAR = 0, 1, 2, 3
GRIPPER_SET_ZERO = 0xAE
MOTOR_DISABLE, MOTOR_ENABLE_FLAG = 0x01, 0x02
# Motor number for "all motors": the SDK's EnableArm/DisableArm default to 7 and document it as "all
# motors", while its 0x471 message class documents 7 as the gripper motor and 0xFF as all motors
# including the gripper. The driver sends 7 (what the SDK's EnablePiper sends to real arms) and also
# enables the gripper through 0x159; the simulator treats both 7 and 0xFF as "all".
MOTOR_ALL = 7
MOTOR_ALL_FF = 0xFF
# 0x472 byte 1: what is asked (the SDK's SearchMotorMaxAngleSpdAccLimit search_content).
QUERY_ANGLE_SPEED, QUERY_ACCELERATION = 0x01, 0x02

ARM_STATUS_NAMES = {
    0x00: "normal",
    0x01: "emergency stop",
    0x02: "no solution",
    0x03: "singularity",
    0x04: "target angle beyond joint limit",
    0x05: "joint communication error",
    0x06: "joint brake not released",
    0x07: "collision",
    0x08: "overspeed during drag teaching",
    0x09: "joint status error",
    0x0A: "other error",
    0x0B: "teach recording",
    0x0C: "teach replay",
    0x0D: "teach paused",
    0x0E: "main controller over temperature",
    0x0F: "release resistor over temperature",
}
ENABLED_BIT = 1 << 6  # driver / gripper "enabled" bit in 0x261-0x266 and 0x2A8 status bytes
DRIVER_FAULT_BITS = 0b0011_1111 | 0x80  # low-speed status: voltage, temps, current, collision, error, stall
GRIPPER_FAULT_BITS = 0b0011_1111  # gripper status: voltage, temps, current, sensor, driver error

_MDEG_PER_RAD = 180_000.0 / math.pi
_DECIDEG_PER_RAD = 1800.0 / math.pi  # 0x473's angle limits are in 0.1 degree
LIMIT_RESOLUTION = math.radians(0.1)
"""rad: the step a Piper's firmware keeps its joint limits in (0x473)."""
_UM_PER_M = 1_000_000.0


# ---- field conversions ----------------------------------------------------------------------------------
def _scaled(value: float, scale: float, lo: int, hi: int, what: str) -> int:
    """``round(value * scale)`` checked to lie in [lo, hi] (ValueError for NaN, inf, or out of range)."""
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{what} must be finite, got {v}")
    i = round(v * scale)
    if not lo <= i <= hi:
        raise ValueError(f"{what} {v} is out of range for its CAN field ({lo / scale:g} .. {hi / scale:g})")
    return i


def _uint(value: int, bits: int, what: str) -> int:
    i = int(value)
    if i != value or not 0 <= i < (1 << bits):
        raise ValueError(f"{what} must be an integer in 0..{(1 << bits) - 1}, got {value}")
    return i


INT32 = (-(1 << 31), (1 << 31) - 1)
INT16 = (-(1 << 15), (1 << 15) - 1)
UINT16 = (0, (1 << 16) - 1)


def rad_to_mdeg(rad: float, what: str = "joint angle") -> int:
    """Radians -> int32 in 0.001 degree (ValueError if NaN/inf or beyond int32)."""
    return _scaled(rad, _MDEG_PER_RAD, *INT32, what + " (rad)")


def mdeg_to_rad(mdeg: int) -> float:
    return mdeg / _MDEG_PER_RAD


def _frame(arbitration_id: int, data: bytes) -> can.Message:
    return can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=False, dlc=8)


# ---- commands -----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class MotionCtrl1:
    """0x150: emergency stop (1 stop, 2 resume; the SDK calls 2 a reset after which the arm is unpowered)."""

    emergency_stop: int = ESTOP_NONE
    track_ctrl: int = 0
    drag_teach: int = 0
    ID: ClassVar[int] = MOTION_CTRL_1

    def to_frame(self) -> can.Message:
        return _frame(
            self.ID,
            struct.pack(
                ">BBB5x",
                _uint(self.emergency_stop, 8, "emergency_stop"),
                _uint(self.track_ctrl, 8, "track_ctrl"),
                _uint(self.drag_teach, 8, "drag_teach"),
            ),
        )

    @classmethod
    def from_data(cls, arbitration_id: int, data: bytes) -> "MotionCtrl1":
        return cls(*struct.unpack_from(">BBB", data))


@dataclass(frozen=True)
class MotionCtrl2:
    """0x151: control mode (1 = CAN command), move mode (1 = joint), speed 0..100 %."""

    ctrl_mode: int = CTRL_MODE_CAN
    move_mode: int = MOVE_MODE_J
    speed_percent: int = 50
    mit_mode: int = 0x00
    residence_time: int = 0
    installation_pos: int = 0
    ID: ClassVar[int] = MOTION_CTRL_2

    def to_frame(self) -> can.Message:
        speed = _uint(self.speed_percent, 8, "speed_percent")
        if speed > 100:
            raise ValueError(f"speed_percent must be in 0..100, got {speed}")
        return _frame(
            self.ID,
            struct.pack(
                ">BBBBBB2x",
                _uint(self.ctrl_mode, 8, "ctrl_mode"),
                _uint(self.move_mode, 8, "move_mode"),
                speed,
                _uint(self.mit_mode, 8, "mit_mode"),
                _uint(self.residence_time, 8, "residence_time"),
                _uint(self.installation_pos, 8, "installation_pos"),
            ),
        )

    @classmethod
    def from_data(cls, arbitration_id: int, data: bytes) -> "MotionCtrl2":
        return cls(*struct.unpack_from(">BBBBBB", data))


@dataclass(frozen=True)
class JointCtrl:
    """0x155 + pair: joint targets (rad) of joints 2*pair+1 and 2*pair+2 (pair 0: J1,J2; 1: J3,J4; 2: J5,J6)."""

    pair: int
    first: float
    second: float

    @property
    def ID(self) -> int:
        return JOINT_CTRL_IDS[self.pair]

    def to_frame(self) -> can.Message:
        return _frame(
            self.ID,
            struct.pack(
                ">ii",
                rad_to_mdeg(self.first, f"J{2 * self.pair + 1} target"),
                rad_to_mdeg(self.second, f"J{2 * self.pair + 2} target"),
            ),
        )

    @classmethod
    def from_data(cls, arbitration_id: int, data: bytes) -> "JointCtrl":
        a, b = struct.unpack_from(">ii", data)
        return cls(JOINT_CTRL_IDS.index(arbitration_id), mdeg_to_rad(a), mdeg_to_rad(b))


def joint_ctrl_frames(q: np.ndarray) -> list[can.Message]:
    """Joint targets q: (6,) radians -> the three frames 0x155, 0x156, 0x157 (ValueError if out of range)."""
    q = np.asarray(q, dtype=np.float64).reshape(-1)
    if q.shape != (6,):
        raise ValueError(f"joint targets must have 6 values, got {q.shape[0]}")
    return [JointCtrl(i, q[2 * i], q[2 * i + 1]).to_frame() for i in range(3)]


@dataclass(frozen=True)
class GripperCtrl:
    """0x159: stroke target (m), effort (N·m, 0..5), code (0 off, 1 on, 2/3 off/on + clear error), set_zero."""

    stroke: float
    effort: float = 1.0
    code: int = GRIPPER_ENABLE
    set_zero: int = 0
    ID: ClassVar[int] = GRIPPER_CTRL

    def to_frame(self) -> can.Message:
        stroke = _scaled(self.stroke, _UM_PER_M, *INT32, "gripper stroke (m)")
        effort = _scaled(self.effort, 1000.0, 0, 5000, "gripper effort (N·m)")
        return _frame(
            self.ID,
            struct.pack(
                ">iHBB", stroke, effort, _uint(self.code, 8, "gripper code"), _uint(self.set_zero, 8, "set_zero")
            ),
        )

    @classmethod
    def from_data(cls, arbitration_id: int, data: bytes) -> "GripperCtrl":
        stroke, effort, code, set_zero = struct.unpack_from(">iHBB", data)
        return cls(stroke / _UM_PER_M, effort / 1000.0, code, set_zero)


@dataclass(frozen=True)
class MotorEnable:
    """0x471: enable (flag 2) or disable (flag 1) motor 1..6, or all (7 / 0xFF)."""

    motor: int = MOTOR_ALL
    flag: int = MOTOR_ENABLE_FLAG
    ID: ClassVar[int] = MOTOR_ENABLE

    @property
    def enable(self) -> bool:
        return self.flag == MOTOR_ENABLE_FLAG

    def to_frame(self) -> can.Message:
        return _frame(self.ID, struct.pack(">BB6x", _uint(self.motor, 8, "motor"), _uint(self.flag, 8, "flag")))

    @classmethod
    def from_data(cls, arbitration_id: int, data: bytes) -> "MotorEnable":
        return cls(*struct.unpack_from(">BB", data))


@dataclass(frozen=True)
class MotorLimitQuery:
    """0x472: ask motor 1..6 for its limits; ``content`` 1 (angle limits and max speed, answered by 0x473) or 2 (max
    acceleration). piper-sdk sends it for every motor when it connects (``SearchAllMotorMaxAngleSpd``)."""

    motor: int
    content: int = QUERY_ANGLE_SPEED
    ID: ClassVar[int] = MOTOR_LIMIT_QUERY

    def to_frame(self) -> can.Message:
        return _frame(self.ID, struct.pack(">BB6x", _uint(self.motor, 8, "motor"), _uint(self.content, 8, "content")))

    @classmethod
    def from_data(cls, arbitration_id: int, data: bytes) -> "MotorLimitQuery":
        return cls(*struct.unpack_from(">BB", data))


# ---- feedback --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ArmStatusFeedback:
    """0x2A1: arm state. ``error_code`` u16: bits 8..13 joint-limit J1..J6, bits 0..5 comm error J1..J6."""

    ctrl_mode: int = 0
    arm_status: int = 0
    mode_feed: int = 0
    teach_status: int = 0
    motion_status: int = 0
    trajectory_num: int = 0
    error_code: int = 0
    ID: ClassVar[int] = ARM_STATUS

    @property
    def joint_limit_bits(self) -> int:
        """Bit i set: joint i+1 beyond its limit (byte 6 of the frame)."""
        return (self.error_code >> 8) & 0x3F

    @property
    def comm_error_bits(self) -> int:
        """Bit i set: joint i+1 communication error (byte 7 of the frame)."""
        return self.error_code & 0x3F

    def to_frame(self) -> can.Message:
        fields = (
            self.ctrl_mode,
            self.arm_status,
            self.mode_feed,
            self.teach_status,
            self.motion_status,
            self.trajectory_num,
        )
        names = ("ctrl_mode", "arm_status", "mode_feed", "teach_status", "motion_status", "trajectory_num")
        return _frame(
            self.ID,
            struct.pack(
                ">BBBBBBH", *(_uint(v, 8, n) for v, n in zip(fields, names)), _uint(self.error_code, 16, "error_code")
            ),
        )

    @classmethod
    def from_data(cls, arbitration_id: int, data: bytes) -> "ArmStatusFeedback":
        return cls(*struct.unpack_from(">BBBBBBH", data))


@dataclass(frozen=True)
class JointFeedback:
    """0x2A5 + pair: measured angles (rad) of joints 2*pair+1 and 2*pair+2."""

    pair: int
    first: float
    second: float

    @property
    def ID(self) -> int:
        return JOINT_FEEDBACK_IDS[self.pair]

    def to_frame(self) -> can.Message:
        return _frame(
            self.ID,
            struct.pack(
                ">ii",
                rad_to_mdeg(self.first, f"J{2 * self.pair + 1} angle"),
                rad_to_mdeg(self.second, f"J{2 * self.pair + 2} angle"),
            ),
        )

    @classmethod
    def from_data(cls, arbitration_id: int, data: bytes) -> "JointFeedback":
        a, b = struct.unpack_from(">ii", data)
        return cls(JOINT_FEEDBACK_IDS.index(arbitration_id), mdeg_to_rad(a), mdeg_to_rad(b))


@dataclass(frozen=True)
class GripperFeedback:
    """0x2A8: stroke (m), effort (N·m), status byte (bit 6 enabled, bits 0..5 faults, bit 7 homed)."""

    stroke: float
    effort: float = 0.0
    status: int = 0
    ID: ClassVar[int] = GRIPPER_FEEDBACK

    @property
    def enabled(self) -> bool:
        return bool(self.status & ENABLED_BIT)

    def to_frame(self) -> can.Message:
        return _frame(
            self.ID,
            struct.pack(
                ">ihBx",
                _scaled(self.stroke, _UM_PER_M, *INT32, "gripper stroke (m)"),
                _scaled(self.effort, 1000.0, *INT16, "gripper effort (N·m)"),
                _uint(self.status, 8, "gripper status"),
            ),
        )

    @classmethod
    def from_data(cls, arbitration_id: int, data: bytes) -> "GripperFeedback":
        stroke, effort, status = struct.unpack_from(">ihB", data)
        return cls(stroke / _UM_PER_M, effort / 1000.0, status)


@dataclass(frozen=True)
class MotorHighSpeed:
    """0x251 + motor - 1: motor speed (rad/s), current (A), raw position counts (unit undocumented)."""

    motor: int  # 1..6
    speed: float = 0.0
    current: float = 0.0
    position: int = 0

    @property
    def ID(self) -> int:
        return HIGH_SPEED_IDS[self.motor - 1]

    def to_frame(self) -> can.Message:
        return _frame(
            self.ID,
            struct.pack(
                ">hhi",
                _scaled(self.speed, 1000.0, *INT16, "motor speed (rad/s)"),
                _scaled(self.current, 1000.0, *INT16, "motor current (A)"),
                _scaled(self.position, 1.0, *INT32, "motor position"),
            ),
        )

    @classmethod
    def from_data(cls, arbitration_id: int, data: bytes) -> "MotorHighSpeed":
        speed, current, position = struct.unpack_from(">hhi", data)
        return cls(HIGH_SPEED_IDS.index(arbitration_id) + 1, speed / 1000.0, current / 1000.0, position)


@dataclass(frozen=True)
class MotorLowSpeed:
    """0x261 + motor - 1: voltage (V), driver/motor temperature (°C), status (bit 6 enabled), bus current (A)."""

    motor: int  # 1..6
    voltage: float = 24.0
    driver_temp: int = 30
    motor_temp: int = 30
    status: int = 0
    bus_current: float = 0.0

    @property
    def ID(self) -> int:
        return LOW_SPEED_IDS[self.motor - 1]

    @property
    def driver_enabled(self) -> bool:
        return bool(self.status & ENABLED_BIT)

    def to_frame(self) -> can.Message:
        return _frame(
            self.ID,
            struct.pack(
                ">HhbBH",
                _scaled(self.voltage, 10.0, *UINT16, "voltage (V)"),
                _scaled(self.driver_temp, 1.0, *INT16, "driver temperature (°C)"),
                _scaled(self.motor_temp, 1.0, -128, 127, "motor temperature (°C)"),
                _uint(self.status, 8, "driver status"),
                _scaled(self.bus_current, 1000.0, *UINT16, "bus current (A)"),
            ),
        )

    @classmethod
    def from_data(cls, arbitration_id: int, data: bytes) -> "MotorLowSpeed":
        voltage, driver_temp, motor_temp, status, bus_current = struct.unpack_from(">HhbBH", data)
        return cls(
            LOW_SPEED_IDS.index(arbitration_id) + 1,
            voltage / 10.0,
            driver_temp,
            motor_temp,
            status,
            bus_current / 1000.0,
        )


@dataclass(frozen=True)
class MotorLimitFeedback:
    """0x473: the limits motor 1..6's firmware enforces, the answer to 0x472 content 1: max and min angle (rad; int16
    in 0.1 degree on the wire), max joint speed (rad/s; u16 in 0.001 rad/s). Decoded as sent, whatever the values
    (a corrupted firmware reports min = max or min > max)."""

    motor: int
    max_angle: float
    min_angle: float
    max_speed: float
    ID: ClassVar[int] = MOTOR_LIMIT_FEEDBACK

    def to_frame(self) -> can.Message:
        return _frame(
            self.ID,
            struct.pack(
                ">BhhHx",
                _uint(self.motor, 8, "motor"),
                _scaled(self.max_angle, _DECIDEG_PER_RAD, *INT16, "max angle limit (rad)"),
                _scaled(self.min_angle, _DECIDEG_PER_RAD, *INT16, "min angle limit (rad)"),
                _scaled(self.max_speed, 1000.0, *UINT16, "max joint speed (rad/s)"),
            ),
        )

    @classmethod
    def from_data(cls, arbitration_id: int, data: bytes) -> "MotorLimitFeedback":
        motor, max_angle, min_angle, max_speed = struct.unpack_from(">BhhH", data)
        return cls(motor, max_angle / _DECIDEG_PER_RAD, min_angle / _DECIDEG_PER_RAD, max_speed / 1000.0)


PiperMessage = Union[
    MotionCtrl1,
    MotionCtrl2,
    JointCtrl,
    GripperCtrl,
    MotorEnable,
    MotorLimitQuery,
    ArmStatusFeedback,
    JointFeedback,
    GripperFeedback,
    MotorHighSpeed,
    MotorLowSpeed,
    MotorLimitFeedback,
]

_BY_ID: dict[int, type] = {
    MOTION_CTRL_1: MotionCtrl1,
    MOTION_CTRL_2: MotionCtrl2,
    GRIPPER_CTRL: GripperCtrl,
    MOTOR_ENABLE: MotorEnable,
    MOTOR_LIMIT_QUERY: MotorLimitQuery,
    MOTOR_LIMIT_FEEDBACK: MotorLimitFeedback,
    ARM_STATUS: ArmStatusFeedback,
    GRIPPER_FEEDBACK: GripperFeedback,
    **{i: JointCtrl for i in JOINT_CTRL_IDS},
    **{i: JointFeedback for i in JOINT_FEEDBACK_IDS},
    **{i: MotorHighSpeed for i in HIGH_SPEED_IDS},
    **{i: MotorLowSpeed for i in LOW_SPEED_IDS},
}
KNOWN_IDS = frozenset(_BY_ID)


class Decoder:
    """Turns ``can.Message`` into the typed messages above; never raises.

    Frames it cannot use are counted in ``counts`` by reason and dropped: ``error_frame``,
    ``remote_frame``, ``extended_id``, ``bad_id`` (standard ID above 0x7FF), ``fd_frame``,
    ``unknown_id``, ``bad_dlc`` (not exactly 8 data bytes), ``malformed`` (a message object whose fields
    contradict each other). Decoded frames count as ``decoded``.
    """

    REASONS = ("error_frame", "remote_frame", "extended_id", "bad_id", "fd_frame", "unknown_id", "bad_dlc", "malformed")

    def __init__(self) -> None:
        self.counts: Counter[str] = Counter()

    def _reject(self, reason: str) -> None:
        self.counts[reason] += 1
        return None

    def decode(self, frame: can.Message) -> PiperMessage | None:
        """The typed message of ``frame``, or None (and a count in ``counts``) if it is not one."""
        try:
            if frame.is_error_frame:
                return self._reject("error_frame")
            if frame.is_remote_frame:
                return self._reject("remote_frame")
            if frame.is_extended_id:
                return self._reject("extended_id")
            arbitration_id = int(frame.arbitration_id)
            if not 0 <= arbitration_id <= 0x7FF:
                return self._reject("bad_id")
            if frame.is_fd:
                return self._reject("fd_frame")
            cls = _BY_ID.get(arbitration_id)
            if cls is None:
                return self._reject("unknown_id")
            data = bytes(frame.data or b"")
            if len(data) != 8 or frame.dlc != 8:
                return self._reject("bad_dlc")
            message = cls.from_data(arbitration_id, data)
        except (TypeError, ValueError, AttributeError, struct.error):
            # A message object with inconsistent fields (possible with ``check=False``): counted, dropped.
            return self._reject("malformed")
        self.counts["decoded"] += 1
        return message
