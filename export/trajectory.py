"""The observation trajectory of verification: streamed through the exported graphs tick by tick, and
given to the PyTorch reference whole (:mod:`export.verify`). Both treat it as one episode.

From the run's dataset (``config.dataset``) when it exists and holds at least the requested number of
steps — its episodes back to back, as stored — otherwise synthetic: a fixed cloud that drifts and a
proprioceptive random walk, both inside the range the normalisers were fitted on.

Shapes: point_cloud (T, P, C) with C = point_dim, agent_pos (T, S); float32, raw units.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dssp_core.errors import DSSPError
from dssp_train.config import RunConfig


@dataclass
class Trajectory:
    point_cloud: np.ndarray  # (T, P, C)
    agent_pos: np.ndarray  # (T, S)
    source: str  # where it came from, for the report

    @property
    def length(self) -> int:
        return int(self.agent_pos.shape[0])


def load_trajectory(config: RunConfig, normalizers: dict, steps: int, seed: int = 0) -> Trajectory:
    """``steps`` observations from the dataset if it is there and long enough, else synthetic ones."""
    m = config.model
    reason = "no dataset recorded in config.json"
    if config.dataset:
        path = Path(config.dataset)
        reason = f"dataset {path} not found"
        if path.exists():
            from dssp_data.replay_buffer import ReplayBuffer  # deferred: loads msgpack, numcodecs, zarr, …

            try:
                data = ReplayBuffer.load(path)
            except DSSPError as exc:
                reason = f"dataset {path} unreadable ({exc})"
            else:
                if data.n_steps >= steps and data.point_dim >= m.point_dim:
                    return Trajectory(
                        np.ascontiguousarray(data.point_cloud[:steps, :, : m.point_dim]),
                        np.ascontiguousarray(data.state[:steps]),
                        f"dataset {path}: first {steps} of {data.n_steps} steps, {data.n_episodes} episodes back to back",
                    )
                reason = f"dataset {path} has {data.n_steps} steps < {steps}"
    return synthetic_trajectory(m.n_points, m.point_dim, normalizers, steps, seed, reason)


def synthetic_trajectory(
    n_points: int, point_dim: int, normalizers: dict, steps: int, seed: int, reason: str = ""
) -> Trajectory:
    """A drifting cloud (T, P, C) and a random walk (T, S) inside the normalisers' fitted ranges."""
    rng = np.random.default_rng(seed)
    pc_lo, pc_hi = (np.asarray(normalizers["point_cloud"][k], dtype=np.float64) for k in ("input_min", "input_max"))
    pos_lo, pos_hi = (np.asarray(normalizers["agent_pos"][k], dtype=np.float64) for k in ("input_min", "input_max"))
    pc_span, pos_span = pc_hi - pc_lo, pos_hi - pos_lo

    base = pc_lo + rng.random((n_points, point_dim)) * pc_span  # (P, C)
    drift = np.cumsum(rng.normal(0.0, 0.01, (steps, 1, point_dim)), axis=0) * pc_span  # (T, 1, C)
    jitter = rng.normal(0.0, 0.002, (steps, n_points, point_dim)) * pc_span
    point_cloud = np.clip(base + drift + jitter, pc_lo, pc_hi)

    pos = np.empty((steps, pos_lo.shape[0]))
    pos[0] = pos_lo + rng.random(pos_lo.shape[0]) * pos_span
    for t in range(1, steps):
        pos[t] = np.clip(pos[t - 1] + rng.normal(0.0, 0.05, pos_lo.shape[0]) * pos_span, pos_lo, pos_hi)
    source = f"synthetic, seed {seed}" + (f" ({reason})" if reason else "")
    return Trajectory(point_cloud.astype(np.float32), pos.astype(np.float32), source)
