"""One robot's devices as one thing: the camera, the arms, their safety settings and the clock they stamp on.

    rig = Rig(camera, robot, camera_to_base, SafetyConfig.load("safety.json"), recorders=[BusRecorder(...)])
    with rig:                                   # the camera, then the arms, then the CAN recorders
        Runner(ModelPolicy(policy, rate_hz=10), rig, cloud_config, LoopSettings(rate_hz=10)).run()
                                                # closed in the reverse order, whatever ends the block

Each part stays behind its own small interface with its fake: :class:`hardware.camera.base.Camera` (RealSense,
the tabletop simulator, the MuJoCo camera, a recording), :class:`hardware.robot.Robot` (the Piper on CAN, the CAN
simulator, the MuJoCo Piper), :mod:`hardware.clock` (the real clock or a manual one in tests). The robot describes
itself (:class:`hardware.robot.RobotDescription`: joints, limits, gripper, rates, arm layout); the safety layer and
the observation contract read the limits and the layout from ``rig.description``, never from constants.

Shapes: ``camera_to_base`` (4, 4) float64, the camera's pose in the robot-base frame; ``limits`` (lower (dof,),
upper (dof,), gripper (dof,) bool) in policy units.
"""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import ContextManager

import numpy as np

from dssp_core.errors import ConfigError
from hardware.camera.base import Camera
from hardware.clock import REAL_CLOCK, Clock
from hardware.robot import Robot, RobotDescription
from hardware.safety import SafetyConfig


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
