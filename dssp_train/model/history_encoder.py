"""History encoder G_psi: z_{1:t} → c_t, causal, over the full history or a window of T_h steps.

Backbones (paper Table 3): a Mamba stack (the DSSP default; constant cost per step) or a causal
Transformer (cost per step grows with the history it attends to). ``history_window = T_h > 0``
encodes each step from only its last T_h observations, the window padded at the episode start
by repeating the first observation (as DP3 pads observation stacks).

Two paths, one set of weights:
- :meth:`HistoryEncoder.forward` — z (B, T, d) → c (B, T, d), the training path.
- :meth:`HistoryEncoder.step` — z_t (B, d) and a state → c_t (B, d) and the new state, the streaming
  path. ``state=None`` starts a new episode. For Mamba over the full history the state is the
  per-layer ``(conv_state, ssm_state)``; otherwise it is the buffer of observations the encoder
  attends to, (B, t or T_h, d).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from dssp_train.config import ModelConfig
from dssp_train.model.mamba_stack import MambaStack


def sinusoidal_embedding(positions: torch.Tensor, dim: int) -> torch.Tensor:
    """(...,) positions (int or float) → (..., dim) sin/cos features."""
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, device=positions.device, dtype=torch.float32) / half)
    args = positions.float().unsqueeze(-1) * freqs
    emb = torch.cat([torch.sin(args), torch.cos(args)], dim=-1)
    if dim % 2:
        emb = torch.cat([emb, emb.new_zeros(*emb.shape[:-1], 1)], dim=-1)
    return emb


class CausalTransformer(nn.Module):
    """Pre-norm causal Transformer encoder with sinusoidal positions: (B, L, d) → (B, L, d)."""

    def __init__(self, d_model: int, n_layer: int, n_heads: int):
        super().__init__()
        layer = nn.TransformerEncoderLayer(
            d_model,
            n_heads,
            dim_feedforward=4 * d_model,
            dropout=0.0,
            activation="gelu",
            batch_first=True,
            norm_first=True,
        )
        self.encoder = nn.TransformerEncoder(layer, n_layer, enable_nested_tensor=False)
        self.norm_f = nn.LayerNorm(d_model)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        length = x.shape[1]
        x = x + sinusoidal_embedding(torch.arange(length, device=x.device), x.shape[-1])
        mask = nn.Transformer.generate_square_subsequent_mask(length, device=x.device)
        return self.norm_f(self.encoder(x, mask=mask, is_causal=True))


class HistoryEncoder(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.backbone = cfg.history_backbone
        self.window = cfg.history_window
        if self.backbone == "mamba":
            self.net = MambaStack(cfg.d_model, cfg.n_history_layers, cfg.d_state, cfg.d_conv, cfg.expand)
        else:
            self.net = CausalTransformer(cfg.d_model, cfg.n_history_layers, cfg.transformer_heads)

    @property
    def is_recurrent(self) -> bool:
        """True when the streaming state is a recurrent state of constant size (Mamba over the full history)."""
        return self.backbone == "mamba" and self.window == 0

    def _encode(self, z: torch.Tensor, unrolled: bool = False) -> torch.Tensor:
        """Run the backbone over whole sequences from a fresh start: (B, L, d) → (B, L, d) (``unrolled``: Mamba's
        traceable path, for export)."""
        if self.backbone == "mamba":
            return self.net(z, unrolled=unrolled)[0]
        return self.net(z)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        """Training path: z (B, T, d) → c (B, T, d); c[:, t] depends on z[:, :t+1] only."""
        if self.window == 0:
            return self._encode(z)
        batch, length, dim = z.shape
        padded = torch.cat([z[:, :1].expand(batch, self.window - 1, dim), z], dim=1)
        windows = padded.unfold(1, self.window, 1).permute(0, 1, 3, 2)  # (B, T, T_h, d)
        c = self._encode(windows.reshape(batch * length, self.window, dim))[:, -1]
        return c.reshape(batch, length, dim)

    def step(self, z_t: torch.Tensor, state=None):
        """Streaming path: z_t (B, d) → (c_t (B, d), new state). ``state=None`` starts an episode."""
        if self.is_recurrent:
            if state is None:
                state = self.net.init_state(z_t.shape[0], z_t.device)
            return self.net.step(z_t, state)
        if self.window:
            return self.window_step(z_t, *(self.window_start(z_t) if state is None else state))
        state = z_t.unsqueeze(1) if state is None else torch.cat([state, z_t.unsqueeze(1)], dim=1)
        return self._encode(state)[:, -1], state

    # ------------------------------------------------------------ a window of T_h steps
    def window_start(self, z_t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The state of a window model at the start of an episode: all zeros, as the runtime starts every state:
        the window (B, T_h, d) and the count of observations seen (B, 1)."""
        batch, dim = z_t.shape
        return z_t.new_zeros(batch, self.window, dim), z_t.new_zeros(batch, 1)

    def window_step(self, z_t: torch.Tensor, window: torch.Tensor, seen: torch.Tensor, unrolled: bool = False):
        """One tick of a window model: z_t (B, d), the last T_h tokens (B, T_h, d) and how many were seen (B, 1)
        → c_t (B, d) and the new (window, seen). Slots not yet seen hold the episode's first z (the training
        path's padding), so the first tick's zeros never reach the encoder; the backbone runs over the window
        from a fresh start (``unrolled``: the traceable path, as the exported history graph runs it)."""
        length = window.shape[1]
        window = torch.cat([window[:, 1:], z_t.unsqueeze(1)], dim=1)
        seen = (seen + 1).clamp(max=length)
        start = (length - seen).long()  # (B, 1): the oldest real token's slot; those before it are padding
        first = window.gather(1, start.unsqueeze(-1).expand(-1, 1, window.shape[2]))  # (B, 1, d)
        padding = torch.arange(length, device=window.device).unsqueeze(0) < start  # (B, T_h)
        window = torch.where(padding.unsqueeze(-1), first, window)
        return self._encode(window, unrolled)[:, -1], (window, seen)
