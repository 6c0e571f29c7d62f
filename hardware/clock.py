"""The time source of the control loop, the recorder and the safety layer: ``now()`` and ``sleep(dt)``.

    clock = REAL_CLOCK                 # time.monotonic seconds; sleep blocks
    clock = FakeClock()                # manual time: starts at 0, moves only by sleep() or advance()
    t = clock.now(); clock.sleep(0.1)  # a clock is also callable: clock() == clock.now()

Being callable, a clock goes wherever a plain time source is taken (``BusMonitor(clock=...)``,
``StampedCamera(clock=...)``). Every time a loop compares (a tick's time against a frame's or a feedback's
arrival) must come from one clock: with a manual clock, the devices have to stamp on it too (a device
thread stamping ``time.monotonic()`` lives on another timeline).
"""

from __future__ import annotations

import time
from typing import Protocol


class Clock(Protocol):
    """Seconds on one timeline (``now``), and a wait on it (``sleep``; a non-positive ``dt`` returns at once)."""

    def now(self) -> float: ...

    def sleep(self, dt: float) -> None: ...

    def __call__(self) -> float: ...


class RealClock:
    """Wall time: ``time.monotonic()`` and ``time.sleep``."""

    def now(self) -> float:
        return time.monotonic()

    __call__ = now

    def sleep(self, dt: float) -> None:
        if dt > 0:
            time.sleep(dt)

    def __repr__(self) -> str:
        return "RealClock()"


REAL_CLOCK = RealClock()


class FakeClock:
    """Manual time in seconds: starts at ``start`` and moves only when slept through or advanced.

    ``sleep(dt)`` returns at once, ``dt`` later on this clock; nothing moves it in between, so code driven
    by it sees the same times on any machine.
    """

    def __init__(self, start: float = 0.0) -> None:
        self.t = float(start)

    def now(self) -> float:
        return self.t

    __call__ = now

    def sleep(self, dt: float) -> None:
        if dt > 0:
            self.t += float(dt)

    def advance(self, dt: float) -> None:
        """Move time ``dt`` >= 0 seconds on (something took that long)."""
        if not dt >= 0:
            raise ValueError(f"time only moves forward: advance({dt!r})")
        self.t += float(dt)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(t={self.t:g})"
