"""The MuJoCo model of the simulated Piper workcell, generated as an MJCF string in code.

Frames and units: metres, radians; the robot-base frame is the world frame (x forward, y left, z up) and
the table top is the plane z = 0. One Piper arm stands at the origin; the task adds its objects
(``dssp_sim.tasks``) and a fixed depth camera looks at the workspace from the front, above the far edge
of the table.

The arm follows the modified Denavit-Hartenberg table of the Piper SDK (``kinematics/piper_fk.py``, kept in
:mod:`dssp_data.arm_kinematics`; the
variant with the 2-degree J2/J3 offsets): body ``link{i}`` is DH frame i, so ``link6`` is the flange.
Six hinge joints carry the limits of ``hardware.piper.limits``; six position actuators (with velocity
feedback ``kv``) drive them, and gravity compensation of the links stands in for the Piper's own. The
gripper is a hand on the flange with two fingers on slide joints along the flange's y axis, kept
symmetric by an equality constraint and driven by one position actuator on their summed travel: the
stroke, 0..``GRIPPER_STROKE_MAX`` (0.07 m) between the finger pads, with the grip force limited to
``GRIP_FORCE_MAX``. Grasping is by friction only (elliptic cones, high ``impratio``, torsional friction on
the pads, multi-point convex contacts); no weld constraint is used.

Collision groups: the links are visual only (they render in the depth camera but do not collide), the
hand and fingers collide with the table and every task object, task objects collide with each other.

Two arms (the 14-value platform) need only a second ``arm_xml(prefix="right_", base_pos=...)`` passed to
``scene_xml``: every name of an arm carries its prefix.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

from dssp_data.arm_kinematics import TCP_OFFSET, dh_link_transform  # the arm's DH table and tool centre point
from hardware.piper.limits import GRIPPER_STROKE_MAX, JOINT_LOWER, JOINT_UPPER

# The gripper on the flange (link6 frame, z = approach direction, fingers slide along +-y).
HAND_LENGTH = 0.045  # flange to the base of the fingers
FINGER_LENGTH = 0.065
FINGER_THICKNESS = 0.008  # along the slide axis
FINGER_WIDTH = 0.02  # across the slide axis
FINGERTIP_BELOW_TCP = HAND_LENGTH + FINGER_LENGTH - TCP_OFFSET  # 0.012 m

# Servo gains (SI): joints (N m / rad, N m s / rad), gripper (N / m, N s / m) and grip force limit (N).
JOINT_KP = (900.0, 900.0, 700.0, 250.0, 250.0, 150.0)
JOINT_KV = (60.0, 60.0, 45.0, 12.0, 12.0, 6.0)
JOINT_ARMATURE = (0.1, 0.1, 0.08, 0.02, 0.02, 0.01)
GRIPPER_KP = 1500.0
GRIPPER_KV = 5.0
GRIP_FORCE_MAX = 25.0

# The depth camera (L515-like: 70 deg horizontal field of view at 4:3, so the vertical one follows).
CAMERA_NAME = "depth_cam"
CAMERA_POS = (0.95, 0.0, 0.50)
CAMERA_TARGET = (0.30, 0.0, 0.05)
CAMERA_HFOV_DEG = 70.0
CAMERA_ASPECT = 4.0 / 3.0
CAMERA_FOVY_DEG = math.degrees(2.0 * math.atan(math.tan(math.radians(CAMERA_HFOV_DEG) / 2.0) / CAMERA_ASPECT))

TIMESTEP = 0.002  # s, physics step

# Table: top at z = 0.
TABLE_HALF = (0.55, 0.6, 0.025)
TABLE_CENTER = (0.30, 0.0, -0.025)

# contype/conaffinity bits: scene objects (1), gripper (2).
SCENE_BIT = 1
GRIPPER_BIT = 2


def fmt(values) -> str:
    """Numbers as an MJCF attribute value (any shape, flattened)."""
    return " ".join(f"{float(v):.9g}" for v in np.ravel(values))


def mat_to_quat(mat: np.ndarray) -> np.ndarray:
    """(3, 3) rotation matrix -> (4,) unit quaternion (w, x, y, z)."""
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.asarray(mat, dtype=np.float64).reshape(-1))
    return q


def camera_xyaxes(pos=CAMERA_POS, target=CAMERA_TARGET) -> np.ndarray:
    """(6,) MJCF ``xyaxes`` of a camera at ``pos`` looking at ``target`` with the world z axis up."""
    z = np.asarray(pos, float) - np.asarray(target, float)
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.concatenate([x, y])


@dataclass(frozen=True)
class ArmXml:
    """MJCF fragments of one arm: ``body`` goes into <worldbody>, the rest into their sections."""

    prefix: str
    body: str
    actuator: str
    tendon: str
    equality: str
    contact: str


def arm_xml(prefix: str = "", base_pos=(0.0, 0.0, 0.0), base_quat=(1.0, 0.0, 0.0, 0.0), flange_xml: str = "") -> ArmXml:
    """One Piper arm with every name prefixed by ``prefix``, its base at ``base_pos`` (3,) m with
        orientation ``base_quat`` (4,) (w, x, y, z) in the world. ``flange_xml``: bodies, sites or cameras fixed to
        the flange (MJCF in the ``link6`` body's frame, DH frame 6; the calibration twin's board or wrist camera).

        Names: joints ``{p}joint1..6``, ``{p}finger_left/right``; actuators ``{p}act1..6``, ``{p}gripper``
        (control = stroke in metres); sites ``{p}tcp`` (tool centre point: z = approach, y = finger axis)
    ; bodies ``{p}base``, ``{p}link1..6``, ``{p}hand``, ``{p}finger_left/right``.
    """
    p = prefix
    link_geom = 'contype="0" conaffinity="0" group="0" rgba="0.75 0.75 0.78 1"'
    # Visual link shapes per body, in the body's own frame (DH frame i).
    child_pos = [dh_link_transform(i)[0] for i in range(1, 6)] + [np.zeros(3)]
    link_shapes = {
        1: f'<geom type="cylinder" size="0.045 0.03" pos="0 0 -0.02" mass="0.8" {link_geom}/>',
        2: (
            f'<geom type="capsule" fromto="0 0 0 {fmt(child_pos[1])}" size="0.032" mass="1.0" {link_geom}/>'
            f'<geom type="cylinder" fromto="0 0 -0.045 0 0 0.045" size="0.04" mass="0.2" {link_geom}/>'
        ),
        3: (
            f'<geom type="capsule" fromto="0 0 0 {fmt(child_pos[2])}" size="0.03" mass="0.7" {link_geom}/>'
            f'<geom type="cylinder" fromto="0 0 -0.04 0 0 0.04" size="0.035" mass="0.2" {link_geom}/>'
        ),
        4: f'<geom type="capsule" fromto="0 0 -0.03 0 0 0.03" size="0.028" mass="0.3" {link_geom}/>',
        5: f'<geom type="capsule" fromto="0 0 0 {fmt(child_pos[4])}" size="0.027" mass="0.3" {link_geom}/>',
        6: f'<geom type="cylinder" fromto="0 0 -0.01 0 0 0.008" size="0.03" mass="0.1" {link_geom}/>',
    }
    grip = f'contype="{GRIPPER_BIT}" conaffinity="{SCENE_BIT}" group="0" condim="4"'
    half_stroke = GRIPPER_STROKE_MAX / 2.0
    finger_z = HAND_LENGTH + FINGER_LENGTH / 2.0
    finger_half = f"{FINGER_WIDTH / 2:.6g} {FINGER_THICKNESS / 2:.6g} {FINGER_LENGTH / 2:.6g}"

    def finger(side: str, sign: int) -> str:
        # Joint travel t >= 0 moves the finger outwards; its inner face is then at sign * t.
        return (
            f'<body name="{p}finger_{side}" pos="0 0 0" gravcomp="1">'
            f'<joint name="{p}finger_{side}" type="slide" axis="0 {sign} 0" range="0 {half_stroke:.6g}" '
            f'damping="5" armature="0.01"/>'
            f'<geom name="{p}finger_{side}" type="box" size="{finger_half}" '
            f'pos="0 {sign * FINGER_THICKNESS / 2:.6g} {finger_z:.6g}" mass="0.03" friction="1.5 0.02 0.001" '
            f'solref="0.005 1" {grip} rgba="0.2 0.2 0.22 1"/>'
            "</body>"
        )

    hand = (
        f'<body name="{p}hand" pos="0 0 0" gravcomp="1">'
        f'<geom name="{p}palm" type="box" size="0.022 0.05 {HAND_LENGTH / 2 - 0.004:.6g}" '
        f'pos="0 0 {HAND_LENGTH / 2 + 0.004:.6g}" mass="0.25" {grip} rgba="0.2 0.2 0.22 1"/>'
        f'<site name="{p}tcp" pos="0 0 {TCP_OFFSET:.6g}" size="0.005" rgba="1 0 0 0.5" group="4"/>'
        f"{finger('left', 1)}{finger('right', -1)}"
        "</body>"
    )

    inner = hand + flange_xml
    for i in range(5, -1, -1):  # build the chain from the flange back to link1
        pos, rot = dh_link_transform(i)
        quat = mat_to_quat(rot)
        j = i + 1
        inner = (
            f'<body name="{p}link{j}" pos="{fmt(pos)}" quat="{fmt(quat)}" gravcomp="1">'
            f'<joint name="{p}joint{j}" type="hinge" axis="0 0 1" range="{JOINT_LOWER[i]:.9g} {JOINT_UPPER[i]:.9g}" '
            f'armature="{JOINT_ARMATURE[i]:g}" damping="0.5"/>'
            f"{link_shapes[j]}{inner}</body>"
        )
    body = (
        f'<body name="{p}base" pos="{fmt(base_pos)}" quat="{fmt(base_quat)}">'
        f'<geom type="cylinder" fromto="0 0 0 0 0 0.1" size="0.05" {link_geom}/>'
        f"{inner}</body>"
    )
    actuator = "".join(
        f'<position name="{p}act{j + 1}" joint="{p}joint{j + 1}" kp="{JOINT_KP[j]:g}" kv="{JOINT_KV[j]:g}" '
        f'ctrlrange="{JOINT_LOWER[j]:.9g} {JOINT_UPPER[j]:.9g}" forcerange="-60 60"/>'
        for j in range(6)
    ) + (
        f'<position name="{p}gripper" tendon="{p}stroke" kp="{GRIPPER_KP:g}" kv="{GRIPPER_KV:g}" '
        f'ctrlrange="0 {GRIPPER_STROKE_MAX:.6g}" forcerange="-{GRIP_FORCE_MAX:g} {GRIP_FORCE_MAX:g}"/>'
    )
    tendon = (
        f'<fixed name="{p}stroke"><joint joint="{p}finger_left" coef="1"/>'
        f'<joint joint="{p}finger_right" coef="1"/></fixed>'
    )
    equality = f'<joint joint1="{p}finger_left" joint2="{p}finger_right" polycoef="0 1 0 0 0" solref="0.005 1"/>'
    contact = f'<exclude body1="{p}hand" body2="{p}link6"/>'
    return ArmXml(prefix=p, body=body, actuator=actuator, tendon=tendon, equality=equality, contact=contact)


def scene_xml(
    objects_xml: str = "",
    arms: tuple[ArmXml, ...] | None = None,
    extra_contact: str = "",
    extra_equality: str = "",
    assets: str = "",
) -> str:
    """The full MJCF: table, arms (default one unprefixed arm at the origin), camera and ``objects_xml``
    (bodies for <worldbody>, from the task); ``assets``: textures, materials and meshes they use."""
    arms = (arm_xml(),) if arms is None else tuple(arms)
    xy = fmt(camera_xyaxes())
    table = (
        f'<geom name="table" type="box" size="{fmt(TABLE_HALF)}" pos="{fmt(TABLE_CENTER)}" '
        f'contype="{SCENE_BIT}" conaffinity="{SCENE_BIT | GRIPPER_BIT}" friction="1 0.01 0.001" '
        'rgba="0.55 0.45 0.35 1"/>'
    )
    return f"""<mujoco model="piper_workcell">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{TIMESTEP}" integrator="implicitfast" cone="elliptic" impratio="10">
    <flag multiccd="enable"/>
  </option>
  <visual>
    <global offwidth="640" offheight="480"/>
    <map znear="0.01" zfar="20"/>
    <quality shadowsize="0"/>
  </visual>
  <asset>{assets}</asset>
  <default>
    <geom solimp="0.95 0.99 0.001" solref="0.004 1"/>
  </default>
  <worldbody>
    <light pos="0.3 0 1.5" dir="0 0 -1" directional="true" castshadow="false"/>
    {table}
    <camera name="{CAMERA_NAME}" pos="{fmt(CAMERA_POS)}" xyaxes="{xy}" fovy="{CAMERA_FOVY_DEG:.9g}"/>
    {"".join(a.body for a in arms)}
    {objects_xml}
  </worldbody>
  <tendon>{"".join(a.tendon for a in arms)}</tendon>
  <equality>{"".join(a.equality for a in arms)}{extra_equality}</equality>
  <contact>{"".join(a.contact for a in arms)}{extra_contact}</contact>
  <actuator>{"".join(a.actuator for a in arms)}</actuator>
</mujoco>
"""


def build_model(objects_xml: str = "", **kwargs) -> mujoco.MjModel:
    """Compile ``scene_xml(objects_xml, **kwargs)`` into an ``MjModel``."""
    return mujoco.MjModel.from_xml_string(scene_xml(objects_xml, **kwargs))


@dataclass(frozen=True)
class ArmIndex:
    """Addresses of one arm's parts in a compiled model (all int indices / (6,) int arrays)."""

    qpos: np.ndarray  # (6,) qpos addresses of joint1..6
    dof: np.ndarray  # (6,) dof addresses of joint1..6
    finger_qpos: np.ndarray  # (2,) qpos addresses of the left/right finger slides
    finger_dof: np.ndarray  # (2,)
    actuators: np.ndarray  # (6,) actuator ids of act1..6
    gripper_actuator: int
    tcp_site: int
    hand_body: int
    finger_geoms: tuple[int, int]  # left, right
    gripper_geoms: tuple[int, ...]  # palm + fingers

    @classmethod
    def find(cls, model: mujoco.MjModel, prefix: str = "") -> "ArmIndex":
        def jid(name: str) -> int:
            return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, prefix + name)

        def aid(name: str) -> int:
            return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, prefix + name)

        def gid(name: str) -> int:
            return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, prefix + name)

        joints = [jid(f"joint{i}") for i in range(1, 7)]
        fingers = [jid("finger_left"), jid("finger_right")]
        return cls(
            qpos=np.array([model.jnt_qposadr[j] for j in joints]),
            dof=np.array([model.jnt_dofadr[j] for j in joints]),
            finger_qpos=np.array([model.jnt_qposadr[j] for j in fingers]),
            finger_dof=np.array([model.jnt_dofadr[j] for j in fingers]),
            actuators=np.array([aid(f"act{i}") for i in range(1, 7)]),
            gripper_actuator=aid("gripper"),
            tcp_site=mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, prefix + "tcp"),
            hand_body=mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, prefix + "hand"),
            finger_geoms=(gid("finger_left"), gid("finger_right")),
            gripper_geoms=(gid("palm"), gid("finger_left"), gid("finger_right")),
        )
