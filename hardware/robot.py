"""The arm interface the control loop sees: one robot in the policy's joint space.

The policy's action and state are, per arm, [J1..J6 in radians, gripper opening in [0, 1]] (1 = open,
0 = closed), as RoboTwin's AgileX data; two arms give 14 values [left 7, right 7]. Implementations
(``hardware.piper``) convert to each device's units (the Piper's gripper is a stroke in metres).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np

from dssp_data.observation import VectorLayout

ARM_DOF = 7  # J1..J6 + gripper


@dataclass(frozen=True)
class ArmStatus:
    """Status of one arm, decoded from its feedback."""

    enabled: bool = False
    estop: bool = False
    error: bool = False  # any error bit or a non-normal arm status
    detail: str = ""  # human-readable reason when estop/error


@dataclass(frozen=True)
class RobotState:
    """What the robot reports: position (dof,) in policy units, with the arrival time of its oldest part."""

    position: np.ndarray  # (dof,) float64: per arm [J1..J6 rad, gripper 0..1]
    timestamp: float  # arrival time (the arms' clock) of the OLDEST feedback frame the position is built from
    status: tuple[ArmStatus, ...] = field(default_factory=tuple)  # one per arm


@dataclass(frozen=True)
class RobotDescription:
    """What a robot is, read from it by the loop, the safety layer and the observation contract (as LeRobot's
    robots expose their features), so that no caller re-derives it from constants.

    model: the hardware's name. layout: the (dof,) vector's arms and channels ("name unit", left arm first).
    lower, upper: (dof,) float64 bounds in policy units. gripper: (dof,) bool, the gripper values.
    max_joint_speed: rad/s, the slowest joint's rated speed (bounds the safety layer's step x rate).
    feedback_hz: the rate the arm's feedback arrives at (a control rate above it reuses feedback).
    """

    model: str
    layout: VectorLayout
    lower: np.ndarray
    upper: np.ndarray
    gripper: np.ndarray
    max_joint_speed: float
    feedback_hz: float

    def __post_init__(self) -> None:
        dof = self.layout.dim
        lower, upper = (np.array(v, dtype=np.float64).reshape(-1) for v in (self.lower, self.upper))
        gripper = np.array(self.gripper, dtype=bool).reshape(-1)
        if not lower.shape == upper.shape == gripper.shape == (dof,):
            raise ValueError(f"{self.model}: lower, upper and gripper must each have the layout's {dof} values")
        if not (np.all(np.isfinite(lower)) and np.all(np.isfinite(upper)) and np.all(lower <= upper)):
            raise ValueError(f"{self.model}: limits must be finite with lower <= upper")
        if not (self.max_joint_speed > 0 and self.feedback_hz > 0):
            raise ValueError(f"{self.model}: max_joint_speed and feedback_hz must be positive")
        for name, array in (("lower", lower), ("upper", upper), ("gripper", gripper)):
            array.setflags(write=False)
            object.__setattr__(self, name, array)

    @property
    def dof(self) -> int:
        return self.layout.dim

    @property
    def n_arms(self) -> int:
        return self.layout.arms

    @property
    def names(self) -> tuple[str, ...]:
        """(dof,) value names: ``J1 rad`` … for one arm; ``left.J1 rad`` … ``right.gripper opening 0..1`` for two."""
        channels, arms = self.layout.channels, self.layout.arms
        if arms == 1:
            return tuple(channels)
        sides = ("left", "right") if arms == 2 else tuple(f"arm{a}" for a in range(arms))
        return tuple(f"{side}.{c}" for side in sides for c in channels)

    def to_dict(self) -> dict:
        """JSON-ready (the run log states the robot it ran on)."""
        return {
            "model": self.model,
            "arms": self.layout.arms,
            "channels": list(self.layout.channels),
            "lower": self.lower.tolist(),
            "upper": self.upper.tolist(),
            "gripper": self.gripper.tolist(),
            "max_joint_speed": self.max_joint_speed,
            "feedback_hz": self.feedback_hz,
        }


@dataclass(frozen=True)
class FirmwareLimits:
    """The joint limits one arm's own firmware enforces, as the arm reports them (it clips targets to them, or faults).

    lower, upper: (n,) float64 rad per joint, NaN for a joint that has not answered yet. max_speed: (n,) rad/s.
    arm: who reported them, as a message names it ("the arm on can0"). resolution: rad, the step the firmware stores
    its limits in (a limit within half of it of another is that one, rounded). advice: (n,) what to do when a joint's
    limits are wrong (empty: a generic line). Nothing is checked on construction: a corrupted firmware reports
    min = max or min > max, and that is what start-up looks for (:func:`hardware.safety.firmware_limits_problem`).
    """

    lower: np.ndarray
    upper: np.ndarray
    max_speed: np.ndarray
    arm: str = "the arm"
    resolution: float = 0.0
    advice: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        arrays = [np.array(v, dtype=np.float64).reshape(-1) for v in (self.lower, self.upper, self.max_speed)]
        if len({a.shape for a in arrays}) != 1:
            raise ValueError(f"{self.arm}: lower, upper and max_speed must have one value per joint each")
        for name, array in zip(("lower", "upper", "max_speed"), arrays):
            array.setflags(write=False)
            object.__setattr__(self, name, array)

    @property
    def missing(self) -> tuple[int, ...]:
        """The joints (0-based) without an answer yet."""
        return tuple(int(j) for j in np.flatnonzero(np.isnan(self.lower) | np.isnan(self.upper)))


class Robot(ABC):
    """One or more arms as one vector. Every method raises ``dssp_core.errors.ArmError``/``CanError``.

    ``description`` says what the robot is (:class:`RobotDescription`) without touching the hardware.
    ``query_firmware_limits`` / ``firmware_limits`` read the joint limits the arms' own firmware enforces, which
    start-up compares with the safety layer's before anything is enabled
    (:meth:`hardware.rig.Rig.check_firmware_limits`); a robot whose hardware keeps no limits of its own keeps the
    defaults (nothing to ask, nothing to check)."""

    dof: int

    @property
    @abstractmethod
    def description(self) -> RobotDescription: ...

    @abstractmethod
    def connect(self) -> None: ...

    @abstractmethod
    def enable(self, timeout: float = 2.0) -> None:
        """Enable motors, confirmed from feedback within ``timeout`` seconds (else ArmError)."""

    @abstractmethod
    def state(self) -> RobotState | None:
        """The latest feedback (never blocks), or None before a full set of feedback frames arrived."""

    @abstractmethod
    def command(self, target: np.ndarray) -> None:
        """Send absolute joint + gripper targets (dof,) in policy units. Callers go through the safety layer."""

    def query_firmware_limits(self) -> None:
        """Ask every arm that has not answered yet for the joint limits its firmware enforces (never blocks; the
        answers come in :meth:`firmware_limits`). Default: nothing to ask."""

    def firmware_limits(self) -> tuple[FirmwareLimits, ...]:
        """What each arm's firmware has reported of its joint limits so far, in arm order (NaN where a joint has not
        answered). Default: () — no arm keeps limits of its own."""
        return ()

    @abstractmethod
    def emergency_stop(self) -> None: ...

    @abstractmethod
    def disable(self) -> None: ...

    @abstractmethod
    def close(self) -> None: ...

    def __enter__(self) -> "Robot":
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.close()
