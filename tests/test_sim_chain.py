"""The simulation behind the robot's own interfaces: MuJoCo under the Piper CAN protocol and the RealSense
software device; expert collection into a DP3 dataset; closed-loop evaluation through the whole chain."""

import hashlib
import json
import threading

import numpy as np
import pytest
from rrd import read_rrd, text_rows

from dssp_core.errors import ConfigError
from dssp_data.pointcloud import frame_to_cloud
from dssp_data.replay_buffer import ReplayBuffer
from dssp_deploy.schedules import Ensemble, RealTimeChunking
from dssp_sim.env import PiperEnv
from dssp_sim.evaluate import wilson_interval
from dssp_sim.mujoco_arm import MujocoPiper
from dssp_sim.mujoco_camera import MujocoCamera
from dssp_sim.settings import cloud_config_for
from dssp_sim.sim_cli import main as sim_main
from hardware.piper.arm import PiperArm
from hardware.piper.piper_robot import PiperRobot


def test_wilson_interval_matches_the_formula_at_known_points():
    assert wilson_interval(0, 0) == (0.0, 0.0)
    lo, hi = wilson_interval(0, 20)
    assert lo == 0.0 and hi == pytest.approx(0.1611, abs=1e-4)
    lo, hi = wilson_interval(20, 20)
    assert lo == pytest.approx(0.8389, abs=1e-4) and hi == 1.0
    lo, hi = wilson_interval(17, 20)
    assert (lo, hi) == (pytest.approx(0.6396, abs=1e-4), pytest.approx(0.9476, abs=1e-4))


def test_mujoco_arm_moves_only_through_can_frames():
    env = PiperEnv("tap", seed=3)
    env.reset(seed=3)
    channel = "dssp-test-mujoco-arm"
    arm = MujocoPiper(env, channel)
    arm.start(thread=False)
    robot = PiperRobot([PiperArm(channel, "virtual")])
    stop = threading.Event()

    def pump():
        while not stop.is_set():
            arm.step(0.0)
            stop.wait(0.003)

    try:
        with robot:
            t = threading.Thread(target=pump, daemon=True)
            t.start()
            robot.enable(timeout=3.0)
            stop.set()
            t.join()
            start = env.joint_positions().copy()
            for _ in range(3):  # the feedback is the MuJoCo arm's pose
                arm.step(0.1)
            state = robot.state()
            assert np.allclose(state.position[:6], env.joint_positions(), atol=1e-4)
            target = np.concatenate([start + np.array([0.1, 0.05, -0.05, 0.0, 0.05, 0.0]), [0.5]])
            robot.command(target)
            for _ in range(15):
                arm.step(0.1)
            assert np.allclose(env.joint_positions(), target[:6], atol=0.02)  # the physics tracked the CAN target
            assert env.data.ctrl[env.arm.gripper_actuator] == pytest.approx(0.5 * 0.07, abs=1e-6)  # opening → stroke
    finally:
        arm.stop()


def test_rendered_depth_goes_through_the_software_device_and_the_pipeline():
    env = PiperEnv("tap", seed=0)
    env.reset(seed=0)
    with MujocoCamera(env) as camera:
        frame = camera.capture()
        depth, unit, intr, _ = env.render_depth()
        assert np.array_equal(frame.depth, depth) and frame.intrinsics.width == intr.width
        cloud, info = frame_to_cloud(frame, cloud_config_for(), camera.camera_to_base)
    # the tabletop crop leaves the button (about 60 depth pixels at 160 x 120); the rest repeats real points
    assert cloud.shape == (256, 3) and 0 < info.n_padded < 256 - 30
    assert len(np.unique(cloud, axis=0)) == 256 - info.n_padded
    lo, hi = np.array(cloud_config_for().crop_min), np.array(cloud_config_for().crop_max)
    assert np.all(cloud >= lo - 1e-6) and np.all(cloud <= hi + 1e-6)


def test_swap_sees_its_small_objects_in_a_finer_cloud():
    """swap renders at 320 x 240 with 5 mm voxels: its cube and cylinder fill the 256 points (at the default
    160 x 120 and 1 cm the whole scene gave about 70, the rest padding)."""
    from dssp_sim.settings import render_size_for

    env = PiperEnv("swap", seed=0)
    env.reset(seed=0)
    assert env.render_size == render_size_for("swap") == (240, 320) and PiperEnv("tap").render_size == (120, 160)
    config = cloud_config_for(task="swap")
    assert config.voxel_size == 0.005 and cloud_config_for(task="tap").voxel_size == 0.01
    with MujocoCamera(env) as camera:
        fine, info = frame_to_cloud(camera.capture(), config, camera.camera_to_base)
        _, coarse = frame_to_cloud(camera.capture(), cloud_config_for(), camera.camera_to_base)
    assert info.n_padded == 0 and info.n_after_voxel > 256 > 2 * coarse.n_after_voxel
    for k in range(2):  # each object is in the cloud: points within its footprint, above the pads
        xy = env.task.objects.pos(env.data, k)[:2]
        assert np.sum(np.linalg.norm(fine[:, :2] - xy, axis=1) < 0.02) >= 10


def test_collect_writes_a_dp3_dataset_of_successful_episodes(tmp_path, capsys):
    out = tmp_path / "tap.zarr"
    assert (
        sim_main(["collect", "--task", "tap", "--episodes", "2", "--out", str(out), "--no-progress", "--points", "128"])
        == 0
    )
    assert "kept 2 successful tap episodes of 2 tried" in capsys.readouterr().out
    buffer = ReplayBuffer.load(out)
    assert buffer.n_episodes == 2
    episode = buffer.episode(0)
    assert episode.point_cloud.shape[1:] == (128, 3) and episode.state.shape[1] == 7 and episode.action.shape[1] == 7
    assert buffer.attrs["control_rate_hz"] == 10.0 and buffer.attrs["task"] == "tap"
    assert buffer.attrs["pointcloud"]["n_points"] == 128 and len(buffer.attrs["camera_to_base"]) == 4
    # appending keeps what was there
    assert (
        sim_main(
            [
                "collect",
                "--task",
                "tap",
                "--episodes",
                "1",
                "--out",
                str(out),
                "--seed",
                "7",
                "--no-progress",
                "--points",
                "128",
            ]
        )
        == 0
    )
    assert ReplayBuffer.load(out).n_episodes == 3


def test_bad_input_is_one_line(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        sim_main(["collect", "--task", "juggle", "--episodes", "1", "--out", str(tmp_path / "x.zarr")])
    assert exc.value.code == 2 and "unknown task 'juggle'" in capsys.readouterr().err
    assert (
        sim_main(["eval", "--model", str(tmp_path / "none"), "--task", "tap", "--episodes", "1", "--no-progress"]) == 2
    )
    assert "does not exist" in capsys.readouterr().err


@pytest.fixture(scope="module")
def sim_model(tmp_path_factory):
    """A briefly trained sim-preset model on a few collected tap episodes (its model directory)."""
    from dssp_train.cli.train import main as train_main
    from export.to_onnx import main as export_main

    root = tmp_path_factory.mktemp("sim_model")
    data = root / "tap.zarr"
    assert sim_main(["collect", "--task", "tap", "--episodes", "3", "--out", str(data), "--no-progress"]) == 0
    assert (
        train_main(
            [
                "--data",
                str(data),
                "--out",
                str(root / "run"),
                "--preset",
                "sim",
                "--steps",
                "20",
                "--set",
                "train.val_every=20",
                "--no-progress",
            ]
        )
        == 0
    )
    assert export_main([str(root / "run"), "-o", str(root / "model"), "--skip-verify", "--quantize", "none"]) == 0
    return root / "model"


def test_eval_runs_the_whole_chain(sim_model, tmp_path, capsys):
    out = tmp_path / "eval.json"
    strips = tmp_path / "strips"
    rrd = tmp_path / "eval.rrd"
    assert (
        sim_main(
            [
                "eval",
                "--model",
                str(sim_model),
                "--task",
                "tap",
                "--episodes",
                "2",
                "--seed",
                "5",
                "--json",
                str(out),
                "--strips",
                str(strips),
                "--threads",
                "1",
                "--no-progress",
                "--rerun-save",
                str(rrd),
            ]
        )
        == 0
    )
    text = capsys.readouterr().out
    assert "tap: success" in text and "Wilson interval" in text and "| 5 |" in text and "| 6 |" in text
    # the Rerun views: both episodes on one timeline, one step per tick
    steps = [e["steps"] for e in json.loads(out.read_text())["episodes"]]
    ticks, _, _ = read_rrd(rrd)
    assert (
        ticks["safety/held"] == list(range(sum(steps))) and f"rerun views: {sum(steps)} ticks logged, 0 dropped" in text
    )
    assert text_rows(rrd, "episode") == ["tap seed 5", "tap seed 6"] and ticks["world/arm0/chunk"]
    result = json.loads(out.read_text())
    assert result["n"] == 2 and len(result["episodes"]) == 2
    manifest = json.loads((sim_model / "dssp_model.json").read_text())
    assert result["model"] == {  # the record names the model it scored
        "weights_sha256": manifest["source"]["sha256"],
        "run": "run",
        "step": manifest["source"]["step"],
        "manifest_sha256": hashlib.sha256((sim_model / "dssp_model.json").read_bytes()).hexdigest(),
    }
    for e in result["episodes"]:
        assert e["steps"] > 0 and (e["success"] or e["reason"])  # every failure has a reason
        assert e["chunk_ms_p50"] > 0
    assert sorted(p.name for p in strips.glob("*.png")) == ["tap_seed5.png", "tap_seed6.png"]


def test_state_token_noise_changes_the_actions_not_the_chain(sim_model):
    from dssp_sim.evaluate import evaluate

    clean = evaluate(sim_model, "tap", 1, seed=3, threads=1, progress=False)
    noisy = evaluate(sim_model, "tap", 1, seed=3, threads=1, state_token_noise=0.15, progress=False)
    again = evaluate(sim_model, "tap", 1, seed=3, threads=1, progress=False)
    assert clean.episodes[0].info == again.episodes[0].info and clean.episodes[0].steps == again.episodes[0].steps
    assert noisy.state_token_noise == 0.15 and noisy.episodes[0].steps > 0
    assert 0.1 < clean.z_rms < 10 and noisy.to_dict()["noise_over_z_rms"] == pytest.approx(0.15 / noisy.z_rms)


def test_temporal_ensembling_reaches_the_loop_and_the_record(sim_model):
    """dssp-sim eval --smoothing ensemble: the Piper's loop computes a chunk every --ensemble-every ticks (it acted on
    every tick it observed), and the result records the settings."""
    from dssp_sim.evaluate import evaluate

    result = evaluate(sim_model, "tap", 1, seed=3, threads=1, progress=False, schedule=Ensemble(every=2, decay=0.0))
    record = result.to_dict()
    assert (record["smoothing"], record["ensemble_every"], record["ensemble_decay"]) == ("ensemble", 2, 0.0)
    acted, chunks = result.latency_ms["observe"]["n"], result.latency_ms["chunk"]["n"]
    assert acted > 2 and chunks == (acted + 1) // 2
    assert evaluate(sim_model, "tap", 0, progress=False).to_dict()["smoothing"] == "none"
    with pytest.raises(ConfigError, match=r"--ensemble-every 1000: .* executes H_a = 4 actions of a chunk"):
        evaluate(sim_model, "tap", 1, progress=False, schedule=Ensemble(every=1000))


def test_inference_delay_and_real_time_chunking_reach_the_loop_and_the_record(sim_model, tmp_path):
    """dssp-sim eval --inject-delay 150 (2 ticks at 10 Hz): without smoothing every chunk is waited for (2 holds a
    chunk); with --smoothing rtc (the same run exported with --inpainting) only the first is, and the record has the
    commanded jerk at the ticks a new chunk took over."""
    from dssp_sim.evaluate import evaluate
    from export.to_onnx import main as export_main

    inpainting = tmp_path / "model_rtc"
    assert (
        export_main(
            [
                str(sim_model.parent / "run"),
                "-o",
                str(inpainting),
                "--inpainting",
                "--skip-verify",
                "--quantize",
                "none",
                "--format",
                "onnx",
                "--no-fused",
            ]
        )
        == 0
    )
    stalled = evaluate(inpainting, "tap", 1, seed=3, threads=1, progress=False, inject_delay_ms=150)
    chunks = stalled.latency_ms["chunk"]["n"]
    assert stalled.injected_delay_ticks == 2 and chunks > 2
    assert stalled.episodes[0].safety_events.get("hold", 0) >= 2 * (chunks - 1)  # the loop waits for every chunk
    rtc = evaluate(
        inpainting, "tap", 1, seed=3, threads=1, progress=False, schedule=RealTimeChunking(), inject_delay_ms=150
    )
    record = rtc.to_dict()
    assert (record["smoothing"], record["injected_delay_ticks"], record["rtc_delay_ticks"]) == ("rtc", 2, 2)
    jerk = record["boundary_jerk"]
    assert jerk["boundary_ticks"] > 0 and jerk["other_ticks"] > 0 and jerk["at_boundaries"] > 0


def test_the_scripted_expert_drives_the_same_loop(tmp_path, capsys):
    """dssp-sim eval --expert: the task's expert as the control loop's policy source, through the safety layer and
    the CAN bus — it passes every tap episode (the task's ceiling through the chain), its decision scored the same way."""
    out = tmp_path / "expert.json"
    assert (
        sim_main(
            [
                "eval",
                "--expert",
                "--task",
                "tap",
                "--episodes",
                "2",
                "--seed",
                "1000",
                "--json",
                str(out),
                "--no-progress",
            ]
        )
        == 0
    )
    text = capsys.readouterr().out
    assert "tap: success 2/2" in text and "memory decision: right in 2 of the 2" in text
    result = json.loads(out.read_text())
    assert result["model_dir"] == "expert" and [e["seed"] for e in result["episodes"]] == [1000, 1001]
    assert all(e["success"] and e["holds"] == 0 and e["chunk_ms_p50"] is None for e in result["episodes"])


@pytest.mark.parametrize(
    "argv, fragment",
    [
        (["--expert", "--noise", "0.1"], "--noise is a model's setting: it goes with --model, not --expert"),
        (["--expert", "--task", "metaworld/reach"], "--expert drives the Piper's control loop"),
        (
            ["--expert", "--smoothing", "ensemble"],
            "--smoothing is a model's setting: it goes with --model, not --expert",
        ),
        (
            ["--model", "m", "--ensemble-decay", "0"],
            "--ensemble-decay is a setting of temporal ensembling: it goes with --smoothing ensemble",
        ),
        (["--expert", "--prefetch"], "--prefetch is a model's setting: it goes with --model, not --expert"),
        (["--expert", "--limit-excludes-holds"], "--limit-excludes-holds is a model's setting"),
        (["--model", "m", "--prefetch", "--smoothing", "ensemble"], "--prefetch does not combine with --smoothing"),
    ],
)
def test_expert_flags_that_do_not_apply_are_one_line(argv, fragment, capsys):
    task = [] if "--task" in argv else ["--task", "tap"]
    assert sim_main(["eval", *argv, *task, "--episodes", "1", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and fragment in err[0], err


def test_holds_can_be_left_out_of_the_step_limit_and_prefetch_hides_the_delay(sim_model):
    """--limit-excludes-holds: each tick spent waiting for a chunk lengthens the episode's budget by one, so waiting
    is not scored as running out of time; --prefetch starts each chunk early by the delay, so the loop does not wait."""
    from dssp_deploy.schedules import Plain
    from dssp_sim.evaluate import evaluate
    from dssp_sim.tasks import make_task

    limit = make_task("tap").max_steps
    run = lambda **kw: evaluate(sim_model, "tap", 2, seed=1000, threads=1, progress=False, inject_delay_ms=200, **kw)  # noqa: E731
    counted, excluded = run(), run(limit_excludes_holds=True)
    for result in (counted, excluded):
        assert not any(e.success for e in result.episodes), "the briefly trained model is not expected to solve tap"
    assert counted.episodes[0].steps == limit and counted.episodes[0].holds > 0
    for episode in excluded.episodes:  # each episode its own budget: the first one's waits do not carry over
        assert episode.holds > 0 and episode.steps == limit + episode.holds  # the same budget of ticks that moved
        assert not episode.safety_events.get("observation_out_of_range")  # every hold here was a wait
    assert excluded.to_dict()["limit_excludes_holds"] and not counted.to_dict()["limit_excludes_holds"]
    prefetched = run(schedule=Plain(prefetch=True))
    assert prefetched.episodes[0].holds < counted.episodes[0].holds
    assert prefetched.episodes[0].steps == limit
