"""``SimulatedPiper``: a Piper arm that speaks the CAN protocol of ``hardware.piper.codec`` on a python-can bus.

What it models (device units: joints (6,) radians, gripper stroke metres):

- Feedback every tick (default 200 Hz): 0x2A1 status, 0x2A5..0x2A7 joints, 0x2A8 gripper, and every
  ``low_speed_divider``-th tick 0x261..0x266 with the driver-enabled bit (6).
- 0x471 enables/disables motor 1..6, or all motors and the gripper (7 or 0xFF); 0x159 code 1/3 enables
  the gripper and sets its target, 0/2 disables it. A motor being enabled holds its current position.
- Joints move only when enabled, in CAN command mode (0x151 ctrl_mode 1) with joint move mode (move_mode 1),
  not e-stopped and without an injected fault. Each joint moves towards its target at most
  ``max_joint_speed * speed% / 100`` rad/s (``track``, the one method a physics simulation replaces).
- A joint target outside ``hardware.piper.limits`` is clamped to the limit. If it lies beyond by more than one
  wire unit (0.001 degree), the joint's limit bit (bit 8+i of the 0x2A1 error code) and arm status 0x04 are
  set until an in-range target for that joint arrives; the arm keeps moving (to the clamped target).
- 0x150 = 1: emergency stop, joints and gripper hold, arm status 0x01, targets ignored. 0x150 = 2: resume
  as the SDK documents it (a reset): e-stop and limit flags cleared, all motors disabled, standby mode.
- 0x472 content 1 (motor 1..6) is answered at once with 0x473: the joint limits its firmware holds
  (``firmware_limits``: by default the factory table, ``hardware.piper.limits.FIRMWARE_LOWER_DEG``/``UPPER_DEG``,
  and ``max_joint_speed``). They are only reported — its motion keeps ``hardware.piper.limits`` — so a test can
  give an arm corrupted ones (min = max, min > max, too narrow), or none at all (``answers_limit_query=False``:
  firmware that does not answer). Content 2 (max acceleration) is not answered.
- Fault injection for tests: ``pause_feedback``/``resume_feedback``, ``raise_error``/``clear_error``.

Run it with its own thread (``start()``) or drive it deterministically (``start(thread=False)``, then
``step(dt)``: handle the commands received so far, advance ``dt`` seconds, send one round of feedback).
It works on ``virtual`` (in-process) and ``udp_multicast`` (between processes) buses.
"""

from __future__ import annotations

import math
import threading
import time

import can
import numpy as np

from dssp_core.errors import CanError
from hardware.piper import codec
from hardware.piper.can_reader import CanReader
from hardware.piper.firmware_limits import factory_limits
from hardware.piper.limits import GRIPPER_STROKE_MAX, GRIPPER_STROKE_MIN, JOINT_LOWER, JOINT_UPPER
from hardware.robot import FirmwareLimits

REACHED_TOL = 1e-4  # rad: motion_status reports "reached" within this of every target
WIRE_UNIT = math.radians(0.001)  # rad: resolution of joint angles on the bus


class SimulatedPiper:
    """One simulated Piper on ``channel`` over ``interface``.

    rate: feedback ticks per second. max_joint_speed: rad/s at 100 % speed, scalar or (6,).
    gripper_speed: m/s. initial_joints: (6,) radians (default zeros). ``bus_options`` go to ``can.Bus``.
    firmware_limits: the joint limits it reports for 0x472 (None: the factory table at ``max_joint_speed``);
    answers_limit_query: False for firmware that never answers 0x472.
    """

    def __init__(
        self,
        channel: str,
        interface: str = "virtual",
        *,
        rate: float = 200.0,
        max_joint_speed: float | np.ndarray = 3.0,
        gripper_speed: float = 0.1,
        initial_joints: np.ndarray | None = None,
        initial_stroke: float = 0.0,
        low_speed_divider: int = 1,
        bus_options: dict | None = None,
        firmware_limits: FirmwareLimits | None = None,
        answers_limit_query: bool = True,
    ) -> None:
        if rate <= 0:
            raise ValueError(f"rate must be > 0 Hz, got {rate}")
        self.channel = channel
        self.interface = interface
        self.rate = float(rate)
        self.bus_options = dict(bus_options or {})
        self.max_joint_speed = np.broadcast_to(np.asarray(max_joint_speed, dtype=np.float64), (6,)).copy()
        self.gripper_speed = float(gripper_speed)
        self.low_speed_divider = max(1, int(low_speed_divider))
        self.firmware_limits = factory_limits(self.max_joint_speed) if firmware_limits is None else firmware_limits
        if self.firmware_limits.lower.shape != (6,):
            raise ValueError(f"firmware_limits must hold 6 joints, got {self.firmware_limits.lower.shape}")
        self.answers_limit_query = bool(answers_limit_query)
        self.decoder = codec.Decoder()
        self.ticks = 0
        self.frames_sent = 0
        self.commands_received = 0
        self.queries_received = 0  # 0x472 limit queries (answered or not)

        q0 = np.zeros(6) if initial_joints is None else np.asarray(initial_joints, dtype=np.float64).reshape(6)
        self._q = np.clip(q0, JOINT_LOWER, JOINT_UPPER)
        self._target = self._q.copy()
        self._stroke = float(np.clip(initial_stroke, GRIPPER_STROKE_MIN, GRIPPER_STROKE_MAX))
        self._stroke_target = self._stroke
        self._effort = 0.0
        self._joint_enabled = np.zeros(6, dtype=bool)
        self._gripper_enabled = False
        self._ctrl_mode = codec.CTRL_MODE_STANDBY
        self._move_mode = codec.MOVE_MODE_P
        self._speed_percent = 0
        self._estop = False
        self._limit_bits = 0  # bit i: joint i's last target was clamped
        self._injected_bits = 0
        self._injected_status = 0
        self._feedback_paused = False

        self._lock = threading.RLock()
        self._last = self._next_tick = 0.0  # monotonic times of the last feedback round and the next one
        self._reader = CanReader(
            channel,
            interface,
            bus_options,
            name=f"sim-piper-{channel}",
            on_frame=self._handle_frame,
            counts=self.decoder.counts,
            tick=self._tick,
        )

    def __repr__(self) -> str:
        return f"SimulatedPiper({self.channel!r}, {self.interface!r})"

    # ---- lifecycle ----------------------------------------------------------------------------------------
    def start(self, thread: bool = True) -> None:
        """Open the bus; with ``thread`` run ticks at ``rate`` in a thread, else wait for ``step`` calls."""
        if self._reader.bus is not None:
            raise RuntimeError(f"{self!r} is already started")
        self._reader.open()
        if thread:
            self._last = self._next_tick = time.monotonic()
            self._reader.start()

    def stop(self) -> None:
        """Stop the thread and close the bus. Raises CanError if the thread had stopped on an error."""
        self._reader.close()
        if self.error is not None:
            raise CanError(f"simulated arm on {self.channel!r} failed: {self.error}") from self.error

    @property
    def error(self) -> BaseException | None:
        """Why the thread stopped, if it failed (printed by dssp-sim-arm)."""
        return self._reader.error

    @property
    def started(self) -> bool:
        """The bus is open (with or without the thread)."""
        return self._reader.bus is not None

    @property
    def running(self) -> bool:
        """The thread is ticking."""
        return self._reader.running

    def _tick(self) -> float:
        """Advance and send one round of feedback when it is due (thread); returns the time left to the next."""
        now = time.monotonic()
        if now >= self._next_tick:
            with self._lock:
                self._advance(min(now - self._last, 0.1))
                self._send_feedback()
            self._last = now
            self._next_tick += 1.0 / self.rate
            if self._next_tick < now:  # fell behind (e.g. a stalled machine): do not try to catch up
                self._next_tick = now + 1.0 / self.rate
        return max(0.0, self._next_tick - time.monotonic())

    def step(self, dt: float) -> None:
        """Deterministic tick (use with ``start(thread=False)``): handle received commands, advance ``dt`` s,
        send one round of feedback (unless paused)."""
        bus = self._reader.bus
        if bus is None:
            raise RuntimeError(f"{self!r} is not started")
        while (frame := bus.recv(timeout=0.0)) is not None:
            self._handle_frame(frame)
        with self._lock:
            self._advance(float(dt))
            self._send_feedback()

    # ---- commands -----------------------------------------------------------------------------------------
    def _handle_frame(self, frame: can.Message) -> None:
        message = self.decoder.decode(frame)
        if message is None:
            return
        with self._lock:
            self._handle(message)

    def _handle(self, m) -> None:
        if isinstance(m, codec.MotionCtrl1):
            self.commands_received += 1
            if m.emergency_stop == codec.ESTOP_STOP:
                self._estop = True
                self._hold()
            elif m.emergency_stop == codec.ESTOP_RESUME:
                self._estop = False
                self._limit_bits = 0
                self._joint_enabled[:] = False
                self._gripper_enabled = False
                self._ctrl_mode = codec.CTRL_MODE_STANDBY
                self._hold()
        elif isinstance(m, codec.MotionCtrl2):
            self.commands_received += 1
            self._ctrl_mode, self._move_mode = m.ctrl_mode, m.move_mode
            self._speed_percent = min(m.speed_percent, 100)
        elif isinstance(m, codec.JointCtrl):
            self.commands_received += 1
            if self._estop:
                return
            for j, value in ((2 * m.pair, m.first), (2 * m.pair + 1, m.second)):
                # Flag only what lies beyond the limit by more than the wire's rounding (0.001 degree): a
                # target clipped to exactly the limit may arrive a fraction of a unit beyond it.
                beyond = value < JOINT_LOWER[j] - WIRE_UNIT or value > JOINT_UPPER[j] + WIRE_UNIT
                if beyond:
                    self._limit_bits |= 1 << j
                else:
                    self._limit_bits &= ~(1 << j)
                self._target[j] = min(max(value, JOINT_LOWER[j]), JOINT_UPPER[j])
        elif isinstance(m, codec.GripperCtrl):
            self.commands_received += 1
            if m.code in (codec.GRIPPER_ENABLE, codec.GRIPPER_ENABLE_CLEAR):
                self._gripper_enabled = True
                if not self._estop:
                    self._stroke_target = min(max(m.stroke, GRIPPER_STROKE_MIN), GRIPPER_STROKE_MAX)
                    self._effort = m.effort
            elif m.code in (codec.GRIPPER_DISABLE, codec.GRIPPER_DISABLE_CLEAR):
                self._gripper_enabled = False
                self._stroke_target = self._stroke
        elif isinstance(m, codec.MotorLimitQuery):
            self.queries_received += 1
            if self.answers_limit_query and m.content == codec.QUERY_ANGLE_SPEED and 1 <= m.motor <= 6:
                self._answer_limits(m.motor)
        elif isinstance(m, codec.MotorEnable):
            self.commands_received += 1
            if m.motor in (codec.MOTOR_ALL, codec.MOTOR_ALL_FF):
                joints, gripper = range(6), True
            elif 1 <= m.motor <= 6:
                joints, gripper = [m.motor - 1], False
            else:
                return
            if m.flag not in (codec.MOTOR_ENABLE_FLAG, codec.MOTOR_DISABLE):
                return
            on = m.flag == codec.MOTOR_ENABLE_FLAG
            for j in joints:
                if on and not self._joint_enabled[j]:
                    self._target[j] = self._q[j]  # a motor being enabled holds where it is
                self._joint_enabled[j] = on
            if gripper:
                if on and not self._gripper_enabled:
                    self._stroke_target = self._stroke
                self._gripper_enabled = on
        # Feedback frames (ours echoed back on udp_multicast, or another arm's) are ignored.

    def _hold(self) -> None:
        self._target = self._q.copy()
        self._stroke_target = self._stroke

    def _answer_limits(self, motor: int) -> None:
        """0x473 for ``motor`` 1..6 at once, as the firmware answers a query (counted in ``frames_sent``)."""
        limits, j = self.firmware_limits, motor - 1
        frame = codec.MotorLimitFeedback(motor, limits.upper[j], limits.lower[j], limits.max_speed[j]).to_frame()
        self._reader.bus.send(frame, timeout=0.05)
        self.frames_sent += 1

    # ---- physics ----------------------------------------------------------------------------------------------
    def track(self, q: np.ndarray, target: np.ndarray, dt: float, speed: np.ndarray) -> np.ndarray:
        """Next joint positions (6,) rad after ``dt`` s moving from q (6,) towards target (6,) at most
        ``speed`` (6,) rad/s. Override to put a physics simulation behind the protocol."""
        step = speed * dt
        return q + np.clip(target - q, -step, step)

    def _moving_allowed(self) -> bool:
        return not self._estop and not self._injected_bits

    def _advance(self, dt: float) -> None:
        self.ticks += 1
        if dt <= 0 or not self._moving_allowed():
            return
        if self._ctrl_mode == codec.CTRL_MODE_CAN and self._move_mode == codec.MOVE_MODE_J:
            speed = self.max_joint_speed * (self._speed_percent / 100.0)
            q_next = np.clip(self.track(self._q.copy(), self._target.copy(), dt, speed), JOINT_LOWER, JOINT_UPPER)
            self._q = np.where(self._joint_enabled, q_next, self._q)
        if self._gripper_enabled:
            delta = self._stroke_target - self._stroke
            step = self.gripper_speed * dt
            self._stroke += min(max(delta, -step), step)

    # ---- feedback -------------------------------------------------------------------------------------------------
    def _arm_status(self) -> int:
        if self._estop:
            return 0x01
        if self._injected_bits:
            return self._injected_status
        if self._limit_bits:
            return 0x04
        return 0x00

    def feedback_frames(self) -> list[can.Message]:
        """One round of feedback frames as the arm would send them now."""
        with self._lock:
            reached = bool(np.all(np.abs(self._q - self._target) <= REACHED_TOL))
            status = codec.ArmStatusFeedback(
                ctrl_mode=self._ctrl_mode,
                arm_status=self._arm_status(),
                mode_feed=self._move_mode,
                motion_status=0 if reached else 1,
                error_code=((self._limit_bits << 8) | self._injected_bits) & 0xFFFF,
            )
            frames = [status.to_frame()]
            frames += [codec.JointFeedback(i, self._q[2 * i], self._q[2 * i + 1]).to_frame() for i in range(3)]
            gripper_status = 0x80 | (codec.ENABLED_BIT if self._gripper_enabled else 0)  # bit 7: homed
            effort = self._effort if self._gripper_enabled else 0.0
            frames.append(codec.GripperFeedback(self._stroke, effort, gripper_status).to_frame())
            if self.ticks % self.low_speed_divider == 0:
                frames += [
                    codec.MotorLowSpeed(j + 1, status=codec.ENABLED_BIT if self._joint_enabled[j] else 0).to_frame()
                    for j in range(6)
                ]
            return frames

    def _send_feedback(self) -> None:
        if self._feedback_paused:
            return
        for frame in self.feedback_frames():
            self._reader.bus.send(frame, timeout=0.05)
            self.frames_sent += 1

    # ---- fault injection -----------------------------------------------------------------------------------
    def pause_feedback(self) -> None:
        """Stop sending feedback (commands are still obeyed) until ``resume_feedback``."""
        with self._lock:
            self._feedback_paused = True

    def resume_feedback(self) -> None:
        with self._lock:
            self._feedback_paused = False

    def raise_error(self, bits: int, arm_status: int | None = None) -> None:
        """Report error-code ``bits`` in 0x2A1 (bits 0..5 comm error J1..J6, 8..13 joint limit J1..J6) and
        hold still until ``clear_error``. ``arm_status`` defaults to 0x05 (comm error) if a comm bit is set,
        else 0x04 (joint limit) if a limit bit is set, else 0x0A (other error)."""
        bits = int(bits) & 0xFFFF
        if not bits:
            raise ValueError("raise_error needs at least one error bit")
        if arm_status is None:
            arm_status = 0x05 if bits & 0x3F else 0x04 if bits & 0x3F00 else 0x0A
        with self._lock:
            self._injected_bits = bits
            self._injected_status = int(arm_status)
            self._hold()

    def clear_error(self) -> None:
        with self._lock:
            self._injected_bits = 0
            self._injected_status = 0

    # ---- inspection ----------------------------------------------------------------------------------------
    @property
    def joints(self) -> np.ndarray:
        """Current joint positions (6,) radians (a copy)."""
        with self._lock:
            return self._q.copy()

    @property
    def joint_targets(self) -> np.ndarray:
        """Current joint targets (6,) radians after clamping (a copy)."""
        with self._lock:
            return self._target.copy()

    @property
    def gripper_stroke(self) -> float:
        """Current gripper stroke in metres."""
        with self._lock:
            return self._stroke

    @property
    def gripper_target(self) -> float:
        with self._lock:
            return self._stroke_target

    @property
    def enabled(self) -> bool:
        """All six joint motors and the gripper enabled."""
        with self._lock:
            return bool(self._joint_enabled.all() and self._gripper_enabled)

    @property
    def estop(self) -> bool:
        with self._lock:
            return self._estop

    @property
    def mode(self) -> tuple[int, int, int]:
        """(ctrl_mode, move_mode, speed_percent) from the last 0x151."""
        with self._lock:
            return self._ctrl_mode, self._move_mode, self._speed_percent

    @property
    def arm_status(self) -> int:
        with self._lock:
            return self._arm_status()

    @property
    def error_code(self) -> int:
        with self._lock:
            return ((self._limit_bits << 8) | self._injected_bits) & 0xFFFF
