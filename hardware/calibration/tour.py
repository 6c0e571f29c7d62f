"""The calibration tour: the arm visits each pose, waits until it is still, and a colour frame is taken there.

    tour = CalibrationTour(poses, camera, clock)               # poses (N, 6) rad, or a function of the start (6,)
    Runner(tour, Rig(None, robot, np.eye(4), SafetyConfig(), clock=clock), None, LoopSettings(control_rate_hz=10)).run()
    tour.views                                                 # one View per pose: the measured joints and the frame

The tour is a policy source of the control loop (:mod:`hardware.policies`), so its moves go where every command
goes: through the safety layer (joint limits, at most ``max_joint_step`` per tick from the last safe target: a far
pose is ramped to), the CAN driver, the loop's stop handling and its final hold. It needs no point cloud. At each
pose it commands the target until the feedback is within ``reach_rad`` of it and has moved less than ``still_rad``
for ``settle_s`` (the arm has settled), then waits for a camera frame that arrived after that moment and keeps it
with the joints measured then. After the last pose it goes back to where it started, and is done (the loop ends,
``ended by: done``). A pose the arm does not settle at within ``settle_timeout``, or no fresh frame within
``frame_timeout``, is an error of the source: the loop ends in its hold. Times are the loop's clock
(:mod:`hardware.clock`), the one the camera's frames are stamped on.

The gripper: ``gripper="close"`` commands it shut all along (a board held between the fingers stays gripped:
eye-to-hand), ``"hold"`` keeps the opening it had at the start.

The plan is checked before the arm moves (:func:`hardware.calibration.pose_plan.check_plan`, the hand-eye solve's own
rule): given poses when the tour is made, generated ones when :meth:`CalibrationTour.reset` makes them from the
measured start, before the first command — a plan that cannot pass is one line (ConfigError, named ``where``), never
a tour.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from dssp_core.errors import ArmError, CameraError, ConfigError
from dssp_data.pointcloud.depth_frame import DepthFrame
from hardware.calibration.pose_plan import check_plan, check_poses
from hardware.camera.base import Camera
from hardware.clock import Clock
from hardware.policies import Act, PolicySource
from hardware.robot import ARM_DOF


def check_robot(description) -> None:
    """Refuse (one-line ConfigError) a robot the tour cannot calibrate with: it moves one arm."""
    if description.dof != ARM_DOF:
        raise ConfigError(
            f"calibration moves one arm ({ARM_DOF} values); the robot has {description.dof}: give one CAN bus"
        )


@dataclass
class View:
    """One pose visited: ``index`` (0-based, in the order given), ``target`` (6,) rad, ``joints`` (6,) rad measured
    when the frame was taken, ``frame`` (its ``color`` (H, W, 3) uint8 and ``intrinsics``)."""

    index: int
    target: np.ndarray
    joints: np.ndarray
    frame: DepthFrame


class CalibrationTour(PolicySource):
    name = "calibration"
    needs_cloud = False

    def __init__(
        self,
        poses: np.ndarray,
        camera: Camera,
        clock: Clock,
        *,
        gripper: str = "hold",
        settle_s: float = 0.5,
        still_rad: float = 0.002,
        reach_rad: float = 0.02,
        settle_timeout: float = 20.0,
        frame_timeout: float = 3.0,
        events=print,
        where: str = "the calibration plan",
    ) -> None:
        if gripper not in ("hold", "close"):
            raise ConfigError(f"gripper must be hold or close, got {gripper!r}")
        self.where = where
        self._make_poses = poses if callable(poses) else None
        self.poses = np.empty((0, 6)) if callable(poses) else self._checked(poses)
        self.camera, self.clock, self.gripper = camera, clock, gripper
        self.settle_s, self.still_rad, self.reach_rad = settle_s, still_rad, reach_rad
        self.settle_timeout, self.frame_timeout = settle_timeout, frame_timeout
        self.events = events
        self.views: list[View] = []
        self.plan: list[np.ndarray] = []
        self.k = 0

    def check(self, description, cloud_config) -> None:
        check_robot(description)

    def _checked(self, poses) -> np.ndarray:
        return check_plan(check_poses(poses, self.where), self.where)

    def reset(self, state: np.ndarray) -> None:
        state = np.asarray(state, dtype=np.float64)
        self.start = state.copy()
        self.opening = 0.0 if self.gripper == "close" else float(state[ARM_DOF - 1])
        if self._make_poses is not None:  # made from the measured start, checked before the first command
            self.poses = self._checked(self._make_poses(state[:6].copy()))
        self.plan = [p for p in self.poses] + [state[:6].copy()]  # the poses, then back to the start
        self.views, self.k = [], 0
        self._begin_pose()

    def _begin_pose(self) -> None:
        self._since: float | None = None
        self._settled_at: float | None = None
        self._recent: deque[tuple[float, np.ndarray]] = deque()

    @property
    def done(self) -> bool:
        return bool(self.plan) and self.k >= len(self.plan)

    def _label(self) -> str:
        n = len(self.poses)
        return f"pose {self.k + 1}/{n}" if self.k < n else "the start pose"

    def act(self, cloud, state: np.ndarray) -> Act:
        now = self.clock.now()
        target = self.plan[self.k]
        joints = np.asarray(state[:6], dtype=np.float64)
        events: list[str] = []
        if self._settled_at is None:
            self._since = now if self._since is None else self._since
            self._recent.append((now, joints.copy()))
            while len(self._recent) > 1 and self._recent[1][0] <= now - self.settle_s:
                self._recent.popleft()
            span = now - self._recent[0][0]
            window = np.array([q for _, q in self._recent])
            moving = float(np.max(window.max(axis=0) - window.min(axis=0)))
            off = float(np.max(np.abs(joints - target)))
            if off <= self.reach_rad and span >= self.settle_s and moving <= self.still_rad:
                if self.k == len(self.poses):  # back at the start: the tour is over
                    self.k += 1
                    return Act(np.append(target, self.opening), events=["back at the start pose"])
                self._settled_at = now
            elif now - self._since > self.settle_timeout:
                raise ArmError(
                    f"{self._label()} not reached and still within {self.settle_timeout:g} s (off by "
                    f"{off:.3f} rad, moving {moving:.4f} rad in {self.settle_s:g} s); check the arm and its load"
                )
        else:
            frame = self.camera.latest()
            if frame is not None and frame.timestamp >= self._settled_at:
                self.views.append(View(self.k, target.copy(), joints.copy(), frame))
                line = f"{self._label()}: settled, frame {frame.frame_number} taken"
                self.events(line)
                events.append(line)
                self.k += 1
                self._begin_pose()
            elif now - self._settled_at > self.frame_timeout:
                raise CameraError(
                    f"{self.camera.name}: no frame within {self.frame_timeout:g} s of the arm settling at "
                    f"{self._label()}; check the camera"
                )
        return Act(np.append(self.plan[min(self.k, len(self.plan) - 1)], self.opening), events=events)
