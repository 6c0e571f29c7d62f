"""A command's Ctrl-C never lands inside the standard library's thread synchronisation.

A KeyboardInterrupt raised in ``concurrent.futures.wait`` just after it took a future's lock leaves the lock
held; zarr's thread then blocks for ever completing that future and the interrupted command never ends.
:func:`dssp_core.cli_runner.interrupts_at_safe_points` holds such a Ctrl-C back until the main thread is out.
"""

from __future__ import annotations

import _thread
import concurrent.futures
import signal
import sys
import threading

import pytest
from waiting import until_interrupted, wait_for

from dssp_core.cli_runner import MAX_HOLD_S, in_thread_machinery, interrupts_at_safe_points, run_cli


@pytest.fixture
def waiting_thread():
    """A thread blocked in ``threading.Event.wait``, and its innermost frame (in threading.py)."""
    gate = threading.Event()
    thread = threading.Thread(target=gate.wait, daemon=True)
    thread.start()
    wait_for(
        lambda: in_thread_machinery(sys._current_frames().get(thread.ident)),
        timeout=10,
        what="the thread blocked in threading's wait",
        poll=0.001,
    )
    yield sys._current_frames()[thread.ident]
    gate.set()
    thread.join()


def test_a_ctrl_c_in_thread_machinery_is_raised_once_the_main_thread_is_out(waiting_thread):
    assert in_thread_machinery(waiting_thread) and not in_thread_machinery(sys._getframe())
    with interrupts_at_safe_points():
        handler = signal.getsignal(signal.SIGINT)
        assert handler is not signal.default_int_handler
        handler(signal.SIGINT, waiting_thread)  # held back: nothing raised here
        with pytest.raises(KeyboardInterrupt):
            until_interrupted(timeout=10.0)  # the held Ctrl-C comes within milliseconds, here outside the machinery
        with pytest.raises(KeyboardInterrupt):
            handler(signal.SIGINT, sys._getframe())  # outside the machinery it is raised at once
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_the_handler_is_restored_and_a_ctrl_c_held_too_long_is_raised_anyway(waiting_thread):
    now = [100.0]
    try:
        with interrupts_at_safe_points(clock=lambda: now[0]):
            handler = signal.getsignal(signal.SIGINT)
            handler(signal.SIGINT, waiting_thread)
            now[0] += MAX_HOLD_S + 0.1  # the main thread stayed in the machinery too long
            with pytest.raises(KeyboardInterrupt):
                handler(signal.SIGINT, waiting_thread)
    except KeyboardInterrupt:  # the retry thread's interrupt arrived before the one above: same outcome
        pass
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_run_cli_holds_the_handler_only_while_the_command_runs():
    seen = []
    assert run_cli(lambda: seen.append(signal.getsignal(signal.SIGINT))) == 0
    assert seen and seen[0] is not signal.default_int_handler
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    assert run_cli(lambda: _thread.interrupt_main()) == 130  # a Ctrl-C during a command: exit code 130


def test_the_step_of_futures_wait_that_takes_the_locks_is_machinery():
    """The frame the bug needs (``concurrent.futures.wait`` taking each future's lock) is one the Ctrl-C waits out."""
    frames = []
    future = concurrent.futures.Future()
    future.set_result(1)
    lock = future._condition

    class Recording:
        def acquire(self, *args):
            frames.append(sys._getframe(1))
            return lock.acquire(*args)

        def release(self):
            lock.release()

    future._condition = Recording()
    concurrent.futures.wait([future])
    assert frames and frames[0].f_code.co_name == "__enter__" and in_thread_machinery(frames[0])
    with interrupts_at_safe_points():
        signal.getsignal(signal.SIGINT)(signal.SIGINT, frames[0])  # held back
        with pytest.raises(KeyboardInterrupt):
            until_interrupted(timeout=10.0)


def test_a_command_with_its_own_stop_handling_takes_sigint_over():
    """dssp-run, dssp-record and dssp-sim-arm end every stop in a hold (hardware.cli.stops): under run_cli their handler
    still replaces the Ctrl-C one."""
    from hardware.cli.stops import Stops

    seen = []

    def command() -> int:
        stops = Stops(streams=False)
        try:
            seen.append(signal.SIGINT in stops.signals and signal.getsignal(signal.SIGINT) == stops._signalled)
        finally:
            stops.restore()
        return 0

    assert run_cli(command) == 0 and seen == [True]


def test_a_ctrl_c_inside_a_finalizer_is_held_back_not_lost():
    """The garbage collector may run a ``__del__`` or a weakref callback between any two bytecodes; a
    KeyboardInterrupt raised there is printed as "Exception ignored" and dropped, so the Ctrl-C waits it out."""
    import gc
    import weakref

    from dssp_core.cli_runner import in_a_finalizer

    seen = []

    class Dropped:
        def __del__(self):
            seen.append(in_a_finalizer(sys._getframe()))
            signal.getsignal(signal.SIGINT)(signal.SIGINT, sys._getframe())  # held back: nothing raised here
            seen.append("returned")

    with pytest.raises(KeyboardInterrupt):  # the held Ctrl-C, raised once the finalizer has returned
        with interrupts_at_safe_points():
            obj = Dropped()
            del obj  # its last reference: __del__ runs here
            until_interrupted(timeout=10.0)  # the held Ctrl-C comes within milliseconds
    assert seen == [True, "returned"]

    class Member:
        pass

    member, frames = Member(), []
    weakref.finalize(member, lambda: frames.append(sys._getframe()))  # called from weakref.py's finalize
    del member
    gc.collect()
    assert frames and in_a_finalizer(frames[0]) and not in_a_finalizer(sys._getframe())
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
