"""``dssp-data``: info on a DP3_DATASET dataset and on a recorded one, pictures, merge / split / convert round trips,
repair after an interrupted write, replay through the safety layer, and one-line errors for bad input."""

import json

import numpy as np
import pytest
import zarr
from conftest import DP3_DATASET, FIXTURES, copy_dataset, refusal

from dssp_data.data_cli import main as data_main
from dssp_data.dataset_layout import Episode
from dssp_data.recording import can_log_dir, episode_infos
from dssp_data.replay_buffer import ReplayBuffer
from dssp_data.replay_buffer_writer import write_replay_buffer
from hardware.cli.replay import main as replay_main


def run(capsys, *argv):
    """dssp-data in-process (``replay ...`` runs dssp-replay): (exit code, stdout, stderr)."""
    main = replay_main if argv[0] == "replay" else data_main
    code = main([str(a) for a in argv[1:]] if argv[0] == "replay" else [str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """Two episodes recorded on the embedded default (scripted leader, simulated follower and camera)."""
    from dssp_sim.teleop import record_main

    path = tmp_path_factory.mktemp("recorded") / "rec.zarr"
    assert record_main(["--out", str(path), "--auto", "--episodes", "2", "--quiet"]) == 0
    return path


# ------------------------------------------------------------------------------------------------ info
def test_info_on_a_dp3_dataset(capsys):
    code, out, _ = run(capsys, "info", DP3_DATASET)
    assert code == 0
    assert "episodes    2, 7 steps; length min 3 / median 3 / max 4" in out
    assert "lengths     [3, 4]" in out
    assert "rate        not recorded" in out
    for line in ("data/point_cloud", "(7, 8, 6)", "data/img", "(7, 4, 4, 3)", "uint8", "meta/episode_ends"):
        assert line in out
    assert "    13       -3.25 .. -0.25           -3.125 .. -0.125" in out  # state and action range of dim 13
    assert "point_cloud x 0 .. 6.07" in out
    assert "problems    none found" in out
    assert "the control rate is not recorded" in out

    code, out, _ = run(capsys, "info", DP3_DATASET, "--json")
    report = json.loads(out)
    assert report["episode_lengths"] == [3, 4] and report["arrays"]["data/state"]["shape"] == [7, 14]
    assert report["ranges"]["state"][0] == [0.0, 3.0]


def test_info_on_a_recorded_dataset(recorded, capsys):
    code, out, _ = run(capsys, "info", recorded)
    assert code == 0
    assert "episodes    2," in out and "rate        10 Hz (control_rate_hz); measured 10.000 Hz" in out
    assert "action      leader_command: the leader arm's joint/gripper target" in out
    for key in (
        "data/timestamp",
        "data/camera_timestamp",
        "data/state_timestamp",
        "data/action_timestamp",
        "data/camera_frame",
        "data/step_problems",
        "data/depth",
        "(120, 256, 3)",
    ):
        assert key in out
    assert "camera_to_base: [[" in out and 'camera_intrinsics: {"width": 160' in out
    assert "recording_sessions: 1 session(s)" in out
    assert "recorded episodes" in out and "clean" in out and "auto: task done  seed 0" in out
    assert "problems    none found" in out
    report = json.loads(run(capsys, "info", recorded, "--json")[1])
    assert report["control_rate_hz"] == 10.0 and report["marked_episodes"] == []
    assert all(e["can_logs"] == {"sim": f"episode_{e['index']:06d}.sim.blf"} for e in report["episodes"])


def test_info_reports_problems(tmp_path, recorded, capsys):
    path = copy_dataset(recorded, tmp_path / "broken.zarr")
    root = zarr.open_group(str(path), mode="r+")
    state = root["data/state"][...]
    state[5, 2] = np.nan
    root["data/state"][...] = state
    action = root["data/action"][...]
    action[70, 1] += 1.0  # a glitch in episode 1
    root["data/action"][...] = action
    for key in ("point_cloud", "state", "action"):
        root[f"data/{key}"].append(root[f"data/{key}"][:3])  # an interrupted append
    (can_log_dir(path) / "episode_000001.sim.blf").unlink()
    code, out, _ = run(capsys, "info", path)
    assert code == 1  # problems listed
    assert "3 steps after the last episode end: a write was interrupted" in out
    assert "data/state holds NaN or inf in episode(s) 0" in out
    assert "episode 1: the action jumps by" in out
    assert "CAN logs missing: episode_000001.sim.blf (episode 1)" in out


# ------------------------------------------------------------------------------------------------ view
def _is_png(path):
    return path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 10_000


def test_view_writes_pictures(recorded, tmp_path, capsys):
    code, out, _ = run(capsys, "view", recorded, "--episode", "1", "--out", tmp_path / "views")
    assert code == 0
    clouds, traj = tmp_path / "views" / "rec_ep1_clouds.png", tmp_path / "views" / "rec_ep1_trajectories.png"
    assert f"wrote {clouds}" in out and _is_png(clouds) and _is_png(traj)
    code, out, _ = run(
        capsys, "view", DP3_DATASET, "--episode", "0", "--out", tmp_path / "dp3", "--steps", "3", "--video"
    )
    assert code == 0
    assert _is_png(tmp_path / "dp3" / "dp3_zarr2_tiny_ep0_clouds.png")
    assert (tmp_path / "dp3" / "dp3_zarr2_tiny_ep0.gif").read_bytes()[:6] == b"GIF89a"


# ------------------------------------------------------------------------------------------------ merge / split
def test_merge_and_split_round_trip(recorded, tmp_path, capsys):
    original = ReplayBuffer.load(recorded, extras=True)
    n = original.n_episodes
    merged = tmp_path / "merged.zarr"
    again = copy_dataset(recorded, tmp_path / "again.zarr")
    code, out, _ = run(capsys, "merge", merged, recorded, again)
    assert code == 0 and f"wrote {merged}: {2 * n} episodes" in out and f"{2 * n} CAN logs" in out
    buffer = ReplayBuffer.load(merged, extras=True)
    assert buffer.n_episodes == 2 * n and set(buffer.extras) == set(original.extras)
    for i in range(2 * n):
        a, b = buffer.episode(i), original.episode(i % n)
        for key in ("point_cloud", "state", "action"):
            np.testing.assert_array_equal(getattr(a, key), getattr(b, key))
        np.testing.assert_array_equal(a.extras["timestamp"], b.extras["timestamp"])
    infos = episode_infos(buffer.attrs, buffer.n_episodes)
    assert [i["index"] for i in infos] == list(range(2 * n))
    assert [i["session"] for i in infos] == [0] * n + [1] * n and len(buffer.attrs["recording_sessions"]) == 2
    assert all((can_log_dir(merged) / f"episode_{i:06d}.sim.blf").is_file() for i in range(2 * n))
    assert buffer.attrs["merged_from"] == [
        {"path": str(p), "episodes": n, "generator": "dssp-record"} for p in (recorded, again)
    ]
    assert buffer.attrs["generator"] == "dssp-data merge"

    train, val = tmp_path / "train.zarr", tmp_path / "val.zarr"
    code, out, _ = run(capsys, "split", merged, "--train", train, "--val", val, "--val-episodes", "1,2")
    assert code == 0 and "source episodes [1, 2]" in out
    t, v = ReplayBuffer.load(train, extras=True), ReplayBuffer.load(val, extras=True)
    assert (t.n_episodes, v.n_episodes) == (2 * n - 2, 2)
    np.testing.assert_array_equal(v.episode(0).state, buffer.episode(1).state)
    np.testing.assert_array_equal(t.episode(1).action, buffer.episode(3).action)
    assert v.attrs["split_from"]["episodes"] == [1, 2] and t.attrs["split_from"]["part"] == "train"
    assert t.attrs["generator"] == "dssp-data split" and t.attrs["split_from"]["generator"] == "dssp-data merge"
    assert [i["sim"]["seed"] for i in v.attrs["episode_info"]] == [1, 0]
    assert (can_log_dir(val) / "episode_000001.sim.blf").is_file()

    code, out, _ = run(
        capsys,
        "split",
        merged,
        "--train",
        tmp_path / "t2.zarr",
        "--val",
        tmp_path / "v2.zarr",
        "--val-ratio",
        "0.25",
        "--seed",
        "3",
    )
    assert code == 0
    assert ReplayBuffer.load(tmp_path / "v2.zarr").n_episodes == 1
    assert ReplayBuffer.load(tmp_path / "t2.zarr").n_episodes == 2 * n - 1


def test_merge_keeps_only_shared_extras(tmp_path, capsys):
    rng = np.random.default_rng(0)
    episodes = [
        Episode(
            rng.normal(size=(t, 8, 6)).astype(np.float32),
            rng.normal(size=(t, 14)).astype(np.float32),
            rng.normal(size=(t, 14)).astype(np.float32),
        )
        for t in (2, 5)
    ]
    plain = tmp_path / "plain.zarr"
    write_replay_buffer(plain, episodes)
    code, out, err = run(capsys, "merge", tmp_path / "m.zarr", DP3_DATASET, plain)
    assert code == 0 and "4 episodes, 14 steps" in out
    assert "warning: per-step arrays not held by every input (or stored differently) were left out: data/img" in err
    merged = ReplayBuffer.load(tmp_path / "m.zarr", extras=True)
    assert merged.extras == {} and merged.n_episodes == 4
    np.testing.assert_array_equal(merged.episode(3).state, episodes[1].state)


# ------------------------------------------------------------------------------------------------ convert
def write_robotwin_episode(path, vector, cloud):
    """An episode in RoboTwin's raw layout, as its collection writes it (joint_action/*, pointcloud)."""
    import h5py

    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, "w") as f:
        f["joint_action/left_arm"] = vector[:, 0:6]
        f["joint_action/left_gripper"] = vector[:, 6]
        f["joint_action/right_arm"] = vector[:, 7:13]
        f["joint_action/right_gripper"] = vector[:, 13]
        f["joint_action/vector"] = vector
        f["pointcloud"] = cloud
        f["observation/head_camera/intrinsic_cv"] = np.eye(3)
        f["endpose/left_endpose"] = np.zeros((len(vector), 7))


def test_convert_robotwin_hdf5(tmp_path, capsys):
    rng = np.random.default_rng(0)
    task = tmp_path / "beat_block_hammer" / "demo_clean"
    raw = {}
    for n, steps in ((0, 5), (1, 4), (10, 6)):  # numeric order: 0, 1, 10
        vector = rng.uniform(-1, 1, (steps, 14))
        cloud = rng.uniform(0, 1, (steps, 16, 6)).astype(np.float32)
        write_robotwin_episode(task / "data" / f"episode{n}.hdf5", vector, cloud)
        raw[n] = (vector, cloud)
    out = tmp_path / "converted.zarr"
    code, text, _ = run(capsys, "convert", task, "--out", out, "--control-rate", "25", "--task", "beat_block_hammer")
    assert code == 0 and "3 episodes, 12 steps" in text
    buffer = ReplayBuffer.load(out)
    assert list(buffer.episode_ends) == [4, 7, 12]
    for i, n in enumerate((0, 1, 10)):
        vector, cloud = raw[n]
        ep = buffer.episode(i)
        np.testing.assert_array_equal(ep.state, vector[:-1].astype(np.float32))
        np.testing.assert_array_equal(ep.action, vector[1:].astype(np.float32))
        np.testing.assert_array_equal(ep.point_cloud, cloud[:-1])
    assert buffer.control_rate_hz == 25.0 and buffer.attrs["action_convention"].startswith("next_state")
    assert buffer.attrs["converted_from"] == ["episode0.hdf5", "episode1.hdf5", "episode10.hdf5"]

    code, text, _ = run(capsys, "convert", task / "data" / "episode1.hdf5", "--out", tmp_path / "xyz.zarr", "--xyz")
    assert code == 0 and ReplayBuffer.load(tmp_path / "xyz.zarr").point_cloud.shape == (3, 16, 3)
    refusal(
        run(capsys, "convert", task, "--out", out),
        "already holds a dataset from dssp-data merge, split or convert; pass --force",
    )
    assert run(capsys, "convert", task, "--out", out, "--force", "--episodes", "1")[0] == 0
    assert ReplayBuffer.load(out).n_episodes == 1

    code, _, err = run(capsys, "info", out)
    assert code == 0


def test_convert_rejects_episodes_without_clouds(tmp_path, capsys):
    import h5py

    task = tmp_path / "task"
    path = task / "data" / "episode0.hdf5"
    path.parent.mkdir(parents=True)
    with h5py.File(path, "w") as f:
        f["joint_action/vector"] = np.zeros((4, 14))
        f["pointcloud"] = np.zeros((4, 0))
    refusal(run(capsys, "convert", task, "--out", tmp_path / "o.zarr"), "collected without point clouds")
    assert not (tmp_path / "o.zarr").exists()
    path.write_bytes(b"not hdf5")
    refusal(run(capsys, "convert", task, "--out", tmp_path / "o.zarr"), "not a readable HDF5 file")
    refusal(run(capsys, "convert", tmp_path / "nowhere", "--out", tmp_path / "o.zarr"), "does not exist")


# ------------------------------------------------------------------------------------------------ repair, replay
def test_repair_after_an_interrupted_write(recorded, tmp_path, capsys):
    path = copy_dataset(recorded, tmp_path / "r.zarr")
    root = zarr.open_group(str(path), mode="r+")
    root.attrs["episode_info"] = list(root.attrs["episode_info"]) + [{"index": 2}]
    for key in ("point_cloud", "state", "action", "timestamp"):
        root[f"data/{key}"].append(root[f"data/{key}"][:4])
    code, out, _ = run(capsys, "repair", path)
    assert code == 0 and "cut off 4 steps and 1 metadata entries" in out
    assert ReplayBuffer.load(path).n_episodes == ReplayBuffer.load(recorded).n_episodes
    assert "problems    none found" in run(capsys, "info", path)[1]
    assert "needed no repair" in run(capsys, "repair", path)[1]


def test_replay_dry_run_and_on_the_simulated_arm(recorded, capsys):
    code, out, _ = run(capsys, "replay", recorded, "--episode", "0")
    assert code == 0 and "dry run without an arm" in out and "0 clips, 0 holds" in out
    code, out, _ = run(capsys, "replay", recorded, "--episode", "0", "--can", "sim")
    assert code == 0 and "dry run on sim (nothing sent)" in out and "note: the first action is" in out
    code, out, _ = run(
        capsys, "replay", recorded, "--episode", "1", "--can", "sim", "--send", "--control-rate", "60"
    )  # 0.05 rad per tick at 60 Hz: 3 rad/s, within the arm's speed
    steps = ReplayBuffer.load(recorded).episode_lengths()[1]
    assert code == 0 and f"sent {steps} commands to sim" in out and "ended by: done" in out


# ------------------------------------------------------------------------------------------------ bad input
@pytest.mark.parametrize(
    "argv, fragment",
    [
        (["info", "nowhere.zarr"], "does not exist"),
        (["info", FIXTURES / "dp3_zarr2_tiny.json"], "is a file, not a zarr dataset"),
        (["view", DP3_DATASET, "--episode", "7"], "episode 7 is out of range"),
        (["view", DP3_DATASET, "--episode", "0", "--steps", "0"], "--steps must be at least 1"),
        (["merge", "out.zarr", DP3_DATASET], "merge needs at least two input datasets"),
        (
            ["split", DP3_DATASET, "--train", "a.zarr", "--val", "a.zarr", "--val-ratio", "0.5"],
            "must be different paths",
        ),
        (
            ["split", DP3_DATASET, "--train", "a.zarr", "--val", "b.zarr", "--val-episodes", "0,1"],
            "at least one episode on each side",
        ),
        (
            ["split", DP3_DATASET, "--train", "a.zarr", "--val", "b.zarr", "--val-episodes", "x"],
            "comma-separated integers",
        ),
        (["replay", DP3_DATASET, "--episode", "0"], "does not record its control rate"),
        (["replay", DP3_DATASET, "--episode", "0", "--control-rate", "100"], "above the arm's 3.14159 rad/s"),
        (["replay", DP3_DATASET, "--episode", "0", "--control-rate", "0"], "--control-rate must be in [0.1, 1000] Hz"),
    ],
)
def test_bad_input_is_one_line(tmp_path, capsys, monkeypatch, argv, fragment):
    monkeypatch.chdir(tmp_path)
    refusal(run(capsys, *argv), fragment)


def test_split_can_leave_out_marked_episodes(tmp_path, capsys):
    rng = np.random.default_rng(1)
    episodes = [
        Episode(
            rng.normal(size=(3, 4, 3)).astype(np.float32),
            rng.normal(size=(3, 7)).astype(np.float32),
            rng.normal(size=(3, 7)).astype(np.float32),
        )
        for _ in range(4)
    ]
    infos = [{"problems": [{"kind": "camera_stale", "steps": 2, "first_step": 0}]}, None, {"problems": []}, {}]
    path = tmp_path / "m.zarr"
    write_replay_buffer(path, episodes, attrs={"episode_info": infos})
    code, out, _ = run(
        capsys,
        "split",
        path,
        "--train",
        tmp_path / "t.zarr",
        "--val",
        tmp_path / "v.zarr",
        "--val-ratio",
        "0.3",
        "--drop-marked",
    )
    assert code == 0 and "left out episodes [0] (recorded with problems)" in out
    t, v = ReplayBuffer.load(tmp_path / "t.zarr"), ReplayBuffer.load(tmp_path / "v.zarr")
    assert (t.n_episodes, v.n_episodes) == (2, 1)
    assert sorted(t.attrs["split_from"]["episodes"] + v.attrs["split_from"]["episodes"]) == [1, 2, 3]
    result = run(
        capsys,
        "split",
        path,
        "--train",
        tmp_path / "t2.zarr",
        "--val",
        tmp_path / "v2.zarr",
        "--val-episodes",
        "0",
        "--drop-marked",
    )
    refusal(result, "validation episode(s) [0] were recorded with problems")


# ------------------------------------------------------------------------------------------------ attributes
@pytest.mark.parametrize(
    "value, shown", [(-10, "-10"), (float("nan"), "NaN"), (0, "0"), ("10", "'10'"), ("abc", "'abc'"), (True, "true")]
)
def test_info_lists_a_control_rate_that_is_not_a_rate(tmp_path, capsys, value, shown):
    path = tmp_path / "d.zarr"
    write_replay_buffer(
        path,
        [Episode(np.zeros((3, 4, 3), np.float32), np.ones((3, 2), np.float32), np.ones((3, 2), np.float32))],
        attrs={"control_rate_hz": value},
    )
    code, out, _ = run(capsys, "info", path)
    assert code == 1 and "rate        control_rate_hz is not a rate (see problems)" in out, out
    assert f"  - attribute control_rate_hz is {shown}, not a rate in Hz (a number > 0); fix it with" in out, out
    assert "the control rate is not recorded" not in out and "problems    none found" not in out
    report = json.loads(run(capsys, "info", path, "--json")[1])
    assert report["control_rate_hz"] is None
    refusal(run(capsys, "view", path, "--episode", "0", "--out", tmp_path / "v"), "attribute control_rate_hz is")
    assert not (tmp_path / "v").exists()


def test_episode_info_of_the_wrong_type_is_a_problem_not_missing_metadata(tmp_path, capsys):
    rng = np.random.default_rng(3)
    eps = [
        Episode(
            rng.normal(size=(3, 4, 3)).astype(np.float32),
            rng.normal(size=(3, 2)).astype(np.float32),
            rng.normal(size=(3, 2)).astype(np.float32),
        )
        for _ in range(2)
    ]
    path = tmp_path / "d.zarr"
    write_replay_buffer(path, eps, attrs={"episode_info": "hello", "control_rate_hz": 10.0})
    code, out, _ = run(capsys, "info", path)
    assert code == 1 and "  - attribute episode_info is 'hello', not a list (one object or null per episode)" in out
    other, good = tmp_path / "e.zarr", tmp_path / "g.zarr"
    write_replay_buffer(other, eps, attrs={"control_rate_hz": 10.0, "camera_to_base": [[1, 2]]})
    write_replay_buffer(good, eps, attrs={"control_rate_hz": 10.0})
    listing = sorted(p.name for p in tmp_path.iterdir())
    for argv, fragment in (
        (["merge", tmp_path / "m.zarr", good, path], "attribute episode_info is 'hello'"),
        (["merge", tmp_path / "m.zarr", good, other], "attribute camera_to_base is [[1, 2]]"),
        (
            ["split", path, "--train", tmp_path / "t.zarr", "--val", tmp_path / "v.zarr", "--val-ratio", "0.5"],
            "attribute episode_info is 'hello'",
        ),
    ):
        refusal(run(capsys, *argv), fragment)
    assert sorted(p.name for p in tmp_path.iterdir()) == listing
