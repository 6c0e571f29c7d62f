"""Parity of an exported model directory with the PyTorch model it came from.

    python -m export.verify MODEL_DIR --checkpoint RUN_DIR [--steps 1000] [--chunks 8] [--threads N] [--seed S]
                            [--batch B] [--json PATH]

One trajectory of T ticks (the run's dataset when it is long enough, else synthetic; see
:mod:`export.trajectory`) is one episode. The reference is PyTorch fp32 on the training path, computed
in batch, never step by step:

- ``z_t`` of every tick: ``DSSPPolicy.encode_observations``, 64 ticks at a time;
- ``c_t`` of every tick: the history encoder's sequence path over the whole trajectory
  (``MambaStack.forward``, 64 ticks at a time with the recurrent state carried over, the same as
  ``HistoryEncoder.forward`` on all T at once), and the history state after the last tick;
- the action chunks: the runtime asks for one every H_a ticks from tick 0; ``--chunks`` of them, spread
  over the trajectory (the first and the last included; 0: all), are sampled in one batch by
  ``DSSPPolicy.sample_normalized`` from the prefix of the reference ``c_t`` and ``z`` tokens, with
  fixed noise. Not all by default: the denoiser keeps nothing from one chunk to the next, so its error
  does not build up along the trajectory as the history's can (that one is checked at every tick), and a
  robotwin chunk costs about 0.3 s in ONNX Runtime and 0.6 s in PyTorch on two busy cores, 167 of them
  per 1000 ticks.

The exported graphs are streamed one tick at a time, as the robot runs them, each keeping its own
recurrent state: the fp32 ONNX graphs through the robot's runtime
(:class:`dssp_deploy.onnx_policy.OnnxPolicy`, so parity covers its state handling too), asked for a
chunk with the same noise at each compared tick. TorchScript graphs, exported next to ONNX, are not
streamed: a trace runs PyTorch's own kernels, so its arithmetic is the reference's, and what tracing can
get wrong (a batch size, a shape or a branch frozen at trace time) shows on any input. They are run once,
in a batch of 3 (the traces were made with 2), at the first, middle and last compared tick: the history
graph on the observation and the streamed ONNX state before that tick, the denoiser on the reference's
inputs. Streaming them would add about 6 s of history steps and 0.6 s per chunk for the robotwin
preset on two busy cores. An export without ONNX graphs streams its TorchScript graphs instead.

Figures, each a max abs error against the reference: ``z_t`` and ``c_t`` at every tick and the history
state after the last one, in model units; the action chunks in normalised action units (raw error times
the scale of the action normaliser saved with the model, which maps each channel's fitted [min, max] to
[-1, 1]: 1 unit is half the channel's range; 1 raw unit on a channel with no range), so that a channel
spanning +-12 is held to the same relative precision as one spanning +-1. Every figure must be within
``BOUND`` (1e-4). The report names the worst figure's graph, tick and channel. The K-step denoiser can
amplify fp32 rounding, so chunks above the bound are also evaluated in float64 on each one's own inputs:
when a graph is about as far from float64 as PyTorch fp32 (within 2x) the model amplifies rounding;
when it is further, precision is lost in the exported graph. Both distances are reported as measured.
The fused graphs (``*.fused.onnx``, the fused Mamba operators of ``dssp_deploy/kernel``), when present,
are streamed the same way and held to the same bound. Quantized graphs (int8, int4; standard and fused),
when present, are streamed too and reported against the fp32 graphs of their own path (action error,
speed-up); they are not held to the bound.

Exit codes: 0 pass, 1 a figure exceeds the bound, 2 bad input (a path, a mismatched checkpoint).

Shapes (T ticks, K compared chunks, B batch, P points, C point channels, S state, A action, d width,
N recent tokens, H horizon): trajectory point_cloud (T, P, C), agent_pos (T, S); per tick point_cloud
(B, P, C), agent_pos (B, S) → z_t, c_t (B, d); states as in the manifest; noise and chunks (K, B, H, A).
"""

from __future__ import annotations

import argparse
import copy
import hashlib
import json
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dssp_core.cli_runner import ArgumentParser, run_cli
from dssp_core.errors import ExportError, ParityError
from dssp_core.output_guard import check_output_file, write_output_text
from dssp_deploy.manifest import (
    DENOISER_GRAPH,
    FUSED,
    HISTORY_GRAPH,
    PRECISIONS,
    Manifest,
    file_kind,
    no_inpainting,
    read_graph,
    read_manifest,
)
from dssp_deploy.sessions import check_threads, default_threads
from dssp_train.config import TIMESTEP_SPACINGS
from export.graph_streams import GraphFn, GraphStream, RuntimeStream, torchscript_graph
from export.manifest_writer import architecture
from export.trajectory import load_trajectory
from export.verify_report import ACTION_UNITS, MODEL_UNITS, check_report, format_report

BOUND = 1e-4
BOUNDED_ALSO = ("onnx_fused",)  # streamed backends held to BOUND besides the main one
CHUNKS = 8  # action chunks compared by default, spread over the trajectory
BLOCK = 64  # ticks per block of the reference's sequence path, chunks per batch of its denoiser
TRACE_CHECKS = 3  # rows of the TorchScript check: the traces were made with batch 2
MAX_FLAGGED = 4  # chunks above the bound evaluated in float64


# ------------------------------------------------------------------ helpers
def worst(got, want, scale: np.ndarray | None = None) -> tuple[float, tuple[int, ...] | None]:
    """Max abs difference, times ``scale`` (broadcast on the last axis) if given, and where it is.

    got and want broadcast against each other. Returns (inf, first non-finite index) when a difference is
    NaN or infinite, (inf, None) when the shapes do not broadcast or one is missing, (0.0, None) when both are None.
    """
    if got is None or want is None:
        return (0.0, None) if got is None and want is None else (float("inf"), None)
    try:
        diff = np.abs(np.asarray(got, dtype=np.float64) - np.asarray(want, dtype=np.float64))
    except ValueError:
        return float("inf"), None
    if scale is not None:
        diff = diff * np.asarray(scale, dtype=np.float64)
    if diff.size == 0:
        return 0.0, None
    bad = ~np.isfinite(diff)
    if bad.any():
        return float("inf"), tuple(int(i) for i in np.argwhere(bad)[0])
    index = np.unravel_index(int(np.argmax(diff)), diff.shape)
    return float(diff[index]), tuple(int(i) for i in index)


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def load_checked_policy(manifest: Manifest, run_dir: Path):
    """The policy the manifest was exported from: same weights file, same sha256, same model config and contract."""

    from dssp_train.training.checkpoint import load_policy  # deferred: loads safetensors, torch, tqdm

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ExportError(
            f"run directory {run_dir} does not exist; pass the dssp-train --out directory the model was exported from"
        )
    source = manifest.source  # checked by read_manifest: weights is a name inside the run directory
    weights = source.weights
    path = run_dir / weights
    if path.is_file():
        sha = file_sha256(path)
        if sha != source.sha256:
            run = f"run {source.run!r}, " if source.run else ""
            raise ExportError(
                f"{path} (sha256 {sha[:12]}) is not the checkpoint this model was exported from "
                f"({run}{weights}, step {source.step}, sha256 {source.sha256[:12]}); pass that run directory, or export again"
            )
    policy, config = load_policy(run_dir, weights=weights)
    # The timesteps' spacing may be chosen at export (--timestep-spacing); the policy samples as the graphs do.
    spacing = (manifest.data["model_config"].get("diffusion") or {}).get("timestep_spacing")
    if spacing in TIMESTEP_SPACINGS:
        config.model.diffusion.timestep_spacing = spacing
    c = manifest.contract
    if (
        architecture(config.model) != manifest.data["model_config"]
        or config.contract(c.ddim_timesteps, c.inpainting) != c
    ):
        raise ExportError(
            f"{run_dir}/config.json does not describe the exported model; pass the run directory it was exported from"
        )
    return policy, config


def chunk_ticks(steps: int, every: int, count: int) -> tuple[list[int], int]:
    """The ticks whose chunks are compared: ``count`` of the runtime's chunk ticks 0, H_a, 2 H_a, ... < T,
    evenly spread, the first and the last included (``count`` 0: all of them); and how many there are."""
    all_ticks = list(range(0, steps, every))
    if count <= 0 or count >= len(all_ticks):
        return all_ticks, len(all_ticks)
    picks = np.unique(np.round(np.linspace(0, len(all_ticks) - 1, count)).astype(int))
    return [all_ticks[i] for i in picks], len(all_ticks)


def _median_ms(times: list[float]) -> float | None:
    return round(1000 * float(np.median(times)), 3) if times else None


# ---------------------------------------------------------------- reference
@dataclass
class Reference:
    """PyTorch fp32 on the training path.

    z (T, d), c (T, d) or None, state: the history state after the last tick (manifest order) or [],
    context (K, d) or None and recent (K, N, d): each compared chunk's inputs, chunks (K, B, H, A) raw units.
    """

    z: np.ndarray
    c: np.ndarray | None
    state: list[np.ndarray]
    context: np.ndarray | None
    recent: np.ndarray
    chunks: np.ndarray


def pytorch_reference(
    policy, point_cloud: np.ndarray, agent_pos: np.ndarray, ticks: list[int], noise: np.ndarray, num_steps: int
) -> Reference:
    """The training path over one episode: point_cloud (T, P, C), agent_pos (T, S), chunk ``ticks`` (K,),
    noise (K, B, H, A) → :class:`Reference`. Every chunk's denoiser call is one batch (in blocks of ``BLOCK``)."""
    import torch  # deferred: loads torch, tqdm

    steps = agent_pos.shape[0]
    with torch.no_grad():
        pc, pos = torch.from_numpy(point_cloud), torch.from_numpy(agent_pos)
        z = torch.cat(
            [
                policy.encode_observations(pc[None, i : i + BLOCK], pos[None, i : i + BLOCK])
                for i in range(0, steps, BLOCK)
            ],
            dim=1,
        )
        c, state = None, []
        encoder = policy.history_encoder
        if encoder is not None and encoder.window:  # exportable: a Mamba stack over a window of T_h steps
            c = torch.cat(
                [
                    encoder(z[:, max(0, i - encoder.window + 1) : i + BLOCK])[:, min(i, encoder.window - 1) :]
                    for i in range(0, steps, BLOCK)
                ],
                dim=1,
            )  # (1, T, d): each block with the window before it
            last = (torch.arange(steps - encoder.window, steps)).clamp(
                min=0
            )  # the final window, the first z before the start
            state = [z[:, last].numpy(), np.full((1, 1), min(steps, encoder.window), np.float32)]  # z_window, z_seen
        elif encoder is not None:  # exportable: a Mamba stack over the full history
            net, parts, layers = encoder.net, [], None
            for i in range(0, steps, BLOCK):
                out, layers = net(z[:, i : i + BLOCK], layers)
                parts.append(out)
            c = torch.cat(parts, dim=1)  # (1, T, d)
            state = [s.numpy() for pair in layers for s in pair]
        starts = torch.tensor(ticks, dtype=torch.long)
        obs_idx, _ = policy.trajectory_windows(steps, starts)  # (K, N)
        context = None if c is None else c[0, starts]  # (K, d)
        recent = z[0, obs_idx]  # (K, N, d)
        count, batch = noise.shape[:2]
        prefix = policy.build_prefix(context, recent).repeat_interleave(batch, dim=0)  # (K B, L_p, d)
        flat_noise = torch.from_numpy(noise.reshape(count * batch, *noise.shape[2:]))
        chunks = torch.cat(
            [
                policy.normalizers["action"].unnormalize(
                    policy.sample_normalized(prefix[i : i + BLOCK], flat_noise[i : i + BLOCK], num_steps)
                )
                for i in range(0, count * batch, BLOCK)
            ]
        )
    return Reference(
        z=z[0].numpy(),
        c=None if c is None else c[0].numpy(),
        state=state,
        context=None if context is None else context.numpy(),
        recent=recent.numpy(),
        chunks=chunks.numpy().reshape(noise.shape),
    )


# ------------------------------------------------------------------- verify
def verify_model(
    model_dir: Path,
    run_dir: Path,
    steps: int = 1000,
    threads: int | None = None,
    seed: int = 0,
    batch: int = 1,
    progress: Callable[[str], None] | None = None,
    chunks: int = CHUNKS,
) -> dict[str, Any]:
    """Compare the graphs in ``model_dir`` with the PyTorch model over ``steps`` ticks; return the report.

    Does not raise on a failed bound: see ``report["passed"]`` (:func:`check_report` raises, :func:`main`
    exits 1).
    """
    import torch  # deferred: loads torch, tqdm

    if steps < 1:
        raise ExportError(f"--steps must be >= 1, got {steps}")
    if chunks < 0:
        raise ExportError(f"--chunks must be >= 0 (0: every chunk), got {chunks}")
    model_dir = Path(model_dir)
    manifest = read_manifest(model_dir)
    threads = threads or default_threads()
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        policy, config = load_checked_policy(manifest, run_dir)
        traj = load_trajectory(config, manifest.normalizers, steps, seed)
        ticks, n_ticks = chunk_ticks(traj.length, manifest.contract.n_action_steps, chunks)
        rng = np.random.default_rng(seed)
        noise = rng.standard_normal(
            (len(ticks), batch, manifest.contract.horizon, manifest.contract.action_dim)
        ).astype(np.float32)
        started = time.perf_counter()
        reference = pytorch_reference(
            policy, traj.point_cloud, traj.agent_pos, ticks, noise, manifest.contract.denoise_steps
        )
        reference_s = time.perf_counter() - started
        if progress:
            progress(
                f"PyTorch reference on the training path: {traj.length} steps, {len(ticks)} of {n_ticks} chunks "
                f"({reference_s:.1f} s); streaming the exported graphs ({traj.source})"
            )
        report = _stream_and_compare(model_dir, manifest, policy, traj, reference, ticks, noise, threads, batch)
        report["seconds"] = {"reference": round(reference_s, 2), **report["seconds"]}
        report.update(chunk_ticks_total=n_ticks, seed=seed)
        return report
    finally:
        torch.set_num_threads(before)


def _open_backends(
    model_dir: Path, manifest: Manifest, threads: int
) -> tuple[dict[str, Any], dict[str, dict[str, GraphFn]]]:
    """(streamed backends by file kind, the main one first; TorchScript graph functions to check in batch, or {}).

    Every ONNX kind the model directory has is streamed through the robot's runtime: ``onnx`` (the main
    one), ``onnx_fused`` (the fused Mamba operators; held to the same bound), and the quantized graphs of
    both paths (figures against fp32, not bounded).
    """
    graphs = (HISTORY_GRAPH, DENOISER_GRAPH)
    kinds = [
        kind
        for kind in manifest.graphs[HISTORY_GRAPH]["files"]
        if all(kind in manifest.graphs[g]["files"] for g in graphs)
    ]
    if not ("onnx" in kinds or "torchscript" in kinds):
        raise ExportError(f"{model_dir} lists no ONNX or TorchScript graphs; export the model again")
    streamed: dict[str, Any] = {}
    traced: dict[str, dict[str, GraphFn]] = {}
    if "torchscript" in kinds:
        # inside the model directory, present, and the size and sha256 the manifest records
        fns = {g: torchscript_graph(*read_graph(model_dir, manifest, g, "torchscript")) for g in graphs}
        if "onnx" in kinds:
            traced["torchscript"] = fns
        else:
            streamed["torchscript"] = GraphStream(manifest, fns[HISTORY_GRAPH], fns[DENOISER_GRAPH])
    onnx_kinds = {file_kind(p, f): (p, f) for p in PRECISIONS for f in (False, True)}
    if "onnx" in kinds:
        streamed = {"onnx": RuntimeStream(model_dir, threads), **streamed}  # the robot's own runtime code
    for kind, (precision, fused) in onnx_kinds.items():
        if kind != "onnx" and kind in kinds:
            streamed[kind] = RuntimeStream(
                model_dir, threads, precision=precision, kernel="fused" if fused else "standard"
            )
    return streamed, traced


@dataclass
class Streamed:
    """What the streamed graphs returned, per backend: z, c (T ticks of (B, d); c None entries without a
    history encoder), chunks (K compared ticks of (B, H, A)), the final history state; and for the main
    backend its denoiser inputs and its history state before each compared tick."""

    z: dict[str, list[np.ndarray]]
    c: dict[str, list[np.ndarray | None]]
    chunks: dict[str, list[np.ndarray]]
    final_state: dict[str, list[np.ndarray]]
    inputs: list[dict[str, np.ndarray]]
    states_before: list[list[np.ndarray] | None]
    times: dict[str, dict[str, list[float]]]


def stream(
    backends: dict[str, Any], point_cloud: np.ndarray, agent_pos: np.ndarray, ticks: list[int], noise: np.ndarray
) -> Streamed:
    """Every tick through every backend (B copies of point_cloud (T, P, C), agent_pos (T, S)); a chunk from
    noise (K, B, H, A) at each compared tick. The first backend is the main one."""
    main = next(iter(backends))
    batch = noise.shape[1]
    out = Streamed(
        {n: [] for n in backends},
        {n: [] for n in backends},
        {n: [] for n in backends},
        {},
        [],
        [],
        {n: {"history_step": [], "denoiser": []} for n in backends},
    )
    at = {t: k for k, t in enumerate(ticks)}
    for t in range(agent_pos.shape[0]):
        pc = np.repeat(point_cloud[t][None], batch, axis=0)  # (B, P, C)
        pos = np.repeat(agent_pos[t][None], batch, axis=0)  # (B, S)
        if t in at:
            out.states_before.append(backends[main].states)
        for name, runner in backends.items():
            start = time.perf_counter()
            out.z[name].append(runner.observe(pc, pos))
            out.times[name]["history_step"].append(time.perf_counter() - start)
            out.c[name].append(runner.context)
        if t in at:
            out.inputs.append(backends[main].denoiser_inputs())
            for name, runner in backends.items():
                start = time.perf_counter()
                out.chunks[name].append(runner.act(noise[at[t]]))
                out.times[name]["denoiser"].append(time.perf_counter() - start)
    out.final_state = {name: runner.states or [] for name, runner in backends.items()}
    return out


def compare_streamed(
    name: str, got: Streamed, ref: Reference, ticks: list[int], scale: np.ndarray, state_names: list[str]
) -> tuple[dict[str, float], dict[str, dict | None]]:
    """(errors, where) of one streamed backend: z_t and c_t at every tick, the state after the last tick
    (model units), the compared chunks (normalised action units: raw error times ``scale`` (A,))."""
    steps = len(got.z[name])
    e_z = worst(np.stack(got.z[name]), ref.z[:, None])  # (T, B, d)
    e_c = worst(np.stack(got.c[name]), ref.c[:, None]) if ref.c is not None else (0.0, None)
    per_input = [worst(g, w) for g, w in zip(got.final_state[name], ref.state)]  # (B, E, W) or (B, E, n) each
    i_s = max(range(len(per_input)), key=lambda i: per_input[i][0], default=None)
    e_s = per_input[i_s] if i_s is not None else (0.0, None)
    e_a = worst(np.stack(got.chunks[name]), ref.chunks, scale)  # (K, B, H, A)
    errors = {"z_t": e_z[0], "c_t": e_c[0], "state": e_s[0], "action": e_a[0]}
    where = {
        "z_t": _at_tick(e_z[1], range(steps)),
        "c_t": _at_tick(e_c[1], range(steps)),
        "state": None if e_s[1] is None else {"step": steps - 1, "input": state_names[i_s], "index": e_s[1][1]},
        "action": _at_chunk(e_a[1], ticks),
    }
    return errors, where


def check_traces(
    fns: dict[str, GraphFn],
    manifest: Manifest,
    point_cloud: np.ndarray,
    agent_pos: np.ndarray,
    ref: Reference,
    ticks: list[int],
    noise: np.ndarray,
    states_before: list,
    scale: np.ndarray,
):
    """TorchScript beside ONNX: both graphs once, on a batch of TRACE_CHECKS compared ticks (first, middle, last).

    The history graph gets each tick's observation and the streamed main backend's state before it; the
    denoiser the reference's inputs and noise (row 0 of B). Returns (errors, where, rows (R,) indices into
    ``ticks``, chunks (R, H, A)).
    """
    rows = np.round(np.linspace(0, len(ticks) - 1, TRACE_CHECKS)).astype(int).tolist()  # indices may repeat
    at = [ticks[r] for r in rows]
    specs = manifest.graphs[HISTORY_GRAPH]["inputs"][2:]
    feeds = {"point_cloud": point_cloud[at], "agent_pos": agent_pos[at]}
    for i, spec in enumerate(specs):
        feeds[spec["name"]] = np.concatenate(
            [
                states_before[r][i][:1] if states_before[r] else np.zeros([1, *spec["shape"][1:]], np.float32)
                for r in rows
            ]
        )
    out = fns[HISTORY_GRAPH](feeds)
    e_z = worst(out[0], ref.z[at])  # (R, d)
    e_c = worst(out[1], ref.c[at]) if ref.c is not None else (0.0, None)
    available = {
        "c_t": None if ref.context is None else ref.context[rows],
        "z_recent": ref.recent[rows],
        "noise": noise[rows, 0],
        **no_inpainting(manifest.contract, len(rows)),
    }
    chunks = fns[DENOISER_GRAPH]({s["name"]: available[s["name"]] for s in manifest.graphs[DENOISER_GRAPH]["inputs"]})[
        0
    ]
    e_a = worst(chunks, ref.chunks[rows, 0], scale)  # (R, H, A)
    errors = {"z_t": e_z[0], "c_t": e_c[0], "state": None, "action": e_a[0]}
    where = {
        "z_t": _at_tick(e_z[1], at),
        "c_t": _at_tick(e_c[1], at),
        "state": None,  # checked through c_t
        "action": None if e_a[1] is None else _at_chunk((rows[e_a[1][0]], 0, *e_a[1][1:]), ticks),
    }
    return errors, where, rows, chunks


def _stream_and_compare(
    model_dir, manifest, policy, traj, ref: Reference, ticks: list[int], noise: np.ndarray, threads: int, batch: int
) -> dict[str, Any]:
    backends, traced = _open_backends(model_dir, manifest, threads)
    main = next(iter(backends))  # the deployed graphs: ONNX (or TorchScript when it is all there is)
    clock = time.perf_counter()
    got = stream(backends, traj.point_cloud, traj.agent_pos, ticks, noise)
    seconds = {"stream": round(time.perf_counter() - clock, 2)}

    clock = time.perf_counter()
    scale = np.asarray(manifest.normalizers["action"]["scale"], dtype=np.float64)  # (A,): raw → normalised units
    errors, where = {}, {}
    for name in [main, *BOUNDED_ALSO]:
        if name in backends:
            errors[name], where[name] = compare_streamed(name, got, ref, ticks, scale, manifest.history_state)
    trace, checked = None, {}
    if traced:
        errors["torchscript"], where["torchscript"], rows, t_chunks = check_traces(
            traced["torchscript"],
            manifest,
            traj.point_cloud,
            traj.agent_pos,
            ref,
            ticks,
            noise,
            got.states_before,
            scale,
        )
        trace, checked = (rows, t_chunks), {"torchscript": [ticks[r] for r in rows]}
    seconds["batch_checks"] = round(time.perf_counter() - clock, 2)

    clock = time.perf_counter()
    figures = [(v, name, f) for name, e in errors.items() for f, v in e.items() if v is not None]
    worst_value, worst_name, worst_figure = max(figures, key=lambda x: x[0])
    flagged = _flagged(ref, ticks, noise, scale, main, got.chunks[main], got.inputs, trace)
    check = _float64_check(policy, manifest.contract.denoise_steps, scale, flagged) if flagged else None
    if check:
        seconds["float64"] = round(time.perf_counter() - clock, 2)
    report: dict[str, Any] = {
        "steps": traj.length,
        "batch": batch,
        "chunks": len(ticks),
        "chunk_ticks": ticks,
        "trajectory": traj.source,
        "threads": threads,
        "reference": (
            "PyTorch fp32 training path: encode_observations, the history encoder's sequence forward "
            "over the whole trajectory, sample_normalized on the compared chunks in one batch"
        ),
        "streamed": list(backends),
        "batch_checked": checked,
        "bound": BOUND,
        "units": {"z_t": MODEL_UNITS, "c_t": MODEL_UNITS, "state": MODEL_UNITS, "action": ACTION_UNITS},
        "errors": errors,
        "where": where,
        "worst": worst_value,
        "worst_at": {
            "backend": worst_name,
            "figure": worst_figure,
            "units": ACTION_UNITS if worst_figure == "action" else MODEL_UNITS,
            **(where[worst_name][worst_figure] or {}),
        },
        "action_float64_check": check,
        "passed": bool(worst_value <= BOUND),
        "latency_ms": {name: {graph: _median_ms(ts) for graph, ts in per.items()} for name, per in got.times.items()},
        "seconds": seconds,
    }
    quantized = {
        name: _quantized_figures(manifest, got, name, scale, report["latency_ms"])
        for name in backends
        if name not in (main, *BOUNDED_ALSO) and name != "torchscript"
    }
    if quantized:
        report["quantized"] = quantized
    return report


def _quantized_figures(manifest, got: Streamed, name: str, scale: np.ndarray, lat: dict) -> dict[str, Any]:
    """A quantized backend (``onnx_int8``, ``onnx_int4_fused``, ...) against the fp32 graphs of its own path (not bounded)."""
    action = manifest.normalizers["action"]
    span = np.asarray(action["input_max"]) - np.asarray(action["input_min"])
    fp32 = "onnx_fused" if name.endswith(FUSED) and "onnx_fused" in got.chunks else "onnx"
    q_chunks, fp32_chunks = np.stack(got.chunks[name]), np.stack(got.chunks[fp32])
    has_c = got.c[fp32][0] is not None
    return {
        "against": fp32,
        "action_max_abs_vs_fp32": worst(q_chunks, fp32_chunks)[0],
        "action_max_abs_over_range": worst(q_chunks, fp32_chunks)[0] / float(max(span.max(), 1e-12)),
        "action_normalised_vs_fp32": worst(q_chunks, fp32_chunks, scale)[0],
        "c_t_max_abs_vs_fp32": worst(np.stack(got.c[name]), np.stack(got.c[fp32]))[0] if has_c else 0.0,
        "speedup_history_step": _ratio(lat[fp32]["history_step"], lat[name]["history_step"]),
        "speedup_denoiser": _ratio(lat[fp32]["denoiser"], lat[name]["denoiser"]),
    }


def _at_tick(index: tuple[int, ...] | None, ticks) -> dict[str, int] | None:
    """(row, [batch,] feature) of a per-tick figure → {"step", "index"}."""
    return None if index is None else {"step": ticks[index[0]], "index": index[-1]}


def _at_chunk(index: tuple[int, ...] | None, ticks: list[int]) -> dict[str, int] | None:
    """(chunk, batch, horizon, channel) → {"step": the chunk's tick, "horizon", "channel"}."""
    return None if index is None else {"step": ticks[index[0]], "horizon": index[-2], "channel": index[-1]}


def _flagged(
    ref: Reference,
    ticks: list[int],
    noise: np.ndarray,
    scale: np.ndarray,
    main: str,
    main_chunks: list,
    main_inputs: list[dict],
    trace: tuple[list[int], np.ndarray] | None,
) -> list[dict]:
    """The compared chunks where a graph's action error exceeds the bound, worst first (at most MAX_FLAGGED per graph).

    ``trace``: (rows, chunks (R, H, A)) of the TorchScript check, or None. Each entry: {"step", "inputs":
    {name: (c_t (b, d) or None, z_recent (b, N, d), noise (b, H, A))}, "chunks": {name: (b, H, A)}}, with
    name "torch" for the reference and b = B for the streamed graphs, 1 for the TorchScript rows.
    """

    def ref_inputs(k: int, rows: int) -> tuple:
        context = None if ref.context is None else np.repeat(ref.context[k : k + 1], rows, axis=0)
        return context, np.repeat(ref.recent[k : k + 1], rows, axis=0), noise[k, :rows]

    def over(err: np.ndarray) -> list[int]:
        err = np.nan_to_num(err, nan=np.inf)
        return [int(i) for i in np.argsort(-err, kind="stable")[:MAX_FLAGGED] if err[i] > BOUND]

    batch = noise.shape[1]
    found = []
    err = (np.abs(np.stack(main_chunks).astype(np.float64) - ref.chunks) * scale).reshape(len(ticks), -1).max(axis=1)
    for k in over(err):
        got = main_inputs[k]
        found.append(
            {
                "step": ticks[k],
                "inputs": {
                    "torch": ref_inputs(k, batch),
                    main: (got.get("c_t"), got.get("z_recent", ref_inputs(k, batch)[1]), noise[k]),
                },
                "chunks": {"torch": ref.chunks[k], main: main_chunks[k]},
            }
        )
    if trace is not None:
        rows, chunks = trace
        err = (np.abs(chunks.astype(np.float64) - ref.chunks[rows, 0]) * scale).reshape(len(rows), -1).max(axis=1)
        for j in over(err):
            k = rows[j]
            found.append(
                {
                    "step": ticks[k],
                    "inputs": {"torch": ref_inputs(k, 1), "torchscript": ref_inputs(k, 1)},
                    "chunks": {"torch": ref.chunks[k, :1], "torchscript": chunks[j : j + 1]},
                }
            )
    return found


def _float64_check(policy, num_steps: int, scale: np.ndarray, flagged: list[dict]) -> dict[str, Any]:
    """For the chunks above the bound: how far PyTorch's fp32 chunk and each graph's are from float64.

    Each chunk is evaluated in float64 (``sample_normalized`` of a float64 copy of the policy) on each
    one's own inputs, so a graph's distance holds its own rounding only (the history's error in its inputs
    is not counted). Distances in normalised action units. Diagnostic only: when the graphs are about as
    far from float64 as PyTorch fp32, the model amplifies rounding (a property of the weights), not the export.
    """

    import torch  # deferred: loads torch, tqdm

    policy64 = copy.deepcopy(policy).double().eval()
    owners = [(i, name) for i, entry in enumerate(flagged) for name in entry["inputs"]]
    rows = [flagged[i]["inputs"][name] for i, name in owners]
    as64 = lambda xs: torch.from_numpy(np.concatenate(xs).astype(np.float64))  # noqa: E731
    with torch.no_grad():
        context = None if rows[0][0] is None else as64([r[0] for r in rows])  # (R, d)
        prefix = policy64.build_prefix(context, as64([r[1] for r in rows]))  # (R, L_p, d)
        x = policy64.sample_normalized(prefix, as64([r[2] for r in rows]), num_steps)
        exact = policy64.normalizers["action"].unnormalize(x).numpy()  # (R, H, A)
    split = np.split(exact, np.cumsum([len(r[2]) for r in rows])[:-1])
    deviation: dict[str, float] = {}
    for (i, name), want in zip(owners, split):
        deviation[name] = max(deviation.get(name, 0.0), worst(flagged[i]["chunks"][name], want, scale)[0])
    torch_dev = deviation.pop("torch", 0.0)
    return {
        "chunks_checked": len(flagged),
        "steps": sorted({entry["step"] for entry in flagged}),
        "units": ACTION_UNITS,
        "torch_fp32_vs_float64": torch_dev,
        "graphs_vs_float64": deviation,
    }


def _ratio(a: float | None, b: float | None) -> float | None:
    return round(a / b, 2) if a and b else None


# ---------------------------------------------------------------------- CLI
def build_parser() -> argparse.ArgumentParser:
    p = ArgumentParser(
        prog="python -m export.verify", description="Check an exported model directory against its checkpoint."
    )
    p.add_argument("model_dir", help="the exported model directory (dssp_model.json)")
    p.add_argument(
        "--checkpoint", required=True, metavar="RUN_DIR", help="the dssp-train run directory it was exported from"
    )
    p.add_argument("--steps", type=int, default=1000, help="control ticks to stream (default 1000)")
    p.add_argument(
        "--chunks",
        type=int,
        default=CHUNKS,
        help=f"action chunks to compare, spread over the trajectory (default {CHUNKS}; 0: every chunk)",
    )
    p.add_argument(
        "--threads", type=int, help="ONNX Runtime and torch intra-op threads (default: all CPUs of this process)"
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the noise (and of a synthetic trajectory)")
    p.add_argument("--batch", type=int, default=1, help="stream B copies of the trajectory at once (default 1)")
    p.add_argument("--json", metavar="PATH", help="also write the report as JSON")
    p.add_argument("--force", action="store_true", help="replace an existing --json file")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)

    def _main() -> int:
        if args.batch < 1:
            raise ExportError(f"--batch must be >= 1, got {args.batch}")
        check_threads(args.threads)
        if args.steps < 1:
            raise ExportError(f"--steps must be >= 1, got {args.steps}")
        if args.chunks < 0:
            raise ExportError(f"--chunks must be >= 0 (0: every chunk), got {args.chunks}")
        if args.json:
            check_output_file(args.json, force=args.force, flag="--json", error=ExportError)
        report = verify_model(
            Path(args.model_dir),
            Path(args.checkpoint),
            args.steps,
            args.threads,
            args.seed,
            args.batch,
            print,
            chunks=args.chunks,
        )
        print(format_report(report))
        if args.json:
            write_output_text(
                args.json, json.dumps(report, indent=2) + "\n", force=args.force, flag="--json", error=ExportError
            )
        try:
            check_report(report)
        except ParityError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 1
        return 0

    return run_cli(_main)


if __name__ == "__main__":
    sys.exit(main())
