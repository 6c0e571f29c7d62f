"""Waiting in tests: for a real device on wall time (``wait_for``), for a signal's handler to raise
(``until_interrupted``), or on a manual clock whose sleeps move the simulated devices (``World``), so that
the code under test never waits at all."""

import os
import select
import signal
import time

from hardware.clock import FakeClock


def wait_for(predicate, timeout: float = 5.0, what: str = "condition", poll: float = 0.003):
    """The first truthy ``predicate()`` within ``timeout`` seconds, else AssertionError naming ``what``.

    The one place the tests poll: for what cannot tell when it changes (a file another process writes, a
    process's state under /proc, a device thread's latest report). What can signal is waited on instead."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"{what} not reached within {timeout} s")
        time.sleep(poll)


def until_interrupted(timeout: float = 10.0) -> None:
    """Wait in the main thread until a signal's handler raises here (a Ctrl-C: KeyboardInterrupt); return if none
    did within ``timeout`` s. The wait is on Python's signal wakeup fd: every signal Python records writes it,
    including one that ``_thread.interrupt_main`` simulates (which no blocking call would notice), so the wait
    ends the moment the signal is recorded, and its handler runs as this function goes on."""
    r, w = os.pipe()
    os.set_blocking(w, False)
    previous = signal.set_wakeup_fd(w)
    try:
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            if select.select([r], [], [], left)[0]:
                os.read(r, 512)  # a signal whose handler returned: wait on for one that raises
    finally:
        signal.set_wakeup_fd(previous)
        os.close(r)
        os.close(w)


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
