"""Control-loop semantics as trained: the history every tick, the tick's action from the chunks by one schedule.

    loop = ChunkedControl(policy, Plain(prefetch=True), control_rate_hz=10)
    loop = ChunkedControl(policy, Ensemble(every=1, decay=0.01))   # ACT's temporal ensembling
    for each tick:
        action, info = loop.tick(point_cloud, agent_pos)   # action (B, A) raw units, for this tick (None: hold)

Which chunk (B, H, A) each action comes from, and where a chunk's computation time comes from (the robot's real time
or a simulated delay), is the schedule's (:mod:`dssp_deploy.schedules`). A refused observation (NaN/inf:
:class:`~dssp_core.errors.NonFiniteObservation`; outside the training range: :class:`~dssp_deploy.ranges.ObservationOutOfRange`)
changes nothing (no history update, no tick counted): the caller holds, as for a stale camera frame, and the next good
observation continues the episode. A refused chunk (NaN/inf or an action outside the action range:
:class:`~dssp_deploy.ranges.ChunkOutOfRange`) is raised from the tick that needs it, which is undone (its observation
taken back out of the history, no tick counted, the schedule as it was): the caller holds the same way, and the next
tick computes a new chunk.
"""

from __future__ import annotations

import copy
import time
import warnings
from dataclasses import dataclass, field
from functools import partial

import numpy as np

from dssp_deploy.manifest import no_inpainting
from dssp_deploy.onnx_policy import OnnxPolicy
from dssp_deploy.ranges import ChunkOutOfRange
from dssp_deploy.schedules import Plain, Schedule, timed

RATE_TOLERANCE = 0.05


@dataclass
class TickInfo:
    tick: int
    chunk_index: int  # which action of the current chunk was returned
    new_chunk: bool
    observe_ms: float
    chunk_ms: float | None = None  # denoiser latency of the chunk that started on this tick
    waited_ms: float = 0.0  # time this tick waited for a background chunk
    over_budget: bool = False
    events: list[str] = field(default_factory=list)
    predictions: int = 1  # how many chunks' predictions the action is the mean of (1 without ensembling)


class ChunkedControl:
    """The runtime's tick (module docstring). ``policy``: the loaded runtime; ``schedule``: a :mod:`dssp_deploy.schedules`
    config, checked against the policy and the rate here (a one-line ValueError), running as ``self.schedule``;
    ``control_rate_hz``: the tick rate (default: the model's); ``seed``: a chunk's seed is ``seed`` + its tick (None: random)."""

    def __init__(
        self,
        policy: OnnxPolicy,
        schedule: Schedule = Plain(),
        control_rate_hz: float | None = None,
        seed: int | None = None,
    ):
        self.policy = policy
        self.control_rate_hz = control_rate_hz or policy.contract.control_rate_hz
        self.period_ms = 1e3 / self.control_rate_hz if self.control_rate_hz else None
        self.seed = seed
        self.schedule = schedule.bind(self)  # refused before the rate is warned about
        trained = policy.contract.control_rate_hz
        if control_rate_hz and trained and abs(control_rate_hz - trained) > RATE_TOLERANCE * trained:
            warnings.warn(
                f"the control loop runs at {control_rate_hz:g} Hz but the model was trained on data at {trained:g} Hz: "
                "the history will be updated at another rate than in training",
                stacklevel=2,
            )
        self.reset()

    def measure_chunk_ms(self, iterations: int = 5) -> float:
        """Median denoiser latency (ms) on zeros, for choosing the prefetch lead or real-time chunking's delay."""
        p, m = self.policy, self.policy.manifest.model
        inputs = {}
        if m.use_history:
            inputs["c_t"] = np.zeros((1, m.d_model), np.float32)
        if m.use_recent_states:
            inputs["z_recent"] = np.zeros((1, p.contract.n_obs_steps, m.d_model), np.float32)
        inputs.update(no_inpainting(p.contract, 1))  # nothing committed: the plain chain, which costs the same
        times = []
        for _ in range(iterations):
            t0 = time.perf_counter()
            try:
                p.denoise(inputs, seed=0)
            except ChunkOutOfRange:  # zeros are no context the model was trained on: only the time counts here
                pass
            times.append((time.perf_counter() - t0) * 1e3)
        return float(np.median(times))

    def reset(self) -> None:
        self.policy.reset()
        self.tick_count = 0
        self._last_tick_time: float | None = None
        self.schedule.reset()

    def chunk_seed(self) -> int | None:
        return None if self.seed is None else self.seed + self.tick_count

    def tick(self, point_cloud, agent_pos) -> tuple[np.ndarray | None, TickInfo]:
        """Update the history with this tick's observation and return this tick's action (B, A) — None while no chunk
        is usable yet (a simulated delay, or real-time chunking's first chunk): hold.

        Raises NonFiniteObservation (NaN/inf in the observation) or ObservationOutOfRange before anything
        changes, and ChunkOutOfRange (a refused chunk) with the tick undone: hold this tick."""
        now = time.perf_counter()
        info_events: list[str] = []
        if self._last_tick_time is not None and self.period_ms:
            actual = (now - self._last_tick_time) * 1e3
            if actual > (1 + 2 * RATE_TOLERANCE) * self.period_ms:
                info_events.append(f"tick period {actual:.1f} ms is longer than the model's {self.period_ms:.1f} ms")

        t0 = time.perf_counter()
        # The history before this tick: each observation replaces its fields (never changes them in place).
        before = copy.copy(self.policy.history)
        self.policy.observe(point_cloud, agent_pos)  # a refused observation raises here, nothing changed
        info = TickInfo(self.tick_count, 0, False, (time.perf_counter() - t0) * 1e3, events=info_events)
        try:
            action = self.schedule.act(self.tick_count, info)
        except ChunkOutOfRange:  # undo the tick: the history as before it, no tick counted
            self.policy.history = before
            raise
        self._last_tick_time = now
        self.tick_count += 1
        return action, info

    def compute(self, info: TickInfo) -> np.ndarray:
        """A new chunk (B, H, A) computed in this tick, its latency and any over-budget event in ``info``; a refused
        chunk raises ChunkOutOfRange here."""
        info.new_chunk = True
        chunk, info.chunk_ms = timed(partial(self.policy.act, seed=self.chunk_seed()))
        took = info.observe_ms + info.chunk_ms
        if self.period_ms and took > self.period_ms:
            info.over_budget = True
            info.events.append(f"tick {info.tick} took {took:.1f} ms > {self.period_ms:.1f} ms (over budget)")
        return chunk
