"""The simulation behind the robot's own interfaces: MuJoCo under the Piper CAN protocol and the RealSense
software device; expert collection into a DP3 dataset; closed-loop evaluation through the whole chain."""

import json
import os
import shutil
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

from rrd import read_rrd, text_rows

import numpy as np
import pytest

from dssp_sim.sim_cli import main as sim_main
from dssp_sim.env import PiperEnv
from dssp_sim.evaluate import wilson_interval
from dssp_sim.settings import cloud_config_for
from dssp_sim.mujoco_arm import MujocoPiper
from dssp_sim.mujoco_camera import MujocoCamera
from dssp_data.replay_buffer import ReplayBuffer
from hardware.piper.arm import PiperArm
from hardware.piper.piper_robot import PiperRobot
from hardware.pointcloud import frame_to_cloud


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
            time.sleep(0.003)

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
    assert sim_main(["collect", "--task", "tap", "--episodes", "2", "--out", str(out), "--no-progress", "--points", "128"]) == 0
    assert "kept 2 successful tap episodes of 2 tried" in capsys.readouterr().out
    buffer = ReplayBuffer.load(out)
    assert buffer.n_episodes == 2
    episode = buffer.episode(0)
    assert episode.point_cloud.shape[1:] == (128, 3) and episode.state.shape[1] == 7 and episode.action.shape[1] == 7
    assert buffer.attrs["control_rate_hz"] == 10.0 and buffer.attrs["task"] == "tap"
    assert buffer.attrs["pointcloud"]["n_points"] == 128 and len(buffer.attrs["camera_to_base"]) == 4
    # appending keeps what was there
    assert sim_main(["collect", "--task", "tap", "--episodes", "1", "--out", str(out), "--seed", "7", "--no-progress", "--points", "128"]) == 0
    assert ReplayBuffer.load(out).n_episodes == 3


def test_bad_input_is_one_line(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        sim_main(["collect", "--task", "juggle", "--episodes", "1", "--out", str(tmp_path / "x.zarr")])
    assert exc.value.code == 2 and "unknown task 'juggle'" in capsys.readouterr().err
    assert sim_main(["eval", "--model", str(tmp_path / "none"), "--task", "tap", "--episodes", "1", "--no-progress"]) == 2
    assert "does not exist" in capsys.readouterr().err


def _gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


def test_the_demo_runs_each_chain_in_order_side_by_side_and_stops_at_the_first_failure(tmp_path, capsys):
    from dssp_data.errors import DSSPError
    from dssp_sim.demo import run_side_by_side

    py, logs = sys.executable, tmp_path / "logs"
    order = tmp_path / "order.txt"
    mark = lambda text: [py, "-c", f"open({str(order)!r}, 'a').write({text!r} + '\\n')"]  # noqa: E731
    seconds = run_side_by_side({
        "a": [("check", [py, "-c", "import os, sys; print('one'); sys.stderr.write('\\rbar 1\\rbar 2\\n'); print(os.environ['OMP_NUM_THREADS'])"]),
              ("then", mark("a2"))],
        "b": [("check", [py, "-c", "print('two')"])],
    }, logs)
    assert set(seconds) == {"check_a_s", "then_a_s", "check_b_s"} and all(s > 0 for s in seconds.values())
    out = capsys.readouterr().out.splitlines()
    assert {"[a] one", "[a] bar 1", "[a] bar 2", "[a] 1", "[b] two"} <= set(out)  # one thread each; a bar's end shown
    assert (logs / "check_a.log").read_text() == "one\nbar 1\nbar 2\n1\n" and (logs / "check_b.log").read_text() == "two\n"
    assert order.read_text() == "a2\n"  # the chain's second command ran after its first

    pid_file = tmp_path / "slow.pid"
    slow = [py, "-c", f"import os, time; open({str(pid_file)!r}, 'w').write(str(os.getpid())); time.sleep(120)"]
    bad = [py, "-c", f"import os, sys, time\nwhile not os.path.exists({str(pid_file)!r}): time.sleep(0.05)\nprint('boom'); sys.exit(3)"]
    t0 = time.perf_counter()
    with pytest.raises(DSSPError) as info:
        run_side_by_side({"slow": [("training", slow)], "bad": [("training", bad), ("export", mark("never"))]}, logs)
    message = str(info.value)
    assert time.perf_counter() - t0 < 60 and _gone(int(pid_file.read_text()))  # the other one was stopped
    assert message.startswith("training of bad failed (exit 3); its log: ") and message.endswith(": boom") and "\n" not in message
    assert "never" not in order.read_text()  # nothing after the failed command ran
    kept = Path(message.split("its log: ")[1].rsplit(": ", 1)[0])  # a copy outside --out, which is removed on failure
    assert kept.read_text() == "boom\n"
    kept.unlink()


def test_ctrl_c_stops_the_demo_processes(tmp_path):
    pid_file = tmp_path / "child.pid"
    code = textwrap.dedent(f"""
        import os, signal, sys, threading, time
        from pathlib import Path
        from dssp_sim.demo import run_side_by_side
        child = [sys.executable, "-c", "import os, time; open({str(pid_file)!r}, 'w').write(str(os.getpid())); time.sleep(120)"]
        def interrupt():
            while not (os.path.exists({str(pid_file)!r}) and open({str(pid_file)!r}).read()):  # the pid written, not only the file
                time.sleep(0.05)
            os.kill(os.getpid(), signal.SIGINT)
        threading.Thread(target=interrupt, daemon=True).start()
        try:
            run_side_by_side({{"dssp": [("training", child)]}}, Path({str(tmp_path / "logs")!r}))
        except KeyboardInterrupt:
            print("interrupted")
        """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.stdout.strip() == "interrupted", out.stderr
    assert _gone(int(pid_file.read_text()))


@pytest.fixture(scope="module")
def sim_model(tmp_path_factory):
    """A briefly trained sim-preset model on a few collected tap episodes (its model directory)."""
    from dssp_train.cli.train import main as train_main
    from export.to_onnx import main as export_main

    root = tmp_path_factory.mktemp("sim_model")
    data = root / "tap.zarr"
    assert sim_main(["collect", "--task", "tap", "--episodes", "3", "--out", str(data), "--no-progress"]) == 0
    assert train_main(["--data", str(data), "--out", str(root / "run"), "--preset", "sim", "--steps", "20",
                       "--set", "train.val_every=20", "--no-progress"]) == 0
    assert export_main([str(root / "run"), "-o", str(root / "model"), "--skip-verify", "--quantize", "none"]) == 0
    return root / "model"


def test_eval_runs_the_whole_chain(sim_model, tmp_path, capsys):
    out = tmp_path / "eval.json"
    strips = tmp_path / "strips"
    rrd = tmp_path / "eval.rrd"
    assert sim_main(["eval", "--model", str(sim_model), "--task", "tap", "--episodes", "2", "--seed", "5",
                     "--json", str(out), "--strips", str(strips), "--threads", "1", "--no-progress", "--rerun-save", str(rrd)]) == 0
    text = capsys.readouterr().out
    assert "tap: success" in text and "Wilson interval" in text and "| 5 |" in text and "| 6 |" in text
    # the Rerun views: both episodes on one timeline, one step per tick
    steps = [e["steps"] for e in json.loads(out.read_text())["episodes"]]
    ticks, _, _ = read_rrd(rrd)
    assert ticks["safety/held"] == list(range(sum(steps))) and f"rerun views: {sum(steps)} ticks logged, 0 dropped" in text
    assert text_rows(rrd, "episode") == ["tap seed 5", "tap seed 6"] and ticks["world/arm0/chunk"]
    result = json.loads(out.read_text())
    assert result["n"] == 2 and len(result["episodes"]) == 2
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


@pytest.mark.slow
def test_the_study_command_writes_its_report(tmp_path, capsys):
    from dssp_sim.experiment import REPORT_NAME, main as study_main

    work, report = tmp_path / "work", tmp_path / "report"
    assert study_main(["--work", str(work), "--report", str(report), "--quick", "--threads", "1"]) == 0
    md = (report / f"{REPORT_NAME}.md").read_text()
    assert "| tap | DSSP (full history) |" in md and "| tap | reactive baseline" in md and "| 0.1 |" in md
    assert "| window T_h = 3 | " in md and "| full (DSSP) | " in md  # the ablation table
    assert (report / f"{REPORT_NAME}.png").read_bytes()[:4] == b"\x89PNG"
    data = json.loads((report / f"{REPORT_NAME}.json").read_text())
    assert set(data["evals"]) == {"tap_dssp_s0", "tap_reactive_s0", "tap_window3_s0"} and data["summary"]["tap"]["dssp"]["n"] == 1
    rms = data["evals"]["tap_dssp_s0"]["z_rms"]  # σ is also read against the tokens' own scale
    assert rms > 0 and f"| 0.1 | {0.1 / rms:.2f} |" in md
    assert set(data["robustness"]) == {f"tap_{v}_s0_noise0.1" for v in ("dssp", "window3", "reactive")}
    assert len(list((work / "logs").glob("*.seconds"))) == 13  # each stage's time, summed by the report
    record = report / "record"  # every evaluation and stage time, kept beside the report
    assert sorted(f.stem for f in (record / "evals").glob("*.json")) == sorted([*data["evals"], *data["robustness"]])
    assert sorted(f.name for f in (record / "seconds").iterdir()) == sorted(f.name for f in (work / "logs").glob("*.seconds"))
    # another machine, without the work directory, resumes from the record: nothing is collected, trained or evaluated again
    capsys.readouterr()
    elsewhere = tmp_path / "elsewhere"
    assert study_main(["--work", str(elsewhere), "--report", str(report), "--quick", "--force"]) == 0
    out = capsys.readouterr().out
    assert out.count(": recorded") == 6 and "done before" not in out and not (elsewhere / "data").exists()
    assert json.loads((report / f"{REPORT_NAME}.json").read_text())["evals"] == data["evals"]
    # a report from the record alone: an evaluation not run yet is listed as pending
    (record / "evals" / "tap_window3_s0_noise0.1.json").unlink()
    assert study_main(["--work", str(elsewhere), "--report", str(report), "--quick", "--force", "--report-only"]) == 0
    md = (report / f"{REPORT_NAME}.md").read_text()
    assert "**Partial report**: 1 evaluation(s) of the plan are pending (not run yet): `tap_window3_s0_noise0.1`" in md
    assert "| 0.1 | " in md and "pending |" in md
    assert json.loads((report / f"{REPORT_NAME}.json").read_text())["pending"] == ["tap_window3_s0_noise0.1"]
    assert study_main(["--work", str(elsewhere), "--report", str(tmp_path / "empty"), "--quick", "--report-only"]) == 2
    assert "holds no evaluation of this plan" in capsys.readouterr().err
    with pytest.raises(SystemExit, match="unknown task"):
        study_main(["--work", str(work), "--report", str(report), "--quick", "--tasks", "swap"])


QUICK_RECORD = Path(__file__).parent / "fixtures" / "sim_study_quick_record"
"""The record of one whole quick-plan study (``python -m dssp_sim.experiment --work W --report R --quick
--threads 1``, then R/record): what the long end-to-end test above produces, kept so that the record's uses
are tested in seconds."""


def test_the_study_resumes_from_its_record_and_reports_from_it(tmp_path, capsys):
    from dssp_sim.experiment import REPORT_NAME, main as study_main

    report = tmp_path / "report"
    shutil.copytree(QUICK_RECORD, report / "record")
    recorded = sorted(f.stem for f in (report / "record" / "evals").glob("*.json"))
    # a machine without the work directory resumes from the record: nothing is collected, trained or evaluated
    elsewhere = tmp_path / "elsewhere"
    assert study_main(["--work", str(elsewhere), "--report", str(report), "--quick", "--force"]) == 0
    out = capsys.readouterr().out
    assert out.count(": recorded") == 6 and "done before" not in out and not (elsewhere / "data").exists()
    md = (report / f"{REPORT_NAME}.md").read_text()
    assert "| tap | DSSP (full history) |" in md and "| tap | reactive baseline" in md and "| 0.1 |" in md
    assert "| window T_h = 3 | " in md and "| full (DSSP) | " in md  # the ablation table
    assert (report / f"{REPORT_NAME}.png").read_bytes()[:4] == b"\x89PNG"
    data = json.loads((report / f"{REPORT_NAME}.json").read_text())
    assert sorted([*data["evals"], *data["robustness"]]) == recorded and "pending" not in md.lower()
    for name, row in data["evals"].items():  # the report's figures are the record's
        assert row == json.loads((report / "record" / "evals" / f"{name}.json").read_text())
    rms = data["evals"]["tap_dssp_s0"]["z_rms"]
    assert rms > 0 and f"| 0.1 | {0.1 / rms:.2f} |" in md
    # a report from the record alone: an evaluation not run yet is listed as pending
    (report / "record" / "evals" / "tap_window3_s0_noise0.1.json").unlink()
    assert study_main(["--work", str(elsewhere), "--report", str(report), "--quick", "--force", "--report-only"]) == 0
    md = (report / f"{REPORT_NAME}.md").read_text()
    assert "**Partial report**: 1 evaluation(s) of the plan are pending (not run yet): `tap_window3_s0_noise0.1`" in md
    assert json.loads((report / f"{REPORT_NAME}.json").read_text())["pending"] == ["tap_window3_s0_noise0.1"]
    assert study_main(["--work", str(elsewhere), "--report", str(tmp_path / "empty"), "--quick", "--report-only"]) == 2
    assert "holds no evaluation of this plan" in capsys.readouterr().err


def test_a_training_stopped_halfway_is_resumed_not_taken_for_done(tmp_path):
    from dssp_sim.experiment import PLAN, train_command

    run_dir, log = tmp_path / "runs" / "tap_dssp_s0", tmp_path / "logs" / "train_tap_dssp_s0.log"
    fresh = train_command(tmp_path / "tap.zarr", run_dir, PLAN, "tap", 0, [], log)
    assert "--force" in fresh and "--preset" in fresh and "--resume" not in fresh
    (run_dir / "checkpoint").mkdir(parents=True)  # a checkpoint, but the stage never finished (no .seconds)
    resumed = train_command(tmp_path / "tap.zarr", run_dir, PLAN, "tap", 0, [], log)
    assert "--resume" in resumed and "--force" not in resumed and resumed[resumed.index("--out") + 1] == str(run_dir)
    log.parent.mkdir()
    log.with_suffix(".seconds").write_text("12.0\n")  # finished: a new run only if asked again (stage skips it)
    assert "--resume" not in train_command(tmp_path / "tap.zarr", run_dir, PLAN, "tap", 0, [], log)


def test_a_collection_stopped_halfway_is_collected_again_not_appended_to(tmp_path, monkeypatch):
    import dssp_sim.experiment as experiment

    seen = []
    monkeypatch.setattr(experiment, "stage", lambda done, what, cmd, log, record=None: seen.append((what, (done.parent).exists())))
    monkeypatch.setattr(experiment, "_evaluate", lambda *args: {"successes": 0, "n": 1, "success_rate": 0.0, "failure_reasons": {}})
    work = tmp_path / "work"
    partial = work / "data" / "tap.zarr"
    (partial / "data").mkdir(parents=True)  # a collection interrupted before its stage finished (no .seconds)
    (work / "logs").mkdir()  # the study's own work directory
    experiment.run_study(work, experiment.QUICK_PLAN)
    assert seen[0] == ("collect 3 demos", False)  # removed before the stage: collect would append to it
    (partial / "meta").mkdir(parents=True)
    (work / "logs" / "collect_tap.seconds").write_text("3.0\n")
    seen.clear()
    experiment.run_study(work, experiment.QUICK_PLAN)
    assert seen[0] == ("collect 3 demos", True)  # a finished collection stays


def test_seeds_split_a_tasks_models_across_processes(tmp_path, monkeypatch, capsys):
    import dssp_sim.experiment as experiment

    trained = []
    monkeypatch.setattr(experiment, "stage", lambda done, what, cmd, log, record=None: trained.append(what) if "train" in what else None)
    monkeypatch.setattr(experiment, "_evaluate", lambda *args: {"successes": 0, "n": 1, "success_rate": 0.0, "failure_reasons": {}})
    plan = {**experiment.QUICK_PLAN, "seeds": {"tap": [0, 1]}, "ablation_seeds": {"tap": [1]}}
    experiment.run_study(tmp_path / "work", plan, seeds=[1])
    assert trained == ["train dssp seed 1", "train reactive seed 1", "train window3 seed 1"]
    trained.clear()
    experiment.run_study(tmp_path / "work", plan, seeds=[0])
    assert trained == ["train dssp seed 0", "train reactive seed 0"]
    with pytest.raises(SystemExit):
        experiment.main(["--work", str(tmp_path / "w"), "--quick", "--seeds", "7"])
    assert "--seeds [7]: the plan trains seeds [0]" in capsys.readouterr().err
