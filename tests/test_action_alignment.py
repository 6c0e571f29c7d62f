"""Action-chunk alignment: the chunk starts at the current step t, or at t - N + 1 as DP3 does (execution from
index N - 1), consistently in training, the manifest and the runtime's control loop."""

import json
import shutil

import numpy as np
import pytest
import torch
from conftest import SET_SMALL

from dssp_core.errors import ConfigError
from dssp_deploy import OnnxPolicy
from dssp_deploy.control_loop import ChunkedControl
from dssp_deploy.manifest import MANIFEST_NAME, ModelDirError
from dssp_deploy.schedules import MeasuredDelay, Plain
from dssp_train.config import apply_overrides, load_preset
from dssp_train.model.policy import DSSPPolicy


def tiny_model(alignment: str):
    config = apply_overrides(
        load_preset("tiny"), [f"model.action_alignment={alignment}", "model.state_dim=2", "model.action_dim=2"]
    )
    return config.model


def test_dp3_alignment_needs_room_for_the_executed_actions():
    model = tiny_model("dp3")  # N 2, H 4, H_a 3: H_a = H - N + 1, the paper's tables
    assert model.action_offset == 1 and tiny_model("current").action_offset == 0
    with pytest.raises(ConfigError, match=r"must be at most horizon - N \+ 1 = 3, got 4") as err:
        apply_overrides(load_preset("tiny"), ["model.action_alignment=dp3", "model.n_action_steps=4"])
    assert "\n" not in str(err.value)


def test_training_targets_start_at_the_oldest_recent_observation_with_dp3():
    starts = torch.tensor([0, 5])  # N = 2, H = 4, a trajectory of 7 steps
    current = DSSPPolicy(tiny_model("current")).trajectory_windows(7, starts)
    dp3 = DSSPPolicy(tiny_model("dp3")).trajectory_windows(7, starts)
    assert current[0].tolist() == dp3[0].tolist() == [[0, 0], [4, 5]]  # the same recent observations
    assert current[1].tolist() == [[0, 1, 2, 3], [5, 6, 6, 6]]  # from t; past the end the last action repeats
    assert dp3[1].tolist() == [[0, 0, 1, 2], [4, 5, 6, 6]]  # from t - N + 1; before the start the first one repeats


def dp3_copy(model_dir, tmp_path):
    """The tiny export relabelled as a DP3-aligned model (the graphs do not depend on the alignment)."""
    copy = tmp_path / "model"
    shutil.copytree(model_dir, copy)
    manifest = json.loads((copy / MANIFEST_NAME).read_text())
    manifest["contract"]["action_offset"] = manifest["contract"]["n_obs_steps"] - 1
    (copy / MANIFEST_NAME).write_text(json.dumps(manifest))
    return copy, manifest


def test_the_control_loop_executes_the_chunk_from_the_manifests_offset(tiny_export, tmp_path):
    _, model_dir, data = tiny_export
    model, manifest = dp3_copy(model_dir, tmp_path)
    policy = OnnxPolicy(model, threads=1)
    offset, ha = policy.contract.action_offset, policy.contract.n_action_steps
    assert (
        offset == manifest["contract"]["n_obs_steps"] - 1 == 1
        and OnnxPolicy(model_dir, threads=1).contract.action_offset == 0
    )
    loop = ChunkedControl(policy, seed=0)
    rng = np.random.default_rng(0)
    obs = [policy.example_observation(rng, 32) for _ in range(2 * ha)]
    ticks = [loop.tick(*o) for o in obs]
    assert [info.chunk_index for _, info in ticks] == [offset + t % ha for t in range(2 * ha)]
    reference = OnnxPolicy(model, threads=1, warmup=0)
    reference.observe(*obs[0])
    chunk = reference.act(seed=0)
    assert all(np.array_equal(ticks[j][0], chunk[:, offset + j]) for j in range(ha))
    with pytest.raises(ValueError, match="H - action_offset - H_a = 0 predicted actions can be dropped"):
        ChunkedControl(
            policy, Plain(prefetch=True, delay=MeasuredDelay(50.0)), control_rate_hz=10
        )  # H_a = H - N + 1 leaves none


def test_a_manifest_whose_offset_is_neither_the_current_step_nor_n_minus_1_is_refused(tiny_export, tmp_path):
    _, model_dir, _ = tiny_export
    model, manifest = dp3_copy(model_dir, tmp_path)
    manifest["contract"]["action_offset"] = 2
    (model / MANIFEST_NAME).write_text(json.dumps(manifest))
    with pytest.raises(ModelDirError, match="contract.action_offset must be 0 or n_obs_steps - 1 = 1, got 2") as err:
        OnnxPolicy(model, threads=1)
    assert "\n" not in str(err.value)


def test_export_records_the_offset(tmp_path):
    from dssp_train.cli.train import main as train_main
    from dssp_train.data.synthetic import write_tap_count_dataset
    from export.to_onnx import main as export_main

    data = write_tap_count_dataset(tmp_path / "tap.zarr", 3, seed=0, n_points=24)
    assert (
        train_main(
            [
                "--data",
                str(data),
                "--out",
                str(tmp_path / "run"),
                "--steps",
                "2",
                "--no-progress",
                *SET_SMALL,
                "--set",
                "model.action_alignment=dp3",
                "--no-holdout",
            ]
        )
        == 0
    )
    assert (
        export_main(
            [
                str(tmp_path / "run"),
                "-o",
                str(tmp_path / "model"),
                "--skip-verify",
                "--quantize",
                "none",
                "--no-fused",
                "--format",
                "onnx",
            ]
        )
        == 0
    )
    manifest = json.loads((tmp_path / "model" / MANIFEST_NAME).read_text())
    assert manifest["contract"]["action_offset"] == manifest["contract"]["n_obs_steps"] - 1
    assert OnnxPolicy(tmp_path / "model", threads=1).contract.action_offset == manifest["contract"]["action_offset"]
