"""Joint limits and gripper range of the AgileX Piper: the one place the driver, simulator and safety
layer read them from.

Device units: joints in radians, gripper stroke in metres. Policy units per arm: [J1..J6 radians,
gripper opening in [0, 1]] where opening g means stroke ``g * GRIPPER_STROKE_MAX``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dssp_data.observation import piper_layout
from hardware.robot import ARM_DOF, RobotDescription

N_JOINTS = 6

# Joint limits (rad), J1..J6, as the piper-sdk's parameter manager lists them. They lie slightly inside
# the round-degree values of its table (J1 +-150 deg, J2 0..180, J3 -170..0, J4 +-100, J5 +-70,
# J6 +-120 deg); J6 is 2.09439 there while other notes give 2.0944 (just above 120 deg): the smaller is used.
JOINT_LOWER = np.array([-2.6179, 0.0, -2.967, -1.745, -1.22, -2.09439])
JOINT_UPPER = np.array([2.6179, 3.14, 0.0, 1.745, 1.22, 2.09439])
JOINT_LOWER.setflags(write=False)
JOINT_UPPER.setflags(write=False)

# Joint limits (degrees), J1..J6, as the arm's firmware holds them (0x473 reports them in 0.1 degree): the round-degree
# values of that table. The simulated arms report them, and a corrupted arm's limits are reset to them (0x474,
# piper-sdk's MotorAngleLimitMaxSpdSet). Each range contains JOINT_LOWER..JOINT_UPPER.
FIRMWARE_LOWER_DEG = (-150.0, 0.0, -170.0, -100.0, -70.0, -120.0)
FIRMWARE_UPPER_DEG = (150.0, 180.0, 0.0, 100.0, 70.0, 120.0)

# Joint speed (rad/s): AgileX rates the Piper's joints at 180 deg/s (J1, J3) to 225 deg/s (J4-J6); the
# slowest, pi rad/s, bounds what a per-tick step times the control rate may ask of any joint.
MAX_JOINT_SPEED = 3.14159

# Feedback rate (Hz): the Piper reports joints, gripper and status at 200 Hz.
FEEDBACK_HZ = 200.0

# Gripper stroke (m): the SDK's gripper range is 0..0.07 m (AgileX's ROS node clamps to 0..0.08 m).
GRIPPER_STROKE_MIN = 0.0
GRIPPER_STROKE_MAX = 0.07
# Gripper effort (N·m) in 0x159: 0..5000 in 0.001 N·m.
GRIPPER_EFFORT_MAX = 5.0


def opening_to_stroke(g):
    """Policy gripper opening in [0, 1] (scalar or array) -> stroke in metres."""
    return np.asarray(g, dtype=np.float64) * GRIPPER_STROKE_MAX


def stroke_to_opening(stroke):
    """Gripper stroke in metres (scalar or array) -> policy opening (1 = 0.07 m, open)."""
    return np.asarray(stroke, dtype=np.float64) / GRIPPER_STROKE_MAX


@dataclass(frozen=True)
class JointLimits:
    """Lower/upper bounds of policy values: (7 * n_arms,) arrays, per arm [J1..J6 rad, gripper 0..1].

    ``JointLimits.piper()`` is one arm; ``.tile(2)`` gives the 14 values of a dual-arm robot
    [left 7, right 7]. The arrays are read-only.
    """

    lower: np.ndarray
    upper: np.ndarray

    def __post_init__(self) -> None:
        lower = np.array(self.lower, dtype=np.float64).reshape(-1)
        upper = np.array(self.upper, dtype=np.float64).reshape(-1)
        if lower.shape != upper.shape or lower.size % ARM_DOF:
            raise ValueError(f"limits need two arrays of 7 * n_arms values, got {lower.shape} and {upper.shape}")
        if not (np.all(np.isfinite(lower)) and np.all(np.isfinite(upper)) and np.all(lower <= upper)):
            raise ValueError("limits must be finite with lower <= upper")
        lower.setflags(write=False)
        upper.setflags(write=False)
        object.__setattr__(self, "lower", lower)
        object.__setattr__(self, "upper", upper)

    @classmethod
    def piper(cls) -> "JointLimits":
        """One Piper arm: (7,) bounds, joints from ``JOINT_LOWER/UPPER``, gripper opening [0, 1]."""
        return cls(np.append(JOINT_LOWER, 0.0), np.append(JOINT_UPPER, 1.0))

    @property
    def dof(self) -> int:
        return int(self.lower.size)

    @property
    def n_arms(self) -> int:
        return self.dof // ARM_DOF

    def tile(self, n_arms: int) -> "JointLimits":
        """These limits repeated for ``n_arms`` arms: (7 * n_arms * self.n_arms,) bounds."""
        if n_arms < 1:
            raise ValueError(f"n_arms must be >= 1, got {n_arms}")
        return JointLimits(np.tile(self.lower, n_arms), np.tile(self.upper, n_arms))

    def clip(self, values: np.ndarray) -> np.ndarray:
        """``values`` (dof,) clipped into the limits (a new float64 array)."""
        return np.clip(np.asarray(values, dtype=np.float64), self.lower, self.upper)

    def violations(self, values: np.ndarray, tol: float = 0.0) -> np.ndarray:
        """Indices (k,) of the values outside [lower - tol, upper + tol] (NaN counts as outside)."""
        v = np.asarray(values, dtype=np.float64)
        inside = (v >= self.lower - tol) & (v <= self.upper + tol)
        return np.flatnonzero(~inside)


def piper_description(n_arms: int = 1) -> RobotDescription:
    """``n_arms`` Pipers (1 or 2, left first) as the loop, the safety layer and the observation contract see them:
    per arm [J1..J6 rad within ``JOINT_LOWER/UPPER``, gripper opening 0..1], the slowest joint's speed, the
    feedback rate."""
    limits = JointLimits.piper().tile(n_arms)
    return RobotDescription(
        model="AgileX Piper",
        layout=piper_layout(n_arms),
        lower=limits.lower,
        upper=limits.upper,
        gripper=np.tile(np.arange(ARM_DOF) == ARM_DOF - 1, n_arms),
        max_joint_speed=MAX_JOINT_SPEED,
        feedback_hz=FEEDBACK_HZ,
    )
