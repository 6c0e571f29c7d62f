"""The LeRobot policy plugin (plugins/lerobot_policy_dssp): ``lerobot-train --policy.type=dssp`` trains DSSP on a
dataset of ``dssp-data export --to lerobot``, or on a LeRobot dataset of depth (the clouds made by the robot's
pipeline in a processor step), and its checkpoint's ``dssp_run/`` exports with ``export.to_onnx``.

LeRobot runs as it does for a user, through its own training entry point, in a child process (as in
tests/test_lerobot.py: a stand-in ``torchvision`` first on its path, the Hugging Face caches in the test's folder,
the hub offline). The plugin is found the way LeRobot finds plugins: by an installed distribution named
``lerobot_policy_dssp``; the child gets the package's folder and a written ``.dist-info`` on its path, so the test
needs no install of the plugin (``make setup`` installs it editable).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import CAMERA, ROOT

from dssp_data.data_cli import main as data_main
from dssp_data.observation import FRAME_ROBOT_BASE, PointCloudConfig
from dssp_data.pointcloud import frame_to_cloud, load_extrinsics, save_extrinsics
from dssp_data.pointcloud.depth_frame import DepthFrame, Intrinsics
from dssp_data.replay_buffer import ReplayBuffer
from dssp_deploy import OnnxPolicy
from dssp_train.data.synthetic import write_tap_count_dataset
from export.to_onnx import main as export_main

PLUGIN = ROOT / "plugins" / "lerobot_policy_dssp"

_REFUSE = "    raise RuntimeError('the torchvision stand-in {}')\n"
_REFUSING_MODULE = (
    '"""Imported by lerobot\'s processors at module level; nothing of it is called."""\n\n\n'
    "def __getattr__(name):\n"
    "    def _refuse(*args, **kwargs):\n"
    "        raise RuntimeError(f'the torchvision stand-in has no {name}')\n"
    "    return _refuse\n"
)
TORCHVISION = {  # what lerobot-train imports of torchvision; every name raises if called (none is, for array data)
    "__init__.py": '"""A stand-in for torchvision: lerobot imports it; nothing here may be called."""\n'
    "from . import io, transforms  # noqa: F401\n\n\n"
    "def set_video_backend(backend):\n" + _REFUSE.format("decodes no video"),
    "io.py": "",
    "transforms/__init__.py": "from . import functional, v2  # noqa: F401\n\n\n"
    "class ToTensor:\n"
    "    def __call__(self, picture):\n" + _REFUSE.replace("    r", "        r").format("converts no image"),
    "transforms/functional.py": _REFUSING_MODULE,
    "transforms/v2/__init__.py": "import torch\n\nfrom . import functional  # noqa: F401\n\n\n"
    "class Transform(torch.nn.Module):\n"
    "    def forward(self, *inputs):\n"
    + _REFUSE.replace("    r", "        r").format("transforms nothing")
    + "\n\nclass Identity(Transform):\n    pass\n",
    "transforms/v2/functional.py": _REFUSING_MODULE,
}

TRAIN = "from lerobot.scripts.lerobot_train import main; main()"
# A LeRobot dataset of depth and state (no point clouds), written by LeRobot, then lerobot-train on it; after
# training (job["check"]), the checkpoint's preprocessor back through LeRobot: the cloud it makes of frame 2's depth,
# an action, and its refusal of a frame with no point in the crop.
DEPTH_TRAIN = r"""
import json, sys, traceback
import numpy as np
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.scripts.lerobot_train import main

job = json.loads(sys.argv[1])
frames = np.load(job["frames"])
depth = frames["depth"]
for case in job["cases"]:  # each: a dataset, then lerobot-train on it
    root = case["root"]
    info = {"info": {"camera_intrinsics": case["intrinsics"]}} if case["intrinsics"] else {}
    features = {"observation.state": {"dtype": "float32", "shape": (7,), "names": None},
                "action": {"dtype": "float32", "shape": (7,), "names": None},
                "observation.depth": {"dtype": "uint16", "shape": depth.shape[1:], "names": ["height", "width"],
                                      **info}}
    ds = LeRobotDataset.create(repo_id="local/depth", root=root, fps=10, features=features, use_videos=False)
    for t in range(len(depth)):
        ds.add_frame({"observation.state": frames["state"][t], "action": frames["state"][t] + np.float32(0.01),
                      "observation.depth": depth[t], "task": "reach"})
    ds.save_episode()
    ds.finalize()
    sys.argv = ["lerobot-train", *case["argv"]]
    if len(job["cases"]) == 1:
        main()
        continue
    try:  # several cases in one process: each one's traceback as the interpreter prints it, then a separator
        main()
    except Exception:
        traceback.print_exc()
    print("-- end of case", file=sys.stderr, flush=True)
if job["check"]:
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors

    path = job["check"]
    cfg = PreTrainedConfig.from_pretrained(path)
    policy = get_policy_class(cfg.type).from_pretrained(path, config=cfg)
    pre, post = make_pre_post_processors(cfg, pretrained_path=path)
    item = LeRobotDataset("local/depth", root=job["cases"][0]["root"])[2]
    batch = pre({k: item[k] for k in ("observation.state", "observation.depth")})
    action = post(policy.select_action(batch))
    # a training sample as LeRobot draws it: frame 2 with its history (the first 5 of T frames pad, outside the episode)
    deltas = [k / 10 for k in range(1 - cfg.history, policy.run_config.model.horizon)]
    sample = LeRobotDataset("local/depth", root=job["cases"][0]["root"],
                            delta_timestamps={k: deltas for k in ("observation.state", "observation.depth")})[2]
    keys = ("observation.state", "observation.depth", "observation.depth_is_pad")
    window = pre({**{k: sample[k][None] for k in keys}, "index": torch.tensor([2]), "episode_index": torch.tensor([0])})
    # a training sample (B, T, H, W) of which one frame sees nothing inside the crop
    T = cfg.history + policy.run_config.model.horizon - 1
    empty = torch.zeros((1, T, *depth.shape[1:]), dtype=torch.int64)
    try:
        pre({"observation.state": torch.zeros((1, T, 7)), "observation.depth": empty,
             "observation.depth_is_pad": torch.arange(T)[None] < cfg.history - 2, "index": torch.tensor([7]),
             "episode_index": torch.tensor([0])})
        refusal = None
    except ValueError as exc:
        refusal = str(exc)
    np.savez(job["out"], cloud=batch["observation.pointcloud"].numpy(), depth=item["observation.depth"].numpy(),
             action=action.numpy(), window=window["observation.pointcloud"][0].numpy(),
             window_pad=window["observation.pointcloud_is_pad"][0].numpy())
    print(json.dumps({"keys": sorted(batch), "refusal": refusal}))
"""
# The saved LeRobot policy back through LeRobot: its processors, select_action on the dataset's first frames, and
# predict_action_chunk (the streaming path) against the training path: the denoiser's prefix, and the chunk of the
# same frames and noise (after 3 steps the chunk is much the same whatever the frames: the prefix is the check).
RELOAD = r"""
import json, sys
import torch
from lerobot.utils.import_utils import register_third_party_plugins
register_third_party_plugins()
from lerobot.configs.policies import PreTrainedConfig
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.factory import get_policy_class, make_pre_post_processors

path, root = sys.argv[1], sys.argv[2]
cfg = PreTrainedConfig.from_pretrained(path)
policy = get_policy_class(cfg.type).from_pretrained(path, config=cfg)
pre, post = make_pre_post_processors(cfg, pretrained_path=path)
ds = LeRobotDataset("local/tap", root=root)
frames = [pre({k: ds[i][k] for k in ("observation.state", "observation.pointcloud")}) for i in range(5)]
policy.reset()
actions = [post(policy.select_action(batch)) for batch in frames]
policy.reset()
m = policy.run_config.model
gen = torch.Generator().manual_seed(0)
worst = 0.0
for i, batch in enumerate(frames):
    noise = torch.randn((1, m.horizon, m.action_dim), generator=gen)
    streamed = policy.predict_action_chunk(batch, noise=noise)
    clouds = torch.stack([f["observation.pointcloud"] for f in frames[:i + 1]])
    states = torch.cat([f["observation.state"] for f in frames[:i + 1]])
    reference = policy.model.sample_trajectory_windows(clouds, states, torch.tensor([i]), noise)
    # the denoiser's prefix [c_t, z_{t-N+1..t}]: streamed, and from the whole trajectory as in training
    prefix = policy.model.build_prefix(policy._stream.context, policy._stream.recent)
    trained, _ = policy.model.window_prefix(*policy.model.encode_trajectory(clouds, states), torch.tensor([i]))
    worst = max(worst, float((streamed - reference).abs().max()), float((prefix - trained).abs().max()))
print(json.dumps({"type": cfg.type, "shape": list(actions[0].shape), "steps": int(policy.optimizer_steps),
                  "finite": all(bool(torch.isfinite(a).all()) for a in actions), "streamed_vs_training": worst}))
"""


def write_plugin_path(tmp: Path) -> list[str]:
    """The stand-in torchvision and the plugin's distribution metadata, written into ``tmp``; the folders to put on
    the child's path (with the plugin's own folder and the repository)."""
    stand_in = tmp / "stand_in"
    for name, text in TORCHVISION.items():
        path = stand_in / "torchvision" / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    dist = tmp / "dist" / "lerobot_policy_dssp-0.1.0.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: lerobot_policy_dssp\nVersion: 0.1.0\n")
    return [str(stand_in), str(dist.parent), str(PLUGIN), str(ROOT)]


def lerobot(tmp: Path, paths: list[str], script: str, *args) -> subprocess.CompletedProcess:
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([*paths, *filter(None, [os.environ.get("PYTHONPATH")])]),
        "HF_HOME": str(tmp / "hf"),
        "HF_HUB_OFFLINE": "1",
        "HF_DATASETS_OFFLINE": "1",
        "OMP_NUM_THREADS": "1",
        "TQDM_DISABLE": "1",
        "WANDB_MODE": "disabled",
    }
    return subprocess.run(
        [sys.executable, "-c", script, *map(str, args)], capture_output=True, text=True, env=env, cwd=ROOT, timeout=300
    )


STANDARD_FP32 = ["--quantize", "none", "--no-fused", "--format", "onnx", "--threads", "1"]
"""Export flags: the fp32 standard graphs, verified on one thread (the fused graphs have their own tests)."""


def train_args(repo_id: str, root: Path, out: Path) -> list[str]:
    return [
        f"--dataset.repo_id={repo_id}",
        f"--dataset.root={root}",
        "--policy.type=dssp",
        "--steps=3",
        "--batch_size=2",
        "--num_workers=0",
        f"--output_dir={out}",
        "--wandb.enable=false",
        "--policy.device=cpu",
        "--policy.push_to_hub=false",
        "--save_freq=3",
        "--seed=0",
    ]


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """(tmp, the child's path, the exported LeRobot dataset, its zarr source)."""
    tmp = tmp_path_factory.mktemp("lerobot_plugin")
    source = write_tap_count_dataset(tmp / "tap.zarr", 2, seed=0, n_points=32)
    root = tmp / "tap_lerobot"
    assert data_main(["export", str(source), "--to", "lerobot", "--out", str(root), "--repo-id", "local/tap"]) == 0
    return tmp, write_plugin_path(tmp), root, source


def test_lerobot_train_then_export_to_onnx(setup, tmp_path):
    tmp, paths, root, source = setup
    out = tmp_path / "train"
    proc = lerobot(tmp, paths, TRAIN, *train_args("local/tap", root, out))
    assert proc.returncode == 0, proc.stderr[-4000:]
    pretrained = out / "checkpoints" / "last" / "pretrained_model"
    run = pretrained / "dssp_run"
    assert {p.name for p in pretrained.iterdir()} >= {
        "config.json",
        "model.safetensors",
        "policy_preprocessor.json",
        "dssp_run",
    }
    assert {str(p.relative_to(run)) for p in run.rglob("*")} == {
        "config.json",
        "model.safetensors",
        "checkpoint",
        "checkpoint/model.safetensors",
    }
    config = json.loads((run / "config.json").read_text())
    data = ReplayBuffer.load(source)
    assert config["preset"] == "tiny" and config["control_rate_hz"] == 10.0
    assert {k: config["model"][k] for k in ("state_dim", "action_dim", "n_points")} == {
        "state_dim": data.state_dim,
        "action_dim": data.action_dim,
        "n_points": data.n_points,
    }
    assert json.loads((pretrained / "config.json").read_text())["run_config"] == config  # recorded by LeRobot too

    model = tmp_path / "model"
    assert export_main([str(run), "-o", str(model), *STANDARD_FP32, "--verify-steps", "40"]) == 0
    manifest = json.loads((model / "dssp_model.json").read_text())
    assert (
        manifest["contract"]["control_rate_hz"] == 10.0
        and manifest["source"]["step"] == 3
        and manifest["source"]["ema"]
    )
    policy = OnnxPolicy(model, threads=1)
    episode = data.episode(0)
    for k in range(3):
        policy.observe(episode.point_cloud[k : k + 1], episode.state[k : k + 1])
    chunk = policy.act(seed=0)
    assert chunk.shape == (1, config["model"]["horizon"], data.action_dim) and np.isfinite(chunk).all()

    # the LeRobot checkpoint itself reloads through LeRobot and acts
    proc = lerobot(tmp, paths, RELOAD, pretrained, root)
    assert proc.returncode == 0, proc.stderr[-4000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result.pop("streamed_vs_training") < 1e-4, result
    assert result == {"type": "dssp", "shape": [1, data.action_dim], "steps": 3, "finite": True}


@pytest.fixture(scope="module")
def depth(setup) -> dict:
    """One episode of the simulated tabletop camera's depth (160x120, noiseless) and a 7-value state: the frames
    (.npz), the camera's calibration file and its intrinsics as a LeRobot depth feature's info holds them."""
    tmp = setup[0]
    t = np.arange(6) / 10
    depth = np.stack([CAMERA.render(s)[0] for s in t])
    state = np.stack([np.sin(t + k) for k in range(7)], axis=1).astype(np.float32)
    np.savez(tmp / "frames.npz", depth=depth, state=state)
    save_extrinsics(tmp / "calib.json", CAMERA.camera_to_base)
    k = CAMERA.intrinsics
    return {
        "frames": tmp / "frames.npz",
        "calib": tmp / "calib.json",
        "intrinsics": {
            "fx": k.fx,
            "fy": k.fy,
            "ppx": k.ppx,
            "ppy": k.ppy,
            "width": k.width,
            "height": k.height,
            "depth_unit": CAMERA.depth_unit,
        },
    }


def train_on_depth(setup, depth: dict, cases: list[tuple[Path, Path, bool, list[str]]], check=None):
    """lerobot-train on depth datasets, in one child: each case (dataset root, output dir, whether the depth
    feature has intrinsics, more arguments)."""
    tmp, paths = setup[:2]
    job = {
        "frames": str(depth["frames"]),
        "check": str(check) if check else None,
        "out": str(cases[0][1] / "check.npz"),
        "cases": [
            {
                "root": str(root),
                "intrinsics": depth["intrinsics"] if intrinsics else None,
                "argv": [*train_args("local/depth", root, out), *args],
            }
            for root, out, intrinsics, args in cases
        ],
    }
    return lerobot(tmp, paths, DEPTH_TRAIN, json.dumps(job))


def test_lerobot_train_on_depth_makes_the_robots_clouds(setup, depth, tmp_path):
    """A dataset of depth with its camera's intrinsics, and the camera's pose: trained on the clouds of the robot's
    pipeline; the dssp_run/ exports and records the clouds' settings and frame; the saved preprocessor makes a
    frame's cloud bit for bit as frame_to_cloud does."""
    frames, calib, intr = depth["frames"], depth["calib"], depth["intrinsics"]
    out = tmp_path / "train"
    pretrained = out / "checkpoints" / "last" / "pretrained_model"
    args = [f"--policy.extrinsics={calib}", "--policy.history=8"]  # the episode's 6 frames: the whole history
    proc = train_on_depth(setup, depth, [(tmp_path / "depth", out, True, args)], check=pretrained)
    assert proc.returncode == 0, proc.stderr[-4000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert "observation.depth" not in result["keys"] and "observation.pointcloud" in result["keys"]
    assert result["refusal"].startswith(
        "the depth frame observation.depth at dataset index 6 (episode 0) has no point in the crop box"
    ), result["refusal"]

    cloud_config = PointCloudConfig(n_points=64)  # the tiny preset's clouds
    run = pretrained / "dssp_run"
    config = json.loads((run / "config.json").read_text())
    assert config["observation"]["pointcloud"] == cloud_config.to_dict()
    assert config["observation"]["frame"] == FRAME_ROBOT_BASE
    assert {k: config["model"][k] for k in ("state_dim", "action_dim", "n_points", "point_dim")} == {
        "state_dim": 7,
        "action_dim": 7,
        "n_points": 64,
        "point_dim": 3,
    }
    saved = json.loads((pretrained / "config.json").read_text())
    pinhole = {k: intr[k] for k in ("width", "height", "fx", "fy", "ppx", "ppy")}
    assert saved["depth_camera"]["intrinsics"] == pinhole
    assert "observation.pointcloud" in saved["input_features"] and "observation.depth" not in saved["input_features"]

    check = np.load(out / "check.npz")
    data = np.load(frames)
    np.testing.assert_array_equal(check["depth"], data["depth"][2])
    camera_to_base = load_extrinsics(calib)
    intrinsics = Intrinsics(**pinhole)
    expected, _ = frame_to_cloud(
        DepthFrame(
            depth=data["depth"][2], depth_unit=intr["depth_unit"], intrinsics=intrinsics, timestamp=0.0, frame_number=2
        ),
        cloud_config,
        camera_to_base,
    )
    assert check["cloud"].dtype == np.float32 and check["cloud"].tobytes() == expected.tobytes()
    assert check["action"].shape == (1, 7) and np.isfinite(check["action"]).all()
    # a training sample's clouds: frame 2 is the 8th of its window (--policy.history=8); the 5 frames before the
    # episode's start are padding, with the cloud of the first frame
    clouds = [
        frame_to_cloud(
            DepthFrame(depth=d, depth_unit=intr["depth_unit"], intrinsics=intrinsics, timestamp=0.0, frame_number=0),
            cloud_config,
            camera_to_base,
        )[0]
        for d in data["depth"]
    ]
    window, pad = check["window"], check["window_pad"]
    assert pad.tolist() == [True] * 5 + [False] * (len(pad) - 5)
    for j in range(len(window)):
        np.testing.assert_array_equal(window[j], clouds[max(j - 5, 0)])

    model = tmp_path / "model"
    assert export_main([str(run), "-o", str(model), *STANDARD_FP32, "--verify-steps", "20"]) == 0
    manifest = json.loads((model / "dssp_model.json").read_text())
    assert manifest["contract"]["observation"]["frame"] == FRAME_ROBOT_BASE
    policy = OnnxPolicy(model, threads=1)
    for k in range(3):
        cloud, _ = frame_to_cloud(
            DepthFrame(
                depth=data["depth"][k],
                depth_unit=intr["depth_unit"],
                intrinsics=intrinsics,
                timestamp=0.0,
                frame_number=k,
            ),
            cloud_config,
            camera_to_base,
        )
        policy.observe(cloud[None], data["state"][k : k + 1])
    chunk = policy.act(seed=0)
    assert chunk.shape == (1, config["model"]["horizon"], 7) and np.isfinite(chunk).all()


def test_depth_without_its_camera_is_refused(setup, depth, tmp_path):
    """Depth without its intrinsics, and depth with them but no --policy.extrinsics: one line each, no checkpoint."""
    cases = [
        (tmp_path / f"depth{i}", tmp_path / f"out{i}", intrinsics, []) for i, intrinsics in enumerate((False, True))
    ]
    proc = train_on_depth(setup, depth, cases)
    assert proc.returncode == 0, proc.stderr[-4000:]
    runs = proc.stderr.split("-- end of case")[:2]
    lasts = [run.strip().splitlines()[-1] for run in runs]
    assert lasts[0].startswith(
        "ValueError: the dataset's depth feature observation.depth has no info.camera_intrinsics"
        " {fx, fy, ppx, ppy, width, height, depth_unit}"
    ), proc.stderr[-4000:]
    assert lasts[1].startswith(
        "ValueError: training on the depth feature observation.depth needs the camera's pose: "
        "give --policy.extrinsics=calib.json"
    ), proc.stderr[-4000:]
    assert all("Traceback" in run for run in runs)
    assert not any((out / "checkpoints").exists() for _, out, _, _ in cases)


# lerobot-train several times in one process (its imports once): each case's traceback as the interpreter prints it
TRAIN_CASES = r"""
import json, sys, traceback
from lerobot.scripts.lerobot_train import main

for argv in json.loads(sys.argv[1]):
    sys.argv = ["lerobot-train", *argv]
    try:
        main()
    except Exception:
        traceback.print_exc()
    print("-- end of case", file=sys.stderr, flush=True)
"""


def test_a_history_out_of_range_or_over_the_read_budget_is_refused_before_training(setup, tmp_path, monkeypatch):
    """--policy.history=0 is refused with its own message as the last line (not draccus' generic one), and a
    history whose samples would take more than DSSP_READ_BUDGET is refused before LeRobot loads a sample."""
    tmp, paths, root, _ = setup
    monkeypatch.setenv("DSSP_READ_BUDGET", "8M")  # a sample of 100,000 frames of this dataset: about 40 MiB
    cases = [[*train_args("local/tap", root, tmp_path / f"out{h}"), f"--policy.history={h}"] for h in (0, 100_000)]
    proc = lerobot(tmp, paths, TRAIN_CASES, json.dumps(cases))
    assert proc.returncode == 0, proc.stderr[-4000:]
    runs = proc.stderr.split("-- end of case")[:2]
    lasts = [run.strip().splitlines()[-1] for run in runs]
    assert lasts[0] == "ValueError: --policy.history must be in [1, 100000] frames, got 0", runs[0][-3000:]
    assert lasts[1].startswith("ValueError: a training sample of --policy.history=100000 frames"), runs[1][-3000:]
    assert (
        "over the read budget of 8.0 MiB (DSSP_READ_BUDGET): lower --policy.history (the longest episode has "
        "40 frames)" in lasts[1]
    )
    assert "Start offline training" not in proc.stderr
    assert not any((tmp_path / f"out{h}" / "checkpoints").exists() for h in (0, 100_000))
