"""The linear recurrence at the heart of Mamba, ``h_t = a_t * h_{t-1} + b_t``, over a whole sequence.

Training runs the history encoder over trajectories of hundreds to thousands of steps, so the
sequence path must not be a Python loop over time steps. :func:`linear_scan` is a work-efficient
(Blelloch-style) parallel scan done in place on strided views: ``2 * log2(L)`` vectorised passes
and O(L) work, with no padding. Its backward pass is the same scan run in reverse (the adjoint of a linear
recurrence is a linear recurrence), so autograd stores only ``a`` and the states ``h``.

Written by hand because no maintained library offers a CPU selective scan with a custom backward
(mamba-ssm's kernels are CUDA/Triton only and cannot be imported without a GPU).

:func:`linear_scan_unrolled` is the plain loop, for short sequences in an exported graph.
:func:`selective_scan` is Mamba's whole selective scan around either of them (softplus, decay, drive,
readout, gate): the arithmetic the fused ONNX Runtime operator (``dssp_deploy/kernel``) does in one pass.

Shapes: ``a``, ``b``, ``h`` are (B, L, D, N); the recurrence runs along dim 1 (L), any length.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def _scan_inplace(a: torch.Tensor, x: torch.Tensor, reverse: bool = False) -> None:
    """In-place inclusive scan of ``x_t = a_t * x_{t-1} + x_t`` along dim 1 (any length L).

    With ``reverse`` the recurrence runs from the end: ``x_t = a_t * x_{t+1} + x_t``.
    ``a`` and ``x`` are (B, L, D, N); ``a`` is overwritten with partial products.
    """
    length = x.shape[1]
    levels = length.bit_length() - 1

    def positions(first: int, step: int, count: int) -> slice:
        """``count`` positions first, first + step, ... counted from the start (or from the end)."""
        if not reverse:
            return slice(first, first + step * (count - 1) + 1, step)
        last = length - 1 - first
        return slice(last - step * (count - 1), last + 1, step)

    # Up-sweep: position p ends up holding the reduction of the block of length lowbit(p+1) ending at p.
    for d in range(levels):
        half, stride = 1 << d, 1 << (d + 1)
        count = length // stride
        target, source = positions(stride - 1, stride, count), positions(half - 1, stride, count)
        x[:, target].addcmul_(a[:, target], x[:, source])
        a[:, target].mul_(a[:, source])
    # Down-sweep: complete the prefixes of positions whose block does not start at the first position.
    for d in range(levels - 1, -1, -1):
        half, stride = 1 << d, 1 << (d + 1)
        count = len(range(stride + half - 1, length, stride))
        if count:
            target, source = positions(stride + half - 1, stride, count), positions(stride - 1, stride, count)
            x[:, target].addcmul_(a[:, target], x[:, source])


class _LinearScan(torch.autograd.Function):
    @staticmethod
    def forward(ctx, a: torch.Tensor, b: torch.Tensor, h0: torch.Tensor) -> torch.Tensor:
        h = b.clone(memory_format=torch.contiguous_format)
        h[:, 0].addcmul_(a[:, 0], h0)
        _scan_inplace(a.clone(memory_format=torch.contiguous_format), h)
        ctx.save_for_backward(a, h, h0)
        return h

    @staticmethod
    def backward(ctx, grad_h: torch.Tensor):
        a, h, h0 = ctx.saved_tensors
        # g_t = grad_h_t + a_{t+1} g_{t+1}: the same recurrence, run from the end.
        a_next = torch.empty_like(a, memory_format=torch.contiguous_format)
        a_next[:, :-1] = a[:, 1:]
        a_next[:, -1] = 0
        g = grad_h.clone(memory_format=torch.contiguous_format)
        _scan_inplace(a_next, g, reverse=True)
        grad_a = torch.empty_like(g)
        torch.mul(g[:, 1:], h[:, :-1], out=grad_a[:, 1:])
        grad_a[:, 0] = g[:, 0] * h0
        grad_h0 = a[:, 0] * g[:, 0]
        return grad_a, g, grad_h0


def linear_scan(a: torch.Tensor, b: torch.Tensor, h0: torch.Tensor | None = None) -> torch.Tensor:
    """All states of ``h_t = a_t * h_{t-1} + b_t`` (with ``h_{-1} = h0``, zeros by default).

    Args:
        a: (B, L, D, N) decay factors.
        b: (B, L, D, N) inputs.
        h0: (B, D, N) initial state, or None for zeros.
    Returns:
        h: (B, L, D, N).
    """
    if h0 is None:
        h0 = a.new_zeros(a.shape[:1] + a.shape[2:])
    return _LinearScan.apply(a, b, h0)


def linear_scan_unrolled(a: torch.Tensor, b: torch.Tensor, h0: torch.Tensor | None = None) -> torch.Tensor:
    """:func:`linear_scan` as a plain loop over time: a, b (B, L, D, N), h0 (B, D, N) or None → h (B, L, D, N).

    One multiply-add per step and nothing in place, so it traces into a plain graph for a short, fixed L
    (the exported denoiser); also the readable reference :func:`linear_scan` is tested against.
    With ``h0`` None the first state is ``b_0`` itself.
    """
    h = None if h0 is None else h0.unsqueeze(1)  # (B, 1, D, N)
    states = []
    for a_t, b_t in zip(a.split(1, dim=1), b.split(1, dim=1)):
        h = b_t if h is None else a_t * h + b_t
        states.append(h)
    return torch.cat(states, dim=1)


def selective_scan(x, dt, B, C, z, A, D, h0=None, scan=linear_scan, state_at=None):
    """Mamba's selective scan: y_t = (C_t . h_t + D x_t) * silu(z_t), h_t = exp(delta_t A) h_{t-1} + delta_t x_t B_t.

    Args:
        x, z: (batch, L, E) the conv branch (after its SiLU) and the gate branch.
        dt: (batch, L, E) ``dt_proj`` output before softplus (delta = softplus(dt)).
        B, C: (batch, L, n).
        A: (E, n), negative; D: (E,).
        h0: (batch, E, n) the state before the first token, or None for zeros.
        scan: :func:`linear_scan` or :func:`linear_scan_unrolled`.
        state_at: the state to return: after this many tokens (1..L), or None: after the last.
    Returns:
        y (batch, L, E) and the state after the last token (after ``state_at`` tokens) (batch, E, n).
    """
    delta = F.softplus(dt)
    decay = torch.exp(delta.unsqueeze(-1) * A)  # (batch, L, E, n)
    drive = (delta * x).unsqueeze(-1) * B.unsqueeze(-2)  # (batch, L, E, n)
    h = scan(decay, drive, h0)  # (batch, L, E, n)
    y = torch.matmul(h, C.unsqueeze(-1))[..., 0]  # (batch, L, E)
    return (y + D * x) * F.silu(z), h[:, -1 if state_at is None else state_at - 1]
