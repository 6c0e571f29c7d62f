"""The exported model as the loop's policy source (``dssp-run --model``, ``dssp-sim eval``).

    source = ModelPolicy(OnnxPolicy("models/tap"), control_rate_hz=10, seed=0)
    source = ModelPolicy(OnnxPolicy("models/tap"), control_rate_hz=10, schedule=Ensemble(every=1))   # ACT's

Each tick runs the runtime's tick (:class:`dssp_deploy.control_loop.ChunkedControl`): the history every tick, the action
from the chunks by the schedule (:mod:`dssp_deploy.schedules`: a new chunk every H_a ticks, prefetched, temporally
ensembled or by real-time chunking). Its refusals pass through to the loop, which holds: an observation with NaN/inf
or outside the trained ranges changes nothing (the history is left alone), a refused chunk undoes the tick. Shapes:
cloud (P, C) float32, state and action (dof,).
"""

from __future__ import annotations

import numpy as np

from dssp_core.errors import ConfigError
from dssp_deploy.control_loop import ChunkedControl
from dssp_deploy.onnx_policy import OnnxPolicy
from dssp_deploy.schedules import Plain, Schedule
from hardware.policies import Act, PolicySource


class ModelPolicy(PolicySource):
    """``policy``: the loaded runtime; ``control_rate_hz``: the loop's rate (the history is updated at it); ``seed`` and
    ``schedule`` (a :mod:`dssp_deploy.schedules` config): :class:`~dssp_deploy.control_loop.ChunkedControl`'s."""

    name = "model"
    needs_cloud = True

    def __init__(
        self, policy: OnnxPolicy, control_rate_hz: float, *, seed: int | None = None, schedule: Schedule = Plain()
    ):
        self.policy, self.control_rate_hz = policy, control_rate_hz
        self.control = ChunkedControl(policy, schedule, control_rate_hz=control_rate_hz, seed=seed)

    def check(self, description, cloud_config) -> None:
        """Refuse a model that does not fit this robot or camera pipeline — before anything moves."""
        policy, dof = self.policy, description.dof
        if policy.contract.state_dim != dof or policy.contract.action_dim != dof:
            raise ConfigError(
                f"the model takes a {policy.contract.state_dim}-dim state and gives "
                f"a {policy.contract.action_dim}-dim action, but the robot has "
                f"{dof} values (7 per arm): pass one bus per arm the model was trained for (--can can0[,can1])"
            )
        model_points = policy.contract.n_points
        if cloud_config is None or cloud_config.n_points != model_points:
            given = "no point-cloud pipeline" if cloud_config is None else f"{cloud_config.n_points} points"
            raise ConfigError(f"the point-cloud pipeline gives {given} but the model was trained on {model_points}")

    def reset(self, state: np.ndarray) -> None:
        self.control.reset()

    def act(self, cloud: np.ndarray | None, state: np.ndarray) -> Act:
        out, info = self.control.tick(cloud[None], state[None].astype(np.float32))
        chunk, shown = None, self.control.schedule
        if info.new_chunk and shown.chunk is not None:
            # (H - offset, A): the new chunk's actions to come (ensembled: the newest chunk's, not the blend)
            chunk = shown.chunk[0, shown.chunk_offset :]
        action = None if out is None else out[0].astype(np.float64)  # None: no chunk usable yet, hold
        return Act(
            action,
            observe_ms=info.observe_ms,
            chunk_ms=info.chunk_ms,
            chunk=chunk,
            over_budget=info.over_budget,
            events=list(info.events),
        )

    def describe(self) -> dict:
        return {
            "policy": self.name,
            "denoise_steps": self.policy.contract.denoise_steps,
            **self.control.schedule.settings(),
        }
