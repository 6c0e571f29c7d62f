"""DSSP against DP3 on the same CPU, like for like: the same exporter, runtime, precision, threads and spinning.

    python benchmarks/dp3_comparison.py [--scale paper|sim] [--precisions fp32 int8] [--threads N] [--no-spin]
                                        [--repeats R] [--quick] [--json PATH [--force]]

Every model is built from its preset with untrained weights (speed does not depend on their values), exported by
``python -m export.to_onnx`` (fp32 and int8 graphs; DSSP's fused Mamba graphs where the kernel loads) and run
by the robot's runtime (``dssp_deploy.OnnxPolicy``) with the same settings. DP3 is DP3 as trained here (its
point encoder, N frames, the conditional 1-D UNet with FiLM: the ``dp3`` presets), so its per-tick work is its
observation encoder and its chunk K UNet evaluations; DSSP's per-tick work is its observation encoder plus the
history update, its chunk K denoiser passes after the prefix.

Models per ``--scale`` (:data:`SCALES`): ``paper`` — DSSP at the paper's size (``robotwin``, 45.4 M), DP3 at
its own (``dp3``, RoboTwin configuration, 262 M) and DP3 at DSSP's parameter count (UNet widths 200/400/800,
44.6 M); ``sim`` — the simulation study's models (``sim`` 0.67 M, ``dp3_sim`` 0.71 M, ``dp3`` at the sim's
shapes). Problem sizes: ``paper`` 1024 points, state = action = 14 (RoboTwin); ``sim`` 256 points, 7 and 7.

Timed, batch 1, one model after the other in one process (2 warm-up calls, then ``--repeats``; medians):

- **per chunk**: ``OnnxPolicy.act`` (the denoiser graph with its K DDIM steps);
- **per step**: ``OnnxPolicy.observe`` (every control tick: encoding, and for DSSP the history update);
- **per tick**: step + chunk / H_a — the chunk amortised over the actions each chunk executes.

Each model at each precision runs with the same ``--threads`` (default: all CPUs) and the same spinning policy
(the runtime's default: the denoiser's threads spin while a chunk runs when it has 2 or more; ``--no-spin``:
never). The headline ratios are DP3 / DSSP per tick and per chunk at the same precision, at each one's own size
and at equal parameter count. ``--json`` writes every figure with the machine described.
"""

from __future__ import annotations

import contextlib
import io
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the benchmarks' shared helpers
from bench_output import check_json, emit  # noqa: E402
from export_report import make_untrained_run  # noqa: E402

from dssp_core import machine  # noqa: E402
from dssp_core.cli_runner import ArgumentParser, run_cli
from dssp_core.errors import ConfigError
from dssp_deploy.latency import time_calls  # noqa: E402
from dssp_deploy.manifest import DENOISER_GRAPH  # noqa: E402
from dssp_deploy.onnx_policy import OnnxPolicy  # noqa: E402
from dssp_deploy.sessions import check_threads, default_threads  # noqa: E402
from studies.protocol import code_commit  # noqa: E402

SCALES = {
    "paper": {
        "n_points": 1024,
        "state_dim": 14,
        "action_dim": 14,
        "models": {
            "dssp": ("DSSP, the paper's size", "robotwin", []),
            "dp3": ("DP3, its own size", "dp3", []),
            "dp3_equal": ("DP3 at DSSP's parameter count", "dp3", ["model.unet_down_dims=[200,400,800]"]),
        },
    },
    "sim": {
        "n_points": 256,
        "state_dim": 7,
        "action_dim": 7,
        "models": {
            "dssp": ("DSSP (sim preset)", "sim", []),
            "dp3": ("DP3, its own size", "dp3", []),
            "dp3_equal": ("DP3 at DSSP's parameter count (dp3_sim)", "dp3_sim", []),
        },
    },
}
QUICK_OVERRIDES = {"dp3": ["model.unet_down_dims=[32,64,128]"]}  # --quick: DP3's own size is a 1 GB export
PRECISIONS = ("fp32", "int8")
WARMUP = 2
REPEATS, QUICK_REPEATS = 30, 3


def export_model(name: str, preset: str, overrides: list[str], scale: dict, folder: Path) -> tuple[Path, int]:
    """An untrained ``preset`` run exported to ``folder/name`` (fp32 and int8 graphs): (model dir, parameters)."""
    from dssp_train.training.checkpoint import load_policy
    from export.to_onnx import main as export_main

    run = make_untrained_run(
        preset,
        folder / f"{name}_run",
        scale["state_dim"],
        scale["action_dim"],
        overrides=[f"model.n_points={scale['n_points']}", *overrides],
    )
    policy, _ = load_policy(run)
    params = sum(p.numel() for p in policy.parameters())
    del policy
    model = folder / f"{name}_model"
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        code = export_main([str(run), "-o", str(model), "--skip-verify", "--quantize", "int8", "--format", "onnx"])
    if code != 0:
        raise ConfigError(f"exporting {name} ({preset}) failed with exit code {code}")
    return model, params


def time_model(model_dir: Path, precision: str, threads: int, spinning: bool | None, repeats: int) -> dict:
    """Medians (ms) of one model's step and chunk at ``precision``, and the per-tick cost."""
    policy = OnnxPolicy(model_dir, threads=threads, precision=precision, kernel="auto", spinning=spinning)
    rng = np.random.default_rng(0)
    pc, pos = policy.example_observation(rng, policy.contract.n_points)
    policy.reset()
    for _ in range(policy.contract.n_obs_steps + 2):
        policy.observe(pc, pos)
    step = time_calls(lambda: policy.observe(pc, pos), repeats, warmup=WARMUP)
    chunk = time_calls(lambda: policy.act(seed=0), repeats, warmup=WARMUP)
    med = {"step_ms": float(np.median(step)), "chunk_ms": float(np.median(chunk))}
    med["tick_ms"] = med["step_ms"] + med["chunk_ms"] / policy.contract.n_action_steps
    return {
        **med,
        "n_action_steps": policy.contract.n_action_steps,
        "graphs": policy.kernel_note,
        # what the denoiser's quantization covered (export.quantize's note; none at fp32)
        "quantization": policy.sessions[DENOISER_GRAPH].get_modelmeta().custom_metadata_map.get("quantization"),
        "spinning": policy.spinning,
        "step_samples_ms": [round(s, 4) for s in step],
        "chunk_samples_ms": [round(s, 4) for s in chunk],
    }


def compare(
    scale_name: str, precisions: tuple[str, ...], threads: int, spinning: bool | None, repeats: int, quick: bool = False
) -> dict:
    scale = SCALES[scale_name]
    out: dict = {
        "scale": scale_name,
        "problem": {k: scale[k] for k in ("n_points", "state_dim", "action_dim")},
        "settings": {
            "threads": threads,
            "spinning": "runtime default" if spinning is None else spinning,
            "warmup": WARMUP,
            "repeats": repeats,
            "quick": quick,
            "batch": 1,
        },
        "machine": machine.describe(),
        "code_commit": code_commit(),
        "models": {},
    }
    with tempfile.TemporaryDirectory(prefix="dp3_comparison_") as tmp:
        for name, (label, preset, overrides) in scale["models"].items():
            overrides = overrides + (QUICK_OVERRIDES.get(name, []) if quick else [])
            model_dir, params = export_model(name, preset, overrides, scale, Path(tmp))
            row = {"label": label, "preset": preset, "overrides": overrides, "params": params, "precisions": {}}
            for precision in precisions:
                row["precisions"][precision] = time_model(model_dir, precision, threads, spinning, repeats)
            out["models"][name] = row
    out["ratios"] = {
        precision: {
            other: {
                kind: out["models"][other]["precisions"][precision][kind]
                / out["models"]["dssp"]["precisions"][precision][kind]
                for kind in ("tick_ms", "chunk_ms", "step_ms")
            }
            for other in out["models"]
            if other != "dssp"
        }
        for precision in precisions
    }
    return out


def precision_cell(row: dict, precision: str, timed: dict) -> str:
    """The precision a row ran at, saying where DP3's UNet convolutions stayed fp32 in its "int8" graph: before
    ``export.quantize`` quantized convolutions (a record without its ``quantization`` note), or if it did not."""
    unet = row["preset"].startswith("dp3")
    if precision == "int8" and unet and "Conv" not in (timed.get("quantization") or ""):
        return "int8 (UNet convolutions fp32)"
    return precision


def markdown(r: dict) -> str:
    s, p, m = r["settings"], r["problem"], r["machine"]
    lines = [
        f"{m['cpu']} ({m['cores']} cores); onnxruntime {m.get('onnxruntime')}; {s['threads']} threads, spinning: "
        f"{s['spinning']}; batch 1, {p['n_points']} points, state {p['state_dim']}, action {p['action_dim']}; medians of "
        f"{s['repeats']} calls after {s['warmup']} warm-up"
        + (" (--quick: DP3's own size shrunk)" if s["quick"] else "")
        + (f"; code {r['code_commit'][:12]}" if "code_commit" in r else ""),
        "",
        "| model | parameters | precision | step ms | chunk ms | tick ms (step + chunk / H_a) | DP3 / DSSP per tick | per chunk |",
        "|---|---:|---|---:|---:|---:|---:|---:|",
    ]
    for name, row in r["models"].items():
        for precision, t in row["precisions"].items():
            ratio = r["ratios"][precision].get(name)
            cells = ("—", "—") if ratio is None else (f"{ratio['tick_ms']:.1f}x", f"{ratio['chunk_ms']:.1f}x")
            lines.append(
                f"| {row['label']} | {row['params'] / 1e6:.2f} M | {precision_cell(row, precision, t)} | {t['step_ms']:.2f} | "
                f"{t['chunk_ms']:.2f} | "
                f"{t['tick_ms']:.2f} (H_a = {t['n_action_steps']}) | {cells[0]} | {cells[1]} |"
            )
    heads = []
    for name, row in r["models"].items():
        if name == "dssp":
            continue
        per = ", ".join(f"{precision} {ratios[name]['tick_ms']:.1f}x" for precision, ratios in r["ratios"].items())
        heads.append(f"{row['label']}: {per}")
    lines += ["", "DP3's tick / DSSP's tick at the same precision — " + "; ".join(heads) + "."]
    if any(precision_cell(row, p, t) != p for row in r["models"].values() for p, t in row["precisions"].items()):
        lines += [
            "",
            "Where DP3's int8 row is marked, its UNet's convolutions ran fp32 (this record predates the exporter's "
            "quantized convolutions): its int8 ratios are not at one precision, and the row awaits a new run.",
        ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = ArgumentParser(prog="dp3_comparison.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--scale", choices=list(SCALES), default="paper", help="the models and problem size (default paper)")
    p.add_argument("--precisions", nargs="+", choices=list(PRECISIONS), default=list(PRECISIONS))
    p.add_argument("--threads", type=int, help="ONNX Runtime threads of every model (default: all CPUs)")
    p.add_argument(
        "--no-spin", action="store_true", help="no model's threads spin (default: the runtime's policy for all)"
    )
    p.add_argument("--repeats", type=int, help=f"timed calls per figure (default {REPEATS}; --quick {QUICK_REPEATS})")
    p.add_argument(
        "--quick", action="store_true", help=f"short run for tests: {QUICK_REPEATS} calls, DP3's own size shrunk"
    )
    p.add_argument("--json", type=Path, help="write every figure here (a new file; --force replaces one)")
    p.add_argument("--force", action="store_true", help="replace an existing --json file")
    args = p.parse_args(argv)

    def _main() -> int:
        check_threads(args.threads)
        repeats = args.repeats if args.repeats is not None else QUICK_REPEATS if args.quick else REPEATS
        if repeats < 1:
            raise ConfigError(f"--repeats must be at least 1, got {repeats}")
        check_json(args.json, args.force)
        report = compare(
            args.scale,
            tuple(args.precisions),
            args.threads or default_threads(),
            False if args.no_spin else None,
            repeats,
            args.quick,
        )
        return emit(report, markdown(report), args.json, args.force)

    return run_cli(_main)


if __name__ == "__main__":
    sys.exit(main())
