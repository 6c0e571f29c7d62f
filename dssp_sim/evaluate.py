"""Closed-loop evaluation in the simulation, through the robot's own chain.

    result = evaluate("models/tap", "tap", n_episodes=20, seed=1000)
    result = evaluate(None, "tap", n_episodes=20, seed=1000)      # the scripted expert through the same loop
    result = evaluate("models/tap", "tap", 20, schedule=Ensemble(every=1))   # ACT's temporal ensembling

Each episode: the MuJoCo env is reset with its seed; its depth render goes through the RealSense software
device and the point-cloud pipeline (:class:`~dssp_sim.mujoco_camera.MujocoCamera`, ``dssp_data.pointcloud``);
the runtime (``dssp_deploy.OnnxPolicy``) runs the control loop of ``dssp-run`` (``hardware.run_loop.Runner``
with the model as its policy source, ``hardware.policies.exported_model``: the history every tick, a chunk every H_a
ticks, the safety layer); commands go as Piper CAN frames on a python-can ``virtual`` bus to
:class:`~dssp_sim.mujoco_arm.MujocoPiper`, which moves the MuJoCo arm. Without a model the task's scripted expert
is the loop's source (:class:`dssp_sim.expert_policy.ScriptedExpert`): the task's ceiling through the same chain.

The loop runs in lockstep with simulated time: each tick advances the physics one control period, then
renders, then runs the policy. The simulation waits for the policy, so the safety layer's deadline rule
is off here (latency is measured and reported instead; ``dssp-profile`` and ``dssp-run`` judge it).

``state_token_noise`` (σ) adds Gaussian noise to the N most recent state tokens z at every chunk (the
paper's robustness test, Table 4); the context token c_t is left as computed. Every evaluation records the
tokens' RMS per element (``z_rms``, before any noise), so σ reads against the tokens' own scale.
"""

from __future__ import annotations

import math
import sys
import threading
import time
import uuid
from collections import Counter
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from dssp_core.errors import ConfigError, NonFiniteObservation
from dssp_core.output_guard import OutputKind
from dssp_data.pointcloud import frame_to_cloud
from dssp_deploy.control_loop import ChunkedControl
from dssp_deploy.onnx_policy import OnnxPolicy
from dssp_deploy.ranges import ChunkOutOfRange, ObservationOutOfRange
from dssp_deploy.schedules import Plain, Schedule, SimulatedDelay
from dssp_sim.expert_policy import ScriptedExpert
from dssp_sim.mujoco_arm import MujocoPiper
from dssp_sim.mujoco_camera import MujocoCamera
from dssp_sim.settings import cloud_config_for
from dssp_sim.strips import save_strip
from hardware.cli.schedule_flags import refusal
from hardware.pacing import latency_stats
from hardware.piper.arm import PiperArm
from hardware.piper.piper_robot import PiperRobot
from hardware.policies import PolicySource
from hardware.policies.exported_model import ModelPolicy
from hardware.rig import Rig
from hardware.run_loop import LoopSettings, Runner
from hardware.safety import SafetyConfig
from hardware.subscribers import Subscriber, Tick
from hardware.subscribers.rerun_ticks import RerunTicks

# Lockstep: inputs are fresh by construction; generous timeouts only catch a stalled bridge.
EVAL_SAFETY = SafetyConfig(camera_timeout=2.0, feedback_timeout=2.0, deadline_hold=False)


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson score interval of a success rate (0, 0 for n = 0)."""
    if n == 0:
        return 0.0, 0.0
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


@dataclass
class EpisodeOutcome:
    seed: int
    success: bool
    reason: str
    steps: int
    info: dict
    holds: int
    safety_events: dict
    chunk_ms_p50: float | None
    decision: dict = field(default_factory=dict)  # the memory decision (dssp_sim.tasks.Task.decision)
    jerk: dict = field(default_factory=dict)  # commanded jerk at chunk boundaries and elsewhere (command_jerk)

    def to_dict(self) -> dict:
        return asdict(self)


def command_jerk(commands: list, boundaries: list[bool], control_rate_hz: float) -> dict:
    """The commanded joints' jerk per tick, ‖q[t+1] - 3 q[t] + 3 q[t-1] - q[t-2]‖ × rate³ (rad/s³, J1..J6 of each arm),
    split into the ticks a new chunk took over at (t: its first command) and the others; ``commands``: each tick's
    sent command (dof,) or None (nothing sent), ``boundaries``: whether a new chunk took over at that tick. Returns
    {at_boundaries, boundary_ticks, elsewhere, other_ticks} (means; None where no tick of that kind had 4 commands)."""
    at, off = [], []
    for t in range(2, len(commands) - 1):
        window = commands[t - 2 : t + 2]
        if any(c is None for c in window):
            continue
        q = np.asarray(window, dtype=np.float64)
        q = q.reshape(4, -1, 7)[:, :, :6].reshape(4, -1)  # the joints, not the grippers
        jerk = float(np.linalg.norm(q[3] - 3 * q[2] + 3 * q[1] - q[0])) * control_rate_hz**3
        (at if boundaries[t] else off).append(jerk)
    return {
        "at_boundaries": float(np.mean(at)) if at else None,
        "boundary_ticks": len(at),
        "elsewhere": float(np.mean(off)) if off else None,
        "other_ticks": len(off),
    }


class _Waits:
    """A policy source that counts the ticks it answered with no action (waiting for a chunk), else the source."""

    def __init__(self, source: PolicySource):
        self.source, self.count = source, 0

    def act(self, cloud, state):
        out = self.source.act(cloud, state)
        self.count += out.action is None
        return out

    def __getattr__(self, name: str):
        return getattr(self.source, name)


class _CommandTrace(Subscriber):
    """Each tick's sent command and whether a new chunk took over (for :func:`command_jerk`)."""

    def __init__(self):
        self.commands: list = []
        self.boundaries: list[bool] = []

    def on_tick(self, tick: Tick) -> None:
        command = tick.record.get("command")
        self.commands.append(None if command is None else np.array(command, dtype=np.float64))
        self.boundaries.append(tick.chunk is not None)


@dataclass
class EvalResult:
    model_dir: str
    task: str
    episodes: list[EpisodeOutcome] = field(default_factory=list)
    state_token_noise: float = 0.0
    latency_ms: dict = field(default_factory=dict)
    precision: str = ""  # the graphs that ran: "fp32", "int8" or "int4"; "fused" or "standard"
    kernel: str = ""
    z_rms: float | None = None  # RMS per element of the recent state tokens the denoiser saw, before noise
    smoothing: str = "none"  # the loop's schedule (dssp_deploy.schedules.MODES); the ensemble's settings or None
    ensemble_every: int | None = None
    ensemble_decay: float | None = None
    injected_delay_ms: float = 0.0  # the inference delay simulated per chunk (--inject-delay), and in control ticks
    injected_delay_ticks: int = 0
    rtc_delay_ticks: int | None = None
    model: dict | None = None  # the model scored (scored_model); None: the expert
    limit_excludes_holds: bool = False  # the task's step limit did not count the ticks the loop held

    @property
    def successes(self) -> int:
        return sum(e.success for e in self.episodes)

    @property
    def success_rate(self) -> float:
        return self.successes / max(1, len(self.episodes))

    def interval(self) -> tuple[float, float]:
        return wilson_interval(self.successes, len(self.episodes))

    def reasons(self) -> Counter:
        return Counter(e.reason for e in self.episodes if not e.success)

    def decisions(self) -> dict:
        """The memory decision apart from the manipulation: episodes that reached it, how many decided right, and
        what was chosen (e.g. tap's count of presses, its confusion row)."""
        reached = [e.decision for e in self.episodes if e.decision.get("reached")]
        return {
            "reached": len(reached),
            "correct": sum(bool(d["correct"]) for d in reached),
            "choices": dict(Counter(d["choice"] for d in reached)),
        }

    def to_dict(self) -> dict:
        lo, hi = self.interval()
        return {
            "model_dir": self.model_dir,
            "model": self.model,
            "task": self.task,
            "n": len(self.episodes),
            "successes": self.successes,
            "success_rate": self.success_rate,
            "wilson95": [lo, hi],
            "state_token_noise": self.state_token_noise,
            "z_rms": self.z_rms,
            "noise_over_z_rms": self.state_token_noise / self.z_rms if self.z_rms else None,
            "failure_reasons": dict(self.reasons()),
            "decisions": self.decisions(),
            "latency_ms": self.latency_ms,
            "precision": self.precision,
            "kernel": self.kernel,
            "smoothing": self.smoothing,
            "ensemble_every": self.ensemble_every,
            "ensemble_decay": self.ensemble_decay,
            "injected_delay_ms": self.injected_delay_ms,
            "injected_delay_ticks": self.injected_delay_ticks,
            "rtc_delay_ticks": self.rtc_delay_ticks,
            "limit_excludes_holds": self.limit_excludes_holds,
            "boundary_jerk": self.boundary_jerk(),
            "episodes": [e.to_dict() for e in self.episodes],
        }

    def boundary_jerk(self) -> dict | None:
        """The commanded joints' jerk (rad/s³, :func:`command_jerk`) at the ticks a new chunk took over and at the
        other ticks, averaged over every such tick of every episode (None: no episode was traced)."""
        traced = [e.jerk for e in self.episodes if e.jerk]
        if not traced:
            return None
        out = {}
        for kind, count in (("at_boundaries", "boundary_ticks"), ("elsewhere", "other_ticks")):
            n = sum(j[count] for j in traced)
            total = sum(j[kind] * j[count] for j in traced if j[kind] is not None)
            out[kind], out[count] = (total / n if n else None), n
        return out


def _wait_for_feedback(robot, after: float, timeout: float = 2.0) -> None:
    deadline = time.monotonic() + timeout
    while True:
        state = robot.state()
        if state is not None and state.timestamp > after:
            return
        if time.monotonic() > deadline:
            raise TimeoutError("the simulated arm's feedback did not arrive")
        time.sleep(0.0005)


class _RecentStates:
    """Whenever the denoiser's inputs are taken: records z_recent's mean square per element, then adds N(0, σ²)
    to it (σ > 0)."""

    def __init__(self, policy, sigma: float, rng: np.random.Generator):
        self.policy, self.sigma, self.rng = policy, sigma, rng
        self.original = policy.denoiser_inputs
        self.mean_squares: list[float] = []

    def __call__(self, *args, **kwargs):
        feeds = self.original(*args, **kwargs)
        if "z_recent" in feeds:
            z = feeds["z_recent"]
            self.mean_squares.append(float(np.mean(np.square(z, dtype=np.float64))))
            if self.sigma > 0:
                feeds["z_recent"] = (z + self.rng.normal(0.0, self.sigma, z.shape)).astype(np.float32)
        return feeds

    def rms(self) -> float | None:
        return float(np.sqrt(np.mean(self.mean_squares))) if self.mean_squares else None


def run_episode(
    source: PolicySource,
    env,
    seed: int,
    cloud_config,
    frames: list | None = None,
    latencies: dict[str, list[float]] | None = None,
    views=None,
    limit_excludes_holds: bool = False,
) -> EpisodeOutcome:
    """One closed-loop episode (env already constructed; it is reset here with ``seed``) of the control loop with
    ``source`` deciding (:mod:`hardware.policies`; reset by the loop at its start). ``cloud_config``: the
    point-cloud settings (None: a source that needs no cloud). ``limit_excludes_holds``: each tick the source waits
    for a chunk (it answers no action; a refused observation or chunk is no wait) adds one to the task's step limit,
    so that waiting is not scored as running out of time.

    ``frames`` collects each tick's depth image; ``latencies`` each tick's latencies in ms by stage
    (cloud, observe, chunk, tick), when given; ``views`` (:class:`dssp_data.rerun_views.TickViews`) get every
    tick, continuing their timeline after the previous episode's."""

    env.reset(seed=seed)
    waits = _Waits(source)
    if limit_excludes_holds:
        source = waits
    channel = f"dssp-eval-{uuid.uuid4().hex[:8]}"
    arm = MujocoPiper(env, channel)
    arm.start(thread=False)
    robot = PiperRobot([PiperArm(channel, "virtual")])
    camera = MujocoCamera(env)
    rig = Rig(camera, robot, camera.camera_to_base, EVAL_SAFETY)
    period = 1.0 / env.control_rate_hz
    try:
        with rig:
            stop_pump = threading.Event()

            def pump():  # answer the driver (enable) without advancing the physics
                while not stop_pump.is_set():
                    arm.step(0.0)
                    time.sleep(0.003)

            pumper = threading.Thread(target=pump, daemon=True)
            pumper.start()
            try:
                camera.capture()
                trace = _CommandTrace()
                subscribers = [trace] + ([RerunTicks(views)] if views is not None else [])
                runner = Runner(
                    source,
                    rig,
                    cloud_config,
                    LoopSettings(control_rate_hz=env.control_rate_hz),
                    subscribers=subscribers,
                )
                if views is not None:
                    views.text(subscribers[1].next_tick, "episode", f"{env.task.name} seed {seed}")
                runner.start()
            finally:
                stop_pump.set()
                pumper.join()
            status = env.status()
            while not status.done and runner.fault is None:
                before, waited = time.monotonic(), waits.count
                arm.step(period)
                camera.capture()
                _wait_for_feedback(robot, before)
                runner.tick()
                env.max_steps += waits.count - waited
                if frames is not None:
                    frames.append(camera.latest().depth.copy())
                status = env.status()
            runner.finish("episode over")
            runner.close()
    finally:
        arm.stop()
    chunk = runner.latencies["chunk"]
    if latencies is not None:
        for key, values in runner.latencies.items():
            latencies.setdefault(key, []).extend(values)
    reason = status.reason if status.done else f"fault: {runner.fault}"
    return EpisodeOutcome(
        seed=seed,
        success=bool(status.done and status.success),
        reason="" if status.success else reason,
        steps=env.steps,
        info=dict(status.info),
        holds=runner.holds,
        safety_events=dict(runner.event_counts),
        chunk_ms_p50=float(np.median(chunk)) if chunk else None,
        decision=env.task.decision(dict(status.info)),
        jerk=command_jerk(trace.commands, trace.boundaries, env.control_rate_hz),
    )


def run_direct_episode(
    policy,
    env,
    seed: int,
    cloud_config,
    frames: list | None = None,
    latencies: dict[str, list[float]] | None = None,
    schedule: Schedule = Plain(),
) -> EpisodeOutcome:
    """One closed-loop episode of an env whose arm is stepped directly, not over CAN (MetaWorld's Sawyer,
    :class:`~dssp_sim.metaworld_env.MetaWorldEnv`): render → point-cloud pipeline → runtime
    (``dssp_deploy.ChunkedControl``: the history every tick, a chunk every H_a) → ``env.step``. ``schedule``:
    ChunkedControl's (a :mod:`dssp_deploy.schedules` config).

    A tick the runtime refuses (NaN/inf or an out-of-range observation, a refused chunk) holds (``env.hold()``)
    and is counted in ``holds`` and ``safety_events``; the next tick goes on."""

    env.reset(seed=seed)
    loop = ChunkedControl(policy, schedule, control_rate_hz=env.control_rate_hz, seed=seed)
    camera = MujocoCamera(env)
    holds, events = 0, Counter()
    stages: dict[str, list[float]] = {"cloud": [], "observe": [], "chunk": [], "tick": []}
    with camera:
        status = env.status()
        while not status.done:
            t0 = time.perf_counter()
            frame = camera.capture()
            cloud, _ = frame_to_cloud(frame, cloud_config, camera.camera_to_base)
            t1 = time.perf_counter()
            stages["cloud"].append((t1 - t0) * 1e3)
            try:
                action, info = loop.tick(cloud, env.state())
            except (NonFiniteObservation, ObservationOutOfRange, ChunkOutOfRange) as e:
                holds += 1
                events[type(e).__name__] += 1
                env.hold()
            else:
                stages["observe"].append(info.observe_ms)
                if info.chunk_ms is not None:
                    stages["chunk"].append(info.chunk_ms)
                if action is None:  # no chunk usable yet (a simulated delay): hold
                    holds += 1
                    events["no_chunk_yet"] += 1
                    env.hold()
                else:
                    env.step(action[0])
            stages["tick"].append((time.perf_counter() - t0) * 1e3)
            if frames is not None:
                frames.append(frame.depth.copy())
            status = env.status()
    if latencies is not None:
        for key, values in stages.items():
            latencies.setdefault(key, []).extend(values)
    chunk = stages["chunk"]
    return EpisodeOutcome(
        seed=seed,
        success=status.success,
        reason=status.reason,
        steps=env.steps,
        info=dict(status.info),
        holds=holds,
        safety_events=dict(events),
        chunk_ms_p50=float(np.median(chunk)) if chunk else None,
    )


STRIPS_DIR = OutputKind("a folder of episode strips", "dssp-sim eval", entries=("*.png",))
"""``dssp-sim eval --strips``: one PNG per episode (``TASK_seedS.png``), written all at once."""


@dataclass
class Evaluation:
    """An evaluation with every setting checked, its model loaded and its task built, before any output is opened
    (:func:`prepare_evaluation`); :meth:`run` plays its episodes."""

    result: EvalResult
    env: Any
    episode: Callable  # (seed, frames, ticks, views) -> EpisodeOutcome
    n_episodes: int
    seed: int
    recent: _RecentStates | None = None

    def run(self, strips_dir: Path | None = None, progress: bool = True, views=None) -> EvalResult:
        """Episodes seed, seed + 1, ... (their strips into ``strips_dir``; ``views``: Rerun views of every tick, closed
        by the caller); the environment is closed after."""

        def episode(s, frames, ticks):
            return self.episode(s, frames, ticks, views)

        _run_episodes(self.result, self.env, episode, self.n_episodes, self.seed, strips_dir, progress)
        if self.recent is not None:
            self.result.z_rms = self.recent.rms()
        return self.result


def prepare_evaluation(
    model_dir: Path | None,
    task: str,
    n_episodes: int,
    seed: int = 1000,
    threads: int | None = None,
    state_token_noise: float = 0.0,
    precision: str | None = None,
    kernel: str = "auto",
    spinning: bool | None = None,
    views: bool = False,
    schedule: Schedule = Plain(),
    inject_delay_ms: float = 0.0,
    limit_excludes_holds: bool = False,
) -> Evaluation:
    """Check every setting against the model and the task, load the model and build the task; nothing is opened
    or written. Episodes are seeded ``seed``, ``seed`` + 1, ...; ``precision`` and ``kernel`` choose the graphs
    (:class:`dssp_deploy.onnx_policy.OnnxPolicy`); ``schedule``: the control loop's (a :mod:`dssp_deploy.schedules`
    config, on either kind of task); ``inject_delay_ms``: its delay, each chunk usable only that long after its
    observation, in whole control ticks (rounded up: at 10 Hz 50 and 100 ms are one tick;
    :class:`~dssp_deploy.schedules.SimulatedDelay`) — the inference delay simulated in lockstep;
    ``limit_excludes_holds``: the ticks spent waiting for a chunk leave the step limit (:func:`run_episode`);
    ``views``: whether Rerun views will be given to :meth:`Evaluation.run`. ``model_dir`` None: the task's scripted
    expert drives the same loop (:class:`dssp_sim.expert_policy.ScriptedExpert`; Piper tasks)."""
    from dssp_sim import metaworld_env  # deferred: loads mujoco

    if metaworld_env.is_metaworld(task) and limit_excludes_holds:
        raise ConfigError("--limit-excludes-holds counts the Piper loop's holds; MetaWorld evaluations have none")
    if metaworld_env.is_metaworld(task) and views:
        raise ConfigError(
            "--rerun views show the Piper's control loop; MetaWorld evaluations have none (drop the flag)"
        )
    if not (math.isfinite(inject_delay_ms) and 0 <= inject_delay_ms <= 10_000):
        raise ConfigError(f"--inject-delay must be in [0, 10000] ms, got {inject_delay_ms:g}")
    if model_dir is None:
        if schedule != Plain():
            raise ConfigError(
                "smoothing is the model's control loop's: the scripted expert gives each tick's action itself"
            )
        return _prepare_expert(task, n_episodes, seed)
    policy = OnnxPolicy(model_dir, threads=threads, precision=precision, kernel=kernel, spinning=spinning)
    recent = policy.denoiser_inputs = _RecentStates(policy, state_token_noise, np.random.default_rng(seed))
    # The model's own point-cloud settings (its observation contract), as dssp-run uses them; a model trained on
    # data that recorded none sees the simulation's settings at its point count.
    n_points = policy.contract.n_points
    if metaworld_env.is_metaworld(task):
        metaworld_env.check_model_dims(policy.contract, model_dir)
        env = metaworld_env.MetaWorldEnv(task, seed=seed)
        cloud_config = policy.contract.observation.pointcloud or metaworld_env.cloud_config(n_points)

        def episode(s, frames, ticks, views):
            return run_direct_episode(policy, env, s, cloud_config, frames, ticks, schedule)
    else:
        from dssp_sim.env import PiperEnv  # deferred: loads mujoco

        env = PiperEnv(task, seed=seed)
        cloud_config = policy.contract.observation.pointcloud or cloud_config_for(n_points, task)

        def episode(s, frames, ticks, views):
            return run_episode(
                ModelPolicy(policy, env.control_rate_hz, seed=s, schedule=schedule),
                env,
                s,
                cloud_config,
                frames,
                ticks,
                views,
                limit_excludes_holds,
            )

    # the delay in the loop's ticks (the simulation's rate): the schedule's, read when each episode starts
    delay_ticks = math.ceil(inject_delay_ms * env.control_rate_hz / 1000 - 1e-9) if inject_delay_ms > 0 else 0
    schedule = replace(schedule, delay=SimulatedDelay(delay_ticks))
    try:  # bad settings: one line now, not a failure in the first episode
        settings = ChunkedControl(policy, schedule, control_rate_hz=env.control_rate_hz).schedule.settings()
    except ValueError as exc:
        env.close()
        raise refusal(exc, "smoothing") from None
    print(f"graphs: {policy.kernel_note}", file=sys.stderr)
    result = EvalResult(
        str(model_dir),
        task,
        state_token_noise=state_token_noise,
        precision=policy.precision,
        kernel=policy.kernel,
        injected_delay_ms=float(inject_delay_ms),
        limit_excludes_holds=limit_excludes_holds,
        model=scored_model(policy),
        **settings,
    )
    return Evaluation(result, env, episode, n_episodes, seed, recent)


def scored_model(policy) -> dict:
    """What names the model an evaluation scored: its weights' sha256, training run and step (the manifest's
    ``source``) and the sha256 of its ``dssp_model.json``, which holds every graph file's sha256."""
    from dssp_deploy.manifest import MANIFEST_NAME, sha256_hex  # deferred: loads numpy

    source = policy.manifest.source
    manifest = sha256_hex((Path(policy.model_dir) / MANIFEST_NAME).read_bytes())
    return {"weights_sha256": source.sha256, "run": source.run, "step": source.step, "manifest_sha256": manifest}


def evaluate(
    model_dir: Path | None,
    task: str,
    n_episodes: int,
    *,
    strips_dir: Path | None = None,
    progress: bool = True,
    views=None,
    **settings,
) -> EvalResult:
    """Evaluate a model directory on ``task`` for ``n_episodes`` seeded episodes: :func:`prepare_evaluation` with
    ``settings`` (its keyword arguments: seed, threads, precision, kernel, schedule, inject_delay_ms, ...), then
    :meth:`Evaluation.run` (each episode's strip into ``strips_dir``; ``views``: Rerun views of every tick of every
    episode, on one timeline, closed by the caller)."""
    evaluation = prepare_evaluation(model_dir, task, n_episodes, views=views is not None, **settings)
    return evaluation.run(strips_dir, progress, views)


def _prepare_expert(task: str, n_episodes: int, seed: int) -> Evaluation:
    """``dssp-sim eval --expert``: the task's scripted expert as the loop's policy source."""
    from dssp_sim import metaworld_env  # deferred: loads mujoco
    from dssp_sim.env import PiperEnv  # deferred: loads mujoco

    if metaworld_env.is_metaworld(task):
        raise ConfigError(
            f"--expert drives the Piper's control loop; {task} has no Piper (its expert's demonstrations: "
            "dssp-sim collect)"
        )
    env = PiperEnv(task, seed=seed)

    def episode(s, frames, ticks, views):
        return run_episode(ScriptedExpert(env), env, s, None, frames, ticks, views)

    return Evaluation(EvalResult("expert", task), env, episode, n_episodes, seed)


def _run_episodes(
    result: EvalResult, env, episode, n_episodes: int, seed: int, strips_dir: Path | None, progress: bool
) -> None:
    """Episodes seed, seed + 1, ... into ``result`` (and their strips into ``strips_dir``); the env closed after."""
    bar = None
    if progress:
        from tqdm import tqdm  # deferred: loads tqdm; dssp-demo and the studies import this module at start-up

        bar = tqdm(total=n_episodes, desc=f"eval {result.task}", unit="episode")
    wall = []
    ticks: dict[str, list[float]] = {}
    try:
        for i in range(n_episodes):
            frames = [] if strips_dir is not None else None
            t0 = time.perf_counter()
            outcome = episode(seed + i, frames, ticks)
            wall.append(time.perf_counter() - t0)
            result.episodes.append(outcome)
            if frames:
                save_strip(
                    frames,
                    Path(strips_dir) / f"{result.task}_seed{seed + i}.png",
                    f"{result.task} seed {seed + i}: {'success' if outcome.success else outcome.reason}",
                )
            if bar is not None:
                bar.update(1)
                bar.set_postfix(success=f"{result.successes}/{i + 1}")
    finally:
        env.close()
    if bar is not None:
        bar.close()
    result.latency_ms = {key: latency_stats(v) for key, v in ticks.items() if v}
    result.latency_ms["episode_wall_s_p50"] = float(np.median(wall)) if wall else None


def print_eval(result) -> None:
    lo, hi = result.interval()
    print(
        f"\n{result.task}: success {result.successes}/{len(result.episodes)} = {100 * result.success_rate:.0f} % "
        f"(95 % Wilson interval {100 * lo:.0f}–{100 * hi:.0f} %)"
        + (f", state-token noise σ={result.state_token_noise:g}" if result.state_token_noise else "")
        + (
            f" ({result.state_token_noise / result.z_rms:.2f} x the tokens' RMS {result.z_rms:.2f})"
            if result.state_token_noise and result.z_rms
            else ""
        )
        + (
            f", temporal ensembling (a chunk every {result.ensemble_every} ticks, decay {result.ensemble_decay:g})"
            if result.smoothing == "ensemble"
            else ""
        )
        + (f", real-time chunking (d = {result.rtc_delay_ticks} ticks)" if result.smoothing == "rtc" else "")
        + (
            f", inference delay {result.injected_delay_ms:g} ms injected ({result.injected_delay_ticks} ticks)"
            if result.injected_delay_ms
            else ""
        )
    )
    jerk = result.boundary_jerk()
    if jerk and jerk["at_boundaries"] is not None:
        print(
            f"commanded jerk: {jerk['at_boundaries']:.1f} rad/s³ at the {jerk['boundary_ticks']} ticks a new chunk took "
            f"over, {jerk['elsewhere'] or 0:.1f} at the other {jerk['other_ticks']}"
        )
    print("| seed | outcome | steps | detail | holds |")
    print("|---:|---|---:|---|---:|")
    for e in result.episodes:
        detail = ", ".join(f"{k}={v}" for k, v in e.info.items() if isinstance(v, (int, float, str, bool)))
        print(f"| {e.seed} | {'success' if e.success else e.reason} | {e.steps} | {detail} | {e.holds} |")
    if result.reasons():
        print("failures: " + ", ".join(f"{k} × {v}" for k, v in result.reasons().most_common()))
    d = result.decisions()
    from dssp_sim.metaworld_env import is_metaworld  # deferred: loads mujoco

    direct = is_metaworld(result.task)
    if not direct:  # MetaWorld's tasks (and the cue variant, whose success is the decision) hold no separate one
        print(
            f"memory decision: right in {d['correct']} of the {d['reached']} episodes that reached it ("
            + ", ".join(f"{k} × {v}" for k, v in sorted(d["choices"].items()))
            + ")"
        )
    print_latency(result.latency_ms, tick="whole tick (cloud + policy + step)" if direct else None)


def print_latency(lat: dict, tick: str | None = None) -> None:
    """The control loop's latencies over every tick of the evaluation (ms); ``tick``: what a whole tick holds."""
    labels = {
        "cloud": "point cloud (pipeline)",
        "observe": "history step (ORT)",
        "chunk": "denoiser chunk (ORT)",
        "tick": tick or "whole tick (cloud + policy + safety + CAN)",
    }
    print("\n| stage | p50 ms | p95 ms | max ms | ticks |")
    print("|---|---:|---:|---:|---:|")
    for key, label in labels.items():
        s = lat.get(key)
        if s:
            print(f"| {label} | {s['p50']:.2f} | {s['p95']:.2f} | {s['max']:.2f} | {s['n']} |")
    if lat.get("episode_wall_s_p50") is not None:
        print(f"one episode takes {lat['episode_wall_s_p50']:.1f} s (p50; lockstep with simulated time)")
