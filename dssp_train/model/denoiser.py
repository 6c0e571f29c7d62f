"""Denoiser f_theta: a Mamba stack over ``[c_t, z_{t-N+1}, ..., z_t, x_tau tokens]`` that predicts x_0.

The diffusion timestep tau enters **only the action tokens**, through AdaLN in every block
(shift, scale and a residual gate from a zero-initialised projection of the timestep embedding);
the prefix tokens are never modulated, so the prefix is a stable condition for every denoising step
and — because Mamba is causal — its per-layer recurrent state can be computed once per chunk and
reused for all K DDIM steps (:meth:`Denoiser.encode_prefix` / :meth:`Denoiser.denoise`).
With ``timestep_decoupled=False`` (paper Table 5 ablation) the prefix is modulated too.

Shapes: prefix (B, L_p, d), x_tau (B, H, A), timesteps (B,) → x0_hat (B, H, A).
"""

from __future__ import annotations

import torch
from torch import nn

from dssp_train.config import ModelConfig
from dssp_train.model.history_encoder import sinusoidal_embedding
from dssp_train.model.mamba import Mamba, MambaState
from dssp_train.model.mamba_stack import RMSNorm, init_mamba_weights


def modulate(x: torch.Tensor, shift: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """AdaLN: x (B, L, d), shift/scale (B, d)."""
    return x * (1 + scale.unsqueeze(1)) + shift.unsqueeze(1)


class TimestepEmbedding(nn.Module):
    """tau (B,) → (B, d): sinusoidal features and an MLP."""

    def __init__(self, d_model: int):
        super().__init__()
        self.d_model = d_model
        self.mlp = nn.Sequential(nn.Linear(d_model, 4 * d_model), nn.SiLU(), nn.Linear(4 * d_model, d_model))

    def forward(self, timesteps: torch.Tensor) -> torch.Tensor:
        return self.mlp(sinusoidal_embedding(timesteps, self.d_model))


class DenoiserBlock(nn.Module):
    def __init__(self, d_model: int, d_state: int, d_conv: int, expand: int, layer_idx: int):
        super().__init__()
        self.norm = RMSNorm(d_model)
        self.mixer = Mamba(d_model, d_state=d_state, d_conv=d_conv, expand=expand, layer_idx=layer_idx)
        self.modulation = nn.Sequential(nn.SiLU(), nn.Linear(d_model, 3 * d_model))


class Denoiser(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        d = cfg.d_model
        self.decoupled = cfg.timestep_decoupled
        self.horizon = cfg.horizon
        self.action_in = nn.Linear(cfg.action_dim, d)
        self.action_pos = nn.Parameter(torch.zeros(cfg.horizon, d))
        self.time_embed = TimestepEmbedding(d)
        self.layers = nn.ModuleList(
            DenoiserBlock(d, cfg.d_state, cfg.d_conv, cfg.expand, i) for i in range(cfg.n_denoiser_layers)
        )
        self.norm_f = RMSNorm(d)
        self.final_modulation = nn.Sequential(nn.SiLU(), nn.Linear(d, 2 * d))
        self.action_out = nn.Linear(d, cfg.action_dim)

        self.apply(lambda m: init_mamba_weights(m, cfg.n_denoiser_layers))
        nn.init.normal_(self.action_pos, std=0.02)
        for layer in self.layers:
            nn.init.zeros_(layer.modulation[-1].weight)
            nn.init.zeros_(layer.modulation[-1].bias)
        nn.init.zeros_(self.final_modulation[-1].weight)
        nn.init.zeros_(self.final_modulation[-1].bias)

    # ------------------------------------------------------------ full forward
    def forward(self, prefix: torch.Tensor, x_tau: torch.Tensor, timesteps: torch.Tensor) -> torch.Tensor:
        """Training path over the whole sequence: returns x0_hat (B, H, A)."""
        temb = self.time_embed(timesteps)
        p, a = prefix, self.embed_actions(x_tau)
        n_prefix = p.shape[1]
        for layer in self.layers:
            shift, scale, gate = layer.modulation(temb).chunk(3, dim=-1)
            hp = layer.norm(p)
            if not self.decoupled:
                hp = modulate(hp, shift, scale)
            ha = modulate(layer.norm(a), shift, scale)
            out, _ = layer.mixer(torch.cat([hp, ha], dim=1))
            op, oa = out[:, :n_prefix], out[:, n_prefix:]
            p = p + (op if self.decoupled else gate.unsqueeze(1) * op)
            a = a + gate.unsqueeze(1) * oa
        return self.readout(a, temb)

    # ---------------------------------------------------- prefix-cached forward
    def encode_prefix(self, prefix: torch.Tensor) -> list[MambaState]:
        """Run the (unmodulated) prefix once: the recurrent state of every layer after it."""
        if not self.decoupled:
            raise RuntimeError("prefix caching needs timestep_decoupled=True (the prefix depends on tau otherwise)")
        states = []
        p = prefix
        for layer in self.layers:
            out, state = layer.mixer(layer.norm(p))
            p = p + out
            states.append(state)
        return states

    def denoise(self, prefix_states: list[MambaState], x_tau: torch.Tensor, timesteps: torch.Tensor) -> torch.Tensor:
        """x0_hat (B, H, A) from the cached prefix states; equals :meth:`forward` on the same prefix."""
        temb = self.time_embed(timesteps)
        a = self.embed_actions(x_tau)
        for layer, state in zip(self.layers, prefix_states):
            shift, scale, gate = layer.modulation(temb).chunk(3, dim=-1)
            out, _ = layer.mixer(modulate(layer.norm(a), shift, scale), state)
            a = a + gate.unsqueeze(1) * out
        return self.readout(a, temb)

    # ----------------------------------------------------------------- helpers
    def embed_actions(self, x_tau: torch.Tensor) -> torch.Tensor:
        return self.action_in(x_tau) + self.action_pos

    def readout(self, a: torch.Tensor, temb: torch.Tensor) -> torch.Tensor:
        shift, scale = self.final_modulation(temb).chunk(2, dim=-1)
        return self.action_out(modulate(self.norm_f(a), shift, scale))
