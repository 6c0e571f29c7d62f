"""One robot's devices as one thing: the camera, the arms, their safety settings and the clock they stamp on.

    rig = Rig(camera, robot, camera_to_base, SafetyConfig.load("safety.json"), recorders=[BusRecorder(...)])
    with rig:                                   # the camera, then the arms, then the CAN recorders
        Runner(ModelPolicy(policy, control_rate_hz=10), rig, cloud_config, LoopSettings(control_rate_hz=10)).run()
                                                # closed in the reverse order, whatever ends the block

Each part stays behind its own small interface with its fake: :class:`hardware.camera.base.Camera` (RealSense,
the tabletop simulator, the MuJoCo camera, a recording), :class:`hardware.robot.Robot` (the Piper on CAN, the CAN
simulator, the MuJoCo Piper), :mod:`hardware.clock` (the real clock or a manual one in tests). The robot describes
itself (:class:`hardware.robot.RobotDescription`: joints, limits, gripper, rates, arm layout); the safety layer and
the observation contract read the limits and the layout from ``rig.description``, never from constants.

Before anything is enabled the rig reads the joint limits the arms' own firmware enforces and refuses, with one
line, those that would clip or fault inside what the safety layer lets the policy command
(:meth:`Rig.check_firmware_limits`: the control loop's start calls it before it enables the arms; ``dssp-record``
before it records).

Shapes: ``camera_to_base`` (4, 4) float64, the camera's pose in the robot-base frame; ``limits`` (lower (dof,),
upper (dof,), gripper (dof,) bool) in policy units.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import ContextManager

import numpy as np

from dssp_core.errors import ArmError, ConfigError
from hardware.camera.base import Camera
from hardware.clock import REAL_CLOCK, Clock
from hardware.robot import Robot, RobotDescription
from hardware.safety import SafetyConfig, allowed_range, firmware_limits_problem

LIMIT_QUERY_TIMEOUT = 1.0
"""s (of the rig's clock) the arms get to answer the joint-limit query; a Piper answers within milliseconds."""
LIMIT_QUERY_REPEAT = 0.1
"""s between two queries to the arms that have not answered (a frame can be missed, as with enabling)."""


@dataclass
class Rig:
    """The devices of one robot, opened and closed together.

    camera: the depth camera (not started yet: :meth:`__enter__` starts it), or None for a loop whose policy source
    needs no point cloud (``dssp-replay``). robot: the arms as one vector (not
    connected yet). camera_to_base: (4, 4), the camera's pose in the robot-base frame. safety: the safety layer's
    settings. clock: the timeline of the camera's and the arms' timestamps. recorders: what else opens with the
    devices and closes after them (the CAN-bus recorders of ``dssp-run``), entered after the arms, whose
    simulators must be up first. limits: narrower joint limits than the robot's own (a test, a cautious first
    run); None: the robot's.
    """

    camera: Camera | None
    robot: Robot
    camera_to_base: np.ndarray
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    clock: Clock = REAL_CLOCK
    recorders: Sequence[ContextManager] = ()
    limits: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    _open: contextlib.ExitStack | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        pose = np.asarray(self.camera_to_base, dtype=np.float64)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise ConfigError(f"camera_to_base must be a finite 4x4 matrix, got shape {pose.shape}")
        self.camera_to_base = pose
        if self.limits is not None:
            dof = self.robot.dof
            lower, upper, gripper = (np.asarray(v) for v in self.limits)
            if not lower.shape == upper.shape == gripper.shape == (dof,):
                raise ConfigError(f"limits must be (lower, upper, gripper) of the robot's {dof} values each")

    @property
    def description(self) -> RobotDescription:
        """What the arms are (read from the robot, without touching the hardware)."""
        return self.robot.description

    def joint_limits(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(lower (dof,), upper (dof,), gripper (dof,) bool): ``limits`` if given, else the robot's own."""
        if self.limits is not None:
            return self.limits
        described = self.description
        return described.lower, described.upper, described.gripper

    def check_firmware_limits(self, stopped: Callable[[], bool] = lambda: False) -> None:
        """Read the joint limits the arms' own firmware enforces (:meth:`Robot.query_firmware_limits`, asked again
        every :data:`LIMIT_QUERY_REPEAT` s, polled on the rig's clock) and refuse, with one line (ArmError), an arm
        that does not answer within :data:`LIMIT_QUERY_TIMEOUT` s, or whose limits would clip or fault inside what the
        safety layer lets the policy command (:func:`hardware.safety.firmware_limits_problem` against
        :func:`hardware.safety.allowed_range` of :meth:`joint_limits` and ``safety``). Sends only the query: call it
        once the arms are open and before they are enabled. Returns early when ``stopped()`` (a stop request). A robot
        without limits of its own (``firmware_limits() == ()``) passes at once."""
        clock, robot = self.clock, self.robot
        start = clock.now()
        deadline, next_query = start + LIMIT_QUERY_TIMEOUT, start
        while True:
            reported = robot.firmware_limits()
            if stopped() or all(not arm.missing for arm in reported):
                break
            now = clock.now()
            if now > deadline:
                silent = next(arm for arm in reported if arm.missing)
                joints = ",".join(f"J{j + 1}" for j in silent.missing)
                raise ArmError(
                    f"{silent.arm} did not answer the joint-limit query (0x472) for {joints} within "
                    f"{LIMIT_QUERY_TIMEOUT:g} s, so its firmware limits are unknown: check that it is "
                    "powered and on this bus; an arm that sends feedback but never answers needs a newer "
                    "firmware (AgileX's Piper tool), then start again"
                )
            if now >= next_query:
                robot.query_firmware_limits()
                next_query = now + LIMIT_QUERY_REPEAT
            clock.sleep(0.005)
        if stopped() or not reported:  # a stop request; a robot without limits of its own
            return
        lower, upper, gripper = self.joint_limits()
        lower, upper = allowed_range(self.safety, lower, upper, gripper)
        gripper = np.asarray(gripper, bool)
        if len(reported) != self.description.n_arms:
            raise ArmError(f"{len(reported)} arms reported firmware limits, the robot has {self.description.n_arms}")
        per_arm = self.description.dof // self.description.n_arms
        for i, arm in enumerate(reported):
            entries = np.arange(i * per_arm, (i + 1) * per_arm)
            joints = entries[~gripper[entries]]
            problem = firmware_limits_problem(arm, lower[joints], upper[joints])
            if problem is not None:
                raise ArmError(problem)

    def __enter__(self) -> "Rig":
        if self._open is not None:
            raise RuntimeError("the rig is already open")
        with contextlib.ExitStack() as stack:  # a part that fails to open closes the ones opened before it
            if self.camera is not None:
                stack.enter_context(self.camera)
            stack.enter_context(self.robot)
            for recorder in self.recorders:
                stack.enter_context(recorder)
            self._open = stack.pop_all()
        return self

    def __exit__(self, *exc_info) -> None:
        opened, self._open = self._open, None
        if opened is not None:
            opened.__exit__(*exc_info)
