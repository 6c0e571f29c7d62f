"""Mamba (selective state-space) layer in pure PyTorch, weight-compatible with ``mamba_ssm.Mamba``.

Parameter names, shapes and initialisation follow ``mamba_ssm/modules/mamba_simple.py`` (Mamba-1),
so a state dict trained on a GPU with mamba-ssm loads here and back. One set of weights, three paths, one result:

- :meth:`Mamba.forward` — the sequence path (training, prefixes): a parallel scan over L tokens,
  optionally continuing from and returning the recurrent state.
- :meth:`Mamba.forward_unrolled` — the same for a few tokens with the scan unrolled token by token,
  a graph that traces (the exported denoiser).
- :meth:`Mamba.step` — the recurrent path (streaming, the exported history step): one token in,
  explicit ``(conv_state, ssm_state)`` in and out, no in-place updates.

Reference math, per channel d and state index n::

    x, z     = split(in_proj(u))
    x        = silu(causal_depthwise_conv(x))
    dt, B, C = split(x_proj(x));  dt = softplus(dt_proj(dt))
    h_t      = exp(dt_t * A) * h_{t-1} + dt_t * B_t * x_t        (A = -exp(A_log))
    y_t      = C_t . h_t + D * x_t;   out = out_proj(y * silu(z))

Shapes: tokens (B, L, d_model); conv_state (B, d_inner, d_conv) — the last d_conv conv inputs,
newest last; ssm_state (B, d_inner, d_state).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from dssp_train.model.selective_scan import linear_scan, linear_scan_unrolled, selective_scan

MambaState = tuple[torch.Tensor, torch.Tensor]


class Mamba(nn.Module):
    # Set on the copies export traces into the fused graphs (``export.fused_ops.FusedOps``): an object whose
    # ``selective_scan`` and ``causal_conv`` replace :func:`selective_scan` (without ``scan``) and
    # :func:`causal_conv`, each one graph node. None (the default) everywhere else.
    fused_ops = None

    def __init__(
        self,
        d_model: int,
        d_state: int = 16,
        d_conv: int = 4,
        expand: int = 2,
        dt_rank: int | str = "auto",
        dt_min: float = 0.001,
        dt_max: float = 0.1,
        dt_init: str = "random",
        dt_scale: float = 1.0,
        dt_init_floor: float = 1e-4,
        conv_bias: bool = True,
        bias: bool = False,
        layer_idx: int | None = None,
    ):
        super().__init__()
        self.d_model = d_model
        self.d_state = d_state
        self.d_conv = d_conv
        self.expand = expand
        self.d_inner = int(expand * d_model)
        self.dt_rank = math.ceil(d_model / 16) if dt_rank == "auto" else int(dt_rank)
        self.layer_idx = layer_idx

        self.in_proj = nn.Linear(d_model, self.d_inner * 2, bias=bias)
        self.conv1d = nn.Conv1d(
            self.d_inner, self.d_inner, kernel_size=d_conv, groups=self.d_inner, padding=d_conv - 1, bias=conv_bias
        )
        self.x_proj = nn.Linear(self.d_inner, self.dt_rank + 2 * d_state, bias=False)
        self.dt_proj = nn.Linear(self.dt_rank, self.d_inner, bias=True)

        # dt projection: keeps the variance at init; its bias makes softplus(bias) log-uniform in [dt_min, dt_max].
        dt_init_std = self.dt_rank**-0.5 * dt_scale
        if dt_init == "constant":
            nn.init.constant_(self.dt_proj.weight, dt_init_std)
        elif dt_init == "random":
            nn.init.uniform_(self.dt_proj.weight, -dt_init_std, dt_init_std)
        else:
            raise ValueError(f"dt_init must be 'constant' or 'random', got {dt_init!r}")
        dt = torch.exp(torch.rand(self.d_inner) * (math.log(dt_max) - math.log(dt_min)) + math.log(dt_min)).clamp(
            min=dt_init_floor
        )
        inv_dt = dt + torch.log(-torch.expm1(-dt))  # inverse of softplus
        with torch.no_grad():
            self.dt_proj.bias.copy_(inv_dt)
        self.dt_proj.bias._no_reinit = True

        # S4D-real initialisation of A; A_log and D are kept out of weight decay.
        A = torch.arange(1, d_state + 1, dtype=torch.float32).repeat(self.d_inner, 1)
        self.A_log = nn.Parameter(torch.log(A))
        self.A_log._no_weight_decay = True
        self.D = nn.Parameter(torch.ones(self.d_inner))
        self.D._no_weight_decay = True

        self.out_proj = nn.Linear(self.d_inner, d_model, bias=bias)

    # ------------------------------------------------------------------ states
    def init_state(self, batch_size: int, device=None, dtype=torch.float32) -> MambaState:
        """Zero ``(conv_state (B, d_inner, d_conv), ssm_state (B, d_inner, d_state))``."""
        device = device or self.out_proj.weight.device
        return (
            torch.zeros(batch_size, self.d_inner, self.d_conv, device=device, dtype=dtype),
            torch.zeros(batch_size, self.d_inner, self.d_state, device=device, dtype=dtype),
        )

    # ------------------------------------------------------------ sequence path
    def forward(
        self, hidden_states: torch.Tensor, state: MambaState | None = None, state_at: int | None = None
    ) -> tuple[torch.Tensor, MambaState]:
        """Sequence path: the recurrence as a parallel scan (any length, with a backward pass).

        Args:
            hidden_states: (B, L, d_model).
            state: the recurrent state to continue from, or None to start from zeros.
            state_at: return the state after this many tokens (1..L) instead of after the last: a prefix's state
                from a pass over [prefix, more tokens] (the denoiser's first DDIM step, ``Denoiser.joint_step``).
        Returns:
            out (B, L, d_model) and the state after the last token (after ``state_at`` tokens).
        """
        return self._sequence(hidden_states, state, linear_scan, state_at)

    def forward_unrolled(
        self, hidden_states: torch.Tensor, state: MambaState | None = None, state_at: int | None = None
    ) -> tuple[torch.Tensor, MambaState]:
        """Short-sequence path: :meth:`forward` (same arguments, same result) with the recurrence unrolled.

        Every projection runs on all L tokens at once; only ``h_t = decay_t * h_{t-1} + drive_t`` is a
        loop, one multiply-add per token on (B, 1, d_inner, d_state) slices, nothing in place, so the
        layer traces into a plain graph (ONNX, TorchScript) for a small, fixed L. Stepping :meth:`step`
        token by token traces too, but turns every projection into L matrix-vector products.
        """
        return self._sequence(hidden_states, state, linear_scan_unrolled, state_at)

    def _sequence(
        self, hidden_states: torch.Tensor, state: MambaState | None, scan, state_at: int | None
    ) -> tuple[torch.Tensor, MambaState]:
        """hidden_states (B, L, d_model) → out (B, L, d_model), state; ``scan(a, b, h0)`` as :func:`linear_scan`."""
        if state_at is not None and not 1 <= state_at <= hidden_states.shape[1]:
            raise ValueError(f"state_at must be 1..{hidden_states.shape[1]} (the tokens given), got {state_at}")
        x, z = self.in_proj(hidden_states).split(
            self.d_inner, dim=-1
        )  # (B, L, d_inner) each; one Split node when exported

        conv_state = x.new_zeros(x.shape[0], self.d_inner, self.d_conv) if state is None else state[0]
        if self.fused_ops is not None:
            x, new_conv_state = self.fused_ops.causal_conv(
                x, conv_state, self.conv1d.weight[:, 0].t(), self._conv_bias(), state_at
            )
        else:
            x, new_conv_state = causal_conv(
                x, conv_state, self.conv1d.weight, self.conv1d.bias, state_at
            )  # (B, L, d_inner)

        y, last = self._selective_scan(
            x, z, None if state is None else state[1], scan, state_at
        )  # (B, L, d_inner), (B, d_inner, d_state)
        return self.out_proj(y), (new_conv_state, last)

    # ----------------------------------------------------------- recurrent path
    def step(self, hidden_states: torch.Tensor, state: MambaState) -> tuple[torch.Tensor, MambaState]:
        """Recurrent path: one token.

        Args:
            hidden_states: (B, d_model).
            state: ``(conv_state (B, d_inner, d_conv), ssm_state (B, d_inner, d_state))``.
        Returns:
            out (B, d_model) and the new state (new tensors; the inputs are not modified).
        """
        conv_state, ssm_state = state
        x, z = self.in_proj(hidden_states).split(self.d_inner, dim=-1)  # (B, d_inner)
        if self.fused_ops is not None:
            x, conv_state = self.fused_ops.causal_conv(
                x.unsqueeze(1), conv_state, self.conv1d.weight[:, 0].t(), self._conv_bias()
            )
            x = x[:, 0]
        else:  # one token: the window's dot product with the kernel, cheaper than a convolution
            conv_state = torch.cat([conv_state[:, :, 1:], x.unsqueeze(-1)], dim=-1)
            x = (conv_state * self.conv1d.weight.squeeze(1)).sum(-1)
            if self.conv1d.bias is not None:
                x = x + self.conv1d.bias
            x = F.silu(x)

        y, ssm_state = self._selective_scan(x.unsqueeze(1), z.unsqueeze(1), ssm_state, linear_scan_unrolled)
        return self.out_proj(y[:, 0]), (conv_state, ssm_state)

    # ------------------------------------------------------------------ shared
    def _conv_bias(self) -> torch.Tensor:
        return self.conv1d.bias if self.conv1d.bias is not None else self.conv1d.weight.new_zeros(self.d_inner)

    def _selective_scan(
        self, x: torch.Tensor, z: torch.Tensor, h0: torch.Tensor | None, scan, state_at: int | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """x, z (B, L, d_inner), h0 (B, d_inner, d_state) or None → y * silu(z) (B, L, d_inner), the last state (the
        state after ``state_at`` tokens).

        With :attr:`fused_ops` set (the exported fused graphs), its ``selective_scan`` does the work of
        :func:`selective_scan` in one operator; otherwise ``scan`` runs the recurrence.
        """
        dt, B, C = torch.split(self.x_proj(x), [self.dt_rank, self.d_state, self.d_state], dim=-1)
        dt = self.dt_proj(dt)  # (B, L, d_inner), before softplus
        A = -torch.exp(
            self.A_log.to(torch.promote_types(self.A_log.dtype, torch.float32))
        )  # (d_inner, d_state), fp32 or wider
        if self.fused_ops is not None:
            if h0 is None:
                h0 = x.new_zeros(x.shape[0], self.d_inner, self.d_state)
            return self.fused_ops.selective_scan(x, dt, B, C, z, A, self.D, h0, state_at)
        return selective_scan(x, dt, B, C, z, A, self.D, h0, scan, state_at)


def causal_conv(
    x: torch.Tensor,
    state: torch.Tensor,
    weight: torch.Tensor,
    bias: torch.Tensor | None,
    state_at: int | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Mamba's conv branch: the causal depthwise convolution continuing from ``state``, then SiLU.

    Args:
        x: (B, L, E) the tokens' conv inputs.
        state: (B, E, W) the last W conv inputs before them, newest last (zeros at a fresh start).
        weight: (E, 1, W) the depthwise kernel (``nn.Conv1d`` layout); bias: (E,) or None.
        state_at: the new state after this many tokens (1..L) instead of after all L; None: after all.
    Returns:
        silu(conv) (B, L, E) and the new state (B, E, W): the last W of [state, x] (of [state, x[:state_at]]).
    """
    width = state.shape[-1]
    x_ext = torch.cat([state, x.transpose(1, 2)], dim=-1)  # (B, E, W + L)
    y = F.conv1d(x_ext[:, :, 1:], weight, bias, groups=x.shape[-1])  # (B, E, L)
    new_state = x_ext[:, :, -width:] if state_at is None else x_ext[:, :, state_at : state_at + width]
    return F.silu(y).transpose(1, 2), new_state
