"""The memory tasks of dssp_sim and their scripted experts: success, every failure reason, and the
aliased moments (same observation, different expert action) that make each task need memory."""

import mujoco
import numpy as np
import pytest

import dssp_sim  # noqa: F401  (first: sets MUJOCO_GL before MuJoCo is imported)
from dssp_sim.env import PiperEnv
from dssp_sim.experts import MAX_GRIPPER_STEP, MAX_JOINT_STEP, make_expert
from dssp_sim.tasks import BIN_FLOOR, BLOCK_HALF, HOME, SLOT_TOLERANCE, TAP_PRESSES

SAFETY_JOINT_STEP = 0.05  # rad per tick the safety layer clips above


def _episode(env, render: bool = False, expert=None):
    """Run the expert to the end: per step dicts (state (7,), action (7,), phase, info, depth or None)."""
    expert = expert or make_expert(env)
    log = []
    while not env.status().done:
        record = {"state": env.state(), "info": env.status().info, "depth": env.render_depth()[0] if render else None}
        record["action"] = expert.act(env)
        record["phase"] = expert.phase
        log.append(record)
        env.step(record["action"])
    return log


@pytest.mark.parametrize("task,seeds", [("tap", (0, 1)), ("swap", (0, 5)), ("put2", (0, 1))])
def test_expert_succeeds_with_small_steps(task, seeds):
    env = PiperEnv(task)
    for seed in seeds:
        env.reset(seed)
        log = _episode(env)
        status = env.status()
        assert status.done and status.success and status.reason == "", (seed, status)
        assert 50 <= len(log) <= env.max_steps
        actions = np.array([r["action"] for r in log])
        steps = np.abs(np.diff(np.vstack([log[0]["state"], actions]), axis=0))
        assert steps[:, :6].max() <= MAX_JOINT_STEP + 1e-9 < SAFETY_JOINT_STEP
        assert steps[:, 6].max() <= MAX_GRIPPER_STEP + 1e-9
        assert np.abs(env.joint_positions() - HOME).max() < 0.05


@pytest.mark.parametrize("task", ["tap", "swap", "put2"])
def test_the_experts_memory_decision_is_scored_right(task):
    env = PiperEnv(task)
    env.reset(3)
    _episode(env)
    info = env.status().info
    decision = env.task.decision(info)
    assert decision["reached"] and decision["correct"], (decision, info)
    if task == "swap":
        assert info["moves"] == info["plan"] and len(info["moves"]) == 3
    if task == "put2":
        assert info["reaches"] == [1, 1, 0]  # one reach for each block, none after both


@pytest.mark.parametrize(
    "task, info, reached, correct",
    [
        ("tap", {"presses": 2}, True, False),
        ("tap", {"presses": 4}, True, False),
        ("swap", {"moves": [], "plan": ["cube A->C", "cylinder B->A", "cube C->B"]}, False, None),
        (
            "swap",
            {"moves": ["cube A->C", "cube C->B"], "plan": ["cube A->C", "cylinder B->A", "cube C->B"]},
            True,
            False,
        ),
        ("swap", {"moves": ["cube A->C"], "plan": ["cube A->C", "cylinder B->A", "cube C->B"]}, True, False),
        ("put2", {"in_basket": 0, "reaches": [3, 0, 0]}, False, None),
        ("put2", {"in_basket": 1, "reaches": [1, 0, 0]}, True, False),
        ("put2", {"in_basket": 1, "reaches": [1, 1, 0]}, True, True),
        ("put2", {"in_basket": 2, "reaches": [1, 1, 0]}, True, True),
        (
            "put2",
            {"in_basket": 2, "reaches": [1, 1, 1]},
            True,
            False,
        ),  # back into the source bin after both: memory failed
        ("put2", {"in_basket": 1, "reaches": [1, 1, 2]}, True, False),  # one taken out again after both were in
    ],
)
def test_a_wrong_or_unreached_memory_decision_is_told_apart(task, info, reached, correct):
    from dssp_sim.tasks import TASKS

    decision = TASKS[task].decision(info)
    assert (decision["reached"], decision["correct"]) == (reached, correct)


def test_swap_randomises_both_arrangements_and_moves_the_cube_first():
    env = PiperEnv("swap")
    seen = set()
    for seed in range(12):
        env.reset(seed)
        seen.add((env.task.first, env.task.start))
        assert env.task.plan()[0][0] == 0  # the cube goes to the buffer first: no coin toss at the start
    assert seen == {("A", ("A", "B")), ("B", ("B", "A"))}  # both directions, each following from the layout
    env.reset(0, {"first": "B", "a_object": "cube"})  # the other object first, on request
    assert env.task.plan()[0] == (1, "B", "C")
    with pytest.raises(ValueError, match="unknown reset options"):
        env.reset(0, {"colour": "red"})


# --------------------------------------------------------------------------------------------- failures
def test_tap_fourth_press_is_a_wrong_count():
    env = PiperEnv("tap", seed=2)
    expert = make_expert(env)
    while not (env.task.presses == TAP_PRESSES and expert.phase == "hover_dwell"):
        env.step(expert.act(env))
    assert not env.status().done
    press, hover = expert.waypoints["press"], expert.waypoints["hover"]
    for q in (press, press, press, hover, hover, hover):
        env.step(np.append(q, 0.0))
    status = env.status()
    assert status.done and not status.success and status.reason == "wrong count"
    assert status.info["presses"] == TAP_PRESSES + 1


@pytest.mark.parametrize("task", ["tap", "swap", "put2"])
def test_timeout(task):
    env = PiperEnv(task, seed=0)
    env.max_steps = 4
    for _ in range(3):
        env.step(env.state())
        assert not env.status().done
    env.step(env.state())
    status = env.status()
    assert status.done and not status.success and status.reason == "timeout"
    env.step(env.state())  # the status stays latched
    assert env.status().reason == "timeout"


def test_tap_going_home_early_does_not_succeed():
    env = PiperEnv("tap", seed=1)
    for _ in range(10):
        env.step(np.append(HOME, 0.0))
    assert env.at_home() and not env.status().done and env.status().info["presses"] == 0


@pytest.mark.parametrize("task", ["swap", "put2"])
def test_dropping_the_carried_object_is_a_failure(task):
    env = PiperEnv(task, seed=3)
    expert = make_expert(env)
    while expert.phase != "carry":
        env.step(expert.act(env))
    held = [k for k in range(2) if env.task.objects.held(env, k)]
    assert len(held) == 1
    # carry it away from every slot and bin, and let go above the bare table
    away = expert.solve([0.2, -0.18, 0.09])
    for q, g in expert.move(away):
        env.step(np.append(q, g))
    for _ in range(12):
        env.step(np.append(away, 1.0))
        if env.status().done:
            break
    status = env.status()
    assert status.done and not status.success and status.reason == "dropped object"


def test_swap_object_left_between_slots_is_dropped():
    env = PiperEnv("swap", seed=4)
    k = 0
    pos = env.task.objects.pos(env.data, k)
    env.task.objects.place(env.data, k, [pos[0] - 2 * SLOT_TOLERANCE, pos[1], pos[2]])
    mujoco.mj_forward(env.model, env.data)
    env.step(env.state())
    assert env.status().reason == "dropped object"


# --------------------------------------------------------------------------------------------- hidden blocks
def test_put2_blocks_in_the_bins_are_hidden_from_the_camera():
    env = PiperEnv("put2", seed=5, render_size=(240, 320))
    objs = env.task.objects
    with_blocks = env.render_depth()[0]
    for k in range(2):
        objs.place(env.data, k, [0.0, 0.5 + 0.1 * k, -0.5])  # under the table
    mujoco.mj_forward(env.model, env.data)
    without = env.render_depth()[0]
    for k in range(2):
        xy = env.task.place_xy("basket", k)
        objs.place(env.data, k, [xy[0], xy[1], BIN_FLOOR + BLOCK_HALF[2]], env.task.bin_yaw["basket"])
    mujoco.mj_forward(env.model, env.data)
    in_basket = env.render_depth()[0]
    np.testing.assert_array_equal(with_blocks, without)
    np.testing.assert_array_equal(in_basket, without)
    env.close()


# --------------------------------------------------------------------------------------------- aliasing
STATE_TOL = 2e-3  # rad (and gripper opening): "the same proprioception"
DEPTH_MAD_TOL = 0.5e-3  # m, mean absolute depth difference over pixels valid in both images


def _decision(log, phase, after_phase, pred=lambda r: True, nth=0):
    """Index of the ``nth`` step whose action starts ``phase`` right after ``after_phase``."""
    hits = [
        i
        for i in range(1, len(log))
        if log[i]["phase"] == phase and log[i - 1]["phase"] == after_phase and pred(log[i])
    ]
    return hits[nth]


def _assert_aliased(a, b, log_a, ia, log_b, ib):
    """Near-identical observation (state and depth) at a and b, clearly different expert actions (at
    once, and over the next steps: an action chunk of up to 4)."""
    assert np.abs(a["state"] - b["state"]).max() < STATE_TOL
    da, db = a["depth"].astype(np.float64), b["depth"].astype(np.float64)
    valid = (da > 0) & (db > 0)
    assert valid.mean() > 0.5
    assert ((da > 0) != (db > 0)).mean() < 0.002
    assert np.abs(da - db)[valid].mean() * 0.00025 < DEPTH_MAD_TOL
    assert np.abs(a["action"] - b["action"]).max() > 5 * STATE_TOL
    n = min(4, len(log_a) - ia, len(log_b) - ib)  # an episode may end (success) within the chunk
    assert n >= 2
    chunk_a = np.array([r["action"] for r in log_a[ia : ia + n]])
    chunk_b = np.array([r["action"] for r in log_b[ib : ib + n]])
    assert np.abs(chunk_a - chunk_b).max() > 0.05


def test_tap_aliasing_after_second_and_third_press():
    """At the hover pose after tap 2 and after tap 3 the arm and the (sprung-back) button look the same;
    the expert taps again after the second and goes home after the third."""
    env = PiperEnv("tap", seed=3)
    log = _episode(env, render=True)
    assert env.status().success
    i = _decision(log, "press", "hover_dwell", lambda r: r["info"]["presses"] == 2)
    j = _decision(log, "home", "hover_dwell")
    assert log[j]["info"]["presses"] == 3
    _assert_aliased(log[i], log[j], log, i, log, j)
    env.close()


def test_put2_aliasing_at_home_between_and_after_the_transfers():
    """At home after the first block and after the second, both blocks are hidden in the bins: the same
    observation; the expert fetches the second block after the first and stays after the second."""
    env = PiperEnv("put2", seed=3)
    log = _episode(env, render=True)
    assert env.status().success
    i = _decision(log, "approach", "home_dwell")
    j = _decision(log, "done", "home_dwell")
    assert log[i]["info"]["in_basket"] == 1 and log[j]["info"]["in_basket"] == 2
    _assert_aliased(log[i], log[j], log, i, log, j)
    env.close()


def test_swap_aliasing_across_directions():
    """The cube in the buffer, the cylinder on B, A empty and the arm at home: reached after the first
    move when the cube started on A, and after the second move when it started on B (the cube goes first
    in both). The expert then moves the cylinder B->A in the first case and the cube
    C->A in the second: only the history tells which (the slots are the same: same seed)."""
    env_a = PiperEnv("swap", seed=6)
    env_a.reset(6, {"a_object": "cube"})
    log_a = _episode(env_a, render=True)
    env_b = PiperEnv("swap", seed=6)
    env_b.reset(6, {"a_object": "cylinder"})
    log_b = _episode(env_b, render=True)
    assert env_a.status().success and env_b.status().success
    i = _decision(log_a, "approach", "home_dwell", nth=0)
    j = _decision(log_b, "approach", "home_dwell", nth=1)
    layout = {"cube": "C", "cylinder": "B"}
    assert log_a[i]["info"]["slots"] == layout and log_b[j]["info"]["slots"] == layout
    _assert_aliased(log_a[i], log_b[j], log_a, i, log_b, j)
    env_a.close()
    env_b.close()
