"""dssp-run's start-up: a signal at any moment of it is a clean stop, and a model without a recorded rate
is refused rather than run at a guessed one.

The signal test is real time by nature (a signal into a real process at a point of its start-up); its
verdict does not depend on where the signal lands: either start-up stops with nothing enabled, or the
loop ends in its final hold — both exit 130, and neither may blame another cause.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from hardware.cli.run import main as run_main


@pytest.mark.parametrize("delay", [0.3, 1.0, 2.0, 3.5])
def test_ctrl_c_during_start_up_is_a_clean_stop(arm_export, tmp_path, delay):
    proc = subprocess.Popen(
        [sys.executable, "-m", "hardware.cli.run", "--model", str(arm_export), "--camera", "sim", "--can", "sim",
         "--log-dir", str(tmp_path / "log"), "--threads", "1", "--quiet"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
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
