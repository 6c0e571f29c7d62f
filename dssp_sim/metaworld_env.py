"""MetaWorld's Sawyer tasks behind the simulation's interfaces, observed the way DP3 observes them.

    env = MetaWorldEnv("door-open", seed=0)      # a v3 task of the ``metaworld`` package
    expert = MetaWorldExpert(env)                # MetaWorld's scripted policy for it
    while not env.status().done:
        env.step(expert.act(env))

The same policy-level interface as :class:`~dssp_sim.env.PiperEnv` (``reset``, ``state``, ``step``, ``status``,
``render_depth``), so :mod:`dssp_sim.collect` writes its demonstrations and :mod:`dssp_sim.evaluate` runs a model on
it through the runtime, and the clouds come from the robot's own point-cloud pipeline (``dssp_data.pointcloud``)
through :class:`~dssp_sim.mujoco_camera.MujocoCamera`.

DP3's protocol, as its MetaWorld wrapper and demonstration script do it:
- state (9,) = [hand xyz, right fingertip xyz, left fingertip xyz] m (DP3's ``agent_pos``); action (4,) =
  [dx, dy, dz in 1/100 m (MetaWorld's action scale), gripper effort], stored as the expert gives it (DP3 does;
  its values reach about 7) and clipped to [-1, 1] by MetaWorld when it steps;
- the depth camera: ``corner2`` moved to (0.6, 0.295, 0.8) m, 128 x 128 pixels, depth up to 1.5 m;
- the clouds: in DP3's cloud frame (below), cropped to DP3's box, 512 points by farthest point sampling of every
  cropped point (no voxel grid);
- episodes of 200 steps; a demonstration is kept when the task's success flag held at 5 steps or more; an
  evaluation episode succeeds when the flag is set at any step (it ends there: the rest cannot change it).

The memory variant ``metaworld-cue/NAME`` (this project's own, not part of MetaWorld; NAME in :data:`CUE_TASKS`,
tasks whose goal no object shows): the task's goal marker is a cue — a sphere of :data:`CUE_RADIUS_M` at the goal,
in the clouds for the first :data:`CUE_STEPS` steps of an episode, then too small to render — so after the first
tenth of a second a policy knows the goal only from what it remembers. The expert knows it throughout (MetaWorld's
scripted policy reads it from the simulator), the scoring is the task's own.

DP3's cloud frame. DP3 turns corner2's depth into points with the rotation of camera 0 (``topview``, the identity)
and no translation, then rotates them by Rx(61.4°)·Ry(-7°) (its ``pc_transform``); its crop box
``[-0.5, -1.5, -0.795]``–``[1, -0.4, 100]`` is given in that frame. ``render_depth`` returns that frame as the
camera's pose, so the same crop on the same frame keeps the same points. The camera is at the frame's origin.

MuJoCo versions. metaworld 3.1.1 declares ``mujoco==3.3.0``; the project runs a newer MuJoCo, in which a weld's
``eq_data`` row grew from 11 numbers to 12 (the 12th: 1 = take the relative pose from the model's reference
configuration, 0 = use the one given). metaworld writes 11 numbers with the relative pose given, so the one
place it does (``SawyerMocapBase.reset_mocap_welds``) is given the 12th as 0 (:func:`_patch_mocap_welds`).
Install metaworld without its pin: ``pip install --no-deps metaworld==3.1.1 && pip install "gymnasium>=1.1" imageio``
(``make setup`` does).
"""

from __future__ import annotations

import math
import os
import threading
import warnings

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from dssp_core.errors import ConfigError
from dssp_data.model_contract import ModelContract  # noqa: E402
from dssp_data.observation import ObservationContract, PointCloudConfig, VectorLayout  # noqa: E402
from dssp_data.pointcloud.depth_frame import Intrinsics
from dssp_sim.render import CameraRenders  # noqa: E402
from dssp_sim.tasks import TaskStatus  # noqa: E402

PREFIX = "metaworld/"
# This project's memory variant (not MetaWorld's own): the goal marker is a cue shown for the first CUE_STEPS steps of
# an episode, then hidden, so the goal must be remembered (see the module docstring).
CUE_PREFIX = "metaworld-cue/"
CUE_TASKS = ("reach", "push", "pick-place")  # tasks whose goal is only a marker (no object shows it)
CUE_STEPS = 10
CUE_RADIUS_M = 0.04
HIDDEN_RADIUS_M = 1e-6
INSTALL = "pip install --no-deps metaworld==3.1.1, with the sim extra (its gymnasium, imageio and scipy): pip install -e '.[sim]'"

# The difficulty groups DP3 and the papers after it report MetaWorld by (Seo et al., 2022): all 50 tasks.
DIFFICULTY: dict[str, tuple[str, ...]] = {
    "easy": (
        "button-press",
        "button-press-topdown",
        "button-press-topdown-wall",
        "button-press-wall",
        "coffee-button",
        "dial-turn",
        "door-close",
        "door-lock",
        "door-open",
        "door-unlock",
        "drawer-close",
        "drawer-open",
        "faucet-close",
        "faucet-open",
        "handle-press",
        "handle-press-side",
        "handle-pull",
        "handle-pull-side",
        "lever-pull",
        "plate-slide",
        "plate-slide-back",
        "plate-slide-back-side",
        "plate-slide-side",
        "reach",
        "reach-wall",
        "window-close",
        "window-open",
        "peg-unplug-side",
    ),
    "medium": (
        "basketball",
        "bin-picking",
        "box-close",
        "coffee-pull",
        "coffee-push",
        "hammer",
        "peg-insert-side",
        "push-wall",
        "soccer",
        "sweep",
        "sweep-into",
    ),
    "hard": ("assembly", "hand-insert", "pick-out-of-hole", "pick-place", "push", "push-back"),
    "very_hard": ("shelf-place", "disassemble", "stick-pull", "stick-push", "pick-place-wall"),
}
TASKS: tuple[str, ...] = tuple(t for group in DIFFICULTY.values() for t in group)

EPISODE_STEPS = 200
DEMO_SUCCESS_STEPS = 5
N_POINTS = 512
RENDER_SIZE = (128, 128)  # (H, W)
CAMERA = "corner2"
CAMERA_POS = (0.6, 0.295, 0.8)
DEPTH_UNIT = 0.00025  # m per raw depth unit, as the Piper simulation's camera
DEPTH_FAR_M = 1.5
CROP_MIN = (-0.5, -1.5, -0.795)
CROP_MAX = (1.0, -0.4, 100.0)
FRAME = "dp3_metaworld: DP3's MetaWorld cloud frame (the corner2 camera at the origin, rotated as DP3's wrapper does)"
STATE_CHANNELS = (
    "hand x m",
    "hand y m",
    "hand z m",
    "right finger x m",
    "right finger y m",
    "right finger z m",
    "left finger x m",
    "left finger y m",
    "left finger z m",
)
ACTION_CHANNELS = ("dx 0.01 m", "dy 0.01 m", "dz 0.01 m", "gripper effort -1..1")


def _dp3_rotation() -> np.ndarray:
    """DP3's ``pc_transform``: its two matrices as it writes them (x by 61.4°, then y by -7°)."""
    a, b = math.radians(61.4), math.radians(-7.0)
    rx = np.array([[1, 0, 0], [0, math.cos(a), math.sin(a)], [0, -math.sin(a), math.cos(a)]])
    ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    return rx @ ry


# Optical frame (x right, y down, z forward) to DP3's cloud frame: camera 0's rotation (the identity) times the 180°
# turn about x DP3 applies, then its pc_transform.
CAMERA_TO_CLOUD = np.eye(4)
CAMERA_TO_CLOUD[:3, :3] = _dp3_rotation() @ np.diag([1.0, -1.0, -1.0])


def is_metaworld(task: str) -> bool:
    """``metaworld/NAME`` or the memory variant ``metaworld-cue/NAME``."""
    return isinstance(task, str) and task.startswith((PREFIX, CUE_PREFIX))


def is_cue(task: str) -> bool:
    return isinstance(task, str) and task.startswith(CUE_PREFIX)


def task_name(task: str) -> str:
    """``metaworld/door-open`` -> ``door-open`` (``metaworld-cue/reach`` -> ``reach``); an unknown task is a
    one-line ConfigError."""
    if is_cue(task):
        name = task[len(CUE_PREFIX) :]
        if name not in CUE_TASKS:
            raise ConfigError(
                f"unknown MetaWorld cue task {name!r}; choose one of {', '.join(CUE_TASKS)} (as {CUE_PREFIX}NAME)"
            )
        return name
    name = task[len(PREFIX) :] if is_metaworld(task) else task
    if name not in TASKS:
        raise ConfigError(f"unknown MetaWorld task {name!r}; choose one of {', '.join(TASKS)} (as metaworld/NAME)")
    return name


def task_id(task: str) -> str:
    """The canonical id: ``metaworld/NAME`` or ``metaworld-cue/NAME`` (a bare name is MetaWorld's own task)."""
    return (CUE_PREFIX if is_cue(task) else PREFIX) + task_name(task)


def tasks_of(selection: list[str]) -> list[str]:
    """Task names from names and groups (``easy``, ``medium``, ``hard``, ``very_hard``, ``all``), in order, once each."""
    out: list[str] = []
    for item in selection:
        names = TASKS if item == "all" else DIFFICULTY.get(item) or (task_name(item),)
        out.extend(n for n in names if n not in out)
    return out


def difficulty_of(name: str) -> str:
    return next(group for group, names in DIFFICULTY.items() if name in names)


def check_model_dims(contract: ModelContract, where) -> None:
    """Refuse, before any episode, a model whose state or action is not MetaWorld's (9,) and (4,)."""
    have = (contract.state_dim, contract.action_dim)
    if have != (len(STATE_CHANNELS), len(ACTION_CHANNELS)):
        raise ConfigError(
            f"{where} takes state ({have[0]},) and action ({have[1]},); MetaWorld's are (9,) and (4,): "
            "evaluate a model trained on a `dssp-sim collect --task metaworld/NAME` dataset"
        )


def cloud_config(n_points: int | None = None) -> PointCloudConfig:
    """DP3's MetaWorld clouds: its crop in its frame, every cropped point, farthest point sampling."""
    return PointCloudConfig(
        n_points=n_points or N_POINTS,
        depth_near=0.01,
        depth_far=DEPTH_FAR_M,
        crop_min=CROP_MIN,
        crop_max=CROP_MAX,
        voxel_size=0.0,
        sampling="fps",
    )


def _import_metaworld():
    try:
        import metaworld  # deferred: loads gymnasium, imageio, metaworld, …
        import metaworld.policies  # deferred: loads gymnasium, imageio, metaworld, …
    except ImportError as e:
        raise ConfigError(f"MetaWorld is not installed ({e}); install it with: {INSTALL}") from None
    _patch_mocap_welds()
    return metaworld


_patched = threading.Lock()


def _patch_mocap_welds() -> None:
    """On a MuJoCo whose weld rows hold 12 numbers, metaworld's 11 get the 12th (0: the relative pose is given)."""
    import metaworld.sawyer_xyz_env as sawyer  # optional: metaworld (make setup); only _import_metaworld calls this

    with _patched:
        base = sawyer.SawyerMocapBase
        if getattr(base.reset_mocap_welds, "dssp_weld_row", False) or mujoco.mjNEQDATA == 11:
            return
        original = base.reset_mocap_welds

        def reset_mocap_welds(self) -> None:
            if self.model.nmocap > 0 and self.model.eq_data is not None:
                for i in range(self.model.eq_data.shape[0]):
                    if self.model.eq_type[i] == mujoco.mjtEq.mjEQ_WELD:
                        row = np.zeros(self.model.eq_data.shape[1])
                        row[:11] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 5.0)
                        self.model.eq_data[i] = row

        reset_mocap_welds.dssp_weld_row = True
        reset_mocap_welds.original = original
        base.reset_mocap_welds = reset_mocap_welds


class MetaWorldEnv:
    """One MetaWorld v3 task (``task``: ``"door-open"``, ``"metaworld/door-open"`` or the memory variant
    ``"metaworld-cue/reach"``), its scene drawn from ``seed`` at each ``reset``.

    success_steps: steps with the task's success flag set that make the episode a success (1 for evaluation,
    :data:`DEMO_SUCCESS_STEPS` for demonstrations); stop_on_success: end the episode once it is one."""

    def __init__(
        self,
        task: str,
        seed: int = 0,
        success_steps: int = 1,
        stop_on_success: bool = True,
        render_size: tuple[int, int] = RENDER_SIZE,
    ):
        metaworld = _import_metaworld()
        self.task, self.name = task_id(task), task_name(task)
        self.cue_steps = CUE_STEPS if is_cue(task) else None
        self.success_steps, self.stop_on_success = int(success_steps), bool(stop_on_success)
        self.render_size = tuple(render_size)
        cls = metaworld.env_dict.ALL_V3_ENVIRONMENTS_GOAL_OBSERVABLE[f"{self.name}-v3-goal-observable"]
        self.env = cls(seed=seed)
        self.model, self.data = self.env.model, self.env.data
        self._camera_id = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, CAMERA)
        self.model.cam_pos[self._camera_id] = CAMERA_POS
        self.control_rate_hz = 1.0 / (self.env.frame_skip * float(self.model.opt.timestep))
        self._goal_site = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, "goal")
        self.lock = threading.RLock()
        self._renders = CameraRenders(self, self.model, self.render_size, self._camera_id)
        self.reset(seed)

    # ------------------------------------------------------------------------------------------- episode
    def reset(self, seed: int) -> None:
        """A new scene drawn from ``seed`` (MetaWorld's random object and goal positions)."""
        with self.lock:
            self.seed = int(seed)
            self.env.seed(self.seed)
            self.env._freeze_rand_vec = False  # draw the scene from the env's generator, seeded just above
            self.env.seeded_rand_vec = True
            self.obs, _ = self.env.reset()
            if self.cue_steps is not None:
                self._show_cue(True)
            mujoco.mj_forward(self.model, self.data)
            self.steps = 0
            self.gripper_effort = -1.0  # open, as MetaWorld's reset leaves the hand
            self.succeeded = 0
            self.first_success: int | None = None

    def state(self) -> np.ndarray:
        """(9,) [hand xyz, right fingertip xyz, left fingertip xyz] m."""
        with self.lock:
            return np.concatenate(
                [
                    self.env.get_endeff_pos(),
                    self.env._get_site_pos("rightEndEffector"),
                    self.env._get_site_pos("leftEndEffector"),
                ]
            ).astype(np.float32)

    def step(self, action) -> None:
        """One policy step: MetaWorld's step (its 5 physics steps) with ``action`` (4,)."""
        action = np.asarray(action, np.float64).reshape(4)
        with self.lock:
            self.obs, _, _, _, info = self.env.step(np.clip(action, -1.0, 1.0))
            self.gripper_effort = float(np.clip(action[3], -1.0, 1.0))
            self.steps += 1
            if self.cue_steps is not None and self.steps >= self.cue_steps:
                self._show_cue(False)
            if info.get("success"):
                self.succeeded += 1
                if self.first_success is None:
                    self.first_success = self.steps

    def _show_cue(self, shown: bool) -> None:
        """The goal marker as the cue: a sphere of :data:`CUE_RADIUS_M`, or too small to render (its position stays
        the task's: MetaWorld's reward checks it)."""
        self.model.site_size[self._goal_site] = CUE_RADIUS_M if shown else HIDDEN_RADIUS_M

    def cue_shown(self) -> bool:
        return self.cue_steps is not None and self.steps < self.cue_steps

    def hold(self) -> None:
        """One step that stays: no hand displacement, the gripper effort of the last step."""
        self.step(np.array([0.0, 0.0, 0.0, self.gripper_effort]))

    def status(self) -> TaskStatus:
        with self.lock:
            success = self.succeeded >= self.success_steps
            done = self.steps >= EPISODE_STEPS or (success and self.stop_on_success)
            info = {"success_steps": self.succeeded, "first_success_step": self.first_success}
            if self.cue_steps is not None:
                info["cue_steps"] = self.cue_steps
            return TaskStatus(
                done=done, success=done and success, reason="" if success or not done else "timeout", info=info
            )

    # ------------------------------------------------------------------------------------------- camera
    def intrinsics(self) -> Intrinsics:
        h, w = self.render_size
        f = 0.5 * h / math.tan(math.radians(float(self.model.cam_fovy[self._camera_id])) / 2.0)
        return Intrinsics(width=w, height=h, fx=f, fy=f, ppx=(w - 1) / 2.0, ppy=(h - 1) / 2.0)

    def render_depth(self) -> tuple[np.ndarray, float, Intrinsics, np.ndarray]:
        """(depth (H, W) uint16 raw, depth unit m, intrinsics, camera pose (4, 4) in DP3's cloud frame)."""
        with self.lock:
            metres = self._renders.render(self.data)
        valid = (metres > 0) & (metres <= DEPTH_FAR_M)
        raw = np.where(valid, np.rint(metres / DEPTH_UNIT), 0.0).astype(np.uint16)
        return raw, DEPTH_UNIT, self.intrinsics(), CAMERA_TO_CLOUD.copy()

    def close(self) -> None:
        self._renders.close()

    def __enter__(self) -> "MetaWorldEnv":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class MetaWorldExpert:
    """MetaWorld's scripted policy for the env's task; ``act(env)`` -> action (4,) from the env's full observation."""

    def __init__(self, env: MetaWorldEnv):
        from metaworld.policies import ENV_POLICY_MAP  # deferred: loads gymnasium, imageio, metaworld, …

        self.policy = ENV_POLICY_MAP[f"{env.name}-v3"]()

    def act(self, env: MetaWorldEnv) -> np.ndarray:
        with warnings.catch_warnings():  # "Constant(s) may be too high": MetaWorld clips the action itself
            warnings.simplefilter("ignore", UserWarning)
            return np.asarray(self.policy.get_action(env.obs), np.float32)


def dataset_attrs(env: MetaWorldEnv, camera, config: PointCloudConfig) -> dict:
    """Dataset attributes of MetaWorld demonstrations: what the clouds, state and action are."""
    import metaworld  # deferred: loads gymnasium, imageio, metaworld, …

    return {
        "control_rate_hz": float(env.control_rate_hz),
        "task": env.task,
        "generator": "dssp_sim.collect",
        "benchmark": {
            "name": "metaworld",
            "version": getattr(metaworld, "__version__", "3.1.1"),
            "task": f"{env.name}-v3",
            "difficulty": difficulty_of(env.name),
            "protocol": "DP3",
            "episode_steps": EPISODE_STEPS,
            "demo_success_steps": DEMO_SUCCESS_STEPS,
            **(
                {
                    "variant": f"this project's memory variant: the goal marker, a {CUE_RADIUS_M * 100:.0f} cm "
                    f"sphere, is shown for the first {env.cue_steps} steps, then hidden",
                    "cue_steps": env.cue_steps,
                }
                if env.cue_steps is not None
                else {}
            ),
        },
        "action_convention": "the scripted expert's action as DP3 stores it: hand displacement in 1/100 m and gripper "
        "effort, unclipped (MetaWorld clips it to [-1, 1] when it steps)",
        "state_convention": "measured [hand xyz, right fingertip xyz, left fingertip xyz] m (DP3's agent_pos)",
        **ObservationContract(
            pointcloud=config,
            frame=FRAME,
            state=VectorLayout(arms=1, channels=STATE_CHANNELS),
            action=VectorLayout(arms=1, channels=ACTION_CHANNELS),
        ).attrs(),
        "camera_intrinsics": camera.intrinsics.to_dict(),
        "camera_depth_unit": float(camera.depth_unit),
        "camera_to_base": camera.camera_to_base.tolist(),
    }
