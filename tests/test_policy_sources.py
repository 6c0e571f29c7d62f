"""Policy sources: the one control loop with something other than a model deciding the action.

``dssp-run --policy hold`` and ``--policy episode:PATH@K`` on the embedded simulation (real time: what is logged,
sent and kept within the limits is checked exactly, how many ticks hold is the machine's business); a source added
the documented way (one module, one registry line) runs in dssp-run unchanged; ``dssp-replay`` is the same loop
(ideal tracking on a fake clock: exact); bad specs are one line before anything opens.
"""

from __future__ import annotations

import json
import textwrap

import numpy as np
import pytest
from conftest import GRIPPER, WIRE, assert_within_limits, one_error_line, run_dssp, sent_commands, write_arm_dataset

from dssp_core.errors import ConfigError
from dssp_data.dataset_layout import Episode
from dssp_data.replay_buffer import ReplayBuffer
from dssp_data.replay_buffer_writer import write_replay_buffer
from hardware import policies
from hardware.clock import FakeClock
from hardware.episode_replay import replay_episode
from hardware.ideal_robot import IdealRobot
from hardware.piper.limits import piper_description
from hardware.policies.hold import Hold
from hardware.rig import Rig
from hardware.run_log import read_clouds, read_ticks
from hardware.run_loop import LoopSettings, Runner
from hardware.safety import SafetyConfig

STEP = np.where(GRIPPER, SafetyConfig().max_gripper_step, SafetyConfig().max_joint_step)


def test_hold_runs_the_whole_rig_and_moves_nothing(tmp_path, capsys):
    """The bring-up check: the camera, the cloud, the safety layer, the log and the bus all run; every command is
    the position the arm started at."""
    log_dir = tmp_path / "log"
    code, out, err = run_dssp(
        capsys,
        "--policy",
        "hold",
        "--camera",
        "tabletop",
        "--can",
        "sim",
        "--max-steps",
        "30",
        "--log-dir",
        log_dir,
        "--quiet",
    )
    assert code == 0, out + err
    assert "ticks 30" in out and "ended by: max steps" in out
    run = json.loads((log_dir / "run.json").read_text())
    assert run["settings"]["policy"] == {"policy": "hold"} and "model" not in run["settings"]
    assert run["settings"]["rate_hz"] == 10.0  # no model, no --control-rate: the documented default
    ticks = read_ticks(log_dir)
    acted = [t for t in ticks if t["action"] is not None]
    assert acted and all(np.array_equal(t["action"], acted[0]["action"]) for t in acted)
    assert read_clouds(log_dir).shape == (len(acted), 1024, 3)  # the cloud was built for every tick that acted
    [blf] = log_dir.glob("can_*.blf")
    commands = sent_commands(blf)
    assert len(commands) == sum(t["command"] is not None for t in ticks) + 1  # the final hold adds one
    assert np.allclose(commands, commands[0], atol=WIRE)  # nothing moved
    assert np.allclose(commands[0], acted[0]["action"], atol=WIRE)


def test_a_recorded_episode_in_dssp_run_ends_when_it_is_played(tmp_path, capsys):
    data = write_arm_dataset(tmp_path / "d.zarr", n_episodes=2, steps=25)
    recorded = ReplayBuffer.load(data).episode(1).action.astype(np.float64)
    log_dir = tmp_path / "log"
    code, out, err = run_dssp(
        capsys,
        "--policy",
        f"episode:{data}@1",
        "--camera",
        "tabletop",
        "--can",
        "sim",
        "--max-steps",
        "500",
        "--log-dir",
        log_dir,
        "--quiet",
        "--control-rate",
        "20",
    )
    assert code == 0, out + err
    assert "ended by: done" in out
    ticks = read_ticks(log_dir)
    actions = np.array([t["action"] for t in ticks if t["action"] is not None])
    np.testing.assert_array_equal(actions, recorded)  # every recorded action once, in order
    run = json.loads((log_dir / "run.json").read_text())
    assert run["settings"]["policy"] == {"policy": "episode", "episode": f"{data} episode 1", "steps": 25}
    assert not (log_dir / "clouds").exists() or read_clouds(log_dir).size == 0  # it takes no point cloud
    [blf] = log_dir.glob("can_*.blf")
    assert_within_limits(sent_commands(blf), STEP)


SWEEP = '''
    """A source for the test: joint 1 moves by ``step`` rad per tick from where the arm starts."""
    import numpy as np

    from hardware.policies import Act, PolicySource


    class Sweep(PolicySource):
        name = "sweep"
        needs_cloud = False

        def __init__(self, step):
            self.step = step

        @classmethod
        def from_spec(cls, arg):
            return cls(float(arg))

        def reset(self, state):
            self.target = np.array(state, dtype=np.float64)

        def act(self, cloud, state):
            self.target[0] += self.step
            return Act(self.target.copy())
'''


def test_a_new_source_is_one_module_and_one_registry_line(tmp_path, capsys, monkeypatch):
    (tmp_path / "sweep_source.py").write_text(textwrap.dedent(SWEEP))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(policies.REGISTRY, "sweep", "sweep_source:Sweep")
    log_dir = tmp_path / "log"
    code, out, err = run_dssp(
        capsys,
        "--policy",
        "sweep:0.2",
        "--camera",
        "tabletop",
        "--can",
        "sim",
        "--max-steps",
        "20",
        "--log-dir",
        log_dir,
        "--quiet",
    )
    assert code == 0, out + err
    ticks = [t for t in read_ticks(log_dir) if t["action"] is not None]
    assert len(ticks) >= 2
    moves = np.diff([t["action"][0] for t in ticks])
    assert np.allclose(moves, 0.2)  # the source's own steps, asked for once a tick it acted
    clipped = [t for t in ticks if any(e["kind"] == "clip" for e in t["safety"])]
    assert clipped  # 0.2 rad a tick is beyond the per-tick step: the safety layer clipped it
    [blf] = log_dir.glob("can_*.blf")
    assert_within_limits(sent_commands(blf), STEP)


@pytest.mark.parametrize(
    "argv, fragment",
    [
        (["--policy", "nope"], "--policy nope: no such policy source; choose from episode, hold"),
        (["--policy", "hold:3"], "--policy hold:3: hold takes no argument"),
        (["--policy", "episode:data.zarr"], "give the dataset and the episode as episode:PATH.zarr@K"),
        (
            ["--policy", "hold", "--prefetch"],
            "--prefetch is a model's setting: it goes with --model, not --policy hold",
        ),
        (["--policy", "hold", "--precision", "int8"], "--precision is a model's setting"),
        (["--policy", "hold", "--model", "m"], "not allowed with argument"),
        ([], "one of the arguments --model --policy is required"),
    ],
)
def test_a_bad_policy_is_one_line_before_anything_opens(tmp_path, capsys, monkeypatch, argv, fragment):
    monkeypatch.chdir(tmp_path)
    code, _, err = run_dssp(capsys, *argv, "--log-dir", tmp_path / "log")
    assert code == 2 and fragment in one_error_line(err), err
    assert not (tmp_path / "log").exists()


def test_an_episode_for_other_arms_is_refused_before_anything_opens(tmp_path, capsys):
    data = write_arm_dataset(tmp_path / "d.zarr", n_episodes=1, steps=10, n_arms=2)
    code, _, err = run_dssp(capsys, "--policy", f"episode:{data}@0", "--can", "sim", "--log-dir", tmp_path / "log")
    assert code == 2 and "has 14 action values but the robot has 7" in one_error_line(err)
    assert not (tmp_path / "log").exists()


def test_a_source_that_needs_clouds_needs_a_camera():
    robot = IdealRobot(piper_description(1), np.zeros(7), FakeClock())
    with pytest.raises(ConfigError, match="needs point clouds"):
        Runner(Hold(), Rig(None, robot, np.eye(4)), None, LoopSettings(control_rate_hz=10.0))


def test_the_replay_is_the_loop_the_safety_layer_clips_a_jump(tmp_path):
    """dssp-replay without an arm: ideal tracking on a fake clock; an action 0.5 rad away is reached in per-tick
    steps, each clip counted, the largest change to a recorded action reported, nothing left unplayed."""
    steps = 8
    action = np.zeros((steps, 7), np.float32)
    action[3:, 0] = 0.5
    path = tmp_path / "jump.zarr"
    write_replay_buffer(
        path,
        [Episode(np.zeros((steps, 4, 3), np.float32), np.zeros((steps, 7), np.float32), action)],
        attrs={"control_rate_hz": 10.0},
    )
    clock = FakeClock(5.0)
    result = replay_episode(path, 0, None, events=lambda _: None, clock=clock)
    step = SafetyConfig().max_joint_step
    assert result["ended_by"] == "done" and result["ticks"] == steps and result["fault"] is None
    assert result["clips"] == steps - 3 and result["holds"] == 0  # from the jump on, every tick is a clipped step
    assert result["max_change"] == pytest.approx(0.5 - step)
    assert clock.now() == pytest.approx(5.0 + steps / 10.0)  # paced on its own clock: no wall time spent


def test_a_source_that_commands_nothing_only_reports():
    """The leader arm's shape (``commands`` false): the loop asks the source every tick and hands its report to the
    subscribers, but enables, sends and holds nothing — even an action far outside every limit is never a command."""
    from hardware.policies import Act, PolicySource
    from hardware.subscribers import Subscriber

    class Reporter(PolicySource):
        name, needs_cloud, commands = "reporter", False, False

        def act(self, cloud, state):
            return Act(state + 5.0)

    class Calls(IdealRobot):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.calls = []

        def enable(self, timeout=2.0):
            self.calls.append("enable")

        def command(self, target):
            self.calls.append("command")

        def disable(self):
            self.calls.append("disable")

    class Seen(Subscriber):
        def __init__(self):
            self.ticks = []

        def on_tick(self, tick):
            self.ticks.append(tick)

    clock = FakeClock(1.0)
    robot = Calls(piper_description(1), np.zeros(7), clock=clock)
    seen = Seen()
    runner = Runner(
        Reporter(),
        Rig(None, robot, np.eye(4), SafetyConfig(disable_on_exit=True), clock=clock),
        None,
        LoopSettings(control_rate_hz=10.0, max_steps=6),
        subscribers=[seen],
    )
    summary = runner.run()
    assert robot.calls == [] and summary["commands_sent"] == 0 and summary["holds"] == 0
    assert summary["ticks"] == 6 and summary["ended_by"] == "max steps" and summary["fault"] is None
    assert [t.record["command"] for t in seen.ticks] == [None] * 6
    np.testing.assert_array_equal(seen.ticks[0].record["action"], np.full(7, 5.0))
    assert [t.scheduled for t in seen.ticks] == pytest.approx(1.0 + 0.1 * np.arange(6))
