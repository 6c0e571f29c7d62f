"""Mamba's fused operators in an exported graph: ``ai.dssp::CausalConv1d`` and ``ai.dssp::SelectiveScan``.

:data:`FUSED_OPS` is what :attr:`dssp_train.model.mamba.Mamba.fused_ops` is set to on the copies traced
into the ``*.fused.onnx`` graphs. Run eagerly, each operator is the layer's own PyTorch math
(:func:`dssp_train.model.mamba.causal_conv`, :func:`dssp_train.model.selective_scan.selective_scan`), so
tracing sees the right shapes and values; exported, the ONNX exporter writes one custom node where the
standard graph has a chain of elementwise nodes. ONNX Runtime runs them with the library built from
``dssp_deploy/kernel/mamba_ops.cc`` (shapes there).

The graph feeds the operators expressions of the weights (``A = -exp(A_log)``, the conv kernel as (W, E)),
which the exporter or ONNX Runtime fold to constants.
"""

from __future__ import annotations

import torch

from dssp_deploy.mamba_kernel import CONV_OP, DOMAIN, SCAN_OP
from dssp_train.model.mamba import causal_conv
from dssp_train.model.selective_scan import linear_scan_unrolled, selective_scan


class _SelectiveScan(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, dt, B, C, z, A, D, h0):  # noqa: N803 (the math's names)
        return selective_scan(x, dt, B, C, z, A, D, h0, linear_scan_unrolled)

    @staticmethod
    def symbolic(g, x, dt, B, C, z, A, D, h0):  # noqa: N803
        y, h = g.op(f"{DOMAIN}::{SCAN_OP}", x, dt, B, C, z, A, D, h0, outputs=2)
        y.setType(x.type())  # the exporter's shape inference cannot see inside a custom node
        h.setType(h0.type())
        return y, h


class _CausalConv(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, state, weight_we, bias):
        return causal_conv(x, state, weight_we.t().unsqueeze(1), bias)

    @staticmethod
    def symbolic(g, x, state, weight_we, bias):
        y, new_state = g.op(f"{DOMAIN}::{CONV_OP}", x, state, weight_we, bias, outputs=2)
        y.setType(x.type())
        new_state.setType(state.type())
        return y, new_state


class FusedOps:
    """The operators :class:`dssp_train.model.mamba.Mamba` calls when its ``fused_ops`` is set."""

    @staticmethod
    def selective_scan(x, dt, B, C, z, A, D, h0):  # noqa: N803
        """x, dt, z (batch, L, E), B, C (batch, L, n), A (E, n), D (E,), h0 (batch, E, n) → y (batch, L, E), h (batch, E, n)."""
        return _SelectiveScan.apply(x, dt, B, C, z, A, D, h0)

    @staticmethod
    def causal_conv(x, state, weight, bias):
        """x (batch, L, E), state (batch, E, W), weight (W, E), bias (E,) → silu(conv) (batch, L, E), new state (batch, E, W)."""
        return _CausalConv.apply(x, state, weight, bias)


FUSED_OPS = FusedOps()


def mark_unread_states(model) -> int:
    """Set ``state_out = 0`` on every ``SelectiveScan`` node whose state output nothing reads; returns how many.

    In the denoiser graph the K action-token scans of each layer start from the prefix's state and their
    final state is never used: the kernel then skips writing it back, (E, n) floats per layer and step.
    """
    import onnx  # deferred: loads onnx

    graph = model.graph
    read = _names_read(graph.node) | {o.name for o in graph.output}
    marked = 0
    for node in graph.node:
        if node.domain == DOMAIN and node.op_type == SCAN_OP and node.output[1] not in read:
            node.attribute.append(onnx.helper.make_attribute("state_out", 0))
            marked += 1
    return marked


def _names_read(nodes) -> set[str]:
    """Every name the nodes read, in their subgraphs (If branches) too."""
    names = set()
    for node in nodes:
        names.update(node.input)
        for attr in node.attribute:
            for sub in [attr.g] if attr.type == attr.GRAPH else list(attr.graphs):
                names |= _names_read(sub.node)
    return names
