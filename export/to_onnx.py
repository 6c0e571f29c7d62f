"""Export a trained DSSP run directory to a self-contained model directory for ONNX Runtime.

    python -m export.to_onnx RUN_DIR -o MODEL_DIR [--denoise-steps K] [--opset N] [--format onnx|torchscript|both]
                             [--no-ema] [--quantize int8 int4 | none] [--no-fused] [--skip-verify] [--verify-steps T]
                             [--force] [--threads N]

The split follows the architecture: the recurrent history encoder becomes a stepwise graph run once per
control tick (``history_step``), the action generator a fixed-step denoiser graph run once per action
chunk (``denoiser``, K DDIM steps inside). MODEL_DIR gets::

    history_step.onnx, denoiser.onnx     fp32 graphs (--format onnx|both)
    *.fused.onnx                         the same graphs with the fused Mamba operators (ai.dssp::CausalConv1d,
                                         ai.dssp::SelectiveScan), when the kernel library loads here (make kernel)
                                         and unless --no-fused
    history_step.pt, denoiser.pt         the same traced modules as TorchScript archives (--format torchscript|both)
    *.int8.onnx, *.int4.onnx             quantized graphs, standard and fused (--quantize, default both)
    dssp_model.json                      the manifest (see export.manifest_writer): graph inputs/outputs, N, H, H_a, K, DDIM
                                         timesteps, normalisers, control rate, source (run name, weights file,
                                         sha256, step, EMA or raw; no path), file sizes and sha256, versions,
                                         parity figures

The directory appears all at once (see :mod:`export.output_dir`); an existing previous export is replaced
only with ``--force``, and a second export into the same MODEL_DIR while one runs is refused. A config.json
edited since training (it differs from the config the weights record) is refused, naming the fields. Unless
``--skip-verify``, :mod:`export.verify` compares the graphs with the PyTorch
model over ``--verify-steps`` ticks (the ONNX graphs streamed through the robot's runtime, the reference
computed in batch on the training path) before the directory is moved into place; a parity failure
leaves nothing behind.

Exit codes: 0 done, 1 parity failed, 2 bad input (the message says what to do).
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import importlib.metadata
import math
import platform
import sys
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

import dssp_train
from dssp_core.cli_runner import ArgumentParser, run_cli
from dssp_core.errors import ExportError, ParityError
from dssp_core.staging import writer_lock
from dssp_deploy.mamba_kernel import DOMAIN, OPSET_VERSION, kernel
from dssp_deploy.manifest import (
    DENOISER_GRAPH,
    GRAPHS,
    HISTORY_GRAPH,
    MANIFEST_NAME,
    PRECISIONS,
    file_kind,
    file_suffix,
    graph_io,
)
from dssp_deploy.sessions import check_threads
from dssp_train.config import TIMESTEP_SPACINGS as SPACINGS
from dssp_train.model.mamba import Mamba
from export.fused_ops import fitting_blocks, mark_unread_states, use_fused_blocks
from export.graphs import DenoiserGraph, HistoryStepGraph, check_exportable, use_fused_ops
from export.manifest_writer import build_manifest, metadata_props, write_manifest
from export.output_dir import StagedDirectory
from export.quantize import QUANTIZERS, keep_int8_blocks
from export.verify import file_sha256, verify_model
from export.verify_report import check_report, describe_worst, format_report

EXPORTER_VERSION = "1"
SUPPORTED_OPSETS = range(17, 21)  # LayerNormalization needs 17; torch's TorchScript-based exporter stops at 20
DEFAULT_OPSET = 17
FORMATS = {"onnx": ("onnx",), "torchscript": ("torchscript",), "both": ("onnx", "torchscript")}
WEIGHTS = {True: "model.safetensors", False: "checkpoint/model.safetensors"}
QUANTIZED = tuple(p for p in PRECISIONS if p != "fp32")


# ------------------------------------------------------------------ loading
def load_source(run_dir: Path, ema: bool = True):
    """(policy, config, source facts) for RUN_DIR's EMA (default) or raw weights."""
    from safetensors import safe_open  # deferred: loads safetensors

    from dssp_train.training.checkpoint import load_policy  # deferred: loads safetensors

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ExportError(f"run directory {run_dir} does not exist; pass a dssp-train --out directory")
    weights = WEIGHTS[ema]
    if not ema and not (run_dir / weights).is_file():
        raise ExportError(
            f"{run_dir / weights} is missing: --no-ema needs the run's checkpoint folder; drop --no-ema to export the EMA weights"
        )
    policy, config = load_policy(run_dir, weights=weights)
    check_exportable(policy)
    path = run_dir / weights
    check_finite_weights(policy, path)
    with safe_open(str(path), "pt") as f:
        step = (f.metadata() or {}).get("step")
    source = {  # the run's identity, not where it lived on the training machine
        "run": run_dir.resolve().name,
        "weights": weights,
        "ema": ema,
        "sha256": file_sha256(path),
        "step": int(step) if step and step.isdecimal() else None,
    }
    return policy, config, source


def check_finite_weights(policy, path: Path) -> None:
    """Refuse weights (and normaliser statistics) with NaN or infinity, naming the first such tensor: the graphs
    would compute NaN, or with int8 plausible-looking garbage, on every input."""

    for name, tensor in policy.state_dict().items():
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            count = int((~torch.isfinite(tensor)).sum())
            raise ExportError(
                f"{path}: tensor {name} {list(tensor.shape)} holds {count} non-finite value(s) (NaN/inf); "
                "nothing was exported: export an earlier checkpoint of the run, or train again (the loss "
                "diverged: a lower learning rate)"
            )


def without_local_paths(report: dict[str, Any], dataset: str | None) -> dict[str, Any]:
    """The parity report for the manifest: the dataset named by its folder name, not its path on this machine."""
    if not dataset or not isinstance(report.get("trajectory"), str):
        return report
    return {**report, "trajectory": report["trajectory"].replace(str(Path(dataset)), Path(dataset).name)}


def library_versions() -> dict[str, str]:
    import onnx  # deferred: loads onnx
    import onnxruntime  # deferred: loads onnxruntime

    try:
        dssp = importlib.metadata.version("dssp")
    except importlib.metadata.PackageNotFoundError:
        dssp = dssp_train.__version__
    return {
        "dssp": dssp,
        "torch": torch.__version__,
        "onnx": onnx.__version__,
        "onnxruntime": onnxruntime.__version__,
        "python": platform.python_version(),
    }


@contextlib.contextmanager
def quiet_tracing():
    """Silence the deprecation notices of torch.jit.trace and of the TorchScript-based ONNX exporter.

    Both are used on purpose: the torch.export-based exporter took 96 s for the tiny denoiser (the
    TorchScript-based one 3 s) and gave a larger graph that ran 2x slower in ONNX Runtime.
    """

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=DeprecationWarning)
        warnings.filterwarnings("ignore", category=FutureWarning)
        warnings.filterwarnings("ignore", category=torch.jit.TracerWarning)
        warnings.filterwarnings("ignore", message="no signature found")
        warnings.filterwarnings(
            "ignore", message="Constant folding - Only steps=1"
        )  # harmless: such slices stay in the graph
        yield


# ----------------------------------------------------------------- tracing
def example_inputs(contract, model, graph: str, batch: int = 2) -> tuple:
    """Random inputs with the graph's shapes (``contract``: the model's contract, ``model``: its architecture), B =
    ``batch`` (2, so no size-1 broadcast is baked in)."""

    gen = torch.Generator().manual_seed(0)
    inputs, _ = graph_io(contract, model, graph)
    shapes = [[batch if d == "B" else contract.n_points if d == "P" else d for d in s["shape"]] for s in inputs]
    return tuple(torch.randn(shape, generator=gen) for shape in shapes)


def graph_modules(policy, denoise_steps: int, inpainting: bool = False) -> dict[str, Any]:
    """{graph name: the torch module that becomes it}."""

    return {
        HISTORY_GRAPH: HistoryStepGraph(policy).eval(),
        DENOISER_GRAPH: DenoiserGraph(policy, denoise_steps, inpainting).eval(),
    }


def trace(module, example: tuple):
    """The TorchScript trace of one graph module."""

    with torch.no_grad(), quiet_tracing():
        return torch.jit.trace(module, example, check_trace=False)


# -------------------------------------------------------------------- ONNX
def write_onnx(
    module,
    example: tuple,
    path: Path,
    contract,
    model,
    graph: str,
    opset: int,
    metadata: dict[str, str],
    fused: bool = False,
) -> None:
    """Export one graph module to ``path``; set the manifest's IO shapes and metadata; run the full checker.

    ``fused``: the module's Mamba layers use :data:`export.fused_ops.FUSED_OPS`, so the graph holds the
    ``ai.dssp`` operators (the checker checks everything but their inside).

    The module itself is exported (the exporter traces it again): a TorchScript trace loses the tensor
    ranks that the ONNX conversion of ``transpose`` needs.
    """
    import onnx  # deferred: loads onnx

    inputs, outputs = graph_io(contract, model, graph)
    dynamic_axes = {s["name"]: {i: d for i, d in enumerate(s["shape"]) if isinstance(d, str)} for s in inputs + outputs}
    with torch.no_grad(), quiet_tracing():
        torch.onnx.export(
            module,
            example,
            str(path),
            dynamo=False,
            opset_version=opset,
            input_names=[s["name"] for s in inputs],
            output_names=[s["name"] for s in outputs],
            dynamic_axes=dynamic_axes,
            do_constant_folding=True,
            custom_opsets={DOMAIN: OPSET_VERSION} if fused and has_fused_layers(module) else None,
        )
    model = onnx.load(str(path))
    for values, specs in ((model.graph.input, inputs), (model.graph.output, outputs)):
        names = [v.name for v in values]
        if names != [s["name"] for s in specs]:
            raise RuntimeError(f"{path.name}: graph {names} != manifest {[s['name'] for s in specs]}")
        for value, spec in zip(values, specs):
            dims = value.type.tensor_type.shape.dim
            del dims[:]
            for d in spec["shape"]:
                dim = dims.add()
                if isinstance(d, str):
                    dim.dim_param = d
                else:
                    dim.dim_value = d
    drop_weight_identities(model)
    if fused:
        mark_unread_states(model)
    model.producer_name = "dssp export.to_onnx"
    model.producer_version = EXPORTER_VERSION
    model.doc_string = f"DSSP {graph} graph; see {MANIFEST_NAME} next to this file"
    onnx.helper.set_model_props(model, metadata)
    onnx.save(model, str(path))
    onnx.checker.check_model(str(path), full_check=True)


def write_block_graph(
    module, example: tuple, beside: Path, contract, model, graph: str, opset: int, metadata: dict[str, str]
) -> Path:
    """The graph to quantize into the int8 fused one when ``module`` has denoiser blocks that run as one node each
    (``ai.dssp::MambaBlockQ8``, int8 weights: :class:`export.fused_ops.QuantizedMambaBlock`): a copy of the fused
    module with those blocks, written to a hidden file beside ``beside`` (the caller removes it)."""
    blocks = copy.deepcopy(module)
    use_fused_blocks(blocks)
    path = beside.with_name(f".{beside.stem}.blocks.onnx")
    write_onnx(blocks, example, path, contract, model, graph, opset, metadata, fused=True)
    return path


def has_fused_layers(module) -> bool:
    """Whether ``module`` has a layer routed through the fused operators (a Mamba layer or the point encoder; a
    Transformer denoiser has none)."""
    return any(getattr(m, "fused_ops", None) is not None for m in module.modules())


def drop_weight_identities(model) -> int:
    """Let every node read shared weights directly; returns the number of Identity nodes removed.

    The exporter gives each reuse of a weight (the K unrolled denoiser steps share every layer) its own
    ``Identity`` of the initializer. ONNX Runtime removes them when it loads the graph, but the int8
    quantizer only quantizes a MatMul whose weight *is* an initializer: with the Identities in place it
    quantized one use in eleven and kept the fp32 copy for the rest.
    """
    graph = model.graph
    weights = {t.name for t in graph.initializer}
    outputs = {o.name for o in graph.output}
    alias = {
        node.output[0]: node.input[0]
        for node in graph.node
        if node.op_type == "Identity" and node.input[0] in weights and node.output[0] not in outputs
    }
    kept = [node for node in graph.node if not (node.op_type == "Identity" and node.output[0] in alias)]
    _rename_inputs(kept, alias)
    del graph.node[:]
    graph.node.extend(kept)
    return len(alias)


def _rename_inputs(nodes, alias: dict[str, str]) -> None:
    """Rename node inputs, in subgraphs (If branches) too, which may read outer names."""
    for node in nodes:
        node.input[:] = [alias.get(name, name) for name in node.input]
        for attr in node.attribute:
            for sub in [attr.g] if attr.type == attr.GRAPH else list(attr.graphs):
                _rename_inputs(sub.node, alias)


def onnx_node_count(path: Path) -> int:
    import onnx  # deferred: loads onnx

    return len(onnx.load(str(path), load_external_data=False).graph.node)


def weight_reads(path: Path) -> int:
    """How many nodes of the graph at ``path`` read its largest weight (the initializer with the most elements):
    how often one run reads its weights. The denoiser's: K, once per DDIM step (the first step carries the prefix);
    the history step's: 1."""
    import onnx  # deferred: loads onnx

    graph = onnx.load(str(path), load_external_data=False).graph
    if not graph.initializer:
        return 0
    largest = max(graph.initializer, key=lambda t: math.prod(t.dims)).name
    return sum(largest in node.input for node in graph.node)


# ------------------------------------------------------------------- export
def export_model(
    run_dir: Path,
    out_dir: Path,
    *,
    denoise_steps: int | None = None,
    timestep_spacing: str | None = None,
    opset: int = DEFAULT_OPSET,
    fmt: str = "both",
    ema: bool = True,
    quantize: tuple[str, ...] | str | None = None,
    fused: bool = True,
    verify: bool = True,
    verify_steps: int = 1000,
    force: bool = False,
    threads: int | None = None,
    inpainting: bool = False,
    progress: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Export RUN_DIR to MODEL_DIR; return a summary (files with sizes and node counts, parity report).
    ``inpainting``: the denoiser graph also takes the committed actions and their weights (real-time chunking,
    ``dssp-run --smoothing rtc``); with zero weights it is the plain chain.

    Raises:
        ExportError: bad input (nothing is written).
        ParityError: the graphs do not reproduce the PyTorch model (nothing is left behind).
    """
    from dssp_train.training.checkpoint import config_recorded  # deferred: loads safetensors

    if opset not in SUPPORTED_OPSETS:
        raise ExportError(
            f"--opset {opset} is not supported; use {SUPPORTED_OPSETS.start}..{SUPPORTED_OPSETS.stop - 1} (default {DEFAULT_OPSET})"
        )
    if fmt not in FORMATS:
        raise ExportError(f"--format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    if quantize is None:  # the default: every precision, when there are ONNX graphs to quantize
        quantize = QUANTIZED if "onnx" in FORMATS.get(fmt, ()) else ()
    quantize = tuple(dict.fromkeys((quantize,) if isinstance(quantize, str) else quantize))
    unknown = [q for q in quantize if q not in QUANTIZED]
    if unknown:
        raise ExportError(f"--quantize takes {', '.join(QUANTIZED)} or none, got {', '.join(unknown)}")
    if quantize and "onnx" not in FORMATS[fmt]:
        raise ExportError(
            f"--quantize {' '.join(quantize)} quantizes the ONNX graphs; use --format onnx or both, or --quantize none"
        )
    if verify and verify_steps < 1:
        raise ExportError(f"--verify-steps must be >= 1, got {verify_steps}")
    formats = FORMATS[fmt]
    run_dir, out_dir = Path(run_dir), Path(out_dir)
    started = time.perf_counter()
    kernel_note = None
    if fused and "onnx" in formats:
        found = kernel()
        fused = found.available
        if not fused:
            kernel_note = f"fused graphs not written: {found.reason}"
    else:
        fused = False
    n_stages = 4 + bool(quantize) + verify + fused

    clock = [time.perf_counter(), 0]

    def stage(message: str) -> None:
        clock[1] += 1
        now = time.perf_counter()
        progress(f"[{clock[1]}/{n_stages}] {message} ({now - clock[0]:.1f} s)")
        clock[0] = now

    with (
        writer_lock(out_dir, what="model directory", flag="-o", error=ExportError),
        StagedDirectory(out_dir, force) as staged,
    ):
        policy, config, source = load_source(run_dir, ema)  # refuses a config.json edited since training
        if fused and not any(isinstance(m, Mamba) for m in policy.modules()):  # e.g. DP3: nothing to fuse
            fused, kernel_note = (
                False,
                "fused graphs not written: the model has no Mamba layer (they would be its standard graphs)",
            )
            n_stages -= 1
        unrecorded = (
            ""
            if config_recorded(run_dir / WEIGHTS[ema])
            else ("; its config is not recorded (saved by an older version): config.json taken as it is")
        )
        diffusion = config.model.diffusion
        if timestep_spacing is not None:
            if timestep_spacing not in SPACINGS:
                raise ExportError(f"--timestep-spacing must be one of {', '.join(SPACINGS)}, got {timestep_spacing!r}")
            diffusion.timestep_spacing = timestep_spacing  # the policy's schedule reads these same settings
        k = diffusion.num_inference_steps if denoise_steps is None else denoise_steps
        if not 1 <= k <= diffusion.num_train_timesteps:
            raise ExportError(
                f"--denoise-steps must be in [1, {diffusion.num_train_timesteps}] (the training timesteps), got {k}"
            )
        timesteps = policy.schedule.inference_timesteps(k)
        stage(
            f"loaded {run_dir} ({'EMA' if ema else 'raw'} weights, step {source['step']}, sha256 {source['sha256'][:12]}{unrecorded})"
        )

        modules = graph_modules(policy, k, inpainting)
        contract = config.contract(timesteps, inpainting)
        examples = {g: example_inputs(contract, config.model, g) for g in GRAPHS}
        caching = (
            "prefix in every step (timestep_decoupled false)"
            if not config.model.timestep_decoupled
            else "prefix in the first step's pass, its state cached"
            if k > 1 and policy.denoiser.joins_prefix
            else "prefix encoded once"
            if k > 1
            else "prefix and actions in one pass"
        )
        stage(f"built {HISTORY_GRAPH} and {DENOISER_GRAPH} (K = {k} DDIM steps {timesteps}, {caching})")

        files: dict[str, dict[str, str]] = {g: {} for g in GRAPHS}
        onnx_kinds = (
            [file_kind(p, f) for p in ("fp32", *quantize) for f in (False, True)[: 1 + fused]]
            if "onnx" in formats
            else []
        )
        for g in GRAPHS:
            for kind in onnx_kinds + (["torchscript"] if "torchscript" in formats else []):
                files[g][kind] = f"{g}{file_suffix(kind)}"
        manifest = build_manifest(
            config,
            contract,
            normalizers={name: norm.stats() for name, norm in policy.normalizers.items()},
            files=files,
            source=source,
            exporter={
                "name": "export.to_onnx",
                "version": EXPORTER_VERSION,
                "onnx_exporter": "torch.onnx.export (TorchScript-based, dynamo=False) of the traced modules",
                "opset": opset if "onnx" in formats else None,
            },
            versions=library_versions(),
        )

        if "torchscript" in formats:
            for g in GRAPHS:
                trace(modules[g], examples[g]).save(str(staged.path / files[g]["torchscript"]))
            stage(f"wrote {', '.join(files[g]['torchscript'] for g in GRAPHS)} (TorchScript)")
        else:
            stage("TorchScript not requested")
        if "onnx" in formats:
            for g in GRAPHS:
                write_onnx(
                    modules[g],
                    examples[g],
                    staged.path / files[g]["onnx"],
                    contract,
                    config.model,
                    g,
                    opset,
                    metadata_props(manifest, g),
                )
            stage(
                f"wrote {', '.join(files[g]['onnx'] for g in GRAPHS)} (opset {opset}, onnx.checker full_check passed)"
            )
        else:
            stage("ONNX not requested")
        if fused:
            kind = file_kind("fp32", fused=True)
            for g in GRAPHS:  # the same modules, their Mamba layers now on the fused operators
                use_fused_ops(modules[g])
                write_onnx(
                    modules[g],
                    examples[g],
                    staged.path / files[g][kind],
                    contract,
                    config.model,
                    g,
                    opset,
                    metadata_props(manifest, g),
                    fused=True,
                )
            stage(f"wrote {', '.join(files[g][kind] for g in GRAPHS)} (fused Mamba operators)")
        elif kernel_note:
            progress(kernel_note)
        if quantize:
            written = []
            for precision in quantize:
                for is_fused in (False, True)[: 1 + fused]:
                    src, dst = file_kind("fp32", is_fused), file_kind(precision, is_fused)
                    for g in GRAPHS:
                        source = staged.path / files[g][src]
                        blocks = precision == "int8" and is_fused and fitting_blocks(modules[g])
                        if blocks:  # each denoiser block as one int8 node: a graph traced anew, kept as it is
                            source = write_block_graph(
                                modules[g],
                                examples[g],
                                source,
                                contract,
                                config.model,
                                g,
                                opset,
                                metadata_props(manifest, g),
                            )
                        quantizer = keep_int8_blocks if blocks else QUANTIZERS[precision]
                        quantizer(source, staged.path / files[g][dst], metadata_props(manifest, g))
                        if blocks:
                            source.unlink()
                        written.append(files[g][dst])
            stage(f"wrote {', '.join(written)} (ONNX Runtime quantization: {', '.join(quantize)})")

        manifest["files"] = {}
        for g in GRAPHS:
            for kind, name in files[g].items():
                path = staged.path / name
                info = {"bytes": path.stat().st_size, "sha256": file_sha256(path)}
                if name.endswith(".onnx"):
                    info["onnx_nodes"] = onnx_node_count(path)
                    info["weight_reads"] = weight_reads(path)
                manifest["files"][name] = info
        write_manifest(staged.path, manifest)
        del modules, policy

        report = None
        if verify:
            report = verify_model(staged.path, run_dir, verify_steps, threads, progress=progress)
            progress(format_report(report))
            manifest["verification"] = without_local_paths(report, config.dataset)
            write_manifest(staged.path, manifest)
            stage(f"verified: worst {describe_worst(report)} (bound {report['bound']:g})")
            check_report(report)
        final = staged.commit()

    summary = {
        "model_dir": str(final),
        "seconds": round(time.perf_counter() - started, 1),
        "files": {name: manifest["files"][name] for name in sorted(manifest["files"])},
        "manifest": MANIFEST_NAME,
        "verification": report,
    }
    return summary


def format_summary(summary: dict[str, Any]) -> str:
    lines = [f"exported to {summary['model_dir']} in {summary['seconds']} s"]
    for name, info in summary["files"].items():
        nodes = f"{info['onnx_nodes']:>7} nodes" if "onnx_nodes" in info else ""
        lines.append(f"  {name:<26}{info['bytes'] / 2**20:>9.2f} MiB{nodes}")
    lines.append(f"  {summary['manifest']}")
    report = summary["verification"]
    if report is None:
        lines.append("parity: not verified (--skip-verify); run python -m export.verify MODEL_DIR --checkpoint RUN_DIR")
    else:
        lines.append(
            f"parity: {', '.join(report['errors'])} vs PyTorch fp32 (training path) over {report['steps']} steps and "
            f"{report['chunks']} of {report.get('chunk_ticks_total', report['chunks'])} chunks: worst {describe_worst(report)} "
            f"<= {report['bound']:g}"
        )
        for name, q in report.get("quantized", {}).items():
            lines.append(
                f"{name}: action max abs error vs fp32 {q['action_max_abs_vs_fp32']:.2e}, "
                f"speed-up {q['speedup_history_step']}x per history step, {q['speedup_denoiser']}x per chunk"
            )
    return "\n".join(lines)


# ---------------------------------------------------------------------- CLI
def build_parser() -> argparse.ArgumentParser:
    p = ArgumentParser(
        prog="python -m export.to_onnx", description="Export a DSSP run directory to ONNX / TorchScript graphs."
    )
    p.add_argument("run_dir", metavar="RUN_DIR", help="a dssp-train run directory (config.json, model.safetensors)")
    p.add_argument("-o", "--out", required=True, metavar="MODEL_DIR", help="the model directory to create")
    p.add_argument(
        "--denoise-steps",
        type=int,
        metavar="K",
        help="DDIM steps inside the denoiser graph (default: the config's, 10)",
    )
    p.add_argument(
        "--timestep-spacing",
        choices=SPACINGS,
        help="where the K timesteps sit: leading [90..0] or trailing "
        "[99..9] (default: the config's; trailing lets K = 1 start from noise)",
    )
    p.add_argument(
        "--opset",
        type=int,
        default=DEFAULT_OPSET,
        help=f"ONNX opset, {SUPPORTED_OPSETS.start}..{SUPPORTED_OPSETS.stop - 1} (default {DEFAULT_OPSET})",
    )
    p.add_argument("--format", dest="fmt", default="both", choices=list(FORMATS), help="graphs to write (default both)")
    p.add_argument(
        "--no-ema",
        action="store_true",
        help="export the raw weights (RUN_DIR/checkpoint/model.safetensors), not the EMA ones",
    )
    p.add_argument(
        "--quantize",
        nargs="+",
        metavar="PRECISION",
        choices=[*QUANTIZED, "none"],
        help=f"quantized graphs to write beside the fp32 ONNX ones: {' '.join(QUANTIZED)} (default: both) or none",
    )
    p.add_argument(
        "--no-fused",
        action="store_true",
        help="do not write the *.fused.onnx graphs (written by default when the fused Mamba kernel loads)",
    )
    p.add_argument("--skip-verify", action="store_true", help="do not stream the parity check before finishing")
    p.add_argument(
        "--verify-steps", type=int, default=1000, help="control ticks the parity check streams (default 1000)"
    )
    p.add_argument("--threads", type=int, help="threads for the parity check (default: all CPUs of this process)")
    p.add_argument(
        "--inpainting",
        action="store_true",
        help="the denoiser also takes the committed actions and their weights, for real-time chunking "
        "(dssp-run --smoothing rtc); zero weights give the plain chain",
    )
    p.add_argument("--force", action="store_true", help="replace MODEL_DIR when it holds a previous export")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)

    def _main() -> int:
        check_threads(args.threads)
        try:
            summary = export_model(
                Path(args.run_dir),
                Path(args.out),
                denoise_steps=args.denoise_steps,
                timestep_spacing=args.timestep_spacing,
                opset=args.opset,
                fmt=args.fmt,
                ema=not args.no_ema,
                quantize=None if args.quantize is None else tuple(q for q in args.quantize if q != "none"),
                fused=not args.no_fused,
                verify=not args.skip_verify,
                verify_steps=args.verify_steps,
                force=args.force,
                threads=args.threads,
                inpainting=args.inpainting,
            )
        except ParityError as exc:
            print(f"error: {exc}; nothing was written to {args.out}", file=sys.stderr)
            return 1
        print(format_summary(summary))
        return 0

    return run_cli(_main)


if __name__ == "__main__":
    sys.exit(main())
