"""Camera -> robot-base extrinsics: a 4x4 rigid transform kept in a small JSON calibration file.

    {"camera_to_base": [[r00, r01, r02, tx], [r10, r11, r12, ty], [r20, r21, r22, tz], [0, 0, 0, 1]],
     "frame": "piper_base", "notes": "hand-eye calibration 2024-05-02"}

``camera_to_base`` maps a point in the camera's optical frame (x right, y down, z forward, metres) to the
robot-base frame: p_base = R @ p_cam + t. Without a calibration file (``load_extrinsics(None)``) the
identity is used: clouds then stay in the camera frame, and the crop box must be given in camera
coordinates. Every problem is a one-line :class:`~dssp_core.errors.CalibrationError`.

A camera on the wrist has a file of its own (``dssp-calibrate --mode eye-in-hand``), which ``dssp-run`` and
``dssp-record`` do not take (their camera is fixed):

    {"camera_to_gripper": [[...], [...], [...], [0, 0, 0, 1]], "frame": "piper_flange", "notes": "..."}

``camera_to_gripper`` maps a point in the camera's optical frame to the Piper's flange frame (DH frame 6,
:func:`dssp_data.arm_kinematics.flange_pose`); :func:`save_camera_to_gripper`, :func:`load_camera_to_gripper`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from dssp_core.errors import CalibrationError, ConfigError
from dssp_core.files import atomic_write_text
from dssp_core.schema import Settings, read_json_object, setting

ROTATION_TOLERANCE = 1e-3  # max |R^T R - I| entry and |det R - 1|: allows 4-5 printed decimals
MAX_TRANSLATION_M = 10.0  # a camera farther than this from the base is a unit mistake (mm instead of m)


def identity() -> np.ndarray:
    """(4, 4) float64 identity: the camera frame is used as the base frame."""
    return np.eye(4)


def validate_extrinsics(matrix, source: str = "camera_to_base", name: str = "camera_to_base") -> np.ndarray:
    """Check a rigid transform (camera->base, or camera->gripper: ``name``) and return it as (4, 4) float64;
    CalibrationError naming ``source`` and ``name``."""
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise CalibrationError(f"{source}: {name} must be a 4x4 array of numbers") from None
    if m.shape != (4, 4):
        raise CalibrationError(f"{source}: {name} must be 4x4 (4 rows of 4 numbers), got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise CalibrationError(f"{source}: {name} holds NaN or infinite values; redo the calibration")
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise CalibrationError(f"{source}: the last row of {name} must be [0, 0, 0, 1], got {m[3].tolist()}")
    r = m[:3, :3]
    err = float(np.abs(r.T @ r - np.eye(3)).max())
    if err > ROTATION_TOLERANCE:
        raise CalibrationError(
            f"{source}: the rotation part is not orthonormal (max |R^T R - I| = {err:.2g} > "
            f"{ROTATION_TOLERANCE:g}); store a rotation matrix, not a scaled one"
        )
    det = float(np.linalg.det(r))
    if abs(det - 1.0) > ROTATION_TOLERANCE:
        raise CalibrationError(
            f"{source}: the rotation has determinant {det:.4g}, not +1 (a reflection or a "
            f"flipped axis); check the axis convention"
        )
    dist = float(np.linalg.norm(m[:3, 3]))
    if dist > MAX_TRANSLATION_M:
        raise CalibrationError(
            f"{source}: the camera is {dist:.4g} m from the base; translations must be in metres, not millimetres"
        )
    return m


_ROW = tuple[float, float, float, float]


@dataclass(frozen=True)
class CalibrationFile(Settings):
    """The calibration file's schema: ``camera_to_base`` (4 rows of 4 numbers), ``frame``, ``notes``."""

    SECTION: ClassVar[str] = "calibration"

    camera_to_base: tuple[_ROW, _ROW, _ROW, _ROW] = setting(ge=-1e6, le=1e6)
    frame: str = setting("base")
    notes: str = setting("")

    def validate(self) -> None:
        try:
            validate_extrinsics(self.camera_to_base)
        except CalibrationError as exc:
            raise ConfigError(str(exc)) from None


def load_extrinsics(path: str | Path | None) -> np.ndarray:
    """(4, 4) float64 camera->base transform from a calibration JSON file; None -> identity (camera frame)."""
    if path is None:
        return identity()
    path = Path(path).expanduser()
    if not path.exists():
        raise CalibrationError(f"calibration file {path} does not exist; check the path or calibrate the camera")
    try:
        calibration = CalibrationFile.load(path, "calibration")
    except ConfigError as exc:
        raise CalibrationError(str(exc)) from None
    return np.asarray(calibration.camera_to_base, dtype=np.float64)


def save_extrinsics(path: str | Path, camera_to_base, frame: str = "base", notes: str = "") -> Path:
    """Validate and write a calibration file atomically (temporary file + rename). Returns the path."""
    path = Path(path).expanduser()
    m = validate_extrinsics(camera_to_base, source=str(path))
    text = (
        json.dumps(
            {"camera_to_base": [[float(v) for v in row] for row in m], "frame": str(frame), "notes": str(notes)},
            indent=2,
        )
        + "\n"
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, text)
    return path


WRIST_FRAME = "piper_flange"
"""The frame ``camera_to_gripper`` maps into: the Piper's flange, DH frame 6."""


def save_camera_to_gripper(path: str | Path, camera_to_gripper, notes: str = "") -> Path:
    """Validate and write a wrist camera's calibration file atomically; returns the path."""
    path = Path(path).expanduser()
    m = validate_extrinsics(camera_to_gripper, source=str(path), name="camera_to_gripper")
    text = (
        json.dumps(
            {"camera_to_gripper": [[float(v) for v in row] for row in m], "frame": WRIST_FRAME, "notes": str(notes)},
            indent=2,
        )
        + "\n"
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, text)
    return path


def load_camera_to_gripper(path: str | Path) -> np.ndarray:
    """(4, 4) camera_to_gripper from a wrist camera's calibration file; one-line CalibrationError."""
    path = Path(path).expanduser()
    values = read_json_object(path, "calibration", error=CalibrationError)
    unknown = sorted(set(values) - {"camera_to_gripper", "frame", "notes"})
    if "camera_to_gripper" not in values or unknown:
        raise CalibrationError(
            f"{path}: a wrist camera's calibration holds camera_to_gripper, frame and notes, got keys {sorted(values)}"
        )
    if values.get("frame", WRIST_FRAME) != WRIST_FRAME:
        raise CalibrationError(f"{path}: frame must be {WRIST_FRAME!r}, got {values['frame']!r}")
    return validate_extrinsics(values["camera_to_gripper"], source=str(path), name="camera_to_gripper")
