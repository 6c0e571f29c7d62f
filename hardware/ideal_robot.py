"""A robot with ideal tracking: it is wherever it was last commanded, at once (``dssp-replay`` without an arm).

    robot = IdealRobot(piper_description(1), start=first_state, clock=FakeClock())

Its feedback (:meth:`state`) is the last command, or ``start`` before any, stamped with the clock's time when read
(ideal feedback is never stale). It never faults. It stands in for the arms where the question is what the safety
layer does to a sequence of actions, not what an arm does with the commands. Shapes: (dof,) in policy units.
"""

from __future__ import annotations

import numpy as np

from hardware.clock import REAL_CLOCK, Clock
from hardware.robot import ArmStatus, Robot, RobotDescription, RobotState


class IdealRobot(Robot):
    def __init__(self, description: RobotDescription, start: np.ndarray, clock: Clock = REAL_CLOCK):
        self._description, self.clock = description, clock
        self.dof = description.dof
        self.position = np.array(start, dtype=np.float64).reshape(self.dof)
        self.commands = 0

    @property
    def description(self) -> RobotDescription:
        return self._description

    def connect(self) -> None:
        pass

    def enable(self, timeout: float = 2.0) -> None:
        pass

    def state(self) -> RobotState:
        status = tuple(ArmStatus(enabled=True) for _ in range(self._description.n_arms))
        return RobotState(self.position.copy(), self.clock.now(), status)

    def command(self, target: np.ndarray) -> None:
        self.position = np.array(target, dtype=np.float64).reshape(self.dof)
        self.commands += 1

    def emergency_stop(self) -> None:
        pass

    def disable(self) -> None:
        pass

    def close(self) -> None:
        pass
