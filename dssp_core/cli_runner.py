"""What every command shares: one-line errors instead of tracebacks for bad input."""

from __future__ import annotations

import _thread
import argparse
import contextlib
import os
import signal
import sys
import threading
import time
import warnings
from collections.abc import Callable, Iterator

from dssp_core.errors import DSSPError
from dssp_core.staging import settle_background_writes


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    print(f"warning: {message}", file=file or sys.stderr)


class ArgumentParser(argparse.ArgumentParser):
    """argparse with the commands' one-line errors: ``error: PROG: MESSAGE (see PROG --help)``, exit code 2
    (argparse's own prints the whole usage block first)."""

    def error(self, message: str):
        self.exit(2, f"error: {self.prog}: {message} (see {self.prog} --help)\n")


def run_cli(main: Callable[[], int | None]) -> int:
    """Run a command; a :class:`DSSPError` becomes ``error: <message>`` and exit code 2.

    Warnings print as one ``warning: <message>`` line, without the source line.
    """
    warnings.showwarning = _one_line_warning
    written_before = len(_put_in_place())
    try:
        with interrupts_at_safe_points():
            code = int(main() or 0)
        sys.stdout.flush()
        return code
    except DSSPError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        _settle_after_interrupt()
        written = _put_in_place()[written_before:]
        if written:  # the outputs were complete when the Ctrl-C came: say so, they stay
            print(f"interrupted after writing {', '.join(map(str, written))} (complete)", file=sys.stderr)
        else:
            print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # the reader of stdout went away (| head): stop quietly, as command-line tools do
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        except (OSError, ValueError, AttributeError):  # stdout is not a file (tests capture it)
            pass
        return 141


def _put_in_place() -> list:
    """The outputs this process has put in place so far (none while the staging module is not loaded)."""
    staging = sys.modules.get("dssp_core.staging")
    return list(staging.PUT_IN_PLACE) if staging is not None else []


def _settle_after_interrupt() -> None:
    """zarr 3 reads and writes on its own thread: let them end before the process does (a Ctrl-C reaches only
    the main thread), and do not warn about the calls the interruption stopped before they started."""
    if "zarr" not in sys.modules:
        return

    warnings.filterwarnings("ignore", message="coroutine .* was never awaited", category=RuntimeWarning)
    settle_background_writes()


# ------------------------------------------------------------------------------------------- Ctrl-C
# The standard library's thread synchronisation is not safe against an exception raised between two of its
# bytecodes: a KeyboardInterrupt that lands in ``concurrent.futures.wait`` just after it took a future's lock
# leaves that lock held (CPython bpo-20319), and zarr's thread then blocks for ever when it completes the
# future; the process never ends. So a Ctrl-C is raised only once the main thread runs outside these modules.
_STDLIB = os.path.dirname(threading.__file__)
_UNSAFE = tuple(
    os.path.join(_STDLIB, name) for name in ("threading.py", "queue.py", "concurrent" + os.sep, "asyncio" + os.sep)
)
# An exception raised inside a finalizer (``__del__``, a weakref callback, which the garbage collector may run
# between any two bytecodes) is printed as "Exception ignored in ..." and dropped: that Ctrl-C would be lost.
_FINALIZERS = tuple(os.path.join(_STDLIB, name) for name in ("weakref.py", "_weakrefset.py"))
RETRY_S = 0.01  # how often a held-back Ctrl-C looks again for a safe point
MAX_HOLD_S = 5.0  # a Ctrl-C held back longer than this is raised wherever the main thread is


def is_default_interrupt_handler(handler) -> bool:
    """True for Python's own SIGINT handler and for :func:`interrupts_at_safe_points`' (which raises the same
    KeyboardInterrupt, only later): a command that installs its own stop handling replaces either."""
    return handler is signal.default_int_handler or getattr(handler, "safe_point_interrupts", False)


def in_thread_machinery(frame) -> bool:
    """True while ``frame`` (the main thread's innermost) runs the standard library's thread synchronisation."""
    return frame is not None and frame.f_code.co_filename.startswith(_UNSAFE)


def in_a_finalizer(frame) -> bool:
    """True while ``frame`` or a caller of it is a finalizer (a ``__del__``, or the standard library's weakref
    callbacks: WeakSet, the weak dictionaries, ``weakref.finalize``), where Python ignores an exception raised
    instead of passing it on."""
    while frame is not None:
        if frame.f_code.co_name == "__del__" or frame.f_code.co_filename.startswith(_FINALIZERS):
            return True
        frame = frame.f_back
    return False


@contextlib.contextmanager
def interrupts_at_safe_points(clock: Callable[[], float] = time.monotonic) -> Iterator[None]:
    """Inside the block, Ctrl-C (SIGINT) raises KeyboardInterrupt as usual, but never inside the standard
    library's locks, queues and futures (:func:`in_thread_machinery`) nor inside a finalizer, which would drop
    it (:func:`in_a_finalizer`): there it is held back and raised a few milliseconds later, once the main
    thread is elsewhere (at most :data:`MAX_HOLD_S` later). Only in the main thread and where SIGINT has
    Python's default handler; elsewhere a no-op."""
    if (
        threading.current_thread() is not threading.main_thread()
        or signal.getsignal(signal.SIGINT) is not signal.default_int_handler
    ):
        yield
        return
    # since: when the Ctrl-C being held came (None: none held); retry: a retry's interruption not yet handled
    held: dict = {"since": None, "retry": False, "thread": None}
    lock = threading.RLock()  # re-entrant: a handler may run again inside the handler

    def retry() -> None:
        while True:
            time.sleep(RETRY_S)
            with lock:  # look and ask in one step, so no retry is asked for after the Ctrl-C was raised
                if held["since"] is None:
                    return
                held["retry"] = True
                _thread.interrupt_main(signal.SIGINT)

    def handler(signum, frame) -> None:
        with lock:
            from_retry, held["retry"] = held["retry"], False
            if from_retry and held["since"] is None:
                return  # a retry asked for before the held Ctrl-C was raised: nothing left to raise
            since = held["since"]
            unsafe = in_thread_machinery(frame) or in_a_finalizer(frame)
            if unsafe and (since is None or clock() - since < MAX_HOLD_S):
                if since is None:
                    held["since"] = clock()
                    held["thread"] = threading.Thread(target=retry, name="ctrl-c-retry", daemon=True)
                    held["thread"].start()
                return
            held["since"] = None
        raise KeyboardInterrupt

    handler.safe_point_interrupts = True
    signal.signal(signal.SIGINT, handler)
    try:
        yield
    finally:
        with lock:
            held["since"] = None
        if held["thread"] is not None:
            held["thread"].join()
        # signal.signal runs a retry's pending interruption (ignored above) before it puts the default back
        signal.signal(signal.SIGINT, signal.default_int_handler)
