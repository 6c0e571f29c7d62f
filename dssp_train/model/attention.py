"""Causal multi-head self-attention with rotary positions: the mixer of the Transformer denoiser.

The denoiser ablation "w/ Trans." (paper Table 5, ``model.denoiser_backbone = "transformer"``) swaps each
block's Mamba mixer for this layer and keeps everything else. It has Mamba's call interface, so
:class:`dssp_train.model.denoiser.Denoiser` runs either unchanged:

- :meth:`CausalSelfAttention.forward` — tokens (B, L, d) and an optional state → out (B, L, d) and the
  new state. The state is the key/value cache of every token seen so far, ``(k, v)`` each
  (B, heads, L_seen, d_head) with the rotary embedding already applied to ``k``; ``None`` (or an empty
  cache, :meth:`init_state`) starts from nothing. The new tokens sit at positions L_seen .. L_seen + L - 1,
  attend to every cached token and causally among themselves, and the returned state is the cache with
  their keys and values appended. So the denoiser runs its prefix once (``Denoiser.encode_prefix``: the
  per-layer caches) and every DDIM step runs only the action tokens against them, exactly as it reuses
  Mamba's recurrent state.
- :meth:`CausalSelfAttention.forward_unrolled` — the same method (the path the exported graphs trace;
  attention has no recurrence to unroll). The positions, the causal mask and the head layout depend only on
  the token counts, taken as plain ints, so a trace holds them as constants (an exported graph's prefix and
  action lengths are fixed) and only the batch size stays dynamic.

Parameters and math follow mamba-ssm's attention layer (``mamba_ssm.modules.mha.MHA`` with ``causal=True``,
``rotary_emb_dim = r`` below, ``rotary_emb_interleaved=False``, ``qkv_proj_bias = out_proj_bias = False``),
so a mixer's state dict loads into that layer and back: ``in_proj`` d → 3d laid out ``[q | k | v]``, each ``(heads, d_head)``,
and ``out_proj`` d → d, both without biases — like Mamba's own ``in_proj`` and ``out_proj``, and the
attention of mamba-ssm's hybrid models. Rotary embedding (RoPE, GPT-NeoX layout: the first half of each
head's channels rotates against the second half) on q and k by absolute token position, base 10000,
frequencies ``base ** (-2i / r)``; r = d_head, or d_head - 1 for an odd d_head (the last channel then
carries no position). Scores are scaled by 1/sqrt(d_head); attention is
``F.scaled_dot_product_attention`` with a boolean mask (exports to ONNX opset 17 as MatMul and Softmax).

Shapes: tokens (B, L, d_model); state (k, v) each (B, heads, L_seen, d_head).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

KVCache = tuple[torch.Tensor, torch.Tensor]


class CausalSelfAttention(nn.Module):
    def __init__(self, d_model: int, n_heads: int, layer_idx: int | None = None, rope_base: float = 10000.0):
        super().__init__()
        if d_model % n_heads:
            raise ValueError(f"d_model={d_model} must be divisible by n_heads={n_heads}")
        self.d_model = d_model
        self.n_heads = n_heads
        self.d_head = d_model // n_heads
        self.layer_idx = layer_idx
        self.rope_base = rope_base
        self.rotary_dim = self.d_head - self.d_head % 2
        self.in_proj = nn.Linear(d_model, 3 * d_model, bias=False)
        self.out_proj = nn.Linear(d_model, d_model, bias=False)

    # ------------------------------------------------------------------ states
    def init_state(self, batch_size: int, device=None, dtype=torch.float32) -> KVCache:
        """An empty cache: ``(k, v)`` each (B, heads, 0, d_head)."""
        device = device or self.out_proj.weight.device
        empty = torch.zeros(batch_size, self.n_heads, 0, self.d_head, device=device, dtype=dtype)
        return empty, empty.clone()

    # ------------------------------------------------------------ sequence path
    def forward(
        self, hidden_states: torch.Tensor, state: KVCache | None = None, state_at: int | None = None
    ) -> tuple[torch.Tensor, KVCache]:
        """Attention of L new tokens over the cached ones and themselves (causal).

        Args:
            hidden_states: (B, L, d_model).
            state: the key/value cache ``(k, v)`` each (B, heads, L_seen, d_head), or None for none.
            state_at: return the cache with only the first ``state_at`` new tokens (1..L) appended (a prefix's, as
                Mamba's ``state_at``); None: all L.
        Returns:
            out (B, L, d_model) and the cache with the new tokens appended, (B, heads, L_seen + L, d_head) each.
        """
        if state_at is not None and not 1 <= state_at <= hidden_states.shape[1]:
            raise ValueError(f"state_at must be 1..{hidden_states.shape[1]} (the tokens given), got {state_at}")
        # The token counts as plain ints: positions and mask trace to constants (a graph's L_seen and L are fixed).
        length = int(hidden_states.shape[1])
        seen = 0 if state is None else int(state[0].shape[2])
        q, k, v = (
            t.view(-1, length, self.n_heads, self.d_head).transpose(1, 2)  # (B, heads, L, d_head)
            for t in self.in_proj(hidden_states).split(self.d_model, dim=-1)
        )
        cos, sin = self._rotary(seen, length, q)  # (L, r / 2) each
        q, k = self._rotate(q, cos, sin), self._rotate(k, cos, sin)
        if state is not None:
            k = torch.cat([state[0], k], dim=2)  # (B, heads, L_seen + L, d_head)
            v = torch.cat([state[1], v], dim=2)
        # query i (position seen + i) sees key j (position j) when j <= seen + i
        mask = torch.ones(length, seen + length, dtype=torch.bool, device=q.device).tril(seen)  # (L, L_seen + L)
        y = F.scaled_dot_product_attention(q, k, v, attn_mask=mask, scale=self.d_head**-0.5)  # (B, heads, L, d_head)
        if state_at is not None:
            k, v = k[:, :, : seen + state_at], v[:, :, : seen + state_at]
        return self.out_proj(y.transpose(1, 2).reshape(-1, length, self.d_model)), (k, v)

    forward_unrolled = forward

    # ---------------------------------------------------------- rotary embedding
    def _rotate(self, x: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
        """The rotary embedding on x (B, heads, L, d_head): its first r channels rotate, the rest (if any) pass."""
        r = self.rotary_dim
        if r == self.d_head:
            return apply_rotary(x, cos, sin)
        return torch.cat([apply_rotary(x[..., :r], cos, sin), x[..., r:]], dim=-1)

    def _rotary(self, start: int, length: int, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """cos, sin (L, r / 2) of positions start .. start + L - 1, in ``like``'s dtype (angles in fp32 or wider)."""
        dtype = torch.promote_types(like.dtype, torch.float32)
        half = self.rotary_dim // 2
        inv_freq = self.rope_base ** (-torch.arange(half, device=like.device, dtype=dtype) * 2 / self.rotary_dim)
        positions = torch.arange(length, device=like.device, dtype=dtype) + start
        angles = positions.unsqueeze(1) * inv_freq  # (L, r / 2)
        return angles.cos().to(like.dtype), angles.sin().to(like.dtype)


def apply_rotary(x: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
    """Rotate x (B, heads, L, r) by position, channel i < r/2 against i + r/2 (GPT-NeoX layout); cos, sin (L, r / 2)."""
    half = cos.shape[-1]
    x1, x2 = x[..., :half], x[..., half:]
    return torch.cat([x1 * cos - x2 * sin, x2 * cos + x1 * sin], dim=-1)


def init_attention_weights(module: nn.Module, n_layer: int, residuals_per_layer: int = 1) -> None:
    """The residual rule of :func:`dssp_train.model.mamba_stack.init_mamba_weights` for attention (apply with
    ``model.apply``): ``out_proj`` Kaiming-uniform, scaled by 1/sqrt(residuals_per_layer * n_layer), as mamba-ssm
    rescales every ``out_proj``; ``in_proj`` keeps PyTorch's Linear default (as mamba-ssm's MHA)."""
    if isinstance(module, CausalSelfAttention):
        nn.init.kaiming_uniform_(module.out_proj.weight, a=math.sqrt(5))
        with torch.no_grad():
            module.out_proj.weight /= math.sqrt(residuals_per_layer * n_layer)
