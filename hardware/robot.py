"""The arm interface the control loop sees: one robot in the policy's joint space.

The policy's action and state are, per arm, [J1..J6 in radians, gripper opening in [0, 1]] (1 = open,
0 = closed), as RoboTwin's AgileX data; two arms give 14 values [left 7, right 7]. Implementations
(``hardware.piper``) convert to each device's units (the Piper's gripper is a stroke in metres).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np

from dssp_data.errors import ConfigError

ARM_DOF = 7  # J1..J6 + gripper

MIN_RATE_HZ, MAX_RATE_HZ = 0.1, 1000.0
"""Control rates the loop can keep: below 0.1 Hz a tick outlasts any sensible timeout; the Piper's CAN
feedback arrives at 200 Hz, so above 1000 Hz every tick would reuse the same feedback."""


def check_rate(rate, flag: str = "--rate") -> float:
    """``rate`` in [MIN_RATE_HZ, MAX_RATE_HZ] Hz as a float, else a one-line ConfigError naming ``flag``."""
    if isinstance(rate, bool) or not isinstance(rate, (int, float)) or not math.isfinite(rate) \
            or not MIN_RATE_HZ <= rate <= MAX_RATE_HZ:
        raise ConfigError(f"{flag} must be in [{MIN_RATE_HZ:g}, {MAX_RATE_HZ:g}] Hz, got {rate!r}")
    return float(rate)


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


class Robot(ABC):
    """One or more arms as one vector. Every method raises ``dssp_data.errors.ArmError``/``CanError``."""

    dof: int

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
