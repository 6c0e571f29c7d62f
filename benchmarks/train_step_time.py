"""Training cost on this machine: one optimisation step for the ``tiny`` and ``robotwin`` presets, and
the history encoder's forward + backward over a 600-step trajectory.

    python benchmarks/train_step_time.py [--repeats 5] [--robotwin-length 300] [--device cpu|cuda] [--json PATH [--force]]

    python benchmarks/train_step_time.py --paper [--repeats 3] [--device cpu|cuda] [--json PATH [--force]]

Prints a Markdown table of medians (and min/max) in milliseconds. A step is what ``dssp-train``
does: encode one whole trajectory (E_obs, G_psi), B windows through the denoiser, both losses,
backward, AdamW, EMA. Inputs are random tensors of the preset's shapes (RoboTwin: 1024 xyz points,
S = A = 14).

``--paper``: what reproducing one task of the paper costs on this device, for each paper preset — its
step at a typical trajectory of its benchmark (PAPER_TASKS: length, state and action sizes, demonstrations)
times its budget in steps (the preset's epochs x demonstrations, every one trained on, as ``dssp-train``
resolves it).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys

import torch

from dssp_core.cli_runner import run_cli
from dssp_core.errors import DSSPError
from dssp_core.output_guard import check_output_file, write_output_text
from dssp_deploy.latency import time_calls
from dssp_train.config import load_preset, resolve_epochs
from dssp_train.model.history_encoder import HistoryEncoder
from dssp_train.model.policy import DSSPPolicy
from dssp_train.training.ema import EMA

# One typical task per paper preset: (trajectory length T, state size S, action size A, demonstrations).
# MetaWorld: DP3's episodes of 200 steps, agent_pos 9, action 4; Adroit: at most 200 steps (the hammer and
# door tasks' horizon), agent_pos 24, action 26 (hammer); both 10 demonstrations (the paper's Appendix C);
# RoboTwin: 50 demonstrations of about 300 steps (episodes run 100-640), S = A = 14.
PAPER_TASKS = {"metaworld": (200, 9, 4, 10), "adroit": (200, 24, 26, 10), "robotwin": (300, 14, 14, 50)}


def synchronized(step, device: str):
    """``step`` that waits for the device's queued work, so a timed call is the whole step."""
    if device != "cuda":
        return step

    def run():
        step()
        torch.cuda.synchronize()

    return run


def train_step_fn(preset: str, length: int, state_dim: int, action_dim: int, device: str = "cpu"):
    cfg = load_preset(preset)
    m = cfg.model
    m.state_dim, m.action_dim = state_dim, action_dim
    torch.manual_seed(0)
    policy = DSSPPolicy(m)
    pc = torch.randn(length, m.n_points, m.point_dim)
    pos, act = torch.randn(length, state_dim), torch.randn(length, action_dim)
    policy.fit_normalizers(pc.numpy(), pos.numpy(), act.numpy())
    policy.to(device)
    pc, pos, act = pc.to(device), pos.to(device), act.to(device)
    opt = torch.optim.AdamW(policy.parameters(), lr=1e-4, betas=(0.95, 0.999), weight_decay=1e-6)
    ema = EMA(policy)
    gen = torch.Generator().manual_seed(0)
    batch = cfg.train.batch_size

    def step():
        starts = torch.randint(0, length - m.n_action_steps + 1, (batch,), generator=gen).to(device)
        loss = policy.compute_loss(pc, pos, act, starts, gen)["loss"]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        ema.update(policy)

    n_params = sum(p.numel() for p in policy.parameters())
    return synchronized(step, device), f"{preset}: T={length}, P={m.n_points}, B={batch}, {n_params / 1e6:.1f}M params"


def history_fwd_bwd_fn(length: int, device: str = "cpu"):
    m = load_preset("robotwin").model
    torch.manual_seed(0)
    enc = HistoryEncoder(m).to(device)
    z = torch.randn(1, length, m.d_model, device=device, requires_grad=True)

    def step():
        enc.zero_grad(set_to_none=True)
        enc(z).pow(2).mean().backward()

    return synchronized(step, device), f"G_psi (robotwin: d=512, 2 Mamba layers, N=64), T={length}, fwd+bwd"


def row(label: str, times: list[float]) -> dict:
    return {
        "what": label,
        "median_ms": statistics.median(times),
        "min_ms": min(times),
        "max_ms": max(times),
        "n": len(times),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument(
        "--robotwin-length",
        type=int,
        default=300,
        help="trajectory length for the robotwin step (RoboTwin averages 100-640)",
    )
    p.add_argument("--history-length", type=int, default=600)
    p.add_argument(
        "--device", default="cpu", choices=["cpu", "cuda"], help="where to train (cuda: a GPU machine's step time)"
    )
    p.add_argument(
        "--paper", action="store_true", help="the paper presets' step times and what one task's budget costs"
    )
    p.add_argument("--json", help="also write the figures as JSON here (a new file; --force replaces one)")
    p.add_argument("--force", action="store_true", help="replace an existing --json file")
    args = p.parse_args(argv)
    return run_cli(lambda: _measure(args))


def _measure(args) -> int:
    if args.json:
        check_output_file(args.json, force=args.force, flag="--json")  # before measuring

    if args.device == "cuda" and not torch.cuda.is_available():
        raise DSSPError("--device cuda: CUDA is not available here; measure on a GPU machine or use --device cpu")
    if args.paper:
        return _paper_costs(args)
    rows = []
    for fn, label in (
        train_step_fn("tiny", 40, 2, 2, args.device),
        train_step_fn("robotwin", args.robotwin_length, 14, 14, args.device),
        history_fwd_bwd_fn(args.history_length, args.device),
    ):
        rows.append(row(label, time_calls(fn, args.repeats, warmup=1)))
        print(f"measured: {label}", flush=True)

    return _report(args, rows)


def markdown(report: dict) -> str:
    """The Markdown table of a record this script wrote (``--json``): the plain steps, or ``--paper``'s costs."""
    rows = report["rows"]
    if report.get("paper"):
        lines = ["| preset | step (median ms; min-max) | budget | steps | one task |", "|---|---:|---|---:|---:|"]
        lines += [
            f"| {r['what']} | {r['median_ms']:.1f} ({r['min_ms']:.1f}-{r['max_ms']:.1f}) | {r['epochs']} epochs x "
            f"{r['demos']} demos | {r['steps']:,} | {r['hours']:.1f} h ({r['hours'] / 24:.1f} days) |"
            for r in rows
        ]
    else:
        lines = ["| what | median ms | min ms | max ms | n |", "|---|---:|---:|---:|---:|"]
        lines += [
            f"| {r['what']} | {r['median_ms']:.1f} | {r['min_ms']:.1f} | {r['max_ms']:.1f} | {r['n']} |" for r in rows
        ]
    m = report["machine"]
    where = m.get("gpu") or f"{m.get('cpu')}, {m.get('threads')} threads"
    return (
        "\n".join(lines)
        + f"\n\nMeasured on {where}, torch {m.get('torch')} ({report['repeats']} timed steps per row after one warm-up)."
    )


def _report(args, rows: list[dict], paper: bool = False) -> int:
    """Print the machine and the Markdown table; write ``--json`` (the record :func:`markdown` renders)."""
    from dssp_core import machine

    described = {**machine.describe(), "threads": torch.get_num_threads()}
    if args.device == "cuda":
        described["gpu"] = torch.cuda.get_device_name()
    described["torch"] = torch.__version__
    report = {"machine": described, "device": args.device, "paper": paper, "repeats": args.repeats, "rows": rows}
    print("\n" + markdown(report))
    if args.json:
        write_output_text(args.json, json.dumps(report, indent=2) + "\n", force=args.force, flag="--json")
    return 0


def _paper_costs(args) -> int:
    """The ``--paper`` table: per paper preset, the step's median and one task's budget in steps and hours."""
    rows = []
    for preset, (length, state_dim, action_dim, demos) in PAPER_TASKS.items():
        fn, label = train_step_fn(preset, length, state_dim, action_dim, args.device)
        timing = row(label, time_calls(fn, args.repeats, warmup=1))
        cfg = load_preset(preset)
        steps = resolve_epochs(cfg, demos).train.steps
        rows.append(
            {
                **timing,
                "preset": preset,
                "epochs": cfg.train.epochs,
                "demos": demos,
                "steps": steps,
                "hours": timing["median_ms"] * steps / 3.6e6,
            }
        )
        print(f"measured: {label}", flush=True)
    return _report(args, rows, paper=True)


if __name__ == "__main__":
    sys.exit(main())
