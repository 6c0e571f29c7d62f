"""``dssp-data convert`` of LeRobot v3 datasets and ``dssp-data export --to lerobot``, with LeRobot itself (lerobot
0.4.4, which ``make setup`` installs without its dependencies) as the oracle: it writes the dataset that is
converted, and reads back the datasets that are exported.

LeRobot's dataset modules import torchvision at module level, and no torchvision for the torch installed here
(2.13, a CPU build) is on the package index: PyPI's wheel is a CUDA build that fails to import without
libc10_cuda. LeRobot's dataset code calls nothing of torchvision for array features (only images and videos go
through it), so the oracle runs with a small stand-in package ``torchvision`` that this module writes into the
test's folder; its few names raise if anything calls them. The oracle runs in a child process with that package
first on its path, its Hugging Face caches in the test's folder and the hub offline: the stand-in and lerobot's
modules never enter this process, whose sys.path and sys.modules stay as they were.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute  # noqa: F401  (loaded here, not by the first conversion: the tests add no module)
import pyarrow.parquet as pq
import pytest
from conftest import CAMERA, CLOUD, calibration_flags, one_error_line, run_data_cli, snapshot

from dssp_data.dataset_layout import Episode
from dssp_data.lerobot import write as lerobot_write
from dssp_data.observation import PIPER_CHANNELS
from dssp_data.pointcloud import frame_to_cloud
from dssp_data.pointcloud.depth_frame import DepthFrame
from dssp_data.replay_buffer import ReplayBuffer
from dssp_data.replay_buffer_writer import write_replay_buffer
from dssp_train.data.synthetic import write_tap_count_dataset

FPS = 10
LENGTHS = (6, 5)
TASKS = ("push the box", "push the box back")
INTRINSICS = {
    "fx": CAMERA.intrinsics.fx,
    "fy": CAMERA.intrinsics.fy,
    "ppx": CAMERA.intrinsics.ppx,
    "ppy": CAMERA.intrinsics.ppy,
    "width": 160,
    "height": 120,
    "depth_unit": CAMERA.depth_unit,
}
FEATURES = {
    "observation.state": {"dtype": "float32", "shape": [7], "names": list(PIPER_CHANNELS)},
    "action": {"dtype": "float32", "shape": [7], "names": list(PIPER_CHANNELS)},
    "observation.depth": {
        "dtype": "uint16",
        "shape": [120, 160],
        "names": ["height", "width"],
        "info": {"camera_intrinsics": INTRINSICS},
    },
}

TORCHVISION = {
    "__init__.py": '"""A stand-in for torchvision: lerobot\'s dataset modules import it; nothing here may be called."""\n'
    "from . import io, transforms  # noqa: F401\n\n\n"
    "def set_video_backend(backend):\n"
    "    raise RuntimeError('the torchvision stand-in decodes no video')\n",
    "io.py": "",
    "transforms.py": "class ToTensor:\n"
    "    def __call__(self, picture):\n"
    "        raise RuntimeError('the torchvision stand-in converts no image')\n",
}

ORACLE = r"""
import json, sys
import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset

job = json.load(open(sys.argv[1]))
if job["mode"] == "write":
    data = np.load(job["frames"])
    features = {k: {**f, "shape": tuple(f["shape"])} for k, f in job["features"].items()}
    ds = LeRobotDataset.create(repo_id="local/source", root=job["root"], fps=job["fps"], features=features,
                               use_videos=False)
    for e, (n, task) in enumerate(zip(job["lengths"], job["tasks"])):
        for t in range(n):
            ds.add_frame({**{k: data[f"{k}/{e}"][t] for k in features}, "task": task})
        ds.save_episode()
    ds.finalize()
else:
    out = {}
    for name, root in job["roots"].items():
        ds = LeRobotDataset(name, root=root)
        items = [ds[i] for i in range(len(ds))]
        keys = [k for k in ds.meta.features if k not in ("task",)]
        for k in keys:
            out[f"{name}|{k}"] = np.stack([item[k].numpy() for item in items])
        out[f"{name}|task"] = np.array([item["task"] for item in items])
        out[f"{name}|stats"] = np.array(json.dumps({k: {s: np.asarray(v).tolist() for s, v in st.items()}
                                                    for k, st in ds.meta.stats.items()}))
        out[f"{name}|meta"] = np.array(json.dumps({"fps": ds.fps, "episodes": ds.num_episodes,
                                                   "features": ds.meta.features}, default=list))
        # the history of one frame, by the episodes' index ranges: the action of frame 1 of episode 1 and the next
        window = LeRobotDataset(name, root=root, delta_timestamps={"action": [0.0, 1.0 / ds.fps]})
        start = window.meta.episodes[1]["dataset_from_index"]
        last = window[window.meta.episodes[1]["dataset_to_index"] - 1]
        out[f"{name}|window"] = window[start + 1]["action"].numpy()
        out[f"{name}|last_pad"] = last["action_is_pad"].numpy()
    np.savez(job["out"], **out)
"""


def run_oracle(tmp: Path, job: dict) -> None:
    """Run LeRobot on ``job`` in a child process (the stand-in torchvision first on its path, caches in ``tmp``)."""
    package = tmp / "stand_in" / "torchvision"
    if not package.is_dir():
        package.mkdir(parents=True)
        for name, text in TORCHVISION.items():
            (package / name).write_text(text)
    (tmp / "job.json").write_text(json.dumps(job))
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(package.parent), *filter(None, [os.environ.get("PYTHONPATH")])]),
        "HF_HOME": str(tmp / "hf"),
        "HF_HUB_OFFLINE": "1",
        "HF_DATASETS_OFFLINE": "1",
        "OMP_NUM_THREADS": "1",
        "TQDM_DISABLE": "1",
    }
    proc = subprocess.run(
        [sys.executable, "-c", ORACLE, str(tmp / "job.json")], capture_output=True, text=True, env=env, timeout=300
    )
    assert proc.returncode == 0, proc.stderr[-4000:]


def frames() -> dict[str, np.ndarray]:
    """Two episodes: depth of the moving box, and state/action trajectories."""
    data = {}
    for e, n in enumerate(LENGTHS):
        t = np.arange(n) / FPS + 2.0 * e
        data[f"observation.depth/{e}"] = np.stack([CAMERA.render(s)[0] for s in t])
        state = np.stack(
            [
                0.3 * np.sin(t),
                1.0 + 0.1 * t,
                -0.8 + 0 * t,
                0.05 * t,
                0.3 + 0 * t,
                -0.2 + 0 * t,
                0.5 + 0.4 * np.sin(2 * t),
            ],
            axis=1,
        ).astype(np.float32)
        data[f"observation.state/{e}"] = state
        data[f"action/{e}"] = (state + 0.01).astype(np.float32)
    return data


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    """A LeRobot v3 dataset written by LeRobot: (root, its frames)."""
    tmp = tmp_path_factory.mktemp("lerobot_source")
    data = frames()
    np.savez(tmp / "frames.npz", **data)
    root = tmp / "source"
    run_oracle(
        tmp,
        {
            "mode": "write",
            "frames": str(tmp / "frames.npz"),
            "features": FEATURES,
            "root": str(root),
            "fps": FPS,
            "lengths": list(LENGTHS),
            "tasks": list(TASKS),
        },
    )
    return root, data


@pytest.fixture()
def calibration(tmp_path):
    """The LeRobot datasets' calibration flags (:func:`conftest.calibration_flags`)."""
    return calibration_flags(tmp_path)


def test_a_lerobot_dataset_becomes_episodes_with_the_robots_clouds(source, tmp_path, capsys, calibration):
    root, data = source
    out = tmp_path / "demo.zarr"
    code, stdout, stderr = run_data_cli(capsys, "convert", root, "--out", out, *calibration)
    assert code == 0, stderr
    assert "2 episodes (one per LeRobot episode), 11 steps at 10 Hz" in stdout
    buffer = ReplayBuffer.load(out, extras=True)
    assert list(buffer.episode_lengths()) == list(LENGTHS)
    for e in range(2):
        ep = buffer.episode(e)
        depth = data[f"observation.depth/{e}"]
        np.testing.assert_array_equal(ep.extras["depth"], depth)
        for k in range(LENGTHS[e]):
            frame = DepthFrame(depth[k], CAMERA.depth_unit, CAMERA.intrinsics, k / FPS, k)
            cloud, _ = frame_to_cloud(frame, CLOUD, CAMERA.camera_to_base)
            np.testing.assert_array_equal(ep.point_cloud[k], cloud)  # the robot's pipeline, bit for bit
        np.testing.assert_array_equal(ep.state, data[f"observation.state/{e}"])
        np.testing.assert_array_equal(ep.action, data[f"action/{e}"])
        np.testing.assert_allclose(ep.extras["timestamp"], np.arange(LENGTHS[e]) / FPS, atol=1e-6)
    attrs = buffer.attrs
    assert attrs["control_rate_hz"] == 10.0 and attrs["generator"] == "dssp-data convert"
    assert attrs["camera_intrinsics"] == {k: INTRINSICS[k] for k in ("width", "height", "fx", "fy", "ppx", "ppy")}
    assert attrs["camera_depth_unit"] == CAMERA.depth_unit and attrs["episode_tasks"] == list(TASKS)
    assert attrs["pointcloud"] == CLOUD.to_dict() and np.allclose(attrs["camera_to_base"], CAMERA.camera_to_base)
    assert attrs["state_layout"] == {"arms": 1, "channels": list(PIPER_CHANNELS)}  # from the features' names
    assert attrs["action_convention"].startswith("lerobot_action:")


def test_exports_are_read_back_by_lerobot(source, tmp_path, capsys, calibration, monkeypatch):
    root, data = source
    converted = tmp_path / "demo.zarr"
    assert run_data_cli(capsys, "convert", root, "--out", converted, *calibration)[0] == 0
    tap = write_tap_count_dataset(tmp_path / "tap.zarr", 3, seed=0, n_points=32)
    exported = {"local/demo": tmp_path / "demo_lerobot", "local/tap": tmp_path / "tap_lerobot"}
    for dataset, target in zip((converted, tap), exported.values()):
        if dataset == tap:  # the synthetic one in several data files: one per episode
            monkeypatch.setattr(lerobot_write, "DATA_FILE_MB", 0)
        code, stdout, stderr = run_data_cli(capsys, "export", dataset, "--to", "lerobot", "--out", target)
        assert code == 0 and stderr == "", stderr
        assert "LeRobotDataset('local/" in stdout
    assert sorted(p.name for p in (exported["local/tap"] / "data/chunk-000").iterdir()) == [
        "file-000.parquet",
        "file-001.parquet",
        "file-002.parquet",
    ]

    # and back: the export (DATA_FILE_MB is still 0: one file per episode) converts to the dataset it was made from
    split = tmp_path / "demo_split"
    assert run_data_cli(capsys, "export", converted, "--to", "lerobot", "--out", split)[0] == 0
    assert run_data_cli(capsys, "convert", split, "--out", tmp_path / "again.zarr", *calibration)[0] == 0
    again, buffer = (ReplayBuffer.load(p, extras=True) for p in (tmp_path / "again.zarr", converted))
    for key in ("point_cloud", "state", "action"):
        np.testing.assert_array_equal(getattr(again, key), getattr(buffer, key))
    assert list(again.episode_lengths()) == list(LENGTHS)
    assert {
        k: again.attrs[k]
        for k in (
            "state_layout",
            "action_layout",
            "action_convention",
            "episode_tasks",
            "camera_intrinsics",
            "camera_depth_unit",
            "control_rate_hz",
        )
    } == {
        k: buffer.attrs[k]
        for k in (
            "state_layout",
            "action_layout",
            "action_convention",
            "episode_tasks",
            "camera_intrinsics",
            "camera_depth_unit",
            "control_rate_hz",
        )
    }
    run_oracle(
        tmp_path, {"mode": "read", "roots": {k: str(v) for k, v in exported.items()}, "out": str(tmp_path / "read.npz")}
    )
    read = np.load(tmp_path / "read.npz")

    # the converted LeRobot dataset, round trip: LeRobot -> zarr -> LeRobot gives LeRobot the same frames back
    meta = json.loads(str(read["local/demo|meta"]))
    assert meta["fps"] == FPS and meta["episodes"] == 2
    np.testing.assert_array_equal(read["local/demo|observation.state"], buffer.state)
    np.testing.assert_array_equal(read["local/demo|action"], buffer.action)
    np.testing.assert_array_equal(read["local/demo|observation.pointcloud"], buffer.point_cloud)
    depth = np.concatenate([data[f"observation.depth/{e}"] for e in range(2)])
    np.testing.assert_array_equal(read["local/demo|observation.depth"].astype(np.uint16), depth)
    assert (read["local/demo|observation.depth"] == depth).all()  # no value was cut to 16 bits
    assert list(read["local/demo|task"]) == [TASKS[0]] * LENGTHS[0] + [TASKS[1]] * LENGTHS[1]
    np.testing.assert_array_equal(read["local/demo|episode_index"], np.repeat([0, 1], LENGTHS))
    np.testing.assert_array_equal(read["local/demo|frame_index"], np.concatenate([np.arange(n) for n in LENGTHS]))
    np.testing.assert_allclose(
        read["local/demo|timestamp"], np.concatenate([np.arange(n) / FPS for n in LENGTHS]).astype(np.float32)
    )
    start = LENGTHS[0]
    np.testing.assert_array_equal(read["local/demo|window"], buffer.action[start + 1 : start + 3])
    assert read["local/demo|last_pad"].tolist() == [False, True]  # past the episode's end
    for key, wrote in FEATURES.items():  # the features LeRobot wrote come back as they were
        assert {k: list(v) if k == "shape" else v for k, v in meta["features"][key].items() if k in wrote} == wrote, key

    # the same layout as LeRobot's own: file tree, parquet schemas, statistics
    source_files = {p for p in snapshot(root)}
    assert source_files == {p for p in snapshot(exported["local/demo"]) if p != ".dssp-output.json"}
    for rel in ("data/chunk-000/file-000.parquet", "meta/tasks.parquet", "meta/episodes/chunk-000/file-000.parquet"):
        ours, theirs = pq.read_schema(exported["local/demo"] / rel), pq.read_schema(root / rel)
        common = [n for n in theirs.names if n in ours.names]
        assert [ours.field(n) for n in common] == [theirs.field(n) for n in common], rel
        assert all(ours.field(n).metadata == theirs.field(n).metadata for n in common), rel
        assert set(theirs.names) - set(ours.names) == set(), rel
    ours_stats, their_stats = (json.loads((r / "meta/stats.json").read_text()) for r in (exported["local/demo"], root))
    for key, stats in their_stats.items():
        assert {s: np.shape(v) for s, v in ours_stats[key].items()} == {s: np.shape(v) for s, v in stats.items()}, key
        np.testing.assert_allclose(ours_stats[key]["min"], stats["min"], rtol=1e-6)
        np.testing.assert_allclose(ours_stats[key]["max"], stats["max"], rtol=1e-6)
    for key in ("observation.state", "action"):  # LeRobot's std is sqrt(E[x^2] - E[x]^2) in float32: constant
        np.testing.assert_allclose(ours_stats[key]["mean"], their_stats[key]["mean"], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(ours_stats[key]["std"], their_stats[key]["std"], rtol=1e-4, atol=5e-4)  # channels
    loaded = json.loads(str(read["local/demo|stats"]))
    np.testing.assert_allclose(
        loaded["observation.pointcloud"]["mean"], buffer.point_cloud.reshape(-1, 3).mean(0), rtol=1e-5
    )

    # a synthetic dataset: no depth, one task
    tap_buffer = ReplayBuffer.load(tap)
    np.testing.assert_array_equal(read["local/tap|observation.state"], tap_buffer.state)
    np.testing.assert_array_equal(read["local/tap|action"], tap_buffer.action)
    np.testing.assert_array_equal(read["local/tap|observation.pointcloud"], tap_buffer.point_cloud)
    assert set(read["local/tap|task"]) == {"tap_count"}
    assert "local/tap|observation.depth" not in read.files


def test_export_refuses_to_overwrite_and_replaces_its_own(source, tmp_path, capsys, calibration):
    root, _ = source
    tap = write_tap_count_dataset(tmp_path / "tap.zarr", 2, seed=0, n_points=24)
    out = tmp_path / "tap_lerobot"
    assert run_data_cli(capsys, "export", tap, "--to", "lerobot", "--out", out)[0] == 0
    before = snapshot(out)
    code, _, stderr = run_data_cli(capsys, "export", tap, "--to", "lerobot", "--out", out)
    assert code == 2 and "pass --force" in one_error_line(stderr) and snapshot(out) == before
    assert run_data_cli(capsys, "export", tap, "--to", "lerobot", "--out", out, "--force")[0] == 0
    foreign = tmp_path / "copy"
    shutil.copytree(root, foreign)
    before = snapshot(foreign)
    code, _, stderr = run_data_cli(capsys, "export", tap, "--to", "lerobot", "--out", foreign, "--force")
    assert code == 2 and "is not a LeRobot dataset made by dssp-data export" in one_error_line(stderr)
    assert snapshot(foreign) == before


def test_depth_in_metres_gives_the_clouds_of_its_counts(source, tmp_path, capsys, calibration):
    """float32 depth in metres is quantised to the intrinsics' depth_unit: the clouds are those of the raw counts."""
    root, data = source
    copy = edited(root, tmp_path, lambda info: info["features"]["observation.depth"].update(dtype="float32"))
    path = copy / "data/chunk-000/file-000.parquet"
    table = pq.ParquetFile(path).read()
    metres = (np.concatenate([data[f"observation.depth/{e}"] for e in range(2)]) * CAMERA.depth_unit).astype(np.float32)
    n, h, w = metres.shape

    def flat(values):  # from the buffer: pa.array would load pandas into this process
        return pa.Array.from_buffers(pa.from_numpy_dtype(values.dtype), values.size, [None, pa.py_buffer(values)])

    rows = pa.ListArray.from_arrays(flat(np.arange(0, n * h * w + 1, w, dtype=np.int32)), flat(metres.ravel()))
    column = pa.ListArray.from_arrays(flat(np.arange(0, n * h + 1, h, dtype=np.int32)), rows)
    index = table.schema.get_field_index("observation.depth")
    pq.write_table(table.set_column(index, "observation.depth", column), path)
    out = tmp_path / "metres.zarr"
    code, stdout, stderr = run_data_cli(capsys, "convert", copy, "--out", out, *calibration, "--episodes", "1")
    assert code == 0 and "1 episodes" in stdout, stderr
    ep = ReplayBuffer.load(out, extras=True).episode(0)
    np.testing.assert_array_equal(ep.extras["depth"], data["observation.depth/0"])
    for k in range(LENGTHS[0]):
        frame = DepthFrame(data["observation.depth/0"][k], CAMERA.depth_unit, CAMERA.intrinsics, k / FPS, k)
        np.testing.assert_array_equal(ep.point_cloud[k], frame_to_cloud(frame, CLOUD, CAMERA.camera_to_base)[0])


def edited(root: Path, tmp_path: Path, edit) -> Path:
    """A copy of the LeRobot dataset whose meta/info.json went through ``edit(info)``."""
    copy = tmp_path / "edited"
    shutil.copytree(root, copy)
    info = json.loads((copy / "meta/info.json").read_text())
    edit(info)
    (copy / "meta/info.json").write_text(json.dumps(info))
    return copy


def _no_intrinsics(info):
    del info["features"]["observation.depth"]["info"]


def _video_depth(info):
    info["features"]["observation.depth"]["dtype"] = "video"


def _version_2(info):
    info["codebase_version"] = "v2.1"


def _outside(info):
    info["data_path"] = "../elsewhere/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"


def _absolute(info):
    info["data_path"] = "/tmp/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"


def _no_state(info):
    info["features"]["observation.joints"] = info["features"].pop("observation.state")


def _state_shape(info):
    info["features"]["observation.state"]["shape"] = [8]


@pytest.mark.parametrize(
    "edit, message",
    [
        (_no_intrinsics, "observation.depth has no camera intrinsics; add info.camera_intrinsics"),
        (_video_depth, "observation.depth is stored as video; depth in a video is not supported (the codecs are lossy"),
        (_version_2, "codebase_version 'v2.1'; only v3 datasets are read"),
        (_outside, "the data file '../elsewhere/chunk-000/file-000.parquet' leads outside the dataset's folder"),
        (_absolute, "the data file '/tmp/chunk-000/file-000.parquet' leads outside the dataset's folder"),
        (_no_state, "no feature 'observation.state' in meta/info.json"),
        (_state_shape, "observation.state has 7 values where its shape [8] says 8"),
    ],
)
def test_refusals_are_one_line_and_write_nothing(source, tmp_path, capsys, calibration, edit, message):
    root, _ = source
    copy = edited(root, tmp_path, edit)
    before = set(os.listdir(tmp_path))
    code, _, stderr = run_data_cli(capsys, "convert", copy, "--out", tmp_path / "out.zarr", *calibration)
    assert code == 2 and message in one_error_line(stderr), stderr
    assert set(os.listdir(tmp_path)) == before  # no dataset, no staging folder


def test_more_refusals(source, tmp_path, capsys, calibration):
    root, _ = source
    out = tmp_path / "out.zarr"
    code, _, stderr = run_data_cli(capsys, "convert", root, "--out", out)
    assert code == 2 and "--extrinsics is needed to convert a LeRobot dataset" in one_error_line(stderr)
    code, _, stderr = run_data_cli(capsys, "convert", root, "--out", out, *calibration, "--control-rate", "15")
    assert code == 2 and "a LeRobot dataset's control rate is its fps" in one_error_line(stderr)
    # a data file that is a link out of the dataset's folder
    copy = tmp_path / "linked"
    shutil.copytree(root, copy)
    data = copy / "data/chunk-000/file-000.parquet"
    shutil.move(data, tmp_path / "outside.parquet")
    data.symlink_to(tmp_path / "outside.parquet")
    code, _, stderr = run_data_cli(capsys, "convert", copy, "--out", out, *calibration)
    assert code == 2 and "data/chunk-000/file-000.parquet is a link" in one_error_line(stderr)
    # a data file cut short
    data.unlink()
    data.write_bytes((tmp_path / "outside.parquet").read_bytes()[:200])
    code, _, stderr = run_data_cli(capsys, "convert", copy, "--out", out, *calibration)
    assert code == 2 and "file-000.parquet: not a readable parquet file" in one_error_line(stderr)
    assert not out.exists()
    # export: a dataset without a control rate, and one whose rate is no whole number of frames per second
    episode = Episode(np.zeros((3, 8, 3), np.float32), np.zeros((3, 2), np.float32), np.zeros((3, 2), np.float32))
    for attrs, message in (
        ({}, "has no control_rate_hz attribute"),
        ({"control_rate_hz": 7.5}, "is 7.5; LeRobot's fps is a whole number"),
    ):
        plain = tmp_path / "plain.zarr"
        write_replay_buffer(plain, [episode], attrs=attrs)
        code, _, stderr = run_data_cli(capsys, "export", plain, "--to", "lerobot", "--out", tmp_path / "plain_lerobot")
        assert code == 2 and message in one_error_line(stderr), stderr
        assert not (tmp_path / "plain_lerobot").exists()
        shutil.rmtree(plain)
    code, _, stderr = run_data_cli(capsys, "export", root, "--to", "lerobot", "--out", tmp_path / "x")
    assert code == 2 and one_error_line(stderr)  # a LeRobot folder is no zarr dataset
