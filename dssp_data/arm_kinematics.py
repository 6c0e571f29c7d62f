"""Forward kinematics of the AgileX Piper from its modified DH table: the one place the simulation's arm
model and the viewers read it from.

Policy units per arm (7 values): J1..J6 in radians, then the gripper opening in [0, 1]. Frames: each arm's
base frame (metres), z up; frame 6 is the flange, the gripper's approach direction its z axis.

    pose = flange_pose(q)              # q (6,) rad -> (4, 4); flange_poses(q (N, 6)) -> rotations, positions
    tcp = tool_points(joints)          # joints (T, 7 * arms) policy units -> (T, arms, 3) tool centre points
"""

from __future__ import annotations

import math

import numpy as np

ARM_VALUES = 7  # per arm in policy units: 6 joints, 1 gripper opening

# Modified DH table of the Piper (metres, radians), joint i: RotX(alpha) TransX(a) RotZ(theta + q) TransZ(d).
DH_A = (0.0, 0.0, 0.28503, -0.02198, 0.0, 0.0)
DH_ALPHA = (0.0, -math.pi / 2, 0.0, math.pi / 2, -math.pi / 2, math.pi / 2)
DH_THETA = (0.0, math.radians(-172.22), math.radians(-102.78), 0.0, 0.0, 0.0)
DH_D = (0.123, 0.0, 0.0, 0.25075, 0.0, 0.091)

# Flange -> the gripper's tool centre point (between its pads), along the flange's z axis (m).
TCP_OFFSET = 0.098


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def dh_link_transform(i: int) -> tuple[np.ndarray, np.ndarray]:
    """Fixed part of DH joint i (0-based) at q = 0: (pos (3,), rotation (3, 3)) of frame i in frame i-1."""
    rot = _rot_x(DH_ALPHA[i]) @ _rot_z(DH_THETA[i])
    pos = np.array([DH_A[i], 0.0, 0.0]) + _rot_x(DH_ALPHA[i]) @ np.array([0.0, 0.0, DH_D[i]])
    return pos, rot


def flange_poses(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flange poses in the arm's base frame for joints q (N, 6) rad: (rotations (N, 3, 3), positions (N, 3)),
    batched over every pose at once."""
    q = np.asarray(q, np.float64).reshape(-1, 6)
    rot, pos = np.broadcast_to(np.eye(3), (len(q), 3, 3)), np.zeros((len(q), 3))
    for i in range(6):
        c, s = np.cos(DH_THETA[i] + q[:, i]), np.sin(DH_THETA[i] + q[:, i])
        rz = np.zeros((len(q), 3, 3))
        rz[:, 0, 0], rz[:, 0, 1], rz[:, 1, 0], rz[:, 1, 1], rz[:, 2, 2] = c, -s, s, c, 1.0
        pos = pos + rot @ dh_link_transform(i)[0]
        rot = rot @ _rot_x(DH_ALPHA[i]) @ rz
    return rot, pos


def flange_pose(q: np.ndarray) -> np.ndarray:
    """Flange pose (4, 4) in the arm's base frame for joints q (6,) rad."""
    rot, pos = flange_poses(q)
    t = np.eye(4)
    t[:3, :3], t[:3, 3] = rot[0], pos[0]
    return t


def tool_points(joints: np.ndarray, tcp_offset: float = TCP_OFFSET) -> np.ndarray:
    """Tool centre points (T, arms, 3) in each arm's base frame for ``joints`` (T, 7 * arms) in policy units
    (a single (7 * arms,) vector gives (1, arms, 3)). A width that is not a whole number of arms is an error.
    Batched over every pose at once (the viewers call it per chunk)."""
    joints = np.atleast_2d(np.asarray(joints, np.float64))
    if joints.shape[-1] % ARM_VALUES:
        raise ValueError(f"joint vectors have {joints.shape[-1]} values, not {ARM_VALUES} per arm (6 joints + gripper)")
    arms = joints.shape[-1] // ARM_VALUES
    rot, pos = flange_poses(joints.reshape(-1, arms, ARM_VALUES)[..., :6])  # T * arms poses
    return (pos + tcp_offset * rot[:, :, 2]).reshape(joints.shape[0], arms, 3)
