"""The DSSP policy on the robot: two ONNX Runtime graphs, numpy in and out, no torch.

    policy = OnnxPolicy("models/tap")          # validates dssp_model.json against the graphs, warms up
    policy = OnnxPolicy("models/tap", precision="int8")  # the int8 graphs (export --quantize int8)
    policy.reset()
    policy.observe(point_cloud, agent_pos)     # every control tick: the history-update graph
    chunk = policy.act(seed=0)                 # every H_a ticks: the denoiser graph → (B, H, A) raw units

Same semantics as the PyTorch streaming API (``dssp_train.model.streaming.StreamingPolicy``): the
recurrent history state starts at zero, the last N state tokens are kept, and at the start of an
episode the first token repeats. Point clouds with more channels than the model uses (xyz + rgb for an
xyz model) are cut to the model's channels, as in training. An observation with NaN or infinity
anywhere is refused (:class:`NonFiniteObservation`) before any graph runs: the recurrent history would
keep it for the rest of the episode; refused, it leaves the state as it was.

Shapes: point_cloud (B, P, C) or (P, C); agent_pos (B, S) or (S,); noise (B, H, A); chunk (B, H, A).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from dssp_deploy.manifest import (
    DENOISER_GRAPH,
    HISTORY_GRAPH,
    PRECISIONS,
    ModelDirError,
    check_session,
    read_graph,
    read_manifest,
)
from dssp_deploy.sessions import open_session

MAX_LISTED = 4  # non-finite entries named in the message


class NonFiniteObservation(ValueError):
    """An observation holds NaN or infinity; it was refused before any graph ran (the history is unchanged)."""


def check_finite(name: str, values: np.ndarray) -> None:
    """Raise :class:`NonFiniteObservation` naming the input and its first non-finite entries."""
    values = np.asarray(values)
    bad = ~np.isfinite(values)
    if not bad.any():
        return
    where = np.argwhere(bad)
    listed = ", ".join(f"{tuple(int(i) for i in idx)}={values[tuple(idx)]}" for idx in where[:MAX_LISTED])
    more = f" and {len(where) - MAX_LISTED} more" if len(where) > MAX_LISTED else ""
    raise NonFiniteObservation(
        f"{name} {list(values.shape)} has {len(where)} non-finite value(s) at {listed}{more}; "
        "the observation was not used (the history is unchanged)"
    )


def _batch(x, rank: int, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float32)
    if a.ndim == rank - 1:
        a = a[None]
    if a.ndim != rank:
        raise ValueError(f"{name} must have {rank - 1} or {rank} dims, got shape {a.shape}")
    return np.ascontiguousarray(a)


class OnnxPolicy:
    def __init__(self, model_dir: str | Path, threads: int | None = None, spinning: bool = False, warmup: int = 2,
                 precision: str = "fp32"):
        if precision not in PRECISIONS:
            raise ModelDirError(f"precision must be one of {sorted(PRECISIONS)}, got {precision!r}")
        self.precision = precision
        self.model_dir = Path(model_dir)
        self.manifest: dict[str, Any] = read_manifest(self.model_dir)  # every fact checked, see dssp_deploy.manifest
        m = self.manifest
        self.point_dim, self.state_dim, self.action_dim = m["point_dim"], m["state_dim"], m["action_dim"]
        self.d_model, self.n_points = m["d_model"], m["model_config"]["n_points"]
        self.n_obs_steps, self.horizon, self.n_action_steps = m["n_obs_steps"], m["horizon"], m["n_action_steps"]
        self.denoise_steps, self.ddim_timesteps = m["denoise_steps"], list(m["ddim_timesteps"])
        self.control_rate_hz: float | None = m["control_rate_hz"]
        self.use_history, self.use_recent_states = m["use_history"], m["use_recent_states"]
        self.history_state: list[str] = list(m["history_state"])
        self.sessions = {}
        for graph in (HISTORY_GRAPH, DENOISER_GRAPH):
            path, data = read_graph(self.model_dir, m, graph, PRECISIONS[precision])  # size and sha256 checked
            try:
                session = open_session(data, threads, spinning)  # the checked bytes, not the path again
            except Exception as exc:  # onnxruntime raises its own exception types
                raise ModelDirError(f"{path} could not be loaded by ONNX Runtime ({exc}); export the model again") from None
            check_session(session, m, graph, path)
            self.sessions[graph] = session
        self._state_specs = [s for s in m["graphs"][HISTORY_GRAPH]["inputs"] if s["name"] in self.history_state]
        self.reset()
        if warmup:
            self.warmup(warmup)

    # ----------------------------------------------------------------- episode
    def reset(self) -> None:
        """Start a new episode: zero history state, empty recent-token buffer."""
        self.state: dict[str, np.ndarray] | None = None
        self.context: np.ndarray | None = None  # (B, d)
        self.recent: np.ndarray | None = None  # (B, N, d)
        self.steps = 0

    def _zero_state(self, batch: int) -> dict[str, np.ndarray]:
        return {s["name"]: np.zeros([batch, *s["shape"][1:]], np.float32) for s in self._state_specs}

    def observe(self, point_cloud, agent_pos) -> np.ndarray:
        """Run the history-update graph on one observation; returns z_t (B, d).

        Raises ValueError for a wrong shape and :class:`NonFiniteObservation` (a ValueError) for NaN or
        infinity anywhere in either input (as float32): both before any graph runs, the state unchanged."""
        pc = _batch(point_cloud, 3, "point_cloud")
        pos = _batch(agent_pos, 2, "agent_pos")
        if pc.shape[-1] < self.point_dim:
            raise ValueError(f"point_cloud has {pc.shape[-1]} channels per point, the model needs {self.point_dim}")
        if pos.shape[-1] != self.state_dim or pos.shape[0] != pc.shape[0]:
            raise ValueError(f"agent_pos must be (B={pc.shape[0]}, S={self.state_dim}), got {pos.shape}")
        check_finite("point_cloud", pc)
        check_finite("agent_pos", pos)
        pc = np.ascontiguousarray(pc[..., : self.point_dim])
        batch = pc.shape[0]
        if self.state is None:
            self.state = self._zero_state(batch)
        elif self.recent.shape[0] != batch:
            raise ValueError(f"batch size {batch} within an episode of batch size {self.recent.shape[0]}; call reset() first")
        feeds = {"point_cloud": pc, "agent_pos": pos, **self.state}
        outputs = self.sessions[HISTORY_GRAPH].run(None, feeds)
        named = dict(zip([o.name for o in self.sessions[HISTORY_GRAPH].get_outputs()], outputs))
        z_t = named["z_t"]
        if self.use_history:
            self.context = named["c_t"]
            self.state = {name: named[f"{name}_out"] for name in self.state}
        if self.recent is None:
            self.recent = np.repeat(z_t[:, None], self.n_obs_steps, axis=1)
        else:
            self.recent = np.concatenate([self.recent[:, 1:], z_t[:, None]], axis=1)
        self.steps += 1
        return z_t

    # ------------------------------------------------------------------ chunks
    def denoiser_inputs(self) -> dict[str, np.ndarray]:
        """A copy of what the denoiser needs now (c_t, z_recent): safe to use from another thread."""
        if self.recent is None:
            raise RuntimeError("act() before any observe(): feed at least one observation first")
        feeds = {}
        if self.use_history:
            feeds["c_t"] = self.context.copy()
        if self.use_recent_states:
            feeds["z_recent"] = self.recent.copy()
        return feeds

    def noise(self, batch: int, seed: int | None = None) -> np.ndarray:
        return np.random.default_rng(seed).standard_normal((batch, self.horizon, self.action_dim), dtype=np.float32)

    def denoise(self, inputs: dict[str, np.ndarray], noise: np.ndarray | None = None, seed: int | None = None) -> np.ndarray:
        """Run the denoiser graph on given inputs: the action chunk (B, H, A) in raw units."""
        batch = next(iter(inputs.values())).shape[0]
        noise = self.noise(batch, seed) if noise is None else _batch(noise, 3, "noise")
        if noise.shape != (batch, self.horizon, self.action_dim):
            raise ValueError(f"noise must have shape {(batch, self.horizon, self.action_dim)}, got {noise.shape}")
        return self.sessions[DENOISER_GRAPH].run(None, {**inputs, "noise": noise})[0]

    def act(self, noise=None, seed: int | None = None) -> np.ndarray:
        """The action chunk (B, H, A) for the current history, from the given noise or a seeded draw."""
        return self.denoise(self.denoiser_inputs(), noise, seed)

    def warmup(self, iterations: int = 2) -> None:
        """Run both graphs on zeros (allocations, kernel selection), then reset."""
        pc = np.zeros((1, 64, self.point_dim), np.float32)
        pos = np.zeros((1, self.state_dim), np.float32)
        for _ in range(iterations):
            self.observe(pc, pos)
            self.act(seed=0)
        self.reset()
