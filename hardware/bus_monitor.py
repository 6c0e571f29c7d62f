"""A passive listener on one teleoperation bus: the follower's feedback, the leader's commands, the raw log.

    with BusMonitor("can0") as bus:
        state = bus.follower()          # ArmReading: (7,) policy units + arrival time of its oldest frame
        command = bus.leader()          # the leader's latest target, same form
        bus.begin_log("ep.can0.blf")    # every frame from now on goes to this python-can log
        ...
        frames = bus.end_log()

The monitor commands nothing. One thread receives every frame, stamps it on arrival with ``clock()``
(``time.monotonic`` on a robot; the simulated clock in lockstep), decodes it (``hardware.piper.codec``)
and writes it to the episode's log when one is open, so the decoded streams and the log hold exactly the
same frames. ``wait_for_frames(n)`` blocks until ``n`` frames have arrived (lockstep simulation).
:class:`ListeningArms` is the followers the monitors hear as the control loop's robot, one that never commands
(``dssp-record``: the leader drives the follower itself).

The one frame a monitor sends is the joint-limit query (0x472, :meth:`BusMonitor.query_limits`), asked before
recording starts (:meth:`hardware.rig.Rig.check_firmware_limits` from ``dssp-record``), as piper-sdk asks whenever it
connects: a follower whose firmware limits are corrupted is refused before anything is recorded. It is a read of
parameters: nothing moves and no mode changes. The answers (0x473) are heard like any frame; if the leader arm
answers too, every answer counts (:class:`hardware.piper.firmware_limits.LimitAnswers` keeps their intersection).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from pathlib import Path

import can
import numpy as np

from dssp_core.errors import ArmError, CanError
from hardware.leader import ArmReading, JointGripperTracker, LeaderTracker
from hardware.piper import codec
from hardware.piper.can_reader import CanReader
from hardware.piper.firmware_limits import LimitAnswers
from hardware.piper.limits import piper_description
from hardware.robot import ArmStatus, FirmwareLimits, Robot, RobotDescription, RobotState

_NAN = float("nan")
ARM_ERROR_STATUSES = frozenset(range(0x01, 0x0B)) | {0x0E, 0x0F}
"""0x2A1 arm_status values that are faults (e-stop, no solution, limit, communication, collision, ...)."""


class FollowerTracker(JointGripperTracker):
    """The latest feedback of one follower arm: joints (0x2A5..0x2A7), gripper (0x2A8), status (0x2A1)."""

    def __init__(self) -> None:
        super().__init__()
        self.status: codec.ArmStatusFeedback | None = None
        self.status_time = _NAN

    def update(self, message, t: float) -> None:
        if isinstance(message, codec.JointFeedback):
            self._joints[message.pair] = (message.first, message.second, t)
        elif isinstance(message, codec.GripperFeedback):
            self._gripper = (message.stroke, t)
        elif isinstance(message, codec.ArmStatusFeedback):
            self.status, self.status_time = message, t
        else:
            return
        self.frames += 1

    def error(self) -> str | None:
        """What the latest 0x2A1 reports as a fault (e-stop, error status, error bits), or None."""
        s = self.status
        if s is None:
            return None
        problems = []
        if s.arm_status in ARM_ERROR_STATUSES:
            problems.append(codec.ARM_STATUS_NAMES.get(s.arm_status, f"status 0x{s.arm_status:02X}"))
        if s.joint_limit_bits:
            problems.append("joint limit " + ",".join(f"J{i + 1}" for i in range(6) if s.joint_limit_bits >> i & 1))
        if s.comm_error_bits:
            problems.append(
                "communication error " + ",".join(f"J{i + 1}" for i in range(6) if s.comm_error_bits >> i & 1)
            )
        return "; ".join(problems) or None


class BusMonitor:
    """Listens to one bus shared by a leader and a follower arm (``channel`` on ``interface``).

    ``clock`` stamps arrivals (seconds). ``bus_options`` go to ``can.Bus``. ``name``: how logs and
    messages call the bus (default: the channel). ``frames_received`` counts
    every frame; ``decoder.counts`` counts them by outcome. ``check()`` raises the receive thread's error.
    """

    def __init__(
        self,
        channel: str,
        interface: str = "socketcan",
        *,
        clock: Callable[[], float] = time.monotonic,
        bus_options: dict | None = None,
        name: str | None = None,
    ) -> None:
        self.channel, self.interface = channel, interface
        self.name = name or channel
        self.clock = clock
        self.bus_options = dict(bus_options or {})
        self.decoder = codec.Decoder()
        self.frames_received = 0
        self._follower = FollowerTracker()
        self._leader = LeaderTracker()
        self._limits = LimitAnswers()  # the firmware joint limits (0x473) heard since start
        self._lock = threading.Condition()
        self._log: can.Listener | None = None
        self._log_frames = 0
        self.log_error: str | None = None
        """Why the current episode's log stopped early, or None."""
        number = can.util.channel2int(self.name)
        self._log_channel = number if number is not None and 0 <= number <= 0xFFFF else None
        self._reader = CanReader(
            channel,
            interface,
            bus_options,
            name=f"bus-monitor-{channel}",
            on_frame=self._receive,
            counts=self.decoder.counts,
            on_error=self._wake,
        )

    def __repr__(self) -> str:
        return f"BusMonitor({self.channel!r}, {self.interface!r})"

    # ---- lifecycle ----------------------------------------------------------------------------------
    def start(self) -> None:
        """Open the bus and start receiving (no-op if started). Raises CanError."""
        if self._reader.bus is None:
            self._limits.clear()
            self._reader.start()

    def stop(self) -> None:
        """Stop receiving, close an open log, shut the bus down."""
        self._reader.stop()
        self.end_log()
        self._reader.close()

    def __enter__(self) -> "BusMonitor":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def _wake(self, _exc: BaseException) -> None:
        """The receive thread failed: wake ``wait_for_frames`` so that it raises at once."""
        with self._lock:
            self._lock.notify_all()

    def _receive(self, frame: can.Message) -> None:
        """Stamp, decode and log one frame (receive thread)."""
        now = self.clock()
        message = self.decoder.decode(frame)
        with self._lock:
            if message is not None:
                self._follower.update(message, now)
                self._leader.update(message, now)
                if isinstance(message, codec.MotorLimitFeedback):
                    self._limits.update(message)
            if self._log is not None:
                self._write_log(frame)
            self.frames_received += 1
            self._lock.notify_all()

    def _write_log(self, frame: can.Message) -> None:
        """Write one frame to the open log (lock held). A failing log is closed and its error kept."""
        try:
            frame.channel = self._log_channel  # BLF stores a small integer channel
            self._log.on_message_received(frame)
            self._log_frames += 1
        except Exception as exc:  # the recording goes on; the episode's metadata says its log is incomplete
            self.log_error = f"{type(exc).__name__}: {exc}"
            logger, self._log = self._log, None
            try:
                logger.stop()
            except Exception:
                pass

    def check(self) -> None:
        """Raise CanError if receiving failed (the thread has stopped)."""
        if self._reader.error is not None:
            raise CanError(f"receiving from CAN bus {self.channel!r} failed: {self._reader.error}; check the CAN link")

    # ---- streams --------------------------------------------------------------------------------------
    def follower(self) -> ArmReading:
        """The follower's latest measured position (7,) in policy units, with arrival time."""
        with self._lock:
            return self._follower.reading()

    def leader(self) -> ArmReading:
        """The leader's latest commanded target (7,) in policy units, with arrival time."""
        with self._lock:
            return self._leader.reading()

    def query_limits(self, send_timeout: float = 0.05) -> None:
        """Send the joint-limit query (0x472, content 1) to every motor that has not answered since :meth:`start`:
        the only frame a monitor sends. Raises CanError if it cannot be sent."""
        self.check()
        bus = self._reader.bus
        if bus is None:
            raise CanError(f"bus {self.channel!r} is not open: start() the monitor first")
        for frame in self._limits.query_frames():
            try:
                bus.send(frame, timeout=send_timeout)
            except (can.CanError, OSError, ValueError) as exc:
                raise CanError(
                    f"sending the joint-limit query on {self.channel!r} failed ({exc}); check the CAN link"
                ) from exc

    def firmware_limits(self) -> FirmwareLimits:
        """The joint limits J1..J6 the follower's firmware reported since :meth:`start` (NaN where not yet)."""
        self.check()
        return self._limits.limits(f"the arm on {self.name}", self.channel)

    def follower_error(self) -> str | None:
        """A fault the follower reports in its latest status frame, or None."""
        with self._lock:
            return self._follower.error()

    def counts(self) -> dict[str, int]:
        """Frames received: total, follower feedback, leader commands."""
        with self._lock:
            return {"total": self.frames_received, "follower": self._follower.frames, "leader": self._leader.frames}

    def wait_for_frames(self, n: int, timeout: float = 2.0) -> None:
        """Block until at least ``n`` frames have been received in total (CanError after ``timeout`` s)."""
        deadline = time.monotonic() + timeout
        with self._lock:
            while self.frames_received < n:
                self.check()
                left = deadline - time.monotonic()
                if left <= 0:
                    raise CanError(
                        f"bus {self.channel!r}: {self.frames_received} of {n} expected frames arrived "
                        f"within {timeout:g} s"
                    )
                self._lock.wait(min(left, 0.05))

    # ---- raw log ------------------------------------------------------------------------------------------
    def begin_log(self, path: str | Path) -> None:
        """Write every frame received from now on to ``path`` (format from the suffix: .blf, .asc, .csv, .log)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            logger = can.Logger(str(path))
        except (ValueError, OSError) as exc:
            raise CanError(f"cannot write the CAN log {path}: {exc}") from exc
        with self._lock:
            previous, self._log, self._log_frames, self.log_error = self._log, logger, 0, None
        if previous is not None:
            previous.stop()

    def end_log(self) -> int:
        """Close the current log (flushing it); returns the number of frames it holds (0 if none was open)."""
        with self._lock:
            logger, self._log = self._log, None
            frames = self._log_frames
        if logger is None:
            return 0
        logger.stop()
        return frames


def oldest(readings: list[ArmReading]) -> float:
    """The oldest arrival time over several arms' readings (nan if any is missing)."""
    times = [r.time for r in readings]
    return _NAN if any(math.isnan(t) for t in times) else min(times)


class ListeningArms(Robot):
    """The follower arms heard by ``monitors`` (one per leader/follower pair, left first) as one robot that only
    listens: :meth:`state` is the followers' feedback (dof = 7 per arm, policy units), :meth:`command`, :meth:`enable`
    and :meth:`disable` refuse (ArmError) — the leaders drive the followers; :meth:`query_firmware_limits` asks for
    the followers' firmware joint limits, the one thing it sends. The monitors are opened and closed by their owner
    (the recording session), not here."""

    def __init__(self, monitors: list[BusMonitor]) -> None:
        self.monitors = list(monitors)
        self.dof = 7 * len(self.monitors)
        self._description = piper_description(len(self.monitors))

    @property
    def description(self) -> RobotDescription:
        return self._description

    def connect(self) -> None:
        """Nothing to open: the monitors are already listening."""

    def state(self) -> RobotState | None:
        readings = [m.follower() for m in self.monitors]
        if any(r.position is None for r in readings):
            return None
        status = []
        for monitor in self.monitors:
            error = monitor.follower_error()
            status.append(ArmStatus(enabled=True, error=error is not None, detail=error or ""))
        return RobotState(np.concatenate([r.position for r in readings]), oldest(readings), tuple(status))

    def query_firmware_limits(self) -> None:
        """The joint-limit query on every bus (:meth:`BusMonitor.query_limits`): the one frame the recorder sends."""
        for monitor in self.monitors:
            monitor.query_limits()

    def firmware_limits(self) -> tuple[FirmwareLimits, ...]:
        """Each follower's joint limits as its firmware reported them (NaN where not yet), left first."""
        return tuple(monitor.firmware_limits() for monitor in self.monitors)

    def _refuse(self, what: str) -> None:
        raise ArmError(f"{what}: the followers are driven by their leader arms; the recorder only listens")

    def enable(self, timeout: float = 2.0) -> None:
        self._refuse("enable")

    def command(self, target: np.ndarray) -> None:
        self._refuse("command")

    def emergency_stop(self) -> None:
        self._refuse("emergency stop")

    def disable(self) -> None:
        self._refuse("disable")

    def close(self) -> None:
        """Nothing to close: the monitors' owner stops them."""
