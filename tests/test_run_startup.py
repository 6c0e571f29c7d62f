"""dssp-run's start-up: a signal at any moment of it is a clean stop, a model without a recorded rate
is refused rather than run at a guessed one, and the waits for the first frame and the first feedback are
bounded on the loop's clock. What can be judged before a device opens is: a second writer of a log directory,
default log names that would collide, a --prefetch lead the control rate cannot hold.

The signal test is real time by nature (a signal into a real process at a point of its start-up); the point is
one the process shows from outside (:data:`START_UP`: a handler it caught, a file it made, a line it printed, a
tick it logged), never a delay. Its verdict does not depend on where after that point the signal lands: either
start-up stops with nothing enabled, or the loop ends in its final hold — both exit 130, and neither may blame
another cause; from the log directory's claim on, the stop is the runner's and the summary says so.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import numpy as np
import pytest
from conftest import START_UP, catches, wait_for_start_up
from waiting import Output, wait_for

from dssp_core.errors import CameraError, DSSPError
from hardware.camera.base import Camera
from hardware.cli.run import main as run_main
from hardware.clock import FakeClock
from hardware.piper.limits import piper_description
from hardware.robot import Robot


def wait_for_start_up_handler(proc: subprocess.Popen, timeout: float = 60.0) -> None:
    """Wait until ``proc`` catches SIGTERM: main() has installed its start-up handler (Python itself catches
    only SIGINT), so the moments below come after it, whatever the machine's load did to the interpreter's
    own start-up (a Ctrl-C before that is Python's, not dssp-run's)."""
    wait_for(
        lambda: proc.poll() is not None or catches(proc.pid, signal.SIGTERM),
        timeout=timeout,
        what="dssp-run's start-up handler",
        poll=0.005,
    )
    assert proc.poll() is None, f"dssp-run ended before it installed its start-up handler (exit code {proc.poll()})"


RUNNERS = START_UP[START_UP.index("log claimed") :]  # the moments from which the runner ends the run


@pytest.mark.parametrize("moment", START_UP)
def test_ctrl_c_during_start_up_is_a_clean_stop(arm_export, tmp_path, moment):
    log_dir = tmp_path / "log"
    proc = subprocess.Popen(
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
            str(log_dir),
            "--threads",
            "1",
            "--quiet",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    output = Output(proc)
    try:
        wait_for_start_up_handler(proc)
        wait_for_start_up(proc, output, log_dir, moment)
        proc.send_signal(signal.SIGINT)
        out, err = output.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, (moment, out, err)
    assert "Traceback" not in err and "cannot be imported" not in err, err
    assert "during start-up; no arm was enabled" in err or "ended by: SIGINT" in out, (out, err)
    if moment in RUNNERS:  # the log was claimed before the signal: the runner ended the run and said why
        assert "ended by: SIGINT" in out, (moment, out, err)
    if moment == "first tick":  # the arm was enabled: the loop ended in its final hold, not the start-up
        assert "during start-up" not in err, (moment, err)


def test_a_model_without_a_control_rate_needs_rate(tiny_export, tmp_path, capsys):
    _, model_dir, _ = tiny_export
    import json

    manifest = json.loads((model_dir / "dssp_model.json").read_text())
    if manifest["contract"]["control_rate_hz"] is not None:
        import shutil

        copy = tmp_path / "model"
        shutil.copytree(model_dir, copy)
        manifest["contract"]["control_rate_hz"] = None
        (copy / "dssp_model.json").write_text(json.dumps(manifest))
        model_dir = copy
    code = run_main(["--model", str(model_dir), "--max-steps", "3", "--quiet", "--log-dir", str(tmp_path / "log")])
    err = capsys.readouterr().err
    assert code == 2 and "records no control rate" in err and "--control-rate" in err, err
    assert not (tmp_path / "log").exists()


class SilentArm(Robot):
    """An arm that never reports (unpowered, or the wrong bus); enabling it would be a bug."""

    dof = 7
    connect = close = emergency_stop = disable = lambda self: None
    description = property(lambda self: piper_description(1))

    def state(self):
        return None

    def enable(self, timeout=2.0):
        raise AssertionError("an arm without feedback was enabled")

    def command(self, target):
        raise AssertionError("an arm without feedback was commanded")


class StillCamera(Camera):
    """A camera whose newest frame is ``frame`` (start-up only asks whether there is one)."""

    start = stop = lambda self: None

    def __init__(self, frame):
        self.frame = frame

    def latest(self):
        return self.frame


def test_start_up_gives_up_on_its_clock(arm_export):
    """No joint feedback, or no camera frame: start-up gives up after ``startup_timeout`` s of the runner's
    clock, polling on it; on a manual clock that takes no wall time, and the time it gave up at is exact."""
    from dssp_data.pointcloud import PointCloudConfig
    from dssp_deploy.onnx_policy import OnnxPolicy
    from hardware.piper.limits import JointLimits
    from hardware.policies.exported_model import ModelPolicy
    from hardware.rig import Rig
    from hardware.run_loop import LoopSettings, Runner
    from hardware.safety import SafetyConfig

    clock, camera = FakeClock(start=100.0), StillCamera(object())
    limits = JointLimits.piper()
    rig = Rig(
        camera,
        SilentArm(),
        np.eye(4),
        SafetyConfig(),
        clock=clock,
        limits=(limits.lower, limits.upper, np.arange(7) == 6),
    )
    runner = Runner(
        ModelPolicy(OnnxPolicy(arm_export, threads=1), 50.0),
        rig,
        PointCloudConfig(n_points=64),
        LoopSettings(control_rate_hz=50.0, startup_timeout=2.0),
    )
    with pytest.raises(DSSPError, match="no joint feedback within 2 s"):
        runner.start()
    assert 102.0 < clock.now() <= 102.005 + 1e-9  # the first poll past the deadline
    camera.frame = None
    with pytest.raises(CameraError, match="no frame within 2 s"):
        runner.start()
    assert 104.0 < clock.now() <= 104.01 + 1e-9 and runner.safety is None


# ------------------------------------------------------------------------------------------------ before any device
def _devices_opened(monkeypatch) -> list[str]:
    """The devices dssp-run opens from here on (none, if it refuses first)."""
    opened = []
    # a robot is described before it connects (what it is, not a device opened): connecting is what counts
    monkeypatch.setattr("hardware.piper.piper_robot.PiperRobot.connect", lambda self: opened.append("robot"))
    monkeypatch.setattr("hardware.camera.open_camera", lambda *a, **k: opened.append("camera"))
    return opened


def test_a_second_writer_of_a_log_directory_gets_one_line_before_anything_opens(
    arm_export, tmp_path, capsys, monkeypatch
):
    """One writer per log directory: while another run holds it (here a lock taken in this process, as a first
    dssp-run would), the second is refused with one line naming the holder, before the model or any device, and
    nothing of the first's is touched."""
    from conftest import one_error_line, snapshot

    from dssp_core.staging import WriterLock

    log_dir = tmp_path / "log"
    first = WriterLock(log_dir, what="log directory", flag="--log-dir")
    try:
        log_dir.mkdir()
        (log_dir / "ticks.jsonl").write_text('{"tick": 0}\n')
        before = snapshot(tmp_path)
        opened = _devices_opened(monkeypatch)
        code = run_main(["--model", str(arm_export), "--log-dir", str(log_dir), "--quiet", "--max-steps", "3"])
        line = one_error_line(capsys.readouterr().err)
        assert code == 2 and f"is being written by pid {os.getpid()}" in line and "choose another --log-dir" in line
        assert opened == [] and snapshot(tmp_path) == before
    finally:
        first.release()


def test_default_log_directories_never_collide(arm_export, tmp_path, capsys, monkeypatch):
    """Runs started in the same second: the default name gets a suffix chosen under its lock — past a finished
    run's log and past a name another run holds — and neither of those is touched."""
    import json

    from dssp_core.staging import WriterLock
    from hardware.cli import run as run_module

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(run_module, "log_stamp", lambda: "20260101-120000")
    root = tmp_path / "runs" / "dssp-run"
    finished = root / "20260101-120000"
    finished.mkdir(parents=True)
    (finished / "run.json").write_text("{}")
    starting = WriterLock(root / "20260101-120000-2", what="log directory", flag="--log-dir")
    try:
        code = run_main(["--model", str(arm_export), "--max-steps", "3", "--threads", "1", "--quiet"])
    finally:
        starting.release()
    out = capsys.readouterr().out
    assert code == 0 and "episode log: runs/dssp-run/20260101-120000-3" in out, out
    assert json.loads((root / "20260101-120000-3" / "run.json").read_text())["summary"]["ticks"] == 3
    assert (finished / "run.json").read_text() == "{}" and not (root / "20260101-120000-2").exists()
    assert sorted(p.name for p in root.iterdir()) == ["20260101-120000", "20260101-120000-3"]  # no lock left


def test_a_prefetch_lead_the_rate_cannot_hold_is_refused_before_anything_opens(
    arm_export, tmp_path, capsys, monkeypatch
):
    """--prefetch: the chunk's latency is measured once, before any device opens; a lead that does not fit the
    horizon at the control rate is one line (here a chunk of 1 s at 50 Hz), and the loop chooses its lead from
    that same measurement (it is not measured again after the devices opened)."""
    from conftest import one_error_line

    from dssp_deploy.control_loop import ChunkedControl

    measured = []
    monkeypatch.setattr(ChunkedControl, "measure_chunk_ms", lambda self, iterations=5: measured.append(1) or 1000.0)
    opened = _devices_opened(monkeypatch)
    code = run_main(
        [
            "--model",
            str(arm_export),
            "--prefetch",
            "--log-dir",
            str(tmp_path / "log"),
            "--quiet",
            "--max-steps",
            "3",
            "--threads",
            "1",
        ]
    )
    line = one_error_line(capsys.readouterr().err)
    assert code == 2 and "--prefetch at 50 Hz: a chunk takes 1000.0 ms = 50 ticks" in line, line
    assert "run without prefetch or at a lower rate" in line
    assert opened == [] and not (tmp_path / "log").exists()

    monkeypatch.undo()
    measured.clear()
    monkeypatch.setattr(ChunkedControl, "measure_chunk_ms", lambda self, iterations=5: measured.append(1) or 5.0)
    code = run_main(
        [
            "--model",
            str(arm_export),
            "--prefetch",
            "--log-dir",
            str(tmp_path / "log"),
            "--quiet",
            "--max-steps",
            "5",
            "--threads",
            "1",
        ]
    )
    assert code == 0 and measured == [1], capsys.readouterr()
