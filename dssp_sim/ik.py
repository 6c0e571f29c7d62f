"""Numerical inverse kinematics of one simulated Piper arm: damped least squares on MuJoCo's site Jacobian.

Poses are of the tool centre point (site ``tcp``) in the base frame: position (3,) metres and rotation
(3, 3) whose columns are the tool's x, y (finger axis) and z (approach) axes. The solver works on its own
``MjData`` (a scratch copy), never on the simulation's.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from dssp_sim.mjcf import ArmIndex
from hardware.piper.limits import JOINT_LOWER, JOINT_UPPER


def rotation_error(target: np.ndarray, current: np.ndarray) -> np.ndarray:
    """(3,) rotation vector w (world frame, rad) with exp(w) @ current = target."""
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, (target @ current.T).reshape(-1))
    vel = np.zeros(3)
    mujoco.mju_quat2Vel(vel, quat, 1.0)
    return vel


class IKSolver:
    """Damped-least-squares IK for the arm ``prefix`` of ``model`` on a private ``MjData``.

    ``solve(pos (3,), rot (3, 3) or None, seed (6,))`` -> (6,) joints (rad, inside the Piper limits) and
    sets ``last_error`` to (position error m, rotation error rad). With ``rot=None`` only the position is
    matched.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        prefix: str = "",
        damping: float = 0.02,
        max_iters: int = 200,
        pos_tol: float = 1e-4,
        rot_tol: float = 1e-3,
    ) -> None:
        self.model = model
        self.data = mujoco.MjData(model)
        self.index = ArmIndex.find(model, prefix)
        self.damping = damping
        self.max_iters = max_iters
        self.pos_tol = pos_tol
        self.rot_tol = rot_tol
        self.last_error = (math.inf, math.inf)
        self._jacp = np.zeros((3, model.nv))
        self._jacr = np.zeros((3, model.nv))

    def forward(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """TCP pose for joints q (6,): (position (3,), rotation (3, 3))."""
        self.data.qpos[self.index.qpos] = q
        mujoco.mj_kinematics(self.model, self.data)
        site = self.index.tcp_site
        return self.data.site_xpos[site].copy(), self.data.site_xmat[site].reshape(3, 3).copy()

    def solve(self, pos, rot=None, seed=None) -> np.ndarray:
        pos = np.asarray(pos, dtype=np.float64)
        q = np.clip(np.zeros(6) if seed is None else np.asarray(seed, dtype=np.float64), JOINT_LOWER, JOINT_UPPER)
        site, dofs = self.index.tcp_site, self.index.dof
        err_p, err_r = math.inf, 0.0
        for _ in range(self.max_iters):
            self.data.qpos[self.index.qpos] = q
            mujoco.mj_kinematics(self.model, self.data)
            mujoco.mj_comPos(self.model, self.data)
            cur_p = self.data.site_xpos[site]
            e_p = pos - cur_p
            err_p = float(np.linalg.norm(e_p))
            mujoco.mj_jacSite(self.model, self.data, self._jacp, self._jacr, site)
            if rot is None:
                e, jac = e_p, self._jacp[:, dofs]
                err_r = 0.0
            else:
                e_r = rotation_error(np.asarray(rot, float), self.data.site_xmat[site].reshape(3, 3))
                err_r = float(np.linalg.norm(e_r))
                e = np.concatenate([e_p, 0.3 * e_r])
                jac = np.vstack([self._jacp[:, dofs], 0.3 * self._jacr[:, dofs]])
            if err_p < self.pos_tol and err_r < self.rot_tol:
                break
            lam2 = self.damping**2
            dq = jac.T @ np.linalg.solve(jac @ jac.T + lam2 * np.eye(jac.shape[0]), e)
            step = float(np.abs(dq).max())
            if step > 0.2:
                dq *= 0.2 / step
            q = np.clip(q + dq, JOINT_LOWER, JOINT_UPPER)
        self.last_error = (err_p, err_r)
        return q
