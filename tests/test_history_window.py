"""A history window of T_h steps (the paper's "w/o full history", Table 4): the streaming step equals the
training path, and the model exports, verifies and runs on the runtime like a full-history one."""

import json

import numpy as np
import torch
from conftest import SET_SMALL

from dssp_deploy import OnnxPolicy
from dssp_deploy.manifest import MANIFEST_NAME
from dssp_train.config import apply_overrides, load_preset
from dssp_train.model.history_encoder import HistoryEncoder


def test_the_streaming_window_equals_the_training_path_from_a_zero_state():
    config = apply_overrides(load_preset("tiny"), ["model.history_window=4", "model.state_dim=2", "model.action_dim=2"])
    torch.manual_seed(0)
    encoder = HistoryEncoder(config.model).eval()
    z = torch.randn(2, 9, config.model.d_model)
    with torch.no_grad():
        full = encoder(z)  # (B, T, d): each step from its last 4 observations, the first one repeated before the start
        state, streamed = None, []
        for t in range(z.shape[1]):
            c, state = encoder.step(z[:, t], state)
            streamed.append(c)
        unrolled = encoder.window_step(z[:, 0], *encoder.window_start(z[:, 0]), unrolled=True)[0]
    assert torch.allclose(torch.stack(streamed, dim=1), full, atol=1e-5)
    assert torch.allclose(unrolled, full[:, 0], atol=1e-5)  # the traceable path the history graph runs
    window, seen = state
    assert window.shape == (2, 4, config.model.d_model) and seen.tolist() == [[4.0], [4.0]]


def test_a_window_model_exports_verifies_and_runs(tmp_path, capsys):
    from dssp_train.cli.train import main as train_main
    from dssp_train.data.synthetic import write_tap_count_dataset
    from export.to_onnx import main as export_main

    data = write_tap_count_dataset(tmp_path / "tap.zarr", 3, seed=0, n_points=24)
    run, model = tmp_path / "run", tmp_path / "model"
    assert (
        train_main(
            [
                "--data",
                str(data),
                "--out",
                str(run),
                "--steps",
                "2",
                "--no-progress",
                *SET_SMALL,
                "--history-window",
                "5",
                "--no-holdout",
            ]
        )
        == 0
    )
    # parity against PyTorch's streaming step over 1000 ticks, the standard and fused graphs alike
    assert (
        export_main([str(run), "-o", str(model), "--quantize", "none", "--format", "onnx", "--verify-steps", "200"])
        == 0
    )
    assert "PASS" in capsys.readouterr().out
    manifest = json.loads((model / MANIFEST_NAME).read_text())
    assert [s["name"] for s in manifest["graphs"]["history_step"]["inputs"][2:]] == ["z_window", "z_seen"]
    assert manifest["model_config"]["history_window"] == 5
    policy = OnnxPolicy(model, threads=1)
    rng = np.random.default_rng(0)
    for _ in range(7):
        policy.observe(*policy.example_observation(rng, 24))
    assert policy.state["z_window"].shape == (1, 5, manifest["model_config"]["d_model"]) and policy.state[
        "z_seen"
    ].tolist() == [[5.0]]
    assert np.isfinite(policy.act(seed=0)).all()
