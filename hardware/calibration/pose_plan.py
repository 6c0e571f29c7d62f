"""Where the arm goes to be calibrated: joint vectors from a JSON file, or generated around where the arm starts.

    poses = load_poses("poses.json")          # (N, 6) rad: {"poses": [[J1..J6], ...]} or a bare list of them
    poses = auto_poses(start_joints, 12)      # (12, 6) rad: small moves of every joint around the start
    check_plan(poses, "--auto 12")            # refuses a plan whose views could never pass the solve's check

Every pose must be ``N_JOINTS`` JSON numbers (``"0.1"`` is not a number) inside the Piper's joint limits
(:mod:`hardware.piper.limits`, the one source of limits); one outside is refused with one line naming the pose and the
joint, before anything moves. A plan is also refused before anything moves when even a perfect view at every pose
could not pass the hand-eye solve's own check (:class:`hardware.calibration.hand_eye.PoseSpread`: too few poses, too
few distinct orientations, rotations about one axis only): :func:`check_plan`, on the flange poses of the plan's
joints. Generated poses stay ``AUTO_MARGIN`` inside the limits. They are the start pose plus offsets from a Halton
sequence (deterministic, spread evenly) scaled by :data:`AUTO_SPREAD`: the wrist (J4..J6) turns the most, so that the
board is seen from directions about three axes, while the shoulder and elbow move the board a few centimetres — the
board stays in view of a camera that sees it at the start pose.
"""

from __future__ import annotations

import math
import numbers
from pathlib import Path

import numpy as np

from dssp_core.errors import ConfigError
from dssp_core.schema import read_json
from dssp_data.arm_kinematics import flange_pose
from hardware.calibration.hand_eye import MIN_POSES, PoseSpread
from hardware.piper.limits import JOINT_LOWER, JOINT_UPPER, N_JOINTS

AUTO_SPREAD = np.array([0.08, 0.06, 0.06, 0.3, 0.25, 0.4])
"""rad, J1..J6: the largest offset of a generated pose from the start pose."""

AUTO_MARGIN = 0.05
"""rad kept from every joint limit by generated poses."""

MAX_POSES = 200
"""Poses a plan may hold (``--poses`` and ``--auto N``): at 10 Hz and a few seconds a pose, 200 is a quarter-hour
tour, far more than the solve needs (``hand_eye.MIN_POSES``)."""


def _is_number(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def _as_float(value) -> float:
    try:
        return float(value)
    except OverflowError:  # an integer beyond any float
        return math.inf


def check_poses(poses, where: str = "poses") -> np.ndarray:
    """``poses`` as (N, 6) float64 rad: a list of joint vectors of numbers (or a numeric array), each finite and
    inside the joint limits; else one-line ConfigError."""
    if isinstance(poses, np.ndarray):
        if poses.dtype.kind not in "iuf":
            raise ConfigError(f"{where}: poses must be numbers (J1..J6, rad), got an array of {poses.dtype}")
        rows = poses
    elif isinstance(poses, (list, tuple)) and all(isinstance(pose, (list, tuple, np.ndarray)) for pose in poses):
        rows = poses
        for i, pose in enumerate(poses):
            for j, value in enumerate(pose):
                if not _is_number(value):
                    raise ConfigError(
                        f"{where}: pose {i + 1} gives J{j + 1} as {value!r:.40}, not a number; write "
                        f'the angle as a JSON number in radians (0.1, not "0.1")'
                    )
                if not math.isfinite(_as_float(value)):
                    raise ConfigError(
                        f"{where}: pose {i + 1} gives J{j + 1} as {value!r:.40}, not a finite number of radians"
                    )
    else:
        raise ConfigError(
            f"{where}: poses must be a list of joint vectors (J1..J6, rad), each a list of {N_JOINTS} numbers"
        )
    try:
        array = np.array(rows, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        array = None
    if array is None or array.ndim != 2 or array.shape[1] != N_JOINTS or not 1 <= len(array) <= MAX_POSES:
        shape = "ragged lists" if array is None else f"shape {array.shape}"
        raise ConfigError(
            f"{where}: give 1 to {MAX_POSES} poses of {N_JOINTS} joint angles each (J1..J6, rad), got {shape}"
        )
    for i, pose in enumerate(array):
        if not np.all(np.isfinite(pose)):
            raise ConfigError(f"{where}: pose {i + 1} holds NaN or infinite values")
        outside = np.flatnonzero((pose < JOINT_LOWER) | (pose > JOINT_UPPER))
        if outside.size:
            j = int(outside[0])
            raise ConfigError(
                f"{where}: pose {i + 1} has J{j + 1} = {pose[j]:.4g} rad, outside the Piper's "
                f"{JOINT_LOWER[j]:.4g}..{JOINT_UPPER[j]:.4g} rad (angles are radians)"
            )
    return array


def check_plan(poses: np.ndarray, where: str) -> np.ndarray:
    """Refuse (one-line ConfigError starting with ``where``) a plan of (N, 6) poses whose views, even every one
    detected perfectly, would be refused by the hand-eye solve (:class:`~hardware.calibration.hand_eye.PoseSpread`,
    on the flange poses of the planned joints); returns the poses."""
    problem = PoseSpread.of([flange_pose(q) for q in np.asarray(poses, np.float64).reshape(-1, N_JOINTS)]).problem(
        "poses"
    )
    if problem is not None:
        raise ConfigError(f"{where}: a calibration plan that cannot pass: {problem}")
    return poses


def read_poses(path) -> np.ndarray:
    """(N, 6) rad from a JSON file, ``{"poses": [[J1..J6], ...]}`` (and optionally ``"notes"``) or a bare list of
    joint vectors, each checked (:func:`check_poses`); the file is read through the one read of a file a user names
    (:func:`dssp_core.schema.read_json`: a FIFO, a device, a directory or an oversized file is refused before
    a byte is read), parsed with nesting bounded and a key given twice refused."""
    path = Path(path).expanduser()
    label = f"--poses {path}"
    data = read_json(path, label)
    if isinstance(data, dict):
        if set(data) - {"poses", "notes"} or "poses" not in data:
            raise ConfigError(
                f'{label}: a JSON object needs the key "poses" (a list of joint vectors) and '
                f'may have "notes", got keys {sorted(data)}'
            )
        data = data["poses"]
    if not isinstance(data, list):
        raise ConfigError(f"{label}: poses must be a list of joint vectors (J1..J6, rad)")
    return check_poses(data, label)


def load_poses(path) -> np.ndarray:
    """The calibration plan of a ``--poses`` file (:func:`read_poses`), refused unless it can pass the solve
    (:func:`check_plan`)."""
    poses = read_poses(path)
    return check_plan(poses, f"--poses {Path(path).expanduser()}")


def _halton(i: int, base: int) -> float:
    f, r = 1.0, 0.0
    while i > 0:
        f /= base
        r += f * (i % base)
        i //= base
    return r


def check_pose_count(n: int, flag: str = "--auto") -> int:
    """``n`` poses to generate: MIN_POSES (what the solve needs) to MAX_POSES; else a one-line ConfigError."""
    if isinstance(n, bool) or not isinstance(n, int) or not MIN_POSES <= n <= MAX_POSES:
        raise ConfigError(
            f"{flag} must be {MIN_POSES} to {MAX_POSES} poses (the solve needs {MIN_POSES} views), got {n!r}"
        )
    return n


def auto_poses(start, n: int) -> np.ndarray:
    """``n`` poses (n, 6) rad around ``start`` (6,) rad: start + AUTO_SPREAD * h, h in [-1, 1]^6 from the Halton
    sequence (bases 2, 3, 5, 7, 11, 13), kept AUTO_MARGIN inside the limits. ``n`` is checked by
    :func:`check_pose_count`."""
    check_pose_count(n)
    start = np.asarray(start, dtype=np.float64).reshape(N_JOINTS)
    bases = (2, 3, 5, 7, 11, 13)
    h = np.array([[2.0 * _halton(i + 1, b) - 1.0 for b in bases] for i in range(n)])
    poses = start + AUTO_SPREAD * h
    return np.clip(poses, JOINT_LOWER + AUTO_MARGIN, JOINT_UPPER - AUTO_MARGIN)
