"""Denoiser f_theta: a stack of AdaLN blocks over ``[c_t, z_{t-N+1}, ..., z_t, x_tau tokens]`` that predicts x_0.

The diffusion timestep tau enters **only the action tokens**, through AdaLN in every block
(shift, scale and a residual gate from a zero-initialised projection of the timestep embedding);
the prefix tokens are never modulated, so the prefix is a stable condition for every denoising step
and — because the mixer is causal — its per-layer state can be computed once per chunk and
reused for all K DDIM steps (:meth:`Denoiser.encode_prefix` / :meth:`Denoiser.denoise`).
The timestep reaches the blocks only through its AdaLN parameters (:meth:`Denoiser.modulation`), so
sampling computes them once for the K DDIM timesteps and each step looks its row up
(:meth:`Denoiser.forward_modulated` / :meth:`Denoiser.denoise_modulated`).
With ``timestep_decoupled=False`` (paper Table 5 ablation) the prefix is modulated too.

Each block's mixer (``model.denoiser_backbone``) is Mamba (the paper's; the per-layer state is the
recurrent ``(conv_state, ssm_state)``) or causal multi-head self-attention with rotary positions (Table 5's
"w/ Trans.", :class:`dssp_train.model.attention.CausalSelfAttention`; the per-layer state is the prefix's
key/value cache). The mixer is optionally followed by an MLP (``model.denoiser_mlp``): mamba-ssm's
GatedMLP (its ``Block`` with ``mlp_cls=GatedMLP``; unmodulated) or DiT's MLP (with its own AdaLN shift,
scale and gate on the action tokens, so a block's modulation has 6 rows instead of 3). The MLP is
token-wise, so the prefix caching above holds.

Shapes: prefix (B, L_p, d), x_tau (B, H, A), timesteps (B,) → x0_hat (B, H, A).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from dssp_train.config import ModelConfig
from dssp_train.model.attention import CausalSelfAttention, init_attention_weights
from dssp_train.model.history_encoder import sinusoidal_embedding
from dssp_train.model.mamba import Mamba
from dssp_train.model.mamba_stack import RMSNorm, init_mamba_weights

# One layer's cached prefix: Mamba's (conv_state, ssm_state) (MambaState), or attention's (k, v) cache (KVCache).
MixerState = tuple[torch.Tensor, torch.Tensor]


class Modulation(NamedTuple):
    """AdaLN parameters for T timesteps: T = B (one per sample) or T = 1 (shared by the batch).

    layers (T, n_layers, R, d): shift, scale, gate of every block's mixer (R = 3), then of its MLP (R = 6, DiT's
    MLP); final (T, 2, d): shift, scale of the readout.
    """

    layers: torch.Tensor
    final: torch.Tensor

    def block(self, i: int) -> tuple[torch.Tensor, ...]:
        """Shift, scale, gate (T, d) of block i's mixer (, and of its MLP)."""
        return self.layers[:, i].unbind(1)

    def at(self, k: int) -> Modulation:
        """Row k of a table (timestep k of K) as a one-row Modulation: (1, n_layers, 3, d), (1, 2, d)."""
        return Modulation(self.layers[k : k + 1], self.final[k : k + 1])


def mixer_path(mixer: Mamba | CausalSelfAttention, unrolled: bool):
    """The sequence path of ``mixer`` to run: ``forward`` (Mamba: parallel scan) or ``forward_unrolled`` (traceable)."""
    return mixer.forward_unrolled if unrolled else mixer


def modulate(x: torch.Tensor, shift: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """AdaLN: x (B, L, d), shift/scale (B, d) or (1, d) → (B, L, d)."""
    return x * (1 + scale.unsqueeze(1)) + shift.unsqueeze(1)


class TimestepEmbedding(nn.Module):
    """tau (B,) → (B, d): sinusoidal features and an MLP."""

    def __init__(self, d_model: int):
        super().__init__()
        self.d_model = d_model
        self.mlp = nn.Sequential(nn.Linear(d_model, 4 * d_model), nn.SiLU(), nn.Linear(4 * d_model, d_model))

    def forward(self, timesteps: torch.Tensor) -> torch.Tensor:
        """timesteps (B,) → (B, d), in the dtype of the weights."""
        return self.mlp(sinusoidal_embedding(timesteps, self.d_model).to(self.mlp[0].weight.dtype))


class GatedMLP(nn.Module):
    """mamba-ssm's GatedMLP: x (..., d) → fc2(y * silu(g)), [y, g] = fc1(x); hidden 8d/3 rounded up to 128, no biases."""

    def __init__(self, d_model: int):
        super().__init__()
        hidden = (int(8 * d_model / 3) + 127) // 128 * 128
        self.fc1 = nn.Linear(d_model, 2 * hidden, bias=False)
        self.fc2 = nn.Linear(hidden, d_model, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y, gate = self.fc1(x).chunk(2, dim=-1)
        return self.fc2(y * F.silu(gate))


class DiTMLP(nn.Module):
    """DiT's MLP: x (..., d) → fc2(gelu_tanh(fc1(x))), hidden 4d, with biases."""

    def __init__(self, d_model: int):
        super().__init__()
        self.fc1 = nn.Linear(d_model, 4 * d_model)
        self.fc2 = nn.Linear(4 * d_model, d_model)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(F.gelu(self.fc1(x), approximate="tanh"))


MLPS = {"gated": GatedMLP, "dit": DiTMLP}


class DenoiserBlock(nn.Module):
    """A pre-norm block — ``norm``, the ``mixer`` (Mamba, or causal self-attention for ``backbone="transformer"``),
    then ``norm2`` and an MLP unless ``mlp`` is "none" — with its AdaLN projection: temb (B, d) → shift, scale,
    gate (B, 3 * d), and the MLP's shift, scale, gate too for "dit" (B, 6 * d).

    The copies export traces into the int8 fused graphs get a submodule ``fused_block``
    (``export.fused_ops.QuantizedMambaBlock``) that does the block's work — on the prefix (its state out), and on the
    action tokens (norm, AdaLN, the Mamba mixer from the prefix's state, the gated residual, the MLP), or on both in
    one pass (one DDIM step with the timestep decoupled) — as one graph node each; no other block has one."""

    def __init__(
        self,
        d_model: int,
        d_state: int,
        d_conv: int,
        expand: int,
        layer_idx: int,
        mlp: str = "none",
        backbone: str = "mamba",
        n_heads: int = 8,
    ):
        super().__init__()
        self.norm = RMSNorm(d_model)
        if backbone == "mamba":
            self.mixer = Mamba(d_model, d_state=d_state, d_conv=d_conv, expand=expand, layer_idx=layer_idx)
        elif backbone == "transformer":
            self.mixer = CausalSelfAttention(d_model, n_heads, layer_idx=layer_idx)
        else:
            raise ValueError(f"denoiser backbone must be 'mamba' or 'transformer', got {backbone!r}")
        self.mlp_kind = mlp
        if mlp != "none":
            self.norm2 = RMSNorm(d_model)
            self.mlp = MLPS[mlp](d_model)
        self.modulation = nn.Sequential(nn.SiLU(), nn.Linear(d_model, (6 if mlp == "dit" else 3) * d_model))

    def mlp_residual(self, x: torch.Tensor, mod: tuple[torch.Tensor, ...] = (), plain: int = 0) -> torch.Tensor:
        """x (B, L, d) → x + MLP(norm2(x)); ``mod``: the MLP's (shift, scale, gate) (B or 1, d) for modulated tokens,
        all but the first ``plain`` (the prefix's, unmodulated, in the same pass: each weight read once)."""
        if self.mlp_kind == "none":
            return x
        h = self.norm2(x)
        if not mod or self.mlp_kind != "dit":
            return x + self.mlp(h)
        shift, scale, gate = mod
        if not plain:
            return x + gate.unsqueeze(1) * self.mlp(modulate(h, shift, scale))
        y = self.mlp(torch.cat([h[:, :plain], modulate(h[:, plain:], shift, scale)], dim=1))
        return x + torch.cat([y[:, :plain], gate.unsqueeze(1) * y[:, plain:]], dim=1)


class Denoiser(nn.Module):
    # Set on the copies export traces into the fused graphs (``export.fused_ops.FusedOps``): its ``ddim_step`` ends a
    # DDIM step (the readout, the update, the next step's action tokens) in one operator; None: the plain modules.
    fused_ops = None

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        d = cfg.d_model
        self.decoupled = cfg.timestep_decoupled
        self.horizon = cfg.horizon
        self.action_in = nn.Linear(cfg.action_dim, d)
        self.action_pos = nn.Parameter(torch.zeros(cfg.horizon, d))
        # training-time real-time chunking: what marks an action token as committed (given clean), else None
        self.committed_embed = nn.Parameter(torch.zeros(d)) if cfg.committed_prefix_max else None
        self.time_embed = TimestepEmbedding(d)
        self.layers = nn.ModuleList(
            DenoiserBlock(
                d,
                cfg.d_state,
                cfg.d_conv,
                cfg.expand,
                i,
                cfg.denoiser_mlp,
                cfg.denoiser_backbone,
                cfg.transformer_heads,
            )
            for i in range(cfg.n_denoiser_layers)
        )
        self.norm_f = RMSNorm(d)
        self.final_modulation = nn.Sequential(nn.SiLU(), nn.Linear(d, 2 * d))
        self.action_out = nn.Linear(d, cfg.action_dim)

        residuals = 1 if cfg.denoiser_mlp == "none" else 2
        self.apply(lambda m: init_mamba_weights(m, cfg.n_denoiser_layers, residuals))
        self.apply(lambda m: init_attention_weights(m, cfg.n_denoiser_layers, residuals))
        nn.init.normal_(self.action_pos, std=0.02)
        for layer in self.layers:
            nn.init.zeros_(layer.modulation[-1].weight)
            nn.init.zeros_(layer.modulation[-1].bias)
        nn.init.zeros_(self.final_modulation[-1].weight)
        nn.init.zeros_(self.final_modulation[-1].bias)

    # ---------------------------------------------------------- AdaLN parameters
    def modulation(self, timesteps: torch.Tensor) -> Modulation:
        """The AdaLN parameters of timesteps (T,): a batch's (T = B), or a DDIM table's (T = K), computed once."""
        temb = self.time_embed(timesteps)  # (T, d)
        count, d = temb.shape
        layers = torch.stack([layer.modulation(temb).view(count, -1, d) for layer in self.layers], dim=1)
        return Modulation(layers, self.final_modulation(temb).view(count, 2, d))

    def fold_timestep(self) -> None:
        """Drop the timestep MLP and the AdaLN projections (an exported graph has the K steps' table as constants)."""
        self.time_embed = self.final_modulation = None
        for layer in self.layers:
            layer.modulation = None

    # ------------------------------------------------------------ full forward
    def forward(
        self, prefix: torch.Tensor, x_tau: torch.Tensor, timesteps: torch.Tensor, committed: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Training path over the whole sequence: prefix (B, L_p, d), x_tau (B, H, A), timesteps (B,) → x0_hat (B, H, A);
        ``committed`` (B, H) 0/1: the action tokens given clean (training-time real-time chunking)."""
        return self.forward_modulated(prefix, x_tau, self.modulation(timesteps), committed=committed)

    def forward_modulated(
        self,
        prefix: torch.Tensor,
        x_tau: torch.Tensor,
        mod: Modulation,
        unrolled: bool = False,
        committed: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """:meth:`forward` with the AdaLN parameters given: prefix (B, L_p, d), x_tau (B, H, A) → x0_hat (B, H, A).

        ``mod`` has B rows or one (shared by the batch); ``unrolled`` runs the mixers' ``forward_unrolled``
        (:meth:`Mamba.forward_unrolled`; the same as ``forward`` for attention); ``committed`` as in :meth:`forward`.
        """
        return self.readout(self.forward_tokens(prefix, self.embed_actions(x_tau, committed), mod, unrolled), mod)

    def forward_tokens(
        self, prefix: torch.Tensor, a: torch.Tensor, mod: Modulation, unrolled: bool = False
    ) -> torch.Tensor:
        """:meth:`forward_modulated` from the action tokens a (B, H, d) (:meth:`embed_actions`) to the last block's
        output on them (B, H, d), before :meth:`readout`."""
        if self.decoupled and self.fused_blocks:  # export's int8 fused graphs: [p, a] whole through every block
            return self.joint_tokens(prefix, a, mod, state_out=False)[0]
        p = prefix
        for i, layer in enumerate(self.layers):
            p, a, _ = self._block(layer, mod.block(i), p, a, unrolled)
        return a

    def _block(
        self,
        layer: DenoiserBlock,
        mod: tuple[torch.Tensor, ...],
        p: torch.Tensor,
        a: torch.Tensor,
        unrolled: bool,
        state_at: int | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, MixerState]:
        """One block over the prefix p (B, L_p, d) and the action tokens a (B, H, d) in one pass of its mixer, ``mod``
        the block's AdaLN rows (:meth:`Modulation.block`) → p, a and the mixer's state after the last token (after
        ``state_at`` tokens: the prefix's, for ``state_at`` = L_p)."""
        shift, scale, gate, *mlp_mod = mod
        n = int(p.shape[1])
        hp = layer.norm(p)
        if not self.decoupled:
            hp = modulate(hp, shift, scale)
        ha = modulate(layer.norm(a), shift, scale)
        out, state = mixer_path(layer.mixer, unrolled)(torch.cat([hp, ha], dim=1), state_at=state_at)
        p, a = (
            p + (out[:, :n] if self.decoupled else gate.unsqueeze(1) * out[:, :n]),
            a + gate.unsqueeze(1) * out[:, n:],
        )
        if layer.mlp_kind == "none":
            return p, a, state
        seq = layer.mlp_residual(torch.cat([p, a], dim=1), mlp_mod, n if self.decoupled else 0)  # each weight read once
        return seq[:, :n], seq[:, n:], state

    def joint_step(
        self,
        prefix: torch.Tensor,
        x_tau: torch.Tensor,
        mod: Modulation,
        committed: torch.Tensor | None = None,
        state_out: bool = True,
        unrolled: bool = False,
    ) -> tuple[torch.Tensor, list[MixerState]]:
        """A DDIM step with the prefix in the same pass (:attr:`joins_prefix`): prefix (B, L_p, d), x_tau (B, H, A) →
        x0_hat (B, H, A) and every layer's state after the prefix, which the later steps start from
        (:meth:`denoise_modulated`; empty without ``state_out``: K = 1). The first of K steps this way equals
        :meth:`encode_prefix` and then :meth:`denoise_modulated`, and reads each weight once instead of twice: a chunk
        of K steps reads the weights K times, not K + 1. ``unrolled`` as in :meth:`forward_modulated`. Where every
        block is a ``fused_block`` (export's int8 fused graphs) each is one node and [p, a] stays whole between them."""
        a, states = self.joint_tokens(prefix, self.embed_actions(x_tau, committed), mod, state_out, unrolled)
        return self.readout(a, mod), states

    def joint_tokens(
        self, prefix: torch.Tensor, a: torch.Tensor, mod: Modulation, state_out: bool = True, unrolled: bool = False
    ) -> tuple[torch.Tensor, list[MixerState]]:
        """:meth:`joint_step` from the action tokens a (B, H, d) to the last block's output on them (B, H, d), before
        :meth:`readout`, and the states after the prefix."""
        if not self.joins_prefix:
            raise RuntimeError(
                "a step joins the prefix only with timestep_decoupled=True and the blocks all fused or none"
            )
        states = []
        if self.fused_blocks:
            seq = torch.cat([prefix, a], dim=1)
            for i, layer in enumerate(self.layers):
                shift, scale, gate, *_ = mod.block(i)
                seq, state = layer.fused_block.joint(seq, prefix, shift, scale, gate, state_out)
                states.append(state)
            return seq[:, prefix.shape[1] :], states
        p, n_prefix = prefix, int(prefix.shape[1])  # a constant of a graph
        for i, layer in enumerate(self.layers):
            p, a, state = self._block(layer, mod.block(i), p, a, unrolled, n_prefix if state_out else None)
            if state_out:
                states.append(state)
        return a, states

    @property
    def fused_blocks(self) -> bool:
        """Whether every block runs as one fused node (``fused_block``: export's int8 fused graphs)."""
        return all(getattr(layer, "fused_block", None) is not None for layer in self.layers)

    @property
    def joins_prefix(self) -> bool:
        """Whether a chunk's first DDIM step can carry the prefix (:meth:`joint_step`): the timestep decoupled (the
        prefix the same at every step) and the blocks all fused nodes or none."""
        fused = [getattr(layer, "fused_block", None) is not None for layer in self.layers]
        return self.decoupled and (all(fused) or not any(fused))

    # ---------------------------------------------------- prefix-cached forward
    def encode_prefix(self, prefix: torch.Tensor, unrolled: bool = False) -> list[MixerState]:
        """Run the (unmodulated) prefix (B, L_p, d) once: every layer's state after it — Mamba's (conv (B, E, W),
        ssm (B, E, n)), or attention's key/value cache (k, v) each (B, heads, L_p, d_head)."""
        if not self.decoupled:
            raise RuntimeError("prefix caching needs timestep_decoupled=True (the prefix depends on tau otherwise)")
        states = []
        p = prefix
        for layer in self.layers:
            fused = getattr(layer, "fused_block", None)
            if fused is not None:
                p, state = fused.prefix(p)
                states.append(state)
                continue
            out, state = mixer_path(layer.mixer, unrolled)(layer.norm(p))
            p = layer.mlp_residual(p + out)
            states.append(state)
        return states

    def denoise(self, prefix_states: list[MixerState], x_tau: torch.Tensor, timesteps: torch.Tensor) -> torch.Tensor:
        """x0_hat (B, H, A) from the cached prefix states, x_tau (B, H, A), timesteps (B,); equals :meth:`forward`."""
        return self.denoise_modulated(prefix_states, x_tau, self.modulation(timesteps))

    def denoise_modulated(
        self,
        prefix_states: list[MixerState],
        x_tau: torch.Tensor,
        mod: Modulation,
        unrolled: bool = False,
        committed: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """:meth:`denoise` with the AdaLN parameters given (B rows or one): x_tau (B, H, A) → x0_hat (B, H, A);
        ``committed`` as in :meth:`forward`."""
        return self.readout(
            self.denoise_tokens(prefix_states, self.embed_actions(x_tau, committed), mod, unrolled), mod
        )

    def denoise_tokens(
        self, prefix_states: list[MixerState], a: torch.Tensor, mod: Modulation, unrolled: bool = False
    ) -> torch.Tensor:
        """:meth:`denoise_modulated` from the action tokens a (B, H, d) to the last block's output on them (B, H, d),
        before :meth:`readout`."""
        for i, (layer, state) in enumerate(zip(self.layers, prefix_states)):
            shift, scale, gate, *mlp_mod = mod.block(i)
            fused = getattr(layer, "fused_block", None)
            if fused is not None:
                a = fused(a, state, shift, scale, gate)
                continue
            out, _ = mixer_path(layer.mixer, unrolled)(modulate(layer.norm(a), shift, scale), state)
            a = layer.mlp_residual(a + gate.unsqueeze(1) * out, mlp_mod)
        return a

    def step_tokens(
        self,
        prefix: torch.Tensor,
        a: torch.Tensor,
        mod: Modulation,
        states: list[MixerState] | None,
        join: bool,
        unrolled: bool = False,
    ) -> tuple[torch.Tensor, list[MixerState] | None]:
        """One DDIM step's pass over the action tokens a (B, H, d) → the last block's output on them (B, H, d), and the
        prefix's states for the later steps: from the cached ``states`` when there are some, else with the prefix in
        the same pass (``join``: :meth:`joint_tokens`, which gives the states) or on its own (:meth:`forward_tokens`)."""
        if states is not None:
            return self.denoise_tokens(states, a, mod, unrolled), states
        if join:
            return self.joint_tokens(prefix, a, mod, unrolled=unrolled)
        return self.forward_tokens(prefix, a, mod, unrolled), None

    # ----------------------------------------------------------------- helpers
    def embed_actions(self, x_tau: torch.Tensor, committed: torch.Tensor | None = None) -> torch.Tensor:
        """x_tau (B, H, A) → action tokens (B, H, d); the tokens ``committed`` (B, H) marks get the committed embedding."""
        tokens = self.action_in(x_tau) + self.action_pos
        if committed is not None and self.committed_embed is not None:
            tokens = tokens + committed.unsqueeze(-1).to(tokens.dtype) * self.committed_embed
        return tokens

    def readout(self, a: torch.Tensor, mod: Modulation) -> torch.Tensor:
        """Action tokens (B, H, d) → x0_hat (B, H, A) through the final AdaLN."""
        shift, scale = mod.final.unbind(1)
        return self.action_out(modulate(self.norm_f(a), shift, scale))
