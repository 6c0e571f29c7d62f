"""The teleoperation leader arm as the loop's source: the follower obeys the leader over their shared bus.

    monitors = [BusMonitor("can0")]                     # one per leader/follower pair: left, right
    runner = Runner(LeaderArm(monitors), Rig(None, ListeningArms(monitors), camera_to_base), None, settings,
                    subscribers=[record_session])       # dssp-record: the recorder is a subscriber

On the Piper platform the leader arm commands its follower itself (both on one CAN bus); the loop sends nothing
(:attr:`commands` false) and the action each tick is the leader's latest target, (dof,) = 7 per arm in policy
units [J1..J6 rad, gripper opening 0..1], left then right — what ``dssp-record``'s ``leader_command`` convention
stores as the action. A pair whose leader has not been heard yet gives no action (None).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from hardware.bus_monitor import BusMonitor
from hardware.policies import Act, PolicySource


class LeaderArm(PolicySource):
    """The leaders heard by ``monitors`` (one per pair, left first); needs no point cloud, commands nothing."""

    name = "leader-arm"
    needs_cloud = False
    commands = False

    def __init__(self, monitors: Sequence[BusMonitor]) -> None:
        self.monitors = list(monitors)

    def act(self, cloud: np.ndarray | None, state: np.ndarray) -> Act:
        readings = [m.leader() for m in self.monitors]
        if any(r.position is None for r in readings):
            return Act(None, events=["no leader command yet"])
        return Act(np.concatenate([r.position for r in readings]))

    def describe(self) -> dict:
        return {"policy": self.name, "buses": [m.name for m in self.monitors]}
