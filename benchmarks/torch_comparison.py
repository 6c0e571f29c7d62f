"""PyTorch against the ONNX runtime on the same model, in one run: eager and TorchScript per component, and
DSSP's history step against a causal Transformer history encoder over the full history.

    python benchmarks/torch_comparison.py MODEL_DIR [--checkpoint RUN_DIR] [--precision fp32|int8] [--quick]
                                          [--threads N] [--json PATH [--force]]

Measures, batch 1, the model's point count, with ``dssp-profile``'s timing helpers:
- ONNX Runtime: the history step and the denoiser chunk (K DDIM steps) of MODEL_DIR;
- PyTorch eager: the same two of the run the model was exported from (``--checkpoint``; its weights'
  sha256 must be the manifest's source), through the streaming API;
- TorchScript: the same two from the model directory's ``*.pt`` graphs, when it has them;
- a history-length sweep: one DSSP history update (ORT) against a causal Transformer of the model's width
  and depth (paper Table 3's alternative) that re-encodes the whole history each step, so its cost grows.
Prints medians in ms and each one's ratio to the ONNX Runtime figure of the same run, and the target
"ORT at least 3x faster than eager per chunk"; ``--json`` writes every figure (a new file; ``--force``
replaces one, checked before measuring).
"""

from __future__ import annotations

import hashlib
import io
import platform
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the benchmarks' shared helpers
from bench_output import check_json, emit  # noqa: E402

from dssp_core.cli_runner import ArgumentParser, run_cli
from dssp_deploy.latency import LatencyStats, time_calls  # noqa: E402
from dssp_deploy.manifest import PRECISIONS, Manifest, ModelDirError, read_graph, read_manifest
from dssp_deploy.onnx_policy import OnnxPolicy
from dssp_deploy.profile import (
    FULL as PROFILE_FULL,
)
from dssp_deploy.profile import (
    QUICK as PROFILE_QUICK,
)
from dssp_deploy.profile import (
    history_sweep,
    profile_components,
    random_observation,
)
from dssp_deploy.sessions import check_threads
from dssp_train.model.history_encoder import CausalTransformer
from dssp_train.model.streaming import StreamingPolicy
from dssp_train.training.checkpoint import load_policy

FULL = {**PROFILE_FULL, "torch_iterations": 30, "sweep": [10, 100, 1000, 3000]}
QUICK = {**PROFILE_QUICK, "torch_iterations": 5, "sweep": [10, 100, 300]}
ORT_VS_EAGER_CHUNK = 3.0  # ORT at least this many times faster than eager PyTorch per chunk
COMPONENTS = ("history_step", "denoiser_chunk")


def check_source(model_dir: Path, checkpoint: Path, manifest: Manifest) -> None:
    """``--checkpoint`` must be the run the model was exported from: its weights file's sha256 is the manifest's."""
    source = manifest.source
    path = Path(checkpoint) / source.weights
    try:
        digest = hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError as exc:
        raise ModelDirError(
            f"--checkpoint {checkpoint}: {path} cannot be read ({exc.strerror or exc}); give the run "
            f"directory {model_dir} was exported from"
        ) from None
    if digest != source.sha256:
        raise ModelDirError(
            f"--checkpoint {checkpoint} is not the run {model_dir} was exported from ({source.weights} "
            f"sha256 {digest[:12]}…, the model's source {source.sha256[:12]}… of run "
            f"{source.run or '?'!r} step {source.step}); give that run, or export this one"
        )


def eager_samples(checkpoint: Path, manifest: Manifest, pc, pos, settings: dict) -> dict[str, list[float]]:
    policy, _ = load_policy(checkpoint, weights=manifest.source.weights)
    stream = StreamingPolicy(policy)
    with torch.inference_mode():
        return {
            "history_step": time_calls(lambda: stream.observe(pc, pos), settings["iterations"]),
            "denoiser_chunk": time_calls(
                lambda: stream.act(seed=0, num_steps=manifest.contract.denoise_steps), settings["torch_iterations"]
            ),
        }


def torchscript_samples(
    model_dir: Path, manifest: Manifest, pc, pos, settings: dict, rng
) -> dict[str, list[float]] | None:
    """None when the model directory has no TorchScript graphs (export --format onnx)."""
    if not all(manifest.graphs[g]["files"].get("torchscript") for g in ("history_step", "denoiser")):
        return None
    m, c = manifest.model, manifest.contract
    history = torch.jit.load(io.BytesIO(read_graph(model_dir, manifest, "history_step", "torchscript")[1]))
    denoiser = torch.jit.load(io.BytesIO(read_graph(model_dir, manifest, "denoiser", "torchscript")[1]))
    state_specs = [s for s in manifest.graphs["history_step"]["inputs"] if s["name"] in manifest.history_state]
    state = [torch.zeros([1, *s["shape"][1:]]) for s in state_specs]
    inputs = []
    if m.use_history:
        inputs.append(torch.zeros(1, m.d_model))
    if m.use_recent_states:
        inputs.append(torch.zeros(1, c.n_obs_steps, m.d_model))
    noise = torch.randn(1, c.horizon, c.action_dim, generator=rng)
    with torch.inference_mode():
        return {
            "history_step": time_calls(lambda: history(pc, pos, *state), settings["iterations"]),
            "denoiser_chunk": time_calls(lambda: denoiser(*inputs, noise), settings["torch_iterations"]),
        }


def transformer_sweep(m: dict, lengths: list[int], rng) -> list[float]:
    """Median ms of one step of a causal Transformer (the model's width and depth) over the whole history."""
    heads = 8 if m["d_model"] % 8 == 0 else 4
    net = CausalTransformer(m["d_model"], m["n_history_layers"], heads).eval()
    out = []
    for length in lengths:
        past = torch.randn(1, length - 1, m["d_model"], generator=rng)

        def step():
            with torch.inference_mode():
                net(torch.cat([past, torch.randn(1, 1, m["d_model"])], dim=1))[:, -1]

        out.append(float(np.median(time_calls(step, 3, warmup=1))))
    return out


def compare(model_dir: Path, checkpoint: Path | None, quick: bool, threads: int | None, precision: str) -> dict:
    settings = QUICK if quick else FULL
    if threads:
        torch.set_num_threads(threads)
    policy = OnnxPolicy(model_dir, threads=threads, precision=precision)
    manifest, m = policy.manifest, policy.manifest.model_config
    ort = profile_components(policy, settings, np.random.default_rng(0))
    pc_np, pos_np = random_observation(policy, np.random.default_rng(0))
    policy.reset()
    dssp_sweep = history_sweep(lambda: policy.observe(pc_np, pos_np), settings["sweep"], settings["window"])

    rng = torch.Generator().manual_seed(0)
    pc, pos = torch.from_numpy(pc_np), torch.from_numpy(pos_np)
    backends = {"ort": {k: ort[k] for k in COMPONENTS}}
    if checkpoint is not None:
        backends["eager"] = eager_samples(checkpoint, manifest, pc, pos, settings)
    scripted = torchscript_samples(model_dir, manifest, pc, pos, settings, rng)
    if scripted is not None:
        backends["torchscript"] = scripted
    tf = transformer_sweep(m, settings["sweep"], rng)

    stats = {b: {k: LatencyStats.of(v).to_dict() for k, v in s.items()} for b, s in backends.items()}
    medians = {b: {k: float(np.median(v)) for k, v in s.items()} for b, s in backends.items()}
    ratios = {b: {k: medians[b][k] / medians["ort"][k] for k in COMPONENTS} for b in medians if b != "ort"}
    sweep = [
        {"length": r["length"], "dssp_ort_ms": r["p50_ms"], "transformer_torch_ms": t, "ratio": t / r["p50_ms"]}
        for r, t in zip(dssp_sweep, tf)
    ]
    return {
        "model_dir": str(model_dir),
        "checkpoint": str(checkpoint) if checkpoint else None,
        "precision": precision,
        "machine": {
            "processor": platform.processor() or platform.machine(),
            "threads": threads,
            "torch": torch.__version__,
            "torch_threads": torch.get_num_threads(),
        },
        "settings": {"quick": quick, **settings},
        "median_ms": medians,
        "latency_ms": stats,
        "ratio_to_ort": ratios,
        "history_sweep": sweep,
        "target_ort_vs_eager_chunk": ORT_VS_EAGER_CHUNK,
    }


def markdown(report: dict) -> str:
    med, ratios = report["median_ms"], report["ratio_to_ort"]
    names = {"eager": "PyTorch eager", "torchscript": "TorchScript"}
    others = [b for b in names if b in med]
    lines = [
        f"Model: {report['model_dir']} ({report['precision']} ONNX graphs; PyTorch in fp32, torch "
        f"{report['machine']['torch']}, {report['machine']['torch_threads']} threads) — medians, same run",
        "",
        "| component | ONNX Runtime ms | " + " | ".join(f"{names[b]} ms | {names[b]} / ORT" for b in others) + " |",
        "|---|---:|" + "---:|---:|" * len(others),
    ]
    for key, label in (("history_step", "history step"), ("denoiser_chunk", "denoiser chunk")):
        cells = "".join(f" {med[b][key]:.2f} | {ratios[b][key]:.1f}x |" for b in others)
        lines.append(f"| {label} | {med['ort'][key]:.2f} |{cells}")
    if "eager" not in med:
        lines += ["", "PyTorch eager: not measured (give --checkpoint RUN_DIR, the run the model was exported from)"]
    else:
        ratio, target = ratios["eager"]["denoiser_chunk"], report["target_ort_vs_eager_chunk"]
        lines += [
            "",
            f"ONNX Runtime vs PyTorch eager per chunk: eager takes {ratio:.1f}x ORT's time (target ≥ {target:g}x: "
            f"{'met' if ratio >= target else 'not met'})",
        ]
    if "torchscript" not in med:
        lines.append("TorchScript: not measured (the model directory has no *.pt graphs)")
    lines += [
        "",
        "| history length | DSSP step (ORT) ms | causal Transformer, full history (torch) ms | Transformer / DSSP |",
        "|---:|---:|---:|---:|",
    ]
    for r in report["history_sweep"]:
        lines.append(
            f"| {r['length']} | {r['dssp_ort_ms']:.3f} | {r['transformer_torch_ms']:.2f} | {r['ratio']:.1f}x |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = ArgumentParser(prog="torch_comparison.py", description=__doc__.split("\n\n")[0])
    p.add_argument("model_dir", type=Path, help="a model directory (python -m export.to_onnx)")
    p.add_argument("--checkpoint", type=Path, help="the run directory it was exported from, for PyTorch eager")
    p.add_argument(
        "--precision", choices=sorted(PRECISIONS), default="fp32", help="ONNX graphs to time (PyTorch runs in fp32)"
    )
    p.add_argument("--quick", action="store_true", help="short run (tests)")
    p.add_argument("--threads", type=int, help="ONNX Runtime and torch intra-op threads (default: all CPUs)")
    p.add_argument("--json", type=Path, help="write every figure here (a new file; --force replaces one)")
    p.add_argument("--force", action="store_true", help="replace an existing --json file")
    args = p.parse_args(argv)

    def _main() -> int:
        check_threads(args.threads)
        check_json(args.json, args.force)
        if args.checkpoint is not None:  # before minutes of measuring
            check_source(args.model_dir, args.checkpoint, read_manifest(args.model_dir))
        report = compare(args.model_dir, args.checkpoint, args.quick, args.threads, args.precision)
        return emit(report, markdown(report), args.json, args.force)

    return run_cli(_main)


if __name__ == "__main__":
    sys.exit(main())
