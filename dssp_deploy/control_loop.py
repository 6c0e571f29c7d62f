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

Real-time chunking (``smoothing="rtc"``, Black et al. 2025) starts the next chunk every H_a ticks while the current
one still executes, and conditions it to agree with the actions already committed: the denoiser (exported with
``--inpainting``) pulls every DDIM step's clean prediction to the current chunk's actions for the ticks the new one
covers, with weight 1 for the d ticks that execute while it is computed (d = the inference delay in ticks) and the
ticks before the observation, then weights decaying to 0 over the rest of the overlap (RTC's soft mask,
:func:`rtc_weights`). The new chunk takes over d ticks after its observation, at the action for that tick. On the
robot it runs in a background thread and d comes from the measured chunk latency (as prefetch's lead); a tick with
no chunk ready waits and is reported over budget.

Inference delay in simulation (``injected_delay`` = d ticks, ``dssp-sim eval --inject-delay MS``; None, the default:
real time, the robot's): each chunk is
computed at once but usable only d ticks after the observation it was computed from, as if the computation took
that long; until a chunk is usable the tick has no action (``tick`` returns None: the caller holds). Without
smoothing the loop then stalls: it holds d ticks, executes the H_a actions from the chunk's first, starts the next
chunk, holds again. Ensembling takes each chunk in d ticks late, at the actions for the ticks it then covers.
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
SMOOTHINGS = ("none", "ensemble", "rtc")
"""How a tick's action is taken from the chunks: ``none``, the current chunk's (a new one every H_a ticks);
``ensemble``, the weighted mean of every kept chunk's prediction for the tick; ``rtc``, real-time chunking (the next
chunk computed while the current one executes, inpainted to agree with it) (module docstring)."""


def rtc_weights(horizon: int, offset: int, covered: int, delay: int) -> np.ndarray:
    """Real-time chunking's soft mask (H,) for a new chunk: index i is the tick i - ``offset`` after its observation;
    ``covered``: how many of the indices from 0 the current chunk has actions for; ``delay``: the ticks it still
    executes while the new chunk is computed. Weight 1 for the indices before ``offset + delay`` (the past and the
    committed ticks), then c (e^c - 1) / (e - 1) with c falling linearly from 1 towards 0 over the rest of the
    covered indices (RTC's exponential decay), 0 where nothing is committed."""
    w = np.zeros(horizon, np.float64)
    frozen = min(covered, offset + delay)
    w[:frozen] = 1.0
    rest = covered - frozen
    if rest > 0:
        c = (rest - np.arange(rest)) / (rest + 1)
        w[frozen:covered] = c * np.expm1(c) / np.expm1(1.0)
    return w


def add_smoothing_arguments(parser, also: str = "") -> None:
    """``--smoothing none|ensemble``, ``--ensemble-every N``, ``--ensemble-decay M``: how a command's loop takes each
    tick's action from the chunks (:class:`ChunkedControl`); ``also``: a note for ``--smoothing``'s help."""
    parser.add_argument("--smoothing", choices=SMOOTHINGS, default="none",
                        help="none (default): each tick's action from the current chunk, a new one every H_a ticks; "
                             "ensemble: a chunk every --ensemble-every ticks and the weighted mean of every kept chunk's "
                             "prediction for the tick (ACT's temporal ensembling; H_a / N times the denoiser work"
                             + (f"; {also}" if also else "") + "); rtc: real-time chunking, the next chunk computed while "
                             "the current one executes and inpainted to agree with it (a model exported with --inpainting)")
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


class _Computed:
    """A denoiser call already made (injected delay: the chunk is ready, only its time has not come)."""

    def __init__(self, chunk: np.ndarray, ms: float):
        self._chunk, self._ms = chunk, ms

    def done(self) -> bool:
        return True

    def result(self) -> tuple[np.ndarray, float]:
        return self._chunk, self._ms


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
        injected_delay: int | None = None,
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
        if injected_delay is not None and (isinstance(injected_delay, bool) or not isinstance(injected_delay, (int, np.integer))
                                           or injected_delay < 0):
            raise ValueError(f"injected_delay must be a whole number of ticks >= 0, got {injected_delay!r}")
        if injected_delay is not None and prefetch:
            raise ValueError("an injected delay simulates the chunk's computation time; prefetch runs it in the background "
                             "for real: use one or the other")
        if smoothing == "rtc":
            if prefetch:
                raise ValueError("real-time chunking computes the next chunk in the background itself; leave prefetch off")
            if not policy.inpainting:
                raise ValueError("real-time chunking needs a denoiser that takes the committed actions: export the model "
                                 "with python -m export.to_onnx --inpainting")
        self.injected_delay = None if injected_delay is None else int(injected_delay)  # None: real time (the robot)
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
        if prefetch:  # chunks start `lead` ticks early; their first `lead` actions, whose time has passed, are dropped
            self.lead = self._ticks_ahead(chunk_ms_estimate, "prefetch", "predicted actions can be dropped; run without "
                                          "prefetch or at a lower rate")
        self.delay = self.injected_delay or 0  # d: ticks from a chunk's observation to its first executed action
        if smoothing == "rtc" and injected_delay is None:
            self.delay = self._ticks_ahead(chunk_ms_estimate, "real-time chunking", "ticks beyond its H_a are covered by "
                                           "a chunk: real-time chunking cannot keep up; run at a lower rate")
        self.reset()

    def _ticks_ahead(self, chunk_ms: float | None, what: str, beyond: str) -> int:
        """The ticks a chunk takes (at least 1) from ``chunk_ms`` (None: measured here), which must fit in the
        H - action_offset - H_a actions a chunk predicts beyond the H_a it executes; a one-line ValueError otherwise."""
        p = self.policy
        if self.period_ms is None:
            raise ValueError(f"{what} needs a tick rate: pass rate_hz (the manifest records none)")
        if chunk_ms is None:
            chunk_ms = self.measure_chunk_ms()
        ticks = max(1, math.ceil(chunk_ms / self.period_ms))
        spare = p.horizon - p.action_offset - p.n_action_steps
        if ticks > spare:
            raise ValueError(f"a chunk takes {chunk_ms:.1f} ms = {ticks} ticks at {self.rate_hz:g} Hz, but only "
                             f"H - action_offset - H_a = {spare} {beyond}")
        return ticks

    def measure_chunk_ms(self, iterations: int = 5) -> float:
        """Median denoiser latency (ms) on zeros, for choosing the prefetch lead or real-time chunking's delay."""
        p = self.policy
        inputs = {}
        if p.use_history:
            inputs["c_t"] = np.zeros((1, p.d_model), np.float32)
        if p.use_recent_states:
            inputs["z_recent"] = np.zeros((1, p.n_obs_steps, p.d_model), np.float32)
        if p.inpainting:  # nothing committed: the plain chain, which costs the same
            inputs["committed"] = np.zeros((1, p.horizon, p.action_dim), np.float32)
            inputs["committed_weight"] = np.zeros((1, p.horizon, 1), np.float32)
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
        self.in_flight: tuple[int, _Background | _Computed] | None = None  # (observation tick, the chunk's computation)
        self.arriving: list[tuple[int, np.ndarray]] = []  # ensembling with an injected delay: not usable yet
        self.exec_end = 0  # an injected delay without smoothing: the current chunk's last tick + 1
        self.next_start = 0  # real-time chunking: the tick the next chunk starts at
        self.kept: list[tuple[int, np.ndarray]] = []
        self._last_tick_time: float | None = None

    def smoothing_settings(self) -> dict:
        """What the loop smooths with, for a run's log: {smoothing, ensemble_every, ensemble_decay} (None without
        ensembling)."""
        return {"smoothing": self.smoothing, "ensemble_every": self.ensemble_every,
                "ensemble_decay": self.ensemble_decay, "rtc_delay_ticks": self.delay if self.smoothing == "rtc" else None,
                "injected_delay_ticks": self.injected_delay}

    def _chunk_seed(self) -> int | None:
        return None if self.seed is None else self.seed + self.tick_count

    def tick(self, point_cloud, agent_pos) -> tuple[np.ndarray | None, TickInfo]:
        """Update the history with this tick's observation and return this tick's action (B, A) — None while no chunk
        is usable yet (an injected delay, or real-time chunking's first chunk): hold.

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
        if self.smoothing == "rtc":
            return self._real_time(info)
        if self.injected_delay:
            return self._stalled(info)
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
        arriving = self.arriving
        if t % self.ensemble_every == 0:
            info.new_chunk = True
            chunk = self._chunk_now(info)  # a refused chunk raises here: the kept chunks are left as they were
            arriving = [*arriving, (t, chunk)]
            self.chunk, self.chunk_offset, self.chunk_start = chunk, offset, t  # the newest: what is shown as to come
        # an injected delay: a chunk joins d ticks after its observation (none: at once)
        kept = [*kept, *[(s, c) for s, c in arriving if t >= s + self.delay]]
        self.arriving = [(s, c) for s, c in arriving if t < s + self.delay]
        # A chunk computed at tick s predicts ticks s .. s + H - offset - 1; without a delay the newest always covers t
        # (t - s < ensemble_every <= H_a <= H - offset).
        self.kept = kept = [(s, c) for s, c in kept if offset + t - s < c.shape[1]]
        if not kept:  # an injected delay: no chunk has come yet
            info.predictions = 0
            return None, info
        predictions = np.stack([c[:, offset + t - s] for s, c in kept])  # (n, B, A), oldest first
        weights = np.exp(-self.ensemble_decay * np.arange(len(kept)))  # ACT: the oldest weighs most
        action = np.tensordot(weights / weights.sum(), predictions.astype(np.float64), axes=1)
        info.chunk_index = offset + t - self.chunk_start
        info.predictions = len(kept)
        return action.astype(predictions.dtype), info

    def _start_chunk(self, info: TickInfo, committed: np.ndarray | None = None, weight: np.ndarray | None = None):
        """Start a chunk from this tick's history: computed now with an injected delay (a refused chunk raises here),
        else in a background thread."""
        inputs = self.policy.denoiser_inputs(committed, weight)
        if self.injected_delay is not None or not self.delay:
            c0 = time.perf_counter()
            chunk = self.policy.denoise(inputs, seed=self._chunk_seed())
            return _Computed(chunk, (time.perf_counter() - c0) * 1e3)
        return _Background(self.policy, inputs, self._chunk_seed())

    def _take(self, info: TickInfo) -> tuple[int, np.ndarray]:
        """The chunk in flight, now that its time has come: (its observation tick, chunk (B, H, A)); a chunk still
        computing is waited for (over budget)."""
        start, job = self.in_flight
        self.in_flight = None  # taken, whether its chunk is used or refused
        w0 = time.perf_counter()
        if not job.done():
            info.over_budget = True
        chunk, info.chunk_ms = job.result()
        info.waited_ms = (time.perf_counter() - w0) * 1e3
        if info.over_budget:
            info.events.append(f"chunk not ready at tick {info.tick}: waited {info.waited_ms:.1f} ms (over budget)")
        info.new_chunk = True
        return start, chunk

    def _stalled(self, info: TickInfo) -> tuple[np.ndarray | None, TickInfo]:
        """No smoothing with an injected delay: hold while a chunk computes, then its H_a actions from the first."""
        t, offset, ha = self.tick_count, self.policy.action_offset, self.policy.n_action_steps
        if self.in_flight is None and (self.chunk is None or t >= self.exec_end):
            self.in_flight = (t, self._start_chunk(info))
        if self.in_flight is not None and t >= self.in_flight[0] + self.delay:
            _, self.chunk = self._take(info)
            self.chunk_offset, self.chunk_start, self.exec_end = offset, t, t + ha
        if self.chunk is None or t >= self.exec_end:
            return None, info
        info.chunk_index = offset + t - self.chunk_start
        return self.chunk[:, info.chunk_index], info

    def _take_due(self, info: TickInfo) -> None:
        """Real-time chunking: the chunk in flight becomes the current one once d ticks have passed since its observation."""
        if self.in_flight is not None and self.tick_count >= self.in_flight[0] + self.delay:
            self.chunk_start, self.chunk = self._take(info)
            self.chunk_offset = self.policy.action_offset + (self.tick_count - self.chunk_start)

    def _real_time(self, info: TickInfo) -> tuple[np.ndarray | None, TickInfo]:
        """Real-time chunking: the chunk in flight takes over d ticks after its observation; a new one starts every
        H_a ticks (once none is in flight) from this tick's history, inpainted with the current chunk's actions."""
        t, offset, ha, horizon = self.tick_count, self.policy.action_offset, self.policy.n_action_steps, self.policy.horizon
        self._take_due(info)
        if self.in_flight is None and (self.chunk is None and t == 0 or t >= self.next_start):
            committed = weight = None
            if self.chunk is not None:  # new index i is the tick t + i - offset: the current chunk's index i + shift
                shift = t - self.chunk_start
                covered = max(0, horizon - shift)
                committed = np.zeros_like(self.chunk)
                committed[:, :covered] = self.chunk[:, shift:]
                weight = rtc_weights(horizon, offset, covered, self.delay)[None, :, None]
            self.in_flight = (t, self._start_chunk(info, committed, weight))
            self.next_start = t + ha
            self._take_due(info)  # no delay: the chunk takes over at once
        if self.chunk is None:
            return None, info
        index = offset + t - self.chunk_start
        if index >= horizon:  # the chunk ran out before the next took over (a delay beyond what H allows): hold
            return None, info
        info.chunk_index = index
        return self.chunk[:, index], info
