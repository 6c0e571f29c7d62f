"""The DSSP policy on the robot: two ONNX Runtime graphs, numpy in and out, no torch.

    policy = OnnxPolicy("models/tap")          # validates dssp_model.json against the graphs, warms up
    policy = OnnxPolicy("models/tap", precision="fp32")  # the fp32 graphs (default: DEFAULT_PRECISION's, int8)
    print(policy.kernel_note)                  # one line: which graphs run (fused Mamba kernel or standard)
    policy.reset()
    policy.observe(point_cloud, agent_pos)     # every control tick: the history-update graph
    chunk = policy.act(seed=0)                 # every H_a ticks: the denoiser graph → (B, H, A) raw units
    policy.contract.n_action_steps             # what the model promises (dssp_data.model_contract.ModelContract)

The history is kept by :class:`dssp_data.streaming_history.StreamingHistory`, the state machine of the
PyTorch streaming API (``dssp_train.model.streaming.StreamingPolicy``) too: the recurrent history state
starts at zero, the last N state tokens are kept, and at the start of an episode the first token
repeats. Point clouds with more channels than the model uses (xyz + rgb for an xyz model) are cut to the
model's channels, as in training. An observation with NaN or infinity anywhere is refused
(:class:`dssp_core.errors.NonFiniteObservation`) before any graph runs: the recurrent history would keep
it for the rest of the episode; refused, it leaves the state as it was. So is one with a value far outside
the training range (:class:`dssp_deploy.ranges.ObservationOutOfRange`), and a chunk with NaN/inf or an
action outside the action range is never returned (:class:`dssp_deploy.ranges.ChunkOutOfRange`), on every
precision: the ranges and their margin are in :mod:`dssp_deploy.ranges`.

Graphs: with ``kernel="auto"`` (the default) the ``*.fused.onnx`` graphs run when the model directory has
them and the fused Mamba library loads (:mod:`dssp_deploy.mamba_kernel`); otherwise the standard graphs,
which compute the same actions (both pass ``export.verify``). ``kernel="fused"`` refuses to fall back,
``kernel="standard"`` never uses the library. :attr:`OnnxPolicy.kernel_note` says in one line which runs and why.

Threads: ``threads`` (default: all CPUs) for both graphs; with ``background_chunks`` (the control loop's
prefetch, where a chunk is computed while ticks go on) the history graph gets one thread and the
denoiser the rest, so the tick's history step never waits for cores the chunk holds. ``spinning``: the
denoiser's threads busy-wait between its operators while a chunk runs, and sleep between chunks
(default ``None``: when the denoiser has 2 threads or more). A chunk is hundreds of operators of tens of
µs each; without spinning each one waits for a sleeping thread to wake and 2 threads gain nothing over 1.
Spinning is slower when another busy process shares the cores (``--no-spin``; README, CPU targets).

Shapes: point_cloud (B, P, C) or (P, C); agent_pos (B, S) or (S,); noise (B, H, A); chunk (B, H, A);
z_t, c_t (B, d); recent (B, N, d); state {name: (B, ...)} as the manifest's history inputs.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from dssp_data.model_contract import ModelContract
from dssp_data.streaming_history import StreamingHistory, check_finite
from dssp_deploy.mamba_kernel import kernel as find_kernel
from dssp_deploy.manifest import (
    DENOISER_GRAPH,
    GRAPHS,
    HISTORY_GRAPH,
    PRECISIONS,
    Manifest,
    ModelDirError,
    check_session,
    file_kind,
    no_inpainting,
    read_graph_files,
    read_manifest,
)
from dssp_deploy.ranges import ChunkOutOfRange, ObservationOutOfRange, model_ranges
from dssp_deploy.sessions import check_threads, default_threads, open_session

KERNELS = ("auto", "fused", "standard")
# The precision run when none is asked for: the fastest one whose closed-loop success stays inside fp32's
# 95 % interval (reports/sampling, the README's CPU table), as long as its export measured its actions within
# QUANTIZED_ACTION_BOUND of fp32's. A model directory without its graphs (exported with --quantize none), or
# whose graphs were measured further off, runs fp32, and the start-up line says why.
DEFAULT_PRECISION = "int8"
QUANTIZED_ACTION_BOUND = 0.05
"""The largest action error of a quantized graph against fp32, as a fraction of the action range (the export's
verification, ``verification.quantized`` in the manifest), at which it is still run by default."""


def quantized_action_error(manifest: Manifest, precision: str) -> float | None:
    """The worst action error of ``precision``'s graphs against fp32 that the export measured (a fraction of the
    action range), or None when the model was not verified."""
    verification = manifest.verification
    quantized = verification.get("quantized") if isinstance(verification, dict) else None
    if not isinstance(quantized, dict):
        return None
    errors = [
        q.get("action_max_abs_over_range")
        for name, q in quantized.items()
        if isinstance(q, dict) and name.removeprefix("onnx_").removesuffix("_fused") == precision
    ]
    errors = [float(e) for e in errors if isinstance(e, (int, float))]
    return max(errors) if errors else None


def default_precision(manifest: Manifest) -> tuple[str, str]:
    """(precision, why) when none is asked for: :data:`DEFAULT_PRECISION` if the model has those graphs and their
    measured error is within :data:`QUANTIZED_ACTION_BOUND`, else fp32."""
    kind = file_kind(DEFAULT_PRECISION)
    if not all(kind in manifest.graphs[g]["files"] for g in GRAPHS):
        return "fp32", f"; fp32: the model directory has no {DEFAULT_PRECISION} graphs"
    error = quantized_action_error(manifest, DEFAULT_PRECISION)
    if error is not None and error > QUANTIZED_ACTION_BOUND:
        return "fp32", (
            f"; fp32: its {DEFAULT_PRECISION} graphs' actions were {100 * error:.1f} % of the action range off "
            f"fp32's at export (more than {100 * QUANTIZED_ACTION_BOUND:.0f} %); --precision {DEFAULT_PRECISION} "
            "runs them anyway"
        )
    return DEFAULT_PRECISION, ""


def add_runtime_arguments(parser) -> None:
    """``--precision`` and ``--kernel``: which of a model directory's graphs a command runs."""
    parser.add_argument(
        "--precision",
        choices=list(PRECISIONS),
        help=f"the model's graphs to run: {', '.join(PRECISIONS)} (default {DEFAULT_PRECISION} when the model has "
        "them, else fp32; export writes all three)",
    )
    parser.add_argument(
        "--kernel",
        choices=KERNELS,
        default="auto",
        help="fused: the fused Mamba kernel's graphs (make kernel), standard: the plain ONNX graphs, "
        "auto (default): fused when the library loads, else standard",
    )
    parser.add_argument(
        "--no-spin",
        action="store_true",
        help="the chunk's threads sleep between its operators (default: with 2 threads or more they spin "
        "while a chunk runs, never between chunks; slower when another busy process shares the cores)",
    )


class GraphLoadError(ModelDirError):
    """ONNX Runtime could not load a graph file (which matched the manifest's size and sha256)."""


def choose_graphs(manifest: Manifest, precision: str, kernel: str = "auto") -> tuple[bool, str]:
    """(run the fused graphs?, why) for a model's manifest, the precision and the ``kernel`` choice.

    Raises :class:`ModelDirError` when ``kernel="fused"`` cannot be honoured."""
    if kernel not in KERNELS:
        raise ModelDirError(f"kernel must be one of {', '.join(KERNELS)}, got {kernel!r}")
    if kernel == "standard":
        return False, "standard ONNX graphs (asked for)"
    kind = file_kind(precision, fused=True)
    if not all(kind in manifest.graphs[g]["files"] for g in GRAPHS):
        why = (
            f"the model directory has no {precision} fused graphs; export it again with the kernel built (make kernel)"
        )
    else:
        found = find_kernel()
        if found.available:
            return True, f"fused Mamba kernel ({found.implementation}, {found.path.name})"
        why = f"the fused Mamba kernel is unavailable: {found.reason}"
    if kernel == "fused":
        raise ModelDirError(f"kernel fused: {why}")
    return False, f"standard ONNX graphs ({why})"


def _batch(x, rank: int, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float32)
    if a.ndim == rank - 1:
        a = a[None]
    if a.ndim != rank:
        raise ValueError(f"{name} must have {rank - 1} or {rank} dims, got shape {a.shape}")
    return np.ascontiguousarray(a)


class OnnxPolicy:
    def __init__(
        self,
        model_dir: str | Path,
        threads: int | None = None,
        spinning: bool | None = None,
        warmup: int = 2,
        precision: str | None = None,
        kernel: str = "auto",
        background_chunks: bool = False,
    ):
        if precision is not None and precision not in PRECISIONS:
            raise ModelDirError(f"precision must be one of {sorted(PRECISIONS)}, got {precision!r}")
        self.model_dir = Path(model_dir)
        self.manifest: Manifest = read_manifest(self.model_dir)  # every fact checked, see dssp_deploy.manifest
        m = self.manifest
        self.contract: ModelContract = m.contract  # what the model promises: dims, N, H, H_a, K, the rate, ...
        self.ranges = model_ranges(m.normalizers, m.contract.point_dim)  # what observe() and denoise() accept
        check_threads(threads)
        total = threads or default_threads()
        # With chunks computed in the background (prefetch) the history step and the denoiser run at the same
        # time: the history gets one thread and the denoiser the others, so they do not compete for cores.
        self.threads = (
            {HISTORY_GRAPH: 1, DENOISER_GRAPH: max(1, total - 1)} if background_chunks else dict.fromkeys(GRAPHS, total)
        )
        self.spinning = self.threads[DENOISER_GRAPH] > 1 if spinning is None else bool(spinning)
        why_precision = ""
        if precision is None:
            precision, why_precision = default_precision(m)
        self.precision = precision
        self.fused, self.kernel_note = choose_graphs(m, precision, kernel)
        self.kernel_note = f"{precision}, {self.kernel_note}{why_precision}"
        # Every other ONNX graph file of the directory is checked too (size, sha256, its external data), once, before
        # anything runs: a damaged model directory is refused as a whole, whichever graphs a fallback would take.
        chosen = file_kind(precision, self.fused)
        for graph in GRAPHS:
            for kind in m.graphs[graph]["files"]:
                if kind.startswith("onnx") and kind != chosen:
                    read_graph_files(self.model_dir, m, graph, kind)
        try:
            self.sessions = self._open_sessions()
        except GraphLoadError as exc:  # ONNX Runtime refused a fused graph (not a file or interface mismatch)
            if not self.fused or kernel == "fused":
                raise
            self.fused, self.kernel_note = (
                False,
                f"{precision}, standard ONNX graphs (the fused graphs failed to load: {exc})",
            )
            self.sessions = self._open_sessions()
        self._state_specs = [s for s in m.graphs[HISTORY_GRAPH]["inputs"] if s["name"] in m.history_state]
        self._history_outputs = [o.name for o in self.sessions[HISTORY_GRAPH].get_outputs()]
        self.history: StreamingHistory[np.ndarray] = StreamingHistory(
            m.contract.n_obs_steps, self._history_step, lambda tokens: np.stack(tokens, axis=1), self._zero_state
        )
        if warmup:
            self.warmup(warmup)

    def _open_sessions(self) -> dict[str, Any]:
        sessions = {}
        for graph in (HISTORY_GRAPH, DENOISER_GRAPH):
            # size and sha256 checked, of the graph and of each file of external data it names
            path, data, external = read_graph_files(
                self.model_dir, self.manifest, graph, file_kind(self.precision, self.fused)
            )
            try:
                spin = self.spinning and graph == DENOISER_GRAPH  # a history step is too short to gain from it
                # the checked bytes, not the paths again
                session = open_session(data, self.threads[graph], spin, fused=self.fused, external=external)
            except ModelDirError:
                raise
            except Exception as exc:  # onnxruntime raises its own exception types
                first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
                raise GraphLoadError(
                    f"{path} could not be loaded by ONNX Runtime ({first}); export the model again"
                ) from None
            check_session(session, self.manifest, graph, path)
            sessions[graph] = session
        return sessions

    @property
    def kernel(self) -> str:
        """The graphs that run: "fused" or "standard" (:attr:`kernel_note`: "<precision>, <graphs> (<why>)", one line)."""
        return "fused" if self.fused else "standard"

    # ----------------------------------------------------------------- episode
    def reset(self) -> None:
        """Start a new episode: zero history state, empty recent-token buffer."""
        self.history.reset()

    @property
    def state(self) -> dict[str, np.ndarray] | None:
        """The history state {name: (B, ...)} the next tick starts from; None before the first observation."""
        return self.history.state

    @property
    def context(self) -> np.ndarray | None:
        """c_t (B, d) after the last observation; None before it or without a history encoder."""
        return self.history.context

    @property
    def recent(self) -> np.ndarray | None:
        """The last N z tokens (B, N, d), oldest first; None before the first observation."""
        return self.history.recent

    @property
    def steps(self) -> int:
        return self.history.steps

    def _zero_state(self, batch: int) -> dict[str, np.ndarray]:
        return {s["name"]: np.zeros([batch, *s["shape"][1:]], np.float32) for s in self._state_specs}

    def _history_step(self, pc: np.ndarray, pos: np.ndarray, state: dict[str, np.ndarray]):
        """The history graph: pc (B, P, C), pos (B, S), state → z_t (B, d), c_t (B, d) or None, new state."""
        session = self.sessions[HISTORY_GRAPH]
        named = dict(zip(self._history_outputs, session.run(None, {"point_cloud": pc, "agent_pos": pos, **state})))
        if not self.manifest.model.use_history:
            return named["z_t"], None, state
        return named["z_t"], named["c_t"], {name: named[f"{name}_out"] for name in state}

    def observe(self, point_cloud, agent_pos) -> np.ndarray:
        """Run the history-update graph on one observation; returns z_t (B, d).

        Raises ValueError for a wrong shape or a batch size other than the episode's,
        :class:`NonFiniteObservation` (a ValueError) for NaN or infinity anywhere in either input (as
        float32), and :class:`ObservationOutOfRange` for a value of agent_pos or of the cloud's model
        channels outside the training range plus the margin (:mod:`dssp_deploy.ranges`): all before any
        graph runs, the state unchanged."""
        pc = _batch(point_cloud, 3, "point_cloud")
        pos = _batch(agent_pos, 2, "agent_pos")
        if pc.shape[-1] < self.contract.point_dim:
            raise ValueError(
                f"point_cloud has {pc.shape[-1]} channels per point, the model needs {self.contract.point_dim}"
            )
        if pos.shape[-1] != self.contract.state_dim or pos.shape[0] != pc.shape[0]:
            raise ValueError(f"agent_pos must be (B={pc.shape[0]}, S={self.contract.state_dim}), got {pos.shape}")
        check_finite("point_cloud", pc)
        check_finite("agent_pos", pos)
        pc = np.ascontiguousarray(pc[..., : self.contract.point_dim])
        for name, values in (("point_cloud", pc), ("agent_pos", pos)):
            wrong = self.ranges[name].outside(values)
            if wrong:
                raise ObservationOutOfRange(f"{wrong}; the observation was not used (the history is unchanged)")
        return self.history.observe(pc, pos)

    # ------------------------------------------------------------------ chunks
    def denoiser_inputs(
        self, committed: np.ndarray | None = None, weight: np.ndarray | None = None
    ) -> dict[str, np.ndarray]:
        """A copy of what the denoiser needs now (c_t, z_recent; with an inpainting denoiser the committed actions
        (B, H, A) raw units and their weights (B, H, 1), zero unless given): safe to use from another thread."""
        if self.recent is None:
            raise RuntimeError("act() before any observe(): feed at least one observation first")
        feeds = {}
        if self.manifest.model.use_history:
            feeds["c_t"] = self.context.copy()
        if self.manifest.model.use_recent_states:
            feeds["z_recent"] = self.recent.copy()
        if (committed is not None or weight is not None) and not self.contract.inpainting:
            raise ValueError("this model's denoiser takes no committed actions: export it with --inpainting")
        feeds.update(no_inpainting(self.contract, self.recent.shape[0]))
        for name, given in (("committed", committed), ("committed_weight", weight)):
            if given is not None:
                feeds[name] = np.ascontiguousarray(np.broadcast_to(given, feeds[name].shape), dtype=np.float32)
        return feeds

    def noise(self, batch: int, seed: int | None = None) -> np.ndarray:
        return np.random.default_rng(seed).standard_normal(
            (batch, self.contract.horizon, self.contract.action_dim), dtype=np.float32
        )

    def denoise(
        self, inputs: dict[str, np.ndarray], noise: np.ndarray | None = None, seed: int | None = None
    ) -> np.ndarray:
        """Run the denoiser graph on given inputs: the action chunk (B, H, A) in raw units.

        Raises :class:`ChunkOutOfRange` for a chunk with NaN/inf or an action outside the action range plus
        the margin (:mod:`dssp_deploy.ranges`): such a chunk is never returned."""
        batch = next(iter(inputs.values())).shape[0]
        noise = self.noise(batch, seed) if noise is None else _batch(noise, 3, "noise")
        if noise.shape != (batch, self.contract.horizon, self.contract.action_dim):
            raise ValueError(
                f"noise must have shape {(batch, self.contract.horizon, self.contract.action_dim)}, got {noise.shape}"
            )
        chunk = self.sessions[DENOISER_GRAPH].run(None, {**inputs, "noise": noise})[0]
        wrong = self.ranges["action"].outside(chunk)
        if wrong:
            raise ChunkOutOfRange(f"{wrong}; the chunk was not used")
        return chunk

    def act(self, noise=None, seed: int | None = None) -> np.ndarray:
        """The action chunk (B, H, A) for the current history, from the given noise or a seeded draw."""
        return self.denoise(self.denoiser_inputs(), noise, seed)

    def example_observation(
        self, rng: np.random.Generator, n_points: int | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """An observation the model accepts, drawn uniformly from the training ranges: point_cloud (1, P, point_dim)
        (P: ``n_points``, default the model's), agent_pos (1, S); for warm-up and timing."""
        pc = self.ranges["point_cloud"].sample(rng, (1, n_points or self.contract.n_points))
        return pc, self.ranges["agent_pos"].sample(rng, (1,))

    def warmup(self, iterations: int = 2) -> None:
        """Run both graphs on an example observation (allocations, kernel selection), then reset."""
        pc, pos = self.example_observation(np.random.default_rng(0), 64)
        for _ in range(iterations):
            self.observe(pc, pos)
            self.act(seed=0)
        self.reset()
