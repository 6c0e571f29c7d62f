"""Our DDPM noising and DDIM sampling against diffusers' schedulers as the oracle.

DP3's settings: 100 training timesteps, squaredcos_cap_v2 betas, clip_sample, set_alpha_to_one,
steps_offset 0, x0 ("sample") prediction, 10 DDIM steps. The epsilon-prediction variant, other beta
schedules and other step counts are checked too.
"""

import dataclasses

import numpy as np
import pytest
import torch
from diffusers import DDIMScheduler, DDPMScheduler

from dssp_train.config import DiffusionConfig, apply_overrides, load_preset
from dssp_train.model.policy import DSSPPolicy
from dssp_train.model.scheduler import DiffusionSchedule

DP3 = dict(
    num_train_timesteps=100,
    beta_start=1e-4,
    beta_end=0.02,
    beta_schedule="squaredcos_cap_v2",
    clip_sample=True,
    set_alpha_to_one=True,
    steps_offset=0,
    prediction_type="sample",
)
TOL = 1e-5
MODEL_RTOL = 2e-4
"""One float32 forward pass of the perturbed tiny policy, computed two ways (the sampler's cached AdaLN row and
prefix states against the whole timestep and prefix), agrees to ~3e-5 of its output's scale when the two use
different reduction orders (two torch threads; identical with one): this bound leaves a margin of ~7x, and the
neighbouring timestep's output lies >100x outside it."""


def ours(**changes) -> DiffusionSchedule:
    return DiffusionSchedule(DiffusionConfig(**{**DP3, "num_inference_steps": 10, **changes}))


def ddim(**changes) -> DDIMScheduler:
    return DDIMScheduler(**{**DP3, **changes})


def ddpm(**changes) -> DDPMScheduler:
    settings = {k: v for k, v in {**DP3, **changes}.items() if k not in ("set_alpha_to_one", "steps_offset")}
    return DDPMScheduler(**settings)


def run_diffusers(scheduler: DDIMScheduler, model, noise: torch.Tensor, num_steps: int) -> torch.Tensor:
    scheduler.set_timesteps(num_steps)
    x = noise
    for t in scheduler.timesteps:
        x = scheduler.step(model(x, int(t)), t, x).prev_sample
    return x


def run_ours(schedule: DiffusionSchedule, model, noise: torch.Tensor, num_steps: int) -> torch.Tensor:
    x = noise
    for t in schedule.inference_timesteps(num_steps):
        x = schedule.ddim_step(model(x, t), t, x, num_steps)
    return x


def toy_model(x: torch.Tensor, t: int) -> torch.Tensor:
    """A fixed, deterministic, timestep-dependent stand-in for the denoiser; exceeds [-1, 1] so clipping matters."""
    return 1.6 * torch.tanh(1.3 * x + 0.05 * t - 2.0) + 0.1 * torch.sin(x * (t + 1) / 17.0)


# --------------------------------------------------------------------- schedule
@pytest.mark.parametrize("beta_schedule", ["squaredcos_cap_v2", "linear", "scaled_linear"])
def test_betas_and_alphas_cumprod_equal_diffusers(beta_schedule):
    mine, theirs = ours(beta_schedule=beta_schedule), ddim(beta_schedule=beta_schedule)
    assert mine.betas.dtype == theirs.betas.dtype == torch.float32
    assert torch.equal(mine.betas, theirs.betas)
    assert torch.equal(mine.alphas_cumprod, theirs.alphas_cumprod)
    assert torch.equal(mine.final_alpha_cumprod, theirs.final_alpha_cumprod)
    assert torch.equal(mine.alphas_cumprod, ddpm(beta_schedule=beta_schedule).alphas_cumprod)


def test_final_alpha_cumprod_without_set_alpha_to_one():
    mine, theirs = ours(set_alpha_to_one=False), ddim(set_alpha_to_one=False)
    assert float(mine.final_alpha_cumprod) == float(theirs.final_alpha_cumprod) < 1.0


def test_timesteps_are_dp3s_leading_spacing():
    schedule = ours()
    assert schedule.inference_timesteps() == [90, 80, 70, 60, 50, 40, 30, 20, 10, 0]
    scheduler = ddim()
    scheduler.set_timesteps(10)
    assert schedule.inference_timesteps(10) == scheduler.timesteps.tolist()


@pytest.mark.parametrize("num_steps,steps_offset", [(1, 0), (3, 0), (7, 0), (10, 1), (16, 0), (100, 0)])
def test_timesteps_equal_diffusers_for_other_step_counts(num_steps, steps_offset):
    scheduler = ddim(steps_offset=steps_offset)
    scheduler.set_timesteps(num_steps)
    assert ours(steps_offset=steps_offset).inference_timesteps(num_steps) == scheduler.timesteps.tolist()


@pytest.mark.parametrize("num_steps", [1, 2, 3, 7, 10])
def test_trailing_timesteps_equal_diffusers_and_start_at_the_noise_level(num_steps):
    scheduler = ddim(timestep_spacing="trailing")
    scheduler.set_timesteps(num_steps)
    mine = ours(timestep_spacing="trailing").inference_timesteps(num_steps)
    assert mine == scheduler.timesteps.tolist() and mine[0] == 99
    assert ours().inference_timesteps(1) == [0]  # leading spacing: one step would start where no noise is


@pytest.mark.parametrize("beta_schedule", ["squaredcos_cap_v2", "linear"])
def test_add_noise_equals_ddpm_add_noise(beta_schedule):
    gen = torch.Generator().manual_seed(0)
    x0 = torch.rand((200, 4, 3), generator=gen) * 2 - 1
    noise = torch.randn((200, 4, 3), generator=gen)
    timesteps = torch.cat([torch.arange(100), torch.randint(0, 100, (100,), generator=gen)])
    mine = ours(beta_schedule=beta_schedule).add_noise(x0, noise, timesteps)
    theirs = ddpm(beta_schedule=beta_schedule).add_noise(x0, noise, timesteps)
    assert mine.shape == theirs.shape == x0.shape
    assert (mine - theirs).abs().max().item() <= 1e-6
    # Not the identity: at t = 99 the sample is mostly noise.
    assert (mine[99] - x0[99]).abs().max().item() > 0.5


# ------------------------------------------------------------ DDIM with a toy model
@pytest.mark.parametrize("prediction_type", ["sample", "epsilon"])
@pytest.mark.parametrize(
    "changes,num_steps",
    [
        ({}, 10),
        ({"beta_schedule": "linear"}, 10),
        ({"set_alpha_to_one": False}, 10),
        ({"clip_sample": False}, 10),
        ({"steps_offset": 1}, 10),
        ({}, 7),
        ({}, 1),
        ({"timestep_spacing": "trailing"}, 1),
        ({"timestep_spacing": "trailing"}, 2),
        ({"timestep_spacing": "trailing"}, 10),
    ],
)
def test_ddim_loop_with_toy_model_matches_diffusers(prediction_type, changes, num_steps):
    changes = {**changes, "prediction_type": prediction_type}
    noise = torch.randn((5, 4, 3), generator=torch.Generator().manual_seed(1))
    mine = run_ours(ours(**changes), toy_model, noise, num_steps)
    theirs = run_diffusers(ddim(**changes), toy_model, noise, num_steps)
    assert torch.isfinite(mine).all()
    assert (mine - theirs).abs().max().item() <= TOL
    assert (mine - noise).abs().max().item() > 0.1


def test_single_ddim_step_matches_diffusers_at_every_timestep():
    gen = torch.Generator().manual_seed(2)
    for prediction_type in ("sample", "epsilon"):
        schedule, scheduler = ours(prediction_type=prediction_type), ddim(prediction_type=prediction_type)
        scheduler.set_timesteps(10)
        for t in scheduler.timesteps.tolist():
            sample = torch.randn((3, 4, 2), generator=gen)
            output = 2 * torch.randn((3, 4, 2), generator=gen)  # partly outside [-1, 1]: clipping is exercised
            mine = schedule.ddim_step(output, t, sample)
            theirs = scheduler.step(output, t, sample).prev_sample
            assert (mine - theirs).abs().max().item() <= TOL, (prediction_type, t)


def test_clipping_is_what_diffusers_does():
    """Sanity check that the comparison can fail: without clipping the result differs from diffusers'."""
    noise = torch.randn((5, 4, 3), generator=torch.Generator().manual_seed(1))
    unclipped = run_ours(ours(clip_sample=False), toy_model, noise, 10)
    theirs = run_diffusers(ddim(), toy_model, noise, 10)
    assert (unclipped - theirs).abs().max().item() > 1e-2


# ------------------------------------------------------- DDIM with a DSSP policy
def tiny_policy(prediction_type: str, decoupled: bool = True) -> DSSPPolicy:
    config = apply_overrides(
        load_preset("tiny"),
        [
            "model.d_model=32",
            "model.d_state=8",
            "model.n_denoiser_layers=2",
            "model.n_history_layers=1",
            "model.n_points=24",
            "model.state_dim=2",
            "model.action_dim=3",
            f"model.timestep_decoupled={'true' if decoupled else 'false'}",
            f"model.diffusion.prediction_type={prediction_type}",
        ],
    )
    torch.manual_seed(0)
    policy = DSSPPolicy(config.model)
    rng = np.random.default_rng(0)
    policy.fit_normalizers(
        rng.normal(size=(50, 24, 3)).astype(np.float32),
        rng.normal(size=(50, 2)).astype(np.float32),
        rng.normal(size=(50, 3)).astype(np.float32),
    )
    # The zero-initialised AdaLN projections would make the output independent of the timestep and the
    # prefix; perturb every parameter so that the sampler sees a model that depends on both.
    gen = torch.Generator().manual_seed(3)
    with torch.no_grad():
        for p in policy.parameters():
            p.add_(0.3 * torch.randn(p.shape, generator=gen))
    return policy.eval()


def policy_prefix(policy: DSSPPolicy, batch: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(4)
    m = policy.cfg
    with torch.no_grad():
        z = policy.encode_observations(torch.randn((1, 6, 24, 3), generator=gen), torch.randn((1, 6, 2), generator=gen))
        c = policy.history_encoder(z)
        starts = torch.tensor([5, 3, 0, 1][:batch])
        obs_idx, _ = policy.trajectory_windows(6, starts)
        prefix = policy.build_prefix(c[0, starts], z[0, obs_idx])
    assert prefix.shape == (batch, m.prefix_length, m.d_model)
    return prefix


def record_denoiser_calls(policy: DSSPPolicy, monkeypatch) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Make the policy's denoiser record each call of its sampler: (x_tau in, model output out)."""
    calls = []
    den = policy.denoiser
    # joint_step: the first of K steps, with the prefix in its pass
    for name in ("denoise_modulated", "forward_modulated", "joint_step"):
        original = getattr(den, name)

        def recording(first, x, *rest, _original=original, **kwargs):
            out = _original(first, x, *rest, **kwargs)
            calls.append((x.clone(), (out[0] if isinstance(out, tuple) else out).clone()))
            return out

        monkeypatch.setattr(den, name, recording)
    return calls


@pytest.mark.parametrize(
    "prediction_type,decoupled", [("sample", True), ("epsilon", True), ("sample", False), ("epsilon", False)]
)
@pytest.mark.parametrize("threads", [1, 2])
def test_policy_sampling_matches_diffusers_ddim(prediction_type, decoupled, threads, monkeypatch):
    """The policy's sampler is diffusers' DDIM on the policy's denoiser, compared step by step.

    A 10-step chain of a random tiny model is ill-conditioned: a rounding difference of 1e-7 in one model
    output grows ~100x per late step (the chain itself differs by ~4e-3 between one and two torch threads).
    So each part is compared where it is well-conditioned: (1) the DDIM arithmetic — diffusers' scheduler,
    fed the outputs our sampler's model produced, visits the same x_tau at every step and ends at the same
    sample (TOL); (2) the model — at every step, the policy's denoiser called as diffusers would call it
    (the whole timestep through the AdaLN embedding, one forward pass) on that step's x_tau gives the
    output our sampler used (its cached modulation row, its cached prefix states) to the rounding of one
    float32 forward pass (MODEL_RTOL of the output's scale). Both hold at any thread count.
    """
    policy = tiny_policy(prediction_type, decoupled)
    torch.set_num_threads(threads)
    m = policy.cfg
    assert dataclasses.asdict(m.diffusion) == {
        **DP3,
        "num_inference_steps": 10,
        "prediction_type": prediction_type,
        "timestep_spacing": "leading",
    }
    prefix = policy_prefix(policy, 4)
    noise = torch.randn((4, m.horizon, m.action_dim), generator=torch.Generator().manual_seed(5))

    calls = record_denoiser_calls(policy, monkeypatch)
    mine = policy.sample_normalized(prefix, noise)
    monkeypatch.undo()
    assert len(calls) == 10

    visited = []

    def replay(x, t):  # (1): identical model outputs, so only the schedulers' arithmetic differs
        k = len(visited)
        visited.append(t)
        assert (x - calls[k][0]).abs().max().item() <= TOL * max(1.0, x.abs().max().item()), f"step {k} (t = {t})"
        return calls[k][1]

    theirs = run_diffusers(ddim(prediction_type=prediction_type), replay, noise, 10)
    assert visited == policy.schedule.inference_timesteps()
    assert mine.shape == noise.shape and torch.isfinite(mine).all()
    assert (mine - theirs).abs().max().item() <= TOL

    with torch.no_grad():  # (2): the model our sampler ran is the policy's denoiser, at every step's timestep
        states = policy.denoiser.encode_prefix(prefix) if decoupled else None

        def direct(x, t):
            timesteps = torch.full((x.shape[0],), t, dtype=torch.long)
            return policy.denoiser.denoise(states, x, timesteps) if decoupled else policy.denoiser(prefix, x, timesteps)

        for (x, out), t in zip(calls, visited):
            scale = max(1.0, out.abs().max().item())
            assert (direct(x, t) - out).abs().max().item() <= MODEL_RTOL * scale, f"t = {t}"
            # the comparison can fail: the neighbouring timestep's output is far outside that tolerance
            assert (direct(x, t + 1) - out).abs().max().item() > 100 * MODEL_RTOL * scale, f"t = {t}"

    # The model is not trivial: its output depends on the timestep, and the sample moved away from the noise.
    outputs = [out for _, out in calls]
    assert (outputs[0] - outputs[-1]).abs().max().item() > 1e-3
    assert (mine - noise).abs().max().item() > 0.1
    if prediction_type == "sample":
        assert max(o.abs().max().item() for o in outputs) > 1.0  # clipping is exercised
        assert mine.abs().max().item() <= 1.0 + 1e-6  # the last step returns the clipped x0


def test_policy_sampling_with_fewer_steps_matches_diffusers():
    policy = tiny_policy("sample")
    m = policy.cfg
    prefix = policy_prefix(policy, 2)
    noise = torch.randn((2, m.horizon, m.action_dim), generator=torch.Generator().manual_seed(6))
    timesteps = policy.schedule.inference_timesteps(4)
    table = policy.denoiser.modulation(torch.tensor(timesteps))  # the sampler's own AdaLN rows: only DDIM is compared
    states = []  # the prefix's, from the first step's pass, as the sampler takes them

    def model(x, t):
        k = timesteps.index(t)
        with torch.no_grad():
            if k == 0:
                x0, states[:] = policy.denoiser.joint_step(prefix, x, table.at(0))
                return x0
            return policy.denoiser.denoise_modulated(states, x, table.at(k))

    mine = policy.sample_normalized(prefix, noise, num_steps=4)
    theirs = run_diffusers(ddim(), model, noise, 4)
    assert (mine - theirs).abs().max().item() <= TOL
    assert (mine - policy.sample_normalized(prefix, noise)).abs().max().item() > 1e-4
