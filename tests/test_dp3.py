"""DP3 as a trained baseline: its UNet denoiser in the policy, its presets, and the whole chain (train, export with
parity, the runtime, dssp-sim eval) run unchanged on it."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from torch import nn

from dssp_core.errors import ConfigError
from dssp_deploy.flops import chunk_flops, unet_flops
from dssp_train.config import apply_overrides, load_preset
from dssp_train.model.param_count import parameter_breakdown
from dssp_train.model.policy import DSSPPolicy
from dssp_train.model.unet import StepTable, UNetDenoiser

SMALL_UNET = ["model.unet_down_dims=[16,32]", "model.unet_step_embed_dim=16"]


def dp3_config(preset: str = "dp3_sim", dims: int = 7, extra: tuple[str, ...] = ()):
    return apply_overrides(load_preset(preset), [f"model.state_dim={dims}", f"model.action_dim={dims}", *extra]).model


def test_the_dp3_preset_is_dp3s_robotwin_configuration():
    cfg = dp3_config("dp3", 14)
    policy = DSSPPolicy(cfg)
    assert isinstance(policy.denoiser, UNetDenoiser) and policy.history_encoder is None and policy.dynamics is None
    assert isinstance(policy.obs_encoder.projection, nn.Identity)  # DP3 conditions on the features themselves
    assert (cfg.n_obs_steps, cfg.horizon, cfg.n_action_steps, cfg.action_offset) == (3, 8, 6, 2)
    assert cfg.unet_down_dims == [512, 1024, 2048] and cfg.unet_step_embed_dim == 64 and cfg.d_model == 128 + 64
    # FiLM of the first block: Mish + Linear(step embedding + 3 frames of 192 features, 2 x 512)
    assert policy.denoiser.down[0][0].film[1].weight.shape == (2 * 512, 64 + 3 * 192)
    rows = dict(parameter_breakdown(policy))
    assert rows["f_theta UNet convolutions (DP3)"] > 200e6 and "G_psi history encoder" not in rows
    assert rows["total"] == sum(p.numel() for p in policy.parameters())


def test_the_small_dp3_preset_has_the_sim_presets_parameter_count():
    sim = sum(
        p.numel()
        for p in DSSPPolicy(
            apply_overrides(load_preset("sim"), ["model.state_dim=7", "model.action_dim=7"]).model
        ).parameters()
    )
    dp3 = sum(p.numel() for p in DSSPPolicy(dp3_config()).parameters())
    assert abs(dp3 / sim - 1) < 0.1, (dp3, sim)


@pytest.mark.parametrize(
    "override, says",
    [
        ("model.d_model=64", "model.d_model must be point_feature_dim + state_widths[-1] = 96"),
        ("model.horizon=6", "model.horizon must be a multiple of 4"),
        ("model.unet_down_dims=[32,44,64]", "multiples of model.unet_n_groups=8"),
        ("model.unet_kernel_size=4", "model.unet_kernel_size must be odd"),
    ],
)
def test_a_unet_config_that_cannot_be_built_is_one_line(override, says):
    with pytest.raises(ConfigError, match=None) as info:
        dp3_config(extra=(override,))
    assert says in str(info.value) and "\n" not in str(info.value)


def test_the_training_path_equals_the_sampling_paths():
    cfg = dp3_config(extra=tuple(SMALL_UNET))
    den = UNetDenoiser(cfg).eval()
    g = torch.Generator().manual_seed(0)
    prefix = torch.randn(3, cfg.prefix_length, cfg.d_model, generator=g)
    x = torch.randn(3, cfg.horizon, cfg.action_dim, generator=g)
    t = torch.tensor([90, 90, 90])
    with torch.no_grad():
        full = den(prefix, x, t)
        table = den.modulation(torch.tensor([90, 40]))
        cached = den.denoise_modulated(den.encode_prefix(prefix), x, table.at(0))  # one row shared by the batch
        other = den(prefix, x, torch.tensor([40, 40, 40]))
    assert isinstance(table, StepTable) and table.embedding.shape == (2, cfg.unet_step_embed_dim)
    torch.testing.assert_close(cached, full, rtol=1e-5, atol=1e-6)
    assert not torch.allclose(other, full)  # the timestep reaches the output
    # each frame of the prefix is a separate part of the condition: swapping the two frames changes the chunk
    with torch.no_grad():
        swapped = den(prefix.flip(1), x, t)
    assert not torch.allclose(swapped, full)


def test_the_flop_count_is_the_unets_own():
    """unet_flops (what dssp-profile divides by) equals 2 x the multiply-adds the UNet's layers run."""
    cfg = dp3_config()
    den = UNetDenoiser(cfg).eval()
    macs = [0]

    def count(module, inputs, output):
        if isinstance(module, nn.Linear):
            macs[0] += output.shape[0] * module.in_features * module.out_features
        elif isinstance(module, nn.Conv1d):
            macs[0] += output.numel() * module.in_channels * module.kernel_size[0]
        else:  # ConvTranspose1d: every input position meets every output channel through the kernel
            macs[0] += (
                inputs[0].shape[0]
                * inputs[0].shape[2]
                * module.in_channels
                * module.out_channels
                * module.kernel_size[0]
            )

    step = {id(m) for m in den.step_encoder.modules()}
    for m in den.modules():
        if isinstance(m, (nn.Linear, nn.Conv1d, nn.ConvTranspose1d)) and id(m) not in step:
            m.register_forward_hook(count)
    with torch.no_grad():
        den.denoise_modulated(
            torch.zeros(1, cfg.prefix_length * cfg.d_model),
            torch.zeros(1, cfg.horizon, cfg.action_dim),
            den.modulation(torch.tensor([5])),
        )
    assert unet_flops(cfg.to_dict()) == 2 * macs[0]
    assert chunk_flops(cfg.to_dict(), 10) == 10 * 2 * macs[0]


@pytest.fixture(scope="module")
def dp3_model(tmp_path_factory):
    """A briefly trained small DP3 for one simulated Piper, exported with its parity verified."""
    from conftest import write_arm_dataset

    from dssp_train.cli.train import main as train_main
    from export.to_onnx import main as export_main

    root = tmp_path_factory.mktemp("dp3")
    data = write_arm_dataset(root / "arm.zarr", n_points=256)  # one Piper: state = action = 7, clouds in the sim's crop
    sets = [a for item in [*SMALL_UNET, "train.val_every=10"] for a in ("--set", item)]
    assert (
        train_main(
            [
                "--data",
                str(data),
                "--out",
                str(root / "run"),
                "--preset",
                "dp3_sim",
                "--steps",
                "10",
                *sets,
                "--no-progress",
            ]
        )
        == 0
    )
    # export verifies parity of every graph against the PyTorch policy and fails above its bound
    assert (
        export_main([str(root / "run"), "-o", str(root / "model"), "--quantize", "none", "--verify-steps", "20"]) == 0
    )
    return root / "model"


def test_dp3_exports_as_an_observation_graph_and_a_denoiser_graph(dp3_model):
    from dssp_deploy.onnx_policy import OnnxPolicy

    manifest = json.loads((dp3_model / "dssp_model.json").read_text())
    history_inputs = [s["name"] for s in manifest["graphs"]["history_step"]["inputs"]]
    assert manifest["model_config"]["use_history"] is False and history_inputs == ["point_cloud", "agent_pos"]
    assert manifest["model_config"]["denoiser_backbone"] == "unet"
    assert not any("fused" in name for name in manifest["files"])  # no Mamba layer: nothing to fuse
    assert manifest["verification"]["passed"] is True
    policy = OnnxPolicy(dp3_model, threads=1, precision="fp32")
    rng = np.random.default_rng(0)
    pc, pos = policy.example_observation(rng, policy.contract.n_points)
    policy.reset()
    for _ in range(3):
        policy.observe(pc, pos)
    chunk = policy.act(seed=0)
    assert chunk.shape == (1, 8, 7) and np.isfinite(chunk).all()
    np.testing.assert_array_equal(chunk, policy.act(seed=0))


def test_dssp_sim_eval_runs_dp3(dp3_model, tmp_path, capsys):
    from dssp_sim.sim_cli import main as sim_main

    out = tmp_path / "eval.json"
    assert (
        sim_main(
            [
                "eval",
                "--model",
                str(dp3_model),
                "--task",
                "tap",
                "--episodes",
                "1",
                "--seed",
                "5",
                "--json",
                str(out),
                "--threads",
                "1",
                "--no-progress",
                "--precision",
                "fp32",
            ]
        )
        == 0
    )
    record = json.loads(out.read_text())
    assert record["n"] == 1 and record["episodes"][0]["steps"] > 0


def test_dssp_run_runs_dp3_on_the_embedded_simulation(dp3_model, tmp_path, capsys):
    from hardware.cli.run import main as run_main

    log_dir = tmp_path / "log"
    code = run_main(
        [
            "--model",
            str(dp3_model),
            "--camera",
            "tabletop",
            "--can",
            "sim",
            "--max-steps",
            "30",
            "--log-dir",
            str(log_dir),
            "--seed",
            "0",
            "--threads",
            "1",
            "--quiet",
        ]
    )
    out = capsys.readouterr().out
    assert code == 0, out
    assert "ticks 30" in out and "ended by: max steps" in out
    summary = json.loads((log_dir / "run.json").read_text())["summary"]
    assert summary["ticks"] == 30 and summary["commands_sent"] > 0
