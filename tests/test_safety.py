"""The safety layer: limits, per-tick step, holds on stale inputs, faults latch, nothing outside ever."""

import numpy as np
import pytest
from conftest import GRIPPER
from hypothesis import given, settings
from hypothesis import strategies as st

from dssp_core.errors import ConfigError
from hardware.piper.piper_robot import open_robot
from hardware.robot import ArmStatus, RobotState
from hardware.safety import Safety, SafetyConfig

LOWER = np.array([-2.6179, 0.0, -2.967, -1.745, -1.22, -2.0944, 0.0])
UPPER = np.array([2.6179, 3.14, 0.0, 1.745, 1.22, 2.0944, 1.0])
START = np.array([0.0, 0.5, -0.5, 0.0, 0.3, 0.0, 0.5])


def make(config=SafetyConfig(), start=START):
    return Safety(config, LOWER, UPPER, GRIPPER, start)


def state(now, position=START, status=(ArmStatus(enabled=True),)):
    return RobotState(position=np.asarray(position, float), timestamp=now, status=status)


def test_a_reachable_action_passes_unchanged():
    s = make()
    target = START + 0.01
    d = s.decide(target, now=10.0, camera_time=10.0, state=state(10.0))
    assert np.allclose(d.command, target) and not d.held and not d.clipped and not d.events


def test_limits_then_step_are_applied_and_logged():
    s = make()
    d = s.decide(np.full(7, 100.0), now=1.0, camera_time=1.0, state=state(1.0))
    expected = np.minimum(START + s.max_step, UPPER)
    assert np.allclose(d.command, expected)
    kinds = [e.detail for e in d.events]
    assert any("joint limits" in k for k in kinds) and any("per-tick step" in k for k in kinds)
    # the next tick continues from the last safe target
    d2 = s.decide(np.full(7, 100.0), now=1.1, camera_time=1.1, state=state(1.1))
    assert np.allclose(d2.command, np.minimum(expected + s.max_step, UPPER))


@pytest.mark.parametrize(
    "kwargs, reason",
    [
        ({"camera_time": 0.0}, "camera frame is"),
        ({"camera_time": None}, "no camera frame"),
        ({"state": None}, "no joint feedback"),
        ({"feedback_age": 0.5}, "joint feedback is"),
        ({"deadline_missed": True}, "deadline"),
        ({"action": np.full(7, np.nan)}, "NaN"),
        ({"action": np.ones(6)}, "6 values"),
    ],
)
def test_every_stale_or_bad_input_holds_the_last_safe_target(kwargs, reason):
    s = make()
    first = s.decide(START + 0.02, now=5.0, camera_time=5.0, state=state(5.0)).command
    now = 5.1
    args = {
        "action": START + 0.04,
        "camera_time": now,
        "state": state(now - kwargs.pop("feedback_age", 0.0)),
        "deadline_missed": False,
    }
    args.update(kwargs)
    d = s.decide(args.pop("action"), now=now, **args)
    assert d.held and np.array_equal(d.command, first)
    assert any(reason in e.detail for e in d.events), [e.detail for e in d.events]
    assert all(e.time == now and e.tick == 1 for e in d.events)


def test_arm_error_latches_and_nothing_is_sent_afterwards():
    s = make()
    bad = state(1.0, status=(ArmStatus(enabled=True, error=True, detail="joint 3 over limit"),))
    d = s.decide(START, now=1.0, camera_time=1.0, state=bad)
    assert d.command is None and s.fault and "joint 3 over limit" in s.fault
    d = s.decide(START, now=1.1, camera_time=1.1, state=state(1.1))  # even after the error clears
    assert d.command is None


def test_estop_latches():
    s = make()
    d = s.decide(START, now=1.0, camera_time=1.0, state=state(1.0, status=(ArmStatus(), ArmStatus(estop=True))))
    assert d.command is None and "arm 1" in s.fault


def test_stop_gives_one_final_hold_then_nothing():
    s = make()
    last = s.decide(START + 0.03, now=1.0, camera_time=1.0, state=state(1.0)).command
    final = s.stop(2.0, "SIGTERM")
    assert final.held and np.array_equal(final.command, last)
    assert [e.kind for e in final.events] == ["hold", "stop"]
    assert s.decide(START, now=2.1, camera_time=2.1, state=state(2.1)).command is None
    assert s.stop(2.2, "again").command is None


def test_start_outside_the_limits_fails_before_motion():
    outside = START.copy()
    outside[2] = 0.5  # J3 must be <= 0
    with pytest.raises(ConfigError, match="outside its limits on entries \\[2\\]"):
        make(start=outside)


def test_config_validates_itself():
    with pytest.raises(ConfigError, match="max_joint_step"):
        SafetyConfig(max_joint_step=0)
    with pytest.raises(ConfigError, match="unknown safety setting"):
        SafetyConfig.from_dict({"max_speed": 1})
    assert SafetyConfig.from_dict(SafetyConfig().to_dict()) == SafetyConfig()


finite_or_not = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.floats(-10, 10))


@settings(max_examples=300, deadline=None)
@given(
    actions=st.lists(st.lists(finite_or_not, min_size=7, max_size=7), min_size=1, max_size=30),
    stale=st.lists(st.booleans(), min_size=30, max_size=30),
)
def test_no_command_ever_leaves_the_limits_or_the_step(actions, stale):
    s = make()
    previous = s.last_safe.copy()
    for i, action in enumerate(actions):
        now = float(i)
        d = s.decide(np.array(action), now=now, camera_time=now - (1.0 if stale[i] else 0.0), state=state(now))
        assert d.command is not None
        assert np.all(d.command >= LOWER) and np.all(d.command <= UPPER)
        assert np.all(np.abs(d.command - previous) <= s.max_step + 1e-12)
        previous = d.command


def test_the_step_limit_is_checked_against_the_robots_own_joint_speed():
    config = SafetyConfig(max_joint_step=0.1)  # 5 rad/s at 50 Hz
    config.check_speed(50.0, max_joint_speed=6.0)  # a faster arm takes it
    with pytest.raises(ConfigError, match=r"above the arm's 3 rad/s: lower max_joint_step to at most 0\.06"):
        config.check_speed(50.0, max_joint_speed=3.0)
    with pytest.raises(ConfigError, match="above the arm's 3.14159 rad/s"):  # the Piper, as it describes itself
        config.check_speed(50.0, open_robot("sim").description.max_joint_speed)
