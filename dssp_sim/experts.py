"""Scripted experts for the simulated tasks: phase machines over tool waypoints, solved by IK.

    env.reset(seed)
    expert = make_expert(env)            # one expert per episode, made right after reset
    while not env.status().done:
        env.step(expert.act(env))        # (7,) policy units: [J1..J6 rad (absolute), gripper opening 0..1]

Each expert runs a script (a generator of per-step targets): the waypoints are tool poses (tool centre
point position in metres, pointing down and tilted ``TOOL_TILT`` towards the radial direction, fingers
across it), solved by damped least squares on a scratch copy of the model (``dssp_sim.ik``) seeded with
the previous waypoint, and joined by joint-space trapezoids whose largest per-step change is
``MAX_JOINT_STEP`` rad (gripper: ``MAX_GRIPPER_STEP``). Between subtasks the arm returns to ``HOME`` and
dwells there (``DWELL_STEPS``), and the tap expert dwells at one fixed hover pose between taps: these
are the moments where the observation alone cannot tell what comes next.

Experts read the true object poses from the task (privileged information) and are deterministic: the
same seed gives the same episode. ``expert.phase`` names the current phase (for tests and logs).
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np

from dssp_sim.ik import IKSolver
from dssp_sim.mjcf import FINGER_WIDTH, FINGERTIP_BELOW_TCP
from dssp_sim.tasks import (
    BIN_FLOOR,
    BIN_LOW_TOP,
    BLOCK_HALF,
    CAP_TRAVEL,
    CUBE_HALF,
    CYLINDER_RADIUS,
    HOME,
    PRESS_DEPTH,
    SLOT_PAD_HALF,
    TAP_PRESSES,
    Put2Task,
    SwapTask,
    TapTask,
)
from hardware.piper.limits import GRIPPER_STROKE_MAX, JOINT_LOWER, JOINT_UPPER

MAX_JOINT_STEP = 0.04  # rad per control step (the safety layer clips above 0.05)
MAX_GRIPPER_STEP = 0.19  # opening per control step
DWELL_STEPS = 2  # control steps held at a decision pose (hover between taps, home between transfers)
TOOL_TILT = math.radians(25.0)  # approach direction tilted from straight down towards the radial direction
GRIP_SQUEEZE = 0.016  # m: the gripper is commanded this far inside the object's width (grip force)
HOVER_CLEARANCE = 0.015  # m between the fingertips and an object's top before descending
RELEASE_DROP = 0.004  # m: an object is released this high above its resting surface

# Lowest point of the fingers below the tool centre point (m, world z) at the tool tilt.
TIP_DROP = FINGERTIP_BELOW_TCP * math.cos(TOOL_TILT) + FINGER_WIDTH / 2 * math.sin(TOOL_TILT)

Command = tuple[np.ndarray, float]  # joints (6,) rad, gripper opening


def tool_rotation(xy, radial: bool = True) -> np.ndarray:
    """(3, 3) tool rotation for work at table point ``xy`` (2,): approach pointing down, tilted
    ``TOOL_TILT`` towards the radial direction atan2(y, x) (``radial=False``: towards +x), finger axis
    horizontal, across the tilt."""
    yaw = math.atan2(float(xy[1]), float(xy[0])) if radial else 0.0
    ahead = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    z = math.sin(TOOL_TILT) * ahead + math.cos(TOOL_TILT) * np.array([0.0, 0.0, -1.0])
    y = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
    return np.column_stack([np.cross(y, z), y, z])


def trapezoid(n: int) -> np.ndarray:
    """(n,) cumulative fractions 0 < s_1 < ... < s_n = 1 of a move in n steps: half-size first and last
    steps, equal steps between."""
    v = np.ones(n)
    if n >= 2:
        v[0] = v[-1] = 0.5
    return np.cumsum(v) / v.sum()


def steps_for(dq: np.ndarray, dg: float) -> int:
    """Fewest steps of ``trapezoid`` keeping each step within the joint and gripper limits."""
    for n in range(1, 1000):
        peak = 1.0 / (n - 1.0) if n >= 2 else 1.0
        if np.abs(dq).max() * peak <= MAX_JOINT_STEP and abs(dg) * peak <= MAX_GRIPPER_STEP:
            return n
    raise ValueError("move too large")


class Expert:
    """Base: holds the commanded target (``q_cmd`` (6,) rad, ``g_cmd`` opening), runs ``script`` one
    step per ``act``. The building blocks (``move``, ``hold``, ``pick``, ``place``, ``go_home``) are
    generators that update the command and yield it once per control step.

    Phases (``phase``): approach, descend, close, lift, carry, lower, release, retreat, home, home_dwell,
    hover_dwell and press (tap), done.
    """

    RADIAL = True  # tool yaw follows the radial direction (False: fingers along the world y axis)

    def __init__(self, env) -> None:
        self.env = env
        self.ik = IKSolver(env.model)
        self.q_cmd = env.joint_positions()
        self.g_cmd = float(env.state()[6])
        self.phase = "start"
        self.waypoints: dict[str, np.ndarray] = {}
        self._script = self.script(env)
        self.finished = False

    # --- what subclasses write
    def script(self, env) -> Iterator[Command]:
        yield from ()

    # --- driving
    def act(self, env) -> np.ndarray:
        """(7,) float64 target for this control step: [J1..J6 rad, gripper opening 0..1]."""
        if env is not self.env:
            raise ValueError("this expert belongs to another env; make one per env with make_expert(env)")
        if not self.finished:
            try:
                next(self._script)  # the building blocks keep q_cmd / g_cmd
            except StopIteration:
                self.finished = True
                self.phase = "done"
        return np.append(self.q_cmd, self.g_cmd)

    # --- building blocks
    def solve(self, pos, xy_for_rotation=None, seed=None) -> np.ndarray:
        """Joints (6,) putting the tool centre point at ``pos`` (3,) m, oriented by ``tool_rotation`` for
        ``xy_for_rotation`` (default: pos's xy); the search starts at ``seed`` (6,) (default: the current
        command)."""
        pos = np.asarray(pos, dtype=np.float64)
        q = self.ik.solve(
            pos,
            self.rotation(pos[:2] if xy_for_rotation is None else xy_for_rotation),
            seed=self.q_cmd if seed is None else seed,
        )
        err_p, err_r = self.ik.last_error
        if err_p > 2e-3 or err_r > 2e-2:
            raise RuntimeError(
                f"{type(self).__name__}: no IK solution for {pos} (errors {err_p:.3g} m, {err_r:.3g} rad)"
            )
        return q

    def rotation(self, xy) -> np.ndarray:
        """(3, 3) tool rotation used for work at table point ``xy`` (2,)."""
        return tool_rotation(xy, radial=self.RADIAL)

    def move(self, q_goal, g_goal: float | None = None, phase: str | None = None) -> Iterator[Command]:
        """Joint-space trapezoid from the current command to ``q_goal`` (6,) / gripper ``g_goal``; a move
        of the gripper alone goes in equal steps."""
        if phase:
            self.phase = phase
        q0, g0 = self.q_cmd.copy(), self.g_cmd
        q1 = np.clip(np.asarray(q_goal, dtype=np.float64), JOINT_LOWER, JOINT_UPPER)
        g1 = g0 if g_goal is None else float(np.clip(g_goal, 0.0, 1.0))
        if np.abs(q1 - q0).max() < 1e-9:
            if abs(g1 - g0) < 1e-9:
                return
            n = int(math.ceil(abs(g1 - g0) / MAX_GRIPPER_STEP - 1e-9))
            for i in range(1, n + 1):
                yield self._command(q1, g0 + (g1 - g0) * i / n)
            return
        for s in trapezoid(steps_for(q1 - q0, g1 - g0)):
            yield self._command(q0 + s * (q1 - q0), g0 + s * (g1 - g0))

    def _command(self, q: np.ndarray, g: float) -> Command:
        self.q_cmd, self.g_cmd = np.asarray(q, dtype=np.float64).copy(), float(g)
        return self.q_cmd.copy(), self.g_cmd

    def hold(self, n: int, phase: str | None = None) -> Iterator[Command]:
        if phase:
            self.phase = phase
        for _ in range(n):
            yield self.q_cmd.copy(), self.g_cmd

    def hold_forever(self, phase: str = "done") -> Iterator[Command]:
        self.phase = phase
        while True:
            yield self.q_cmd.copy(), self.g_cmd

    def go_home(self, opening: float, dwell: int = DWELL_STEPS) -> Iterator[Command]:
        yield from self.move(HOME, opening, phase="home")
        yield from self.hold(dwell, phase="home_dwell")

    # --- grasping
    def _held_offset(self, k: int) -> np.ndarray:
        """(3,) centre of object k in the tool frame (constant while it is held), metres."""
        obj = self.env.task.objects.pos(self.env.data, k)
        tcp, rot = self.env.tcp_pose()
        return rot.T @ (obj - tcp)

    def pick(
        self,
        k: int,
        half_height: float,
        width: float,
        hover_tip_z: float,
        grip_tip_z: float,
        open_g: float,
        clear_z: float,
    ) -> Iterator[Command]:
        """Object k (``width`` m across the fingers, ``half_height`` m): hover with the fingertips at
        ``hover_tip_z``, descend until they are at ``grip_tip_z``, close, and lift straight up until the
        object's bottom is at ``clear_z``."""
        xy = self.env.task.objects.pos(self.env.data, k)[:2]
        hover = self.solve([xy[0], xy[1], hover_tip_z + TIP_DROP])
        yield from self.move(hover, open_g, phase="approach")
        grasp = self.solve([xy[0], xy[1], grip_tip_z + TIP_DROP])
        yield from self.move(grasp, phase="descend")
        close = max(0.0, (width - GRIP_SQUEEZE) / GRIPPER_STROKE_MAX)
        yield from self.move(self.q_cmd, close, phase="close")
        offset = self.rotation(xy) @ self._held_offset(k)
        tcp = self.env.tcp_pose()[0]
        lift = self.solve([tcp[0], tcp[1], clear_z + half_height - offset[2]], xy)
        yield from self.move(lift, phase="lift")

    def place(
        self,
        k: int,
        half_height: float,
        target_xy,
        surface_z: float,
        clear_z: float,
        open_g: float,
        retreat_tip_z: float,
    ) -> Iterator[Command]:
        """Carry object k (held) over ``target_xy`` with its bottom at ``clear_z``, lower it until its
        bottom is ``RELEASE_DROP`` above ``surface_z``, open, and retreat until the fingertips are at
        ``retreat_tip_z``."""
        target_xy = np.asarray(target_xy, dtype=np.float64)
        offset = self.rotation(target_xy) @ self._held_offset(k)  # object centre - tcp at the target
        over = target_xy - offset[:2]
        carry = self.solve([over[0], over[1], clear_z + half_height - offset[2]], target_xy)
        yield from self.move(carry, phase="carry")
        down = self.solve([over[0], over[1], surface_z + RELEASE_DROP + half_height - offset[2]], target_xy)
        yield from self.move(down, phase="lower")
        yield from self.move(self.q_cmd, open_g, phase="release")
        up = self.solve([over[0], over[1], retreat_tip_z + TIP_DROP], target_xy)
        yield from self.move(up, phase="retreat")


class TapExpert(Expert):
    """Hover over the button, tap until three presses are counted, dwelling at the hover pose before each
    decision, then go home (gripper closed throughout)."""

    def script(self, env) -> Iterator[Command]:
        task: TapTask = env.task
        top = task.button_position(env)
        hover = self.solve(top + [0.0, 0.0, 0.03 + TIP_DROP])
        # Fingertips 2 mm short of the cap's stop: past the press threshold, never forcing the stop.
        depth = min(CAP_TRAVEL - 0.002, PRESS_DEPTH + 0.003)
        press = self.solve(top + [0.0, 0.0, -depth + TIP_DROP], seed=hover)
        self.waypoints = {"hover": hover, "press": press}
        yield from self.move(hover, 0.0, phase="approach")
        while True:
            yield from self.hold(DWELL_STEPS, phase="hover_dwell")
            if task.presses >= TAP_PRESSES:
                break
            yield from self.move(press, phase="press")
            yield from self.hold(1, phase="press")
            yield from self.move(hover, phase="release")
        yield from self.move(HOME, 0.0, phase="home")
        yield from self.hold_forever()


class SwapExpert(Expert):
    """Three pick-and-place moves through the buffer slot (the task's ``plan``), home between them.

    No slot lies between two others, so an object is carried just ``LIFT`` above its slot."""

    LIFT = 0.02

    def script(self, env) -> Iterator[Command]:
        task: SwapTask = env.task
        open_g = task.home_opening
        surface = 2 * SLOT_PAD_HALF[2]
        for k, _src, dst in task.plan():
            h = task.half_height(k)
            width = 2 * CUBE_HALF if k == 0 else 2 * CYLINDER_RADIUS
            top = surface + 2 * h
            grip_tip = max(surface + 0.008, top - 0.03)
            yield from self.pick(k, h, width, top + HOVER_CLEARANCE, grip_tip, open_g, surface + self.LIFT)
            # retreat until the fingertips are above the object's top before heading home sideways
            yield from self.place(k, h, task.slots[dst], surface, surface + self.LIFT, open_g, top + 0.005)
            yield from self.go_home(open_g)
        yield from self.hold_forever()


class Put2Expert(Expert):
    """Move block 0 then block 1 from the source bin into the basket, home between and after."""

    def script(self, env) -> Iterator[Command]:
        task: Put2Task = env.task
        open_g = task.home_opening
        grip_tip = BIN_FLOOR + 0.004
        clear_z = BIN_LOW_TOP + 0.01  # carried with the block's bottom 1 cm above the low walls
        hover_tip = BIN_FLOOR + 2 * BLOCK_HALF[2] + HOVER_CLEARANCE
        h = BLOCK_HALF[2]
        for k in range(2):
            yield from self.pick(k, h, 2 * BLOCK_HALF[1], hover_tip, grip_tip, open_g, clear_z)
            yield from self.place(k, h, task.place_xy("basket", k), BIN_FLOOR, clear_z, open_g, hover_tip)
            yield from self.go_home(open_g)
        yield from self.hold_forever()


EXPERTS = {"tap": TapExpert, "swap": SwapExpert, "put2": Put2Expert}


def make_expert(env) -> Expert:
    """The scripted expert for ``env.task`` and the episode ``env`` was just reset to."""
    try:
        cls = EXPERTS[env.task.name]
    except KeyError:
        raise ValueError(f"no expert for task {env.task.name!r}") from None
    return cls(env)
