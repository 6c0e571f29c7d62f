"""``dssp-params``: the parameter breakdown of a preset (or of a trained run).

    dssp-params --preset robotwin [--state-dim 14 --action-dim 14] [--set model.d_model=256]
    dssp-params --run RUN_DIR
"""

from __future__ import annotations

import argparse
import sys

from dssp_train.cli.common import run_cli
from dssp_train.config import apply_overrides, load_preset, preset_names


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="dssp-params", description="Parameter breakdown of a DSSP model.")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--preset", help=f"one of {', '.join(preset_names())}")
    src.add_argument("--run", help="a run directory (config.json)")
    p.add_argument("--state-dim", type=int, default=14, help="agent_pos dimension for a preset (default 14, RoboTwin)")
    p.add_argument("--action-dim", type=int, default=14, help="action dimension for a preset (default 14, RoboTwin)")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE")
    args = p.parse_args(argv)

    def _main() -> int:
        from dssp_train.model.param_count import format_breakdown, parameter_breakdown
        from dssp_train.model.policy import DSSPPolicy
        from dssp_train.training.checkpoint import load_config

        if args.run:
            config = apply_overrides(load_config(args.run), args.set)
        else:
            config = load_preset(args.preset)
            config.model.state_dim = config.model.state_dim or args.state_dim
            config.model.action_dim = config.model.action_dim or args.action_dim
            config = apply_overrides(config, args.set)
        m = config.model
        print(
            f"preset {config.preset}: d_model {m.d_model}, d_state {m.d_state}, expand {m.expand}, "
            f"{m.n_history_layers} history + {m.n_denoiser_layers} denoiser layers, S={m.state_dim}, A={m.action_dim}"
        )
        print(format_breakdown(parameter_breakdown(DSSPPolicy(m))))
        return 0

    return run_cli(_main)


if __name__ == "__main__":
    sys.exit(main())
