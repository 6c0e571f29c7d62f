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

from dssp_train.model.selective_scan import linear_scan, linear_scan_unrolled

MambaState = tuple[torch.Tensor, torch.Tensor]


class Mamba(nn.Module):
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
        dt = torch.exp(
            torch.rand(self.d_inner) * (math.log(dt_max) - math.log(dt_min)) + math.log(dt_min)
        ).clamp(min=dt_init_floor)
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
    def forward(self, hidden_states: torch.Tensor, state: MambaState | None = None) -> tuple[torch.Tensor, MambaState]:
        """Sequence path: the recurrence as a parallel scan (any length, with a backward pass).

        Args:
            hidden_states: (B, L, d_model).
            state: the recurrent state to continue from, or None to start from zeros.
        Returns:
            out (B, L, d_model) and the state after the last token.
        """
        return self._sequence(hidden_states, state, linear_scan)

    def forward_unrolled(
        self, hidden_states: torch.Tensor, state: MambaState | None = None
    ) -> tuple[torch.Tensor, MambaState]:
        """Short-sequence path: :meth:`forward` (same arguments, same result) with the recurrence unrolled.

        Every projection runs on all L tokens at once; only ``h_t = decay_t * h_{t-1} + drive_t`` is a
        loop, one multiply-add per token on (B, 1, d_inner, d_state) slices, nothing in place, so the
        layer traces into a plain graph (ONNX, TorchScript) for a small, fixed L. Stepping :meth:`step`
        token by token traces too, but turns every projection into L matrix-vector products.
        """
        return self._sequence(hidden_states, state, linear_scan_unrolled)

    def _sequence(self, hidden_states: torch.Tensor, state: MambaState | None, scan) -> tuple[torch.Tensor, MambaState]:
        """hidden_states (B, L, d_model) → out (B, L, d_model), state; ``scan(a, b, h0)`` as :func:`linear_scan`."""
        x, z = self.in_proj(hidden_states).chunk(2, dim=-1)  # (B, L, d_inner) each

        # Causal depthwise convolution, continuing from the last d_conv conv inputs (zeros at a fresh start).
        x = x.transpose(1, 2)  # (B, d_inner, L)
        x_ext = F.pad(x, (self.d_conv, 0)) if state is None else torch.cat([state[0], x], dim=-1)  # (B, d_inner, d_conv + L)
        new_conv_state = x_ext[:, :, -self.d_conv :]
        x = F.conv1d(x_ext[:, :, 1:], self.conv1d.weight, self.conv1d.bias, groups=self.d_inner)
        x = F.silu(x).transpose(1, 2)  # (B, L, d_inner)

        decay, drive, C = self._ssm_inputs(x)  # (B, L, d_inner, d_state) twice, (B, L, d_state)
        h = scan(decay, drive, None if state is None else state[1])  # (B, L, d_inner, d_state)
        return self._output(h, C, x, z), (new_conv_state, h[:, -1])

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
        x, z = self.in_proj(hidden_states).chunk(2, dim=-1)  # (B, d_inner)
        conv_state = torch.cat([conv_state[:, :, 1:], x.unsqueeze(-1)], dim=-1)
        x = (conv_state * self.conv1d.weight.squeeze(1)).sum(-1)
        if self.conv1d.bias is not None:
            x = x + self.conv1d.bias
        x = F.silu(x)

        decay, drive, C = self._ssm_inputs(x)  # (B, d_inner, d_state) twice, (B, d_state)
        ssm_state = decay * ssm_state + drive
        return self._output(ssm_state, C, x, z), (conv_state, ssm_state)

    # ------------------------------------------------------------------ shared
    def _ssm_inputs(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """x (..., d_inner) → decay exp(dt A), drive dt B x (..., d_inner, d_state) and C (..., d_state)."""
        dt, B, C = torch.split(self.x_proj(x), [self.dt_rank, self.d_state, self.d_state], dim=-1)
        dt = F.softplus(self.dt_proj(dt))  # (..., d_inner)
        A = -torch.exp(self.A_log.to(torch.promote_types(self.A_log.dtype, torch.float32)))  # (d_inner, d_state), fp32 or wider
        decay = torch.exp(dt.unsqueeze(-1) * A)
        drive = (dt * x).unsqueeze(-1) * B.unsqueeze(-2)
        return decay, drive, C

    def _output(self, h: torch.Tensor, C: torch.Tensor, x: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """States h (..., d_inner, d_state), C (..., d_state), x and z (..., d_inner) → out (..., d_model)."""
        y = torch.matmul(h, C.unsqueeze(-1))[..., 0]  # (..., d_inner)
        return self.out_proj((y + self.D * x) * F.silu(z))
