"""Camera -> robot-base extrinsics: a 4x4 rigid transform kept in a small JSON calibration file.

    {"camera_to_base": [[r00, r01, r02, tx], [r10, r11, r12, ty], [r20, r21, r22, tz], [0, 0, 0, 1]],
     "frame": "piper_base", "notes": "hand-eye calibration 2024-05-02"}

``camera_to_base`` maps a point in the camera's optical frame (x right, y down, z forward, metres) to the
robot-base frame: p_base = R @ p_cam + t. Without a calibration file (``load_extrinsics(None)``) the
identity is used: clouds then stay in the camera frame, and the crop box must be given in camera
coordinates. Every problem is a one-line :class:`~hardware.errors.CalibrationError`.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import numpy as np

from hardware.errors import CalibrationError

ROTATION_TOLERANCE = 1e-3  # max |R^T R - I| entry and |det R - 1|: allows 4-5 printed decimals
MAX_TRANSLATION_M = 10.0  # a camera farther than this from the base is a unit mistake (mm instead of m)


def identity() -> np.ndarray:
    """(4, 4) float64 identity: the camera frame is used as the base frame."""
    return np.eye(4)


def validate_extrinsics(matrix, source: str = "camera_to_base") -> np.ndarray:
    """Check a camera->base transform and return it as (4, 4) float64; CalibrationError naming ``source``."""
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise CalibrationError(f"{source}: camera_to_base must be a 4x4 array of numbers") from None
    if m.shape != (4, 4):
        raise CalibrationError(f"{source}: camera_to_base must be 4x4 (4 rows of 4 numbers), got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise CalibrationError(f"{source}: camera_to_base holds NaN or infinite values; redo the calibration")
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise CalibrationError(f"{source}: the last row of camera_to_base must be [0, 0, 0, 1], got {m[3].tolist()}")
    r = m[:3, :3]
    err = float(np.abs(r.T @ r - np.eye(3)).max())
    if err > ROTATION_TOLERANCE:
        raise CalibrationError(f"{source}: the rotation part is not orthonormal (max |R^T R - I| = {err:.2g} > "
                               f"{ROTATION_TOLERANCE:g}); store a rotation matrix, not a scaled one")
    det = float(np.linalg.det(r))
    if abs(det - 1.0) > ROTATION_TOLERANCE:
        raise CalibrationError(f"{source}: the rotation has determinant {det:.4g}, not +1 (a reflection or a "
                               f"flipped axis); check the axis convention")
    dist = float(np.linalg.norm(m[:3, 3]))
    if dist > MAX_TRANSLATION_M:
        raise CalibrationError(f"{source}: the camera is {dist:.4g} m from the base; translations must be in "
                               f"metres, not millimetres")
    return m


def load_extrinsics(path: str | Path | None) -> np.ndarray:
    """(4, 4) float64 camera->base transform from a calibration JSON file; None -> identity (camera frame)."""
    if path is None:
        return identity()
    path = Path(path).expanduser()
    if not path.exists():
        raise CalibrationError(f"calibration file {path} does not exist; check the path or calibrate the camera")
    if not path.is_file():
        raise CalibrationError(f"calibration file {path} is not a file")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise CalibrationError(f"calibration file {path} is not valid JSON (line {e.lineno}: {e.msg})") from None
    except (OSError, UnicodeDecodeError) as e:
        raise CalibrationError(f"calibration file {path} cannot be read ({e})") from None
    if not isinstance(data, dict) or "camera_to_base" not in data:
        raise CalibrationError(f"calibration file {path} needs a 'camera_to_base' key holding a 4x4 matrix")
    matrix = data["camera_to_base"]
    if not (isinstance(matrix, list) and all(isinstance(row, list) for row in matrix)):
        raise CalibrationError(f"{path}: camera_to_base must be a list of 4 rows of 4 numbers")
    if any(isinstance(v, bool) or not isinstance(v, (int, float)) for row in matrix for v in row):
        raise CalibrationError(f"{path}: camera_to_base must hold only numbers")
    return validate_extrinsics(matrix, source=str(path))


def save_extrinsics(path: str | Path, camera_to_base, frame: str = "base", notes: str = "") -> Path:
    """Validate and write a calibration file atomically (temporary file + rename). Returns the path."""
    path = Path(path).expanduser()
    m = validate_extrinsics(camera_to_base, source=str(path))
    text = json.dumps({"camera_to_base": [[float(v) for v in row] for row in m], "frame": str(frame),
                       "notes": str(notes)}, indent=2) + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return path

