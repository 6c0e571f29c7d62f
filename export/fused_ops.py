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

from dssp_deploy.mamba_kernel import BLOCK_OP, CONV_OP, DOMAIN, POOL_OP, SCAN_OP, STEP_OP
from dssp_train.model.denoiser import DenoiserBlock, modulate
from dssp_train.model.mamba import Mamba, causal_conv
from dssp_train.model.scheduler import ddim_update
from dssp_train.model.selective_scan import linear_scan_unrolled, selective_scan


def _state_at(state_at: int) -> dict:
    """The nodes' attribute: ``state_at`` > 0, the state after that many tokens; none (0, the default): after the last."""
    return {"state_at_i": int(state_at)} if state_at else {}


class _SelectiveScan(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, dt, B, C, z, A, D, h0, state_at):  # noqa: N803 (the math's names)
        return selective_scan(x, dt, B, C, z, A, D, h0, linear_scan_unrolled, state_at or None)

    @staticmethod
    def symbolic(g, x, dt, B, C, z, A, D, h0, state_at):  # noqa: N803
        y, h = g.op(f"{DOMAIN}::{SCAN_OP}", x, dt, B, C, z, A, D, h0, outputs=2, **_state_at(state_at))
        y.setType(x.type())  # the exporter's shape inference cannot see inside a custom node
        h.setType(h0.type())
        return y, h


class _CausalConv(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, state, weight_we, bias, state_at):
        return causal_conv(x, state, weight_we.t().unsqueeze(1), bias, state_at or None)

    @staticmethod
    def symbolic(g, x, state, weight_we, bias, state_at):
        y, new_state = g.op(f"{DOMAIN}::{CONV_OP}", x, state, weight_we, bias, outputs=2, **_state_at(state_at))
        y.setType(x.type())
        new_state.setType(state.type())
        return y, new_state


class _LayerNormMaxOverPoints(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, weight, bias, eps):
        return torch.nn.functional.layer_norm(x, (x.shape[-1],), weight, bias, eps).amax(dim=-2)

    @staticmethod
    def symbolic(g, x, weight, bias, eps):
        y = g.op(f"{DOMAIN}::{POOL_OP}", x, weight, bias, eps_f=float(eps))
        y.setType(x.type().with_sizes([None, None]))  # (batch, F)
        return y


def ddim_step_reference(h, x, norm_w, mod, out_w, out_b, in_w, in_b, pos, eps, a_t, a_prev, sample, clip, tokens):
    """What ``ai.dssp::DdimStep`` computes, in PyTorch (the denoiser's readout, :func:`ddim_update` and its next action
    tokens, as :meth:`Denoiser.readout`, :meth:`DiffusionSchedule.ddim_step` and :meth:`Denoiser.embed_actions` do
    them): h (B, H, d), the last block's output on the action tokens, and x (B, H, A), the sample x_t → (x_prev
    (B, H, A), the next step's action tokens (B, H, d), or (B, H, 0) without ``tokens``). mod (2, d): the readout's
    shift and scale; out_w (A, d), out_b (A); in_w (A, d) (the input layer's weight transposed), in_b (d), pos (H, d)."""
    y = torch.nn.functional.linear(modulate(rms_norm(h, norm_w, eps), mod[:1], mod[1:]), out_w, out_b)
    x_prev = ddim_update(y, x, a_t, a_prev, sample, clip)
    a = x_prev @ in_w + in_b + pos if tokens else h[..., :0]
    return x_prev, a


class _DdimStep(torch.autograd.Function):
    @staticmethod
    def forward(ctx, *inputs):
        return ddim_step_reference(*inputs)

    @staticmethod
    def symbolic(g, h, x, norm_w, mod, out_w, out_b, in_w, in_b, pos, eps, a_t, a_prev, sample, clip, tokens):
        x_prev, a = g.op(
            f"{DOMAIN}::{STEP_OP}",
            h,
            x,
            norm_w,
            mod,
            out_w,
            out_b,
            in_w,
            in_b,
            pos,
            eps_f=float(eps),
            c_t_f=a_t**0.5,
            s_t_f=(1 - a_t) ** 0.5,
            c_prev_f=a_prev**0.5,
            s_prev_f=(1 - a_prev) ** 0.5,
            sample_i=int(sample),
            clip_i=int(clip),
            tokens_i=int(tokens),
            outputs=2,
        )
        x_prev.setType(x.type())
        a.setType(h.type().with_sizes([None, None, None]))
        return x_prev, a


class FusedOps:
    """The operators :class:`dssp_train.model.mamba.Mamba` and the point encoder call when their ``fused_ops`` is
    set."""

    @staticmethod
    def selective_scan(x, dt, B, C, z, A, D, h0, state_at=None):  # noqa: N803
        """x, dt, z (batch, L, E), B, C (batch, L, n), A (E, n), D (E,), h0 (batch, E, n) → y (batch, L, E), h (batch, E, n)
        the state after the last token (after ``state_at`` tokens)."""
        return _SelectiveScan.apply(x, dt, B, C, z, A, D, h0, state_at or 0)  # a traced call takes no None: 0, the last

    @staticmethod
    def layer_norm_max_over_points(x, norm: torch.nn.LayerNorm):
        """x (batch, P, F) → (batch, F): the max over the points of ``norm`` (over F) of each."""
        return _LayerNormMaxOverPoints.apply(x, norm.weight, norm.bias, norm.eps)

    @staticmethod
    def ddim_step(den, schedule, h, x, mod, t: int, num_steps: int | None, tokens: bool):
        """The end of DDIM step t (of ``num_steps``) of the denoiser ``den`` under ``schedule``: its last block's output
        on the action tokens h (B, H, d), x_t (B, H, A) and the step's one-row :class:`Modulation` ``mod`` → (x_prev
        (B, H, A), the next step's action tokens (B, H, d); (B, H, 0) without ``tokens``: the chunk's last step)."""
        if mod.final.shape[0] != 1:
            raise ValueError(f"DdimStep takes one row of AdaLN parameters (the step's), got {mod.final.shape[0]}")
        a_t, a_prev = schedule.ddim_coefficients(t, num_steps)
        cfg = schedule.cfg
        return _DdimStep.apply(
            h,
            x,
            den.norm_f.weight,
            mod.final[0],
            den.action_out.weight,
            den.action_out.bias,
            den.action_in.weight.t(),
            den.action_in.bias,
            den.action_pos,
            den.norm_f.eps,
            a_t,
            a_prev,
            cfg.prediction_type == "sample",
            cfg.clip_sample,
            tokens,
        )

    @staticmethod
    def causal_conv(x, state, weight, bias, state_at=None):
        """x (batch, L, E), state (batch, E, W), weight (W, E), bias (E,) → silu(conv) (batch, L, E), new state (batch, E, W)
        after the last token (after ``state_at`` tokens)."""
        return _CausalConv.apply(x, state, weight, bias, state_at or 0)


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


# ------------------------------------------------------------------------------------------------ the whole block
def quantize_weight(w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """W (n, k) fp32 → (int8 (n, k), scale (n,)): symmetric per output row, scale = max|W[j]| / 127 (1 for a row of
    zeros), rounded half to even — as ``dssp_deploy/kernel/qgemm.h`` ``pack`` quantizes."""
    w = w.detach().float()
    scale = w.abs().amax(dim=1) / 127.0
    scale = torch.where(scale > 0, scale, torch.ones_like(scale))
    q = torch.round(w / scale[:, None]).clamp(-127, 127).to(torch.int8)
    return q, scale


def quantize_rows(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """x (m, k) fp32 → (uint8 values as float (m, k), scale (m,), zero point (m,)): per row, asymmetric, the range
    holding 0 — as ``qgemm.h`` ``quantize_rows`` does before every product."""
    lo = x.amin(dim=1).clamp(max=0.0)
    hi = x.amax(dim=1).clamp(min=0.0)
    scale = (hi - lo) / 255.0
    scale = torch.where(scale > 0, scale, torch.ones_like(scale))
    zero = torch.round(-lo / scale).clamp(0, 255)
    q = torch.round(x / scale[:, None] + zero[:, None]).clamp(0, 255)
    return q, scale, zero


def q8_linear(x: torch.Tensor, q: torch.Tensor, scale: torch.Tensor, bias: torch.Tensor | None = None) -> torch.Tensor:
    """x (..., k) @ W.T with W as int8 rows ``q`` (n, k) and their ``scale`` (n,), the activations quantized per row:
    the product ``MambaBlockQ8`` computes (the integer sums exact, here in float64)."""
    shape = x.shape
    xq, xs, zero = quantize_rows(x.reshape(-1, shape[-1]).float())
    acc = (xq - zero[:, None]).double() @ q.double().t()
    y = (acc * (xs[:, None].double() * scale[None, :].double())).float()
    if bias is not None:
        y = y + bias
    return y.reshape(*shape[:-1], q.shape[0])


def rms_norm(x: torch.Tensor, weight: torch.Tensor, eps: float) -> torch.Tensor:
    return x * torch.rsqrt(x.pow(2).mean(-1, keepdim=True) + eps) * weight


def block_reference(
    a,
    conv_state,
    ssm_state,
    mod,
    norm_w,
    in_q,
    in_s,
    conv_w,
    conv_b,
    xp_q,
    xp_s,
    dt_q,
    dt_s,
    dt_b,
    A,
    D,
    out_q,
    out_s,
    norm2_w,
    fc1_q,
    fc1_s,
    fc2_q,
    fc2_s,
    eps,
    plain: int = 0,
):  # noqa: N803
    """What ``ai.dssp::MambaBlockQ8`` computes, in PyTorch: a (B, L, d) → (a (B, L, d), the mixer's state after the L
    tokens: conv (B, E, W), ssm (B, E, n)). ``mod`` (3, d) is the AdaLN row (shift, scale, gate) of the action
    tokens; (0, d) for the prefix alone (no modulation, gate 1). ``plain``: the first tokens that are the prefix
    (unmodulated, gate 1) before the action tokens, in one pass; the states are then those after the prefix, which
    the later DDIM steps start from. States (B, 0, W) and (B, 0, n) are zeros. Shapes: :class:`QuantizedMambaBlock`."""
    E, R = conv_w.shape[1], dt_q.shape[1]  # noqa: N806
    n = A.shape[1]
    if conv_state.shape[1] == 0:  # empty: a start from zeros
        conv_state = a.new_zeros(a.shape[0], E, conv_w.shape[0])
    if ssm_state.shape[1] == 0:
        ssm_state = a.new_zeros(a.shape[0], E, n)
    h = rms_norm(a, norm_w, eps)
    if mod.shape[0]:
        shift, scale, gate = mod.unbind(0)  # (d,) each
        actions = torch.arange(a.shape[1]) >= plain  # (L,): the tokens AdaLN and the gate act on
        h = torch.where(actions[:, None], h * (1 + scale) + shift, h)
        gate = torch.where(actions[:, None], gate, torch.ones_like(gate))  # (L, d)
    state_at = plain if mod.shape[0] and 0 < plain < a.shape[1] else None  # the states after the prefix's tokens
    xz = q8_linear(h, in_q, in_s)
    x, z = xz[..., :E], xz[..., E:]
    x, conv_after = causal_conv(x, conv_state, conv_w.t().unsqueeze(1), conv_b, state_at)
    dbc = q8_linear(x, xp_q, xp_s)
    dt_in, Bm, Cm = torch.split(dbc, [R, n, n], dim=-1)  # noqa: N806
    dt = q8_linear(dt_in, dt_q, dt_s, dt_b)
    y, ssm_after = selective_scan(x, dt, Bm, Cm, z, A, D, ssm_state, linear_scan_unrolled, state_at)
    out = q8_linear(y, out_q, out_s)
    a = a + (gate * out if mod.shape[0] else out)
    if fc1_q.numel():
        u, g = q8_linear(rms_norm(a, norm2_w, eps), fc1_q, fc1_s).chunk(2, dim=-1)
        a = a + q8_linear(u * torch.nn.functional.silu(g), fc2_q, fc2_s)
    return a, conv_after, ssm_after


class _MambaBlockQ8(torch.autograd.Function):
    @staticmethod
    def forward(ctx, *inputs):
        *tensors, eps, state_out, plain = inputs
        a, conv, ssm = block_reference(*tensors, eps, plain)
        if not state_out:  # as the operator allocates them: empty
            conv, ssm = conv[:, :0], ssm[:, :0]
        return a, conv, ssm

    @staticmethod
    def symbolic(g, *inputs):
        *tensors, eps, state_out, plain = inputs
        a, conv, ssm = g.op(
            f"{DOMAIN}::{BLOCK_OP}",
            *tensors,
            eps_f=float(eps),
            state_out_i=int(state_out),
            plain_i=int(plain),
            outputs=3,
        )
        a.setType(tensors[0].type())
        conv.setType(tensors[1].type())
        ssm.setType(tensors[2].type())
        return a, conv, ssm


class QuantizedMambaBlock(torch.nn.Module):
    """A denoiser block (:class:`dssp_train.model.denoiser.DenoiserBlock`, Mamba mixer, no MLP or the gated one) as
    one ``ai.dssp::MambaBlockQ8`` node, its matrices as int8 rows with per-row scales — on the prefix (once per
    chunk) and on the action tokens (every DDIM step), both reading the same weights.

    :meth:`prefix`: p (B, L_p, d) → (p + mixer(norm(p)) + mlp, the state after it (conv (B, E, W), ssm (B, E, n))).
    forward(a (B, H, d), prefix state, shift, scale, gate (1, d)) → a (B, H, d): ``a + gate *
    mixer(modulate(norm(a), shift, scale))`` from the prefix's state, then ``+ mlp(norm2(.))``.
    Weights: in_proj (2E, d), conv (W, E) + bias (E), x_proj (R + 2n, E), dt_proj (E, R) + bias (E), A (E, n),
    D (E), out_proj (d, E), fc1 (2h, d), fc2 (d, h) — the int8 ones with their scales; the MLP's are empty
    (shape (0, 0)) when the block has none.
    """

    def __init__(self, block):
        super().__init__()
        mixer = block.mixer
        self.eps = block.norm.eps
        self.d_state, self.d_conv = mixer.d_state, mixer.d_conv
        self.register_buffer("norm_w", block.norm.weight.detach().clone())
        for name, linear in (
            ("in", mixer.in_proj),
            ("xp", mixer.x_proj),
            ("dt", mixer.dt_proj),
            ("out", mixer.out_proj),
        ):
            q, s = quantize_weight(linear.weight)
            self.register_buffer(f"{name}_q", q)
            self.register_buffer(f"{name}_s", s)
        self.register_buffer("conv_w", mixer.conv1d.weight[:, 0].t().detach().clone())  # (W, E)
        self.register_buffer("conv_b", mixer._conv_bias().detach().clone())
        self.register_buffer("dt_b", mixer.dt_proj.bias.detach().clone())
        self.register_buffer("A", -torch.exp(mixer.A_log.detach().float()))
        self.register_buffer("D", mixer.D.detach().clone())
        self.register_buffer("no_mod", torch.zeros(0, block.norm.weight.shape[0]))
        if block.mlp_kind == "gated":
            self.register_buffer("norm2_w", block.norm2.weight.detach().clone())
            for name, linear in (("fc1", block.mlp.fc1), ("fc2", block.mlp.fc2)):
                q, s = quantize_weight(linear.weight)
                self.register_buffer(f"{name}_q", q)
                self.register_buffer(f"{name}_s", s)
        else:
            self.register_buffer("norm2_w", torch.zeros(0))
            for name in ("fc1", "fc2"):
                self.register_buffer(f"{name}_q", torch.zeros((0, 0), dtype=torch.int8))
                self.register_buffer(f"{name}_s", torch.zeros(0))

    @staticmethod
    def fits(block) -> bool:
        """Whether the block can run as one node: a Mamba mixer, no MLP or the gated one (DiT's MLP has its own AdaLN)."""
        return isinstance(block.mixer, Mamba) and block.mlp_kind in ("none", "gated")

    def _run(self, a, conv_state, ssm_state, mod, state_out: bool, plain: int = 0):
        return _MambaBlockQ8.apply(
            a,
            conv_state,
            ssm_state,
            mod,
            self.norm_w,
            self.in_q,
            self.in_s,
            self.conv_w,
            self.conv_b,
            self.xp_q,
            self.xp_s,
            self.dt_q,
            self.dt_s,
            self.dt_b,
            self.A,
            self.D,
            self.out_q,
            self.out_s,
            self.norm2_w,
            self.fc1_q,
            self.fc1_s,
            self.fc2_q,
            self.fc2_s,
            self.eps,
            state_out,
            plain,
        )

    def _zero_state(self, x):
        """Empty states (B, 0, W) and (B, 0, n): the operator starts from zeros without reading any."""
        return x.new_zeros(x.shape[0], 0, self.d_conv), x.new_zeros(x.shape[0], 0, self.d_state)

    def prefix(self, p):
        p, conv, ssm = self._run(p, *self._zero_state(p), self.no_mod, True)
        return p, (conv, ssm)

    def joint(self, seq, p, shift, scale, gate, state_out: bool):
        """The prefix and the action tokens, seq = [p, a] (B, L_p + H, d), in one pass (one DDIM step with the timestep
        decoupled: the prefix unmodulated) → (seq after the block, the prefix's state after it: conv (B, E, W), ssm
        (B, E, n) for the later steps, or both (B, 0, .) without ``state_out``). ``p`` is the prefix as it entered the
        first such block: its length, a constant of the model, is the node's attribute, and every block takes its
        zero states from its batch (one shape computation the graph shares). The caller keeps seq whole between
        blocks, so the graph holds no split and join per block."""
        mod = torch.cat([shift, scale, gate], dim=0)
        seq, conv, ssm = self._run(seq, *self._zero_state(p), mod, state_out, int(p.shape[1]))
        return seq, (conv, ssm)

    def forward(self, a, state, shift, scale, gate):
        conv_state, ssm_state = state
        mod = torch.cat([shift, scale, gate], dim=0)  # (3, d): one timestep's row of the table
        return self._run(a, conv_state, ssm_state, mod, False)[0]


def fitting_blocks(module: torch.nn.Module) -> list:
    """The denoiser blocks of ``module`` that can run as one node (:meth:`QuantizedMambaBlock.fits`)."""
    return [b for b in module.modules() if isinstance(b, DenoiserBlock) and QuantizedMambaBlock.fits(b)]


def use_fused_blocks(module: torch.nn.Module) -> int:
    """Give every denoiser block of ``module`` that fits its :class:`QuantizedMambaBlock`; returns how many."""
    blocks = fitting_blocks(module)
    for block in blocks:
        block.fused_block = QuantizedMambaBlock(block)
    return len(blocks)
