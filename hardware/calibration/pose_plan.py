"""Where the arm goes to be calibrated: joint vectors from a JSON file, or generated around where the arm starts.

    poses = load_poses("poses.json")          # (N, 6) rad: {"poses": [[J1..J6], ...]} or a bare list of them
    poses = auto_poses(start_joints, 12)      # (12, 6) rad: small moves of every joint around the start

Every pose must lie inside the Piper's joint limits (:mod:`hardware.piper.limits`, the one source of limits); one
outside is refused with one line naming the pose and the joint, before anything moves. Generated poses stay
``AUTO_MARGIN`` inside the limits. They are the start pose plus offsets from a Halton sequence (deterministic, spread
evenly) scaled by :data:`AUTO_SPREAD`: the wrist (J4..J6) turns the most, so that the board is seen from directions
about three axes, while the shoulder and elbow move the board a few centimetres — the board stays in view of a camera
that sees it at the start pose.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dssp_core.errors import ConfigError
from hardware.piper.limits import JOINT_LOWER, JOINT_UPPER, N_JOINTS

AUTO_SPREAD = np.array([0.08, 0.06, 0.06, 0.3, 0.25, 0.4])
"""rad, J1..J6: the largest offset of a generated pose from the start pose."""

AUTO_MARGIN = 0.05
"""rad kept from every joint limit by generated poses."""

MAX_POSES = 200


def check_poses(poses, where: str = "poses") -> np.ndarray:
    """``poses`` as (N, 6) float64 rad, each finite and inside the joint limits; else one-line ConfigError."""
    try:
        array = np.asarray(poses, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: poses must be lists of {N_JOINTS} numbers (J1..J6, rad)") from None
    if array.ndim != 2 or array.shape[1] != N_JOINTS or not 1 <= len(array) <= MAX_POSES:
        raise ConfigError(f"{where}: give 1 to {MAX_POSES} poses of {N_JOINTS} joint angles each (J1..J6, rad), "
                          f"got shape {array.shape}")
    for i, pose in enumerate(array):
        if not np.all(np.isfinite(pose)):
            raise ConfigError(f"{where}: pose {i + 1} holds NaN or infinite values")
        outside = np.flatnonzero((pose < JOINT_LOWER) | (pose > JOINT_UPPER))
        if outside.size:
            j = int(outside[0])
            raise ConfigError(f"{where}: pose {i + 1} has J{j + 1} = {pose[j]:.4g} rad, outside the Piper's "
                              f"{JOINT_LOWER[j]:.4g}..{JOINT_UPPER[j]:.4g} rad (angles are radians)")
    return array


def load_poses(path) -> np.ndarray:
    """(N, 6) rad from a JSON file: ``{"poses": [[J1..J6], ...]}`` or a bare list of joint vectors."""
    path = Path(path).expanduser()
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"--poses {path} does not exist") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"--poses {path} is not readable JSON ({exc})") from None
    if isinstance(data, dict):
        if set(data) - {"poses", "notes"} or "poses" not in data:
            raise ConfigError(f"--poses {path}: a JSON object needs the key \"poses\" (a list of joint vectors) and "
                              f"may have \"notes\", got keys {sorted(data)}")
        data = data["poses"]
    if not isinstance(data, list) or any(isinstance(v, bool) for pose in data if isinstance(pose, list) for v in pose):
        raise ConfigError(f"--poses {path}: poses must be a list of joint vectors (J1..J6, rad)")
    return check_poses(data, f"--poses {path}")


def _halton(i: int, base: int) -> float:
    f, r = 1.0, 0.0
    while i > 0:
        f /= base
        r += f * (i % base)
        i //= base
    return r


def auto_poses(start, n: int) -> np.ndarray:
    """``n`` poses (n, 6) rad around ``start`` (6,) rad: start + AUTO_SPREAD * h, h in [-1, 1]^6 from the Halton
    sequence (bases 2, 3, 5, 7, 11, 13), kept AUTO_MARGIN inside the limits."""
    if not 1 <= n <= MAX_POSES:
        raise ConfigError(f"--auto must be 1 to {MAX_POSES} poses, got {n}")
    start = np.asarray(start, dtype=np.float64).reshape(N_JOINTS)
    bases = (2, 3, 5, 7, 11, 13)
    h = np.array([[2.0 * _halton(i + 1, b) - 1.0 for b in bases] for i in range(n)])
    poses = start + AUTO_SPREAD * h
    return np.clip(poses, JOINT_LOWER + AUTO_MARGIN, JOINT_UPPER - AUTO_MARGIN)

