"""DP3's denoiser: the conditional 1-D temporal UNet with FiLM (``model.denoiser_backbone = "unet"``).

The baseline the paper compares with (3D Diffusion Policy). Written from DP3's published architecture
(its ``ConditionalUnet1D`` with ``condition_type: film``, taken over from Diffusion Policy); it contains no
DP3 code. With the ``dp3`` presets the whole policy is DP3: its point encoder and state MLP
(:mod:`dssp_train.model.obs_encoder`, without the projection), N observation frames, this UNet, its
normalisation and DDIM schedule. It plugs into :class:`dssp_train.model.policy.DSSPPolicy` behind the same
interface as :class:`dssp_train.model.denoiser.Denoiser`, so the trainer, the exporter, the runtime,
``dssp-run`` and ``dssp-sim eval`` run it unchanged.

    global cond: the prefix [z_{t-N+1}, ..., z_t] flattened (B, L_p * d) (each z the concatenated point and
                 state features, d = point_feature_dim + state_widths[-1]; with a history encoder c_t leads)
    step:        tau (B,) -> sinusoidal (B, e) -> Linear(e, 4e) + Mish + Linear(4e, e) -> (B, e)
    FiLM cond:   concat(step, global cond) (B, e + L_p * d)
    x_tau (B, H, A) -> (B, A, H)
      down:  per width w of ``unet_down_dims``: 2 FiLM residual blocks, then Conv1d k3 stride 2 (not after the last)
      mid:   2 FiLM residual blocks at the last width
      up:    per level back: concat the skip, 2 FiLM residual blocks, ConvTranspose1d k4 stride 2
      head:  Conv1d k + GroupNorm + Mish, Conv1d 1x1 -> (B, A, H) -> x0_hat (B, H, A)
    FiLM residual block: Conv1d k (same padding) + GroupNorm + Mish, then per channel ``scale * h + bias``
    with [scale, bias] = Linear(Mish(cond)), then Conv1d + GroupNorm + Mish; a 1x1 Conv on the residual when
    the width changes. H must be divisible by 2^(levels - 1).

The timestep enters only through the step embedding, so sampling computes the K embeddings once
(:meth:`UNetDenoiser.modulation`, a :class:`StepTable`), as the Mamba denoiser does its AdaLN table; the
exported graph keeps them as constants. The prefix is a plain condition: ``encode_prefix`` flattens it.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import nn

from dssp_train.config import ModelConfig


class StepTable(NamedTuple):
    """The step embeddings of T timesteps (T, e): T = B (one per sample) or T = K (a DDIM table)."""

    embedding: torch.Tensor

    def at(self, k: int) -> StepTable:
        """Row k (timestep k of K) as a one-row table (1, e)."""
        return StepTable(self.embedding[k : k + 1])


class SinusoidalEmbedding(nn.Module):
    """tau (B,) -> (B, dim): sin and cos of tau at geometrically spaced frequencies (Diffusion Policy's)."""

    def __init__(self, dim: int):
        super().__init__()
        half = dim // 2
        scale = math.log(10000.0) / max(half - 1, 1)
        self.register_buffer("freqs", torch.exp(torch.arange(half, dtype=torch.float32) * -scale), persistent=False)

    def forward(self, timesteps: torch.Tensor) -> torch.Tensor:
        arg = timesteps.to(torch.float32)[:, None] * self.freqs[None, :]
        return torch.cat([arg.sin(), arg.cos()], dim=-1)


class ConvBlock(nn.Sequential):
    """(B, C_in, L) -> (B, C_out, L): Conv1d (same padding) + GroupNorm + Mish."""

    def __init__(self, c_in: int, c_out: int, kernel_size: int, n_groups: int):
        super().__init__(
            nn.Conv1d(c_in, c_out, kernel_size, padding=kernel_size // 2), nn.GroupNorm(n_groups, c_out), nn.Mish()
        )


class FiLMResidualBlock(nn.Module):
    """(B, C_in, L), cond (B or 1, D) -> (B, C_out, L): per-channel scale and bias from cond after the first conv."""

    def __init__(self, c_in: int, c_out: int, cond_dim: int, kernel_size: int, n_groups: int):
        super().__init__()
        self.c_out = c_out
        self.conv1 = ConvBlock(c_in, c_out, kernel_size, n_groups)
        self.conv2 = ConvBlock(c_out, c_out, kernel_size, n_groups)
        self.film = nn.Sequential(nn.Mish(), nn.Linear(cond_dim, 2 * c_out))
        self.skip = nn.Conv1d(c_in, c_out, 1) if c_in != c_out else nn.Identity()

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        scale, bias = self.film(cond).reshape(cond.shape[0], 2, self.c_out, 1).unbind(1)
        return self.conv2(self.conv1(x) * scale + bias) + self.skip(x)


class UNetDenoiser(nn.Module):
    """f_theta as DP3's UNet: prefix (B, L_p, d), x_tau (B, H, A), timesteps (B,) -> x0_hat (B, H, A)."""

    joins_prefix = False  # the prefix is a global condition, flattened apart from the steps (Denoiser.joins_prefix)

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        e, k, groups = cfg.unet_step_embed_dim, cfg.unet_kernel_size, cfg.unet_n_groups
        dims = list(cfg.unet_down_dims)
        self.step_encoder = nn.Sequential(SinusoidalEmbedding(e), nn.Linear(e, 4 * e), nn.Mish(), nn.Linear(4 * e, e))
        cond = e + cfg.prefix_length * cfg.d_model
        widths = [cfg.action_dim, *dims]
        levels = list(zip(widths[:-1], widths[1:]))

        def block(c_in: int, c_out: int) -> FiLMResidualBlock:
            return FiLMResidualBlock(c_in, c_out, cond, k, groups)

        self.down = nn.ModuleList(
            nn.ModuleList(
                [
                    block(c_in, c_out),
                    block(c_out, c_out),
                    nn.Conv1d(c_out, c_out, 3, stride=2, padding=1) if i < len(levels) - 1 else nn.Identity(),
                ]
            )
            for i, (c_in, c_out) in enumerate(levels)
        )
        self.mid = nn.ModuleList([block(dims[-1], dims[-1]), block(dims[-1], dims[-1])])
        self.up = nn.ModuleList(  # one level per downsampling, each back to twice the length
            nn.ModuleList(
                [block(2 * c_out, c_in), block(c_in, c_in), nn.ConvTranspose1d(c_in, c_in, 4, stride=2, padding=1)]
            )
            for c_in, c_out in reversed(levels[1:])
        )
        self.head = nn.Sequential(ConvBlock(dims[0], dims[0], k, groups), nn.Conv1d(dims[0], cfg.action_dim, 1))

    # ------------------------------------------------------------ step embedding
    def modulation(self, timesteps: torch.Tensor) -> StepTable:
        """The step embeddings of timesteps (T,), computed once: a batch's (T = B) or a DDIM table's (T = K)."""
        return StepTable(self.step_encoder(timesteps))

    def fold_timestep(self) -> None:
        """Drop the step encoder (an exported graph has the K embeddings as constants)."""
        self.step_encoder = None

    # ------------------------------------------------------------------ forward
    def forward(self, prefix: torch.Tensor, x_tau: torch.Tensor, timesteps: torch.Tensor) -> torch.Tensor:
        """Training path: prefix (B, L_p, d), x_tau (B, H, A), timesteps (B,) -> x0_hat (B, H, A)."""
        return self.forward_modulated(prefix, x_tau, self.modulation(timesteps))

    def forward_modulated(
        self, prefix: torch.Tensor, x_tau: torch.Tensor, mod: StepTable, unrolled: bool = False
    ) -> torch.Tensor:
        """:meth:`forward` with the step embeddings given (B rows or one shared by the batch)."""
        return self.denoise_modulated(self.encode_prefix(prefix), x_tau, mod)

    def encode_prefix(self, prefix: torch.Tensor, unrolled: bool = False) -> torch.Tensor:
        """The global condition: prefix (B, L_p, d) -> (B, L_p * d)."""
        return prefix.flatten(1)

    def denoise_modulated(
        self, global_cond: torch.Tensor, x_tau: torch.Tensor, mod: StepTable, unrolled: bool = False
    ) -> torch.Tensor:
        """x0_hat (B, H, A) from the global condition (B, G), x_tau (B, H, A) and the step embeddings (B or 1, e)."""
        step = mod.embedding.expand(x_tau.shape[0], -1)
        cond = torch.cat([step, global_cond], dim=-1)
        x = x_tau.transpose(1, 2)
        skips = []
        for first, second, down in self.down:
            x = second(first(x, cond), cond)
            skips.append(x)
            x = down(x)
        for mid in self.mid:
            x = mid(x, cond)
        for first, second, up in self.up:
            x = up(second(first(torch.cat([x, skips.pop()], dim=1), cond), cond))
        return self.head(x).transpose(1, 2)
