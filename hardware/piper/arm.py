"""``PiperArm``: one AgileX Piper on one CAN bus, in device units (joints (6,) radians, gripper stroke in metres).

A receive thread keeps the latest feedback frame of each kind with its arrival time on the arm's clock
(``hardware.clock``; wall time by default).
Commands are sent synchronously; a frame that cannot be sent raises ``CanError``. The arm obeys joint
targets only in CAN command mode with joint move mode (``set_joint_mode``), after ``enable``. ``query_limits`` asks
the firmware for the joint limits it enforces (0x472); ``firmware_limits`` is what it answered (0x473) since connect.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import can
import numpy as np

from dssp_core.errors import ArmError, CanError
from hardware.clock import REAL_CLOCK, Clock
from hardware.piper import codec
from hardware.piper.can_reader import CanReader
from hardware.piper.codec import ArmStatusFeedback, GripperFeedback, JointFeedback, MotorLimitFeedback, MotorLowSpeed
from hardware.piper.firmware_limits import LimitAnswers
from hardware.robot import ArmStatus, FirmwareLimits

_FEEDBACK_TYPES = (ArmStatusFeedback, JointFeedback, GripperFeedback, MotorLowSpeed, codec.MotorHighSpeed)
_NAN = float("nan")


def _status_name(arm_status: int) -> str:
    return codec.ARM_STATUS_NAMES.get(arm_status, f"0x{arm_status:02X}")


def _joint_list(bits: int) -> str:
    return ",".join(f"J{i + 1}" for i in range(6) if bits >> i & 1)


@dataclass(frozen=True)
class PiperFeedback:
    """The latest feedback of one arm, with arrival times on the arm's clock (nan when missing).

    joints: (6,) radians, None until all of 0x2A5..0x2A7 arrived; ``joints_time`` is the OLDEST of the three.
    gripper: 0x2A8 (stroke m, effort N·m, status). status: 0x2A1. drivers: 0x261..0x266 per motor J1..J6
    (None where not received); ``drivers_time`` is the oldest of the six.
    """

    joints: np.ndarray | None
    joints_time: float
    gripper: GripperFeedback | None
    gripper_time: float
    status: ArmStatusFeedback | None
    status_time: float
    drivers: tuple[MotorLowSpeed | None, ...]
    drivers_time: float

    @property
    def drivers_enabled(self) -> bool:
        """All six joint drivers report bit 6 (enabled)."""
        return all(d is not None and d.driver_enabled for d in self.drivers)

    @property
    def gripper_stroke(self) -> float | None:
        """Gripper stroke in metres, or None before the first 0x2A8."""
        return None if self.gripper is None else self.gripper.stroke


class PiperArm:
    """One Piper on ``channel`` (e.g. ``can0``) over ``interface`` (socketcan, virtual, udp_multicast).

    ``bus_options`` go to ``can.Bus`` (e.g. ``{"port": 43113}`` for udp_multicast). ``send_timeout`` (s)
    bounds how long a send may wait for room in a full queue before it raises CanError. ``stale_after`` (s):
    ``status()`` reports an error when the newest status frame is older than this. ``decoder.counts`` counts
    the frames received by outcome (``decoded``, or why one was dropped) and failed reads (``receive_error``).
    ``clock``: the timeline of arrival times, staleness and ``enable``'s waits (one clock with the loop that
    compares them; a ``FakeClock`` in tests).
    """

    def __init__(
        self,
        channel: str,
        interface: str = "socketcan",
        *,
        bus_options: dict | None = None,
        send_timeout: float = 0.05,
        gripper_effort: float = 1.0,
        stale_after: float = 0.5,
        clock: Clock = REAL_CLOCK,
    ) -> None:
        self.channel = channel
        self.interface = interface
        self.bus_options = dict(bus_options or {})
        self.send_timeout = send_timeout
        self.gripper_effort = gripper_effort  # N·m, used when command_gripper gets no effort
        self.stale_after = stale_after
        self.clock = clock
        self.decoder = codec.Decoder()
        self._reader = CanReader(
            channel,
            interface,
            bus_options,
            name=f"piper-rx-{channel}",
            on_frame=self._receive,
            counts=self.decoder.counts,
        )
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()
        self._latest: dict[int, tuple[object, float]] = {}  # arbitration ID -> (message, arrival time)
        self._limits = LimitAnswers()  # the firmware's joint limits (0x473) since connect

    def __repr__(self) -> str:
        return f"PiperArm({self.channel!r}, {self.interface!r})"

    # ---- lifecycle ------------------------------------------------------------------------------------------
    def connect(self) -> None:
        """Open the bus and start the receive thread (no-op if connected). Raises CanError."""
        if self._reader.bus is not None:
            return
        with self._lock:
            self._latest.clear()  # feedback from before a reconnect is not reused
        self._limits.clear()
        self._reader.start()

    def close(self) -> None:
        """Stop the receive thread and shut the bus down (sends nothing; idempotent)."""
        self._reader.close()

    def __enter__(self) -> "PiperArm":
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _receive(self, frame: can.Message) -> None:
        """Keep one feedback frame with its arrival time (receive thread)."""
        now = self.clock()
        message = self.decoder.decode(frame)
        if isinstance(message, _FEEDBACK_TYPES):
            with self._lock:
                self._latest[frame.arbitration_id] = (message, now)
        elif isinstance(message, MotorLimitFeedback):
            self._limits.update(message)

    def _check_rx(self) -> None:
        if self._reader.error is not None:
            raise CanError(
                f"receiving from CAN bus {self.channel!r} failed: {self._reader.error}; "
                "check the CAN link, then reconnect"
            )

    # ---- sending ----------------------------------------------------------------------------------------------
    def _send(self, *frames: can.Message) -> None:
        bus = self._reader.bus
        if bus is None:
            raise CanError(f"arm on {self.channel!r} is not connected: call connect() first")
        with self._send_lock:
            for frame in frames:
                try:
                    bus.send(frame, timeout=self.send_timeout)
                except (can.CanError, OSError, ValueError) as exc:
                    raise CanError(
                        f"sending frame 0x{frame.arbitration_id:03X} on {self.channel!r} failed ({exc}); "
                        "check the CAN link and that the arm is powered"
                    ) from exc

    def query_limits(self) -> None:
        """0x472 (content 1: angle limits and max speed) to every motor that has not answered since connect; the
        answers arrive in :meth:`firmware_limits`. Sends nothing once all six have answered."""
        self._check_rx()
        frames = self._limits.query_frames()
        if frames:
            self._send(*frames)

    def firmware_limits(self) -> FirmwareLimits:
        """The joint limits J1..J6 the firmware reported (0x473) since connect, NaN for a motor without an answer."""
        self._check_rx()
        return self._limits.limits(f"the arm on {self.channel}", self.channel)

    def set_joint_mode(self, speed_percent: int = 50) -> None:
        """0x151: CAN command mode, joint move mode (MOVE J), speed ``speed_percent`` in 0..100."""
        if not (isinstance(speed_percent, (int, np.integer)) and 0 <= speed_percent <= 100):
            raise ArmError(f"speed {speed_percent!r} % is invalid: give an integer in 0..100")
        self._send(codec.MotionCtrl2(codec.CTRL_MODE_CAN, codec.MOVE_MODE_J, int(speed_percent)).to_frame())

    def command_joints(self, q: np.ndarray) -> None:
        """0x155..0x157: absolute joint targets q: (6,) radians (not clipped here; the safety layer clips)."""
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (6,) or not np.all(np.isfinite(q)):
            raise ArmError(f"joint targets must be 6 finite values in radians, got shape {q.shape}: {q.tolist()}")
        try:
            frames = codec.joint_ctrl_frames(q)
        except ValueError as exc:
            raise ArmError(f"joint targets cannot be encoded: {exc}") from exc
        self._send(*frames)

    def command_gripper(self, stroke: float, effort: float | None = None) -> None:
        """0x159: gripper stroke target in metres (0 .. 0.07), effort in N·m (0..5), with the enable code."""
        effort = self.gripper_effort if effort is None else effort
        try:
            frame = codec.GripperCtrl(float(stroke), float(effort), codec.GRIPPER_ENABLE).to_frame()
        except (TypeError, ValueError) as exc:
            raise ArmError(f"gripper command cannot be encoded: {exc}") from exc
        self._send(frame)

    def emergency_stop(self) -> None:
        """0x150 = 1: the arm stops and holds (arm status 1) until ``resume``."""
        self._send(codec.MotionCtrl1(codec.ESTOP_STOP).to_frame())

    def resume(self) -> None:
        """0x150 = 2: leave the emergency stop and clear errors.

        The SDK documents this code as a reset after which the motors are unpowered (a real arm drops):
        support the arm, then ``enable()`` and ``set_joint_mode()`` again.
        """
        self._send(codec.MotionCtrl1(codec.ESTOP_RESUME).to_frame())

    def disable(self) -> None:
        """0x471 (all motors off) and 0x159 with the disable code. A real arm drops: support it first."""
        stroke = self.feedback().gripper_stroke
        self._send(
            codec.MotorEnable(codec.MOTOR_ALL, codec.MOTOR_DISABLE).to_frame(),
            codec.GripperCtrl(stroke or 0.0, 0.0, codec.GRIPPER_DISABLE).to_frame(),
        )

    def enable(self, timeout: float = 2.0) -> None:
        """Enable all motors and the gripper; return once feedback received after the request shows all six
        joint drivers (0x261..0x266 bit 6) and the gripper (0x2A8 bit 6) enabled. ArmError after ``timeout`` s.
        The request is repeated every 0.1 s, as the arm may miss one.
        """
        start = self.clock()
        deadline = start + timeout
        next_send = start
        while True:
            self._check_rx()
            fb = self._feedback_since(start)
            if fb.drivers_enabled and fb.gripper is not None and fb.gripper.enabled:
                return
            now = self.clock()
            if now >= deadline:
                raise ArmError(
                    f"arm on {self.channel!r} did not confirm enable within {timeout:g} s "
                    f"({self._enable_problem(fb)}); check its power, cable and e-stop, then retry"
                )
            if now >= next_send:
                frames = [codec.MotorEnable(codec.MOTOR_ALL, codec.MOTOR_ENABLE_FLAG).to_frame()]
                stroke = self.feedback().gripper_stroke
                if stroke is not None:  # hold the gripper where it is while enabling it
                    frames.append(codec.GripperCtrl(stroke, self.gripper_effort, codec.GRIPPER_ENABLE).to_frame())
                self._send(*frames)
                next_send = now + 0.1
            self.clock.sleep(0.005)

    def _enable_problem(self, fb: PiperFeedback) -> str:
        if all(d is None for d in fb.drivers) and fb.gripper is None:
            return "no driver or gripper feedback received"
        missing = [f"J{i + 1}" for i, d in enumerate(fb.drivers) if d is None]
        off = [f"J{i + 1}" for i, d in enumerate(fb.drivers) if d is not None and not d.driver_enabled]
        parts = []
        if missing:
            parts.append("no driver feedback from " + ",".join(missing))
        if off:
            parts.append("drivers not enabled: " + ",".join(off))
        if fb.gripper is None:
            parts.append("no gripper feedback")
        elif not fb.gripper.enabled:
            parts.append("gripper not enabled")
        if fb.status is not None and fb.status.arm_status != 0:
            parts.append("arm status: " + _status_name(fb.status.arm_status))
        return "; ".join(parts)

    # ---- feedback ----------------------------------------------------------------------------------------
    def _feedback_since(self, since: float) -> PiperFeedback:
        with self._lock:
            latest = {k: v for k, v in self._latest.items() if v[1] >= since}

        def get(frame_id):
            return latest.get(frame_id, (None, _NAN))

        pairs = [get(i) for i in codec.JOINT_FEEDBACK_IDS]
        if all(m is not None for m, _ in pairs):
            joints = np.array([v for m, _ in pairs for v in (m.first, m.second)])
            joints_time = min(t for _, t in pairs)
        else:
            joints, joints_time = None, _NAN
        drivers = [get(i) for i in codec.LOW_SPEED_IDS]
        drivers_time = min(t for _, t in drivers) if all(m is not None for m, _ in drivers) else _NAN
        gripper, gripper_time = get(codec.GRIPPER_FEEDBACK)
        status, status_time = get(codec.ARM_STATUS)
        return PiperFeedback(
            joints, joints_time, gripper, gripper_time, status, status_time, tuple(m for m, _ in drivers), drivers_time
        )

    def feedback(self) -> PiperFeedback:
        """The latest feedback (never blocks). Raises CanError if the receive thread stopped on an error."""
        self._check_rx()
        return self._feedback_since(-math.inf)

    def status(self) -> ArmStatus:
        """Enabled / e-stop / error summary from the latest 0x2A1, 0x2A8 and 0x261..0x266 frames."""
        fb = self.feedback()
        if fb.status is None:
            return ArmStatus(enabled=False, estop=False, error=True, detail="no status frame (0x2A1) received yet")
        s = fb.status
        problems = []
        age = self.clock() - fb.status_time
        if age > self.stale_after:
            problems.append(f"no status frame for {age:.2f} s")
        estop = s.arm_status == 0x01
        if s.arm_status not in (0x00, 0x01):
            problems.append("arm status: " + _status_name(s.arm_status))
        if s.joint_limit_bits:
            problems.append("joint limit " + _joint_list(s.joint_limit_bits))
        if s.comm_error_bits:
            problems.append("communication error " + _joint_list(s.comm_error_bits))
        for i, d in enumerate(fb.drivers):
            if d is not None and d.status & codec.DRIVER_FAULT_BITS:
                problems.append(f"J{i + 1} driver fault 0x{d.status:02X}")
        if fb.gripper is not None and fb.gripper.status & codec.GRIPPER_FAULT_BITS:
            problems.append(f"gripper fault 0x{fb.gripper.status:02X}")
        enabled = fb.drivers_enabled and fb.gripper is not None and fb.gripper.enabled
        detail = "; ".join((["emergency stop"] if estop else []) + problems)
        return ArmStatus(enabled=enabled, estop=estop, error=bool(problems), detail=detail)
