"""A stack of pre-norm residual Mamba blocks, laid out like mamba-ssm's ``MixerModel``.

State-dict keys match mamba-ssm (``layers.{i}.norm.weight``, ``layers.{i}.mixer.*``, ``norm_f.weight``),
and so does the initialisation (``_init_weights``: zero Linear biases, ``out_proj`` rescaled by
``1/sqrt(n_layer)``). Each block computes ``x + mixer(norm(x))``; the stack ends with ``norm_f``.

Shapes: tokens (B, L, d_model); the state is one ``(conv_state, ssm_state)`` pair per layer.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from dssp_train.model.mamba import Mamba, MambaState

StackState = list[MambaState]


class RMSNorm(nn.Module):
    """Root-mean-square norm with a learned scale (mamba-ssm's default norm, eps 1e-5)."""

    def __init__(self, dim: int, eps: float = 1e-5):
        super().__init__()
        self.eps = eps
        self.weight = nn.Parameter(torch.ones(dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * torch.rsqrt(x.pow(2).mean(-1, keepdim=True) + self.eps) * self.weight


class MambaBlock(nn.Module):
    """``norm`` and ``mixer`` of one residual block: x (B, L, d_model) → x + mixer(norm(x))."""

    def __init__(self, d_model: int, d_state: int, d_conv: int, expand: int, layer_idx: int):
        super().__init__()
        self.norm = RMSNorm(d_model)
        self.mixer = Mamba(d_model, d_state=d_state, d_conv=d_conv, expand=expand, layer_idx=layer_idx)


def init_mamba_weights(module: nn.Module, n_layer: int, residuals_per_layer: int = 1) -> None:
    """mamba-ssm's ``_init_weights`` for one submodule (apply with ``model.apply``): the last projection of each
    residual branch (Mamba's ``out_proj``, an MLP's ``fc2``) scaled by 1/sqrt(residuals_per_layer * n_layer)."""
    if isinstance(module, nn.Linear) and module.bias is not None and not getattr(module.bias, "_no_reinit", False):
        nn.init.zeros_(module.bias)
    last = module.out_proj if isinstance(module, Mamba) else getattr(module, "fc2", None)
    if isinstance(last, nn.Linear):
        nn.init.kaiming_uniform_(last.weight, a=math.sqrt(5))
        with torch.no_grad():
            last.weight /= math.sqrt(residuals_per_layer * n_layer)


class MambaStack(nn.Module):
    """``n_layer`` residual Mamba blocks and a final RMSNorm."""

    def __init__(self, d_model: int, n_layer: int, d_state: int = 16, d_conv: int = 4, expand: int = 2):
        super().__init__()
        self.d_model = d_model
        self.layers = nn.ModuleList(MambaBlock(d_model, d_state, d_conv, expand, i) for i in range(n_layer))
        self.norm_f = RMSNorm(d_model)
        self.apply(lambda m: init_mamba_weights(m, n_layer))

    def init_state(self, batch_size: int, device=None) -> StackState:
        return [layer.mixer.init_state(batch_size, device) for layer in self.layers]

    def forward(
        self, x: torch.Tensor, state: StackState | None = None, unrolled: bool = False
    ) -> tuple[torch.Tensor, StackState]:
        """Sequence path: x (B, L, d_model) → (B, L, d_model) and the state after the last token (``unrolled``: each
        layer's traceable :meth:`Mamba.forward_unrolled`, for export over a few tokens)."""
        new_state = []
        for i, layer in enumerate(self.layers):
            mixer = layer.mixer.forward_unrolled if unrolled else layer.mixer
            out, layer_state = mixer(layer.norm(x), None if state is None else state[i])
            x = x + out
            new_state.append(layer_state)
        return self.norm_f(x), new_state

    def step(self, x: torch.Tensor, state: StackState) -> tuple[torch.Tensor, StackState]:
        """Recurrent path: x (B, d_model) → (B, d_model) and the new state."""
        new_state = []
        for layer, layer_state in zip(self.layers, state):
            out, layer_state = layer.mixer.step(layer.norm(x), layer_state)
            x = x + out
            new_state.append(layer_state)
        return self.norm_f(x), new_state
