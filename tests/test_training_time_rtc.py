"""Training-time real-time chunking (``model.committed_prefix_max``): a training chunk's first d actions given clean
and marked, no loss on them; at run time the committed actions are given the same way (not guided), kept exactly,
in PyTorch and in the exported graphs (standard and fused) alike."""

import numpy as np
import pytest
import torch
from conftest import SET_SMALL

from dssp_core.errors import ConfigError
from dssp_train.config import apply_overrides, load_preset
from dssp_train.model.policy import DSSPPolicy

TRAINED_RTC = ["model.committed_prefix_max=2", "model.state_dim=2", "model.action_dim=2"]


def policy_with(overrides=TRAINED_RTC) -> DSSPPolicy:
    torch.manual_seed(0)
    policy = DSSPPolicy(apply_overrides(load_preset("tiny"), overrides).model)
    with torch.no_grad():  # an untrained model's mark and gates are zero (AdaLN-zero): tokens would not interact
        policy.denoiser.committed_embed.normal_(std=0.5)
        for layer in policy.denoiser.layers:
            layer.modulation[-1].weight.normal_(std=0.1)
    return policy.eval()


def test_the_committed_actions_are_given_clean_and_marked_and_carry_no_loss(monkeypatch):
    policy = policy_with()
    seen = {}

    class OffByOne(torch.nn.Module):  # every token off by one, before the loss's mask
        def forward(self, prefix, x_in, timesteps, committed=None):
            seen.update(x_in=x_in, committed=committed)
            return x_in + 1.0

    monkeypatch.setattr(policy, "denoiser", OffByOne())
    x0 = torch.rand(64, policy.cfg.horizon, 2) * 2 - 1
    loss = policy.diffusion_loss(torch.zeros(64, 3, policy.cfg.d_model), x0, torch.Generator().manual_seed(1))
    committed = seen["committed"]
    counts = committed.sum(1)
    assert set(counts.tolist()) == {0, 1, 2}  # d ~ U{0, 1, 2}
    assert torch.equal(committed, torch.arange(policy.cfg.horizon) < counts[:, None])  # the chunk's first d
    assert torch.equal(seen["x_in"][committed], x0[committed])  # given clean
    free = ~committed
    want = ((seen["x_in"] + 1.0 - x0)[free] ** 2).mean()  # the committed tokens, off by one too, do not count
    assert loss.item() == pytest.approx(want.item(), rel=1e-6)


def test_the_chain_keeps_the_committed_actions_and_ignores_partial_weights():
    policy = policy_with()
    h = policy.cfg.horizon
    prefix, noise = torch.randn(1, 3, policy.cfg.d_model), torch.randn(1, h, 2)
    target = torch.rand(1, h, 2) * 2 - 1
    weights = {w: torch.tensor([*w] + [0.0] * (h - len(w)))[None, :, None] for w in ((1.0, 1.0), (1.0, 1.0, 0.5))}
    with torch.no_grad():
        chunks = {w: policy.sample_normalized(prefix, noise, inpaint=(target, weight)) for w, weight in weights.items()}
        plain = policy.sample_normalized(prefix, noise)
    first = chunks[(1.0, 1.0)]
    torch.testing.assert_close(first[:, :2], target[:, :2], atol=1e-6, rtol=0)  # kept exactly
    torch.testing.assert_close(chunks[(1.0, 1.0, 0.5)], first)  # guidance's partial weight: not this model's
    assert (first[:, 2:] - plain[:, 2:]).abs().max() > 1e-3  # the committed actions condition the rest


@pytest.mark.parametrize(
    "preset, overrides, words",
    [
        ("tiny", ["model.committed_prefix_max=4"], "at most horizon - 1 = 3"),
        ("tiny", ["model.action_alignment=dp3", "model.committed_prefix_max=1"], "current action alignment"),
        ("dp3_sim", ["model.committed_prefix_max=1"], "Mamba or Transformer denoiser"),
    ],
)
def test_what_training_time_rtc_cannot_be_is_refused_in_one_line(preset, overrides, words):
    with pytest.raises(ConfigError, match=words) as err:
        apply_overrides(load_preset(preset), overrides)
    assert "\n" not in str(err.value)


def test_the_exported_graphs_give_the_committed_actions_as_pytorch_does(data, tmp_path):
    from dssp_deploy.onnx_policy import OnnxPolicy
    from dssp_train.cli.train import main as train_main
    from export.to_onnx import load_source
    from export.to_onnx import main as export_main

    run, model = tmp_path / "run", tmp_path / "model"
    sets = [a for o in ("model.committed_prefix_max=2",) for a in ("--set", o)]
    assert train_main(["--data", str(data), "--out", str(run), "--steps", "2", "--no-progress", *SET_SMALL, *sets]) == 0
    assert export_main([str(run), "-o", str(model), "--inpainting", "--quantize", "none"]) == 0  # parity verified
    policy, _, _ = load_source(run, True)
    norm = policy.normalizers["action"]
    torch.set_num_threads(1)
    kernels = ["standard", "fused"] if (model / "denoiser.fused.onnx").is_file() else ["standard"]
    for kernel in kernels:
        graph = OnnxPolicy(model, threads=1, precision="fp32", kernel=kernel)
        rng = np.random.default_rng(0)
        pc, pos = graph.example_observation(rng)
        graph.observe(pc, pos)
        h, a = graph.contract.horizon, graph.contract.action_dim
        committed = rng.uniform(-0.5, 0.5, (1, h, a)).astype(np.float32)
        weight = np.array([1.0, 1.0] + [0.5] * (h - 2), dtype=np.float32)[None, :, None]
        feeds, noise = graph.denoiser_inputs(committed, weight), graph.noise(1, seed=3)
        chunk = graph.denoise(feeds, noise=noise)
        with torch.no_grad():
            prefix = policy.build_prefix(torch.from_numpy(feeds["c_t"]), torch.from_numpy(feeds["z_recent"]))
            inpaint = (norm.normalize(torch.from_numpy(committed)), torch.from_numpy(weight))
            want = policy.sample_normalized(
                prefix, torch.from_numpy(noise), graph.contract.denoise_steps, inpaint=inpaint
            )
        np.testing.assert_allclose(chunk, norm.unnormalize(want).numpy(), atol=1e-5, err_msg=kernel)
        np.testing.assert_allclose(chunk[0, :2], committed[0, :2], atol=1e-5)  # the committed actions, exactly
