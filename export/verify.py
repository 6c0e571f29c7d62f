"""Parity of an exported model directory with the PyTorch model it came from.

    python -m export.verify MODEL_DIR --checkpoint RUN_DIR [--steps 1000] [--threads N] [--seed S] [--json PATH]

Streams one trajectory (the run's dataset when it is long enough, else synthetic; see
:mod:`export.trajectory`) one control tick at a time through ONNX Runtime (the robot's runtime,
``dssp_deploy.onnx_policy.OnnxPolicy``), TorchScript and the PyTorch streaming API (:class:`dssp_train.model.streaming.StreamingPolicy`), each keeping its own recurrent state,
and asks for an action chunk every H_a ticks with identical noise, as the runtime will. Reported: the
max abs error against PyTorch of ``z_t``, ``c_t``, the history state and the action chunks, and of the
streamed ``c_t`` against the training (sequence) path ``policy.history_encoder(z)`` over the whole
trajectory. Every fp32 figure must be within ``BOUND`` (1e-4). The K-step denoiser can amplify fp32
rounding (seen: a model trained for 5 steps, whose PyTorch fp32 chunks were 2.7e-5 from float64), so the
chunks above the bound are also evaluated in float64 and both distances are reported: alike, they point
at the model's conditioning rather than at the export (the bound still decides).
Int8 graphs, when present, are reported against the fp32 graphs (action error, speed-up) and are not
held to the bound.

Exit codes: 0 pass, 1 a figure exceeds the bound, 2 bad input (a path, a mismatched checkpoint).

Shapes: point_cloud (B, P, C), agent_pos (B, S) per tick; z_t, c_t (B, d); states as in the manifest;
noise and chunks (B, H, A).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from dssp_deploy.manifest import read_graph
from dssp_deploy.sessions import check_threads, default_threads, open_session
from dssp_data.cli_runner import ArgumentParser, run_cli
from dssp_data.output_guard import check_output_file, write_output_text
from dssp_data.errors import ExportError, ParityError
from export.manifest_writer import DENOISER_GRAPH, HISTORY_GRAPH, read_manifest

BOUND = 1e-4
MAX_FLAGGED = 8
FIGURES = ("z_t", "c_t", "state", "action")

GraphFn = Callable[[dict[str, np.ndarray]], list[np.ndarray]]


# ------------------------------------------------------------- graph runtime
class GraphStream:
    """The runtime loop over the two exported graphs, numpy in and out.

    Keeps the history state (zeros at the start) and the buffer of the last N ``z_t`` (the first
    observation repeated at the start), and calls the denoiser with the inputs the manifest lists.
    """

    def __init__(self, manifest: dict[str, Any], history: GraphFn, denoiser: GraphFn, batch: int = 1):
        self.manifest = manifest
        self.history, self.denoiser = history, denoiser
        self.batch = batch
        self.state_specs = manifest["graphs"][HISTORY_GRAPH]["inputs"][2:]
        self.denoiser_inputs = [s["name"] for s in manifest["graphs"][DENOISER_GRAPH]["inputs"]]
        self.reset()

    def reset(self) -> None:
        """A new episode: zero state, empty recent buffer."""
        self.states = [np.zeros([self.batch, *s["shape"][1:]], dtype=np.float32) for s in self.state_specs]
        self.recent: np.ndarray | None = None  # (B, N, d)
        self.context: np.ndarray | None = None  # (B, d)

    def observe(self, point_cloud: np.ndarray, agent_pos: np.ndarray) -> np.ndarray:
        """One tick: point_cloud (B, P, C), agent_pos (B, S) raw → z_t (B, d); updates c_t and the state."""
        feeds = {"point_cloud": point_cloud, "agent_pos": agent_pos}
        feeds.update({s["name"]: v for s, v in zip(self.state_specs, self.states)})
        out = self.history(feeds)
        z_t = out[0]
        if self.manifest["use_history"]:
            self.context, self.states = out[1], list(out[2:])
        if self.recent is None:
            self.recent = np.repeat(z_t[:, None], self.manifest["n_obs_steps"], axis=1)
        else:
            self.recent = np.concatenate([self.recent[:, 1:], z_t[:, None]], axis=1)
        return z_t

    def act(self, noise: np.ndarray) -> np.ndarray:
        """noise (B, H, A) → the action chunk (B, H, A) in raw units."""
        available = {"c_t": self.context, "z_recent": self.recent, "noise": noise}
        return self.denoiser({name: available[name] for name in self.denoiser_inputs})[0]


class RuntimeStream:
    """The robot's runtime, :class:`dssp_deploy.onnx_policy.OnnxPolicy`, with the interface of :class:`GraphStream`.

    The fp32 ONNX graphs are checked through it, so parity covers the runtime's state handling too.
    observe: point_cloud (B, P, C), agent_pos (B, S) → z_t (B, d); act: noise (B, H, A) → chunk (B, H, A).
    """

    def __init__(self, model_dir: Path, threads: int):
        from dssp_deploy.onnx_policy import OnnxPolicy

        self.policy = OnnxPolicy(model_dir, threads=threads, warmup=0)

    def observe(self, point_cloud: np.ndarray, agent_pos: np.ndarray) -> np.ndarray:
        return self.policy.observe(point_cloud, agent_pos)

    @property
    def context(self) -> np.ndarray | None:
        return self.policy.context

    @property
    def states(self) -> list[np.ndarray]:
        return list((self.policy.state or {}).values())

    def act(self, noise: np.ndarray) -> np.ndarray:
        return self.policy.act(noise=noise)


def onnx_graph(path: Path, outputs: list[str], threads: int, data: bytes | None = None) -> GraphFn:
    """An ONNX graph as a function; ``data``: the file's bytes, already checked against the manifest."""
    session = open_session(path if data is None else data, threads)
    names = [o.name for o in session.get_outputs()]
    if names != outputs:
        raise ExportError(f"{path} outputs {names}, the manifest lists {outputs}; export the model again")
    return lambda feeds: session.run(None, feeds)


def torchscript_graph(path: Path, data: bytes | None = None) -> GraphFn:
    """A TorchScript graph as a function; ``data``: the file's bytes, already checked against the manifest."""
    import io

    import torch

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=DeprecationWarning)  # torch.jit is deprecated, still the .pt reader
        source = str(path) if data is None else io.BytesIO(data)
        module = torch.jit.load(source, map_location="cpu").eval()

    def run(feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
        with torch.no_grad():
            out = module(*[torch.from_numpy(v) for v in feeds.values()])
        return [t.numpy() for t in (out if isinstance(out, tuple) else (out,))]

    return run


class TorchStream:
    """:class:`StreamingPolicy` with the same observe/act interface as :class:`GraphStream`.

    observe: point_cloud (B, P, C), agent_pos (B, S) → z_t (B, d); ``context`` c_t (B, d); ``states`` the
    history state flattened as the graph's (conv (B, E, W), ssm (B, E, n) per layer); act: noise (B, H, A)
    → chunk (B, H, A).
    """

    def __init__(self, policy, num_steps: int):
        from dssp_train.model.streaming import StreamingPolicy

        self.stream = StreamingPolicy(policy)
        self.num_steps = num_steps

    def observe(self, point_cloud: np.ndarray, agent_pos: np.ndarray) -> np.ndarray:
        self.stream.observe(point_cloud, agent_pos)
        return self.stream.recent[:, -1].numpy()

    @property
    def context(self) -> np.ndarray | None:
        return None if self.stream.context is None else self.stream.context.numpy()

    @property
    def states(self) -> list[np.ndarray]:
        state = self.stream.history_state or []
        return [t.numpy() for pair in state for t in pair]

    def act(self, noise: np.ndarray) -> np.ndarray:
        return self.stream.act(noise=noise, num_steps=self.num_steps)


# ------------------------------------------------------------------ helpers
def max_abs(a: np.ndarray | None, b: np.ndarray | None) -> float:
    """Max abs difference (inf when either has a NaN/inf or the shapes differ; 0 when both are None)."""
    if a is None or b is None:
        return 0.0 if a is None and b is None else float("inf")
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        return float("inf")
    if a.size == 0:
        return 0.0
    worst = float(np.abs(a - b).max())
    return worst if np.isfinite(worst) else float("inf")


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def load_checked_policy(manifest: dict[str, Any], run_dir: Path):
    """The policy the manifest was exported from: same weights file, same sha256, same model config."""
    import dataclasses

    from dssp_train.training.checkpoint import load_policy

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ExportError(f"run directory {run_dir} does not exist; pass the dssp-train --out directory the model was exported from")
    source = manifest["source"]  # checked by read_manifest: weights is a name inside the run directory
    weights = source["weights"]
    path = run_dir / weights
    if path.is_file():
        sha = file_sha256(path)
        if sha != source["sha256"]:
            run = f"run {source['run']!r}, " if source.get("run") else ""
            raise ExportError(
                f"{path} (sha256 {sha[:12]}) is not the checkpoint this model was exported from "
                f"({run}{weights}, step {source['step']}, sha256 {source['sha256'][:12]}); pass that run directory, or export again"
            )
    policy, config = load_policy(run_dir, weights=weights)
    if dataclasses.asdict(config.model) != manifest["model_config"]:
        raise ExportError(f"{run_dir}/config.json does not describe the exported model; pass the run directory it was exported from")
    return policy, config


def _median_ms(times: list[float]) -> float | None:
    return round(1000 * float(np.median(times)), 3) if times else None


# ------------------------------------------------------------------- verify
def verify_model(
    model_dir: Path,
    run_dir: Path,
    steps: int = 1000,
    threads: int | None = None,
    seed: int = 0,
    batch: int = 1,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Stream ``steps`` ticks through every backend in ``model_dir`` and return the parity report.

    Does not raise on a failed bound: see ``report["passed"]`` (:func:`main` turns it into exit 1).
    """
    import torch

    from export.trajectory import load_trajectory

    if steps < 1:
        raise ExportError(f"--steps must be >= 1, got {steps}")
    model_dir = Path(model_dir)
    manifest = read_manifest(model_dir)
    threads = threads or default_threads()
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        policy, config = load_checked_policy(manifest, run_dir)
        traj = load_trajectory(config, manifest["normalizers"], steps, seed)
        if progress:
            progress(f"streaming {steps} steps ({traj.source})")
        return _stream_and_compare(model_dir, manifest, policy, traj, threads, seed, batch)
    finally:
        torch.set_num_threads(before)


def _open_backends(model_dir: Path, manifest: dict[str, Any], threads: int, batch: int) -> dict[str, GraphStream]:
    outputs = {g: [o["name"] for o in manifest["graphs"][g]["outputs"]] for g in (HISTORY_GRAPH, DENOISER_GRAPH)}
    files = {g: manifest["graphs"][g]["files"] for g in outputs}
    backends = {}
    for kind in ("onnx", "torchscript", "onnx_int8"):
        if not all(kind in files[g] for g in outputs):
            continue
        if kind == "onnx":
            backends[kind] = RuntimeStream(model_dir, threads)  # the robot's own runtime code (it checks the files)
            continue
        # inside the model directory, present, and the size and sha256 the manifest records
        checked = {g: read_graph(model_dir, manifest, g, kind) for g in outputs}
        if kind == "torchscript":
            fns = {g: torchscript_graph(*checked[g]) for g in outputs}
        else:
            fns = {g: onnx_graph(checked[g][0], outputs[g], threads, checked[g][1]) for g in outputs}
        backends[kind] = GraphStream(manifest, fns[HISTORY_GRAPH], fns[DENOISER_GRAPH], batch)
    if not any(k in backends for k in ("onnx", "torchscript")):
        raise ExportError(f"{model_dir} lists no ONNX or TorchScript graphs; export the model again")
    return backends


def _stream_and_compare(model_dir, manifest, policy, traj, threads: int, seed: int, batch: int) -> dict[str, Any]:
    import torch

    backends = _open_backends(model_dir, manifest, threads, batch)
    reference = TorchStream(policy, manifest["denoise_steps"])
    runners: dict[str, Any] = {"torch": reference, **backends}
    fp32 = [k for k in ("onnx", "torchscript") if k in backends]
    errors = {k: dict.fromkeys(FIGURES, 0.0) for k in fp32}
    int8_action, int8_context = 0.0, 0.0
    times = {k: {"history_step": [], "denoiser": []} for k in runners}
    rng = np.random.default_rng(seed)
    main = fp32[0]  # the deployed graphs: their c_t is also checked against the sequence path
    streamed_c, streamed_z = [], []
    h, a = manifest["horizon"], manifest["action_dim"]
    n_chunks = 0
    flagged = []  # chunks where a backend exceeds the bound: (error, inputs, chunks), for the float64 check

    for t in range(traj.length):
        pc = np.repeat(traj.point_cloud[t][None], batch, axis=0)  # (B, P, C)
        pos = np.repeat(traj.agent_pos[t][None], batch, axis=0)  # (B, S)
        z = {}
        for name, runner in runners.items():
            start = time.perf_counter()
            z[name] = runner.observe(pc, pos)
            times[name]["history_step"].append(time.perf_counter() - start)
        for name in fp32:
            e = errors[name]
            e["z_t"] = max(e["z_t"], max_abs(z[name], z["torch"]))
            e["c_t"] = max(e["c_t"], max_abs(backends[name].context, reference.context))
            for got, want in zip(backends[name].states, reference.states):
                e["state"] = max(e["state"], max_abs(got, want))
        if "onnx_int8" in backends:
            int8_context = max(int8_context, max_abs(backends["onnx_int8"].context, backends[main].context))
        streamed_z.append(z[main][0])
        if manifest["use_history"]:
            streamed_c.append(backends[main].context[0])

        if t % manifest["n_action_steps"] == 0:
            noise = rng.standard_normal((batch, h, a)).astype(np.float32)
            chunks = {}
            for name, runner in runners.items():
                start = time.perf_counter()
                chunks[name] = runner.act(noise)
                times[name]["denoiser"].append(time.perf_counter() - start)
            chunk_errors = [max_abs(chunks[name], chunks["torch"]) for name in fp32]
            for name, err in zip(fp32, chunk_errors):
                errors[name]["action"] = max(errors[name]["action"], err)
            if max(chunk_errors) > BOUND:
                inputs = (reference.context, reference.stream.recent.numpy(), noise)
                flagged = sorted([*flagged, (max(chunk_errors), t, inputs, chunks)], key=lambda f: -f[0])[:MAX_FLAGGED]
            if "onnx_int8" in backends:
                int8_action = max(int8_action, max_abs(chunks["onnx_int8"], chunks[main]))
            n_chunks += 1

    # The training path over the whole trajectory at once (observations encoded in blocks to bound memory).
    with torch.no_grad():
        pc_all, pos_all = torch.from_numpy(traj.point_cloud), torch.from_numpy(traj.agent_pos)
        z_seq = torch.cat(
            [policy.encode_observations(pc_all[None, i : i + 64], pos_all[None, i : i + 64]) for i in range(0, traj.length, 64)],
            dim=1,
        )  # (1, T, d)
        sequence = {"z_t": max_abs(np.stack(streamed_z), z_seq[0].numpy())}
        if policy.history_encoder is not None:
            c_seq = policy.history_encoder(z_seq)[0].numpy()  # (T, d)
            sequence["c_t"] = max_abs(np.stack(streamed_c), c_seq)
            sequence["c_t_at_T"] = max_abs(streamed_c[-1], c_seq[-1])

    worst = max([v for e in errors.values() for v in e.values()] + list(sequence.values()))
    floor = _float64_floor(policy, manifest["denoise_steps"], fp32, flagged) if flagged else None
    report: dict[str, Any] = {
        "steps": traj.length,
        "batch": batch,
        "chunks": n_chunks,
        "trajectory": traj.source,
        "threads": threads,
        "bound": BOUND,
        "errors": errors,
        "sequence": {"backend": main, **sequence},
        "action_float64_check": floor,
        "worst": worst,
        "passed": bool(worst <= BOUND),
        "latency_ms": {
            name: {graph: _median_ms(ts) for graph, ts in per.items()} for name, per in times.items()
        },
    }
    if "onnx_int8" in backends:
        lat = report["latency_ms"]
        span = np.asarray(manifest["normalizers"]["action"]["input_max"]) - np.asarray(manifest["normalizers"]["action"]["input_min"])
        report["int8"] = {
            "action_max_abs_vs_fp32": int8_action,
            "action_max_abs_over_range": int8_action / float(max(span.max(), 1e-12)),
            "c_t_max_abs_vs_fp32": int8_context,
            "speedup_history_step": _ratio(lat[main]["history_step"], lat["onnx_int8"]["history_step"]),
            "speedup_denoiser": _ratio(lat[main]["denoiser"], lat["onnx_int8"]["denoiser"]),
        }
    return report


def _float64_floor(policy, num_steps: int, backends: list[str], flagged: list) -> dict[str, Any]:
    """For the chunks above the bound: how far PyTorch's fp32 chunk and each graph's are from float64.

    Diagnostic only: when PyTorch's own fp32 chunk is about as far from float64 as the graphs', the model
    amplifies rounding (a property of the weights), not the export.
    """
    import copy

    import torch

    from export.graphs import DenoiserGraph

    graph64 = DenoiserGraph(copy.deepcopy(policy), num_steps).double().eval()
    floor, deviation = 0.0, dict.fromkeys(backends, 0.0)
    for _, _, (context, recent, noise), chunks in flagged:
        inputs = [torch.from_numpy(x).double() for x, use in ((context, graph64.use_history), (recent, graph64.use_recent)) if use]
        with torch.no_grad():
            exact = graph64(*inputs, torch.from_numpy(noise).double()).numpy()  # (B, H, A)
        floor = max(floor, max_abs(chunks["torch"], exact))
        for name in backends:
            deviation[name] = max(deviation[name], max_abs(chunks[name], exact))
    return {"chunks_checked": len(flagged), "torch_fp32_vs_float64": floor, "graphs_vs_float64": deviation}


def _ratio(a: float | None, b: float | None) -> float | None:
    return round(a / b, 2) if a and b else None


# ------------------------------------------------------------------- report
def format_report(report: dict[str, Any]) -> str:
    """The report as a few aligned lines."""
    lines = [
        f"parity over {report['steps']} steps x batch {report['batch']}, {report['chunks']} chunks "
        f"({report['trajectory']}); max abs error vs the PyTorch streaming policy, bound {report['bound']:g}",
        f"  {'':<12}" + "".join(f"{f:>11}" for f in FIGURES),
    ]
    for name, e in report["errors"].items():
        lines.append(f"  {name:<12}" + "".join(f"{e[f]:>11.2e}" for f in FIGURES))
    seq = report["sequence"]
    parts = ", ".join(f"{k} {v:.2e}" for k, v in seq.items() if k != "backend")
    lines.append(f"  streamed ({seq['backend']}) vs training path over the whole trajectory: {parts}")
    check = report.get("action_float64_check")
    if check:
        graphs = ", ".join(f"{k} {v:.2e}" for k, v in check["graphs_vs_float64"].items())
        lines.append(
            f"  {check['chunks_checked']} chunk(s) above the bound, evaluated in float64: PyTorch fp32 is "
            f"{check['torch_fp32_vs_float64']:.2e} away, the graphs {graphs} (alike: the model amplifies rounding)"
        )
    lines.append(f"  median latency, ms ({report['threads']} threads):   history step      chunk")
    for name, lat in report["latency_ms"].items():
        hs, dn = lat["history_step"], lat["denoiser"]
        lines.append(f"  {name:<12}{'':20}{hs if hs is not None else '-':>12}{dn if dn is not None else '-':>11}")
    if "int8" in report:
        q = report["int8"]
        lines.append(
            f"  int8 vs fp32: action max abs {q['action_max_abs_vs_fp32']:.2e} "
            f"({100 * q['action_max_abs_over_range']:.2f} % of the action range), c_t {q['c_t_max_abs_vs_fp32']:.2e}; "
            f"speed-up history step {q['speedup_history_step']}x, chunk {q['speedup_denoiser']}x (not bounded)"
        )
    lines.append(f"  {'PASS' if report['passed'] else 'FAIL'}: worst fp32 error {report['worst']:.2e}")
    return "\n".join(lines)


def check_report(report: dict[str, Any]) -> None:
    """Raise :class:`ParityError` when a figure exceeds the bound."""
    if report["passed"]:
        return
    check = report.get("action_float64_check")
    others = [v for e in report["errors"].values() for f, v in e.items() if f != "action"]
    others += [v for k, v in report["sequence"].items() if k != "backend"]
    if check and max(others, default=0.0) <= report["bound"]:
        advice = (
            f"only action chunks exceed it, and there PyTorch's own fp32 result is {check['torch_fp32_vs_float64']:.1e} "
            f"from float64 (the graphs {max(check['graphs_vs_float64'].values()):.1e}): this model amplifies rounding; "
            "to keep the graphs anyway, export with --skip-verify"
        )
    else:
        advice = "this is an export bug, please report it with the run's config.json"
    raise ParityError(
        f"exported graphs differ from the PyTorch model by {report['worst']:.2e} > {report['bound']:g} (see the table above); {advice}"
    )


# ---------------------------------------------------------------------- CLI
def build_parser() -> argparse.ArgumentParser:
    p = ArgumentParser(prog="python -m export.verify", description="Check an exported model directory against its checkpoint.")
    p.add_argument("model_dir", help="the exported model directory (dssp_model.json)")
    p.add_argument("--checkpoint", required=True, metavar="RUN_DIR", help="the dssp-train run directory it was exported from")
    p.add_argument("--steps", type=int, default=1000, help="control ticks to stream (default 1000)")
    p.add_argument("--threads", type=int, help="ONNX Runtime and torch intra-op threads (default: all CPUs of this process)")
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
        if args.json:
            check_output_file(args.json, force=args.force, flag="--json", error=ExportError)
        report = verify_model(Path(args.model_dir), Path(args.checkpoint), args.steps, args.threads, args.seed, args.batch, print)
        print(format_report(report))
        if args.json:
            write_output_text(args.json, json.dumps(report, indent=2) + "\n", force=args.force, flag="--json", error=ExportError)
        try:
            check_report(report)
        except ParityError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 1
        return 0

    return run_cli(_main)


if __name__ == "__main__":
    sys.exit(main())
