"""DSSPPolicy: the whole model — normalisers, E_obs, G_psi, g_phi and f_theta — and its losses.

Training is trajectory-wise (paper Appendix C.1): one whole trajectory is encoded causally,
``z = E_obs(o_{1:T})`` and ``c = G_psi(z)``, and B action windows are sampled from it; the window
starting at t is conditioned only on ``c_t`` and ``z_{t-N+1..t}`` (indices before 0 repeat the
first observation) and predicts ``a_t .. a_{t+H-1}`` (indices past the end repeat the last action).

A model without history may instead train on windows drawn from anywhere in the data, DP3's way
(``train.sampling = "windows"``, :meth:`DSSPPolicy.compute_window_loss`): the same windows, the same loss.

Raw (unnormalised) shapes at the boundary:
    point_cloud (T, P, C) or (B, T, P, C); agent_pos (T, S); action (T, A); action chunk (B, H, A).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from dssp_train.config import ModelConfig
from dssp_train.model.denoiser import Denoiser, Modulation
from dssp_train.model.dynamics import DynamicsPredictor, dynamics_diagnostics, dynamics_loss
from dssp_train.model.history_encoder import HistoryEncoder
from dssp_train.model.normalizer import RangeNormalizer
from dssp_train.model.obs_encoder import ObservationEncoder
from dssp_train.model.scheduler import DiffusionSchedule
from dssp_train.model.unet import UNetDenoiser


class DSSPPolicy(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        if cfg.state_dim < 1 or cfg.action_dim < 1:
            raise ValueError("ModelConfig.state_dim and action_dim must be set (from the dataset) before building")
        self.cfg = cfg
        self.normalizers = nn.ModuleDict(
            {
                "point_cloud": RangeNormalizer(cfg.point_dim),
                "agent_pos": RangeNormalizer(cfg.state_dim),
                "action": RangeNormalizer(cfg.action_dim),
            }
        )
        self.obs_encoder = ObservationEncoder(cfg)
        self.history_encoder = HistoryEncoder(cfg) if cfg.use_history else None
        self.dynamics = DynamicsPredictor(cfg.d_model, cfg.action_dim) if cfg.uses_dynamics_loss else None
        self.denoiser = UNetDenoiser(cfg) if cfg.denoiser_backbone == "unet" else Denoiser(cfg)
        self.schedule = DiffusionSchedule(cfg.diffusion)

    # ------------------------------------------------------------ normalisers
    def fit_normalizers(self, point_cloud, agent_pos, action) -> None:
        """Fit the min/max statistics on training data: (..., C), (..., S), (..., A)."""
        self.normalizers["point_cloud"].fit(point_cloud[..., : self.cfg.point_dim])
        self.normalizers["agent_pos"].fit(agent_pos)
        self.normalizers["action"].fit(action)

    # --------------------------------------------------------------- encoding
    def encode_observations(self, point_cloud: torch.Tensor, agent_pos: torch.Tensor) -> torch.Tensor:
        """Raw (..., P, C) and (..., S) → z (..., d). Extra point channels (rgb) beyond point_dim are dropped."""
        pc = self.normalizers["point_cloud"].normalize(point_cloud[..., : self.cfg.point_dim])
        pos = self.normalizers["agent_pos"].normalize(agent_pos)
        return self.obs_encoder(pc, pos)

    def build_prefix(self, context: torch.Tensor | None, recent: torch.Tensor) -> torch.Tensor:
        """Prefix [c_t, z_{t-N+1}, ..., z_t]: context (B, d) or None, recent (B, N, d) → (B, L_p, d)."""
        parts = []
        if self.cfg.use_history:
            parts.append(context.unsqueeze(1))
        if self.cfg.use_recent_states:
            parts.append(recent)
        return torch.cat(parts, dim=1)

    def encode_trajectory(
        self, point_cloud: torch.Tensor, agent_pos: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """One raw trajectory (T, P, C), (T, S) → its state tokens z (1, T, d) and context tokens c (1, T, d)
        (None without a history encoder), each causal."""
        z = self.encode_observations(point_cloud.unsqueeze(0), agent_pos.unsqueeze(0))
        return z, (self.history_encoder(z) if self.history_encoder is not None else None)

    def window_prefix(
        self, z: torch.Tensor, c: torch.Tensor | None, starts: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The prefix (B, L_p, d) of the windows starting at ``starts`` (B,) of one encoded trajectory (z, c: (1, T, d)),
        and the indices (B, H) of their target actions."""
        obs_idx, act_idx = self.trajectory_windows(z.shape[1], starts)
        return self.build_prefix(None if c is None else c[0, starts], z[0, obs_idx]), act_idx

    # ----------------------------------------------------------------- losses
    def trajectory_windows(self, length: int, starts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Indices (B, N) of the recent observations and (B, H) of the target actions for each start t: the chunk
        starts at t, or at t - N + 1 with DP3's alignment (``cfg.action_offset``); indices past either end of the
        trajectory repeat its first or last step."""
        n, h = self.cfg.n_obs_steps, self.cfg.horizon
        obs_idx = (starts.unsqueeze(1) + torch.arange(-n + 1, 1, device=starts.device)).clamp(min=0)
        first = starts.unsqueeze(1) - self.cfg.action_offset
        act_idx = (first + torch.arange(h, device=starts.device)).clamp(min=0, max=length - 1)
        return obs_idx, act_idx

    def compute_loss(
        self,
        point_cloud: torch.Tensor,
        agent_pos: torch.Tensor,
        action: torch.Tensor,
        starts: torch.Tensor,
        generator: torch.Generator | None = None,
    ) -> dict[str, torch.Tensor]:
        """Losses on one trajectory.

        Args:
            point_cloud (T, P, C), agent_pos (T, S), action (T, A): one raw trajectory.
            starts (B,): the window start times t.
            generator: source of the diffusion noise and timesteps.
        Returns:
            {"loss", "diffusion", "dynamics"} scalars, and with the dynamics loss its diagnostics (no gradient):
            "dyn_cos", "dyn_cos_mean", "dyn_cos_prev" (:func:`dssp_train.model.dynamics.dynamics_diagnostics`).
        """
        length = action.shape[0]
        z, c = self.encode_trajectory(point_cloud, agent_pos)
        a_norm = self.normalizers["action"].normalize(action)  # (T, A)
        prefix, act_idx = self.window_prefix(z, c, starts)
        diffusion = self.diffusion_loss(prefix, a_norm[act_idx], generator)

        dyn = diffusion.new_zeros(())
        diagnostics = {}
        if self.dynamics is not None and length > 1:
            z_hat = self.dynamics(c[0, :-1], a_norm[:-1])
            dyn = dynamics_loss(z_hat, z[0, 1:])
            diagnostics = dynamics_diagnostics(z_hat, z[0])
        return {
            "loss": diffusion + self.cfg.dynamics_weight * dyn,
            "diffusion": diffusion,
            "dynamics": dyn,
            **diagnostics,
        }

    def compute_window_loss(
        self,
        point_cloud: torch.Tensor,
        agent_pos: torch.Tensor,
        action: torch.Tensor,
        generator: torch.Generator | None = None,
    ) -> dict[str, torch.Tensor]:
        """Losses on B windows drawn from anywhere in the data (DP3's sampling; a model without history only).

        Args:
            point_cloud (B, N, P, C), agent_pos (B, N, S): each window's N recent raw observations.
            action (B, H, A): each window's raw target actions.
        Returns:
            {"loss", "diffusion", "dynamics"} scalars (no dynamics loss without a history)."""
        if self.cfg.use_history:
            raise ValueError("windows from anywhere in the data need a model without history (model.use_history=false)")
        prefix = self.build_prefix(None, self.encode_observations(point_cloud, agent_pos))
        diffusion = self.diffusion_loss(prefix, self.normalizers["action"].normalize(action), generator)
        return {"loss": diffusion, "diffusion": diffusion, "dynamics": diffusion.new_zeros(())}

    def diffusion_loss(self, prefix: torch.Tensor, x0: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
        """The denoising loss of normalised chunks x0 (B, H, A) given their prefixes (B, L_p, d): noise and a timestep
        drawn per chunk, the prediction compared with x0 or the noise (``diffusion.prediction_type``)."""
        noise = torch.randn(x0.shape, generator=generator).to(x0.device)
        timesteps = torch.randint(0, self.cfg.diffusion.num_train_timesteps, (x0.shape[0],), generator=generator)
        timesteps = timesteps.to(x0.device)
        x_tau = self.schedule.add_noise(x0, noise, timesteps)
        target = x0 if self.cfg.diffusion.prediction_type == "sample" else noise
        if not self.cfg.committed_prefix_max:
            return F.mse_loss(self.denoiser(prefix, x_tau, timesteps), target)
        # training-time real-time chunking: the first d actions given clean and marked, the loss on the others only
        d = torch.randint(0, self.cfg.committed_prefix_max + 1, (x0.shape[0], 1), generator=generator).to(x0.device)
        committed = torch.arange(x0.shape[1], device=x0.device).unsqueeze(0) < d  # (B, H)
        pred = self.denoiser(prefix, torch.where(committed.unsqueeze(-1), x0, x_tau), timesteps, committed)
        free = (~committed).unsqueeze(-1).to(pred.dtype)
        return ((pred - target) ** 2 * free).sum() / (free.sum() * x0.shape[-1])

    def forward(self, *args, windows: bool = False, **kwargs) -> dict[str, torch.Tensor]:
        """:meth:`compute_loss`, or with ``windows`` :meth:`compute_window_loss` (what DistributedDataParallel calls)."""
        return self.compute_window_loss(*args, **kwargs) if windows else self.compute_loss(*args, **kwargs)

    # --------------------------------------------------------------- sampling
    @torch.no_grad()
    def sample_normalized(self, *args, **kwargs) -> torch.Tensor:
        """:meth:`ddim_chain` without gradients: how every chunk is sampled."""
        return self.ddim_chain(*args, **kwargs)

    def ddim_chain(
        self,
        prefix: torch.Tensor,
        noise: torch.Tensor,
        num_steps: int | None = None,
        table: Modulation | None = None,
        unrolled: bool = False,
        inpaint: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> torch.Tensor:
        """DDIM from noise (B, H, A) to a normalised action chunk (B, H, A), given the prefix (B, L_p, d); with
        gradients (a distilled student trains its K-step chain end to end), :meth:`sample_normalized` without.

        The AdaLN parameters of the K timesteps are computed once (or given: ``table``, K rows) and each
        step takes its row; with ``timestep_decoupled`` the prefix runs once, in the first step's pass, and its states
        serve the later steps (:meth:`Denoiser.joint_step`).
        ``unrolled`` runs the Mamba layers' traceable path (:meth:`Mamba.forward_unrolled`). ``inpaint`` (target
        (B, H, A) normalised, weight (B, H, 1)): every step's clean prediction is pulled to the target
        (:meth:`~dssp_train.model.scheduler.DiffusionSchedule.ddim_step`): real-time chunking's committed actions.
        A model trained with committed prefixes (``committed_prefix_max``) is given the fully committed actions
        (weight 1) clean and marked instead, at every step, and keeps them exactly; it ignores partial weights.
        """
        den = self.denoiser
        timesteps = self.schedule.inference_timesteps(num_steps)
        if table is None:
            table = den.modulation(torch.tensor(timesteps, device=noise.device))
        # The prefix's states serve the K steps; one step needs none: it runs [prefix, x] in one pass (each weight
        # read once per chunk instead of twice). With K > 1 the first step carries the prefix and gives its states
        # (K weight reads a chunk instead of K + 1); DP3's UNet, whose prefix is a global condition, encodes it apart.
        cached = self.cfg.timestep_decoupled and len(timesteps) > 1
        joined = cached and den.joins_prefix
        states = den.encode_prefix(prefix, unrolled) if cached and not joined else None
        committed = None
        if inpaint is not None and self.cfg.committed_prefix_max:  # trained on committed actions: given, not guided
            target, weight = inpaint
            mask = weight >= 1.0  # (B, H, 1): the actions fully committed; a partial weight is guidance's, not used
            committed = mask.squeeze(-1)
            inpaint = (target, mask.to(target.dtype))
        marked = {} if committed is None else {"committed": committed}
        x = noise
        # export's fused graphs (inpainting aside): each step's end, the readout, the update and the next step's
        # action tokens, one node (export.fused_ops.FusedOps.ddim_step)
        fused = getattr(den, "fused_ops", None) if inpaint is None else None
        if fused is not None:
            a = den.embed_actions(x)
            for k, t in enumerate(timesteps):
                h, states = den.step_tokens(prefix, a, table.at(k), states, joined, unrolled)
                x, a = fused.ddim_step(den, self.schedule, h, x, table.at(k), t, num_steps, k < len(timesteps) - 1)
            return x
        for k, t in enumerate(timesteps):
            given = x if committed is None else torch.where(inpaint[1] > 0, inpaint[0], x)
            if states is not None:
                x0 = den.denoise_modulated(states, given, table.at(k), unrolled, **marked)
            elif joined:
                x0, states = den.joint_step(prefix, given, table.at(k), unrolled=unrolled, **marked)
            else:
                x0 = den.forward_modulated(prefix, given, table.at(k), unrolled, **marked)
            x = self.schedule.ddim_step(x0, t, x, num_steps, inpaint)
        return x

    @torch.no_grad()
    def sample_trajectory_windows(
        self,
        point_cloud: torch.Tensor,
        agent_pos: torch.Tensor,
        starts: torch.Tensor,
        noise: torch.Tensor,
    ) -> torch.Tensor:
        """Raw action chunks (B, H, A) for windows of one raw trajectory, from noise (B, H, A)."""
        prefix, _ = self.window_prefix(*self.encode_trajectory(point_cloud, agent_pos), starts)
        return self.normalizers["action"].unnormalize(self.sample_normalized(prefix, noise))
