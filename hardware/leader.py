"""The leader arm of a Piper teleoperation pair: reading its commands, and a scripted stand-in for it.

In AgileX's leader/follower teleoperation both arms share one CAN bus: the leader (set up with 0x470
0xFA) sends only commands, 0x151 (mode), 0x155..0x157 (joint targets) and 0x159 (gripper target), and
the follower obeys them and sends all the feedback. So the operator's command is read from the bus:

- :class:`LeaderTracker` keeps the latest commanded target of one leader, fed with decoded frames and
  their arrival times, as policy units (7,) [J1..J6 rad, gripper opening = stroke / 0.07 m].
- :class:`ScriptedLeader` sends those same frames from a script (a callable giving the next (7,) target),
  so a simulated follower moves like a teleoperated arm; the simulated default (``dssp-record --can
  sim``) scripts it with the simulation's expert (``dssp_sim.teleop``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import can
import numpy as np

from dssp_core.errors import CanError
from hardware.piper import codec
from hardware.piper.can_reader import CanReader
from hardware.piper.limits import opening_to_stroke, stroke_to_opening

_NAN = float("nan")


@dataclass(frozen=True)
class ArmReading:
    """One arm's latest position in policy units and when it arrived.

    position: (7,) float64 [J1..J6 rad, gripper opening (stroke / 0.07 m, 1 = open)], or None until a
    complete set of frames arrived. time: arrival time (the clock of whoever stamped the frames) of the
    OLDEST frame the position is built from; nan when position is None.
    """

    position: np.ndarray | None
    time: float

    @property
    def complete(self) -> bool:
        return self.position is not None


class JointGripperTracker:
    """Three joint-pair frames and one gripper frame assembled into one (7,) reading.

    Subclasses decide which frames feed ``_joints`` (pair -> (first rad, second rad, time)) and
    ``_gripper`` ((stroke m, time)): a leader's commands or a follower's feedback.
    """

    def __init__(self) -> None:
        self._joints: dict[int, tuple[float, float, float]] = {}
        self._gripper: tuple[float, float] | None = None
        self.frames = 0

    def reading(self) -> ArmReading:
        """(7,) [J1..J6 rad, opening] and the arrival of its oldest frame; None until all four frames came."""
        if len(self._joints) < 3 or self._gripper is None:
            return ArmReading(None, _NAN)
        joints = [v for pair in range(3) for v in self._joints[pair][:2]]
        stroke, gripper_time = self._gripper
        oldest = min([self._joints[pair][2] for pair in range(3)] + [gripper_time])
        return ArmReading(np.append(np.array(joints), float(stroke_to_opening(stroke))), oldest)


class LeaderTracker(JointGripperTracker):
    """The latest command of one leader arm, built from its 0x155..0x157 and 0x159 frames.

    ``update(message, t)`` takes any decoded frame (others are ignored) with its arrival time ``t``.
    ``mode_time`` is the arrival of the latest 0x151 (nan before one), ``frames`` counts command frames.
    """

    def __init__(self) -> None:
        super().__init__()
        self.mode_time = _NAN

    def update(self, message, t: float) -> None:
        if isinstance(message, codec.JointCtrl):
            self._joints[message.pair] = (message.first, message.second, t)
        elif isinstance(message, codec.GripperCtrl):
            self._gripper = (message.stroke, t)
        elif isinstance(message, codec.MotionCtrl2):
            self.mode_time = t
        else:
            return
        self.frames += 1


def leader_frames(target: np.ndarray, speed_percent: int = 100, gripper_effort: float = 1.0) -> list[can.Message]:
    """The frames a leader sends for one target (7,) in policy units: 0x151 (CAN command, joint mode,
    ``speed_percent``), 0x155..0x157 (joints, rad) and 0x159 (stroke = opening * 0.07 m, enable code).
    Raises ValueError for a target that cannot be encoded."""
    target = np.asarray(target, dtype=np.float64).reshape(-1)
    if target.shape != (7,) or not np.all(np.isfinite(target)):
        raise ValueError(f"a leader target is 7 finite values [J1..J6 rad, opening], got {target.tolist()}")
    stroke = float(opening_to_stroke(min(max(target[6], 0.0), 1.0)))
    return (
        [codec.MotionCtrl2(codec.CTRL_MODE_CAN, codec.MOVE_MODE_J, speed_percent).to_frame()]
        + codec.joint_ctrl_frames(target[:6])
        + [codec.GripperCtrl(stroke, gripper_effort, codec.GRIPPER_ENABLE).to_frame()]
    )


class ScriptedLeader:
    """A leader arm played by a script, on ``channel`` over ``interface`` (e.g. a python-can virtual bus).

    ``script()`` returns the next target (7,) in policy units, or None to repeat the previous one;
    ``step()`` sends it (:func:`leader_frames`); ``send(target)`` sends a given target. Frames the bus
    delivers to this node (the follower's feedback) are drained and ignored. ``frames_sent`` counts
    every frame sent.
    """

    def __init__(
        self,
        channel: str,
        interface: str = "virtual",
        *,
        script: Callable[[], np.ndarray | None] | None = None,
        speed_percent: int = 100,
        bus_options: dict | None = None,
        send_timeout: float = 0.05,
    ) -> None:
        self.channel, self.interface = channel, interface
        self.script = script
        self.speed_percent = int(speed_percent)
        self.bus_options = dict(bus_options or {})
        self.send_timeout = send_timeout
        self.frames_sent = 0
        self.last_target: np.ndarray | None = None
        self._reader = CanReader(channel, interface, bus_options)  # no thread: send_frames drains what arrives

    def start(self) -> None:
        """Open the bus (no-op if open). Raises CanError."""
        self._reader.open()

    def stop(self) -> None:
        """Shut the bus down (idempotent)."""
        self._reader.close()

    def __enter__(self) -> "ScriptedLeader":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def send_frames(self, frames: list[can.Message]) -> None:
        """Send raw frames (e.g. the setup that powers a follower on). Raises CanError."""
        bus = self._reader.bus
        if bus is None:
            raise CanError(f"scripted leader on {self.channel!r} is not started")
        while bus.recv(timeout=0.0) is not None:  # what others send is not for us
            pass
        for frame in frames:
            try:
                bus.send(frame, timeout=self.send_timeout)
            except (can.CanError, OSError, ValueError) as exc:
                raise CanError(
                    f"scripted leader: sending 0x{frame.arbitration_id:03X} on {self.channel!r} failed ({exc})"
                ) from exc
            self.frames_sent += 1

    def send(self, target: np.ndarray) -> None:
        """Send one target (7,) in policy units as leader frames."""
        frames = leader_frames(target, self.speed_percent)
        self.last_target = np.asarray(target, dtype=np.float64).reshape(7).copy()
        self.send_frames(frames)

    def step(self) -> np.ndarray | None:
        """Send the script's next target (or repeat the last one); returns what was sent (None: nothing yet)."""
        target = self.script() if self.script is not None else None
        if target is None:
            target = self.last_target
        if target is None:
            return None
        self.send(target)
        return self.last_target
