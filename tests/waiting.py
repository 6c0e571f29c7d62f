"""Waiting in tests: for a real device on wall time (``wait_for``), for a line a subprocess prints
(``Output``), for a signal's handler to raise (``until_interrupted``), or on a manual clock whose sleeps move
the simulated devices (``World``), so that the code under test never waits at all."""

import os
import select
import signal
import threading
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


class Output:
    """The stdout and stderr of ``proc`` (a ``subprocess.Popen`` with both piped, text mode), read on two threads
    as the process writes them: :meth:`wait_for_line` wakes on each new line (no polling), :meth:`communicate`
    is ``Popen.communicate``'s (out, err). Reading both keeps either pipe from filling up while a test waits."""

    STREAMS = ("stdout", "stderr")

    def __init__(self, proc) -> None:
        self.proc = proc
        self._changed = threading.Condition()
        self._lines = {name: [] for name in self.STREAMS}
        self._ended = set()
        self._threads = [threading.Thread(target=self._read, args=(name,), daemon=True) for name in self.STREAMS]
        for thread in self._threads:
            thread.start()

    def _read(self, name: str) -> None:
        try:
            for line in getattr(self.proc, name):
                with self._changed:
                    self._lines[name].append(line)
                    self._changed.notify_all()
        finally:
            with self._changed:
                self._ended.add(name)
                self._changed.notify_all()

    def wait_for_line(self, stream: str, text: str, timeout: float = 60.0, what: str | None = None) -> bool:
        """True once a line of ``stream`` holds ``text``; False if the stream ended first (the process ended);
        AssertionError after ``timeout`` seconds of neither."""

        def seen() -> bool:
            return any(text in line for line in self._lines[stream])

        with self._changed:
            if not self._changed.wait_for(lambda: seen() or stream in self._ended, timeout):
                raise AssertionError(f"{what or repr(text)} not printed within {timeout} s")
            return seen()

    def communicate(self, timeout: float = 60.0) -> tuple[str, str]:
        """(stdout, stderr), all of them, once the process has ended (``timeout``: as ``Popen.wait``'s)."""
        self.proc.wait(timeout=timeout)
        for thread in self._threads:
            thread.join(timeout)
        with self._changed:
            return "".join(self._lines["stdout"]), "".join(self._lines["stderr"])


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
