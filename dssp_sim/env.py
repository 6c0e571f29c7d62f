"""``PiperEnv``: one simulated Piper arm on a table with a memory task, stepped at the policy's rate.

Two levels of use:

- low level (what a CAN simulator drives): ``set_targets(joints (6,) rad, stroke m)`` then ``advance(dt s)``;
  read back ``joint_positions()`` (6,) rad and ``gripper_stroke()`` m;
- policy level, in policy units (7,) = [J1..J6 rad, gripper opening 0..1, 1 = open]:
  ``state()``, ``step(target)`` (one control period, 1 / ``control_rate_hz`` s), ``render_depth()``,
  ``status()``.

    env = PiperEnv("tap", seed=3)
    expert = make_expert(env)                      # dssp_sim.experts
    while not env.status().done:
        env.step(expert.act(env))

The depth camera is fixed (``dssp_sim.mjcf.CAMERA_*``); ``render_depth`` returns a raw uint16 image in
units of ``DEPTH_UNIT`` (0.25 mm, as an L515), exact pinhole intrinsics of the render and the camera's
pose in the base frame (optical frame: x right, y down, z forward).
"""

from __future__ import annotations

import math
import os
import threading

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from dssp_core.schema import DEFAULT_CONTROL_RATE_HZ  # noqa: E402
from dssp_data.pointcloud.depth_frame import Intrinsics
from dssp_sim.mjcf import CAMERA_NAME, TIMESTEP, ArmIndex, scene_xml  # noqa: E402
from dssp_sim.render import CameraRenders  # noqa: E402
from dssp_sim.settings import render_size_for  # noqa: E402
from dssp_sim.tasks import HOME, HOME_TOLERANCE, START_JITTER, Task, TaskStatus, make_task  # noqa: E402
from hardware.piper.limits import (  # noqa: E402
    GRIPPER_STROKE_MAX,
    GRIPPER_STROKE_MIN,
    JOINT_LOWER,
    JOINT_UPPER,
    opening_to_stroke,
    stroke_to_opening,
)

DEPTH_UNIT = 0.00025  # m per raw depth unit
DEPTH_MIN_M = 0.25  # nearer than this reads 0 (L515 minimum range)
DEPTH_MAX_M = 4.0  # farther than this (or nothing hit) reads 0

# Optical frame (x right, y down, z forward) in MuJoCo's camera frame (x right, y up, looking along -z).
_OPTICAL_IN_MJCAM = np.diag([1.0, -1.0, -1.0])


class ArmServos:
    """The simulated arm's servo targets and what it measures, under the scene's lock (what
    :class:`~dssp_sim.mujoco_arm.MujocoPiper` drives): for a scene with ``data``, ``lock`` and ``arm``
    (:class:`ArmIndex`), and ``_time_debt`` — the task env and the calibration twin."""

    def _whole_steps(self, dt: float) -> int:
        """The whole physics steps (of TIMESTEP) that ``dt`` seconds and the time carried over from the previous call
        make; the remainder is carried over to the next (``_time_debt``)."""
        total = self._time_debt + dt
        n = int(math.floor(total / TIMESTEP + 1e-9))
        self._time_debt = total - n * TIMESTEP
        return n

    def set_targets(self, joints: np.ndarray, stroke: float) -> None:
        """Servo targets: joints (6,) rad and gripper stroke (m), clamped to the Piper's limits."""
        q = np.clip(np.asarray(joints, dtype=np.float64).reshape(6), JOINT_LOWER, JOINT_UPPER)
        with self.lock:
            self.data.ctrl[self.arm.actuators] = q
            self.data.ctrl[self.arm.gripper_actuator] = float(np.clip(stroke, GRIPPER_STROKE_MIN, GRIPPER_STROKE_MAX))

    def joint_positions(self) -> np.ndarray:
        """(6,) float64 measured joint angles, rad."""
        with self.lock:
            return self.data.qpos[self.arm.qpos].copy()

    def gripper_stroke(self) -> float:
        """Measured distance between the finger pads, metres (0..0.07)."""
        with self.lock:
            stroke = self.data.qpos[self.arm.finger_qpos].sum()
        return float(np.clip(stroke, GRIPPER_STROKE_MIN, GRIPPER_STROKE_MAX))


class PiperEnv(ArmServos):
    """One Piper arm and ``task`` ("tap" | "swap" | "put2"), seeded by ``seed``.

    render_size: (H, W) pixels of the depth render (default: the task's, :func:`dssp_sim.settings.render_size_for`;
    4:3 keeps the camera's 70 x 55 degree field of view;
    another aspect keeps the vertical field of view). Attributes: ``task`` (the :class:`Task`), ``model``,
    ``data`` (MuJoCo), ``control_rate_hz``, ``max_steps`` (the task's step budget), ``steps`` (control
    periods simulated since reset, also counted when driven through ``advance``), ``arm`` (an
    :class:`ArmIndex`).

    Threads: every method takes ``lock`` (a re-entrant lock), so e.g. a CAN-simulator thread calling
    ``set_targets``/``advance`` and a camera thread calling ``render_depth`` can share one env; rendering
    runs in a thread of its own that holds the GL context (``close()`` stops it).
    """

    def __init__(self, task: str, seed: int = 0, render_size: tuple[int, int] | None = None) -> None:
        self.task: Task = make_task(task)
        self.model = mujoco.MjModel.from_xml_string(
            scene_xml(self.task.objects_xml(), extra_contact=self.task.extra_contact())
        )
        self.data = mujoco.MjData(self.model)
        self.arm = ArmIndex.find(self.model)
        self.control_rate_hz = DEFAULT_CONTROL_RATE_HZ  # the simulated Piper runs at the toolkit's default rate
        render_size = render_size or render_size_for(task)
        self.render_size = (int(render_size[0]), int(render_size[1]))
        self._substeps_per_control = int(round(1.0 / (self.control_rate_hz * TIMESTEP)))
        self._camera_id = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, CAMERA_NAME)
        self._renders = CameraRenders(self, self.model, self.render_size, self._camera_id)
        self.lock = threading.RLock()
        self._substeps = 0
        self._time_debt = 0.0
        self.seed = int(seed)
        self._rng = np.random.default_rng(self.seed)
        self.task.bind(self)
        self.reset(self.seed)

    # ------------------------------------------------------------------------------------------- episode
    def reset(self, seed: int | None = None, options: dict | None = None) -> None:
        """Start a new episode: the scene randomised from ``seed`` (None: continue this env's generator),
        the arm at HOME plus a small jitter, holding still. ``options`` go to the task (see its ``reset``)."""
        with self.lock:
            self._reset(seed, options)

    def _reset(self, seed: int | None, options: dict | None) -> None:
        if seed is not None:
            self.seed = int(seed)
            self._rng = np.random.default_rng(self.seed)
        rng = self._rng
        mujoco.mj_resetData(self.model, self.data)
        self.max_steps = self.task.max_steps  # each episode's own budget (an evaluation may lengthen it)
        self.task.reset(self, rng, options)
        start = np.clip(HOME + rng.uniform(-START_JITTER, START_JITTER, 6), JOINT_LOWER, JOINT_UPPER)
        stroke = float(opening_to_stroke(self.task.home_opening))
        self.data.qpos[self.arm.qpos] = start
        self.data.qpos[self.arm.finger_qpos] = stroke / 2.0
        self.set_targets(start, stroke)
        mujoco.mj_forward(self.model, self.data)
        self._substeps = 0
        self._time_debt = 0.0
        self.task.update(self)

    @property
    def steps(self) -> int:
        """Control periods (1 / control_rate_hz s) simulated since reset."""
        return self._substeps // self._substeps_per_control

    # ------------------------------------------------------------------------------------------- low level
    def advance(self, dt: float) -> None:
        """Simulate ``dt`` seconds (whole physics steps of 2 ms; the remainder is carried over to the next
        call). A task that needs it (the tap's press counter) watches every physics step; the task's
        status is updated at the end."""
        if dt < 0:
            raise ValueError(f"dt must be >= 0, got {dt}")
        with self.lock:
            self._advance(dt)

    def _advance(self, dt: float) -> None:
        n = self._whole_steps(dt)
        if n <= 0:
            return
        if type(self.task).on_substep is Task.on_substep:
            mujoco.mj_step(self.model, self.data, nstep=n)
        else:
            for _ in range(n):
                mujoco.mj_step(self.model, self.data)
                self.task.on_substep(self)
        self._substeps += n
        self.task.update(self)

    # ------------------------------------------------------------------------------------------- policy level
    def state(self) -> np.ndarray:
        """(7,) float64 measured [J1..J6 rad, gripper opening 0..1]."""
        with self.lock:
            return np.append(self.joint_positions(), float(stroke_to_opening(self.gripper_stroke())))

    def step(self, target: np.ndarray) -> None:
        """Apply a (7,) policy target [J1..J6 rad, opening 0..1] (clamped) for one control period."""
        t = np.asarray(target, dtype=np.float64).reshape(7)
        if not np.all(np.isfinite(t)):
            raise ValueError(f"target must be finite, got {t}")
        with self.lock:
            self.set_targets(t[:6], float(opening_to_stroke(np.clip(t[6], 0.0, 1.0))))
            self.advance(1.0 / self.control_rate_hz)

    def status(self) -> TaskStatus:
        """The task's status (latched once done)."""
        with self.lock:
            return self.task.status()

    # ------------------------------------------------------------------------------------------- queries
    def at_home(self, tol: float = HOME_TOLERANCE) -> bool:
        """Every measured joint within ``tol`` rad of ``HOME``."""
        return bool(np.abs(self.joint_positions() - HOME).max() <= tol)

    def tcp_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Measured tool centre point: position (3,) m and rotation (3, 3) in the base frame."""
        s = self.arm.tcp_site
        return self.data.site_xpos[s].copy(), self.data.site_xmat[s].reshape(3, 3).copy()

    def touching(self, geom_a: int, geom_b: int) -> bool:
        """Whether geoms ``geom_a`` and ``geom_b`` are in contact now."""
        n = self.data.ncon
        if n == 0:
            return False
        pairs = self.data.contact.geom[:n]
        return bool(
            np.any(
                ((pairs[:, 0] == geom_a) & (pairs[:, 1] == geom_b))
                | ((pairs[:, 0] == geom_b) & (pairs[:, 1] == geom_a))
            )
        )

    # ------------------------------------------------------------------------------------------- camera
    def intrinsics(self) -> Intrinsics:
        """Pinhole intrinsics (pixels) of ``render_depth``: square pixels from the camera's vertical field of
        view, principal point at the image centre (pixel (u, v) has its centre at u + 0.5, v + 0.5)."""
        h, w = self.render_size
        f = 0.5 * h / math.tan(math.radians(float(self.model.cam_fovy[self._camera_id])) / 2.0)
        return Intrinsics(width=w, height=h, fx=f, fy=f, ppx=(w - 1) / 2.0, ppy=(h - 1) / 2.0)

    def camera_to_base(self) -> np.ndarray:
        """(4, 4) pose of the camera's optical frame (x right, y down, z forward) in the base frame."""
        t = np.eye(4)
        t[:3, :3] = self.data.cam_xmat[self._camera_id].reshape(3, 3) @ _OPTICAL_IN_MJCAM
        t[:3, 3] = self.data.cam_xpos[self._camera_id]
        return t

    def render_depth(self) -> tuple[np.ndarray, float, Intrinsics, np.ndarray]:
        """Depth image of the scene now: (depth (H, W) uint16 raw, depth_unit 0.00025 m, intrinsics,
        camera_to_base (4, 4)).

        Depth is the distance along the optical axis (z), rounded to the raw unit; 0 where nothing is hit
        or the hit is outside [``DEPTH_MIN_M``, ``DEPTH_MAX_M``]. Measured 1.3-3.6 ms at 120 x 160 (13 ms at
        480 x 640) on a shared 2-core CPU with EGL/llvmpipe; the first call also creates the GL context
        (~0.2 s)."""
        with self.lock:
            metres = self._renders.render(self.data)
            cam_to_base = self.camera_to_base()
        valid = (metres >= DEPTH_MIN_M) & (metres <= DEPTH_MAX_M)
        raw = np.where(valid, np.rint(metres / DEPTH_UNIT), 0.0).astype(np.uint16)
        return raw, DEPTH_UNIT, self.intrinsics(), cam_to_base

    def close(self) -> None:
        """Stop the render thread and free its GL context (the env stays usable; rendering again starts a
        new one)."""
        self._renders.close()

    def __enter__(self) -> "PiperEnv":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
