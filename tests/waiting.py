"""Waiting in tests: for a real device on wall time (``wait_for``), or on a manual clock whose sleeps move
the simulated devices (``World``), so that the code under test never waits at all."""

import time

from hardware.clock import FakeClock


def wait_for(predicate, timeout: float = 5.0, what: str = "condition", poll: float = 0.003):
    """The first truthy ``predicate()`` within ``timeout`` seconds, else AssertionError naming ``what``."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"{what} not reached within {timeout} s")
        time.sleep(poll)


class World(FakeClock):
    """Manual time in which the devices move while the loop sleeps: ``sleep(dt)`` advances the clock, then
    calls each of ``steps`` with ``dt`` (the devices move and report); ``advance(dt)``, time the loop spends
    computing, moves nothing."""

    def __init__(self, start: float = 0.0) -> None:
        super().__init__(start)
        self.steps = []

    def sleep(self, dt: float) -> None:
        super().sleep(dt)
        if dt > 0:
            for step in self.steps:
                step(dt)
