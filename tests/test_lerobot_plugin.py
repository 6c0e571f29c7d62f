"""The LeRobot policy plugin (plugins/lerobot_policy_dssp): ``lerobot-train --policy.type=dssp`` trains DSSP on a
dataset of ``dssp-data export --to lerobot``, and its checkpoint's ``dssp_run/`` exports with ``export.to_onnx``.

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

from dssp_data.data_cli import main as data_main
from dssp_data.replay_buffer import ReplayBuffer
from dssp_deploy import OnnxPolicy
from dssp_train.data.synthetic import write_tap_count_dataset
from export.to_onnx import main as export_main

ROOT = Path(__file__).resolve().parents[1]
PLUGIN = ROOT / "plugins" / "lerobot_policy_dssp"

_REFUSE = "    raise RuntimeError('the torchvision stand-in {}')\n"
_REFUSING_MODULE = ('"""Imported by lerobot\'s processors at module level; nothing of it is called."""\n\n\n'
                    "def __getattr__(name):\n"
                    "    def _refuse(*args, **kwargs):\n"
                    "        raise RuntimeError(f'the torchvision stand-in has no {name}')\n"
                    "    return _refuse\n")
TORCHVISION = {  # what lerobot-train imports of torchvision; every name raises if called (none is, for array data)
    "__init__.py": '"""A stand-in for torchvision: lerobot imports it; nothing here may be called."""\n'
                   "from . import io, transforms  # noqa: F401\n\n\n"
                   "def set_video_backend(backend):\n" + _REFUSE.format("decodes no video"),
    "io.py": "",
    "transforms/__init__.py": "from . import functional, v2  # noqa: F401\n\n\n"
                              "class ToTensor:\n"
                              "    def __call__(self, picture):\n" + _REFUSE.replace("    r", "        r").format(
                                  "converts no image"),
    "transforms/functional.py": _REFUSING_MODULE,
    "transforms/v2/__init__.py": "import torch\n\nfrom . import functional  # noqa: F401\n\n\n"
                                 "class Transform(torch.nn.Module):\n"
                                 "    def forward(self, *inputs):\n" + _REFUSE.replace("    r", "        r").format(
                                     "transforms nothing") + "\n\nclass Identity(Transform):\n    pass\n",
    "transforms/v2/functional.py": _REFUSING_MODULE,
}

TRAIN = "from lerobot.scripts.lerobot_train import main; main()"
# A LeRobot dataset without point clouds (depth and state), written by LeRobot, then lerobot-train on it.
DEPTH_ONLY = r'''
import sys
import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset

root = sys.argv[1]
intr = {"fx": 40.0, "fy": 40.0, "ppx": 16.0, "ppy": 12.0, "width": 32, "height": 24, "depth_unit": 0.001}
features = {"observation.state": {"dtype": "float32", "shape": (2,), "names": ["a", "b"]},
            "action": {"dtype": "float32", "shape": (2,), "names": ["a", "b"]},
            "observation.depth": {"dtype": "uint16", "shape": (24, 32), "names": ["height", "width"],
                                  "info": {"camera_intrinsics": intr}}}
ds = LeRobotDataset.create(repo_id="local/depth", root=root, fps=10, features=features, use_videos=False)
for t in range(6):
    ds.add_frame({"observation.state": np.full(2, t, np.float32), "action": np.full(2, t, np.float32),
                  "observation.depth": np.full((24, 32), 800, np.uint16), "task": "reach"})
ds.save_episode()
ds.finalize()
sys.argv = ["lerobot-train", *sys.argv[2:]]
from lerobot.scripts.lerobot_train import main
main()
'''
# The saved LeRobot policy back through LeRobot: its processors, select_action on the dataset's first frames, and
# predict_action_chunk (the streaming path) against the training path: the denoiser's prefix, and the chunk of the
# same frames and noise (after 3 steps the chunk is much the same whatever the frames: the prefix is the check).
RELOAD = r'''
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
'''


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
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([*paths, *filter(None, [os.environ.get("PYTHONPATH")])]),
           "HF_HOME": str(tmp / "hf"), "HF_HUB_OFFLINE": "1", "HF_DATASETS_OFFLINE": "1", "OMP_NUM_THREADS": "1",
           "TQDM_DISABLE": "1", "WANDB_MODE": "disabled"}
    return subprocess.run([sys.executable, "-c", script, *map(str, args)], capture_output=True, text=True, env=env,
                          cwd=ROOT, timeout=300)


def train_args(repo_id: str, root: Path, out: Path) -> list[str]:
    return [f"--dataset.repo_id={repo_id}", f"--dataset.root={root}", "--policy.type=dssp", "--steps=3",
            "--batch_size=2", "--num_workers=0", f"--output_dir={out}", "--wandb.enable=false", "--policy.device=cpu",
            "--policy.push_to_hub=false", "--save_freq=3", "--seed=0"]


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
    assert {p.name for p in pretrained.iterdir()} >= {"config.json", "model.safetensors", "policy_preprocessor.json",
                                                     "dssp_run"}
    assert {str(p.relative_to(run)) for p in run.rglob("*")} == {"config.json", "model.safetensors", "checkpoint",
                                                                "checkpoint/model.safetensors"}
    config = json.loads((run / "config.json").read_text())
    data = ReplayBuffer.load(source)
    assert config["preset"] == "tiny" and config["control_rate_hz"] == 10.0
    assert {k: config["model"][k] for k in ("state_dim", "action_dim", "n_points")} == \
        {"state_dim": data.state_dim, "action_dim": data.action_dim, "n_points": data.n_points}
    assert json.loads((pretrained / "config.json").read_text())["run_config"] == config  # recorded by LeRobot too

    model = tmp_path / "model"
    code = export_main([str(run), "-o", str(model), "--quantize", "none", "--format", "onnx", "--verify-steps", "40",
                        "--threads", "1"])
    assert code == 0
    manifest = json.loads((model / "dssp_model.json").read_text())
    assert manifest["control_rate_hz"] == 10.0 and manifest["source"]["step"] == 3 and manifest["source"]["ema"]
    policy = OnnxPolicy(model, threads=1)
    episode = data.episode(0)
    for k in range(3):
        policy.observe(episode.point_cloud[k:k + 1], episode.state[k:k + 1])
    chunk = policy.act(seed=0)
    assert chunk.shape == (1, config["model"]["horizon"], data.action_dim) and np.isfinite(chunk).all()

    # the LeRobot checkpoint itself reloads through LeRobot and acts
    proc = lerobot(tmp, paths, RELOAD, pretrained, root)
    assert proc.returncode == 0, proc.stderr[-4000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result.pop("streamed_vs_training") < 1e-4, result
    assert result == {"type": "dssp", "shape": [1, data.action_dim], "steps": 3, "finite": True}


def test_a_dataset_without_point_clouds_is_refused(setup, tmp_path):
    tmp, paths, _, _ = setup
    proc = lerobot(tmp, paths, DEPTH_ONLY, tmp_path / "depth", *train_args("local/depth", tmp_path / "depth",
                                                                           tmp_path / "out"))
    assert proc.returncode != 0
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("ValueError: the dataset has no observation.pointcloud feature"), proc.stderr[-4000:]
    assert "dssp-data convert" in last and "dssp-data export --to lerobot" in last
    assert not (tmp_path / "out" / "checkpoints").exists()
