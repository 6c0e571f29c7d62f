"""Mamba in pure PyTorch: one set of weights, sequence path == recurrent path, mamba-ssm layout."""

import math

import pytest
import torch
import torch.nn.functional as F

from dssp_train.model.mamba import Mamba
from dssp_train.model.mamba_stack import MambaStack
from dssp_train.model.selective_scan import linear_scan, linear_scan_unrolled


# Parameter names and shapes of mamba_ssm.Mamba(d_model, d_state, d_conv, expand) (mamba_simple.py).
def mamba_ssm_shapes(d_model, d_state, d_conv, expand):
    d_inner = expand * d_model
    dt_rank = math.ceil(d_model / 16)
    return {
        "in_proj.weight": (2 * d_inner, d_model),
        "conv1d.weight": (d_inner, 1, d_conv),
        "conv1d.bias": (d_inner,),
        "x_proj.weight": (dt_rank + 2 * d_state, d_inner),
        "dt_proj.weight": (d_inner, dt_rank),
        "dt_proj.bias": (d_inner,),
        "A_log": (d_inner, d_state),
        "D": (d_inner,),
        "out_proj.weight": (d_model, d_inner),
    }


@pytest.mark.parametrize("d_model,d_state", [(32, 16), (512, 64)])
def test_parameter_names_and_shapes_match_mamba_ssm(d_model, d_state):
    m = Mamba(d_model, d_state=d_state)
    got = {k: tuple(v.shape) for k, v in m.state_dict().items()}
    assert got == mamba_ssm_shapes(d_model, d_state, 4, 2)


def test_initialisation_matches_mamba_ssm():
    torch.manual_seed(0)
    m = Mamba(64, d_state=16)
    assert torch.equal(m.A_log, torch.log(torch.arange(1, 17, dtype=torch.float32)).repeat(128, 1))
    assert torch.equal(m.D, torch.ones(128))
    dt = F.softplus(m.dt_proj.bias)
    assert dt.min() >= 1e-3 * 0.999 and dt.max() <= 0.1 * 1.001
    bound = m.dt_rank**-0.5
    assert m.dt_proj.weight.abs().max() <= bound and m.dt_proj.weight.abs().max() > 0.5 * bound
    assert m.A_log._no_weight_decay and m.D._no_weight_decay


def test_stack_keys_follow_mixer_model_layout():
    keys = set(MambaStack(32, 2, d_state=8).state_dict())
    assert "layers.0.mixer.in_proj.weight" in keys and "layers.1.norm.weight" in keys and "norm_f.weight" in keys


def test_stack_out_proj_rescaled_by_layer_count():
    torch.manual_seed(0)
    deep = MambaStack(64, 16, d_state=8).layers[0].mixer.out_proj.weight.std()
    torch.manual_seed(0)
    shallow = MambaStack(64, 1, d_state=8).layers[0].mixer.out_proj.weight.std()
    assert (deep / shallow).item() == pytest.approx(1 / 4, rel=0.1)


@pytest.mark.parametrize("length", [1, 7, 1000])
def test_stepping_equals_sequence_path(length):
    torch.manual_seed(length)
    stack = MambaStack(32, 2, d_state=16).eval()
    x = torch.randn(2, length, 32)
    with torch.no_grad():
        y_seq, state_seq = stack(x)
        state = stack.init_state(2)
        outs = []
        for t in range(length):
            y, state = stack.step(x[:, t], state)
            outs.append(y)
    assert (torch.stack(outs, 1) - y_seq).abs().max().item() <= 1e-5
    for (c1, s1), (c2, s2) in zip(state, state_seq):
        assert (c1 - c2).abs().max().item() <= 1e-5
        assert (s1 - s2).abs().max().item() <= 1e-5


def test_sequence_path_continues_from_a_state():
    torch.manual_seed(1)
    m = Mamba(16, d_state=4)
    x = torch.randn(3, 11, 16)
    with torch.no_grad():
        full, _ = m(x)
        first, state = m(x[:, :4])
        rest, _ = m(x[:, 4:], state)
    assert torch.allclose(torch.cat([first, rest], 1), full, atol=1e-6)


@pytest.mark.parametrize("length", [1, 2, 3, 8, 17])
@pytest.mark.parametrize("with_state", [False, True], ids=["fresh", "continued"])
def test_unrolled_path_equals_sequence_path_and_stepping(length, with_state):
    """forward_unrolled == forward == step over the tokens: outputs (B, L, d) and the final state."""
    torch.manual_seed(length)
    m = Mamba(32, d_state=16)
    u = torch.randn(2, length, 32)
    with torch.no_grad():
        state = m(torch.randn(2, 5, 32))[1] if with_state else None
        unrolled, (conv_u, ssm_u) = m.forward_unrolled(u, state)
        sequence, (conv_s, ssm_s) = m(u, state)
        stepped, step_state = [], state or m.init_state(2)
        for t in range(length):
            y, step_state = m.step(u[:, t], step_state)
            stepped.append(y)
    for out, (conv, ssm) in ((sequence, (conv_s, ssm_s)), (torch.stack(stepped, 1), step_state)):
        assert (unrolled - out).abs().max().item() <= 1e-5
        assert (conv_u - conv).abs().max().item() <= 1e-5 and (ssm_u - ssm).abs().max().item() <= 1e-5


@pytest.mark.parametrize("length", [1, 2, 5, 12, 33, 257])
def test_scan_forward_and_gradients_equal_sequential_reference(length):
    torch.manual_seed(length)
    a = torch.rand(2, length, 3, 4, dtype=torch.float64, requires_grad=True)
    b = torch.randn(2, length, 3, 4, dtype=torch.float64, requires_grad=True)
    h0 = torch.randn(2, 3, 4, dtype=torch.float64, requires_grad=True)
    w = torch.randn(2, length, 3, 4, dtype=torch.float64)
    fast = linear_scan(a, b, h0)
    ref = linear_scan_unrolled(a, b, h0)
    assert (fast - ref).abs().max().item() < 1e-12
    g_fast = torch.autograd.grad((fast * w).sum(), (a, b, h0))
    g_ref = torch.autograd.grad((ref * w).sum(), (a, b, h0))
    for gf, gr in zip(g_fast, g_ref):
        assert (gf - gr).abs().max().item() < 1e-12


def test_scan_passes_gradcheck():
    torch.manual_seed(0)
    a = torch.rand(1, 6, 2, 2, dtype=torch.float64, requires_grad=True)
    b = torch.randn(1, 6, 2, 2, dtype=torch.float64, requires_grad=True)
    h0 = torch.randn(1, 2, 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(linear_scan, (a, b, h0))


def naive_mamba(m: Mamba, u: torch.Tensor) -> torch.Tensor:
    """mamba_simple.py's math token by token, straight from the parameters."""
    batch, length, _ = u.shape
    x, z = m.in_proj(u).chunk(2, dim=-1)
    x = F.silu(m.conv1d(x.transpose(1, 2))[..., :length]).transpose(1, 2)
    dt, B, C = torch.split(m.x_proj(x), [m.dt_rank, m.d_state, m.d_state], dim=-1)
    dt = F.softplus(m.dt_proj(dt))
    A = -torch.exp(m.A_log)
    h = torch.zeros(batch, m.d_inner, m.d_state)
    ys = []
    for t in range(length):
        h = torch.exp(dt[:, t, :, None] * A) * h + (dt[:, t] * x[:, t])[..., None] * B[:, t, None, :]
        ys.append((h * C[:, t, None, :]).sum(-1) + m.D * x[:, t])
    y = torch.stack(ys, 1) * F.silu(z)
    return m.out_proj(y)


def test_gradients_of_the_layer_equal_a_naive_sequential_layer():
    torch.manual_seed(3)
    m = Mamba(16, d_state=8)
    u = torch.randn(2, 40, 16)
    out_fast, _ = m(u)
    out_ref = naive_mamba(m, u)
    assert (out_fast - out_ref).abs().max().item() < 1e-5
    w = torch.randn_like(out_fast)
    g_fast = torch.autograd.grad((out_fast * w).sum(), list(m.parameters()))
    g_ref = torch.autograd.grad((out_ref * w).sum(), list(m.parameters()))
    for (name, _), gf, gr in zip(m.named_parameters(), g_fast, g_ref):
        assert (gf - gr).abs().max().item() <= 1e-4 * max(1.0, gr.abs().max().item()), name
