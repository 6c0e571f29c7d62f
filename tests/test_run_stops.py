"""Every way ``dssp-run`` is stopped ends in its safe stop: each signal whose default would end the process, at
random moments of a real process (during start-up and while running), and an output stream that goes away. The
exit code says which (128 + the signal's number; 141 for a lost stdout/stderr), the episode log and its summary
name the true reason, the final hold and the disable are on the CAN log, which is complete and readable.

The signals are real time by nature (a signal into a real process); the moments are drawn from a seed, printed
(``DSSP_STOP_SEED=N`` replays them), each one the process shows from outside (a start-up moment of
``conftest.START_UP``, or a number of logged ticks), never a delay. Whatever moment a signal lands at,
the verdict is exact: either the start-up ended with nothing enabled or sent, or the loop ended in its final
hold. A stop before the first tick, a run that failed before it, a failed print and dssp-replay's stop are
checked in-process, where the stop lands exactly.
"""

from __future__ import annotations

import io
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import GRIPPER, START_UP, assert_within_limits, catches, sent_commands, ticks_logged, wait_for_start_up
from waiting import Output, wait_for

from dssp_core.errors import CameraError, DSSPError
from hardware.can_log import read_log
from hardware.cli.run import main as run_main
from hardware.cli.stops import LOST_STREAM_CODE, Stops, exit_code, signal_name, stop_signals
from hardware.piper import codec
from hardware.run_log import read_ticks

SEED = int(os.environ.get("DSSP_STOP_SEED", time.time_ns() % 2**31))
LISTED = (
    "SIGINT",
    "SIGTERM",
    "SIGHUP",
    "SIGQUIT",
    "SIGUSR1",
    "SIGUSR2",
    "SIGALRM",
    "SIGPIPE",
    "SIGXCPU",
    "SIGXFSZ",
    "SIGVTALRM",
    "SIGPROF",
)
NUMBERS = {signal_name(s): s for s in stop_signals()}
MAX_STEP = np.where(GRIPPER, 0.2, 0.05)


def _env():
    return {**os.environ, "OMP_NUM_THREADS": "1"}


def _start(arm_export, tmp_path, *extra, quiet=True):
    safety = tmp_path / "safety.json"
    safety.write_text(json.dumps({"disable_on_exit": True}))
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "hardware.cli.run",
            "--model",
            str(arm_export),
            "--camera",
            "tabletop",
            "--can",
            "sim",
            "--log-dir",
            str(tmp_path / "log"),
            "--threads",
            "1",
            "--safety",
            str(safety),
            *(["--quiet"] if quiet else []),
            *extra,
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=_env(),
    )


def check_safe_stop(log_dir: Path, reason: str, err: str) -> dict | None:
    """The verdict on a stopped run: its log complete, naming ``reason``; the final hold and the disable on the
    bus if the arm was enabled, nothing sent if it was not. Returns the summary (None: stopped before the log)."""
    assert "Traceback" not in err, err
    if not log_dir.exists():  # stopped before the log directory was claimed
        assert f"stopped by {reason} during start-up; no arm was enabled, nothing was sent" in err, err
        assert not list(log_dir.parent.glob(f".{log_dir.name}.lock"))  # its lock went with it
        return None
    summary = json.loads((log_dir / "run.json").read_text())["summary"]
    assert summary["ended_by"] == reason and summary["fault"] is None, summary
    ticks = read_ticks(log_dir)
    assert summary["ticks"] == len(ticks) and [t["tick"] for t in ticks] == list(range(len(ticks)))
    [blf] = log_dir.glob("can_*.blf")
    frames = read_log(blf)  # the CAN log was closed properly: readable to its end
    assert frames, "the CAN log is empty"
    decoder = codec.Decoder()
    enables = [m for m in map(decoder.decode, frames) if isinstance(m, codec.MotorEnable)]
    commands = sent_commands(blf)
    if summary["safety_events"]:  # the arm was enabled: the loop ended in its final hold, then disabled it
        events = summary["safety_events"]
        assert [e["kind"] for e in events[-2:]] == ["hold", "stop"] and reason in events[-1]["detail"], events
        logged = [t["command"] for t in ticks if t["command"] is not None]
        assert len(commands) == len(logged) + 1  # every command logged, then the final hold
        assert np.allclose(commands[:-1], np.array(logged).reshape(-1, 7), atol=2e-5)
        assert_within_limits(commands, MAX_STEP)
        assert summary["disabled"] and enables and not enables[-1].enable  # the last word to the motors: off
    else:  # stopped before the arm was enabled: nothing was enabled or sent
        assert summary["ticks"] == 0 and not summary["disabled"]
        assert len(commands) == 0 and not any(m.enable for m in enables)
        assert f"stopped by {reason} during start-up; no arm was enabled, nothing was sent" in err, err
    return summary


# ------------------------------------------------------------------------------------------------ the signals
# Sends a fresh process (``cat`` reading a pipe, every signal at its default, no core file) each signal, and prints
# the numbers of those it died of. The child's input is closed right after the signal is sent: a signal that ends a
# process is acted on the next time the child runs, before it can see the end of its input; one it ignores is
# dropped and the child ends on the end of its input; one that stops it is reported as a stop. So every wait ends
# on a change of the child's state, none on a timer. A small process of its own starts them: forking the test
# process 62 times takes seconds.
ORACLE = """
import json, os, resource, signal, subprocess

def fresh():
    for signum in signal.valid_signals():
        if signum not in (signal.SIGKILL, signal.SIGSTOP):
            signal.signal(signum, signal.SIG_DFL)
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))

children = {int(s): subprocess.Popen(["cat"], stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, preexec_fn=fresh)
            for s in signal.valid_signals()}
ends = []
try:
    for signum, child in children.items():
        os.kill(child.pid, signum)
        child.stdin.close()
    for signum, child in children.items():
        _, status = os.waitpid(child.pid, os.WUNTRACED)  # it died, ended at the end of its input, or stopped
        if os.WIFSTOPPED(status):
            os.kill(child.pid, signal.SIGKILL)
            _, status = os.waitpid(child.pid, 0)
        elif os.WIFSIGNALED(status) and os.WTERMSIG(status) == signum:
            ends.append(signum)
        child.returncode = os.waitstatus_to_exitcode(status)
finally:
    for child in children.values():
        if child.returncode is None:
            child.kill()
            child.wait()
print(json.dumps(sorted(ends)))
"""


def test_the_stop_signals_are_every_signal_whose_default_ends_a_process(tmp_path):
    """The oracle is the system itself: a fresh process is sent each signal; the ones it dies of, less SIGKILL and
    the hardware faults, are exactly the ones a command catches — the real-time signals and the listed ones among
    them."""
    done = subprocess.run([sys.executable, "-c", ORACLE], capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    ends = set(json.loads(done.stdout))
    faults = {signal.SIGSEGV, signal.SIGBUS, signal.SIGFPE, signal.SIGILL}
    assert set(stop_signals()) == ends - {signal.SIGKILL} - faults
    assert set(LISTED) <= set(NUMBERS) and any(name.startswith("SIGRTMIN") for name in NUMBERS)


def test_each_stop_signal_is_one_stop_request():
    """In-process: every signal of the set reaches the handler, which records its name and 128 + its number; the
    first stop wins, and the handlers found at start are put back."""
    before = {s: signal.getsignal(s) for s in stop_signals()}
    for signum in stop_signals():
        stops = Stops(streams=False)
        told, asked = [], []
        stop = stops.stop
        stops.stop = lambda reason, code: asked.append(reason) or stop(reason, code)  # each request, the ignored too
        second = signal.SIGUSR1 if signum != signal.SIGUSR1 else signal.SIGUSR2
        try:
            assert signum in stops.signals
            stops.during(told.append)
            os.kill(os.getpid(), signum)
            wait_for(lambda: stops.reason is not None, timeout=5, what=f"{signal_name(signum)} handled")
            os.kill(os.getpid(), second)  # a second stop
            wait_for(lambda: len(asked) == 2, timeout=5, what=f"the second stop, {signal_name(second)}, handled")
        finally:
            stops.restore()
        assert asked == [signal_name(signum), signal_name(second)]
        assert (stops.reason, stops.code, told) == (signal_name(signum), 128 + signum, [signal_name(signum)])
    assert {s: signal.getsignal(s) for s in stop_signals()} == before


def _moments(names):
    """One random moment per signal (seeded): during start-up, once the process shows one of the moments of
    ``START_UP`` before its first tick, or while running, after ``ticks`` logged ticks; the two kinds alternate,
    so both are always tried."""
    rng = random.Random(SEED)
    kinds = ["start-up", "running"] if rng.random() < 0.5 else ["running", "start-up"]
    return {
        name: (kinds[i % 2], rng.choice(START_UP[:-1]) if kinds[i % 2] == "start-up" else rng.randint(1, 40))
        for i, name in enumerate(names)
    }


MOMENTS = _moments(LISTED + ("real-time",))


@pytest.mark.parametrize("name", list(MOMENTS))
def test_a_signal_at_a_random_moment_ends_in_the_safe_stop(arm_export, tmp_path, name):
    """The signal is sent once the process catches it (and SIGTERM: Python catches SIGINT from its own start, the
    command's handlers are installed together), then at the drawn moment; "real-time" is one of SIGRTMIN..SIGRTMAX."""
    if name == "real-time":
        signum = int(signal.SIGRTMIN) + random.Random(SEED).randrange(int(signal.SIGRTMAX) - int(signal.SIGRTMIN) + 1)
    else:
        signum = NUMBERS[name]
    kind, when = MOMENTS[name]
    print(f"DSSP_STOP_SEED={SEED}: {signal_name(signum)} {kind} {when}")
    log_dir = tmp_path / "log"
    proc = _start(arm_export, tmp_path)
    output = Output(proc)
    try:
        wait_for(
            lambda: proc.poll() is not None or (catches(proc.pid, signal.SIGTERM) and catches(proc.pid, signum)),
            timeout=60,
            what=f"{signal_name(signum)} caught (seed {SEED})",
            poll=0.002,
        )
        if kind == "start-up":
            wait_for_start_up(proc, output, log_dir, when)
        else:
            wait_for(
                lambda: proc.poll() is not None or ticks_logged(log_dir) >= when,
                timeout=120,
                what=f"{when} logged ticks (seed {SEED})",
                poll=0.01,
            )
        proc.send_signal(signum)
        out, err = output.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == exit_code(signum) == 128 + signum, (SEED, signal_name(signum), kind, when, err)
    summary = check_safe_stop(log_dir, signal_name(signum), err)
    if kind == "running":
        assert summary is not None and summary["ticks"] >= when and summary["safety_events"], (SEED, summary)
    if summary is not None:
        assert f"ended by: {signal_name(signum)}" in out, out


# ------------------------------------------------------------------------------------------------ lost streams
def test_stdout_and_stderr_going_away_end_in_the_safe_stop(arm_export, tmp_path):
    """Real time: both pipes' readers close once 10 ticks are logged; the run is --quiet (nothing written to
    either), so the stop comes from noticing the closed pipe itself."""
    log_dir = tmp_path / "log"
    proc = _start(arm_export, tmp_path)
    try:
        wait_for(
            lambda: proc.poll() is not None or ticks_logged(log_dir) >= 10,
            timeout=120,
            what="10 logged ticks",
            poll=0.01,
        )
        proc.stdout.close()
        proc.stderr.close()
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == LOST_STREAM_CODE == 141
    summary = json.loads((log_dir / "run.json").read_text())["summary"]
    reason = summary["ended_by"]
    # the closed pipe, noticed by its watcher; or (had the process written to it first) the SIGPIPE of that write
    assert reason in ("lost stdout (its reader closed it)", "lost stderr (its reader closed it)", "SIGPIPE"), reason
    check_safe_stop(log_dir, reason, "")


class _Terminal(io.StringIO):
    """stderr whose reader goes away as the first status line is written."""

    def write(self, text):
        if text.startswith("tick"):
            raise BrokenPipeError(32, "Broken pipe")
        return super().write(text)

    def isatty(self):
        return False


def _run_in_process(arm_export, tmp_path, *extra):
    safety = tmp_path / "safety.json"
    safety.write_text(json.dumps({"disable_on_exit": True}))
    return run_main(
        [
            "--model",
            str(arm_export),
            "--log-dir",
            str(tmp_path / "log"),
            "--threads",
            "1",
            "--seed",
            "0",
            "--safety",
            str(safety),
            *extra,
        ]
    )


def test_a_failed_print_is_a_stop_not_a_traceback(arm_export, tmp_path, capsys, monkeypatch):
    """In-process: the live status line's write fails (BrokenPipeError) in the middle of the loop: the print
    does not raise, the loop ends in its final hold, the summary says why, exit code 141."""
    monkeypatch.setattr(sys, "stderr", _Terminal())
    log_dir = tmp_path / "log"
    code = _run_in_process(arm_export, tmp_path)
    assert code == LOST_STREAM_CODE
    assert sys.stderr.__class__ is _Terminal  # put back
    summary = check_safe_stop(log_dir, "lost stderr (Broken pipe)", "")
    assert summary["ticks"] >= 1 and summary["safety_events"]
    assert "ended by: lost stderr (Broken pipe)" in capsys.readouterr().out


# ------------------------------------------------------------------------------------------------ true reasons
def test_a_stop_before_the_first_tick_is_logged_as_that_stop(arm_export, tmp_path, capsys, monkeypatch):
    """In-process, the signal lands exactly where start() begins (the devices open, the log claimed): nothing is
    enabled or sent, the log's summary names SIGHUP (not "max steps"), exit code 129."""
    from hardware.run_loop import Runner

    start = Runner.start

    def signalled_start(self):
        os.kill(os.getpid(), signal.SIGHUP)
        # the handler has run once it passed the stop on to this runner (dssp-run's stops.during)
        wait_for(lambda: self.stop_reason is not None, timeout=5, what="SIGHUP handled")
        return start(self)

    monkeypatch.setattr(Runner, "start", signalled_start)
    log_dir = tmp_path / "log"
    code = _run_in_process(arm_export, tmp_path, "--quiet", "--max-steps", "50")
    out, err = capsys.readouterr()
    assert code == 129, err
    summary = check_safe_stop(log_dir, "SIGHUP", err)
    assert summary["ticks"] == 0 and not summary["safety_events"] and "ended by: SIGHUP" in out


@pytest.mark.parametrize("where", ["start", "camera"])
def test_a_run_that_failed_before_its_first_tick_says_why(arm_export, tmp_path, capsys, monkeypatch, where):
    """No feedback at start-up, or a camera that does not open: one error line, exit 2, and the log's summary
    gives that error as what ended the run."""
    from hardware.camera.tabletop import SimCamera
    from hardware.run_loop import Runner

    message = "no joint feedback within 5 s: check the CAN bus" if where == "start" else "sim: the camera failed"

    def fail(self):
        raise (DSSPError if where == "start" else CameraError)(message)

    monkeypatch.setattr(Runner if where == "start" else SimCamera, "start", fail)
    log_dir = tmp_path / "log"
    code = _run_in_process(arm_export, tmp_path, "--quiet", "--max-steps", "50")
    err = capsys.readouterr().err
    assert code == 2 and err.strip().splitlines()[-1] == f"error: {message}" and "Traceback" not in err, err
    summary = json.loads((log_dir / "run.json").read_text())["summary"]
    assert summary["ended_by"] == f"error: {message}" and summary["ticks"] == 0 and not summary["safety_events"]


# ------------------------------------------------------------------------------------------------ the other commands
def test_dssp_replay_stops_like_dssp_run(tmp_path, capsys, monkeypatch):
    """In-process: SIGHUP lands right after the replay's fifth command; it ends between two commands in its hold
    (one more command: the last safe target), says so, exit code 129."""
    from conftest import write_arm_dataset

    from hardware.cli.replay import main as replay_main
    from hardware.piper.piper_robot import PiperRobot

    data = write_arm_dataset(tmp_path / "d.zarr", n_episodes=1, steps=40)
    commands = []
    command = PiperRobot.command

    def counted(self, target):
        command(self, target)
        commands.append(np.array(target))
        if len(commands) == 5:
            os.kill(os.getpid(), signal.SIGHUP)

    monkeypatch.setattr(PiperRobot, "command", counted)
    code = replay_main([str(data), "--episode", "0", "--can", "sim", "--send"])
    out = capsys.readouterr().out
    assert code == 129 and "sent 5 commands" in out and "ended by: SIGHUP" in out, out
    assert len(commands) == 6 and np.array_equal(commands[-1], commands[-2])  # the hold: the last command again
