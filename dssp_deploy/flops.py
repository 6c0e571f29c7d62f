"""Floating-point operations of one history step and one action chunk, counted from the model config.

Counts multiply-adds of every matrix product as 2 flops (the dominant cost) plus the selective-scan
update (about 7 flops per (channel, state) pair per token); norms and activations are left out, so the
achieved GFLOP/s reported by the profiler is a slight underestimate. ``cfg`` is the ``model`` section of
``dssp_model.json`` (a plain dict), so this needs no torch.
"""

from __future__ import annotations

import math


def _mlp(widths: list[int]) -> int:
    return sum(2 * a * b for a, b in zip(widths[:-1], widths[1:]))


def mamba_token_flops(cfg: dict) -> int:
    """One token through one Mamba layer (recurrent step)."""
    d, n, expand, w = cfg["d_model"], cfg["d_state"], cfg["expand"], cfg["d_conv"]
    e = expand * d
    rank = math.ceil(d / 16)
    return (
        2 * d * 2 * e  # in_proj
        + 2 * e * w  # depthwise conv
        + 2 * e * (rank + 2 * n)  # x_proj
        + 2 * rank * e  # dt_proj
        + 7 * e * n  # exp(dt A), dt B x, decay * h + drive, C . h
        + 2 * e * d  # out_proj
    )


def mlp_token_flops(cfg: dict) -> int:
    """One token through a denoiser block's MLP (``denoiser_mlp``: none, gated = mamba-ssm's GatedMLP, dit)."""
    d, kind = cfg["d_model"], cfg.get("denoiser_mlp", "none")
    if kind == "gated":
        hidden = (int(8 * d / 3) + 127) // 128 * 128
        return 2 * d * 2 * hidden + 2 * hidden * d
    return 2 * 2 * d * 4 * d if kind == "dit" else 0


def attention_token_flops(cfg: dict, context: float) -> int:
    """One token through one causal self-attention layer that attends to ``context`` tokens."""
    d = cfg["d_model"]
    return int(2 * d * 3 * d + 2 * 2 * context * d + 2 * d * d)  # qkv, scores and weighted sum, out projection


def observation_flops(cfg: dict, n_points: int) -> int:
    """E_obs on one observation: per-point MLP, max-pool, state MLP and the fusion projection."""
    widths = list(cfg["point_widths"])
    if cfg["point_dim"] == 6 and len(widths) == 3:
        widths.append(512)
    point = n_points * _mlp([cfg["point_dim"], *widths]) + 2 * widths[-1] * cfg["point_feature_dim"]
    state = _mlp([cfg["state_dim"], *cfg["state_widths"]])
    fuse = (
        0
        if cfg.get("denoiser_backbone") == "unet"
        else 2 * (cfg["point_feature_dim"] + cfg["state_widths"][-1]) * cfg["d_model"]
    )
    return point + state + fuse


def history_step_flops(cfg: dict, n_points: int) -> int:
    """One control tick: E_obs plus one step of every history layer (with a window of T_h steps, every layer
    runs over the T_h tokens of the window)."""
    layers = cfg["n_history_layers"] if cfg["use_history"] else 0
    tokens = cfg.get("history_window", 0) or 1
    return observation_flops(cfg, n_points) + layers * tokens * mamba_token_flops(cfg)


def unet_flops(cfg: dict) -> int:
    """One evaluation of DP3's UNet (``denoiser_backbone`` unet) on a chunk of H actions: its convolutions and the
    FiLM projections of every residual block (level i runs at length H / 2^i)."""
    k, h, a = cfg["unet_kernel_size"], cfg["horizon"], cfg["action_dim"]
    n_prefix = int(cfg["use_history"]) + (cfg["n_obs_steps"] if cfg["use_recent_states"] else 0)
    cond = cfg["unet_step_embed_dim"] + n_prefix * cfg["d_model"]
    dims = list(cfg["unet_down_dims"])
    levels = list(zip([a, *dims[:-1]], dims))
    lengths = [h // 2**i for i in range(len(dims))]

    def block(
        c_in: int, c_out: int, n: int
    ) -> int:  # two convs, the FiLM projection, a 1x1 residual if the width changes
        return (
            2 * n * k * (c_in * c_out + c_out * c_out)
            + 2 * cond * 2 * c_out
            + (2 * n * c_in * c_out if c_in != c_out else 0)
        )

    total = 0
    for i, (c_in, c_out) in enumerate(levels):
        total += block(c_in, c_out, lengths[i]) + block(c_out, c_out, lengths[i])
        if i < len(levels) - 1:
            total += 2 * lengths[i + 1] * 3 * c_out * c_out  # Conv1d k3 stride 2
    total += 2 * block(dims[-1], dims[-1], lengths[-1])
    for j, (c_in, c_out) in enumerate(reversed(levels[1:])):
        n = lengths[-1 - j]
        total += (
            block(2 * c_out, c_in, n) + block(c_in, c_in, n) + 2 * n * 4 * c_in * c_in
        )  # ConvTranspose1d k4 stride 2
    return total + 2 * h * k * dims[0] * dims[0] + 2 * h * dims[0] * a  # the head


def chunk_flops(cfg: dict, denoise_steps: int) -> int:
    """One action chunk: the prefix once (cached), then K passes over the H action tokens (each denoiser block's
    mixer, Mamba or attention to the tokens before it, and its MLP); DP3's UNet: K evaluations."""
    if cfg.get("denoiser_backbone") == "unet":
        return denoise_steps * unet_flops(cfg)
    n_prefix = int(cfg["use_history"]) + (cfg["n_obs_steps"] if cfg["use_recent_states"] else 0)
    h = cfg["horizon"]
    if (
        cfg.get("denoiser_backbone", "mamba") == "transformer"
    ):  # an action token attends to the prefix and the tokens before it
        mixer = attention_token_flops(cfg, n_prefix + (h + 1) / 2)
    else:
        mixer = mamba_token_flops(cfg)
    per_token = cfg["n_denoiser_layers"] * (mixer + mlp_token_flops(cfg))
    d, a = cfg["d_model"], cfg["action_dim"]
    io = h * (2 * a * d + 2 * d * a)  # action_in and action_out
    prefix_passes = 1 if cfg["timestep_decoupled"] else denoise_steps
    return prefix_passes * n_prefix * per_token + denoise_steps * (h * per_token + io)
