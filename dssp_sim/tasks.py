"""The three memory tasks of the simulated workcell: their objects (MJCF), seeded randomisation and scoring.

Every task is a :class:`Task`: it adds bodies to the model (``objects_xml``), places them at ``reset``
from the environment's random generator, watches the physics (``on_substep`` after every physics step,
``update`` after every ``advance``) and reports a :class:`TaskStatus`. Positions are metres in the
robot-base frame (table top z = 0), angles radians. Every task ends with the arm back at ``HOME`` (all
joints within ``HOME_TOLERANCE``); success is declared once the goal has held for ``HOME_SETTLE_S``.

- ``tap``: a spring-loaded button; press it exactly ``TAP_PRESSES`` (3) times, then go home. The button
  springs back after each press, so the scene after press 1, 2 or 3 looks the same.
- ``swap``: a cube and a cylinder on slots A and B (which starts on A is seeded), a free buffer slot C in
  front of them; exchange them through the buffer, the cube first (A->C, B->A, C->B when it starts on A,
  the mirror B->C, A->B, C->A when it starts on B). With one object in the buffer the next move depends on
  the past: the layout "cube in C, cylinder on B, A empty" follows A->C when the cube started on A (next:
  B->A) and A->B when it started on B (next: C->A); and each start layout is the other's goal.
- ``put2``: two blocks in a source bin, moved one after the other into the basket beside it, then home.
  Both bins have tall walls on the camera side, so a block lying in either is hidden from the depth
  camera: the scene at home looks the same before, between and after the two transfers.

Failure reasons: "wrong count" (a fourth press), "dropped object" (an object at rest outside every slot
or bin, tipped over, or off the table), "timeout" (``max_steps`` control steps without success).

The memory decision, scored apart from the manipulation (``Task.decision(info)`` on an episode's final
``info``): tap — the number of presses (3 is right); swap — the move made from the first layout that only
memory can settle (after the first move: the cylinder to the cube's start slot is right, the cube on to it is
the other start's plan); put2 — at home after the first block, going back into the source bin for the second,
and at home after both, not reaching into it again (the scene at home looks the same before, between and after
the transfers). Each decision is counted only in the episodes that reached it (tap: every episode; swap: the
first move made; put2: one block in the basket), so a failed grasp is not scored as a wrong memory.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import mujoco
import numpy as np

from dssp_sim.mjcf import GRIPPER_BIT, SCENE_BIT

# The arm's home pose (rad, J1..J6): tool centre point at about (0.31, 0, 0.11) m, tilted 25 deg forward,
# above the middle of the work area.
HOME = np.array([0.0, 1.479, -0.777, 0.0, 0.52, 0.0])
HOME.setflags(write=False)
HOME_TOLERANCE = 0.05  # rad, max |joint - HOME| to count as "at home"
HOME_SETTLE_S = 0.5  # s the goal state (task done and arm at home) must last before success is declared
START_JITTER = 0.04  # rad, uniform jitter of each joint of the start pose around HOME

# tap
TAP_PRESSES = 3
BUTTON_BASE_HALF = (0.035, 0.035, 0.0125)  # housing box half sizes; its top is at z = 0.025
CAP_RADIUS = 0.022  # m
CAP_HALF_HEIGHT = 0.008  # m
CAP_TRAVEL = 0.012  # m, cap travel down to its stop
CAP_TOP = 2 * BUTTON_BASE_HALF[2] + 2 * CAP_HALF_HEIGHT  # z of the cap's top at rest, 0.041 m
PRESS_DEPTH = 0.007  # m below rest: a press is counted when the cap passes this (rising edge)
RELEASE_DEPTH = 0.003  # m: the press ends (hysteresis) above this
BUTTON_STIFFNESS = 400.0  # N/m
BUTTON_PRELOAD = 0.004  # m: spring reference above the rest stop (1.6 N holding it up)
BUTTON_CENTER = (0.32, 0.0)
BUTTON_JITTER = 0.025  # m, uniform jitter of the button's x and y

# swap
SLOT_SPACING = 0.06  # A at (x0, y0 + 0.06), B at (x0, y0 - 0.06), the buffer C in front at (x0 + 0.075, y0)
SLOT_BUFFER_AHEAD = 0.075
SLOT_CENTER = (0.29, 0.0)
SLOT_JITTER = 0.015  # m, uniform jitter of (x0, y0)
SLOT_PAD_HALF = (0.03, 0.03, 0.0015)  # thin pads marking the slots (half sizes, m)
SLOT_TOLERANCE = 0.03  # m, xy distance to a slot centre to count as "in the slot"
CUBE_HALF = 0.02  # m: a 4 cm cube
CYLINDER_RADIUS = 0.018  # m: a 3.6 cm wide, 6 cm tall cylinder
CYLINDER_HALF_HEIGHT = 0.03

# put2
# Two bins side by side across the robot's front, source at -y, basket at +y, each turned to face the
# robot. Each has tall walls on the camera side and at its outer end (they hide what lies inside from the
# camera) and low walls facing the robot and facing the other bin (so a block is carried between the bins
# just above the low walls). The open gripper (6 cm between the fingers) misses the block it straddles by 1.4 cm
# on each side and clears the other block by 1.7 cm and the end wall by 1.2 cm; across the bin (8 cm inside)
# the fingers clear the walls by 2 cm. With 0.9 cm along (4.9 cm open, bins 13 cm long, blocks 5.6 cm apart) and
# 1 cm across (6 cm inside) the policies' centimetre-scale misses put a finger on the block or on a wall's top,
# or pushed the other block away. The tall walls (7.5 cm) still hide the blocks from the camera.
BIN_INNER_HALF = (0.04, 0.085)  # interior half sizes (x, y)
BIN_WALL = 0.006  # wall thickness
BIN_FLOOR = 0.005  # floor thickness (its top is z = BIN_FLOOR)
BIN_WALL_TOP = 0.075  # z of the tall walls
BIN_LOW_TOP = 0.03  # z of the low walls
SOURCE_CENTER = (0.31, -0.1)
BASKET_CENTER = (0.31, 0.1)
BIN_JITTER = 0.01  # m, uniform jitter of each bin's x and y
BLOCK_HALF = (0.015, 0.015, 0.01)  # m: 3 x 3 x 2 cm blocks
BLOCK_SPACING = 0.035  # blocks sit at y = centre -+ BLOCK_SPACING in the source and go to the same spots in the basket

REST_SPEED = 0.05  # m/s: an object slower than this is "at rest"
REACH_Z = 0.05  # m: the tool centre point below this inside the source bin is a reach into it (put2's scoring)
REACH_HYSTERESIS = 0.02  # m: the reach ends above REACH_Z + this, or outside the bin


@dataclass
class TaskStatus:
    """done: the episode is over; success: it ended well; reason: "" or why it failed ("wrong count",
    "dropped object", "timeout"); info: task progress (e.g. ``{"presses": 2}``)."""

    done: bool = False
    success: bool = False
    reason: str = ""
    info: dict = field(default_factory=dict)


def _free_body(name: str, geom: str, rgba: str) -> str:
    return (
        f'<body name="{name}" pos="0 0 0.5"><freejoint name="{name}"/>'
        f'<geom name="{name}" {geom} mass="0.05" friction="1 0.01 0.001" condim="4" '
        f'contype="{SCENE_BIT}" conaffinity="{SCENE_BIT | GRIPPER_BIT}" rgba="{rgba}"/></body>'
    )


def _static_box(name: str, half, pos, rgba: str = "0.5 0.5 0.55 1") -> str:
    return (
        f'<geom name="{name}" type="box" size="{half[0]:.6g} {half[1]:.6g} {half[2]:.6g}" '
        f'pos="{pos[0]:.6g} {pos[1]:.6g} {pos[2]:.6g}" contype="{SCENE_BIT}" '
        f'conaffinity="{SCENE_BIT | GRIPPER_BIT}" rgba="{rgba}"/>'
    )


def yaw_quat(yaw: float) -> np.ndarray:
    """(4,) quaternion (w, x, y, z) of a rotation by ``yaw`` rad about z."""
    return np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])


class Task:
    """Base class. Subclasses set ``name``, ``max_steps`` and ``home_opening`` (gripper opening 0..1 that
    the expert holds at home) and implement the hooks; ``status()`` returns the latched status."""

    name = "task"
    max_steps = 100
    home_opening = 1.0

    def __init__(self) -> None:
        self._status = TaskStatus()

    # --- model ---
    def objects_xml(self) -> str:
        return ""

    def extra_contact(self) -> str:
        return ""

    def bind(self, env) -> None:
        """Look up ids in ``env.model`` (called once after the model is built)."""

    # --- episode ---
    def reset(self, env, rng: np.random.Generator, options: dict | None = None) -> None:
        """Place the objects in ``env.data`` (qpos / static geom positions in ``env.model``)."""
        self._status = TaskStatus()
        self._goal_since: float | None = None

    def on_substep(self, env) -> None:
        """After every physics step (cheap checks only)."""

    def update(self, env) -> None:
        """After every ``env.advance``: latch done/success/failure. Success needs ``goal_reached`` to hold
        for ``HOME_SETTLE_S`` seconds of simulated time (the arm has come to rest at home)."""
        if self._status.done:
            return
        self.watch(env)
        self._status.info = self.progress(env)
        reason = self.failure(env)
        if reason:
            self._finish(False, reason)
            return
        if self.goal_reached(env):
            if self._goal_since is None:
                self._goal_since = float(env.data.time)
            if env.data.time - self._goal_since >= HOME_SETTLE_S - 1e-9:
                self._finish(True, "")
                return
        else:
            self._goal_since = None
        if env.steps >= env.max_steps:
            self._finish(False, "timeout")

    def watch(self, env) -> None:
        """After every ``env.advance``, before ``progress``: follow events the scoring needs (moves, reaches)."""

    def progress(self, env) -> dict:
        return {}

    @staticmethod
    def decision(info: dict) -> dict:
        """The memory decision of an episode from its final ``info``: {"reached": the episode got to the decision,
        "correct": it decided right (None when not reached), "choice": what it did, as a short label}."""
        return {"reached": False, "correct": None, "choice": ""}

    def failure(self, env) -> str:
        return ""

    def goal_reached(self, env) -> bool:
        """The task's goal holds now (objects in place, arm at home)."""
        return False

    def status(self) -> TaskStatus:
        s = self._status
        return TaskStatus(s.done, s.success, s.reason, dict(s.info))

    def _finish(self, success: bool, reason: str) -> None:
        self._status.done = True
        self._status.success = success
        self._status.reason = reason


# --------------------------------------------------------------------------------------------------- helpers
def _body_id(model, name: str) -> int:
    return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)


def _geom_id(model, name: str) -> int:
    return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name)


class _Objects:
    """Free bodies of a task: pose access, contact with the fingers, rest and upright tests."""

    def __init__(self, model, names: tuple[str, ...]) -> None:
        self.names = names
        self.bodies = [_body_id(model, n) for n in names]
        self.geoms = [_geom_id(model, n) for n in names]
        joints = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n) for n in names]
        self.qpos = [int(model.jnt_qposadr[j]) for j in joints]
        self.dof = [int(model.jnt_dofadr[j]) for j in joints]

    def place(self, data, k: int, pos, yaw: float = 0.0) -> None:
        a = self.qpos[k]
        data.qpos[a : a + 3] = pos
        data.qpos[a + 3 : a + 7] = yaw_quat(yaw)
        data.qvel[self.dof[k] : self.dof[k] + 6] = 0.0

    def pos(self, data, k: int) -> np.ndarray:
        return data.xpos[self.bodies[k]].copy()

    def yaw(self, data, k: int) -> float:
        m = data.xmat[self.bodies[k]].reshape(3, 3)
        return math.atan2(m[1, 0], m[0, 0])

    def speed(self, data, k: int) -> float:
        return float(np.linalg.norm(data.qvel[self.dof[k] : self.dof[k] + 3]))

    def upright(self, data, k: int, any_face: bool = False) -> bool:
        m = data.xmat[self.bodies[k]].reshape(3, 3)
        return float(np.abs(m[2]).max() if any_face else abs(m[2, 2])) > 0.9

    def held(self, env, k: int) -> bool:
        """Both finger pads touch object k."""
        return all(env.touching(g, self.geoms[k]) for g in env.arm.finger_geoms)

    def dropped(self, env, placed) -> str:
        """The failure ``dropped object`` when an object fell off the table, or lies at rest (not held)
        where ``placed(k)`` (upright, in a slot or a bin) is False; else ``""``."""
        for k in range(len(self.bodies)):
            if self.pos(env.data, k)[2] < -0.02:
                return "dropped object"
            if self.held(env, k) or self.speed(env.data, k) > REST_SPEED:
                continue
            if not placed(k):
                return "dropped object"
        return ""


# --------------------------------------------------------------------------------------------------- tap
class TapTask(Task):
    """Press the button exactly three times, then go home and stay.

    ``presses`` counts rising edges of the cap's travel past ``PRESS_DEPTH``; ``button_position(env)`` is
    the (3,) centre of the cap's top at rest (m).
    """

    name = "tap"
    max_steps = 90
    home_opening = 0.0

    def objects_xml(self) -> str:
        b = BUTTON_BASE_HALF
        return (
            f'<body name="button" pos="{BUTTON_CENTER[0]} {BUTTON_CENTER[1]} 0">'
            + _static_box("button_base", b, (0, 0, b[2]), "0.3 0.3 0.32 1")
            + f'<body name="button_cap" pos="0 0 {2 * b[2]:.6g}">'
            f'<joint name="button" type="slide" axis="0 0 1" range="{-CAP_TRAVEL:.6g} 0" '
            f'stiffness="{BUTTON_STIFFNESS:g}" springref="{BUTTON_PRELOAD:g}" damping="3"/>'
            f'<geom name="button_cap" type="cylinder" size="{CAP_RADIUS:g} {CAP_HALF_HEIGHT:g}" '
            f'pos="0 0 {CAP_HALF_HEIGHT:g}" mass="0.02" contype="{SCENE_BIT}" '
            f'conaffinity="{SCENE_BIT | GRIPPER_BIT}" rgba="0.85 0.15 0.1 1"/>'
            "</body></body>"
        )

    def extra_contact(self) -> str:
        return '<exclude body1="button" body2="button_cap"/>'

    def bind(self, env) -> None:
        m = env.model
        self._button_body = _body_id(m, "button")
        j = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "button")
        self._qpos = int(m.jnt_qposadr[j])
        self._dof = int(m.jnt_dofadr[j])

    def reset(self, env, rng, options=None) -> None:
        super().reset(env, rng, options)
        offset = rng.uniform(-BUTTON_JITTER, BUTTON_JITTER, 2)
        env.model.body_pos[self._button_body] = [BUTTON_CENTER[0] + offset[0], BUTTON_CENTER[1] + offset[1], 0.0]
        env.data.qpos[self._qpos] = 0.0
        env.data.qvel[self._dof] = 0.0
        self.presses = 0
        self._down = False

    def button_position(self, env) -> np.ndarray:
        """(3,) centre of the cap's top at rest, metres."""
        x, y, _ = env.model.body_pos[self._button_body]
        return np.array([x, y, CAP_TOP])

    def travel(self, env) -> float:
        """How far the cap is pushed in, metres (0 at rest)."""
        return -float(env.data.qpos[self._qpos])

    def on_substep(self, env) -> None:
        d = self.travel(env)
        if not self._down and d > PRESS_DEPTH:
            self._down = True
            self.presses += 1
        elif self._down and d < RELEASE_DEPTH:
            self._down = False

    def progress(self, env) -> dict:
        return {"presses": self.presses, "button_down": self._down}

    @staticmethod
    def decision(info: dict) -> dict:
        presses = int(info.get("presses", 0))
        return {"reached": True, "correct": presses == TAP_PRESSES, "choice": f"{presses} presses"}

    def failure(self, env) -> str:
        return "wrong count" if self.presses > TAP_PRESSES else ""

    def goal_reached(self, env) -> bool:
        return self.presses == TAP_PRESSES and not self._down and env.at_home()


# --------------------------------------------------------------------------------------------------- swap
SWAP_OBJECTS = ("cube", "cylinder")


class SwapTask(Task):
    """Exchange the cube and the cylinder on slots A and B through the buffer slot C, then go home.

    ``reset`` options: ``a_object`` ("cube" | "cylinder": which object starts on A; a seeded choice by
    default) and ``first`` ("A" | "B": which slot's object goes to the buffer first; by default the cube's,
    so the first move follows from the scene: with a coin toss no observation could settle, the policies
    hesitated between A and B at the start and swept into the object they reached late). The slot jitter
    is drawn the same way whatever the options.

    After ``reset``: ``slots`` {"A" | "B" | "C": (2,) centre, m}, ``start`` / ``goal`` (slot of the cube,
    slot of the cylinder), ``first``, ``objects`` (index 0 cube, 1 cylinder).
    """

    name = "swap"
    max_steps = 220
    home_opening = 0.85

    def objects_xml(self) -> str:
        pads = "".join(
            f'<body name="slot_{s}" pos="0 0 0">'
            + _static_box(f"slot_{s}", SLOT_PAD_HALF, (0, 0, SLOT_PAD_HALF[2]), "0.35 0.35 0.4 1")
            + "</body>"
            for s in "ACB"
        )
        cube = _free_body("cube", f'type="box" size="{CUBE_HALF} {CUBE_HALF} {CUBE_HALF}"', "0.8 0.2 0.2 1")
        cyl = _free_body(
            "cylinder", f'type="cylinder" size="{CYLINDER_RADIUS} {CYLINDER_HALF_HEIGHT}"', "0.2 0.3 0.8 1"
        )
        return pads + cube + cyl

    def bind(self, env) -> None:
        self.objects = _Objects(env.model, SWAP_OBJECTS)
        self._slot_bodies = {s: _body_id(env.model, f"slot_{s}") for s in "ACB"}

    @staticmethod
    def half_height(k: int) -> float:
        """Half height (m) of object k (0 cube, 1 cylinder)."""
        return CUBE_HALF if k == 0 else CYLINDER_HALF_HEIGHT

    def reset(self, env, rng, options=None) -> None:
        super().reset(env, rng, options)
        options = dict(options or {})
        centre = np.array(SLOT_CENTER) + rng.uniform(-SLOT_JITTER, SLOT_JITTER, 2)
        a_is_cube = bool(rng.integers(2))
        yaw_jitter = rng.uniform(-0.1, 0.1)
        if "a_object" in options:
            a_is_cube = options.pop("a_object") == "cube"
        first = options.pop("first", "A" if a_is_cube else "B")  # the cube goes first
        if options:
            raise ValueError(f"swap: unknown reset options {sorted(options)}")
        if first not in ("A", "B"):
            raise ValueError(f"swap: first must be 'A' or 'B', got {first!r}")
        self.slots = {
            "A": centre + [0.0, SLOT_SPACING],
            "B": centre + [0.0, -SLOT_SPACING],
            "C": centre + [SLOT_BUFFER_AHEAD, 0.0],
        }
        for s, body in self._slot_bodies.items():
            env.model.body_pos[body] = [*self.slots[s], 0.0]
        self.first = first
        self.moves: list[str] = []
        # start[k] = slot of object k (0 cube, 1 cylinder) at the start; goal = the other one of A/B.
        self.start = ("A", "B") if a_is_cube else ("B", "A")
        self.goal = (self.start[1], self.start[0])
        self._rest = list(self.start)
        for k in range(2):
            xy = self.slots[self.start[k]]
            yaw = math.atan2(xy[1], xy[0]) + (yaw_jitter if k == 0 else 0.0)
            self.objects.place(env.data, k, [xy[0], xy[1], 2 * SLOT_PAD_HALF[2] + self.half_height(k)], yaw)

    def plan(self) -> list[tuple[int, str, str]]:
        """The three moves as (object index, from slot, to slot)."""
        second = "B" if self.first == "A" else "A"
        k1 = self.start.index(self.first)
        k2 = 1 - k1
        return [(k1, self.first, "C"), (k2, second, self.first), (k1, "C", second)]

    def slot_of(self, env, k: int) -> str:
        """Slot ("A" | "B" | "C") object k rests in, or ""."""
        p = self.objects.pos(env.data, k)
        if p[2] > 2 * SLOT_PAD_HALF[2] + self.half_height(k) + 0.01:
            return ""
        for s, xy in self.slots.items():
            if np.linalg.norm(p[:2] - xy) <= SLOT_TOLERANCE:
                return s
        return ""

    def watch(self, env) -> None:
        """A move: an object coming to rest (not held) in a slot other than the one it last rested in."""
        for k in range(2):
            slot = self.slot_of(env, k)
            if (
                slot
                and slot != self._rest[k]
                and not self.objects.held(env, k)
                and self.objects.speed(env.data, k) <= REST_SPEED
            ):
                self.moves.append(f"{SWAP_OBJECTS[k]} {self._rest[k]}->{slot}")
                self._rest[k] = slot

    def progress(self, env) -> dict:
        return {
            "slots": {SWAP_OBJECTS[k]: self.slot_of(env, k) for k in range(2)},
            "first": self.first,
            "moves": list(self.moves),
            "plan": [f"{SWAP_OBJECTS[k]} {a}->{b}" for k, a, b in self.plan()],
        }

    @staticmethod
    def decision(info: dict) -> dict:
        """Reached once the first planned move is made; right when the next move is the plan's second."""
        moves, plan = list(info.get("moves", [])), list(info.get("plan", []))
        if not plan or moves[:1] != plan[:1]:
            return {"reached": False, "correct": None, "choice": "first move not made"}
        if len(moves) < 2:
            return {"reached": True, "correct": False, "choice": "no second move"}
        return {"reached": True, "correct": moves[1] == plan[1], "choice": moves[1]}

    def failure(self, env) -> str:
        return self.objects.dropped(
            env, lambda k: self.objects.upright(env.data, k, any_face=(k == 0)) and bool(self.slot_of(env, k))
        )

    def goal_reached(self, env) -> bool:
        for k in range(2):
            if (
                self.slot_of(env, k) != self.goal[k]
                or self.objects.held(env, k)
                or self.objects.speed(env.data, k) > REST_SPEED
            ):
                return False
        return env.at_home()


# --------------------------------------------------------------------------------------------------- put2
PUT2_OBJECTS = ("block_0", "block_1")


def _bin_xml(name: str, outer_side: int, rgba: str) -> str:
    """A bin centred at its body's origin; ``outer_side`` (+1 / -1) is the y side of its tall end wall."""
    ix, iy = BIN_INNER_HALF
    t = BIN_WALL
    ox, oy = ix + t, iy + t
    h_floor = BIN_FLOOR / 2
    tall = (BIN_WALL_TOP - BIN_FLOOR) / 2
    low = (BIN_LOW_TOP - BIN_FLOOR) / 2
    ends = {outer_side: tall, -outer_side: low}
    parts = [
        _static_box(f"{name}_floor", (ox, oy, h_floor), (0, 0, h_floor), rgba),
        _static_box(f"{name}_front", (t / 2, oy, tall), (ix + t / 2, 0, BIN_FLOOR + tall), rgba),
        _static_box(f"{name}_back", (t / 2, oy, low), (-ix - t / 2, 0, BIN_FLOOR + low), rgba),
        _static_box(f"{name}_left", (ix, t / 2, ends[1]), (0, iy + t / 2, BIN_FLOOR + ends[1]), rgba),
        _static_box(f"{name}_right", (ix, t / 2, ends[-1]), (0, -iy - t / 2, BIN_FLOOR + ends[-1]), rgba),
    ]
    return f'<body name="{name}" pos="0 0 0">{"".join(parts)}</body>'


class Put2Task(Task):
    """Move the two blocks from the source bin into the basket, one after the other, then go home.

    After ``reset``: ``bins`` {"source" | "basket": (2,) centre, m}, ``bin_yaw`` {name: rad},
    ``objects`` (blocks 0 and 1); ``place_xy(bin, k)`` is block k's spot in a bin.
    """

    name = "put2"
    max_steps = 180
    home_opening = 0.85

    def objects_xml(self) -> str:
        blocks = "".join(
            _free_body(n, f'type="box" size="{BLOCK_HALF[0]} {BLOCK_HALF[1]} {BLOCK_HALF[2]}"', "0.9 0.7 0.1 1")
            for n in PUT2_OBJECTS
        )
        return _bin_xml("source", -1, "0.35 0.45 0.35 1") + _bin_xml("basket", 1, "0.45 0.35 0.3 1") + blocks

    def bind(self, env) -> None:
        self.objects = _Objects(env.model, PUT2_OBJECTS)
        self._bin_bodies = {"source": _body_id(env.model, "source"), "basket": _body_id(env.model, "basket")}

    def reset(self, env, rng, options=None) -> None:
        super().reset(env, rng, options)
        if options:
            raise ValueError(f"put2: unknown reset options {sorted(options)}")
        # Each bin faces the robot: its yaw is the bearing of its centre from the base.
        self.bins = {
            "source": np.array(SOURCE_CENTER) + rng.uniform(-BIN_JITTER, BIN_JITTER, 2),
            "basket": np.array(BASKET_CENTER) + rng.uniform(-BIN_JITTER, BIN_JITTER, 2),
        }
        self.bin_yaw = {name: math.atan2(xy[1], xy[0]) for name, xy in self.bins.items()}
        for name, body in self._bin_bodies.items():
            env.model.body_pos[body] = [*self.bins[name], 0.0]
            env.model.body_quat[body] = yaw_quat(self.bin_yaw[name])
        self.reaches = [0, 0, 0]
        self._reaching = False
        jitter = rng.uniform(-0.003, 0.003, (2, 2))
        for k in range(2):
            xy = self.place_xy("source", k) + jitter[k]
            self.objects.place(env.data, k, [xy[0], xy[1], BIN_FLOOR + BLOCK_HALF[2]], self.bin_yaw["source"])

    def _to_bin(self, name: str, xy) -> np.ndarray:
        """(2,) table point ``xy`` in the bin's own frame (x towards the camera side, y along the bin)."""
        c, s = math.cos(self.bin_yaw[name]), math.sin(self.bin_yaw[name])
        d = np.asarray(xy, dtype=np.float64) - self.bins[name]
        return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]])

    def place_xy(self, bin_name: str, k: int) -> np.ndarray:
        """(2,) spot of block k in a bin, metres: block 0 on the bin's -y side, block 1 on its +y side."""
        c, s = math.cos(self.bin_yaw[bin_name]), math.sin(self.bin_yaw[bin_name])
        along = (2 * k - 1) * BLOCK_SPACING
        return self.bins[bin_name] + along * np.array([-s, c])

    def bin_of(self, env, k: int) -> str:
        """ "source" | "basket" if block k lies inside that bin (below its wall tops), else ""."""
        p = self.objects.pos(env.data, k)
        if p[2] > BIN_WALL_TOP:
            return ""
        for name in self.bins:
            d = np.abs(self._to_bin(name, p[:2]))
            if d[0] <= BIN_INNER_HALF[0] and d[1] <= BIN_INNER_HALF[1]:
                return name
        return ""

    def watch(self, env) -> None:
        """A reach: the tool centre point going down into the source bin (inside its walls, below ``REACH_Z``);
        counted per number of blocks in the basket at the time (``reaches[n]``)."""
        tcp, _ = env.tcp_pose()
        d = np.abs(self._to_bin("source", tcp[:2]))
        inside = d[0] <= BIN_INNER_HALF[0] and d[1] <= BIN_INNER_HALF[1]
        if not self._reaching and inside and tcp[2] < REACH_Z:
            self._reaching = True
            self.reaches[sum(self.bin_of(env, k) == "basket" for k in range(2))] += 1
        elif self._reaching and (not inside or tcp[2] > REACH_Z + REACH_HYSTERESIS):
            self._reaching = False

    def progress(self, env) -> dict:
        return {"in_basket": sum(self.bin_of(env, k) == "basket" for k in range(2)), "reaches": list(self.reaches)}

    @staticmethod
    def decision(info: dict) -> dict:
        """The two moments at home that look the same: after the first block (right: back into the source bin
        for the second) and, once both are in the basket, after the second (right: no reach into the source bin
        again). Reached once a block is in the basket (or was: one taken out again counts); right when every
        moment reached was decided right."""
        reaches = list(info.get("reaches", [0, 0, 0]))
        in_basket = info.get("in_basket", 0)
        if in_basket < 1 and reaches[1] == 0 and reaches[2] == 0:
            return {"reached": False, "correct": None, "choice": "no block in the basket"}
        back = reaches[1] > 0 or in_basket == 2
        if not back:
            return {"reached": True, "correct": False, "choice": "stopped after one"}
        if reaches[2] > 0:
            return {"reached": True, "correct": False, "choice": "back for the second, then in again after both"}
        if in_basket == 2:
            return {"reached": True, "correct": True, "choice": "back for the second, then stayed out"}
        return {"reached": True, "correct": True, "choice": "back for the second"}

    def failure(self, env) -> str:
        return self.objects.dropped(
            env, lambda k: bool(self.bin_of(env, k)) and self.objects.upright(env.data, k, any_face=True)
        )

    def goal_reached(self, env) -> bool:
        for k in range(2):
            if (
                self.bin_of(env, k) != "basket"
                or self.objects.held(env, k)
                or self.objects.speed(env.data, k) > REST_SPEED
            ):
                return False
        return env.at_home()


TASKS: dict[str, type[Task]] = {"tap": TapTask, "swap": SwapTask, "put2": Put2Task}


def make_task(name: str) -> Task:
    """A fresh task by name: one of ``TASKS`` ("tap", "swap", "put2")."""
    try:
        return TASKS[name]()
    except KeyError:
        raise ValueError(f"unknown task {name!r}; choose one of {sorted(TASKS)}") from None
