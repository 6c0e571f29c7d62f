"""``dssp-train``: train DSSP (or an ablation) on a DP3/RoboTwin zarr dataset.

    dssp-train --data PATH.zarr --preset robotwin --out runs/x [--steps N] [--seed S] [--device cpu|cuda]
    dssp-train --data PATH.zarr --out runs/x --resume            # continue where the run stopped
    torchrun --nproc_per_node 2 -m dssp_train.cli.train ...       # data-parallel (gloo on CPU, NCCL on GPU)
"""

from __future__ import annotations

import argparse
import json
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
        import torch

        from dssp_train.training.trainer import Trainer

        out = Path(args.out)
        if not args.resume and (out / "config.json").exists():
            raise DSSPError(f"{out} already holds a run; continue it with --resume or choose another --out")
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
        if trainer.is_main:
            print(json.dumps(summary, indent=2))
        return 0

    return run_cli(_main)


if __name__ == "__main__":
    sys.exit(main())
