"""Data-parallel training on CPU: two processes under torchrun (gloo) end with identical weights."""

import hashlib
import json
import os
import subprocess
import sys

import pytest

from dssp_train.data.synthetic import write_tap_count_dataset
from dssp_train.training.checkpoint import load_policy
from dssp_train.training.train_log import read_log

STEPS = 6
BATCH = 4
WORLD_SIZE = 2
SMALL = [
    "model.d_model=32",
    "model.d_state=8",
    "model.n_denoiser_layers=2",
    "model.n_history_layers=1",
    f"train.batch_size={BATCH}",
    "train.val_windows=4",
    "train.warmup_steps=1",
    "train.log_every=2",
    "train.val_every=3",
    "train.save_every=3",
]
RUN_FILES = {
    "config.json",
    "model.safetensors",
    "log.jsonl",
    "loss.png",
    "checkpoint/model.safetensors",
    "checkpoint/ema.safetensors",
    "checkpoint/optimizer.safetensors",
    "checkpoint/rng.safetensors",
    "checkpoint/trainer_state.json",
}


@pytest.fixture(scope="module")
def ddp_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("ddp")
    data = write_tap_count_dataset(root / "data.zarr", 5, seed=0, n_points=24)
    out = root / "run"
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        "--nproc_per_node",
        str(WORLD_SIZE),
        "-m",
        "dssp_train.cli.train",
        "--data",
        str(data),
        "--out",
        str(out),
        "--steps",
        str(STEPS),
        "--device",
        "cpu",
        "--no-progress",
    ]
    for item in SMALL:
        cmd += ["--set", item]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    for key in ("WORLD_SIZE", "RANK", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        env.pop(key, None)
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    return {"proc": proc, "out": out}


def test_torchrun_exits_cleanly_with_one_summary(ddp_run):
    proc = ddp_run["proc"]
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr
    summary = json.loads(proc.stdout)  # printed by rank 0 only: exactly one JSON object
    assert summary["step"] == STEPS
    assert summary["run_dir"] == str(ddp_run["out"])


def test_run_directory_is_complete(ddp_run):
    out = ddp_run["out"]
    assert ddp_run["proc"].returncode == 0, ddp_run["proc"].stderr[-3000:]
    assert {str(p.relative_to(out)) for p in out.rglob("*") if p.is_file()} == RUN_FILES
    state = json.loads((out / "checkpoint" / "trainer_state.json").read_text())
    assert state["step"] == STEPS and state["world_size"] == WORLD_SIZE
    assert (out / "loss.png").read_bytes().startswith(b"\x89PNG\r\n\x1a\n")

    rows = read_log(out / "log.jsonl")
    # Only rank 0 writes the log: every row once.
    assert [r["step"] for r in rows if r["kind"] == "train"] == [2, 4, 6]
    assert [r["step"] for r in rows if r["kind"] == "val"] == [3, 6]
    assert [r["kind"] for r in rows].count("ddp") == 1


def test_processes_end_with_identical_weights(ddp_run):
    out = ddp_run["out"]
    assert ddp_run["proc"].returncode == 0, ddp_run["proc"].stderr[-3000:]
    rows = [r for r in read_log(out / "log.jsonl") if r["kind"] == "ddp"]
    assert len(rows) == 1
    row = rows[0]
    assert row["world_size"] == WORLD_SIZE
    checksums = row["param_checksums"]
    assert len(checksums) == WORLD_SIZE
    assert all(isinstance(c, str) and len(c) == 64 for c in checksums)
    assert len(set(checksums)) == 1

    # The checksum is that of the trained raw weights the run saved, and it tells weights apart:
    # the EMA weights (model.safetensors) give another one.
    assert state_dict_sha256(out, "checkpoint/model.safetensors") == checksums[0]
    assert state_dict_sha256(out, "model.safetensors") != checksums[0]


def state_dict_sha256(out, weights: str) -> str:
    """What the trainer hashes: every state_dict tensor's bytes, in the module's order."""
    policy, _ = load_policy(out, weights=weights)
    digest = hashlib.sha256()
    for value in policy.state_dict().values():
        digest.update(value.detach().contiguous().numpy().tobytes())
    return digest.hexdigest()


def test_throughput_counts_both_processes(ddp_run):
    assert ddp_run["proc"].returncode == 0, ddp_run["proc"].stderr[-3000:]
    train = [r for r in read_log(ddp_run["out"] / "log.jsonl") if r["kind"] == "train"]
    assert train
    for r in train:
        assert r["steps_per_s"] > 0
        assert r["windows_per_s"] == pytest.approx(r["steps_per_s"] * BATCH * WORLD_SIZE, rel=1e-9)
