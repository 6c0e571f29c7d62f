"""``dssp-train``: train DSSP (or an ablation) on a DP3/RoboTwin zarr dataset.

    dssp-train --data PATH.zarr --preset robotwin --out runs/x [--steps N] [--seed S] [--device cpu|cuda]
    dssp-train --data PATH.zarr --out runs/x --resume            # continue where the run stopped
    torchrun --nproc_per_node 2 -m dssp_train.cli.train ...       # data-parallel (gloo on CPU, NCCL on GPU)

A new run goes into a new or empty --out. A previous run there is refused (continue it with --resume) or,
with --force, replaced: it is moved aside while the new run trains, deleted when the new run completes,
and put back if the new run fails or is interrupted. A folder holding anything but a run is never touched
(:mod:`dssp_train.output_guard`).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
from pathlib import Path

from dssp_train.cli.common import run_cli
from dssp_train.config import apply_overrides, load_preset, preset_names
from dssp_train.errors import DSSPError


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dssp-train", description=__doc__.split("\n\n")[0].strip("`"))
    p.add_argument("--data", required=True, help="DP3/RoboTwin zarr dataset (data/point_cloud, data/state, data/action, meta/episode_ends)")
    p.add_argument("--preset", default=None, help=f"model and training preset: {', '.join(preset_names())} (default tiny)")
    p.add_argument("--out", required=True, help="run directory to create (or to continue with --resume)")
    p.add_argument("--steps", type=int, help="total optimisation steps (with --resume: the new total)")
    p.add_argument("--seed", type=int, help="seed for initialisation, episode split and sampling")
    p.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"], help="default: cuda when available")
    p.add_argument("--batch-size", type=int, help="action windows sampled from each trajectory per step")
    p.add_argument("--lr", type=float, help="peak learning rate")
    p.add_argument("--val-ratio", type=float, help="fraction of episodes held out for validation")
    p.add_argument("--control-rate", type=float, help="control rate of the data in Hz, when the dataset does not record it")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    p.add_argument("--force", action="store_true", help="replace a previous run in --out (once the new one completes)")
    ablations = p.add_argument_group("ablations (paper Tables 3 and 5)")
    ablations.add_argument("--no-history", action="store_true", help="no history encoder: the reactive, DP3-like baseline")
    ablations.add_argument("--no-timestep-decoupling", action="store_true", help="AdaLN modulates the prefix tokens too")
    ablations.add_argument("--no-recent-states", action="store_true", help="prefix is [c_t] only")
    ablations.add_argument("--no-dynamics-loss", action="store_true", help="lambda = 0")
    ablations.add_argument("--history-backbone", choices=["mamba", "transformer"], help="history encoder backbone")
    ablations.add_argument("--history-window", type=int, help="encode only the last T_h observations (0 = full history)")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE", help="any other config field, e.g. model.d_model=256")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def config_from_args(args):
    from dssp_train.training.checkpoint import load_config

    if args.resume:
        if args.preset:
            raise DSSPError("--resume continues the run with its own config; drop --preset")
        config = load_config(Path(args.out))
    else:
        config = load_preset(args.preset or "tiny")
    overrides = list(args.set)
    flags = {
        "train.steps": args.steps,
        "train.seed": args.seed,
        "train.batch_size": args.batch_size,
        "train.lr": args.lr,
        "train.val_ratio": args.val_ratio,
        "model.history_backbone": args.history_backbone,
        "model.history_window": args.history_window,
    }
    overrides += [f"{k}={json.dumps(v)}" for k, v in flags.items() if v is not None]
    for flag, key, value in (
        (args.no_history, "model.use_history", False),
        (args.no_timestep_decoupling, "model.timestep_decoupled", False),
        (args.no_recent_states, "model.use_recent_states", False),
        (args.no_dynamics_loss, "model.dynamics_weight", 0.0),
    ):
        if flag:
            overrides.append(f"{key}={json.dumps(value)}")
    if args.resume:
        changed = [o for o in overrides if not o.startswith("train.steps=")]
        if changed:
            raise DSSPError(f"--resume keeps the run's config; only --steps may change (got {', '.join(changed)})")
    return apply_overrides(config, overrides)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)

    def _main() -> int:
        from dssp_train.output_guard import RUN_DIR, OutputDir, OutputError, check_output

        out = Path(args.out)
        if args.resume and args.force:
            raise DSSPError("--resume continues the run in --out; drop --force")
        is_main = int(os.environ.get("RANK", "0")) == 0
        with contextlib.ExitStack() as stack:
            target = None
            if not args.resume:
                try:  # before anything else: a run that may not be replaced stops here
                    if is_main:
                        target = stack.enter_context(OutputDir(out, RUN_DIR, force=args.force, staged=False, keep_partial=True))
                    else:  # rank 0 moves a replaced run aside and creates --out
                        check_output(out, force=args.force, kind=RUN_DIR)
                except OutputError:
                    if RUN_DIR.owns(out):
                        raise OutputError(f"{out} already holds a run; continue it with --resume, pass --force to replace it "
                                          "or choose another --out") from None
                    raise
            summary = _train(args, out)
            if target is not None:
                target.commit()
        if summary is not None:
            print(json.dumps(summary, indent=2))
        return 0

    return run_cli(_main)


def _train(args, out: Path) -> dict | None:
    """Train into ``out``; the summary on the main process, None on the others."""
    import torch

    from dssp_train.training.trainer import Trainer

    if not Path(args.data).exists():
        raise DSSPError(f"dataset {args.data} does not exist; pass a DP3/RoboTwin .zarr directory (dssp-synth makes one)")
    config = config_from_args(args)
    device = args.device if args.device != "auto" else ("cuda" if torch.cuda.is_available() else "cpu")
    trainer = Trainer(
        config, args.data, out, device=device, resume=args.resume, progress=not args.no_progress, control_rate_hz=args.control_rate
    )
    if trainer.is_main and trainer.config.control_rate_hz is None:
        print(f"warning: {args.data} does not record its control rate; pass --control-rate HZ so the runtime can match it", file=sys.stderr)
    summary = trainer.run()
    return summary if trainer.is_main else None


if __name__ == "__main__":
    sys.exit(main())
