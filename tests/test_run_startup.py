"""dssp-run's start-up: a signal at any moment of it is a clean stop, a model without a recorded rate
is refused rather than run at a guessed one, and the waits for the first frame and the first feedback are
bounded on the loop's clock.

The signal test is real time by nature (a signal into a real process at a point of its start-up, counted
from the moment main() installs its handler); its verdict does not depend on where the signal lands: either start-up stops with nothing enabled, or the
loop ends in its final hold — both exit 130, and neither may blame another cause.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from dssp_data.errors import CameraError, DSSPError
from hardware.camera.base import Camera
from hardware.cli.run import main as run_main
from hardware.clock import FakeClock
from hardware.robot import Robot


def wait_for_start_up_handler(proc: subprocess.Popen, timeout: float = 60.0) -> None:
    """Wait until ``proc`` catches SIGTERM: main() has installed its start-up handler (Python itself catches
    only SIGINT), so the delays below count from there, whatever the machine's load did to the interpreter's
    own start-up (a Ctrl-C before that is Python's, not dssp-run's)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.poll() is None:
        status = Path(f"/proc/{proc.pid}/status").read_text()
        caught = int(next(line.split()[1] for line in status.splitlines() if line.startswith("SigCgt:")), 16)
        if caught >> (signal.SIGTERM - 1) & 1:
            return
        time.sleep(0.005)
    raise AssertionError(f"dssp-run did not install its start-up handler within {timeout} s (exit code {proc.poll()})")


@pytest.mark.parametrize("delay", [0.0, 0.3, 1.0, 2.0, 3.5])
def test_ctrl_c_during_start_up_is_a_clean_stop(arm_export, tmp_path, delay):
    proc = subprocess.Popen(
        [sys.executable, "-m", "hardware.cli.run", "--model", str(arm_export), "--camera", "sim", "--can", "sim",
         "--log-dir", str(tmp_path / "log"), "--threads", "1", "--quiet"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    wait_for_start_up_handler(proc)
    time.sleep(delay)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "cannot be imported" not in err, err
    assert "during start-up; no arm was enabled" in err or "ended by: SIGINT" in out, (out, err)


def test_a_model_without_a_control_rate_needs_rate(tiny_export, tmp_path, capsys):
    _, model_dir, _ = tiny_export
    import json

    manifest = json.loads((model_dir / "dssp_model.json").read_text())
    if manifest.get("control_rate_hz") is not None:
        import shutil

        copy = tmp_path / "model"
        shutil.copytree(model_dir, copy)
        manifest["control_rate_hz"] = None
        manifest["runtime"]["tick_rate_hz"] = None
        (copy / "dssp_model.json").write_text(json.dumps(manifest))
        model_dir = copy
    code = run_main(["--model", str(model_dir), "--max-steps", "3", "--quiet", "--log-dir", str(tmp_path / "log")])
    err = capsys.readouterr().err
    assert code == 2 and "records no control rate" in err and "--rate" in err, err
    assert not (tmp_path / "log").exists()


class SilentArm(Robot):
    """An arm that never reports (unpowered, or the wrong bus); enabling it would be a bug."""

    dof = 7
    connect = close = emergency_stop = disable = lambda self: None

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
    from dssp_deploy.onnx_policy import OnnxPolicy
    from hardware.piper.limits import JointLimits
    from hardware.pointcloud import PointCloudConfig
    from hardware.run_loop import LoopSettings, Runner
    from hardware.safety import SafetyConfig

    clock, camera = FakeClock(start=100.0), StillCamera(object())
    limits = JointLimits.piper()
    runner = Runner(OnnxPolicy(arm_export, threads=1), camera, SilentArm(), PointCloudConfig(n_points=64), np.eye(4),
                    SafetyConfig(), LoopSettings(rate_hz=50.0, startup_timeout=2.0),
                    (limits.lower, limits.upper, np.arange(7) == 6), clock=clock)
    with pytest.raises(DSSPError, match="no joint feedback within 2 s"):
        runner.start()
    assert 102.0 < clock.now() <= 102.005 + 1e-9  # the first poll past the deadline
    camera.frame = None
    with pytest.raises(CameraError, match="no frame within 2 s"):
        runner.start()
    assert 104.0 < clock.now() <= 104.01 + 1e-9 and runner.safety is None
