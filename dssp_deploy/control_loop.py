"""Control-loop semantics as trained: the history every tick, a new chunk every H_a ticks.

    loop = ChunkedControl(policy, rate_hz=10, prefetch=True)
    for each tick:
        action, info = loop.tick(point_cloud, agent_pos)   # action (B, A) raw units, for this tick

Without prefetch, the chunk for ticks [k H_a, (k+1) H_a) is computed at tick k H_a from the history up
to that tick (exactly as trained). With ``prefetch`` the chunk is started ``lead`` ticks earlier in a
background thread — from the history at that earlier tick — and its first ``lead`` actions, whose time
has passed by then, are dropped (as diffusion_policy's real-robot loop does), so the tick that needs it
does not wait. ``lead`` comes from the measured chunk latency and the tick period; it needs
``lead + H_a <= H``. A chunk that is still not ready when needed is waited for and reported as over
budget in the tick's info — never silently late. The history is updated at every tick either way.

An observation with NaN or infinity raises :class:`~dssp_core.errors.NonFiniteObservation` from
``tick``, one outside the training range :class:`~dssp_deploy.ranges.ObservationOutOfRange`, and both
change nothing (no history update, no tick counted): the caller holds, as for a stale camera frame, and
the next good observation continues the episode. A chunk the runtime refuses (NaN/inf or an action outside
the action range: :class:`~dssp_deploy.ranges.ChunkOutOfRange`) is raised from the tick that needs it, and
that tick is undone (its observation taken back out of the history, no tick counted): the caller holds the
same way, and the next tick computes a new chunk.
"""

from __future__ import annotations

import copy
import math
import threading
import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from dssp_deploy.onnx_policy import OnnxPolicy
from dssp_deploy.ranges import ChunkOutOfRange

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


class _Background:
    """One denoiser call on a thread; ``result()`` waits for it."""

    def __init__(self, policy: OnnxPolicy, inputs: dict[str, np.ndarray], seed: int | None):
        self._out: dict = {}

        def run():
            t0 = time.perf_counter()
            try:
                self._out["chunk"] = policy.denoise(inputs, seed=seed)
            except Exception as exc:  # surfaced in result()
                self._out["error"] = exc
            self._out["ms"] = (time.perf_counter() - t0) * 1e3

        self._thread = threading.Thread(target=run, daemon=True)
        self._thread.start()

    def done(self) -> bool:
        return not self._thread.is_alive()

    def result(self) -> tuple[np.ndarray, float]:
        self._thread.join()
        if "error" in self._out:
            raise self._out["error"]
        return self._out["chunk"], self._out["ms"]


class ChunkedControl:
    def __init__(
        self,
        policy: OnnxPolicy,
        rate_hz: float | None = None,
        prefetch: bool = False,
        seed: int | None = None,
        chunk_ms_estimate: float | None = None,
    ):
        self.policy = policy
        self.rate_hz = rate_hz or policy.control_rate_hz
        self.period_ms = 1e3 / self.rate_hz if self.rate_hz else None
        self.seed = seed
        trained = policy.control_rate_hz
        if rate_hz and trained and abs(rate_hz - trained) > RATE_TOLERANCE * trained:
            warnings.warn(
                f"the control loop runs at {rate_hz:g} Hz but the model was trained on data at {trained:g} Hz: "
                "the history will be updated at another rate than in training",
                stacklevel=2,
            )
        self.lead = 0
        if prefetch:
            if self.period_ms is None:
                raise ValueError("prefetch needs a tick rate: pass rate_hz (the manifest records none)")
            if chunk_ms_estimate is None:
                chunk_ms_estimate = self.measure_chunk_ms()
            self.lead = max(1, math.ceil(chunk_ms_estimate / self.period_ms))
            spare = policy.horizon - policy.action_offset - policy.n_action_steps
            if self.lead > spare:
                raise ValueError(
                    f"a chunk takes {chunk_ms_estimate:.1f} ms = {self.lead} ticks at {self.rate_hz:g} Hz, but only "
                    f"H - action_offset - H_a = {spare} predicted actions can be dropped; run without prefetch or at a lower rate"
                )
        self.reset()

    def measure_chunk_ms(self, iterations: int = 5) -> float:
        """Median denoiser latency (ms) on zeros, for choosing the prefetch lead."""
        p = self.policy
        inputs = {}
        if p.use_history:
            inputs["c_t"] = np.zeros((1, p.d_model), np.float32)
        if p.use_recent_states:
            inputs["z_recent"] = np.zeros((1, p.n_obs_steps, p.d_model), np.float32)
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
        self.chunk: np.ndarray | None = None
        self.chunk_offset = 0
        self.chunk_start = 0
        self.pending: _Background | None = None
        self._last_tick_time: float | None = None

    def _chunk_seed(self) -> int | None:
        return None if self.seed is None else self.seed + self.tick_count

    def tick(self, point_cloud, agent_pos) -> tuple[np.ndarray, TickInfo]:
        """Update the history with this tick's observation and return this tick's action (B, A).

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
        try:
            action, info = self._act(t0, info_events)
        except ChunkOutOfRange:  # undo the tick: the history as before it, no tick counted
            self.policy.history = before
            raise
        self._last_tick_time = now
        self.tick_count += 1
        return action, info

    def _act(self, t0: float, info_events: list[str]) -> tuple[np.ndarray, TickInfo]:
        """This tick's action (B, A) after its observation: a new chunk every H_a ticks, else the current one."""
        info = TickInfo(self.tick_count, 0, False, (time.perf_counter() - t0) * 1e3, events=info_events)
        t = self.tick_count
        ha = self.policy.n_action_steps
        if t % ha == 0:
            info.new_chunk = True
            if self.pending is not None:
                w0 = time.perf_counter()
                pending, self.pending = self.pending, None  # taken, whether its chunk is used or refused
                if not pending.done():
                    info.over_budget = True
                chunk, info.chunk_ms = pending.result()
                info.waited_ms = (time.perf_counter() - w0) * 1e3
                self.chunk, self.chunk_offset = chunk, self.policy.action_offset + self.lead
                if info.over_budget:
                    info.events.append(f"chunk not ready at tick {t}: waited {info.waited_ms:.1f} ms (over budget)")
            else:
                c0 = time.perf_counter()
                self.chunk = self.policy.act(seed=self._chunk_seed())
                info.chunk_ms = (time.perf_counter() - c0) * 1e3
                self.chunk_offset = self.policy.action_offset
                if self.period_ms and info.observe_ms + info.chunk_ms > self.period_ms:
                    info.over_budget = True
                    info.events.append(
                        f"tick {t} took {info.observe_ms + info.chunk_ms:.1f} ms > {self.period_ms:.1f} ms (over budget)"
                    )
            self.chunk_start = t
        if self.lead and (t + self.lead) % ha == 0 and self.pending is None:
            self.pending = _Background(self.policy, self.policy.denoiser_inputs(), self._chunk_seed())
        index = self.chunk_offset + (t - self.chunk_start)
        info.chunk_index = index
        return self.chunk[:, index], info
