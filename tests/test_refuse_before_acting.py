"""Every plan and flag is judged before a device opens or a file is created: one table of refusals across the
commands, each run against devices that fail the test when they are opened (a camera, a robot, a CAN bus, the
simulated rigs, a Rerun recording), in a folder that must be left as it was. Each case is one ``error:`` line and
exit code 2."""

from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path

import numpy as np
import pytest
from conftest import CALIBRATION_START, one_error_line, snapshot


class Opened(AssertionError):
    """A device or an output was opened by a command that should have refused first."""


def _refuse(what: str):
    def opened(*args, **kwargs):
        raise Opened(f"{what} was opened before the refusal")

    return opened


@contextlib.contextmanager
def nothing_opens(monkeypatch):
    """Every way the commands open a device or a recording fails the test."""
    import dssp_data.rerun_views as views
    import dssp_sim.calibration_twin as twin
    import dssp_sim.env as env
    import dssp_sim.teleop as teleop
    import hardware.camera as camera
    import hardware.piper.bus as bus
    import hardware.piper.piper_robot as piper_robot

    monkeypatch.setattr(camera, "open_camera", _refuse("a camera"))
    monkeypatch.setattr(piper_robot.PiperRobot, "connect", _refuse("a robot"))
    monkeypatch.setattr(bus, "open_bus", _refuse("a CAN bus"))
    monkeypatch.setattr(twin.TwinRigs, "open", _refuse("the calibration twin"))
    monkeypatch.setattr(teleop.TeleopRigs, "open", _refuse("the simulated recording rig"))
    monkeypatch.setattr(env.PiperEnv, "__init__", _refuse("the MuJoCo Piper"))
    open_views = views.open_views

    def no_views(what, connect, save, *args, **kwargs):
        if connect is None and save is None:  # no view asked for: nothing is opened
            return open_views(what, connect, save, *args, **kwargs)
        raise Opened("a Rerun recording was opened before the refusal")

    monkeypatch.setattr(views, "open_views", no_views)
    yield


def plan(folder: Path, poses) -> str:
    path = folder / "plan.json"
    path.write_text(json.dumps({"poses": np.asarray(poses, dtype=float).tolist()}))
    return str(path)


def commands():
    from dssp_sim.calibration_twin import calibrate_main as sim_calibrate
    from dssp_sim.sim_cli import main as sim_main
    from hardware.cli.calibrate import main as calibrate
    from hardware.cli.record import main as record
    from hardware.cli.replay import main as replay
    from hardware.cli.run import main as run

    return {
        "dssp-calibrate": calibrate,
        "dssp-sim calibrate": sim_calibrate,
        "dssp-sim": sim_main,
        "dssp-run": run,
        "dssp-record": record,
        "dssp-replay": replay,
    }


RIG = ["--mode", "eye-to-hand", "--camera", "l515", "--can", "can0"]  # a real rig for dssp-calibrate
TWIN = ["--mode", "eye-to-hand"]
# case: (command, argv (PLAN_* names a plan written in the folder), what the line says)
CASES = {
    "calibrate: --auto too few to solve": ("dssp-calibrate", [*RIG, "--auto", "3", "--out", "c.json"], "--auto"),
    "calibrate: --auto far too many": ("dssp-calibrate", [*RIG, "--auto", "100000", "--out", "c.json"], "--auto"),
    "calibrate: three poses": ("dssp-calibrate", [*RIG, "--poses", "PLAN_THREE", "--out", "c.json"], "cannot pass"),
    "calibrate: twelve identical poses": (
        "dssp-calibrate",
        [*RIG, "--poses", "PLAN_SAME", "--out", "c.json"],
        "cannot pass",
    ),
    "calibrate: an output under a file": ("dssp-calibrate", [*RIG, "--auto", "12", "--out", "plain/c.json"], "plain"),
    "twin: three poses": ("dssp-sim calibrate", [*TWIN, "--poses", "PLAN_THREE", "--out", "c.json"], "cannot pass"),
    "twin: --auto too few": ("dssp-sim calibrate", [*TWIN, "--auto", "5", "--out", "c.json"], "--auto"),
    "eval: a delay for the expert": (
        "dssp-sim",
        [
            "eval",
            "--expert",
            "--task",
            "tap",
            "--inject-delay",
            "100",
            "--rerun-save",
            "eval.rrd",
            "--strips",
            "strips",
        ],
        "--inject-delay is a model's setting",
    ),
    "eval: a delay beyond 10 s": (
        "dssp-sim",
        ["eval", "--model", "model", "--task", "tap", "--inject-delay", "20000", "--rerun-save", "eval.rrd"],
        "--inject-delay must be in",
    ),
    "run: an interface python-can lacks": (
        "dssp-run",
        ["--model", "m", "--camera", "l515", "--can", "can0", "--interface", "bogus"],
        "not a python-can interface",
    ),
    "run: a rate beyond the arm": (
        "dssp-run",
        ["--policy", "hold", "--camera", "tabletop", "--can", "sim", "--control-rate", "5000"],
        "--control-rate",
    ),
    "run: an episode index that is a digit but no number": (
        "dssp-run",
        ["--policy", "episode:d.zarr@\u00b2", "--camera", "tabletop", "--can", "sim"],
        "episode:PATH.zarr@K",
    ),
    "record: an interface python-can lacks": (
        "dssp-record",
        ["--camera", "l515", "--can", "can0", "--out", "d.zarr", "--interface", "bogus"],
        "not a python-can interface",
    ),
    "record: a real camera without extrinsics": (
        "dssp-record",
        ["--camera", "l515", "--can", "can0", "--out", "d.zarr"],
        "--extrinsics",
    ),
    "replay: a recording that is not there": (
        "dssp-replay",
        ["missing.zarr", "--episode", "0", "--can", "sim", "--send"],
        "missing.zarr",
    ),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_a_refused_plan_or_flag_opens_nothing_and_writes_nothing(case, tmp_path, capsys, monkeypatch):
    command, argv, words = CASES[case]
    monkeypatch.chdir(tmp_path)
    (tmp_path / "plain").write_text("a file, not a folder")
    plans = {
        "PLAN_THREE": plan(
            tmp_path, [CALIBRATION_START] * 1 + [np.add(CALIBRATION_START, [0, 0, 0, 0.3, 0, 0]).tolist()] * 2
        ),
        "PLAN_SAME": plan(tmp_path, [CALIBRATION_START] * 12),
    }
    argv = [plans.get(a, a) for a in argv]
    before = snapshot(tmp_path)
    main = commands()[command]
    with nothing_opens(monkeypatch):
        try:
            code = main(argv)
        except SystemExit as exc:  # argparse's refusals
            code = exc.code
    err = capsys.readouterr().err
    assert code == 2, (case, err)
    assert words in one_error_line(err), (case, err)
    assert snapshot(tmp_path) == before, case
    assert not any(name.startswith(".") for name in os.listdir(tmp_path)), case
