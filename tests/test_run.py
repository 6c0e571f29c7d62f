"""``dssp-run`` end to end on the embedded simulation, and fault injection: every fault holds within one
tick, and the CAN bus log proves that no command outside the limits (or beyond the per-tick step) was sent."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from dssp_deploy.onnx_policy import OnnxPolicy
from hardware.camera.base import Camera
from hardware.camera.tabletop import SimCamera
from hardware.can_log import BusRecorder, read_log
from hardware.cli.run import main as run_main
from hardware.piper import codec
from hardware.piper.limits import GRIPPER_STROKE_MAX, JointLimits
from hardware.piper.piper_robot import open_robot
from hardware.pointcloud import PointCloudConfig
from hardware.run_log import RunLog, read_clouds, read_ticks
from hardware.run_loop import LoopSettings, Runner
from hardware.safety import SafetyConfig

LIMITS = JointLimits.piper()
GRIPPER = np.arange(7) == 6
WIRE = 2e-5  # 0.001 degree on the wire, in rad (and 1 µm of stroke)


def sent_commands(blf_path):
    """The joint+gripper commands on the bus, (n, 7) in policy units, from the 0x155-0x157 + 0x159 frames."""
    decoder = codec.Decoder()
    commands, joints = [], {}
    gripper = None
    for frame in read_log(blf_path):
        msg = decoder.decode(frame)
        if isinstance(msg, codec.JointCtrl):
            joints[msg.pair] = (msg.first, msg.second)
            if msg.pair == 2:
                assert set(joints) == {0, 1, 2}, "joint frames out of order"
                commands.append([*joints[0], *joints[1], *joints[2], np.nan])
                joints = {}
        elif isinstance(msg, codec.GripperCtrl) and msg.code == codec.GRIPPER_ENABLE:
            gripper = msg.stroke / GRIPPER_STROKE_MAX
            if commands and np.isnan(commands[-1][6]):
                commands[-1][6] = gripper
    return np.array(commands).reshape(-1, 7)


def assert_within_limits(commands, max_step):
    assert np.all(commands[:, :6] >= LIMITS.lower[:6] - WIRE) and np.all(commands[:, :6] <= LIMITS.upper[:6] + WIRE)
    grip = commands[:, 6][~np.isnan(commands[:, 6])]
    assert np.all(grip >= -WIRE) and np.all(grip <= 1 + WIRE)
    steps = np.abs(np.diff(commands, axis=0))
    steps = np.where(np.isnan(steps), 0, steps)
    assert np.all(steps <= max_step + 2 * WIRE), steps.max(axis=0)


# ----------------------------------------------------------------------------- the command
def test_dssp_run_on_the_embedded_simulation(arm_export, tmp_path, capsys):
    log_dir = tmp_path / "log"
    code = run_main(["--model", str(arm_export), "--camera", "sim", "--can", "sim", "--max-steps", "300",
                     "--log-dir", str(log_dir), "--seed", "0", "--threads", "1", "--quiet"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "ticks 300" in out and "ended by: max steps" in out
    ticks = read_ticks(log_dir)
    assert [t["tick"] for t in ticks] == list(range(300))
    policy_ticks = [t for t in ticks if t["action"] is not None]
    assert len(policy_ticks) >= 250  # a few may hold when the shared machine stalls a tick
    summary = json.loads((log_dir / "run.json").read_text())["summary"]
    assert summary["ticks"] == 300 and summary["commands_sent"] == sum(t["command"] is not None for t in ticks)
    clouds = read_clouds(log_dir)
    assert clouds.shape == (len(policy_ticks), 64, 3) and np.all(np.isfinite(clouds))
    [blf] = log_dir.glob("can_*.blf")
    commands = sent_commands(blf)
    # every command the loop decided on is on the bus (the final hold adds one), in order, within the limits
    logged = np.array([t["command"] for t in ticks if t["command"] is not None])
    assert len(commands) == len(logged) + 1
    assert np.allclose(commands[: len(logged)], logged, atol=WIRE)
    assert_within_limits(commands, np.where(GRIPPER, SafetyConfig().max_gripper_step, SafetyConfig().max_joint_step))


def test_two_arms_as_one_14_value_robot(dual_arm_export, tmp_path, capsys):
    log_dir = tmp_path / "log"
    code = run_main(["--model", str(dual_arm_export), "--camera", "sim", "--can", "sim:2", "--max-steps", "40",
                     "--log-dir", str(log_dir), "--seed", "0", "--threads", "1", "--quiet"])
    assert code == 0, capsys.readouterr()
    ticks = [t for t in read_ticks(log_dir) if t["command"] is not None]
    assert ticks and all(len(t["command"]) == 14 and len(t["state"]) == 14 for t in ticks)
    logged = np.array([t["command"] for t in ticks])
    blfs = sorted(log_dir.glob("can_*.blf"))
    assert [b.name.rsplit("-", 1)[-1] for b in blfs] == ["left.blf", "right.blf"]
    for side, blf in enumerate(blfs):  # the left arm gets values 0..6, the right arm 7..13
        commands = sent_commands(blf)
        assert np.allclose(commands[: len(logged)], logged[:, 7 * side: 7 * side + 7], atol=WIRE)
        assert_within_limits(commands, np.where(GRIPPER, 0.2, 0.05))


def test_dry_run_sends_nothing(arm_export, tmp_path, capsys):
    log_dir = tmp_path / "log"
    code = run_main(["--model", str(arm_export), "--camera", "sim", "--can", "sim", "--max-steps", "30",
                     "--dry-run", "--log-dir", str(log_dir), "--threads", "1", "--quiet"])
    assert code == 0 and "[dry run]" in capsys.readouterr().out
    [blf] = log_dir.glob("can_*.blf")
    decoder = codec.Decoder()
    kinds = {type(decoder.decode(f)).__name__ for f in read_log(blf)}
    assert "JointFeedback" in kinds  # the arm was heard
    assert not kinds & {"JointCtrl", "GripperCtrl", "MotorEnable", "MotionCtrl2"}
    assert sum(t["command"] is not None for t in read_ticks(log_dir)) > 0  # decided, logged, not sent


def test_bad_input_fails_before_motion(arm_export, tmp_path, capsys):
    code = run_main(["--model", str(arm_export), "--can", "sim:2", "--max-steps", "5", "--log-dir", str(tmp_path / "a")])
    err = capsys.readouterr().err
    assert code == 2 and "robot has 14 values" in err and "Traceback" not in err
    code = run_main(["--model", str(arm_export), "--camera", "d435", "--max-steps", "5", "--log-dir", str(tmp_path / "b")])
    assert code == 2 and "--extrinsics is needed" in capsys.readouterr().err
    code = run_main(["--model", str(tmp_path / "missing"), "--max-steps", "5"])
    assert code == 2 and "does not exist" in capsys.readouterr().err


def test_sigterm_ends_in_a_hold(arm_export, tmp_path):
    log_dir = tmp_path / "log"
    proc = subprocess.Popen(
        [sys.executable, "-m", "hardware.cli.run", "--model", str(arm_export), "--camera", "sim", "--can", "sim",
         "--log-dir", str(log_dir), "--threads", "1"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        if (log_dir / "ticks.jsonl").exists() and len(read_ticks(log_dir)) >= 20:
            break
        time.sleep(0.1)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "ended by: SIGTERM" in out
    events = json.loads((log_dir / "run.json").read_text())["summary"]["safety_events"]
    assert [e["kind"] for e in events[-2:]] == ["hold", "stop"] and "SIGTERM" in events[-1]["detail"]
    [blf] = log_dir.glob("can_*.blf")
    assert_within_limits(sent_commands(blf), np.where(GRIPPER, 0.2, 0.05))


# ----------------------------------------------------------------------------- fault injection
RATE = 20.0
PERIOD = 1 / RATE
# Each fault test makes only its own input strict, so a stalled machine cannot hold for another reason first.
FEEDBACK_SAFETY = SafetyConfig(camera_timeout=1.0, feedback_timeout=0.03)
CAMERA_SAFETY = SafetyConfig(camera_timeout=0.03, feedback_timeout=1.0)


class FreezableCamera(Camera):
    """A stepped SimCamera: ``capture()`` each tick; frozen, it keeps handing out its last frame."""

    name = "freezable"

    def __init__(self):
        self.sim, self.frozen = SimCamera(seed=0), False
        self.camera_to_base = self.sim.camera_to_base

    def start(self):
        self.sim.start(thread=False)
        self.sim.capture()

    def capture(self):
        if not self.frozen:
            self.sim.capture()

    def latest(self):
        return self.sim.latest()

    def stop(self):
        self.sim.stop()


@pytest.fixture
def rig(arm_export, tmp_path, request):
    """A Runner on one simulated arm and a stepped camera, with a bus recorder: yields a helper."""
    policy = OnnxPolicy(arm_export, threads=1)
    robot = open_robot("sim")
    camera = FreezableCamera()
    blf = tmp_path / "bus.blf"
    with camera, robot, BusRecorder(robot.arms[0].channel, "virtual", blf):
        with pytest.warns(UserWarning, match="20 Hz"):  # the model was trained at 50 Hz
            safety = FEEDBACK_SAFETY if "feedback" in request.node.name else CAMERA_SAFETY
            runner = Runner(policy, camera, robot, PointCloudConfig(n_points=64), camera.camera_to_base, safety,
                            LoopSettings(rate_hz=RATE, seed=0), (LIMITS.lower, LIMITS.upper, GRIPPER),
                            log=RunLog(tmp_path / "log", {}))
        runner.start()

        def ticks(n):
            records = []
            for _ in range(n):
                camera.capture()
                records.append(runner.tick())
                time.sleep(PERIOD)
            return records

        yield runner, robot, camera, ticks
        runner.finish("test over")
    runner.log.close(runner.summary())
    assert_within_limits(sent_commands(blf), runner.safety.max_step)


def holds_for(record, text):
    return record["held"] and any(text in e["detail"] for e in record["safety"])


def test_feedback_dropped_holds_within_one_tick(rig):
    runner, robot, _, ticks = rig
    before = ticks(10)
    assert sum(not r["held"] for r in before) >= 3  # the loop commands normally (a stalled machine may hold some)
    robot.simulators[0].pause_feedback()
    after = ticks(3)[1:]  # the first tick comes at once, before the feedback can be older than the timeout;
    # the next one, a period later (the timeout is shorter than a period), must hold
    assert all(holds_for(r, "joint feedback is") for r in after)
    assert all(r["action"] is None for r in after)  # the history is not fed stale inputs
    robot.simulators[0].resume_feedback()
    time.sleep(0.05)
    assert not ticks(3)[-1]["held"]


def test_camera_frozen_holds_within_one_tick(rig):
    runner, _, camera, ticks = rig
    ticks(10)
    camera.frozen = True
    after = ticks(3)
    assert all(holds_for(r, "camera frame is") for r in after)
    held = after[0]["command"]
    assert all(np.array_equal(r["command"], held) for r in after)  # the same last safe target, resent


def test_slow_inference_holds_on_the_late_tick(rig):
    runner, _, _, ticks = rig
    ticks(6)
    denoise = runner.policy.denoise

    def slow(*args, **kwargs):
        time.sleep(2 * PERIOD)
        return denoise(*args, **kwargs)

    runner.policy.denoise = slow
    after = ticks(runner.policy.n_action_steps + 1)
    late = [r for r in after if "chunk_ms" in r]
    assert late and all(holds_for(r, "deadline") for r in late)
    on_time = [r for r in after if "chunk_ms" not in r and r["action"] is not None]
    assert on_time and sum(not r["held"] for r in on_time) >= len(on_time) - 1


def test_arm_error_stops_commanding(rig):
    runner, robot, _, ticks = rig
    ticks(5)
    sent_before = runner.sent
    robot.simulators[0].raise_error(1 << 10)  # J3 joint limit
    time.sleep(PERIOD)
    record = ticks(1)[0]
    assert record["command"] is None and runner.fault and "joint" in runner.fault.lower()
    assert any(e["kind"] == "fault" for e in record["safety"])
    assert all(r["command"] is None for r in ticks(3))
    assert runner.sent == sent_before
