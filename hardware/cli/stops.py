"""How a robot command is stopped: every signal that would end the process, and an output stream that went away,
become one stop request — the same safe stop as Ctrl-C (``dssp-run``, ``dssp-record``, ``dssp-replay``,
``dssp-sim-arm``).

    stops = Stops()                     # first thing in main(): from here no such signal ends the process
    ...; stops.check()                  # between start-up stages: StartupInterrupted once a stop was asked for
    stops.during(runner.request_stop)   # the loop's stop: called at once (a stop that came first) or when one comes
    ...
    code = stops.code                   # 128 + the signal's number; 141 for a lost stdout/stderr
    stops.restore()

The signals (:func:`stop_signals`): every signal whose default action ends the process (signal(7): "Term" and
"Core"), derived from :func:`signal.valid_signals` — the real-time signals included — by leaving out those whose
default is to ignore, stop or continue the process, the two no process can catch (SIGKILL, SIGSTOP), and the
hardware faults of the process's own code (SIGSEGV, SIGBUS, SIGFPE, SIGILL): a Python handler runs only after the
faulting instruction, which would repeat forever, so a crash stays a crash. Python's own ignores (SIGPIPE, SIGXFSZ)
and a signal inherited as ignored (``nohup``'s SIGHUP) are taken too: a robot command does not go on unattended
once its terminal is gone (keep a run going with tmux, screen or a service instead). A handler someone else
installed from Python (a profiler, a test runner's timeout) is left alone.

The streams: stdout and stderr are wrapped so that a write that fails (a closed pipe, a terminal that hung up:
BrokenPipeError, EIO, ...) asks for the stop instead of raising in the middle of the loop, and a watcher thread
notices a pipe whose reader closed it, or a terminal that hung up, even while nothing is printed (``--quiet``).
The lost stream is then pointed at /dev/null: every later write, the final summary's included, goes nowhere
quietly (the episode log keeps it).

The first stop wins; a later one changes nothing (a second Ctrl-C does not cut the final hold short). Only the
standard library: ``main()`` installs this before the heavy imports.
"""

from __future__ import annotations

import os
import select
import signal
import sys
import threading
from collections.abc import Callable

from dssp_core.cli_runner import is_default_interrupt_handler

LOST_STREAM_CODE = 128 + 13
"""The exit code after stdout or stderr went away: as for SIGPIPE (its reader went away), as shells report it."""

# signal(7): the default action ignores ("Ign"), stops ("Stop") or continues ("Cont") the process: not a stop.
_NOT_ENDING = frozenset(
    {"SIGCHLD", "SIGCLD", "SIGCONT", "SIGURG", "SIGWINCH", "SIGTSTP", "SIGTTIN", "SIGTTOU", "SIGINFO"}
)
_UNCATCHABLE = frozenset({"SIGKILL", "SIGSTOP"})
_OWN_FAULTS = frozenset({"SIGSEGV", "SIGBUS", "SIGFPE", "SIGILL"})


class StartupInterrupted(Exception):
    """A stop came before the control loop started: nothing was enabled or sent."""


def signal_name(signum: int) -> str:
    """``SIGTERM``; a real-time signal without a name of its own: ``SIGRTMIN+3``."""
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"SIGRTMIN+{signum - signal.SIGRTMIN}" if hasattr(signal, "SIGRTMIN") else f"signal {signum}"


def stop_signals() -> tuple[int, ...]:
    """Every signal number whose default action ends the process and on which a Python handler can act."""
    left_out = _NOT_ENDING | _UNCATCHABLE | _OWN_FAULTS
    return tuple(sorted(int(s) for s in signal.valid_signals() if signal_name(int(s)) not in left_out))


def exit_code(signum: int) -> int:
    """The exit code of a command stopped by ``signum``: 128 + its number, as shells report a signal."""
    return 128 + int(signum)


class Stops:
    """The stop request of one command (see the module's docstring). ``streams``: also watch stdout and stderr."""

    def __init__(self, streams: bool = True) -> None:
        self.reason: str | None = None  # "SIGHUP", "lost stdout (Broken pipe)", ...; None: no stop asked for
        self.code: int | None = None  # the exit code that goes with it
        self._target: Callable[[str], None] | None = None
        self._previous: dict[int, object] = {}
        self._streams: list[_WatchedStream] = []
        self._watcher: _StreamWatcher | None = None
        if threading.current_thread() is threading.main_thread():  # signals reach the main thread only
            for signum in stop_signals():
                current = signal.getsignal(signum)
                if current in (signal.SIG_DFL, signal.SIG_IGN) or is_default_interrupt_handler(current):
                    self._previous[signum] = signal.signal(signum, self._signalled)
        if streams:
            for name in ("stdout", "stderr"):
                stream = getattr(sys, name)
                if stream is not None and not isinstance(stream, _WatchedStream):
                    watched = _WatchedStream(stream, name, self)
                    setattr(sys, name, watched)
                    self._streams.append(watched)
            self._watcher = _StreamWatcher(self._streams)

    @property
    def signals(self) -> tuple[int, ...]:
        """The signal numbers this instance handles."""
        return tuple(self._previous)

    def _signalled(self, signum: int, _frame) -> None:
        self.stop(signal_name(signum), exit_code(signum))

    def stop(self, reason: str, code: int) -> None:
        """Ask for the stop (the first reason wins): the current target is told at once."""
        if self.reason is not None:
            return
        self.reason, self.code = reason, code
        target = self._target
        if target is not None:
            target(reason)

    def during(self, target: Callable[[str], None] | None) -> None:
        """From now on a stop calls ``target(reason)`` (None: nobody; :meth:`check` then sees it); a stop that
        came already is passed on at once."""
        self._target = target
        if target is not None and self.reason is not None:
            target(self.reason)

    def check(self) -> None:
        """Raise :class:`StartupInterrupted` (the reason) once a stop was asked for."""
        if self.reason is not None:
            raise StartupInterrupted(self.reason)

    def restore(self) -> None:
        """Put back the signal handlers and the streams found at start (idempotent)."""
        self._target = None
        for signum, previous in self._previous.items():
            signal.signal(signum, previous)
        self._previous = {}
        if self._watcher is not None:
            self._watcher.close()
            self._watcher = None
        for watched in self._streams:
            if getattr(sys, watched.name) is watched:
                setattr(sys, watched.name, watched.stream)
        self._streams = []


def run_stoppable(body: Callable, args, stops: Stops | None, nothing_done: str) -> int:
    """``body(args, stops)`` → exit code, with a stop during start-up (:class:`StartupInterrupted`) as one line
    ("stopped by SIGHUP during start-up; " + ``nothing_done``) and ``stops.code``; ``stops``: the request main()
    installed (None: installed here, and restored at the end)."""
    own = stops is None
    stops = stops or Stops()
    try:
        stops.check()
        return body(args, stops)
    except StartupInterrupted as exc:
        print(f"stopped by {exc} during start-up; {nothing_done}", file=sys.stderr)
        return stops.code
    finally:
        if own:
            stops.restore()


def _to_devnull(stream) -> None:
    """Point the file descriptor under ``stream`` at /dev/null (a stream without one: nothing to do)."""
    try:
        fd = stream.fileno()
        devnull = os.open(os.devnull, os.O_WRONLY)
    except (OSError, ValueError, AttributeError):
        return
    try:
        os.dup2(devnull, fd)
    except OSError:
        pass
    finally:
        os.close(devnull)


class _WatchedStream:
    """stdout or stderr: a write that fails because the stream went away asks for the stop and is dropped."""

    def __init__(self, stream, name: str, stops: Stops) -> None:
        self.stream, self.name, self._stops = stream, name, stops
        self.lost = False

    def write(self, text: str) -> int:
        if not self.lost:
            try:
                return self.stream.write(text)
            except (OSError, ValueError) as exc:  # ValueError: the stream was closed
                self.went_away(getattr(exc, "strerror", None) or str(exc))
        return len(text)

    def writelines(self, lines) -> None:
        for line in lines:
            self.write(line)

    def flush(self) -> None:
        if not self.lost:
            try:
                self.stream.flush()
            except (OSError, ValueError) as exc:
                self.went_away(getattr(exc, "strerror", None) or str(exc))

    def went_away(self, why: str) -> None:
        if self.lost:
            return
        self.lost = True
        _to_devnull(self.stream)
        self._stops.stop(f"lost {self.name} ({why})", LOST_STREAM_CODE)

    def __getattr__(self, name: str):
        return getattr(self.stream, name)


class _StreamWatcher:
    """A thread that polls the streams' descriptors for a pipe whose reader closed it or a terminal that hung up
    (POLLERR / POLLHUP): the stream went away although nothing was written to it. Files never report either."""

    def __init__(self, streams: list[_WatchedStream]) -> None:
        self._fds: dict[int, _WatchedStream] = {}
        for watched in streams:
            try:
                self._fds.setdefault(watched.stream.fileno(), watched)
            except (OSError, ValueError, AttributeError):  # no descriptor (a test's capture)
                pass
        self._thread = None
        if not self._fds or not hasattr(select, "poll"):
            return
        self._wake_r, self._wake_w = os.pipe()
        self._thread = threading.Thread(target=self._watch, name="stream-watcher", daemon=True)
        self._thread.start()

    def _watch(self) -> None:
        poll = select.poll()
        poll.register(self._wake_r, select.POLLIN)
        for fd in self._fds:
            poll.register(fd, 0)  # no event asked for: only the errors and hang-ups every poll reports
        gone = select.POLLERR | select.POLLHUP
        while True:
            for fd, events in poll.poll():
                if fd == self._wake_r:
                    return
                if events & gone:
                    poll.unregister(fd)
                    self._fds[fd].went_away("its reader closed it" if events & select.POLLERR else "hung up")
                elif events & select.POLLNVAL:
                    poll.unregister(fd)

    def close(self) -> None:
        if self._thread is None:
            return
        os.write(self._wake_w, b"x")
        self._thread.join(5.0)
        os.close(self._wake_r)
        os.close(self._wake_w)
        self._thread = None
