"""The rig: the camera, the arms and what records them opened together, in order, and closed in reverse
whatever ends the block — a part that fails to open closes the ones opened before it."""

import numpy as np
import pytest

from dssp_core.errors import ConfigError
from hardware.piper.limits import JointLimits
from hardware.piper.piper_robot import open_robot
from hardware.rig import Rig


class Part:
    """A device that says when it opens and closes (``fail``: it cannot open)."""

    def __init__(self, name, events, fail=False):
        self.name, self.events, self.fail = name, events, fail

    def __enter__(self):
        if self.fail:
            raise OSError(f"{self.name} is not there")
        self.events.append(f"open {self.name}")
        return self

    def __exit__(self, *exc):
        self.events.append(f"close {self.name}")


class Arms(Part):
    dof = 7
    description = property(lambda self: open_robot("sim").description)


def test_the_parts_open_in_order_and_close_in_reverse():
    events = []
    rig = Rig(Part("camera", events), Arms("arms", events), np.eye(4), recorders=[Part("recorder", events)])
    with rig:
        assert events == ["open camera", "open arms", "open recorder"]
        with pytest.raises(RuntimeError, match="already open"):
            rig.__enter__()
    assert events[3:] == ["close recorder", "close arms", "close camera"]
    events.clear()
    with pytest.raises(ValueError):
        with rig:  # reopened after closing; an error inside the block still closes everything
            raise ValueError("a fault while running")
    assert events == ["open camera", "open arms", "open recorder", "close recorder", "close arms", "close camera"]


def test_a_part_that_cannot_open_closes_those_opened_before_it():
    events = []
    rig = Rig(Part("camera", events), Arms("arms", events, fail=True), np.eye(4), recorders=[Part("recorder", events)])
    with pytest.raises(OSError, match="arms is not there"):
        with rig:
            pass
    assert events == ["open camera", "close camera"]


def test_the_limits_are_the_robots_own_unless_narrowed_and_the_pose_is_checked():
    robot = open_robot("sim")
    rig = Rig(Part("camera", []), robot, np.eye(4))
    lower, upper, gripper = rig.joint_limits()
    described = robot.description
    assert np.array_equal(lower, described.lower) and np.array_equal(upper, described.upper)
    assert np.array_equal(gripper, described.gripper) and rig.description is not None
    narrow = JointLimits.piper()
    limits = (narrow.lower / 2, narrow.upper / 2, np.arange(7) == 6)
    assert Rig(Part("camera", []), robot, np.eye(4), limits=limits).joint_limits() is limits
    with pytest.raises(ConfigError, match="7 values"):
        Rig(Part("camera", []), robot, np.eye(4), limits=(np.zeros(6), np.ones(6), np.zeros(6, bool)))
    with pytest.raises(ConfigError, match="4x4"):
        Rig(Part("camera", []), robot, np.eye(3))
    with pytest.raises(ConfigError, match="finite"):
        Rig(Part("camera", []), robot, np.full((4, 4), np.nan))
