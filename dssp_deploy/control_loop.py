"""Control-loop semantics as trained: the history every tick, a new chunk every H_a ticks.

    loop = ChunkedControl(policy, rate_hz=10, prefetch=True)
    loop = ChunkedControl(policy, rate_hz=10, smoothing="ensemble", ensemble_every=1, ensemble_decay=0.01)  # ACT's
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

Temporal ensembling (``smoothing="ensemble"``, ACT: Zhao et al. 2023) computes a chunk every ``ensemble_every``
ticks (default 1: every tick) instead of every H_a, and keeps each one for the ticks it covers: the chunk
computed at tick s predicts tick t >= s with its action ``action_offset + (t - s)`` while that index is < H.
The action at tick t is the weighted mean of every kept chunk's prediction for t, with weights
``exp(-ensemble_decay * i)``, i = 0 for the oldest prediction (ACT's convention: older predictions weigh more;
decay 0 is the plain mean). It costs H_a / ensemble_every times the denoiser work of ``"none"``, and a chunk
is computed in the tick that uses it, so it does not combine with prefetch. The history is updated every tick
either way; a refused chunk undoes the tick and leaves the kept chunks as they were.
"""

from __future__ import annotations

import copy
import math
import threading
import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from dssp_core.errors import ConfigError
from dssp_deploy.onnx_policy import OnnxPolicy
from dssp_deploy.ranges import ChunkOutOfRange

RATE_TOLERANCE = 0.05
SMOOTHINGS = ("none", "ensemble")
"""How a tick's action is taken from the chunks: ``none``, the current chunk's (a new one every H_a ticks);
``ensemble``, the weighted mean of every kept chunk's prediction for the tick (module docstring)."""


def add_smoothing_arguments(parser, also: str = "") -> None:
    """``--smoothing none|ensemble``, ``--ensemble-every N``, ``--ensemble-decay M``: how a command's loop takes each
    tick's action from the chunks (:class:`ChunkedControl`); ``also``: a note for ``--smoothing``'s help."""
    parser.add_argument("--smoothing", choices=SMOOTHINGS, default="none",
                        help="none (default): each tick's action from the current chunk, a new one every H_a ticks; "
                             "ensemble: a chunk every --ensemble-every ticks and the weighted mean of every kept chunk's "
                             "prediction for the tick (ACT's temporal ensembling; H_a / N times the denoiser work"
                             + (f"; {also}" if also else "") + ")")
    parser.add_argument("--ensemble-every", type=int, metavar="N",
                        help="--smoothing ensemble: ticks between chunks, 1 to the model's H_a (default 1: every tick)")
    parser.add_argument("--ensemble-decay", type=float, metavar="M",
                        help="--smoothing ensemble: the i-th oldest prediction for a tick weighs exp(-M i) (default 0.01: "
                             "the older weigh more, as in ACT; 0: the plain mean)")


def model_flags_given(args, *also: tuple[str, bool]) -> list[str]:
    """The flags that only a model takes which ``args`` sets: those of
    :func:`dssp_deploy.onnx_policy.add_runtime_arguments` and :func:`add_smoothing_arguments`, then ``also`` (a
    command's own, as (flag, given)) — for a command run with another policy source, which refuses them."""
    flags = (("--precision", args.precision is not None), ("--kernel", args.kernel != "auto"), ("--no-spin", args.no_spin),
             ("--smoothing", args.smoothing != "none"), ("--ensemble-every", args.ensemble_every is not None),
             ("--ensemble-decay", args.ensemble_decay is not None), *also)
    return [flag for flag, given in flags if given]


def check_smoothing_arguments(args) -> None:
    """:func:`add_smoothing_arguments`' flags, as far as they can be judged without the model (--ensemble-every's
    upper bound, the model's H_a: :func:`check_ensemble_every`); one ConfigError line."""
    if args.smoothing != "ensemble":
        for flag, given in (("--ensemble-every", args.ensemble_every is not None),
                            ("--ensemble-decay", args.ensemble_decay is not None)):
            if given:
                raise ConfigError(f"{flag} is a setting of temporal ensembling: it goes with --smoothing ensemble")
        return
    if args.ensemble_every is not None and args.ensemble_every < 1:
        raise ConfigError(f"--ensemble-every must be at least 1 (ticks between chunks), got {args.ensemble_every}")
    if args.ensemble_decay is not None and not (math.isfinite(args.ensemble_decay) and args.ensemble_decay >= 0):
        raise ConfigError(f"--ensemble-decay must be a finite number >= 0 (0: the plain mean), got {args.ensemble_decay}")


def check_ensemble_every(every: int | None, policy: OnnxPolicy, model) -> None:
    """--ensemble-every against the loaded model: at most its H_a (``model``: how the model is named in the line)."""
    if every is not None and every > policy.n_action_steps:
        ha = policy.n_action_steps
        raise ConfigError(f"--ensemble-every {every}: {model} executes H_a = {ha} actions of a chunk, so a chunk is "
                          f"needed at least every {ha} ticks (1 to {ha})")


def smoothing_options(args) -> dict:
    """:class:`ChunkedControl`'s smoothing keywords from :func:`add_smoothing_arguments`' flags (their defaults
    where a flag is not given)."""
    options: dict = {"smoothing": args.smoothing}
    if args.smoothing == "ensemble":
        options["ensemble_every"] = args.ensemble_every
        if args.ensemble_decay is not None:
            options["ensemble_decay"] = args.ensemble_decay
    return options


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
    """The runtime's tick (module docstring). ``policy``: the loaded runtime; ``rate_hz``: the tick rate (default:
    the model's); ``prefetch``: start each chunk ``lead`` ticks early in a background thread (``chunk_ms_estimate``:
    the chunk latency the lead is chosen from; None: measured here); ``seed``: chunk k's noise seed is ``seed`` +
    the tick it is computed at (None: random); ``smoothing``: one of :data:`SMOOTHINGS`; ``ensemble_every`` (ticks
    between chunks, 1..H_a, default 1) and ``ensemble_decay`` (finite, >= 0): used with ``"ensemble"`` only.

    Kept chunks (``"ensemble"``): ``kept`` [(tick computed at, chunk (B, H, A))], oldest first."""

    def __init__(
        self,
        policy: OnnxPolicy,
        rate_hz: float | None = None,
        prefetch: bool = False,
        seed: int | None = None,
        chunk_ms_estimate: float | None = None,
        smoothing: str = "none",
        ensemble_every: int | None = None,
        ensemble_decay: float = 0.01,
    ):
        if smoothing not in SMOOTHINGS:
            raise ValueError(f"smoothing must be one of {', '.join(SMOOTHINGS)}, got {smoothing!r}")
        self.smoothing = smoothing
        self.ensemble_every, self.ensemble_decay = None, None
        if smoothing == "ensemble":
            if prefetch:
                raise ValueError("temporal ensembling computes each chunk in the tick that first uses it, so it does "
                                 "not combine with prefetch; run one or the other")
            every, ha, decay = 1 if ensemble_every is None else ensemble_every, policy.n_action_steps, ensemble_decay
            if isinstance(every, bool) or not isinstance(every, (int, np.integer)) or not 1 <= every <= ha:
                raise ValueError(f"ensemble_every must be a whole number of ticks from 1 to H_a = {ha}, "
                                 f"got {ensemble_every!r}")
            number = isinstance(decay, (int, float, np.integer, np.floating)) and not isinstance(decay, bool)
            if not (number and math.isfinite(decay) and decay >= 0):
                raise ValueError(f"ensemble_decay must be a finite number >= 0 (0: the plain mean), got {decay!r}")
            self.ensemble_every, self.ensemble_decay = int(every), float(decay)
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
        self.kept: list[tuple[int, np.ndarray]] = []
        self._last_tick_time: float | None = None

    def smoothing_settings(self) -> dict:
        """What the loop smooths with, for a run's log: {smoothing, ensemble_every, ensemble_decay} (None without
        ensembling)."""
        return {"smoothing": self.smoothing, "ensemble_every": self.ensemble_every,
                "ensemble_decay": self.ensemble_decay}

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

    def _chunk_now(self, info: TickInfo) -> np.ndarray:
        """A chunk (B, H, A) computed in this tick, its latency and any over-budget event in ``info``; a refused
        chunk raises ChunkOutOfRange here."""
        c0 = time.perf_counter()
        chunk = self.policy.act(seed=self._chunk_seed())
        info.chunk_ms = (time.perf_counter() - c0) * 1e3
        if self.period_ms and info.observe_ms + info.chunk_ms > self.period_ms:
            info.over_budget = True
            info.events.append(
                f"tick {info.tick} took {info.observe_ms + info.chunk_ms:.1f} ms > {self.period_ms:.1f} ms (over budget)"
            )
        return chunk

    def _act(self, t0: float, info_events: list[str]) -> tuple[np.ndarray, TickInfo]:
        """This tick's action (B, A) after its observation: a new chunk every H_a ticks, else the current one."""
        info = TickInfo(self.tick_count, 0, False, (time.perf_counter() - t0) * 1e3, events=info_events)
        if self.smoothing == "ensemble":
            return self._ensembled(info)
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
                self.chunk = self._chunk_now(info)
                self.chunk_offset = self.policy.action_offset
            self.chunk_start = t
        if self.lead and (t + self.lead) % ha == 0 and self.pending is None:
            self.pending = _Background(self.policy, self.policy.denoiser_inputs(), self._chunk_seed())
        index = self.chunk_offset + (t - self.chunk_start)
        info.chunk_index = index
        return self.chunk[:, index], info

    def _ensembled(self, info: TickInfo) -> tuple[np.ndarray, TickInfo]:
        """This tick's action (B, A) with temporal ensembling: a new chunk every ``ensemble_every`` ticks, then the
        weighted mean of every kept chunk's prediction for this tick, oldest first with weight exp(-decay * i)."""
        t, offset = self.tick_count, self.policy.action_offset
        kept = self.kept
        if t % self.ensemble_every == 0:
            info.new_chunk = True
            chunk = self._chunk_now(info)  # a refused chunk raises here: the kept chunks are left as they were
            kept = [*kept, (t, chunk)]
            self.chunk, self.chunk_offset, self.chunk_start = chunk, offset, t  # the newest: what is shown as to come
        # A chunk computed at tick s predicts ticks s .. s + H - offset - 1; the newest always covers t
        # (t - s < ensemble_every <= H_a <= H - offset).
        self.kept = kept = [(s, c) for s, c in kept if offset + t - s < c.shape[1]]
        predictions = np.stack([c[:, offset + t - s] for s, c in kept])  # (n, B, A), oldest first
        weights = np.exp(-self.ensemble_decay * np.arange(len(kept)))  # ACT: the oldest weighs most
        action = np.tensordot(weights / weights.sum(), predictions.astype(np.float64), axes=1)
        info.chunk_index = offset + t - self.chunk_start
        info.predictions = len(kept)
        return action.astype(predictions.dtype), info
