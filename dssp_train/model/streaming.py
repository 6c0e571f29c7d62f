"""The PyTorch streaming API: a trained policy run one control tick at a time, as the robot runs it.

    stream = StreamingPolicy(policy)
    stream.reset()
    for each control tick:
        stream.observe(point_cloud, agent_pos)   # updates the history, every tick
        if it is time for a new chunk:
            chunk = stream.act(seed=0)           # (B, H, A) raw units; execute the first H_a

The history is kept by :class:`dssp_data.streaming_history.StreamingHistory`, the state machine the
robot's runtime (``dssp_deploy.onnx_policy.OnnxPolicy``) uses too: zero recurrent state at the start of
an episode, the last N ``z`` tokens, the first ``z`` repeated until N exist (as in training). Streaming
step by step gives the same ``c_t`` as the sequence path used in training. An observation with NaN or
infinity is refused (:class:`dssp_core.errors.NonFiniteObservation`) before the encoder runs, leaving the
history as it was — the same rule as the robot's runtime.

Shapes: point_cloud (B, P, C) or (P, C); agent_pos (B, S) or (S,); noise (B, H, A); chunk (B, H, A);
c_t (B, d); recent (B, N, d).
"""

from __future__ import annotations

import numpy as np
import torch

from dssp_data.streaming_history import StreamingHistory, check_finite
from dssp_train.model.policy import DSSPPolicy


def _as_batch(x, dims: int) -> torch.Tensor:
    t = torch.as_tensor(np.asarray(x, dtype=np.float32) if not isinstance(x, torch.Tensor) else x).float()
    return t.unsqueeze(0) if t.dim() == dims - 1 else t


class StreamingPolicy:
    def __init__(self, policy: DSSPPolicy):
        self.policy = policy.eval()
        self.cfg = policy.cfg
        self.history = StreamingHistory(self.cfg.n_obs_steps, self._step, lambda tokens: torch.stack(tokens, dim=1))

    def _step(self, pc: torch.Tensor, pos: torch.Tensor, state):
        """pc (B, P, C), pos (B, S), the history encoder's state (None: a new episode) → z_t, c_t, new state."""
        z_t = self.policy.encode_observations(pc, pos)  # (B, d)
        if self.policy.history_encoder is None:
            return z_t, None, state
        context, state = self.policy.history_encoder.step(z_t, state)
        return z_t, context, state

    def reset(self) -> None:
        """Start a new episode: forget the history."""
        self.history.reset()

    @property
    def context(self) -> torch.Tensor | None:
        """c_t (B, d) after the last observation; None before it or without a history encoder."""
        return self.history.context

    @property
    def recent(self) -> torch.Tensor | None:
        """The last N z tokens (B, N, d), oldest first; None before the first observation."""
        return self.history.recent

    @property
    def history_state(self):
        """The history encoder's state (per layer (conv (B, E, W), ssm (B, E, n)) for Mamba); None at the start."""
        return self.history.state

    @property
    def steps(self) -> int:
        return self.history.steps

    @torch.no_grad()
    def observe(self, point_cloud, agent_pos) -> torch.Tensor | None:
        """Update the history with one observation; returns c_t (B, d) (None without a history encoder).

        NaN or infinity anywhere in either input raises NonFiniteObservation; nothing changes."""
        pc = _as_batch(point_cloud, 3)
        pos = _as_batch(agent_pos, 2)
        for name, t in (("point_cloud", pc), ("agent_pos", pos)):
            if not bool(torch.isfinite(t).all()):
                check_finite(name, t.detach().cpu().numpy())
        self.history.observe(pc, pos)
        return self.context

    @property
    def action_offset(self) -> int:
        """Index of the chunk's first action to execute (N - 1 with DP3's alignment, else 0); run H_a from there."""
        return self.cfg.action_offset

    @torch.no_grad()
    def act(self, noise=None, seed: int | None = None, num_steps: int | None = None) -> np.ndarray:
        """The action chunk (B, H, A) in raw units, from the given noise or a seeded draw; execute
        ``chunk[:, action_offset : action_offset + H_a]``."""
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
