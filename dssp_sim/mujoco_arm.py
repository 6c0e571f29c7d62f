"""The simulated Piper of ``hardware.piper.can_simulator`` with MuJoCo doing the motion.

It speaks the Piper CAN protocol exactly as the kinematic simulator does (feedback frames, enable,
e-stop, error bits, the joint-limit query); only the motion differs: the commanded joint and gripper targets go to
the MuJoCo position actuators of a :class:`~dssp_sim.env.PiperEnv`, and the feedback reports the measured joints.
The joint limits it reports for 0x472 (its firmware's) are the MJCF's joint ranges, unless ``firmware_limits`` says
otherwise.

Run it stepped, in lockstep with the control loop (``start(thread=False)``): ``step(dt)`` handles the
command frames received so far, advances the physics ``dt`` seconds and sends one round of feedback.
``step(0.0)`` only answers (no physics): used while the driver enables the arm.
"""

from __future__ import annotations

import numpy as np

from hardware.piper import codec
from hardware.piper.can_simulator import SimulatedPiper
from hardware.robot import FirmwareLimits


def mjcf_limits(env, max_speed: float | np.ndarray) -> FirmwareLimits:
    """The joint ranges J1..J6 of ``env``'s MJCF (``model.jnt_range`` of the arm's hinges) as firmware limits, with
    ``max_speed`` rad/s per joint."""
    ranges = env.model.jnt_range[env.model.dof_jntid[env.arm.dof]]  # (6, 2): the arm's hinges, J1..J6
    return FirmwareLimits(
        ranges[:, 0],
        ranges[:, 1],
        np.broadcast_to(np.asarray(max_speed, dtype=np.float64), (6,)),
        arm="the MJCF",
        resolution=codec.LIMIT_RESOLUTION,
    )


class MujocoPiper(SimulatedPiper):
    def __init__(self, env, channel: str, interface: str = "virtual", **kwargs):
        """env: a :class:`dssp_sim.env.PiperEnv` (already reset); the arm starts where the env's arm is. ``kwargs`` go
        to :class:`SimulatedPiper` (``firmware_limits``: by default the MJCF's joint ranges)."""
        self.env = env
        super().__init__(
            channel, interface, initial_joints=env.joint_positions(), initial_stroke=env.gripper_stroke(), **kwargs
        )
        if kwargs.get("firmware_limits") is None:
            self.firmware_limits = mjcf_limits(env, self.max_joint_speed)
        self.sync_from_env()

    def sync_from_env(self) -> None:
        """Take the env's measured pose as the arm's position and target (after ``env.reset``)."""
        with self._lock:
            self._q = np.array(self.env.joint_positions(), dtype=np.float64)
            self._target = self._q.copy()
            self._stroke = float(self.env.gripper_stroke())
            self._stroke_target = self._stroke

    def _advance(self, dt: float) -> None:
        self.ticks += 1
        if dt <= 0:
            return
        joints = self._q.copy()
        if self._moving_allowed() and self._ctrl_mode == codec.CTRL_MODE_CAN and self._move_mode == codec.MOVE_MODE_J:
            joints = np.where(self._joint_enabled, self._target, self._q)  # a disabled motor holds (no gravity drop)
        stroke = self._stroke_target if self._gripper_enabled and self._moving_allowed() else self._stroke
        self.env.set_targets(joints, stroke)
        self.env.advance(dt)
        self._q = np.array(self.env.joint_positions(), dtype=np.float64)
        self._stroke = float(self.env.gripper_stroke())
