"""How the runtime's tick takes each action from the chunks (B, H, A; index i of a chunk observed at tick s: tick s + i -
action_offset's): one schedule per mode, a frozen config that checks itself (a one-line :class:`SettingError`) and,
bound to a :class:`~dssp_deploy.control_loop.ChunkedControl`, runs with its own state.

    Plain(prefetch=True)                       # a new chunk every H_a ticks, each started early
    Ensemble(every=1, decay=0.01)              # ACT's temporal ensembling
    RealTimeChunking()                         # the next chunk computed while the current one executes, inpainted
    replace(config, delay=SimulatedDelay(2))   # the simulation: each chunk's computation taken to last 2 ticks
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, fields
from functools import partial
from typing import TYPE_CHECKING, ClassVar

import numpy as np

if TYPE_CHECKING:
    from dssp_deploy.control_loop import ChunkedControl, TickInfo

NAMES = {"smoothing": "smoothing", "prefetch": "Plain.prefetch", "every": "Ensemble.every", "decay": "Ensemble.decay"}


class SettingError(ValueError):
    """A refused setting, one line naming settings as {every}, {smoothing}, ...: by :data:`NAMES`, or :meth:`named`."""

    def __init__(self, text: str, **values):
        self.text, self.values = text, values
        super().__init__(self.named({}))

    def named(self, names: dict[str, str]) -> str:
        return self.text.format_map({**NAMES, **names, **self.values})


def _number(value, kinds: tuple = (int, float, np.integer, np.floating)) -> bool:
    return isinstance(value, kinds) and not isinstance(value, bool)


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


def timed(call: Callable[[], np.ndarray]) -> tuple[np.ndarray, float]:
    """``call()``'s chunk (B, H, A) and its latency (ms); a refused chunk raises ChunkOutOfRange."""
    t0 = time.perf_counter()
    return call(), (time.perf_counter() - t0) * 1e3


@dataclass(frozen=True)
class MeasuredDelay:
    """Real time, the robot's (the default ``delay``): a chunk computed in the tick that needs it is usable in that tick
    (``now_ticks`` 0: the tick is late, reported over budget); one started ahead runs in a background thread and takes
    ``chunk_ms`` (None: measured when the loop is built, :meth:`ChunkedControl.measure_chunk_ms`) in whole ticks, >= 1."""

    chunk_ms: float | None = None
    now_ticks: ClassVar[int] = 0

    def ahead_ticks(self, loop: ChunkedControl, what: str, beyond: str) -> int:
        """The ticks a chunk started ahead takes, which must fit in the H - action_offset - H_a actions a chunk predicts
        beyond the H_a it executes; a one-line ValueError otherwise (``what`` needs them; ``beyond``: the line's end)."""
        p = loop.policy
        if loop.period_ms is None:
            raise ValueError(f"{what} needs a tick rate: pass control_rate_hz (the manifest records none)")
        chunk_ms = loop.measure_chunk_ms() if self.chunk_ms is None else self.chunk_ms
        ticks = max(1, math.ceil(chunk_ms / loop.period_ms))
        spare = p.contract.horizon - p.contract.action_offset - p.contract.n_action_steps
        if ticks > spare:
            raise ValueError(
                f"a chunk takes {chunk_ms:.1f} ms = {ticks} ticks at {loop.control_rate_hz:g} Hz, but only "
                f"H - action_offset - H_a = {spare} {beyond}"
            )
        return ticks

    def start(self, loop: ChunkedControl, inputs: dict[str, np.ndarray]) -> Future:  # a refusal: from result()
        pool = ThreadPoolExecutor(1)
        job = pool.submit(timed, partial(loop.policy.denoise, inputs, seed=loop.chunk_seed()))
        pool.shutdown(wait=False)
        return job


@dataclass(frozen=True)
class SimulatedDelay:
    """The simulation's inference delay (``dssp-sim eval --inject-delay MS``, in lockstep): every chunk is computed at
    once but usable only ``ticks`` ticks after the observation it was computed from, as if its computation took that
    long (a delay beyond what H covers leaves ticks with no action)."""

    ticks: int = 0

    def __post_init__(self):
        if not (_number(self.ticks, (int, np.integer)) and self.ticks >= 0):
            raise SettingError("SimulatedDelay.ticks must be a whole number of ticks >= 0, got {got!r}", got=self.ticks)

    def ahead_ticks(self, *_) -> int:
        return self.ticks

    now_ticks = property(ahead_ticks)  # computed now or ahead: usable ``ticks`` after its observation either way

    def start(self, loop: ChunkedControl, inputs: dict[str, np.ndarray]) -> Future:  # a refusal: raised here
        job = Future()
        job.set_result(timed(partial(loop.policy.denoise, inputs, seed=loop.chunk_seed())))
        return job


@dataclass(frozen=True, kw_only=True)
class Schedule:
    """Every schedule's ``delay``: where a chunk's computation time comes from. ``mode``: its name on a command line;
    ``refuses``: why another mode's setting does not go with it (else it names the setting's mode by its ``title``)."""

    delay: MeasuredDelay | SimulatedDelay = MeasuredDelay()
    mode: ClassVar[str]
    title: ClassVar[str]
    refuses: ClassVar[dict[str, str]] = {}

    def bind(self, loop: ChunkedControl) -> _Running:
        """This schedule running in ``loop`` (checked against its policy and rate: a one-line ValueError)."""
        return RUNS[type(self)](self, loop)


@dataclass(frozen=True, kw_only=True)
class Plain(Schedule):
    """The chunk for ticks [k H_a, (k+1) H_a) computed at tick k H_a from the history up to it (exactly as trained), its
    H_a actions from index action_offset. ``prefetch``: it starts ``lead`` ticks earlier (the delay in ticks; lead + H_a
    <= H - action_offset) from the history then, its first ``lead`` actions, whose time has passed, dropped (as
    diffusion_policy's real-robot loop does); one not ready when needed is waited for, reported over budget. A chunk
    needed before it is usable (a simulated delay) stalls the loop: hold, then its H_a actions from the needed tick's."""

    prefetch: bool = False
    mode = "none"


@dataclass(frozen=True, kw_only=True)
class Ensemble(Schedule):
    """Temporal ensembling (ACT: Zhao et al. 2023): a chunk every ``every`` ticks (1 to H_a), computed in the tick; the
    chunk computed at tick s predicts tick t >= s (a simulated delay: t >= s + d) with its action ``action_offset + t -
    s`` while that index is < H. Tick t's action: the mean of every such prediction weighted ``exp(-decay * i)``, i = 0
    for the oldest (ACT's convention: older ones weigh more; 0: the plain mean). H_a / ``every`` times the denoiser work
    of :class:`Plain`; a refused chunk leaves the kept chunks as they were."""

    every: int = 1
    decay: float = 0.01
    mode = "ensemble"
    title = "temporal ensembling"
    refuses = {
        "prefetch": "{prefetch} does not combine with {smoothing} ensemble: ensembling computes each chunk in the "
        "tick that first uses it; run one or the other"
    }

    def __post_init__(self):
        if not _number(self.every, (int, np.integer)):
            raise SettingError("{every} must be a whole number of ticks between chunks, got {got!r}", got=self.every)
        if self.every < 1:
            raise SettingError("{every} must be at least 1 (ticks between chunks), got {got}", got=self.every)
        if not (_number(self.decay) and math.isfinite(self.decay) and self.decay >= 0):
            raise SettingError("{decay} must be a finite number >= 0 (0: the plain mean), got {got}", got=self.decay)


@dataclass(frozen=True, kw_only=True)
class RealTimeChunking(Schedule):
    """Real-time chunking (Black et al. 2025), for a denoiser exported with ``--inpainting``: the next chunk starts every
    H_a ticks while the current one executes, each DDIM step's clean prediction pulled to the current chunk's actions
    (:func:`rtc_weights`: 1 before its observation and for the d delay ticks, then decaying to 0), and takes over d ticks
    after its observation. On the robot it runs in a background thread (d + H_a <= H - action_offset); a tick with no
    chunk ready waits and is reported over budget."""

    mode = "rtc"
    refuses = {
        "prefetch": "{prefetch} does not combine with {smoothing} rtc: real-time chunking computes the next chunk "
        "in the background itself; drop {prefetch}"
    }


MODES: dict[str, type[Schedule]] = {config.mode: config for config in (Plain, Ensemble, RealTimeChunking)}


def config_for(smoothing: str = "none", **given) -> Schedule:
    """The config of the mode named ``smoothing`` (:data:`MODES`) with the settings ``given`` (None: the default), as a
    command line gives them; a mode or a setting it has no field for is a :class:`SettingError`."""
    if smoothing not in MODES:
        raise SettingError("{smoothing} must be one of " + ", ".join(MODES) + ", got {got!r}", got=smoothing)
    config = MODES[smoothing]
    given = {key: value for key, value in given.items() if value is not None}
    for key in given:
        if key not in {f.name for f in fields(config)}:
            owner = next(c for c in MODES.values() if key in {f.name for f in fields(c)})
            raise SettingError(
                config.refuses.get(key)
                or f"{{{key}}} is a setting of {owner.title}: it goes with {{smoothing}} {owner.mode}"
            )
    return config(**given)


class _Running:
    """A schedule bound to ``loop``; its newest chunk ``chunk`` (B, H, A) or None, with ``chunk_offset`` its index for
    tick ``chunk_start``. ``act(t, info)``: tick t's action (B, A) or None; a refused chunk raises, the state unchanged."""

    def __init__(self, config: Schedule, loop: ChunkedControl):
        self.config, self.loop, self.policy = config, loop, loop.policy

    def reset(self) -> None:
        self.chunk: np.ndarray | None = None
        self.chunk_offset = self.chunk_start = 0

    def settings(self) -> dict:
        """For a run's log: {smoothing (the mode), ensemble_every, ensemble_decay, rtc_delay_ticks, injected_delay_ticks}."""
        delay = self.config.delay
        return {
            "smoothing": self.config.mode,
            "ensemble_every": None,
            "ensemble_decay": None,
            "rtc_delay_ticks": None,
            "injected_delay_ticks": delay.ticks if isinstance(delay, SimulatedDelay) else None,
        }

    def _take(self, info: TickInfo) -> tuple[int, np.ndarray]:
        """The chunk in flight, its time come: (its observation tick, chunk (B, H, A)); waited for if still computing."""
        start, job = self.in_flight
        self.in_flight = None  # taken, whether its chunk is used or refused
        w0, late = time.perf_counter(), not job.done()
        chunk, info.chunk_ms = job.result()
        info.waited_ms = (time.perf_counter() - w0) * 1e3
        if late:
            info.over_budget = True
            info.events.append(f"chunk not ready at tick {info.tick}: waited {info.waited_ms:.1f} ms (over budget)")
        info.new_chunk = True
        return start, chunk


class PlainRun(_Running):
    """:class:`Plain` running: ``lead`` (0 without prefetch), ``in_flight`` (the next chunk's observation tick and
    computation), ``exec_end`` (the tick the current chunk's H_a actions end at)."""

    def __init__(self, config: Plain, loop: ChunkedControl):
        super().__init__(config, loop)
        self.lead = (
            config.delay.ahead_ticks(
                loop, "prefetch", "predicted actions can be dropped; run without prefetch or at a lower rate"
            )
            if config.prefetch
            else 0
        )

    def reset(self) -> None:
        super().reset()
        self.in_flight, self.exec_end = None, 0

    def _execute(self, t: int, start: int, chunk: np.ndarray) -> None:
        """``chunk``, observed at tick ``start``, takes over at tick t with its action for the tick it was needed at."""
        self.chunk, self.chunk_offset = chunk, self.policy.contract.action_offset + max(0, self.exec_end - start)
        self.chunk_start, self.exec_end = t, t + self.policy.contract.n_action_steps

    def act(self, t: int, info: TickInfo) -> np.ndarray | None:
        delay = self.config.delay
        if self.in_flight is not None and t >= max(self.exec_end, self.in_flight[0] + delay.now_ticks):
            self._execute(t, *self._take(info))
        if self.in_flight is None and t >= self.exec_end and not delay.now_ticks:  # needed now, usable now
            self._execute(t, t, self.loop.compute(info))
        if self.in_flight is None and t >= self.exec_end - self.lead:  # ahead, or to be waited for (simulated)
            self.in_flight = (t, delay.start(self.loop, self.policy.denoiser_inputs()))
        index = self.chunk_offset + t - self.chunk_start
        if self.chunk is None or t >= self.exec_end or index >= self.policy.contract.horizon:
            return None
        info.chunk_index = index
        return self.chunk[:, index]


class EnsembleRun(_Running):
    """:class:`Ensemble` running: ``kept`` [(tick computed at, chunk (B, H, A))], oldest first, and ``arriving``, those
    not usable yet (a simulated delay); ``chunk``: the newest, shown as to come."""

    def __init__(self, config: Ensemble, loop: ChunkedControl):
        super().__init__(config, loop)
        if config.every > (ha := loop.policy.contract.n_action_steps):
            raise SettingError(
                "{every} {got}: the model executes H_a = {ha} actions of a chunk, so a chunk is needed "
                "at least every {ha} ticks (1 to {ha})",
                got=config.every,
                ha=ha,
            )

    def reset(self) -> None:
        super().reset()
        self.kept, self.arriving = [], []

    def settings(self) -> dict:
        return {
            **super().settings(),
            "ensemble_every": int(self.config.every),
            "ensemble_decay": float(self.config.decay),
        }

    def act(self, t: int, info: TickInfo) -> np.ndarray | None:
        offset, d, arriving = self.policy.contract.action_offset, self.config.delay.now_ticks, self.arriving
        if t % self.config.every == 0:
            chunk = self.loop.compute(info)  # a refused chunk raises here: the kept chunks are left as they were
            arriving = [*arriving, (t, chunk)]
            self.chunk, self.chunk_offset, self.chunk_start = chunk, offset, t
        kept = [*self.kept, *[(s, c) for s, c in arriving if t >= s + d]]
        self.arriving = [(s, c) for s, c in arriving if t < s + d]
        # A chunk computed at tick s predicts ticks s .. s + H - offset - 1; without a delay the newest always covers t
        # (t - s < every <= H_a <= H - offset).
        self.kept = kept = [(s, c) for s, c in kept if offset + t - s < c.shape[1]]
        if not kept:  # a simulated delay: no chunk has come yet
            info.predictions = 0
            return None
        predictions = np.stack([c[:, offset + t - s] for s, c in kept])  # (n, B, A), oldest first
        weights = np.exp(-self.config.decay * np.arange(len(kept)))  # ACT: the oldest weighs most
        action = np.tensordot(weights / weights.sum(), predictions.astype(np.float64), axes=1)
        info.chunk_index = offset + t - self.chunk_start
        info.predictions = len(kept)
        return action.astype(predictions.dtype)


class RealTimeRun(_Running):
    """:class:`RealTimeChunking` running: ``delay`` d (ticks), ``in_flight``, ``next_start`` (the next chunk's tick)."""

    def __init__(self, config: RealTimeChunking, loop: ChunkedControl):
        super().__init__(config, loop)
        if not loop.policy.contract.inpainting:
            raise ValueError(
                "real-time chunking needs a denoiser that takes the committed actions: export the model "
                "with python -m export.to_onnx --inpainting"
            )
        self.delay = config.delay.ahead_ticks(
            loop,
            "real-time chunking",
            "ticks beyond its H_a are covered by a chunk: real-time chunking cannot keep up; run at a lower rate",
        )

    def reset(self) -> None:
        super().reset()
        self.in_flight, self.next_start = None, 0

    def settings(self) -> dict:
        return {**super().settings(), "rtc_delay_ticks": self.delay}

    def _take_due(self, t: int, info: TickInfo) -> None:
        """The chunk in flight becomes the current one once d ticks have passed since its observation."""
        if self.in_flight is not None and t >= self.in_flight[0] + self.delay:
            self.chunk_start, self.chunk = self._take(info)
            self.chunk_offset = self.policy.contract.action_offset + (t - self.chunk_start)

    def act(self, t: int, info: TickInfo) -> np.ndarray | None:
        p, offset, horizon = self.policy, self.policy.contract.action_offset, self.policy.contract.horizon
        self._take_due(t, info)
        if self.in_flight is None and (self.chunk is None and t == 0 or t >= self.next_start):
            committed = weight = None
            if self.chunk is not None:  # new index i is the tick t + i - offset: the current chunk's index i + shift
                shift = t - self.chunk_start
                covered = max(0, horizon - shift)
                committed = np.zeros_like(self.chunk)
                committed[:, :covered] = self.chunk[:, shift:]
                weight = rtc_weights(horizon, offset, covered, self.delay)[None, :, None]
            self.in_flight = (t, self.config.delay.start(self.loop, p.denoiser_inputs(committed, weight)))
            self.next_start = t + p.contract.n_action_steps
            self._take_due(t, info)  # no delay: the chunk takes over at once
        index = offset + t - self.chunk_start
        if self.chunk is None or index >= horizon:  # none yet, or it ran out before the next took over: hold
            return None
        info.chunk_index = index
        return self.chunk[:, index]


RUNS: dict[type[Schedule], type[_Running]] = {Plain: PlainRun, Ensemble: EnsembleRun, RealTimeChunking: RealTimeRun}
