"""``PiperRobot``: one or two Piper arms as one ``hardware.robot.Robot`` in policy units, and ``open_robot``.

Policy vector (RoboTwin order): one arm (7,) [J1..J6 rad, gripper opening 0..1]; two arms (14,)
[left J1..J6, left gripper, right J1..J6, right gripper]. Gripper opening g <-> stroke g * 0.07 m.
"""

from __future__ import annotations

import re
import uuid
from collections.abc import Sequence

import numpy as np

from dssp_core.errors import ArmError, HardwareError
from hardware.piper.arm import PiperArm
from hardware.piper.can_simulator import SimulatedPiper
from hardware.piper.limits import opening_to_stroke, piper_description, stroke_to_opening
from hardware.robot import ARM_DOF, ArmStatus, FirmwareLimits, Robot, RobotDescription, RobotState


class PiperRobot(Robot):
    """Arms in order (left, right). ``speed_percent``: the 0x151 speed sent with every command (0..100).
    ``gripper_effort``: N·m for every gripper command. ``simulators`` are started by ``connect`` and stopped
    by ``close`` (``open_robot("sim")`` fills them; tests use them to inject faults)."""

    def __init__(
        self,
        arms: Sequence[PiperArm],
        *,
        speed_percent: int = 50,
        gripper_effort: float = 1.0,
        simulators: Sequence[SimulatedPiper] = (),
    ) -> None:
        if not 1 <= len(arms) <= 2:
            raise ArmError(f"a Piper robot has 1 or 2 arms, got {len(arms)}")
        if not 0 <= speed_percent <= 100:
            raise ArmError(f"speed {speed_percent} % is invalid: give 0..100")
        self.arms = tuple(arms)
        self.simulators = tuple(simulators)
        self.speed_percent = int(speed_percent)
        self.gripper_effort = float(gripper_effort)
        self.dof = ARM_DOF * len(self.arms)

    def __repr__(self) -> str:
        return f"PiperRobot({', '.join(a.channel for a in self.arms)})"

    @property
    def description(self) -> RobotDescription:
        return piper_description(len(self.arms))

    def connect(self) -> None:
        """Start the simulators (if any), then open every arm's bus. Raises CanError."""
        try:
            for sim in self.simulators:
                if not sim.started:
                    sim.start()
            for arm in self.arms:
                arm.connect()
        except HardwareError:
            self._close_quietly_after_failure()
            raise

    def _close_quietly_after_failure(self) -> None:
        # Called while an error is already propagating: it is the error the caller sees.
        for arm in self.arms:
            try:
                arm.close()
            except HardwareError:
                pass
        for sim in self.simulators:
            try:
                sim.stop()
            except HardwareError:
                pass

    def enable(self, timeout: float = 2.0) -> None:
        """Enable every arm, each confirmed from its feedback within ``timeout`` s (else ArmError)."""
        for arm in self.arms:
            arm.enable(timeout)

    def query_firmware_limits(self) -> None:
        """0x472 to every motor of every arm that has not answered yet (:meth:`PiperArm.query_limits`)."""
        for arm in self.arms:
            arm.query_limits()

    def firmware_limits(self) -> tuple[FirmwareLimits, ...]:
        """Each arm's joint limits as its firmware reported them since connect (NaN where not yet)."""
        return tuple(arm.firmware_limits() for arm in self.arms)

    def state(self) -> RobotState | None:
        """Position (dof,) in policy units and the OLDEST arrival time of the joint and gripper frames used;
        None until every arm has sent all three joint frames and a gripper frame."""
        parts, times, statuses = [], [], []
        for arm in self.arms:
            fb = arm.feedback()
            if fb.joints is None or fb.gripper is None:
                return None
            parts.append(np.append(fb.joints, stroke_to_opening(fb.gripper.stroke)))
            times += [fb.joints_time, fb.gripper_time]
            statuses.append(arm.status())
        return RobotState(np.concatenate(parts), min(times), tuple(statuses))

    def status(self) -> tuple[ArmStatus, ...]:
        """One ArmStatus per arm."""
        return tuple(arm.status() for arm in self.arms)

    def command(self, target: np.ndarray) -> None:
        """Absolute targets (dof,) in policy units: per arm 0x151 (CAN mode, joint, speed), 0x155..0x157, 0x159.
        Nothing is clipped here: callers go through the safety layer."""
        target = np.asarray(target, dtype=np.float64)
        if target.shape != (self.dof,) or not np.all(np.isfinite(target)):
            raise ArmError(f"robot target must be {self.dof} finite values, got shape {target.shape}")
        for i, arm in enumerate(self.arms):
            t = target[i * ARM_DOF : (i + 1) * ARM_DOF]
            arm.set_joint_mode(self.speed_percent)
            arm.command_joints(t[:6])
            arm.command_gripper(float(opening_to_stroke(t[6])), self.gripper_effort)

    def _each(self, method: str) -> None:
        """Call ``method`` on every arm even if one fails; then raise the first failure."""
        first: HardwareError | None = None
        for arm in self.arms:
            try:
                getattr(arm, method)()
            except HardwareError as exc:
                first = first or exc
        if first is not None:
            raise first

    def emergency_stop(self) -> None:
        """E-stop every arm (all are tried even if one fails)."""
        self._each("emergency_stop")

    def resume(self) -> None:
        """Leave the e-stop on every arm; the motors are then unpowered: ``enable`` again."""
        self._each("resume")

    def disable(self) -> None:
        self._each("disable")

    def close(self) -> None:
        """Close every arm, then stop the simulators; raises the first failure after trying all."""
        first: HardwareError | None = None
        for stop in [arm.close for arm in self.arms] + [sim.stop for sim in self.simulators]:
            try:
                stop()
            except HardwareError as exc:
                first = first or exc
        if first is not None:
            raise first


_SIM_SPEC = re.compile(r"^sim(?::(\d+))?$")


def open_robot(
    spec: str, interface: str = "socketcan", *, bus_options: dict | None = None, **robot_options
) -> PiperRobot:
    """A PiperRobot from a spec (not yet connected; use ``with open_robot(...) as robot``).

    spec: ``can0`` or ``can0,can1`` (one bus per arm, left first, on ``interface``), or ``sim`` / ``sim:2``
    (one / two simulated arms on fresh in-process virtual buses, started by ``connect``, reachable as
    ``robot.simulators``). ``bus_options`` go to ``can.Bus`` for real buses (e.g. ``{"port": 43113}`` for
    udp_multicast); ``robot_options`` go to PiperRobot (speed_percent, gripper_effort).
    """
    spec = (spec or "").strip()
    m = _SIM_SPEC.match(spec)
    if m:
        n = int(m.group(1) or 1)
        if not 1 <= n <= 2:
            raise ArmError(f"robot spec {spec!r}: a simulated robot has 1 or 2 arms (sim or sim:2)")
        token = uuid.uuid4().hex[:8]
        channels = [f"dssp-sim-{token}-{side}" for side in (("left", "right") if n == 2 else ("arm",))]
        sims = [SimulatedPiper(ch, "virtual") for ch in channels]
        return PiperRobot([PiperArm(ch, "virtual") for ch in channels], simulators=sims, **robot_options)
    channels = [c.strip() for c in spec.split(",")]
    if not spec or any(not c for c in channels) or len(channels) > 2:
        raise ArmError(f"robot spec {spec!r} is invalid: give can0, can0,can1 (left,right), sim or sim:2")
    return PiperRobot([PiperArm(ch, interface, bus_options=bus_options) for ch in channels], **robot_options)
