"""The hand-eye calibration's twin: a ChArUco board and a camera at known poses in the MuJoCo Piper workcell.

What ``dssp-sim calibrate`` (``dssp-calibrate`` on the twin) calibrates, with no hardware:

- **eye-to-hand**: the workcell's fixed camera (``dssp_sim.mjcf.CAMERA_*``, the one the tasks' depth comes from)
  and the board fixed to the flange, its printed face along the approach axis, just beyond the fingertips;
- **eye-in-hand**: a camera on the wrist (``WRIST_CAMERA_*``: on the flange, looking along the approach axis,
  tilted away from the fingers) and the board lying face up on the table.

The board's texture is made at run time by OpenCV from the same :class:`~hardware.calibration.charuco.CharucoBoardSpec`
the detection uses (``board_image``), put on a thin mesh whose texture coordinates map it to the board's exact size;
no image is stored. The renders are RGB at ``size`` (default 640 x 480) with the camera's exact pinhole intrinsics.

The arm moves as in :mod:`dssp_sim.evaluate`: Piper CAN frames on a python-can ``virtual`` bus to
:class:`~dssp_sim.mujoco_arm.MujocoPiper`, through the driver (``PiperRobot``) and the control loop's safety layer.
Time is simulated: :class:`TwinClock`'s ``sleep(dt)`` advances the physics ``dt`` and waits for the arm's feedback,
so the loop's pacing drives the simulation in lockstep; :class:`TwinCamera` renders when asked for a frame after the
simulation moved (a render per pose, not per tick). The start pose (found by IK) shows the board to the camera; the
true transform (``camera_to_base`` or ``camera_to_gripper``) is read from the model for comparison.
"""

from __future__ import annotations

import math
import threading
import time
import uuid
from dataclasses import replace

import mujoco
import numpy as np

from dssp_data.arm_kinematics import TCP_OFFSET
from dssp_data.pointcloud.depth_frame import DepthFrame, Intrinsics
from dssp_sim.env import DEPTH_UNIT, ArmServos
from dssp_sim.ik import IKSolver
from dssp_sim.mjcf import CAMERA_FOVY_DEG, CAMERA_NAME, CAMERA_POS, ArmIndex, arm_xml, fmt, mat_to_quat, scene_xml
from dssp_sim.mujoco_arm import MujocoPiper
from dssp_sim.render import CameraRenders
from dssp_sim.tasks import HOME
from hardware.calibration.charuco import CharucoBoardSpec, board_image
from hardware.calibration.hand_eye import EYE_TO_HAND, MODES, invert
from hardware.camera.base import Camera
from hardware.camera.software import SoftwareDepthCamera
from hardware.cli import calibrate
from hardware.clock import FakeClock
from hardware.piper.arm import PiperArm
from hardware.piper.limits import GRIPPER_STROKE_MIN
from hardware.piper.piper_robot import PiperRobot

SIZE = (480, 640)  # (H, W) of the renders: what ChArUco detection needs at these distances
BOARD_STANDOFF = 0.115  # m from the flange along the approach axis to the board (just beyond the fingertips, 0.11)
BOARD_THICKNESS = 0.003  # m
BOARD_MARGIN = 0.5  # white border around the squares, in squares (as a printed board has)
PX_PER_SQUARE = 96  # texture resolution

# The wrist camera in the flange frame (link6, DH frame 6): behind the palm, looking along the approach axis tilted
# 10 degrees away from the fingers so they stay out of view; the workcell camera's field of view.
WRIST_CAMERA_NAME = "wrist_cam"
WRIST_CAMERA_POS = (-0.06, 0.0, 0.03)
WRIST_CAMERA_TILT_DEG = -10.0

# Where the board is at the start pose: in front of the fixed camera (eye-to-hand), on the table (eye-in-hand).
EYE_TO_HAND_BOARD = (0.5, 0.0, 0.25)
EYE_TO_HAND_TILT_DEG = 30.0  # the board faces this far below the camera (facing it squarely, J5 is at its limit)
TABLE_BOARD = (0.45, 0.0, 0.0)
WRIST_HEIGHT = 0.25  # m above the table board of the wrist camera at the start pose
WRIST_PITCH_DEG = (
    30.0  # the approach axis at the start pose: down, tilted forward (pointing straight down, J5 is at its limit)
)

OPTICAL_IN_MJCAM = np.diag([1.0, -1.0, -1.0])  # optical frame (x right, y down, z forward) in MuJoCo's camera frame


def _rot_y(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def board_assets(board: CharucoBoardSpec) -> tuple[str, np.ndarray]:
    """(MJCF assets, texture (H, W, 3) uint8): the board's texture and a thin mesh in the board's own frame (OpenCV's:
    origin at the squares' top-left corner, x along the rows, y down the columns, the printed face towards -z)."""
    image = board_image(board, PX_PER_SQUARE, BOARD_MARGIN)
    m = BOARD_MARGIN * board.square_m
    w, h = board.size_m
    x0, x1, y0, y1, z = -m, w + m, -m, h + m, BOARD_THICKNESS
    # front face (z = 0, seen from -z) then the back face; texture row 0 is the board's top (y = y0).
    vertex = [x0, y0, 0, x1, y0, 0, x1, y1, 0, x0, y1, 0, x0, y0, z, x1, y0, z, x1, y1, z, x0, y1, z]
    texcoord = [0, 0, 1, 0, 1, 1, 0, 1] * 2
    face = [0, 2, 1, 0, 3, 2, 4, 5, 6, 4, 6, 7, 0, 1, 5, 0, 5, 4, 1, 2, 6, 1, 6, 5, 2, 3, 7, 2, 7, 6, 3, 0, 4, 3, 4, 7]
    assets = (
        f'<texture name="charuco" type="2d" builtin="flat" width="{image.shape[1]}" height="{image.shape[0]}" '
        'rgb1="1 1 1"/>'
        '<material name="charuco" texture="charuco" specular="0" shininess="0"/>'
        f'<mesh name="charuco" vertex="{fmt(vertex)}" texcoord="{fmt(texcoord)}" face="{fmt(face)}"/>'
    )
    return assets, np.repeat(image[:, :, None], 3, axis=2)


def _board_body(pos, rot) -> str:
    return (
        f'<body name="charuco" pos="{fmt(pos)}" quat="{fmt(mat_to_quat(rot))}">'
        '<geom name="charuco" type="mesh" mesh="charuco" material="charuco" contype="0" conaffinity="0" '
        'mass="0.02"/></body>'
    )


def twin_xml(mode: str, board: CharucoBoardSpec) -> tuple[str, np.ndarray]:
    """(the scene's MJCF, the board's texture) for ``mode``."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    assets, texture = board_assets(board)
    centre = board.centre
    if mode == EYE_TO_HAND:
        # On the flange: the board's z (into the board) against the approach axis, so its face looks outwards.
        rot = np.diag([1.0, -1.0, -1.0])
        flange = _board_body(np.array([0.0, 0.0, BOARD_STANDOFF]) - rot @ centre, rot)
        objects = ""
    else:
        opt = _rot_y(WRIST_CAMERA_TILT_DEG)  # optical frame in the flange frame
        mj = opt @ OPTICAL_IN_MJCAM  # MuJoCo's camera frame: x, y columns
        flange = (
            f'<camera name="{WRIST_CAMERA_NAME}" pos="{fmt(WRIST_CAMERA_POS)}" '
            f'xyaxes="{fmt(np.concatenate([mj[:, 0], mj[:, 1]]))}" fovy="{CAMERA_FOVY_DEG:.9g}"/>'
        )
        rot = np.diag([1.0, -1.0, -1.0])  # face up: the board's z points down into the table
        objects = _board_body(np.array(TABLE_BOARD) + [0.0, 0.0, BOARD_THICKNESS + 1e-4] - rot @ centre, rot)
    xml = scene_xml(objects, arms=(arm_xml(flange_xml=flange),), assets=assets)
    return xml, texture


class CalibrationTwin(ArmServos):
    """The calibration scene of ``mode`` with ``board``: a MuJoCo model, its arm at a start pose that shows the board
    to the camera, and the low-level interface :class:`~dssp_sim.mujoco_arm.MujocoPiper` drives (``set_targets``,
    ``advance``, ``joint_positions``, ``gripper_stroke``). ``size``: (H, W) of the renders."""

    def __init__(self, mode: str, board: CharucoBoardSpec = CharucoBoardSpec(), size: tuple[int, int] = SIZE) -> None:
        self.mode, self.board, self.size = mode, board, (int(size[0]), int(size[1]))
        xml, texture = twin_xml(mode, board)
        self.model = mujoco.MjModel.from_xml_string(xml)
        self.model.vis.global_.offwidth = max(self.model.vis.global_.offwidth, self.size[1])
        self.model.vis.global_.offheight = max(self.model.vis.global_.offheight, self.size[0])
        tex = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_TEXTURE, "charuco")
        adr = self.model.tex_adr[tex]
        self.model.tex_data[adr : adr + texture.size] = texture.reshape(-1)
        self.data = mujoco.MjData(self.model)
        self.arm = ArmIndex.find(self.model)
        self.lock = threading.RLock()
        self._time_debt = 0.0
        self.camera_id = mujoco.mj_name2id(
            self.model, mujoco.mjtObj.mjOBJ_CAMERA, CAMERA_NAME if mode == EYE_TO_HAND else WRIST_CAMERA_NAME
        )
        self.board_body = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, "charuco")
        self.flange_body = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, "link6")
        self._renders = CameraRenders(self, self.model, self.size, self.camera_id)
        start = self.start_pose()
        self.data.qpos[self.arm.qpos] = start
        self.set_targets(start, GRIPPER_STROKE_MIN)
        mujoco.mj_forward(self.model, self.data)

    # ------------------------------------------------------------------------------------------- the start pose
    def start_pose(self) -> np.ndarray:
        """(6,) rad: the joints (by IK from HOME) at which the camera sees the whole board."""
        if self.mode == EYE_TO_HAND:
            board = np.array(EYE_TO_HAND_BOARD)
            y = np.array([0.0, 1.0, 0.0])
            z = np.array(CAMERA_POS) - board
            z /= np.linalg.norm(z)
            a = math.radians(EYE_TO_HAND_TILT_DEG)
            z = math.cos(a) * z + math.sin(a) * np.cross(y, z)  # turned down about y
            x = np.cross(y, z)
            rot = np.column_stack([x, y, z])
            tcp = board - (BOARD_STANDOFF - TCP_OFFSET) * z
        else:
            # The approach axis down and WRIST_PITCH_DEG forward, the flange's x backwards and up: the camera (at -x
            # of the flange, tilted towards -x of the flange) looks forward and down at the board from WRIST_HEIGHT.
            a = math.radians(WRIST_PITCH_DEG)
            rot = np.column_stack(
                [[-math.cos(a), 0.0, -math.sin(a)], [0.0, 1.0, 0.0], [math.sin(a), 0.0, -math.cos(a)]]
            )
            opt = rot @ _rot_y(WRIST_CAMERA_TILT_DEG)
            cam_offset = rot @ np.array(WRIST_CAMERA_POS)
            cam = np.array(TABLE_BOARD) - opt[:, 2] * (WRIST_HEIGHT / -opt[2, 2])  # its axis through the board
            flange = cam - cam_offset
            tcp = flange + TCP_OFFSET * rot[:, 2]
        solver = IKSolver(self.model)
        q = solver.solve(tcp, rot, seed=HOME)
        if solver.last_error[0] > 1e-3 or solver.last_error[1] > 1e-2:
            raise RuntimeError(f"the twin's start pose is out of reach (IK error {solver.last_error})")
        return q

    # ------------------------------------------------------------------------------------------- what MujocoPiper drives
    def advance(self, dt: float) -> None:
        with self.lock:
            n = self._whole_steps(dt)
            if n > 0:
                mujoco.mj_step(self.model, self.data, nstep=n)

    # ------------------------------------------------------------------------------------------- poses and renders
    def _pose(self, xpos, xmat) -> np.ndarray:
        t = np.eye(4)
        t[:3, :3], t[:3, 3] = np.asarray(xmat).reshape(3, 3), xpos
        return t

    def camera_to_base(self) -> np.ndarray:
        """(4, 4) the camera's optical frame in the base frame, now."""
        with self.lock:
            t = self._pose(self.data.cam_xpos[self.camera_id], self.data.cam_xmat[self.camera_id])
        t[:3, :3] = t[:3, :3] @ OPTICAL_IN_MJCAM
        return t

    def flange_to_base(self) -> np.ndarray:
        with self.lock:
            return self._pose(self.data.xpos[self.flange_body], self.data.xmat[self.flange_body])

    def truth(self) -> np.ndarray:
        """The transform the calibration must recover: camera_to_base (eye-to-hand; fixed) or camera_to_gripper
        (eye-in-hand; the camera in the flange frame)."""
        if self.mode == EYE_TO_HAND:
            return self.camera_to_base()
        return invert(self.flange_to_base()) @ self.camera_to_base()

    def intrinsics(self) -> Intrinsics:
        """Pinhole intrinsics of the renders (as ``PiperEnv.intrinsics``: square pixels from the vertical field of
        view, the principal point at the image centre)."""
        h, w = self.size
        f = 0.5 * h / math.tan(math.radians(float(self.model.cam_fovy[self.camera_id])) / 2.0)
        return Intrinsics(width=w, height=h, fx=f, fy=f, ppx=(w - 1) / 2.0, ppy=(h - 1) / 2.0)

    def _render(self, depth: bool) -> np.ndarray:
        with self.lock:
            return self._renders.render(self.data, depth)

    def render_rgb(self) -> np.ndarray:
        """(H, W, 3) uint8 RGB from the calibration camera, now."""
        return np.ascontiguousarray(self._render(False))

    def render_depth(self) -> np.ndarray:
        """(H, W) uint16 depth in units of ``DEPTH_UNIT`` (0 where nothing is hit), now."""
        metres = self._render(True)
        return np.where(metres > 0, np.rint(metres / DEPTH_UNIT), 0).clip(0, 65535).astype(np.uint16)

    def close(self) -> None:
        self._renders.close()


class TwinClock(FakeClock):
    """Simulated time that drives the twin: ``sleep(dt)`` steps the MuJoCo Piper ``dt`` (it handles the commands
    received, moves and sends its feedback) and returns once the driver has that feedback."""

    def __init__(self, arm: MujocoPiper, robot: PiperRobot) -> None:
        super().__init__()
        self.arm, self.robot = arm, robot

    def sleep(self, dt: float) -> None:
        if dt <= 0:
            return
        self.t += float(dt)
        self.arm.step(float(dt))
        deadline = time.monotonic() + 2.0
        while True:  # the driver's receive thread stamps the feedback on this clock: wait until it is this step's
            state = self.robot.state()
            if (state is not None and state.timestamp >= self.t) or time.monotonic() > deadline:
                return  # (late feedback is the loop's to notice: it holds on stale feedback)
            time.sleep(0.0002)


class TwinCamera(Camera):
    """The calibration camera of a :class:`CalibrationTwin` as a :class:`~hardware.camera.base.Camera` with colour:
    depth and RGB go through the RealSense software device (the live camera's conversion code); ``latest()``
    renders when the simulated time moved since the last frame, stamped on ``clock``."""

    name = "mujoco"

    def __init__(self, twin: CalibrationTwin, clock: FakeClock) -> None:
        self.twin, self.clock = twin, clock
        self._device: SoftwareDepthCamera | None = None
        self._latest: DepthFrame | None = None
        self._number = 0

    def start(self) -> None:
        if self._device is None:
            self._device = SoftwareDepthCamera(self.twin.intrinsics(), DEPTH_UNIT, color=True)
            self._device.start()

    def latest(self) -> DepthFrame | None:
        if self._device is None:
            return None
        now = self.clock.now()
        if self._latest is None or self._latest.timestamp != now:
            frame = self._device.push(self.twin.render_depth(), self.twin.render_rgb(), frame_number=self._number)
            self._latest = replace(frame, timestamp=now)
            self._number += 1
        return self._latest

    def stop(self) -> None:
        if self._device is not None:
            self._device.stop()
            self._device = None


class TwinRig:
    """The twin as ``dssp-calibrate`` opens it: ``camera`` (:class:`TwinCamera`), ``robot`` (a ``PiperRobot`` on a
    virtual bus to the MuJoCo Piper), ``clock`` (:class:`TwinClock`), ``truth()``; ``close()`` ends it."""

    def __init__(self, mode: str, board: CharucoBoardSpec, size: tuple[int, int] = SIZE) -> None:
        self.twin = CalibrationTwin(mode, board, size)
        channel = f"dssp-calib-{uuid.uuid4().hex[:8]}"
        self.arm = MujocoPiper(self.twin, channel)
        self.arm.start(thread=False)
        self.robot = PiperRobot([PiperArm(channel, "virtual")])
        self.clock = TwinClock(self.arm, self.robot)
        self.robot.arms[0].clock = self.clock
        self.camera = TwinCamera(self.twin, self.clock)
        self.description = f"the MuJoCo twin ({mode}, its camera {'fixed' if mode == EYE_TO_HAND else 'on the wrist'})"

    def truth(self) -> np.ndarray:
        return self.twin.truth()

    def close(self) -> None:
        self.arm.stop()
        self.twin.close()


class TwinRigs:
    """The twin as ``dssp-calibrate``'s simulated rig (:class:`hardware.cli.calibrate.SimulatedCalibrationRig`)."""

    def __init__(self, size: tuple[int, int] = SIZE) -> None:
        self.size = size

    def open(self, mode: str, board: CharucoBoardSpec) -> TwinRig:
        return TwinRig(mode, board, self.size)


def calibrate_main(argv: list[str] | None = None) -> int:
    """``dssp-sim calibrate``: ``dssp-calibrate`` on the twin (``--camera mujoco --can mujoco`` by default)."""
    return calibrate.main(argv, sim=TwinRigs(), prog="dssp-sim calibrate")
