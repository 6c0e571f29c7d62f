"""The two torch modules that become the exported graphs: wrappers that fix each graph's interface.

- :class:`HistoryStepGraph` — run once per control tick. Raw observation and the recurrent state of
  every history layer in; ``z_t``, ``c_t`` and the new state out. Normalisation happens inside, through
  ``DSSPPolicy.encode_observations``; the history update is ``HistoryEncoder.step`` (``Mamba.step``).
- :class:`DenoiserGraph` — run once per action chunk. ``c_t``, the recent ``z`` tokens and the initial
  noise in; the action chunk in raw units out, after K DDIM steps unrolled in the graph
  (``DSSPPolicy.sample_normalized``).

The model's math lives in ``dssp_train``; these wrappers only choose the export-friendly paths:

- The timestep reaches the denoiser only through its AdaLN parameters: with K fixed, the table of
  ``Denoiser.modulation`` for the K DDIM timesteps is computed once at construction and kept as buffers,
  so the timestep MLP and the AdaLN projections are not part of the graph, and the DDIM coefficients
  are Python constants. With ``timestep_decoupled`` the prefix ``[c_t, z...]`` runs once per call, in the first
  DDIM step's pass, and its per-layer state serves the later steps (``Denoiser.joint_step`` /
  ``Denoiser.denoise_modulated``): Mamba's
  recurrent state, or for the Transformer denoiser (``model.denoiser_backbone = "transformer"``) the prefix's
  keys and values, which each step's action tokens attend to.
- Mamba's sequence path (``Mamba.forward``) uses a parallel scan with in-place strided views that does
  not export; the denoiser runs ``Mamba.forward_unrolled`` instead: the same layer with the recurrence
  unrolled over the few prefix or action tokens. Unrolling ``Mamba.step`` token by token exports as well
  (the history graph is exactly that, for one token), but for the robotwin denoiser it gave 44.6k ONNX
  nodes instead of 9.3k and ran about 2x slower in ONNX Runtime (262 vs ~120 ms per chunk, 2 threads):
  every projection becomes a matrix-vector product. The attention mixer's ``forward_unrolled`` is its
  ``forward``; the Transformer denoiser has no Mamba layer, so its fused graph has no custom operator.

Shapes (B batch, P points, C = ``point_dim``, S state, A action, d width, N recent tokens, H horizon,
E = d_inner = expand * d, n = d_state, W = d_conv):
    history:  point_cloud (B, P, C), agent_pos (B, S), per layer conv (B, E, W) + ssm (B, E, n)
              → z_t (B, d), c_t (B, d), per layer conv (B, E, W) + ssm (B, E, n)
    denoiser: c_t (B, d), z_recent (B, N, d), noise (B, H, A) → action (B, H, A)
"""

from __future__ import annotations

import copy

import torch
from torch import nn

from dssp_core.errors import ConfigError
from dssp_train.model.denoiser import Denoiser
from dssp_train.model.mamba import Mamba
from dssp_train.model.obs_encoder import PointEncoder
from dssp_train.model.policy import DSSPPolicy
from export.fused_ops import FUSED_OPS


def check_exportable(policy: DSSPPolicy) -> None:
    """Refuse history variants that do not export: the Transformer history encoder (over the full history its
    state grows; the exporter does not trace it over a window either).

    Every denoiser exports (Mamba or attention mixer): it keeps nothing from one chunk to the next."""
    cfg = policy.cfg
    if cfg.use_history and cfg.history_backbone != "mamba":
        variant = f"history_backbone={cfg.history_backbone}, history_window={cfg.history_window}"
        raise ConfigError(
            f"this run's history encoder ({variant}) does not export; export supports the Mamba history encoder over "
            "the full history or a window of T_h steps (history_window), and the reactive baseline (use_history false)"
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


def use_fused_ops(module: nn.Module) -> None:
    """Route every Mamba layer, point encoder and denoiser (the end of each DDIM step) of ``module`` through the fused
    operators (:mod:`export.fused_ops`)."""
    for layer in module.modules():
        if isinstance(layer, (Mamba, PointEncoder, Denoiser)):
            layer.fused_ops = FUSED_OPS


def state_names(n_layers: int) -> list[str]:
    """Input names of the recurrent state, per layer: conv_state_i, ssm_state_i."""
    return [f"{kind}_state_{i}" for i in range(n_layers) for kind in ("conv", "ssm")]


# ---------------------------------------------------------------- history step
class HistoryStepGraph(nn.Module):
    """One control tick: raw observation (+ history state) → z_t (, c_t, new state).

    forward(point_cloud (B, P, C), agent_pos (B, S), conv_state_0 (B, E, W), ssm_state_0 (B, E, n), ...)
        → z_t (B, d), c_t (B, d), conv_state_0_out (B, E, W), ssm_state_0_out (B, E, n), ...
    With a window of T_h steps (``history_window``) the state is the window and a count instead:
    forward(point_cloud, agent_pos, z_window (B, T_h, d), z_seen (B, 1)) → z_t, c_t, z_window_out, z_seen_out
    (``HistoryEncoder.window_step``: the Mamba stack runs over the window every tick).
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
        encoder = self.policy.history_encoder
        if encoder.window:
            c_t, (window, seen) = encoder.window_step(z_t, *states, unrolled=True)
            return z_t, c_t, window, seen
        layer_states = [(states[2 * i], states[2 * i + 1]) for i in range(len(states) // 2)]
        c_t, new_states = encoder.step(z_t, layer_states)
        return (z_t, c_t, *[s for pair in new_states for s in pair])


# -------------------------------------------------------------------- denoiser
class DenoiserGraph(nn.Module):
    """K DDIM steps from noise to a raw action chunk, every timestep-only quantity a constant.

    forward(c_t (B, d) [if use_history], z_recent (B, N, d) [if use_recent_states], noise (B, H, A)
            [, committed (B, H, A) raw units, committed_weight (B, H, 1) in [0, 1] — with ``inpainting``])
        → action (B, H, A) in raw units.
    With ``inpainting`` every step's clean prediction is pulled to the committed actions by their weights (real-time
    chunking: the actions already sent while this chunk was computed; weight 0 everywhere is the plain chain).
    ``z_recent`` holds the last N ``z_t`` from the history step, oldest first; at the start of an
    episode the first observation's ``z`` repeats (as in training).
    """

    def __init__(self, policy: DSSPPolicy, num_steps: int, inpainting: bool = False):
        super().__init__()
        self.inpainting = inpainting
        cfg = policy.cfg
        self.policy = policy = pruned_copy(policy, ("denoiser",))
        self.use_history = cfg.use_history
        self.use_recent = cfg.use_recent_states
        self.decoupled = cfg.timestep_decoupled
        self.num_steps = num_steps
        self.timesteps = policy.schedule.inference_timesteps(num_steps)
        den = policy.denoiser
        with torch.no_grad():
            table = den.modulation(torch.tensor(self.timesteps))
        # The table's tensors become buffers: the Mamba/attention denoiser's AdaLN parameters of every block at every
        # step, (K, n_layers, R, d) and (K, 2, d) (R = 3, 6 with DiT's MLP); DP3's UNet's step embeddings (K, e).
        self.table_type = type(table)
        for name, tensor in zip(table._fields, table):
            self.register_buffer(f"table_{name}", tensor, persistent=False)
        den.fold_timestep()  # the timestep MLP and its projections are not part of the graph

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        it = iter(inputs)
        context = next(it) if self.use_history else None
        recent = next(it) if self.use_recent else None
        noise = next(it)
        inpaint = None
        if self.inpainting:
            committed, weight = next(it), next(it)
            inpaint = (self.policy.normalizers["action"].normalize(committed), weight)
        prefix = self.policy.build_prefix(context, recent)  # (B, L_p, d)
        table = self.table_type(*(getattr(self, f"table_{name}") for name in self.table_type._fields))
        x = self.policy.sample_normalized(
            prefix, noise, self.num_steps, table, unrolled=True, inpaint=inpaint
        )  # (B, H, A)
        return self.policy.normalizers["action"].unnormalize(x)
