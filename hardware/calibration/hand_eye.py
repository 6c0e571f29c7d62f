"""The hand-eye solve: the camera's pose from gripper poses (forward kinematics) and board poses (the camera).

    result = solve_hand_eye(gripper_to_base, board_to_camera, "eye-to-hand")   # lists of (4, 4), one per view
    result.check()                     # CalibrationError (one line) when the result may not be trusted
    result.transform                   # (4, 4): camera_to_base (eye-to-hand) or camera_to_gripper (eye-in-hand)

Two set-ups (OpenCV's ``calibrateHandEye``, every method of it that needs no more than the poses):

- **eye-to-hand**: the camera is fixed, the board held by the gripper. Unknowns: X = camera_to_base and the board's
  pose on the gripper. OpenCV solves the eye-in-hand equation, so it gets the inverted gripper poses (base in
  gripper), as its documentation describes; what it returns is then camera_to_base.
- **eye-in-hand**: the camera on the wrist, the board fixed on the table. Unknowns: X = camera_to_gripper and the
  board's pose in the base frame.

Methods TSAI, PARK, HORAUD and DANIILIDIS each give an X; the one whose residuals are smallest is the result, and
how far the others land from it (mm, degrees) is reported as their **disagreement**. Residuals, per view: the
second unknown (the board on the gripper, or on the table) is averaged over the views through X, the board's
pose is predicted for each view through the chain (base -> gripper -> board, seen from X) and compared with what
the camera detected — the board centre's distance (mm) and the rotation between the two (degrees).

Refusals (one line each, :class:`dssp_core.errors.CalibrationError`): views that cannot determine the camera
(:class:`PoseSpread`: fewer than ``MIN_POSES`` views, fewer than ``MIN_POSES`` distinct orientations, or rotations
that all share one axis, leaving the solve underdetermined along it); a result whose residuals or whose methods'
disagreement exceed :class:`Thresholds`. A plan of poses is held to the same :class:`PoseSpread` before the arm
moves (:func:`hardware.calibration.pose_plan.check_plan`), so a tour that cannot pass is never run. "The gripper" is
the Piper's flange, DH frame 6 (:func:`dssp_data.arm_kinematics.flange_pose`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from dssp_core.errors import CalibrationError

EYE_TO_HAND, EYE_IN_HAND = "eye-to-hand", "eye-in-hand"
MODES = (EYE_TO_HAND, EYE_IN_HAND)

METHODS = {
    "TSAI": cv2.CALIB_HAND_EYE_TSAI,
    "PARK": cv2.CALIB_HAND_EYE_PARK,
    "HORAUD": cv2.CALIB_HAND_EYE_HORAUD,
    "DANIILIDIS": cv2.CALIB_HAND_EYE_DANIILIDIS,
}

MIN_POSES = 8
"""Views with a detected board the solve needs. Three with two distinct rotation axes determine X without noise;
with eight the residuals can show a bad view instead of absorbing it."""

MIN_ROTATION_SPREAD_DEG = 5.0
"""The views' rotations (each relative to the first) must reach this far, RMS, about a second axis: rotations about
one axis only leave the translation along it undetermined."""

MIN_ORIENTATION_STEP_DEG = 1.0
"""Views whose gripper orientations differ by less than this count as one orientation: the arm settles to about a
degree (0.02 rad a joint), so a view that close to another repeats it and cannot show a bad view for what it is."""


@dataclass(frozen=True)
class Thresholds:
    """What a trusted result keeps within (mm and degrees). Position: the board centre, predicted vs. detected.

    RMS over the views 3 mm / 0.5 deg and no view beyond 8 mm / 1.5 deg: a RealSense sees a board at 0.3-0.8 m to
    about a millimetre and a few tenths of a degree, and the Piper's kinematic model is good to a few millimetres;
    more than that is a loose board, a pose read while moving or a wrong board size. The methods' disagreement,
    5 mm / 1 deg: they solve the same equations differently and part only when the poses constrain X weakly."""

    rms_mm: float = 3.0
    rms_deg: float = 0.5
    max_mm: float = 8.0
    max_deg: float = 1.5
    disagreement_mm: float = 5.0
    disagreement_deg: float = 1.0


@dataclass(frozen=True)
class Residual:
    """One view's residual: the board centre's distance (mm) and the rotation (deg), predicted vs. detected."""

    mm: float
    deg: float


@dataclass
class HandEyeResult:
    """mode: eye-to-hand | eye-in-hand. transform: (4, 4) camera_to_base or camera_to_gripper (the chosen method's).
    method: its name. by_method: each method's X. disagreement: each other method's distance from the result
    ``(mm, deg)``. target: (4, 4) the board's pose on the gripper (eye-to-hand) or in the base frame (eye-in-hand).
    residuals: one per view, in the order given. rotation_spread_deg: the RMS rotation about the second axis."""

    mode: str
    transform: np.ndarray
    method: str
    by_method: dict[str, np.ndarray]
    disagreement: dict[str, tuple[float, float]]
    target: np.ndarray
    residuals: list[Residual]
    rotation_spread_deg: float
    thresholds: Thresholds = field(default_factory=Thresholds)

    @property
    def name(self) -> str:
        """What ``transform`` is: camera_to_base or camera_to_gripper."""
        return "camera_to_base" if self.mode == EYE_TO_HAND else "camera_to_gripper"

    @property
    def rms(self) -> tuple[float, float]:
        mm = np.array([r.mm for r in self.residuals])
        deg = np.array([r.deg for r in self.residuals])
        return float(np.sqrt(np.mean(mm**2))), float(np.sqrt(np.mean(deg**2)))

    @property
    def worst(self) -> tuple[int, Residual]:
        """(index, residual) of the view farthest from the chain's prediction (by mm, then deg, relative to the
        thresholds)."""
        t = self.thresholds
        i = int(np.argmax([max(r.mm / t.max_mm, r.deg / t.max_deg) for r in self.residuals]))
        return i, self.residuals[i]

    @property
    def max_disagreement(self) -> tuple[float, float]:
        if not self.disagreement:
            return 0.0, 0.0
        return max(d[0] for d in self.disagreement.values()), max(d[1] for d in self.disagreement.values())

    def problem(self) -> str | None:
        """Why this result may not be trusted (one line, what is wrong and what to do), or None."""
        t = self.thresholds
        rms_mm, rms_deg = self.rms
        i, worst = self.worst
        dis_mm, dis_deg = self.max_disagreement
        if worst.mm > t.max_mm or worst.deg > t.max_deg:
            return (
                f"view {i + 1}'s board is {worst.mm:.1f} mm / {worst.deg:.2f} deg from where the chain puts it "
                f"(limits {t.max_mm:g} mm / {t.max_deg:g} deg): check that the board is rigid and was not moving, or "
                f"drop that pose and calibrate again"
            )
        if rms_mm > t.rms_mm or rms_deg > t.rms_deg:
            return (
                f"the residuals are {rms_mm:.1f} mm / {rms_deg:.2f} deg RMS (limits {t.rms_mm:g} mm / "
                f"{t.rms_deg:g} deg): check the board's size (--board), that it is flat and rigid, and the arm's "
                f"settling, then calibrate again"
            )
        if dis_mm > t.disagreement_mm or dis_deg > t.disagreement_deg:
            return (
                f"OpenCV's methods disagree by {dis_mm:.1f} mm / {dis_deg:.2f} deg (limits {t.disagreement_mm:g} mm / "
                f"{t.disagreement_deg:g} deg): the poses constrain the camera weakly; add poses that tilt the "
                f"wrist further about different axes"
            )
        return None

    def check(self) -> None:
        """Raise CalibrationError (one line) when :meth:`problem` finds one."""
        problem = self.problem()
        if problem is not None:
            raise CalibrationError(f"calibration refused: {problem}")


def invert(t: np.ndarray) -> np.ndarray:
    """Inverse of a rigid (4, 4) transform."""
    out = np.eye(4)
    r = t[:3, :3]
    out[:3, :3], out[:3, 3] = r.T, -r.T @ t[:3, 3]
    return out


def rotation_angle_deg(r: np.ndarray) -> float:
    """Angle (degrees) of the rotation matrix ``r``."""
    return math.degrees(math.acos(float(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))))


def distance(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(mm, deg) between two rigid transforms: their translations, and the rotation from one to the other."""
    return 1e3 * float(np.linalg.norm(a[:3, 3] - b[:3, 3])), rotation_angle_deg(a[:3, :3].T @ b[:3, :3])


def mean_transform(transforms: list[np.ndarray]) -> np.ndarray:
    """The mean of rigid transforms: translations averaged, rotations by the chordal mean (the nearest rotation to
    the sum of the matrices)."""
    stack = np.asarray(transforms)
    u, _, vt = np.linalg.svd(stack[:, :3, :3].sum(axis=0))
    r = u @ vt
    if np.linalg.det(r) < 0:
        r = u @ np.diag([1.0, 1.0, -1.0]) @ vt
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = r, stack[:, :3, 3].mean(axis=0)
    return out


def rotation_spread_deg(gripper_to_base: list[np.ndarray]) -> float:
    """RMS rotation (degrees) of the views about their second axis: the second singular value of the rotation
    vectors of each view relative to the first, over sqrt(n - 1). 0 when every rotation shares one axis."""
    if len(gripper_to_base) < 3:
        return 0.0
    r0 = gripper_to_base[0][:3, :3]
    vectors = np.array([cv2.Rodrigues(r0.T @ g[:3, :3])[0].reshape(3) for g in gripper_to_base[1:]])
    s = np.linalg.svd(vectors, compute_uv=False)
    return math.degrees(float(s[1]) / math.sqrt(len(vectors)))


def distinct_orientations(gripper_to_base: list[np.ndarray], step_deg: float = MIN_ORIENTATION_STEP_DEG) -> int:
    """How many of the views' gripper orientations lie at least ``step_deg`` from every one counted before them."""
    kept: list[np.ndarray] = []
    for g in gripper_to_base:
        r = g[:3, :3]
        if all(rotation_angle_deg(k.T @ r) >= step_deg for k in kept):
            kept.append(r)
    return len(kept)


@dataclass(frozen=True)
class PoseSpread:
    """What a set of gripper poses gives the hand-eye solve, and the one rule for whether it is enough: a plan's
    poses before the arm moves (:func:`hardware.calibration.pose_plan.check_plan`) and the views with the board
    detected before the solve (:func:`check_views`) are held to it alike.

    count: the poses. distinct: their orientations at least ``MIN_ORIENTATION_STEP_DEG`` apart
    (:func:`distinct_orientations`). spread_deg: their RMS rotation about a second axis (:func:`rotation_spread_deg`).
    min_poses, min_spread_deg: what the solve needs of ``count`` and ``distinct``, and of ``spread_deg``.
    """

    count: int
    distinct: int
    spread_deg: float
    min_poses: int = MIN_POSES
    min_spread_deg: float = MIN_ROTATION_SPREAD_DEG

    @classmethod
    def of(
        cls,
        gripper_to_base: list[np.ndarray],
        min_poses: int = MIN_POSES,
        min_spread_deg: float = MIN_ROTATION_SPREAD_DEG,
    ) -> PoseSpread:
        poses = [np.asarray(g, np.float64) for g in gripper_to_base]
        return cls(len(poses), distinct_orientations(poses), rotation_spread_deg(poses), min_poses, min_spread_deg)

    def problem(self, what: str) -> str | None:
        """Why the solve cannot trust these poses (one line naming them as ``what``, e.g. "views with the board
        detected", and what to do), or None."""
        if self.count < self.min_poses:
            return (
                f"{self.count} {what}, {self.min_poses} needed; give more poses (--auto N or --poses) with the "
                f"board in view"
            )
        if self.distinct < self.min_poses:
            return (
                f"the {self.count} {what} turn the gripper to {self.distinct} distinct "
                f"orientation{'' if self.distinct == 1 else 's'} (at least "
                f"{MIN_ORIENTATION_STEP_DEG:g} deg apart), {self.min_poses} needed; give poses that tilt the wrist "
                f"differently, not the same pose again"
            )
        if self.spread_deg < self.min_spread_deg:
            return (
                f"the {self.count} {what} rotate the gripper about one axis only ({self.spread_deg:.1f} deg RMS "
                f"about a second axis, {self.min_spread_deg:g} needed); add poses that tilt the wrist further "
                f"about other axes (J4 and J5 as well as J6)"
            )
        return None


def check_views(
    gripper_to_base: list[np.ndarray], min_poses: int = MIN_POSES, min_spread_deg: float = MIN_ROTATION_SPREAD_DEG
) -> float:
    """Refuse views that cannot determine the camera (:class:`PoseSpread`, one line); returns the rotation spread."""
    spread = PoseSpread.of(gripper_to_base, min_poses, min_spread_deg)
    problem = spread.problem("views with the board detected")
    if problem is not None:
        raise CalibrationError(f"calibration refused: {problem}")
    return spread.spread_deg


def _solve_one(
    method: int, gripper_to_base: list[np.ndarray], board_to_camera: list[np.ndarray], mode: str
) -> np.ndarray:
    hand = gripper_to_base if mode == EYE_IN_HAND else [invert(g) for g in gripper_to_base]
    r, t = cv2.calibrateHandEye(
        [h[:3, :3] for h in hand],
        [h[:3, 3] for h in hand],
        [c[:3, :3] for c in board_to_camera],
        [c[:3, 3] for c in board_to_camera],
        method=method,
    )
    x = np.eye(4)
    x[:3, :3], x[:3, 3] = r, np.asarray(t).reshape(3)
    return x


def residuals(
    x: np.ndarray, gripper_to_base: list[np.ndarray], board_to_camera: list[np.ndarray], mode: str, centre: np.ndarray
) -> tuple[np.ndarray, list[Residual]]:
    """The second unknown averaged through ``x`` (the board on the gripper, or in the base frame), and each view's
    residual: the board predicted through the chain vs. detected, at the board point ``centre`` (3,)."""
    if mode == EYE_TO_HAND:  # board_to_gripper = base_to_gripper @ camera_to_base @ board_to_camera
        target = mean_transform([invert(g) @ x @ c for g, c in zip(gripper_to_base, board_to_camera)])
        predicted = [invert(x) @ g @ target for g in gripper_to_base]
    else:  # board_to_base = gripper_to_base @ camera_to_gripper @ board_to_camera
        target = mean_transform([g @ x @ c for g, c in zip(gripper_to_base, board_to_camera)])
        predicted = [invert(x) @ invert(g) @ target for g in gripper_to_base]
    point = np.append(centre, 1.0)
    out = []
    for p, c in zip(predicted, board_to_camera):
        mm = 1e3 * float(np.linalg.norm((p @ point - c @ point)[:3]))
        out.append(Residual(mm, rotation_angle_deg(p[:3, :3].T @ c[:3, :3])))
    return target, out


def solve_hand_eye(
    gripper_to_base: list[np.ndarray],
    board_to_camera: list[np.ndarray],
    mode: str,
    centre: np.ndarray | None = None,
    thresholds: Thresholds = Thresholds(),
    min_poses: int = MIN_POSES,
) -> HandEyeResult:
    """Solve for the camera (see the module docstring). ``gripper_to_base`` and ``board_to_camera``: one (4, 4) each
    per view, in the same order. ``centre``: the board point residuals are measured at (default the origin).
    Too few views or a degenerate set raise CalibrationError; the residual thresholds are checked by
    :meth:`HandEyeResult.check`, so a caller can show the per-view table first."""
    if mode not in MODES:
        raise CalibrationError(f"mode must be one of {', '.join(MODES)}, got {mode!r}")
    if len(gripper_to_base) != len(board_to_camera):
        raise CalibrationError(f"{len(gripper_to_base)} gripper poses but {len(board_to_camera)} board poses")
    gripper_to_base = [np.asarray(g, np.float64) for g in gripper_to_base]
    board_to_camera = [np.asarray(c, np.float64) for c in board_to_camera]
    spread = check_views(gripper_to_base, min_poses)
    centre = np.zeros(3) if centre is None else np.asarray(centre, np.float64)
    by_method, scored = {}, {}
    for name, method in METHODS.items():
        x = _solve_one(method, gripper_to_base, board_to_camera, mode)
        if not np.all(np.isfinite(x)):
            continue
        by_method[name] = x
        target, res = residuals(x, gripper_to_base, board_to_camera, mode, centre)
        scored[name] = (float(np.sqrt(np.mean([r.mm**2 for r in res]))), target, res)
    if not scored:
        raise CalibrationError(
            "calibration refused: none of OpenCV's hand-eye methods found a solution; check the poses"
        )
    best = min(scored, key=lambda name: scored[name][0])
    x = by_method[best]
    return HandEyeResult(
        mode=mode,
        transform=x,
        method=best,
        by_method=by_method,
        disagreement={n: distance(m, x) for n, m in by_method.items() if n != best},
        target=scored[best][1],
        residuals=scored[best][2],
        rotation_spread_deg=spread,
        thresholds=thresholds,
    )
