"""The Transformer denoiser (``model.denoiser_backbone = "transformer"``, paper Table 5 "w/ Trans."): the attention
mixer, the prefix key/value cache against the whole-sequence path, training, parameter counts, export and the
torch-free runtime."""

import json
import math

import numpy as np
import pytest
import torch
from conftest import SET_SMALL

from dssp_train.cli.train import main as train_main
from dssp_train.config import apply_overrides, load_preset
from dssp_train.data.synthetic import write_tap_count_dataset
from dssp_train.model.attention import CausalSelfAttention
from dssp_train.model.param_count import parameter_breakdown
from dssp_train.model.policy import DSSPPolicy
from dssp_train.model.streaming import StreamingPolicy
from dssp_train.training.checkpoint import load_policy

pytestmark = pytest.mark.filterwarnings("ignore:`torch.jit.load` is deprecated:DeprecationWarning")

TRANSFORMER = [
    "model.d_model=32",
    "model.d_state=8",
    "model.n_denoiser_layers=2",
    "model.denoiser_backbone=transformer",
    "model.transformer_heads=4",
]


def build(*overrides: str, seed: int = 0) -> DSSPPolicy:
    """A small Transformer-denoiser policy (S = 3, A = 2), its denoiser weights perturbed so AdaLN matters."""
    config = apply_overrides(load_preset("tiny"), [*TRANSFORMER, *overrides])
    config.model.state_dim, config.model.action_dim = 3, 2
    torch.manual_seed(seed)
    policy = DSSPPolicy(config.model)
    with torch.no_grad():
        for p in policy.denoiser.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return policy.eval()


# ------------------------------------------------------------------ the mixer
def test_attention_continues_from_its_cache_and_is_causal():
    torch.manual_seed(0)
    attn = CausalSelfAttention(24, 3).eval()  # d_head 8
    x = torch.randn(2, 9, 24)
    whole, (k, v) = attn(x)
    assert whole.shape == (2, 9, 24) and k.shape == v.shape == (2, 3, 9, 8)
    first, cache = attn(x[:, :4])
    second, cache = attn(x[:, 4:7], cache)
    third, cache = attn.forward_unrolled(x[:, 7:], cache)
    torch.testing.assert_close(torch.cat([first, second, third], 1), whole, atol=1e-6, rtol=0)
    torch.testing.assert_close(cache[0], k, atol=1e-6, rtol=0)
    from_empty, _ = attn(x, attn.init_state(2))
    torch.testing.assert_close(from_empty, whole, atol=1e-6, rtol=0)
    changed = x.clone()
    changed[:, 5:] += 1.0
    torch.testing.assert_close(attn(changed)[0][:, :5], whole[:, :5], atol=1e-6, rtol=0)  # no token sees a later one


def test_rotary_scores_depend_on_relative_position_only():
    torch.manual_seed(0)
    attn = CausalSelfAttention(18, 2)  # odd d_head 9: 8 channels rotate, the last passes unchanged
    q, k = torch.randn(1, 2, 1, 9), torch.randn(1, 2, 1, 9)

    def score(i, j):
        cos_i, sin_i = attn._rotary(i, 1, q)
        cos_j, sin_j = attn._rotary(j, 1, k)
        return (attn._rotate(q, cos_i, sin_i) * attn._rotate(k, cos_j, sin_j)).sum(-1)

    torch.testing.assert_close(score(7, 3), score(14, 10), atol=1e-5, rtol=0)
    assert not torch.allclose(score(7, 3), score(7, 4))
    cos, sin = attn._rotary(5, 1, q)
    assert torch.equal(attn._rotate(q, cos, sin)[..., 8], q[..., 8])


# ------------------------------------------------------- denoiser: cached path
@pytest.mark.parametrize("mlp", ["none", "gated", "dit"])
def test_prefix_cache_equals_the_whole_sequence(mlp):
    policy = build(f"model.denoiser_mlp={mlp}")
    den, cfg = policy.denoiser, policy.cfg
    assert all(isinstance(layer.mixer, CausalSelfAttention) for layer in den.layers)
    gen = torch.Generator().manual_seed(1)
    prefix = torch.randn(3, cfg.prefix_length, cfg.d_model, generator=gen)
    x_tau = torch.randn(3, cfg.horizon, cfg.action_dim, generator=gen)
    timesteps = torch.tensor([0, 37, 99])
    with torch.no_grad():
        whole = den(prefix, x_tau, timesteps)
        states = den.encode_prefix(prefix)
        cached = den.denoise(states, x_tau, timesteps)
        unrolled = den.denoise_modulated(den.encode_prefix(prefix, True), x_tau, den.modulation(timesteps), True)
        joint, joint_states = den.joint_step(
            prefix, x_tau, den.modulation(timesteps)
        )  # the prefix's cache from one pass
    torch.testing.assert_close(joint, whole, atol=1e-5, rtol=0)
    for got, want in zip(joint_states, states):
        torch.testing.assert_close(got, want, atol=1e-5, rtol=0)
    assert [tuple(k.shape) for k, _ in states] == [(3, 4, cfg.prefix_length, 8)] * cfg.n_denoiser_layers
    torch.testing.assert_close(cached, whole, atol=1e-5, rtol=0)
    torch.testing.assert_close(unrolled, whole, atol=1e-5, rtol=0)
    assert whole.abs().max() > 0.1  # a real output, not zeros that trivially agree


def test_without_timestep_decoupling_the_whole_path_samples():
    policy = build("model.timestep_decoupled=false")
    cfg = policy.cfg
    prefix = torch.randn(2, cfg.prefix_length, cfg.d_model)
    with pytest.raises(RuntimeError, match="timestep_decoupled"):
        policy.denoiser.encode_prefix(prefix)
    chunk = policy.sample_normalized(prefix, torch.randn(2, cfg.horizon, cfg.action_dim))
    assert chunk.shape == (2, cfg.horizon, cfg.action_dim) and torch.isfinite(chunk).all()


# --------------------------------------------------------- weights and counts
def test_state_dict_init_and_parameter_count():
    policy = build("model.denoiser_mlp=gated")
    keys = [k for k in policy.state_dict() if k.startswith("denoiser.layers.0.mixer.")]
    assert sorted(keys) == ["denoiser.layers.0.mixer.in_proj.weight", "denoiser.layers.0.mixer.out_proj.weight"]
    torch.manual_seed(0)
    fresh = DSSPPolicy(policy.cfg).denoiser
    bound = 1 / math.sqrt(32) / math.sqrt(2 * 2)  # Kaiming-uniform over sqrt(2 residual branches x 2 layers)
    out = fresh.layers[0].mixer.out_proj.weight
    assert 0.9 * bound < out.abs().max() <= bound
    rows = dict(parameter_breakdown(policy))
    mlp = 32 * 256 + 128 * 32  # GatedMLP, hidden 128: fc1 32 -> 2 x 128, fc2 128 -> 32
    assert rows["f_theta blocks (mixer + MLP)"] == 2 * (4 * 32 * 32 + 2 * 32 + mlp)


# ------------------------------------------------------------------- training
@pytest.fixture(scope="module")
def trained_run(tmp_path_factory):
    """A Transformer-denoiser run trained for 3 steps on the tap-count task: (run_dir, stdout summary)."""
    root = tmp_path_factory.mktemp("attention")
    data = write_tap_count_dataset(root / "tap.zarr", 4, seed=0, n_points=24)
    run = root / "run"
    args = [
        "--data",
        str(data),
        "--out",
        str(run),
        "--preset",
        "tiny",
        "--steps",
        "3",
        "--no-progress",
        *SET_SMALL,
        "--set",
        "model.transformer_heads=4",
        "--denoiser-backbone",
        "transformer",
    ]
    assert train_main(args) == 0
    return run


def test_trains_with_a_finite_loss(trained_run):
    config = json.loads((trained_run / "config.json").read_text())
    assert config["model"]["denoiser_backbone"] == "transformer"
    train = [json.loads(line) for line in (trained_run / "log.jsonl").read_text().splitlines()]
    losses = [r["loss"] for r in train if r["kind"] == "train"]
    assert len(losses) == 3 and all(math.isfinite(x) and x > 0 for x in losses)
    policy, _ = load_policy(trained_run)
    assert isinstance(policy.denoiser.layers[0].mixer, CausalSelfAttention)
    gen = torch.Generator().manual_seed(0)
    traj = torch.rand(12, 24, 3, generator=gen), torch.rand(12, 2, generator=gen), torch.rand(12, 2, generator=gen)
    policy.train()
    loss = policy.compute_loss(*traj, torch.tensor([0, 5, 11]), generator=gen)["loss"]
    loss.backward()
    assert math.isfinite(loss.item())
    assert policy.denoiser.layers[0].mixer.in_proj.weight.grad.abs().sum() > 0


# --------------------------------------------------------------------- export
def test_export_verifies_and_the_runtime_matches_pytorch(trained_run, tmp_path, capsys):
    from dssp_deploy import OnnxPolicy
    from export.to_onnx import main as export_main

    model = tmp_path / "model"
    assert (
        export_main(
            [str(trained_run), "-o", str(model), "--quantize", "none", "--verify-steps", "60", "--threads", "1"]
        )
        == 0
    )
    assert "PASS" in capsys.readouterr().out
    manifest = json.loads((model / "dssp_model.json").read_text())
    report = manifest["verification"]
    assert report["passed"] and report["steps"] == 60
    for figures in report["errors"].values():
        assert all(value <= 1e-4 for value in figures.values() if value is not None), figures

    policy, config = load_policy(trained_run)
    stream = StreamingPolicy(policy)
    rng = np.random.default_rng(0)
    kernels = ["standard", "fused"] if "onnx_fused" in manifest["graphs"]["denoiser"]["files"] else ["standard"]
    runtimes = [OnnxPolicy(model, threads=1, precision="fp32", kernel=k, warmup=0) for k in kernels]
    worst = 0.0
    for t in range(7):
        pc, pos = runtimes[0].example_observation(rng, 24)  # inside the trained ranges (others are refused)
        stream.observe(pc, pos)
        for runtime in runtimes:
            runtime.observe(pc, pos)
        if t % config.model.n_action_steps == 0:
            noise = rng.standard_normal((1, config.model.horizon, config.model.action_dim)).astype(np.float32)
            expected = stream.act(noise=noise)
            for runtime in runtimes:
                worst = max(worst, float(np.abs(runtime.act(noise=noise) - expected).max()))
    assert worst <= 1e-4, worst
