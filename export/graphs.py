"""The two torch modules that become the exported graphs, and the unrolled Mamba they share.

- :class:`HistoryStepGraph` — run once per control tick. Raw observation and the recurrent state of
  every history layer in; ``z_t``, ``c_t`` and the new state out. Normalisation happens inside, through
  ``DSSPPolicy.encode_observations``; the history update is ``HistoryEncoder.step`` (``Mamba.step``).
- :class:`DenoiserGraph` — run once per action chunk. ``c_t``, the recent ``z`` tokens and the initial
  noise in; the action chunk in raw units out, after K DDIM steps unrolled in the graph.

Everything the diffusion timestep touches is folded into constants at construction: with K fixed, the
timestep embedding, every block's AdaLN (shift, scale, gate), the final AdaLN and the DDIM coefficients
depend on nothing the graph receives. With ``timestep_decoupled`` the prefix ``[c_t, z...]`` is never
modulated, so it runs through the denoiser once per call and its per-layer recurrent state is reused by
all K steps (the math of ``Denoiser.encode_prefix`` / ``Denoiser.denoise``).

Mamba's sequence path (``Mamba.forward``) uses a parallel scan with in-place strided views that does not
export. :func:`mamba_tokens` computes the same layer over a short, fixed number of tokens: every per-token
projection runs on all tokens at once and only the recurrence ``h_t = exp(dt A) h_{t-1} + dt B x_t`` is
unrolled, one broadcast multiply-add per token, with functional (``cat``) state updates and no einsum.
Unrolling ``Mamba.step`` token by token exports as well (the history graph is exactly that, for one
token), but for the robotwin denoiser it gave 44.6k ONNX nodes instead of 9.3k and ran about 2x slower
in ONNX Runtime (262 vs ~120 ms per chunk, 2 threads): every projection becomes a matrix-vector product.

Shapes (B batch, P points, C = ``point_dim``, S state, A action, d width, N recent tokens, H horizon,
L_p = prefix length, E = d_inner = expand * d, n = d_state, W = d_conv):
    history:  point_cloud (B, P, C), agent_pos (B, S), per layer conv (B, E, W) + ssm (B, E, n)
              → z_t (B, d), c_t (B, d), per layer conv (B, E, W) + ssm (B, E, n)
    denoiser: c_t (B, d), z_recent (B, N, d), noise (B, H, A) → action (B, H, A)
"""

from __future__ import annotations

import copy

import torch
import torch.nn.functional as F
from torch import nn

from dssp_data.errors import ConfigError
from dssp_train.model.denoiser import modulate
from dssp_train.model.mamba import Mamba, MambaState
from dssp_train.model.policy import DSSPPolicy


def check_exportable(policy: DSSPPolicy) -> None:
    """Refuse history variants whose streaming state grows or is not a fixed recurrent state."""
    cfg = policy.cfg
    if cfg.use_history and not policy.history_encoder.is_recurrent:
        variant = f"history_backbone={cfg.history_backbone}, history_window={cfg.history_window}"
        raise ConfigError(
            f"this run's history encoder ({variant}) has no constant-size recurrent state; export supports the "
            "Mamba history encoder over the full history (history_window 0) and the reactive baseline (use_history false)"
        )


def pruned_copy(policy: DSSPPolicy, keep: tuple[str, ...]) -> DSSPPolicy:
    """A copy of ``policy`` with only the ``keep`` submodules (and the normalisers).

    A trace stores every weight of the module it traces, used or not: without pruning each TorchScript
    archive would carry the whole policy.
    """
    pruned = copy.deepcopy(policy)
    for name in ("obs_encoder", "history_encoder", "dynamics", "denoiser"):
        if name not in keep:
            setattr(pruned, name, None)
    return pruned.eval()


def state_names(n_layers: int) -> list[str]:
    """Input names of the recurrent state, per layer: conv_state_i, ssm_state_i."""
    return [f"{kind}_state_{i}" for i in range(n_layers) for kind in ("conv", "ssm")]


# --------------------------------------------------------------- unrolled Mamba
def mamba_tokens(mixer: Mamba, u: torch.Tensor, state: MambaState | None) -> tuple[torch.Tensor, MambaState]:
    """``Mamba.forward`` over a few tokens, with the scan unrolled (exportable).

    Args:
        mixer: the layer whose weights to use.
        u: (B, L, d) tokens; L is small and fixed (prefix or action tokens).
        state: ``(conv (B, E, W), ssm (B, E, n))`` to continue from, or None for a fresh start (zeros).
    Returns:
        out (B, L, d) and the state after the last token.
    """
    length = u.shape[1]
    x, z = mixer.in_proj(u).chunk(2, dim=-1)  # (B, L, E) each
    x = x.transpose(1, 2)  # (B, E, L)
    if state is None:
        x_ext, h = F.pad(x, (mixer.d_conv, 0)), None  # a fresh start: zero conv inputs, zero SSM state
    else:
        x_ext, h = torch.cat([state[0], x], dim=-1), state[1]  # (B, E, W + L)
    new_conv = x_ext[:, :, length:]  # the last W conv inputs
    x = F.conv1d(x_ext[:, :, 1:], mixer.conv1d.weight, mixer.conv1d.bias, groups=mixer.d_inner)
    x = F.silu(x).transpose(1, 2)  # (B, L, E)

    dt, b, c = mixer._ssm_params(x)  # (B, L, E), (B, L, n), (B, L, n)
    a = -torch.exp(mixer.A_log.float())  # (E, n)
    decay = torch.exp(dt.unsqueeze(-1) * a)  # (B, L, E, n)
    drive = (dt * x).unsqueeze(-1) * b.unsqueeze(2)  # (B, L, E, n)
    if h is not None:
        h = h.unsqueeze(1)  # (B, 1, E, n)
    # The recurrence, one token at a time: two elementwise ops per token on (B, 1, E, n) slices.
    hs = []
    for decay_i, drive_i in zip(decay.split(1, dim=1), drive.split(1, dim=1)):
        h = drive_i if h is None else decay_i * h + drive_i
        hs.append(h)
    y = torch.matmul(torch.cat(hs, dim=1), c.unsqueeze(-1))[..., 0]  # (B, L, E)
    h = h[:, 0]  # (B, E, n); indexing, not squeeze: squeeze of a dynamic dim exports as an If node
    y = (y + mixer.D * x) * F.silu(z)
    return mixer.out_proj(y), (new_conv, h)


# ---------------------------------------------------------------- history step
class HistoryStepGraph(nn.Module):
    """One control tick: raw observation (+ history state) → z_t (, c_t, new state).

    forward(point_cloud (B, P, C), agent_pos (B, S), conv_state_0 (B, E, W), ssm_state_0 (B, E, n), ...)
        → z_t (B, d), c_t (B, d), conv_state_0_out (B, E, W), ssm_state_0_out (B, E, n), ...
    Without a history encoder (the reactive baseline): forward(point_cloud, agent_pos) → z_t.
    Start an episode with all states zero.
    """

    def __init__(self, policy: DSSPPolicy):
        super().__init__()
        check_exportable(policy)
        self.policy = pruned_copy(policy, ("obs_encoder", "history_encoder"))
        self.has_history = policy.cfg.use_history

    def forward(self, point_cloud: torch.Tensor, agent_pos: torch.Tensor, *states: torch.Tensor):
        z_t = self.policy.encode_observations(point_cloud, agent_pos)  # (B, d)
        if not self.has_history:
            return z_t
        layer_states = [(states[2 * i], states[2 * i + 1]) for i in range(len(states) // 2)]
        c_t, new_states = self.policy.history_encoder.step(z_t, layer_states)
        return (z_t, c_t, *[s for pair in new_states for s in pair])


# -------------------------------------------------------------------- denoiser
class DenoiserGraph(nn.Module):
    """K DDIM steps from noise to a raw action chunk, every timestep-only quantity a constant.

    forward(c_t (B, d) [if use_history], z_recent (B, N, d) [if use_recent_states], noise (B, H, A))
        → action (B, H, A) in raw units.
    ``z_recent`` holds the last N ``z_t`` from the history step, oldest first; at the start of an
    episode the first observation's ``z`` repeats (as in training).
    """

    def __init__(self, policy: DSSPPolicy, num_steps: int):
        super().__init__()
        cfg = policy.cfg
        self.policy = policy = pruned_copy(policy, ("denoiser",))
        self.use_history = cfg.use_history
        self.use_recent = cfg.use_recent_states
        self.decoupled = cfg.timestep_decoupled
        self.num_steps = num_steps
        self.timesteps = policy.schedule.inference_timesteps(num_steps)
        den = policy.denoiser
        with torch.no_grad():
            layer_mod, final_mod = [], []
            for t in self.timesteps:
                temb = den.time_embed(torch.full((1,), t, dtype=torch.long))  # (1, d)
                layer_mod.append(torch.stack([torch.cat(layer.modulation(temb).chunk(3, dim=-1)) for layer in den.layers]))
                final_mod.append(torch.cat(den.final_modulation(temb).chunk(2, dim=-1)))
        # (K, n_layers, 3, d): shift, scale, gate of every block at every step; (K, 2, d): final shift, scale.
        self.register_buffer("layer_mod", torch.stack(layer_mod).clone(), persistent=False)
        self.register_buffer("final_mod", torch.stack(final_mod).clone(), persistent=False)
        # Folded: the timestep MLP and the AdaLN projections are not part of the graph.
        den.time_embed = den.final_modulation = None
        for layer in den.layers:
            layer.modulation = None

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        it = iter(inputs)
        context = next(it) if self.use_history else None
        recent = next(it) if self.use_recent else None
        noise = next(it)
        prefix = self.policy.build_prefix(context, recent)  # (B, L_p, d)
        prefix_states = self.encode_prefix(prefix) if self.decoupled else None
        x = noise
        for k, t in enumerate(self.timesteps):
            if self.decoupled:
                x0 = self.denoise_cached(prefix_states, x, k)
            else:
                x0 = self.denoise_full(prefix, x, k)
            x = self.policy.schedule.ddim_step(x0, t, x, self.num_steps)
        return self.policy.normalizers["action"].unnormalize(x)

    def encode_prefix(self, prefix: torch.Tensor) -> list[MambaState]:
        """Prefix (B, L_p, d) → the (conv, ssm) state of every layer after it (``Denoiser.encode_prefix``)."""
        states = []
        p = prefix
        for layer in self.policy.denoiser.layers:
            out, state = mamba_tokens(layer.mixer, layer.norm(p), None)
            p = p + out
            states.append(state)
        return states

    def denoise_cached(self, prefix_states: list[MambaState], x_tau: torch.Tensor, k: int) -> torch.Tensor:
        """x0_hat (B, H, A) at step k from the cached prefix states (``Denoiser.denoise``)."""
        den = self.policy.denoiser
        a = den.embed_actions(x_tau)  # (B, H, d)
        for layer, mod, state in zip(den.layers, self.layer_mod[k], prefix_states):
            out, _ = mamba_tokens(layer.mixer, modulate(layer.norm(a), mod[0:1], mod[1:2]), state)
            a = a + mod[2] * out
        return self.readout(a, k)

    def denoise_full(self, prefix: torch.Tensor, x_tau: torch.Tensor, k: int) -> torch.Tensor:
        """x0_hat (B, H, A) at step k with the prefix modulated too (``Denoiser.forward``, not decoupled)."""
        den = self.policy.denoiser
        p, a = prefix, den.embed_actions(x_tau)
        n_prefix = p.shape[1]
        for layer, mod in zip(den.layers, self.layer_mod[k]):
            shift, scale, gate = mod[0:1], mod[1:2], mod[2]
            h = torch.cat([modulate(layer.norm(p), shift, scale), modulate(layer.norm(a), shift, scale)], dim=1)
            out, _ = mamba_tokens(layer.mixer, h, None)
            p = p + gate * out[:, :n_prefix]
            a = a + gate * out[:, n_prefix:]
        return self.readout(a, k)

    def readout(self, a: torch.Tensor, k: int) -> torch.Tensor:
        """Action tokens (B, H, d) → x0_hat (B, H, A) with the final AdaLN of step k."""
        den = self.policy.denoiser
        shift, scale = self.final_mod[k, 0:1], self.final_mod[k, 1:2]
        return den.action_out(modulate(den.norm_f(a), shift, scale))
