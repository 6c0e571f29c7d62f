"""The PyTorch streaming API: the reference that exported graphs and the runtime are checked against.

    stream = StreamingPolicy(policy)
    stream.reset()
    for each control tick:
        stream.observe(point_cloud, agent_pos)   # updates the history, every tick
        if it is time for a new chunk:
            chunk = stream.act(seed=0)           # (B, H, A) raw units; execute the first H_a

Streaming step by step gives the same ``c_t`` as the sequence path used in training, and the
recent-state buffer is padded at the episode start by repeating the first observation, as in training.
An observation with NaN or infinity is refused (``dssp_deploy.onnx_policy.NonFiniteObservation``) before the
encoder runs, leaving the history as it was — the same rule as the robot's runtime.

Shapes: point_cloud (B, P, C) or (P, C); agent_pos (B, S) or (S,); noise (B, H, A); chunk (B, H, A).
"""

from __future__ import annotations

import numpy as np
import torch

from dssp_deploy.onnx_policy import NonFiniteObservation, check_finite  # noqa: F401  (NonFiniteObservation: what observe raises)
from dssp_train.model.policy import DSSPPolicy


def _as_batch(x, dims: int) -> torch.Tensor:
    t = torch.as_tensor(np.asarray(x, dtype=np.float32) if not isinstance(x, torch.Tensor) else x).float()
    return t.unsqueeze(0) if t.dim() == dims - 1 else t


class StreamingPolicy:
    def __init__(self, policy: DSSPPolicy):
        self.policy = policy.eval()
        self.cfg = policy.cfg
        self.reset()

    def reset(self) -> None:
        """Start a new episode: forget the history."""
        self.history_state = None
        self.recent: torch.Tensor | None = None  # (B, N, d)
        self.context: torch.Tensor | None = None  # (B, d)
        self.steps = 0

    @torch.no_grad()
    def observe(self, point_cloud, agent_pos) -> torch.Tensor | None:
        """Update the history with one observation; returns c_t (B, d) (None without a history encoder).

        NaN or infinity anywhere in either input raises NonFiniteObservation; nothing changes."""
        pc = _as_batch(point_cloud, 3)
        pos = _as_batch(agent_pos, 2)
        for name, t in (("point_cloud", pc), ("agent_pos", pos)):
            if not bool(torch.isfinite(t).all()):
                check_finite(name, t.detach().cpu().numpy())
        z_t = self.policy.encode_observations(pc, pos)  # (B, d)
        if self.policy.history_encoder is not None:
            self.context, self.history_state = self.policy.history_encoder.step(z_t, self.history_state)
        if self.recent is None:
            self.recent = z_t.unsqueeze(1).repeat(1, self.cfg.n_obs_steps, 1)
        else:
            self.recent = torch.cat([self.recent[:, 1:], z_t.unsqueeze(1)], dim=1)
        self.steps += 1
        return self.context

    @torch.no_grad()
    def act(self, noise=None, seed: int | None = None, num_steps: int | None = None) -> np.ndarray:
        """The action chunk (B, H, A) in raw units, from the given noise or a seeded draw."""
        if self.recent is None:
            raise RuntimeError("act() before any observe(): feed at least one observation first")
        batch = self.recent.shape[0]
        shape = (batch, self.cfg.horizon, self.cfg.action_dim)
        if noise is None:
            gen = torch.Generator().manual_seed(seed) if seed is not None else None
            noise = torch.randn(shape, generator=gen)
        noise = _as_batch(noise, 3)
        if tuple(noise.shape) != shape:
            raise ValueError(f"noise must have shape {shape}, got {tuple(noise.shape)}")
        prefix = self.policy.build_prefix(self.context, self.recent)
        chunk = self.policy.sample_normalized(prefix, noise, num_steps)
        return self.policy.normalizers["action"].unnormalize(chunk).numpy()
