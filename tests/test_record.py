"""``dssp-record`` on the embedded default (scripted leader -> simulated follower on a virtual bus, simulated
camera): episodes recorded, a recorder killed mid-episode leaves every completed episode, training reads
the result; stream problems are flagged per step and per episode; operator commands; the robot's loop.

The sessions run on a clock no machine's speed can move: the rig's simulated clock in lockstep, or a
manual clock (``waiting.World``) for the robot's loop. What stays real time says why."""

import contextlib
import io
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import zarr
from conftest import ROOT, WIRE
from waiting import World, wait_for

from dssp_core.errors import DatasetError
from dssp_data.recording import (
    FLAGS_KEY,
    STEP_PROBLEMS,
    can_log_dir,
    episode_infos,
)
from dssp_data.replay_buffer import ReplayBuffer, ReplayBufferReader
from dssp_sim.teleop import TeleopRigs, record_main
from hardware.can_log import read_log
from hardware.cli.record import Console, LineControls, open_session, parse_args
from hardware.leader import LeaderTracker, leader_frames
from hardware.piper import codec


def _env():
    return {
        **os.environ,
        "OMP_NUM_THREADS": "1",
        "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
    }


class Scripted:
    """Controls for an in-process session: ``plan(session)`` returns the next command (or None) each tick."""

    def __init__(self, session, plan):
        self.session, self.plan = session, plan

    def poll(self):
        return self.plan(self.session)

    def close(self):
        pass


def run_session(args, plan_or_controls, capsys=None):
    """Open a session like dssp-record does and run it with scripted controls; returns (summary, events)."""
    events = []
    console = Console(quiet=True)
    console.event = events.append
    with contextlib.ExitStack() as stack:
        session = open_session(parse_args(args, sim=TeleopRigs()), stack, console)
        controls = plan_or_controls if hasattr(plan_or_controls, "poll") else Scripted(session, plan_or_controls)
        summary = session.run(controls)
    return summary, events


# ------------------------------------------------------------------------------------------------ the leader
def test_leader_frames_decode_to_the_commanded_target():
    target = np.array([0.3, 1.2, -0.8, 0.1, 0.4, -0.2, 0.6])
    tracker, decoder = LeaderTracker(), codec.Decoder()
    assert tracker.reading().position is None
    for k, frame in enumerate(leader_frames(target)):
        tracker.update(decoder.decode(frame), t=float(k))
    ids = [f.arbitration_id for f in leader_frames(target)]
    assert ids == [0x151, 0x155, 0x156, 0x157, 0x159]
    reading = tracker.reading()
    np.testing.assert_allclose(reading.position, target, atol=WIRE)
    assert reading.time == 1.0  # the oldest of the four frames that make the target (0x155 arrived at t = 1)


# ------------------------------------------------------------------------------------------------ end to end
def test_record_kill_mid_episode_then_train(tmp_path, capsys):
    """Real time: a recording process killed mid-episode; paced at ``--sim-speed 3`` (2 s an episode), it is
    killed as soon as it says its second episode is recording (the episode's CAN log is open by then)."""
    out = tmp_path / "demo.zarr"
    assert record_main(["--out", str(out), "--auto", "--episodes", "3", "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert printed.count(": kept, ") == 3 and "holds 3 episodes" in printed
    first = ReplayBuffer.load(out, extras=True)
    assert first.n_episodes == 3

    # A second session appends; it is killed (SIGKILL) in the middle of its second episode.
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "dssp_sim.sim_cli",
            "record",
            "--out",
            str(out),
            "--auto",
            "--episodes",
            "20",
            "--sim-speed",
            "3",
            "--quiet",
        ],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=_env(),
        cwd=tmp_path,
    )
    lines = []
    try:
        for line in proc.stdout:
            lines.append(line.strip())
            if line.startswith("episode 4: recording"):  # 6 s of simulated time, 2 s at --sim-speed 3, to go
                break
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL, (lines, proc.stderr.read())
    assert "episode 3: kept, 60 steps, 10.00 Hz, clean" in lines

    buffer = ReplayBuffer.load(out, extras=True)  # readable as is: the killed episode was never written
    assert buffer.n_episodes == 4 and buffer.dropped_tail_steps == 0
    for i in range(3):  # the first session's episodes are untouched
        np.testing.assert_array_equal(buffer.episode(i).state, first.episode(i).state)
    infos = episode_infos(buffer.attrs, buffer.n_episodes)
    assert [info["index"] for info in infos] == [0, 1, 2, 3]
    assert [info["session"] for info in infos] == [0, 0, 0, 1]
    assert [info["sim"]["seed"] for info in infos] == [0, 1, 2, 3]
    assert len(buffer.attrs["recording_sessions"]) == 2
    logs = sorted(p.name for p in can_log_dir(out).iterdir() if not p.name.startswith("."))
    assert [n for n in logs if ".partial-" not in n] == [f"episode_00000{i}.sim.blf" for i in range(4)]
    assert len([n for n in logs if n.startswith("episode_000004.sim.partial-")]) == 1  # the killed episode's

    # What was recorded is consistent: 16 frames per step on the bus, clouds/state/action/timestamps aligned.
    ep = buffer.episode(3)
    frames = read_log(can_log_dir(out) / infos[3]["can_logs"]["sim"])
    assert len(frames) == infos[3]["can_frames"]["sim"] > 15 * ep.n_steps
    assert {0x151, 0x155, 0x159, 0x2A1, 0x2A5, 0x2A8} <= {f.arbitration_id for f in frames}
    np.testing.assert_allclose(ep.extras["timestamp"], np.arange(ep.n_steps) * 0.1, atol=1e-9)
    for key in ("camera_timestamp", "state_timestamp", "action_timestamp"):
        np.testing.assert_allclose(ep.extras[key], ep.extras["timestamp"], atol=1e-9)  # lockstep: every stream fresh
    assert not ep.extras[FLAGS_KEY].any() and ep.extras["depth"].shape == (ep.n_steps, 120, 160)
    assert np.all(np.diff(ep.extras["camera_frame"]) > 0)
    # The leader's command leads the follower: the state one step later is close to the command.
    assert np.abs(ep.state[1:, :6] - ep.action[:-1, :6]).max() < 0.02
    assert buffer.attrs["action_convention"].startswith("leader_command")
    assert buffer.attrs["control_rate_hz"] == 10.0 and len(buffer.attrs["camera_to_base"]) == 4

    from dssp_train.cli.train import main as train_main

    assert (
        train_main(
            [
                "--data",
                str(out),
                "--preset",
                "sim",
                "--steps",
                "5",
                "--out",
                str(tmp_path / "run"),
                "--set",
                "train.val_every=5",
                "--no-progress",
            ]
        )
        == 0
    )


def signalled_at(out: Path, start: str, sig: int, cwd: Path) -> tuple[subprocess.Popen, list[str]]:
    """``dssp-sim record --auto`` into ``out`` (paced at ``--sim-speed 4``), sent ``sig`` when it prints a line that
    starts with ``start``; (the finished process, its stdout lines)."""
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "dssp_sim.sim_cli",
            "record",
            "--out",
            str(out),
            "--auto",
            "--sim-speed",
            "4",
            "--no-depth",
        ],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=_env(),
        cwd=cwd,
    )
    lines = []
    try:
        for line in proc.stdout:
            lines.append(line.strip())
            if line.startswith(start):
                proc.send_signal(sig)
        proc.wait(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    return proc, lines


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP], ids=["SIGTERM", "SIGHUP"])
def test_a_signal_discards_the_unfinished_episode(tmp_path, sig):
    """Real time: a signal into a recording process; paced at ``--sim-speed 4`` (1.5 s an episode), it is
    signalled as soon as it says its second episode is recording. Any stop signal (here also a closed terminal's SIGHUP) ends the session
    the same way; the exit code is 128 + the signal's number."""
    out = tmp_path / "demo.zarr"
    proc, lines = signalled_at(out, "episode 1: recording", sig, tmp_path)
    name = signal.Signals(sig).name
    assert proc.returncode == 128 + sig, (lines, proc.stderr.read())
    assert any(x.startswith(f"episode 1: discarded (stopped by {name} before keep") for x in lines), lines
    assert lines[-2].startswith("kept 1 episode(s) (60 steps); discarded 1") and lines[-2].endswith(f"ended by: {name}")
    assert ReplayBuffer.load(out).n_episodes == 1
    assert not [p for p in can_log_dir(out).iterdir() if ".partial-" in p.name]


def test_a_stop_before_any_kept_episode_says_what_was_written(tmp_path):
    """Signalled as the first episode starts: nothing was kept, so the dataset was never created, and the summary
    says so instead of naming it (and the empty CAN-log folder the session made is gone)."""
    out = tmp_path / "demo.zarr"
    proc, lines = signalled_at(out, "episode 0: recording", signal.SIGTERM, tmp_path)
    assert proc.returncode == 128 + signal.SIGTERM, (lines, proc.stderr.read())
    assert lines[-2].startswith("kept 0 episode(s) (0 steps); discarded 1") and lines[-2].endswith("ended by: SIGTERM")
    assert lines[-1] == f"nothing was written: no episode was kept, so {out} was not created", lines
    assert sorted(p.name for p in tmp_path.iterdir()) == []


# A stop while dssp-sim record still imports the simulation: the signal arrives as dssp_sim.teleop starts to load.
STOP_WHILE_IMPORTING = """
import os, signal, sys

class SignalOnImport:
    def find_spec(self, name, path=None, target=None):
        if name == "dssp_sim.teleop":
            sys.meta_path.remove(self)
            os.kill(os.getpid(), signal.SIGTERM)
        return None

sys.meta_path.insert(0, SignalOnImport())
from dssp_sim.sim_cli import main
sys.exit(main(["record", "--out", sys.argv[1], "--auto", "--episodes", "1"]))
"""


def test_a_stop_while_the_simulation_loads_is_one_line(tmp_path):
    out = tmp_path / "demo.zarr"
    proc = subprocess.run(
        [sys.executable, "-c", STOP_WHILE_IMPORTING, str(out)],
        capture_output=True,
        text=True,
        env=_env(),
        cwd=tmp_path,
        timeout=60,
    )
    assert proc.returncode == 128 + signal.SIGTERM, proc.stderr
    assert proc.stderr.strip().splitlines() == ["stopped by SIGTERM during start-up; nothing was recorded"], proc.stderr
    assert list(tmp_path.iterdir()) == []


def test_an_interrupted_write_is_repaired_by_the_next_session(tmp_path, capsys):
    out = tmp_path / "demo.zarr"
    assert record_main(["--out", str(out), "--auto", "--episodes", "1", "--quiet", "--no-depth"]) == 0
    good = ReplayBuffer.load(out)
    # What a crash between the writes of one append leaves: the new episode's metadata and part of its data.
    root = zarr.open_group(str(out), mode="r+")
    infos = list(root.attrs["episode_info"])
    root.attrs["episode_info"] = infos + [dict(infos[0], index=1)]
    for key in ("point_cloud", "state", "timestamp"):
        root[f"data/{key}"].append(root[f"data/{key}"][:7])
    with pytest.raises(DatasetError, match="7 steps after the last episode end"):
        ReplayBuffer.load(out)
    partial = ReplayBuffer.load(out, allow_incomplete_tail=True)
    assert partial.n_episodes == 1 and partial.dropped_tail_steps == 7
    assert len(episode_infos(partial.attrs, partial.n_episodes)) == 1
    capsys.readouterr()

    assert record_main(["--out", str(out), "--auto", "--episodes", "1", "--quiet", "--no-depth"]) == 0
    assert "7 steps of an episode whose write was interrupted; they were cut off" in capsys.readouterr().out
    buffer = ReplayBuffer.load(out)
    assert buffer.n_episodes == 2
    np.testing.assert_array_equal(buffer.episode(0).state, good.episode(0).state)
    assert [info["index"] for info in buffer.attrs["episode_info"]] == [0, 1]


# ------------------------------------------------------------------------------------------------ problems
def test_stream_problems_mark_the_episode(tmp_path, capsys):
    out = tmp_path / "faults.zarr"
    state = {"episodes": 0}

    def plan(session):
        rec, rig = session.recorder, session.rig
        if not rec.recording:
            if state["episodes"] == 2:
                return "quit"
            state["episodes"] += 1
            return "start"
        step = rec.steps
        if state["episodes"] == 1:  # faults in the first episode only
            if step == 10:
                rig.pause_feedback()
            elif step == 20:
                rig.resume_feedback()
            elif step == 30:
                rig.freeze_camera(True)
            elif step == 40:
                rig.freeze_camera(False)
        return "keep" if step >= 45 else None

    summary, events = run_session(["--out", str(out), "--quiet", "--sim-speed", "0", "--no-depth"], plan)
    assert summary.kept == [0, 1] and summary.kept_with_problems == [0]
    assert any(
        e.startswith("episode 0: kept with PROBLEMS") and "missing follower feedback" in e and "stale camera" in e
        for e in events
    ), events
    assert "episode 1: kept, 45 steps, 10.00 Hz, clean" in events

    reader = ReplayBufferReader(out)
    flags = reader.episode(0).extras[FLAGS_KEY]
    feedback = np.flatnonzero(flags & STEP_PROBLEMS["feedback_stale"])
    camera = np.flatnonzero(flags & STEP_PROBLEMS["camera_stale"])
    repeat = np.flatnonzero(flags & STEP_PROBLEMS["camera_repeat"])
    assert list(feedback) == list(range(12, 21))  # ages 0.2 .. 1.0 s > 0.1 s
    assert list(camera) == list(range(33, 41))  # ages 0.3 .. 1.0 s > 0.25 s
    assert list(repeat) == list(range(31, 41))  # no new frame for 10 steps
    ep = reader.episode(0)
    ages = ep.extras["timestamp"] - ep.extras["state_timestamp"]
    assert ages[20] == pytest.approx(1.0) and ages[10] == 0.0  # the feedback of step 10 was the last until 21
    np.testing.assert_array_equal(ep.state[20], ep.state[10])  # the last known state is repeated, and flagged

    info = episode_infos(reader.attrs, reader.n_episodes)
    kinds = {p["kind"] for p in info[0]["problems"]}
    assert {"feedback_stale", "camera_stale", "camera_repeat"} <= kinds and not info[0]["clean"]
    assert info[1]["clean"] and not reader.episode(1).extras[FLAGS_KEY].any()

    from dssp_data.data_cli import main as data_main

    capsys.readouterr()
    assert data_main(["info", str(out)]) == 1  # it lists problems
    text = capsys.readouterr().out
    assert (
        "episode 0 was recorded with problems: stale camera at 8 step(s) from step 33; missing follower feedback "
        "at 9 step(s) from step 12; dropped camera frames at 10 step(s) from step 31" in text
    )
    assert "PROBLEMS" in text and "episode 1 was recorded" not in text

    clean, again = tmp_path / "clean.zarr", tmp_path / "again.zarr"
    shutil.copytree(out, again)  # merge refuses one input given twice
    if Path(f"{out}.can").is_dir():
        shutil.copytree(f"{out}.can", f"{again}.can")
    assert data_main(["merge", str(clean), str(out), str(again), "--drop-marked"]) == 0
    assert f"left out episodes [0] of {out}" in capsys.readouterr().out
    merged = ReplayBuffer.load(clean)
    assert merged.n_episodes == 2 and all(info["clean"] for info in merged.attrs["episode_info"])


# ------------------------------------------------------------------------------------------------ operator
def test_operator_commands_from_lines(tmp_path):
    out = tmp_path / "lines.zarr"
    commands = io.StringIO("s\nq\nk\nstart\ndiscard\nbogus\nk\ns\n")  # then the input ends while recording
    summary, events = run_session(["--out", str(out), "--quiet", "--sim-speed", "0"], LineControls(commands))
    assert "an episode is being recorded: keep (k) or discard (d) it before quitting" in events
    assert any(e.startswith("episode 0: kept, 2 steps") for e in events), events
    assert any(e.startswith("episode 1: discarded (operator") for e in events)
    assert any("unknown command 'bogus'" in e for e in events)
    assert any(e.startswith("keep: no episode is being recorded") for e in events)
    assert any(e.startswith("episode 1: discarded (the command stream ended before keep") for e in events)
    assert summary.kept == [0] and summary.discarded == 2 and summary.ended_by == "end of commands"
    assert ReplayBuffer.load(out).n_episodes == 1
    logs = [p.name for p in can_log_dir(out).iterdir() if not p.name.startswith(".")]
    assert logs == ["episode_000000.sim.blf"]  # discarded episodes' logs are deleted


def test_next_state_convention(tmp_path):
    out = tmp_path / "next.zarr"
    summary, _ = run_session(
        ["--out", str(out), "--quiet", "--auto", "--episodes", "1", "--action", "next-state", "--no-depth"],
        lambda s: None,
    )
    buffer = ReplayBuffer.load(out, extras=True)
    ep = buffer.episode(0)
    info = buffer.attrs["episode_info"][0]
    assert ep.n_steps == info["recorded_steps"] - 1
    np.testing.assert_array_equal(ep.action[:-1], ep.state[1:])
    np.testing.assert_array_equal(ep.extras["action_timestamp"][:-1], ep.extras["state_timestamp"][1:])
    assert buffer.attrs["action_convention"].startswith("next_state")
    # Appending with the other convention is refused before anything is recorded.
    with pytest.raises(DatasetError, match="uses the action convention 'next_state'"):
        run_session(["--out", str(out), "--quiet", "--auto", "--episodes", "1", "--no-depth"], lambda s: None)


@pytest.mark.parametrize(
    "args, message",
    [
        (["--can", "mujoco", "--camera", "l515"], "--can mujoco records the MuJoCo scene"),
        (
            ["--can", "can0", "--camera", "mujoco"],
            "it goes with --camera mujoco, and --camera mujoco with --can mujoco",
        ),
        (["--can", "mujoco:2"], "the simulated rig has one leader/follower pair"),
        (["--can", "sim"], "the simulated rig's arms are spelled mujoco"),  # the spelling before two simulators
        (["--camera", "sim"], "camera 'sim' is ambiguous"),
        (["--can", "can0", "--camera", "tabletop", "--auto"], "--auto on a robot needs --max-steps"),
        (["--task-name", "juggle"], "is not a simulated task"),
        (["--max-steps", "0"], "--max-steps must be at least 1"),
        (["--thresholds", "missing.json"], "thresholds file missing.json does not exist"),
    ],
)
def test_bad_input_is_one_line(tmp_path, capsys, args, message):
    assert record_main(["--out", str(tmp_path / "x.zarr"), "--quiet"] + args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and message in err[0]
    assert not (tmp_path / "x.zarr").exists()


# ------------------------------------------------------------------------------------------------ the robot's loop
def test_the_robot_loop_on_its_clock(tmp_path):
    """The robot's path (no lockstep rig): a follower and a leader on one virtual bus heard by a bus monitor, a
    camera, the session pacing itself — ``dssp-run``'s loop with the leader arm as its source. On a manual clock on
    which the devices move while the loop sleeps,
    every time is exact: ticks one period apart, every stream fresh, and the one tick that started late
    (the tick before it took 1.6 periods) is flagged, with the camera frame it repeated."""
    import uuid

    from dssp_data.pointcloud import PointCloudConfig
    from dssp_data.recording import RECORDED_KEYS, RecordingDataset
    from hardware.bus_monitor import BusMonitor
    from hardware.camera.tabletop import SimCamera
    from hardware.leader import ScriptedLeader
    from hardware.piper.can_simulator import SimulatedPiper
    from hardware.record_session import RecordSession, SessionSettings
    from hardware.recorder import Recorder, StampedCamera

    channel = f"rec-{uuid.uuid4().hex[:8]}"
    clock = World()

    def script():
        t = clock.now()
        return np.array([0.3 * np.sin(t), 1.0, -0.8, 0.0, 0.3, 0.0, 0.5 + 0.3 * np.sin(t)])

    follower = SimulatedPiper(channel, "virtual", initial_joints=[0.0, 1.0, -0.8, 0.0, 0.3, 0.0])
    leader = ScriptedLeader(channel, "virtual", script=script)
    monitor = BusMonitor(channel, "virtual", clock=clock, name="can0")
    camera = SimCamera(seed=0)

    def step(dt):  # the leader sends, the follower obeys and reports, the camera renders; all heard at once
        leader.step()
        follower.step(dt)
        camera.capture()
        monitor.wait_for_frames(leader.frames_sent + follower.frames_sent, timeout=30.0)

    with contextlib.ExitStack() as stack:
        follower.start(thread=False)
        stack.callback(follower.stop)
        for device in (leader, monitor):
            device.start()
            stack.callback(device.stop)
        camera.start(thread=False)
        stack.callback(camera.stop)
        leader.send_frames([codec.MotorEnable(codec.MOTOR_ALL, codec.MOTOR_ENABLE_FLAG).to_frame()])
        clock.steps = [step]
        clock.sleep(0.05)
        recorder = Recorder(
            StampedCamera(camera, clock=clock),
            [monitor],
            PointCloudConfig(n_points=128),
            camera.camera_to_base,
            control_rate_hz=20.0,
            store_depth=False,
        )
        dataset = RecordingDataset(
            tmp_path / "rt.zarr",
            {"control_rate_hz": 20.0, "action_convention": "leader_command"},
            {"camera": "sim"},
            RECORDED_KEYS,
        )
        stack.callback(dataset.close)
        started, events = clock.now(), []

        def status(line):  # the tick that recorded step 5 takes 1.6 periods
            if recorder.steps == 6:
                clock.advance(1.6 * 0.05)

        session = RecordSession(
            recorder,
            dataset,
            [monitor],
            clock,
            SessionSettings(max_steps=12, auto=True, episodes=1),
            events=events.append,
            status=status,
        )
        summary = session.run(Scripted(session, lambda s: None))
    assert summary.kept == [0], events
    # dssp-run's loop, the leader arm its source, the followers heard and never commanded
    from dssp_core.errors import ArmError
    from hardware.policies.leader_arm import LeaderArm

    loop = session.loop
    assert isinstance(loop.source, LeaderArm) and loop.sent == 0 and loop.ended_by == "1 episodes kept"
    assert loop.ticks >= 12 and loop.summary()["commands_sent"] == 0
    with pytest.raises(ArmError, match="only listens"):
        loop.robot.command(np.zeros(7))
    buffer = ReplayBuffer.load(tmp_path / "rt.zarr", extras=True)
    ep, info = buffer.episode(0), buffer.attrs["episode_info"][0]
    assert ep.n_steps == 12 and ep.point_cloud.shape == (12, 128, 3)
    t = ep.extras["timestamp"]
    np.testing.assert_allclose(t, np.r_[0:6, 6.6, 7:12] * 0.05, atol=1e-9)  # step 6 began 0.6 period late
    flags = ep.extras[FLAGS_KEY]
    assert flags[6] == STEP_PROBLEMS["late_tick"] | STEP_PROBLEMS["camera_repeat"] and not np.delete(flags, 6).any()
    ages = {key: t - ep.extras[f"{key}_timestamp"] for key in ("camera", "state", "action")}
    for key, age in ages.items():  # fresh every tick but the late one: nothing moved while the loop was busy
        np.testing.assert_allclose(age, np.where(np.arange(12) == 6, 0.08, 0.0), atol=1e-9, err_msg=key)
    # The action is what the leader sent (its script at the time it sent it), the state what the follower measured.
    sent_at = started + ep.extras["action_timestamp"]
    np.testing.assert_allclose(ep.action[:, 0], 0.3 * np.sin(sent_at), atol=WIRE)
    assert np.all(np.abs(ep.action[:, 1] - 1.0) < WIRE) and np.all(np.abs(ep.state[:, 2] + 0.8) < 1e-3)
    assert info["rate_hz"] == pytest.approx(20.0) and info["clean"] and info["can_frames"]["can0"] > 0
    assert info["step_problems"]["late_tick"]["first_step"] == 6
    assert (tmp_path / "rt.zarr.can" / "episode_000000.can0.blf").is_file()


def test_single_keys_on_a_terminal():
    """Real time: a pseudo-terminal, read as it delivers."""
    import pty

    from hardware.cli.record import KeyControls

    master, slave = pty.openpty()
    with os.fdopen(slave, "r") as stream:
        controls = KeyControls(stream)
        try:
            assert controls.poll() is None
            os.write(master, b"sKdQx")
            keys = []  # the terminal hands the bytes over when it does: poll until all five came
            wait_for(lambda: keys.append(controls.poll()) or len([k for k in keys if k]) == 5, 30.0, "five keys")
            assert [k for k in keys if k] == ["start", "keep", "discard", "quit", "key 'x'"]
            assert controls.poll() is None
        finally:
            controls.close()
    os.close(master)


def test_a_failed_append_saves_the_episode_aside(tmp_path):
    out = tmp_path / "demo.zarr"
    state = {"started": 0}

    def full_disk(episode, info):
        raise OSError(28, "No space left on device")

    def plan(session):
        rec = session.recorder
        if not rec.recording:
            state["started"] += 1
            return "start"
        if state["started"] == 2 and rec.steps == 3:
            session.dataset.commit = full_disk
        return "keep" if rec.steps >= 5 else None

    events = []
    console = Console(quiet=True)
    console.event = events.append
    with pytest.raises(OSError, match="No space left"):
        with contextlib.ExitStack() as stack:
            session = open_session(
                parse_args(["--out", str(out), "--quiet", "--sim-speed", "0", "--no-depth"], sim=TeleopRigs()),
                stack,
                console,
            )
            session.run(Scripted(session, plan))
    saved = [e for e in events if e.startswith("error: appending the episode failed")]
    assert len(saved) == 1, events
    rescued = Path(saved[0].rsplit("saved to ", 1)[1])
    buffer = ReplayBuffer.load(rescued, extras=True)
    assert buffer.n_episodes == 1 and buffer.n_steps == 5 and buffer.attrs["episode_info"][0]["recorded_steps"] == 5
    assert ReplayBuffer.load(out).n_episodes == 1


def test_one_recording_session_per_dataset(tmp_path):
    from dssp_data.recording import RECORDED_KEYS, RecordingDataset

    first = RecordingDataset(tmp_path / "d.zarr", {}, {}, RECORDED_KEYS)
    with pytest.raises(DatasetError, match=f"d.zarr is being recorded into by pid {os.getpid()}"):
        RecordingDataset(tmp_path / "d.zarr", {}, {}, RECORDED_KEYS)
    first.close()
    RecordingDataset(tmp_path / "d.zarr", {}, {}, RECORDED_KEYS).close()


def test_a_second_recording_session_is_refused_before_any_device_opens(tmp_path, capsys, monkeypatch):
    from conftest import one_error_line

    from dssp_data.replay_buffer_writer import dataset_lock

    opened = []
    monkeypatch.setattr(TeleopRigs, "open", lambda self, task, seed, pace=None: opened.append(task))
    out = tmp_path / "d.zarr"
    held = dataset_lock(out, doing="recorded into")  # the first session
    try:
        assert record_main(["--out", str(out), "--auto", "--episodes", "1", "--quiet"]) == 2
        assert f"is being recorded into by pid {os.getpid()}" in one_error_line(capsys.readouterr().err)
        assert opened == [] and not out.exists()  # no rig opened, nothing written
    finally:
        held.release()


def test_dssp_record_drives_real_buses_only(tmp_path, capsys):
    """dssp-record itself never reaches into the simulation: --can sim points to dssp-sim record."""
    from hardware.cli.record import main as robot_record_main

    out = tmp_path / "x.zarr"
    for can in ("sim", "mujoco"):
        assert robot_record_main(["--out", str(out), "--camera", "tabletop", "--can", can, "--quiet"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "record the simulation with dssp-sim record" in err[0]
    assert robot_record_main(["--out", str(out), "--camera", "mujoco", "--can", "can0", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "exists only under dssp-sim" in err[0]
    assert not out.exists()
