"""The DSSP model: causality, streaming == training path, prefix caching, ablation switches."""

import numpy as np
import pytest
import torch

from dssp_train.config import apply_overrides, load_preset
from dssp_train.model.policy import DSSPPolicy
from dssp_train.model.streaming import StreamingPolicy

T, P, S, A = 30, 32, 3, 2


def make_policy(*overrides: str, seed: int = 0) -> DSSPPolicy:
    cfg = apply_overrides(
        load_preset("tiny"),
        ["model.d_model=32", "model.d_state=8", "model.n_denoiser_layers=2", "model.transformer_heads=4", *overrides],
    ).model
    cfg.state_dim, cfg.action_dim = S, A
    torch.manual_seed(seed)
    policy = DSSPPolicy(cfg)
    pc, pos, act = trajectory()
    policy.fit_normalizers(pc.numpy(), pos.numpy(), act.numpy())
    return policy.eval()


def trajectory(seed: int = 0, length: int = T):
    g = torch.Generator().manual_seed(seed)
    return (
        torch.randn(length, P, 3, generator=g),
        torch.randn(length, S, generator=g),
        torch.randn(length, A, generator=g),
    )


HISTORY_VARIANTS = [
    [],
    ["model.history_window=5"],
    ['model.history_backbone="transformer"'],
    ['model.history_backbone="transformer"', "model.history_window=4"],
]


@pytest.mark.parametrize(
    "overrides", HISTORY_VARIANTS, ids=["mamba", "mamba-window", "transformer", "transformer-window"]
)
def test_streaming_context_equals_training_path(overrides):
    policy = make_policy(*overrides)
    pc, pos, _ = trajectory()
    with torch.no_grad():
        c_seq = policy.history_encoder(policy.encode_observations(pc[None], pos[None]))[0]
    stream = StreamingPolicy(policy)
    c_stream = torch.cat([stream.observe(pc[t], pos[t]) for t in range(T)])
    assert (c_stream - c_seq).abs().max().item() <= 1e-5


@pytest.mark.parametrize(
    "overrides", HISTORY_VARIANTS, ids=["mamba", "mamba-window", "transformer", "transformer-window"]
)
def test_context_is_causal(overrides):
    policy = make_policy(*overrides)
    pc, pos, _ = trajectory()
    pc2, pos2 = pc.clone(), pos.clone()
    pc2[20:] += 5.0
    pos2[20:] -= 3.0
    with torch.no_grad():
        c1 = policy.history_encoder(policy.encode_observations(pc[None], pos[None]))[0]
        c2 = policy.history_encoder(policy.encode_observations(pc2[None], pos2[None]))[0]
    assert torch.allclose(c1[:20], c2[:20], atol=1e-6)
    assert not torch.allclose(c1[20:], c2[20:], atol=1e-3)


def test_windowed_history_forgets_what_left_the_window():
    policy = make_policy("model.history_window=5")
    pc, pos, _ = trajectory()
    pc2 = pc.clone()
    pc2[:10] += 5.0
    with torch.no_grad():
        c1 = policy.history_encoder(policy.encode_observations(pc[None], pos[None]))[0]
        c2 = policy.history_encoder(policy.encode_observations(pc2[None], pos[None]))[0]
    assert torch.allclose(c1[14:], c2[14:], atol=1e-6)  # steps >= 10 + 5 - 1 see none of the change
    assert not torch.allclose(c1[13], c2[13], atol=1e-4)


def test_full_history_remembers_the_start():
    policy = make_policy()
    pc, pos, _ = trajectory()
    pc2 = pc.clone()
    pc2[:3] += 5.0
    with torch.no_grad():
        c1 = policy.history_encoder(policy.encode_observations(pc[None], pos[None]))[0]
        c2 = policy.history_encoder(policy.encode_observations(pc2[None], pos[None]))[0]
    assert (c1[-1] - c2[-1]).abs().max() > 1e-6  # identical inputs after step 3: only memory differs


def test_streamed_chunks_equal_training_path_chunks():
    policy = make_policy()
    pc, pos, _ = trajectory()
    stream = StreamingPolicy(policy)
    noise = torch.randn(1, policy.cfg.horizon, A, generator=torch.Generator().manual_seed(5))
    for t in range(T):
        stream.observe(pc[t], pos[t])
        if t in (0, 1, 7, T - 1):
            chunk = stream.act(noise=noise)
            ref = policy.sample_trajectory_windows(pc, pos, torch.tensor([t]), noise).numpy()
            assert chunk.shape == (1, policy.cfg.horizon, A)
            assert np.abs(chunk - ref).max() <= 1e-5


def test_act_is_seeded_and_batched():
    policy = make_policy()
    pc, pos, _ = trajectory()
    stream = StreamingPolicy(policy)
    stream.observe(pc[:2].reshape(2, P, 3), pos[:2])
    a1, a2 = stream.act(seed=3), stream.act(seed=3)
    assert a1.shape == (2, policy.cfg.horizon, A) and np.array_equal(a1, a2)
    assert not np.array_equal(a1, stream.act(seed=4))
    with pytest.raises(ValueError, match="noise must have shape"):
        stream.act(noise=np.zeros((1, policy.cfg.horizon, A), np.float32))
    stream.reset()
    with pytest.raises(RuntimeError, match="observe"):
        stream.act(seed=0)


def test_prefix_caching_equals_full_denoiser():
    policy = make_policy()
    prefix = torch.randn(4, policy.cfg.prefix_length, 32)
    x = torch.randn(4, policy.cfg.horizon, A)
    t = torch.tensor([0, 10, 50, 99])
    with torch.no_grad():
        # Make the AdaLN projections non-zero so the test sees the modulation.
        for p in policy.denoiser.parameters():
            p.add_(0.01 * torch.randn_like(p))
        full = policy.denoiser(prefix, x, t)
        cached = policy.denoiser.denoise(policy.denoiser.encode_prefix(prefix), x, t)
    assert (full - cached).abs().max().item() <= 1e-5


def test_sampling_runs_the_prefix_in_the_first_steps_pass():
    """K = 1 runs [prefix, x] in one pass (each weight read once per chunk); with K >= 2 that first pass also gives the
    prefix's states the later steps start from (K reads a chunk, not K + 1): the same chunk as the prefix's own pass
    and then the K steps, on the parallel and the unrolled path."""
    policy = make_policy('model.diffusion.timestep_spacing="trailing"')
    den, schedule = policy.denoiser, policy.schedule
    prefix, noise = torch.randn(3, policy.cfg.prefix_length, 32), torch.randn(3, policy.cfg.horizon, A)
    calls, encode = [], den.encode_prefix
    den.encode_prefix = lambda *args, **kwargs: calls.append(1) or encode(*args, **kwargs)
    with torch.no_grad():
        for p in den.parameters():
            p.add_(0.01 * torch.randn_like(p))
        one = policy.sample_normalized(prefix, noise, 1)
        cached = den.denoise_modulated(encode(prefix), noise, den.modulation(torch.tensor([99])).at(0))
        assert (one - schedule.ddim_step(cached, 99, noise, 1)).abs().max().item() <= 1e-5
        for unrolled in (False, True):
            timesteps = schedule.inference_timesteps(3)
            table = den.modulation(torch.tensor(timesteps))
            states, x = encode(prefix, unrolled), noise
            for k, t in enumerate(timesteps):  # the prefix's own pass, then the K steps
                x = schedule.ddim_step(den.denoise_modulated(states, x, table.at(k), unrolled), t, x, 3)
            chunk = policy.sample_normalized(prefix, noise, 3, table, unrolled=unrolled)
            assert (chunk - x).abs().max().item() <= 1e-5 and x.abs().max() > 0.1
            _, joint = den.joint_step(prefix, noise, table.at(0), unrolled=unrolled)
            for got, want in zip(joint, states):
                assert all((g - w).abs().max().item() <= 1e-5 for g, w in zip(got, want))
    assert calls == []  # sampling never ran the prefix apart


@pytest.mark.parametrize("decoupled", [True, False], ids=["cached", "full"])
def test_modulation_table_and_unrolled_path_equal_the_plain_denoiser(decoupled):
    """One table row per DDIM timestep, shared by the batch, and the unrolled Mamba path: the same x0_hat."""
    policy = make_policy(f"model.timestep_decoupled={str(decoupled).lower()}")
    den = policy.denoiser
    prefix = torch.randn(3, policy.cfg.prefix_length, 32)
    x = torch.randn(3, policy.cfg.horizon, A)
    timesteps = policy.schedule.inference_timesteps(4)
    with torch.no_grad():
        for p in den.parameters():
            p.add_(0.02 * torch.randn_like(p))
        table = den.modulation(torch.tensor(timesteps))
        assert table.layers.shape == (4, 2, 3, 32) and table.final.shape == (4, 2, 32)
        states = {u: den.encode_prefix(prefix, unrolled=u) for u in (False, True)} if decoupled else None
        for k, t in enumerate(timesteps):
            plain = den(prefix, x, torch.full((3,), t))
            for unrolled in (False, True):
                if decoupled:
                    got = den.denoise_modulated(states[unrolled], x, table.at(k), unrolled)
                else:
                    got = den.forward_modulated(prefix, x, table.at(k), unrolled)
                assert (got - plain).abs().max().item() <= 1e-5, (t, unrolled)
        sampled = policy.sample_normalized(prefix, x, 4)
        assert (policy.sample_normalized(prefix, x, 4, unrolled=True) - sampled).abs().max().item() <= 1e-5
        assert (policy.sample_normalized(prefix, x, 4, table=table) - sampled).abs().max().item() == 0


def test_timestep_reaches_only_the_action_tokens():
    torch.manual_seed(0)
    policy = make_policy()
    with torch.no_grad():
        for p in policy.denoiser.parameters():
            p.add_(0.05 * torch.randn_like(p))
    prefix = torch.randn(2, policy.cfg.prefix_length, 32)
    s1 = policy.denoiser.encode_prefix(prefix)
    # The prefix states are computed without any timestep, and outputs still depend on the timestep.
    x = torch.randn(2, policy.cfg.horizon, A)
    with torch.no_grad():
        o1 = policy.denoiser.denoise(s1, x, torch.tensor([5, 5]))
        o2 = policy.denoiser.denoise(s1, x, torch.tensor([80, 80]))
    assert not torch.allclose(o1, o2, atol=1e-4)
    coupled = make_policy("model.timestep_decoupled=false")
    with pytest.raises(RuntimeError, match="timestep_decoupled"):
        coupled.denoiser.encode_prefix(prefix)


def test_training_windows_see_only_their_past():
    policy = make_policy()
    obs_idx, act_idx = policy.trajectory_windows(T, torch.tensor([0, 1, 10, T - 1]))
    n, h = policy.cfg.n_obs_steps, policy.cfg.horizon
    assert obs_idx.tolist()[0] == [0] * n  # start padded by repeating the first observation
    assert obs_idx.tolist()[2] == list(range(10 - n + 1, 11))
    assert act_idx.tolist()[2] == list(range(10, 10 + h))
    assert act_idx.tolist()[3] == [T - 1] * h  # end padded by repeating the last action
    assert (obs_idx <= torch.tensor([0, 1, 10, T - 1]).unsqueeze(1)).all()


@pytest.mark.parametrize(
    "overrides,prefix_len,has_history,has_dynamics",
    [
        ([], 3, True, True),
        (["model.use_history=false"], 2, False, False),
        (["model.use_recent_states=false"], 1, True, True),
        (["model.dynamics_weight=0"], 3, True, False),
        (["model.timestep_decoupled=false"], 3, True, True),
    ],
    ids=["full", "no-history", "no-recent", "no-dynamics", "no-decoupling"],
)
def test_ablation_switches(overrides, prefix_len, has_history, has_dynamics):
    policy = make_policy(*overrides)
    assert policy.cfg.prefix_length == prefix_len
    assert (policy.history_encoder is not None) == has_history
    assert (policy.dynamics is not None) == has_dynamics
    pc, pos, act = trajectory()
    policy.train()
    losses = policy.compute_loss(pc, pos, act, torch.tensor([0, 5, 20]), torch.Generator().manual_seed(0))
    assert torch.isfinite(losses["loss"])
    assert (losses["dynamics"].item() > 0) == has_dynamics
    losses["loss"].backward()
    grads = [p.grad for p in policy.parameters() if p.requires_grad]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    stream = StreamingPolicy(policy)
    stream.observe(pc[0], pos[0])
    assert np.isfinite(stream.act(seed=0)).all()


def test_normaliser_maps_training_range_to_unit_interval_and_back():
    policy = make_policy()
    _, _, act = trajectory()
    norm = policy.normalizers["action"]
    y = norm.normalize(act)
    assert y.min().item() == pytest.approx(-1, abs=1e-5) and y.max().item() == pytest.approx(1, abs=1e-5)
    assert torch.allclose(norm.unnormalize(y), act, atol=1e-5)
    flat = policy.normalizers["agent_pos"].fit(np.ones((10, S)))
    assert torch.equal(flat.normalize(torch.ones(1, S)), torch.zeros(1, S))


def test_extra_colour_channels_are_dropped_for_an_xyz_model():
    policy = make_policy()
    pc, pos, _ = trajectory()
    rgb = torch.cat([pc, torch.rand(T, P, 3)], dim=-1)
    with torch.no_grad():
        assert torch.equal(policy.encode_observations(rgb, pos), policy.encode_observations(pc, pos))


def test_colour_model_uses_dp3_wider_point_mlp():
    policy = make_policy("model.point_dim=6")
    widths = [m.out_features for m in policy.obs_encoder.point_encoder.mlp if isinstance(m, torch.nn.Linear)]
    assert widths[-1] == 512
