"""The exported model as the loop's policy source (``dssp-run --model``, ``dssp-sim eval``).

    source = ModelPolicy(OnnxPolicy("models/tap"), rate_hz=10, prefetch=False, seed=0)
    source = ModelPolicy(OnnxPolicy("models/tap"), rate_hz=10, smoothing="ensemble", ensemble_every=1)   # ACT's

Each tick runs the runtime's tick (:class:`dssp_deploy.control_loop.ChunkedControl`): the history every tick, a new
chunk every H_a ticks (started early in a background thread with ``prefetch``), or with ``smoothing="ensemble"`` a
chunk every ``ensemble_every`` ticks and the weighted mean of the kept chunks' predictions. Its refusals pass through to the
loop, which holds: an observation with NaN/inf or outside the trained ranges changes nothing (the history is left
alone), a refused chunk undoes the tick. Shapes: cloud (P, C) float32, state and action (dof,).
"""

from __future__ import annotations

import numpy as np

from dssp_core.errors import ConfigError
from dssp_deploy.control_loop import ChunkedControl
from dssp_deploy.onnx_policy import OnnxPolicy
from hardware.policies import Act, PolicySource


class ModelPolicy(PolicySource):
    """``policy``: the loaded runtime; ``rate_hz``: the loop's rate (the history is updated at it); ``prefetch``,
    ``seed``, ``chunk_ms`` (the chunk latency the prefetch lead is chosen from; None: measured here),
    ``smoothing``, ``ensemble_every``, ``ensemble_decay`` and ``injected_delay`` (simulation only):
    :class:`~dssp_deploy.control_loop.ChunkedControl`'s."""

    name = "model"
    needs_cloud = True

    def __init__(self, policy: OnnxPolicy, rate_hz: float, *, prefetch: bool = False, seed: int | None = None,
                 chunk_ms: float | None = None, smoothing: str = "none", ensemble_every: int | None = None,
                 ensemble_decay: float = 0.01, injected_delay: int | None = None):
        self.policy = policy
        self.control_rate_hz = policy.control_rate_hz
        self.control = ChunkedControl(policy, rate_hz=rate_hz, prefetch=prefetch, seed=seed, chunk_ms_estimate=chunk_ms,
                                      smoothing=smoothing, ensemble_every=ensemble_every, ensemble_decay=ensemble_decay,
                                      injected_delay=injected_delay)

    def check(self, description, cloud_config) -> None:
        """Refuse a model that does not fit this robot or camera pipeline — before anything moves."""
        policy, dof = self.policy, description.dof
        if policy.state_dim != dof or policy.action_dim != dof:
            raise ConfigError(
                f"the model takes a {policy.state_dim}-dim state and gives a {policy.action_dim}-dim action, but the robot has "
                f"{dof} values (7 per arm): pass one bus per arm the model was trained for (--can can0[,can1])"
            )
        model_points = policy.manifest["model_config"]["n_points"]
        if cloud_config is None or cloud_config.n_points != model_points:
            given = "no point-cloud pipeline" if cloud_config is None else f"{cloud_config.n_points} points"
            raise ConfigError(f"the point-cloud pipeline gives {given} but the model was trained on {model_points}")

    def reset(self, state: np.ndarray) -> None:
        self.control.reset()

    def act(self, cloud: np.ndarray | None, state: np.ndarray) -> Act:
        out, info = self.control.tick(cloud[None], state[None].astype(np.float32))
        chunk = None
        if info.new_chunk and self.control.chunk is not None:
            # (H - offset, A): the new chunk's actions to come (ensembled: the newest chunk's, not the blend)
            chunk = self.control.chunk[0, self.control.chunk_offset:]
        action = None if out is None else out[0].astype(np.float64)  # None: no chunk usable yet, hold
        return Act(action, observe_ms=info.observe_ms, chunk_ms=info.chunk_ms, chunk=chunk,
                   over_budget=info.over_budget, events=list(info.events))

    def describe(self) -> dict:
        return {"policy": self.name, "denoise_steps": self.policy.manifest.get("denoise_steps"),
                **self.control.smoothing_settings()}
