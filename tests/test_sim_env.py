"""The simulated Piper workcell (dssp_sim): model, servo tracking, gripper, depth rendering, determinism."""

import math

import mujoco
import numpy as np
import pytest

import dssp_sim  # noqa: F401  (first: sets MUJOCO_GL before MuJoCo is imported)
from dssp_core.schema import DEFAULT_CONTROL_RATE_HZ
from dssp_data.arm_kinematics import flange_pose as dh_forward
from dssp_data.pointcloud.depth_frame import Intrinsics
from dssp_sim.env import DEPTH_MAX_M, DEPTH_MIN_M, DEPTH_UNIT, PiperEnv
from dssp_sim.experts import make_expert
from dssp_sim.tasks import HOME, SLOT_PAD_HALF, SwapTask
from hardware.piper.limits import GRIPPER_STROKE_MAX, JOINT_LOWER, JOINT_UPPER, JointLimits


@pytest.fixture
def tap_env():
    env = PiperEnv("tap", seed=0)
    yield env
    env.close()


@pytest.fixture
def swap_env():
    env = PiperEnv("swap", seed=1)
    yield env
    env.close()


# --------------------------------------------------------------------------------------------- model
def test_model_joint_limits_are_the_pipers(tap_env):
    m, arm = tap_env.model, tap_env.arm
    for i in range(6):
        jid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, f"joint{i + 1}")
        np.testing.assert_allclose(m.jnt_range[jid], [JOINT_LOWER[i], JOINT_UPPER[i]], atol=1e-9)
        assert m.jnt_limited[jid]
        np.testing.assert_allclose(m.actuator_ctrlrange[arm.actuators[i]], [JOINT_LOWER[i], JOINT_UPPER[i]], atol=1e-9)
    np.testing.assert_allclose(m.actuator_ctrlrange[arm.gripper_actuator], [0.0, GRIPPER_STROKE_MAX])
    assert m.nu == 7
    assert tap_env.control_rate_hz == DEFAULT_CONTROL_RATE_HZ == 10.0
    lim = JointLimits.piper()
    assert lim.violations(tap_env.state()).size == 0


def test_model_follows_the_dh_table(tap_env):
    m, d, arm = tap_env.model, tap_env.data, tap_env.arm
    flange = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "link6")
    rng = np.random.default_rng(0)
    for _ in range(5):
        q = rng.uniform(JOINT_LOWER, JOINT_UPPER)
        d.qpos[arm.qpos] = q
        mujoco.mj_kinematics(m, d)
        t = dh_forward(q)
        np.testing.assert_allclose(d.xpos[flange], t[:3, 3], atol=1e-9)
        np.testing.assert_allclose(d.xmat[flange].reshape(3, 3), t[:3, :3], atol=1e-9)


def test_two_arms_are_a_small_step():
    """The platform's second arm: the same body tree under another prefix and base pose."""
    from dssp_sim.mjcf import ArmIndex, arm_xml, build_model

    m = build_model(arms=(arm_xml("left_", (0.0, 0.3, 0.0)), arm_xml("right_", (0.0, -0.3, 0.0))))
    left, right = ArmIndex.find(m, "left_"), ArmIndex.find(m, "right_")
    assert m.nu == 14 and min(left.qpos.min(), right.qpos.min()) >= 0
    assert set(left.actuators).isdisjoint(right.actuators)
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    np.testing.assert_allclose(d.site_xpos[left.tcp_site] - d.site_xpos[right.tcp_site], [0.0, 0.6, 0.0], atol=1e-9)


def test_set_targets_clamps_to_the_limits(tap_env):
    tap_env.set_targets(JOINT_UPPER + 1.0, 1.0)
    np.testing.assert_allclose(tap_env.data.ctrl[tap_env.arm.actuators], JOINT_UPPER)
    assert tap_env.data.ctrl[tap_env.arm.gripper_actuator] == pytest.approx(GRIPPER_STROKE_MAX)
    tap_env.set_targets(JOINT_LOWER - 1.0, -0.5)
    np.testing.assert_allclose(tap_env.data.ctrl[tap_env.arm.actuators], JOINT_LOWER)
    assert tap_env.data.ctrl[tap_env.arm.gripper_actuator] == 0.0


def test_position_tracking_reaches_the_target(tap_env):
    target = HOME + np.array([0.25, 0.15, -0.2, 0.3, -0.25, 0.4])
    tap_env.set_targets(target, 0.0)
    tap_env.advance(1.0)
    assert np.abs(tap_env.joint_positions() - target).max() < 2e-3
    # a few millimetres at the tool
    tcp, _ = tap_env.tcp_pose()
    d = mujoco.MjData(tap_env.model)
    d.qpos[tap_env.arm.qpos] = target
    mujoco.mj_kinematics(tap_env.model, d)
    assert np.linalg.norm(tcp - d.site_xpos[tap_env.arm.tcp_site]) < 0.003


def test_step_counts_control_periods(tap_env):
    tap_env.step(tap_env.state())
    tap_env.step(tap_env.state())
    assert tap_env.steps == 2
    for _ in range(20):  # the CAN simulator's 200 Hz
        tap_env.advance(0.005)
    assert tap_env.steps == 3
    tap_env.advance(0.0035)  # remainders carry over
    tap_env.advance(0.0035)
    assert tap_env.data.time == pytest.approx(0.306)
    tap_env.reset(0)
    assert tap_env.steps == 0 and tap_env.data.time == 0.0


def test_gripper_closes_and_opens(tap_env):
    q = tap_env.joint_positions()
    tap_env.step(np.append(q, 1.0))
    tap_env.advance(0.4)
    assert tap_env.gripper_stroke() > GRIPPER_STROKE_MAX - 0.001
    assert tap_env.state()[6] == pytest.approx(1.0, abs=0.02)
    tap_env.step(np.append(q, 0.0))
    tap_env.advance(0.4)
    assert tap_env.gripper_stroke() < 0.001
    tap_env.step(np.append(q, 0.5))
    tap_env.advance(0.4)
    assert tap_env.state()[6] == pytest.approx(0.5, abs=0.02)


def test_gripper_grasps_and_lifts_an_object(swap_env):
    env = swap_env
    task: SwapTask = env.task
    expert = make_expert(env)
    k = 0  # the cube
    surface = 2 * SLOT_PAD_HALF[2]
    top = surface + 2 * task.half_height(k)
    z0 = task.objects.pos(env.data, k)[2]
    for q, g in expert.pick(k, task.half_height(k), 0.04, top + 0.015, top - 0.03, 0.85, surface + 0.02):
        env.step(np.append(q, g))
    assert task.objects.held(env, k)
    # keep lifting: the cube follows the fingers
    tcp0 = env.tcp_pose()[0]
    up = expert.solve(tcp0 + [0.0, 0.0, 0.06])
    for q, g in expert.move(up):
        env.step(np.append(q, g))
    env.advance(0.3)
    assert task.objects.held(env, k)
    lifted = task.objects.pos(env.data, k)[2] - z0
    assert lifted > 0.07
    assert env.state()[6] == pytest.approx(0.04 / GRIPPER_STROKE_MAX, abs=0.05)  # the cube's width


# --------------------------------------------------------------------------------------------- camera
def test_render_depth_shape_units_and_pose(tap_env):
    depth, unit, intr, cam_to_base = tap_env.render_depth()
    assert depth.shape == (120, 160) and depth.dtype == np.uint16
    assert unit == DEPTH_UNIT == 0.00025
    assert isinstance(intr, Intrinsics)
    assert (intr.width, intr.height) == (160, 120)
    # 70 degrees horizontal field of view, square pixels
    assert 2 * math.degrees(math.atan(0.5 * intr.width / intr.fx)) == pytest.approx(70.0, abs=0.01)
    assert intr.fx == intr.fy
    assert cam_to_base.shape == (4, 4)
    r = cam_to_base[:3, :3]
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-9)
    assert np.linalg.det(r) == pytest.approx(1.0)
    assert r[2, 2] < -0.3  # the optical axis looks down at the table
    valid = depth > 0
    assert 0.3 < valid.mean() < 0.95  # the table and the arm, and nothing above the far edge
    metres = depth[valid] * unit
    assert metres.min() >= DEPTH_MIN_M and metres.max() <= DEPTH_MAX_M


def test_render_depth_matches_ray_casting(swap_env):
    """Every sampled pixel's ray, built from the returned intrinsics and pose, hits the scene at the
    rendered depth, and zero pixels are exactly those whose rays hit nothing within range."""
    env = swap_env
    depth, unit, intr, cam_to_base = env.render_depth()
    r, t = cam_to_base[:3, :3], cam_to_base[:3, 3]
    group = np.array([1, 1, 1, 0, 0, 0], np.uint8)
    gid = np.zeros(1, np.int32)
    errors, mismatched, n = [], 0, 0
    for v in range(0, intr.height, 3):
        for u in range(0, intr.width, 3):
            ray = r @ np.array([(u - intr.ppx) / intr.fx, (v - intr.ppy) / intr.fy, 1.0])
            norm = np.linalg.norm(ray)
            dist = mujoco.mj_ray(env.model, env.data, t, ray / norm, group, 1, -1, gid)
            z = dist / norm if dist >= 0 else -1.0
            in_range = DEPTH_MIN_M <= z <= DEPTH_MAX_M
            n += 1
            if (depth[v, u] > 0) != in_range:
                mismatched += 1
            elif in_range:
                errors.append(abs(z - depth[v, u] * unit))
    errors = np.array(errors)
    assert mismatched <= 0.005 * n  # only at curved silhouettes (rendered as facets)
    assert np.percentile(errors, 99) < 0.001 and errors.max() < 0.005
    assert (depth == 0).any() and (depth > 0).any()


@pytest.mark.parametrize("k", [0, 1])
def test_known_point_deprojects_to_its_position(swap_env, k):
    """The top centre of an object at a known pose, deprojected with the returned intrinsics and
    camera_to_base, lands within 1 cm of where it is."""
    env = swap_env
    task: SwapTask = env.task
    top = task.objects.pos(env.data, k) + [0.0, 0.0, task.half_height(k)]
    depth, unit, intr, cam_to_base = env.render_depth()
    p_cam = np.linalg.inv(cam_to_base) @ np.append(top, 1.0)
    u = int(round(intr.ppx + intr.fx * p_cam[0] / p_cam[2]))
    v = int(round(intr.ppy + intr.fy * p_cam[1] / p_cam[2]))
    z = depth[v, u] * unit
    assert z > 0
    point = cam_to_base @ np.array([z * (u - intr.ppx) / intr.fx, z * (v - intr.ppy) / intr.fy, z, 1.0])
    assert np.linalg.norm(point[:3] - top) < 0.01


def test_render_depth_from_another_thread(tap_env):
    """A camera thread and the main thread can both render (the GL context lives in one render thread)."""
    import threading

    main = tap_env.render_depth()[0]
    out = {}
    thread = threading.Thread(target=lambda: out.setdefault("depth", tap_env.render_depth()[0]))
    thread.start()
    thread.join()
    np.testing.assert_array_equal(out["depth"], main)
    tap_env.close()
    np.testing.assert_array_equal(tap_env.render_depth()[0], main)  # usable again after close


def _render_threads() -> int:
    import threading

    return sum(t.name == "dssp-sim-render" and t.is_alive() for t in threading.enumerate())


def _piper_env():
    env = PiperEnv("tap", seed=0)
    return env, [env.render_depth]


def _calibration_twin():
    from dssp_sim.calibration_twin import CalibrationTwin

    twin = CalibrationTwin("eye-to-hand", size=(48, 64))
    return twin, [twin.render_depth, twin.render_rgb]


def _metaworld_env():
    from dssp_sim.metaworld_env import MetaWorldEnv

    env = MetaWorldEnv("button-press", seed=0, render_size=(48, 64))
    return env, [env.render_depth]


@pytest.mark.parametrize("make", [_piper_env, _calibration_twin, _metaworld_env])
def test_render_threads_stop_on_close_and_when_their_owner_is_collected(make):
    """A GL context's thread (one per kind of image) starts with its first render and stops on close() or when the
    env that rendered is garbage."""
    import gc

    before = _render_threads()
    env, renders = make()
    assert _render_threads() == before  # started by the first render, not by the env
    for i in range(len(renders)):  # no loop variable left holding a bound method (and the env)
        renders[i]()
    assert _render_threads() == before + len(renders)
    env.close()
    assert _render_threads() == before
    renders[0]()  # usable again after close
    assert _render_threads() == before + 1
    del env, renders
    gc.collect()
    assert _render_threads() == before


def test_render_depth_is_fast(tap_env):
    import time

    tap_env.render_depth()
    t0 = time.perf_counter()
    for _ in range(10):
        tap_env.render_depth()
    per_frame = (time.perf_counter() - t0) / 10
    assert per_frame < 0.05  # about 3 ms on 2 CPU cores; generous for shared machines


# --------------------------------------------------------------------------------------------- determinism
def _run(env, n):
    expert = make_expert(env)
    states = []
    for _ in range(n):
        env.step(expert.act(env))
        states.append(env.state())
    return np.array(states)


@pytest.mark.parametrize("task", ["tap", "swap", "put2"])
def test_same_seed_same_episode(task):
    a, b = PiperEnv(task, seed=7), PiperEnv(task, seed=7)
    sa, sb = _run(a, 40), _run(b, 40)
    np.testing.assert_array_equal(sa, sb)
    # a used env reset to the seed replays it too
    a.reset(7)
    np.testing.assert_array_equal(_run(a, 40), sa)
    c = PiperEnv(task, seed=8)
    assert not np.array_equal(_run(c, 40), sa)


def test_reset_randomises_the_scene():
    env = PiperEnv("tap", seed=0)
    positions, starts = set(), set()
    for seed in range(4):
        env.reset(seed)
        positions.add(tuple(np.round(env.task.button_position(env)[:2], 6)))
        starts.add(tuple(np.round(env.joint_positions(), 6)))
        assert np.abs(env.joint_positions() - HOME).max() <= 0.04 + 1e-9
    assert len(positions) == 4 and len(starts) == 4


def test_unknown_task_is_rejected():
    with pytest.raises(ValueError, match="unknown task"):
        PiperEnv("juggle")
