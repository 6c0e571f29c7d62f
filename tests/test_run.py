"""``dssp-run`` end to end on the embedded simulation, and fault injection: every fault holds within one
tick, and the CAN bus log proves that no command outside the limits (or beyond the per-tick step) was sent.

The fault injection drives the loop on a manual clock (``hardware.clock.FakeClock``) over a stepped arm
and camera, the real driver and CAN bus in between: every age, hold and tick time is exact on any
machine. The ``dssp-run`` tests run the command itself, whose simulated devices are threads on wall time
(a camera thread, a simulated arm and the driver's receive thread on a python-can bus): they are real
time, and assert nothing that depends on how fast the machine is.
"""

import csv
import dataclasses
import json
import os
import signal
import subprocess
import sys
import threading
import time
import uuid

import numpy as np
import pytest
from conftest import GRIPPER, LIMITS, WIRE, assert_within_limits, sent_commands
from waiting import World, wait_for

from dssp_data.pointcloud import PointCloudConfig
from dssp_deploy.onnx_policy import OnnxPolicy
from hardware.camera.base import Camera
from hardware.camera.tabletop import SimCamera
from hardware.can_log import BusRecorder, read_log
from hardware.cli.run import main as run_main
from hardware.piper import codec
from hardware.piper.arm import PiperArm
from hardware.piper.can_simulator import SimulatedPiper
from hardware.piper.piper_robot import PiperRobot
from hardware.policies.exported_model import ModelPolicy
from hardware.rig import Rig
from hardware.robot import Robot
from hardware.run_log import RunLog, read_clouds, read_ticks
from hardware.run_loop import LoopSettings, Runner
from hardware.safety import SafetyConfig
from hardware.subscribers import Subscriber


# ----------------------------------------------------------------------------- the command
def test_dssp_run_on_the_embedded_simulation(arm_export, tmp_path, capsys):
    """Real time (the command's device threads): how many ticks hold is the machine's business; what is
    logged, sent and kept within the limits is checked exactly. The fault injection below shows that fresh
    inputs are commanded every tick."""
    log_dir = tmp_path / "log"
    code = run_main(
        [
            "--model",
            str(arm_export),
            "--camera",
            "tabletop",
            "--can",
            "sim",
            "--max-steps",
            "60",
            "--log-dir",
            str(log_dir),
            "--seed",
            "0",
            "--threads",
            "1",
            "--quiet",
            "--subscribe",
            "csv",
        ]
    )
    out = capsys.readouterr().out
    assert code == 0, out
    assert "ticks 60" in out and "ended by: max steps" in out
    ticks = read_ticks(log_dir)
    assert [t["tick"] for t in ticks] == list(range(60))
    policy_ticks = [t for t in ticks if t["action"] is not None]
    assert policy_ticks
    summary = json.loads((log_dir / "run.json").read_text())["summary"]
    assert summary["ticks"] == 60 and summary["commands_sent"] == sum(t["command"] is not None for t in ticks)
    clouds = read_clouds(log_dir)
    assert clouds.shape == (len(policy_ticks), 64, 3) and np.all(np.isfinite(clouds))
    [blf] = log_dir.glob("can_*.blf")
    commands = sent_commands(blf)
    # every command the loop decided on is on the bus (the final hold adds one), in order, within the limits
    logged = np.array([t["command"] for t in ticks if t["command"] is not None])
    assert len(commands) == len(logged) + 1
    assert np.allclose(commands[: len(logged)], logged, atol=WIRE)
    assert_within_limits(commands, np.where(GRIPPER, SafetyConfig().max_gripper_step, SafetyConfig().max_joint_step))
    # the CSV subscriber (--subscribe csv) saw the same ticks the episode log holds
    with open(log_dir / "ticks.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["tick"]) for r in rows] == list(range(60))
    assert [int(r["held"]) for r in rows] == [int(t["held"]) for t in ticks]
    for row, t in zip(rows, ticks):
        if t["command"] is None:
            assert row["command_0"] == ""
        else:
            assert np.allclose([float(row[f"command_{i}"]) for i in range(7)], t["command"], atol=1e-6)
        assert (row["chunk_ms"] == "") == (t.get("chunk_ms") is None)


def test_an_unknown_subscriber_is_refused_before_anything_opens(arm_export, tmp_path, capsys):
    code = run_main(["--model", str(arm_export), "--log-dir", str(tmp_path / "log"), "--subscribe", "nope"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err == ["error: --subscribe nope: no such subscriber; choose from csv"]
    assert not (tmp_path / "log").exists()


def test_two_arms_as_one_14_value_robot(dual_arm_export, tmp_path, capsys):
    log_dir = tmp_path / "log"
    code = run_main(
        [
            "--model",
            str(dual_arm_export),
            "--camera",
            "tabletop",
            "--can",
            "sim:2",
            "--max-steps",
            "40",
            "--log-dir",
            str(log_dir),
            "--seed",
            "0",
            "--threads",
            "1",
            "--quiet",
        ]
    )
    assert code == 0, capsys.readouterr()
    ticks = [t for t in read_ticks(log_dir) if t["command"] is not None]
    assert ticks and all(len(t["command"]) == 14 and len(t["state"]) == 14 for t in ticks)
    logged = np.array([t["command"] for t in ticks])
    blfs = sorted(log_dir.glob("can_*.blf"))
    assert [b.name.rsplit("-", 1)[-1] for b in blfs] == ["left.blf", "right.blf"]
    for side, blf in enumerate(blfs):  # the left arm gets values 0..6, the right arm 7..13
        commands = sent_commands(blf)
        assert np.allclose(commands[: len(logged)], logged[:, 7 * side : 7 * side + 7], atol=WIRE)
        assert_within_limits(commands, np.where(GRIPPER, 0.2, 0.05))


def test_dry_run_sends_nothing(arm_export, tmp_path, capsys):
    log_dir = tmp_path / "log"
    code = run_main(
        [
            "--model",
            str(arm_export),
            "--camera",
            "tabletop",
            "--can",
            "sim",
            "--max-steps",
            "30",
            "--dry-run",
            "--log-dir",
            str(log_dir),
            "--threads",
            "1",
            "--quiet",
        ]
    )
    assert code == 0 and "[dry run]" in capsys.readouterr().out
    [blf] = log_dir.glob("can_*.blf")
    decoder = codec.Decoder()
    kinds = {type(decoder.decode(f)).__name__ for f in read_log(blf)}
    assert "JointFeedback" in kinds  # the arm was heard
    assert not kinds & {"JointCtrl", "GripperCtrl", "MotorEnable", "MotionCtrl2"}
    assert sum(t["command"] is not None for t in read_ticks(log_dir)) > 0  # decided, logged, not sent


def test_bad_input_fails_before_motion(arm_export, tmp_path, capsys):
    code = run_main(
        ["--model", str(arm_export), "--can", "sim:2", "--max-steps", "5", "--log-dir", str(tmp_path / "a")]
    )
    err = capsys.readouterr().err
    assert code == 2 and "robot has 14 values" in err and "Traceback" not in err
    code = run_main(
        ["--model", str(arm_export), "--camera", "d435", "--max-steps", "5", "--log-dir", str(tmp_path / "b")]
    )
    assert code == 2 and "--extrinsics is needed" in capsys.readouterr().err
    code = run_main(["--model", str(tmp_path / "missing"), "--max-steps", "5"])
    assert code == 2 and "does not exist" in capsys.readouterr().err


def test_sigterm_ends_in_a_hold(arm_export, tmp_path, capsys):
    """Real time: a signal into a running process (it is sent once 20 ticks are logged, whenever that is)."""
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
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    wait_for(
        lambda: proc.poll() is not None or ((log_dir / "ticks.jsonl").exists() and len(read_ticks(log_dir)) >= 20),
        timeout=120,
        what="20 logged ticks",
        poll=0.1,
    )
    # a second dssp-run on the same log directory: one line naming the running one, nothing of it touched
    assert run_main(["--model", str(arm_export), "--log-dir", str(log_dir), "--quiet"]) == 2
    assert f"is being written by pid {proc.pid}" in capsys.readouterr().err
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert "ended by: SIGTERM" in out
    events = json.loads((log_dir / "run.json").read_text())["summary"]["safety_events"]
    assert [e["kind"] for e in events[-2:]] == ["hold", "stop"] and "SIGTERM" in events[-1]["detail"]
    [blf] = log_dir.glob("can_*.blf")
    assert_within_limits(sent_commands(blf), np.where(GRIPPER, 0.2, 0.05))


# ----------------------------------------------------------------------------- fault injection
RATE = 20.0
PERIOD = 1 / RATE
# Only the input under test is strict, and the deadline rule is off except where it is the subject: the
# runtime judges a chunk's budget on the CPU's stopwatch, which no clock of the loop controls.
FEEDBACK_SAFETY = SafetyConfig(camera_timeout=1.0, feedback_timeout=0.03, deadline_hold=False)
CAMERA_SAFETY = SafetyConfig(camera_timeout=0.03, feedback_timeout=1.0, deadline_hold=False)
DEADLINE_SAFETY = SafetyConfig(camera_timeout=1.0, feedback_timeout=1.0)


class SteppedCamera(Camera):
    """A stepped SimCamera whose frames arrive on ``clock``; frozen, it keeps handing out its last frame."""

    name = "stepped"

    def __init__(self, clock):
        self.sim, self.clock, self.frozen, self.frame = SimCamera(seed=0), clock, False, None
        self.camera_to_base = self.sim.camera_to_base

    def start(self):
        self.sim.start(thread=False)
        self.step(0.0)

    def step(self, dt):
        if not self.frozen:
            self.frame = dataclasses.replace(self.sim.capture(), timestamp=self.clock.now())

    def latest(self):
        return self.frame

    def stop(self):
        self.sim.stop()


class SteppedArm(Robot):
    """One simulated Piper behind the real driver on a virtual CAN bus, stepped by hand, its feedback on ``clock``.

    ``step(dt)``: the simulator takes the commands sent so far, moves ``dt`` and reports (nothing while its
    feedback is paused); once the driver's receive thread has the report, it is stamped ``clock.now()``.
    The driver's own waits read the wall clock (hardware.piper): its status-frame age limit is set out of
    reach and its enable confirmation gets a generous bound, so neither can decide a verdict here.
    """

    dof = 7

    @property
    def description(self):
        return self.inner.description

    def __init__(self, clock):
        self.channel, self.clock, self.arrived = f"dssp-test-{uuid.uuid4().hex[:8]}", clock, None
        self.sim = SimulatedPiper(self.channel, "virtual")
        self.arm = PiperArm(self.channel, "virtual", stale_after=3600.0)
        self.inner = PiperRobot([self.arm], simulators=[self.sim])

    def connect(self):
        self.sim.start(thread=False)
        self.inner.connect()

    def step(self, dt):
        sent, mark = self.sim.frames_sent, time.monotonic()
        self.sim.step(dt)
        if self.sim.frames_sent > sent:
            wait_for(lambda: min(self._arrival_times()) >= mark, timeout=30.0, what="the arm's feedback", poll=0.0005)
            self.arrived = self.clock.now()

    def _arrival_times(self):
        fb = self.arm.feedback()
        return fb.joints_time, fb.gripper_time, fb.status_time

    def state(self):
        state = self.inner.state()
        return None if state is None else dataclasses.replace(state, timestamp=self.arrived)

    def enable(self, timeout=2.0):
        """Enable, the simulator answering (without moving) until the driver confirms."""
        done = threading.Event()

        def answer():
            while not done.is_set():
                self.sim.step(0.0)
                done.wait(0.002)

        thread = threading.Thread(target=answer, daemon=True)
        thread.start()
        try:
            self.inner.enable(timeout=30.0)
        finally:
            done.set()
            thread.join()

    def command(self, target):
        self.inner.command(target)

    def emergency_stop(self):
        self.inner.emergency_stop()

    def disable(self):
        self.inner.disable()

    def close(self):
        self.inner.close()


@pytest.fixture
def rig(arm_export, tmp_path, request):
    """A Runner on a manual clock (``waiting.World``) over a stepped arm and camera, with a bus recorder.

    Yields (runner, robot, camera, ticks, clock): ``ticks(n)`` runs n ticks one period apart (the devices
    move and report in between). The safety settings are ``request.param`` (CAMERA_SAFETY by default).
    """
    clock = World()
    policy = OnnxPolicy(arm_export, threads=1)
    robot, camera = SteppedArm(clock), SteppedCamera(clock)
    blf = tmp_path / "bus.blf"
    with camera, robot, BusRecorder(robot.channel, "virtual", blf):
        with pytest.warns(UserWarning, match="20 Hz"):  # the model was trained at 50 Hz
            rig = Rig(
                camera,
                robot,
                camera.camera_to_base,
                getattr(request, "param", CAMERA_SAFETY),
                clock=clock,
                limits=(LIMITS.lower, LIMITS.upper, GRIPPER),
            )
            runner = Runner(
                ModelPolicy(policy, RATE, seed=0),
                rig,
                PointCloudConfig(n_points=64),
                LoopSettings(control_rate_hz=RATE),
                subscribers=[RunLog(tmp_path / "log", {})],
            )
        robot.step(0.0)
        runner.start()
        clock.steps = [robot.step, camera.step]

        def ticks(n):
            records = []
            for _ in range(n):
                clock.sleep(PERIOD)
                records.append(runner.tick())
            return records

        yield runner, robot, camera, ticks, clock
        runner.finish("test over")
    runner.close()
    assert_within_limits(sent_commands(blf), runner.safety.max_step)


def holds_for(record, text):
    return record["held"] and any(text in e["detail"] for e in record["safety"])


@pytest.mark.parametrize("rig", [FEEDBACK_SAFETY], indirect=True, ids=["strict feedback"])
def test_feedback_dropped_holds_within_one_tick(rig):
    _, robot, _, ticks, _ = rig
    assert not any(r["held"] for r in ticks(10))  # fresh inputs: the loop commands every tick
    robot.sim.pause_feedback()
    after = ticks(3)  # a period after the last report, the feedback is past its 30 ms: the first tick holds
    assert all(holds_for(r, "joint feedback is") for r in after)
    assert [r["feedback_age_ms"] for r in after] == pytest.approx([50.0, 100.0, 150.0])
    assert all(r["action"] is None for r in after)  # the history is not fed stale inputs
    robot.sim.resume_feedback()
    assert not ticks(1)[0]["held"]


def test_camera_frozen_holds_within_one_tick(rig):
    _, _, camera, ticks, _ = rig
    assert not any(r["held"] for r in ticks(10))
    camera.frozen = True
    after = ticks(3)
    assert all(holds_for(r, "camera frame is") for r in after)
    assert [r["frame_age_ms"] for r in after] == pytest.approx([50.0, 100.0, 150.0])
    held = after[0]["command"]
    assert all(np.array_equal(r["command"], held) for r in after)  # the same last safe target, resent


@pytest.mark.parametrize("rig", [DEADLINE_SAFETY], indirect=True, ids=["deadline rule"])
def test_slow_inference_holds_on_the_late_tick(rig):
    runner, _, _, ticks, clock = rig
    ticks(6)
    denoise = runner.source.policy.denoise

    def slow(*args, **kwargs):
        clock.advance(2 * PERIOD)  # the chunk takes two periods of the loop's clock
        return denoise(*args, **kwargs)

    runner.source.policy.denoise = slow
    after = ticks(runner.source.policy.contract.n_action_steps + 1)
    late = [r for r in after if "chunk_ms" in r]
    assert late and all(holds_for(r, "deadline") for r in late)
    on_time = [r for r in after if "chunk_ms" not in r]
    assert on_time and not any(r["held"] for r in on_time)


def test_arm_error_stops_commanding(rig):
    runner, robot, _, ticks, _ = rig
    ticks(5)
    sent_before = runner.sent
    robot.sim.raise_error(1 << 10)  # J3 joint limit, in the arm's next report
    record = ticks(1)[0]
    assert record["command"] is None and runner.fault and "joint" in runner.fault.lower()
    assert any(e["kind"] == "fault" for e in record["safety"])
    assert all(r["command"] is None for r in ticks(3))
    assert runner.sent == sent_before


class Seen(Subscriber):
    """What a subscriber is told, in order."""

    def __init__(self):
        self.calls = []

    def on_start(self, loop):
        self.calls.append(("start", loop.ticks, loop.safety is not None))

    def on_tick(self, tick):
        self.calls.append(("tick", tick))

    def on_end(self, summary):
        self.calls.append(("end", summary))


def test_subscribers_see_the_start_every_tick_after_its_command_and_the_end_once(rig):
    runner, robot, camera, ticks, clock = rig
    seen = Seen()
    runner.subscribers.append(seen)
    records = ticks(5)
    got = [c[1] for c in seen.calls if c[0] == "tick"]
    assert [t.record for t in got] == records and [t.record["tick"] for t in got] == list(range(5))
    assert all(t.loop is runner for t in got)
    commanded = [t for t in got if t.record["command"] is not None]
    assert commanded  # each was sent before the subscriber heard of it
    assert all(t.cloud is None or t.cloud.shape == (64, 3) for t in got)
    assert any(t.chunk is not None for t in got) and all(t.chunk is None or t.chunk.ndim == 2 for t in got)
    runner.finish("test over")
    first = runner.close()
    assert runner.close() == first  # told once
    ends = [c[1] for c in seen.calls if c[0] == "end"]
    assert len(ends) == 1 and ends[0]["ended_by"] == "test over" and ends[0]["ticks"] == 5


def test_the_status_line_counts_what_the_loop_counts(rig):
    from hardware.subscribers.status_line import StatusLine

    runner, robot, camera, ticks, clock = rig
    lines = []
    runner.subscribers.append(StatusLine(lines.append))
    ticks(3)
    assert len(lines) == 3 and lines[-1].startswith("tick     3") and f"holds {runner.holds}" in lines[-1]


def test_the_loop_keeps_its_period_on_its_clock(rig):
    """run() sleeps to each next tick on the runner's clock: ticks one period apart; a tick that outlasts
    its period is an overrun, and the schedule restarts from it rather than catching up."""
    runner, _, _, _, clock = rig
    records = []
    tick = runner.tick
    runner.tick = lambda: records.append(tick()) or records[-1]

    class Slow(Subscriber):  # the 4th tick is slow
        def on_tick(self, t):
            if t.record["tick"] == 3:
                clock.advance(1.5 * PERIOD)

    runner.subscribers.append(Slow())
    runner.settings = dataclasses.replace(runner.settings, max_steps=10)
    summary = runner.run()
    gaps = np.diff([r["time"] for r in records]) / PERIOD
    assert len(records) == 10 and gaps == pytest.approx([1, 1, 1, 1.5, 1, 1, 1, 1, 1])
    assert summary["overruns"] == 1 and summary["ended_by"] == "max steps"
    assert summary["rate_hz"] == pytest.approx(9 / (9.5 * PERIOD))


@pytest.mark.parametrize("suffix", [".blf", ".asc"])
def test_the_can_log_takes_any_bus_name(tmp_path, suffix):
    """A generated channel name whose trailing digits overflow BLF/ASC's channel number is still logged."""
    import can

    from hardware.can_log import BusRecorder, read_log

    channel = "dssp-test-b1996431"
    path = tmp_path / f"bus{suffix}"
    with BusRecorder(channel, "virtual", path):
        with can.Bus(channel=channel, interface="virtual") as sender:
            sender.send(can.Message(arbitration_id=0x2A5, data=bytes(8), is_extended_id=False))
    frames = read_log(path)
    assert [f.arbitration_id for f in frames] == [0x2A5]
