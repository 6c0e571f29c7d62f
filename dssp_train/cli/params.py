"""``dssp-params``: the parameter breakdown of a preset (or of a trained run).

dssp-params --preset robotwin [--state-dim 14 --action-dim 14] [--set model.d_model=256]
dssp-params --run RUN_DIR
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

from dssp_core.cli_runner import ArgumentParser, run_cli
from dssp_core.errors import ConfigError
from dssp_core.schema import MAX_DIM, Spec, check_value
from dssp_train.cli.train import set_fields
from dssp_train.config import apply_overrides, load_preset, preset_names

DEFAULT_DIM = 14  # RoboTwin's two arms


def build_parser() -> argparse.ArgumentParser:
    p = ArgumentParser(prog="dssp-params", description="Parameter breakdown of a DSSP model.")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--preset", help=f"one of {', '.join(preset_names())}")
    src.add_argument("--run", help="a run directory (config.json)")
    p.add_argument("--state-dim", type=int, help=f"agent_pos dimension for a preset (default {DEFAULT_DIM}, RoboTwin)")
    p.add_argument("--action-dim", type=int, help=f"action dimension for a preset (default {DEFAULT_DIM}, RoboTwin)")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)

    def _main() -> int:
        from dssp_train.model.param_count import format_breakdown, parameter_breakdown  # deferred: loads torch, tqdm
        from dssp_train.training.checkpoint import load_config  # deferred: loads safetensors, torch, tqdm

        sets = set_fields(args.set, "preset, dataset and control_rate_hz describe a run and change no parameter")
        dims = {
            "model.state_dim": ("--state-dim", args.state_dim),
            "model.action_dim": ("--action-dim", args.action_dim),
        }
        for key, (flag, value) in dims.items():
            if value is None:
                continue
            if args.run:
                raise ConfigError(f"{flag} is for --preset; a run's dimensions come from its config.json (drop {flag})")
            if key in sets:
                raise ConfigError(f"{flag} and --set {sets[key]} both set {key}; keep one")
            check_value(value, int, Spec(ge=1, le=MAX_DIM), flag)
        if args.run:
            config = apply_overrides(load_config(args.run), args.set)
        else:
            config = load_preset(args.preset)
            config.model.state_dim = args.state_dim or config.model.state_dim or DEFAULT_DIM
            config.model.action_dim = args.action_dim or config.model.action_dim or DEFAULT_DIM
            config = apply_overrides(config, args.set)
        m = config.model
        for key in ("model.state_dim", "model.action_dim"):
            if getattr(m, key.split(".")[1]) < 1:
                raise ConfigError(
                    f"--set {sets.get(key, key)}: counting parameters needs {key} of at least 1 "
                    f"(0 means 'from the dataset', which dssp-params has none of)"
                )
        print(
            f"preset {config.preset}: d_model {m.d_model}, d_state {m.d_state}, expand {m.expand}, "
            f"{m.n_history_layers} history + {m.n_denoiser_layers} denoiser layers ({m.denoiser_backbone}, MLP {m.denoiser_mlp}), "
            f"S={m.state_dim}, A={m.action_dim}"
        )
        print(format_breakdown(parameter_breakdown(meta_policy(m))))
        print(block_variants(m))
        return 0

    return run_cli(_main)


PAPER_PARAMS = 44.3e6  # the paper's reported size (RoboTwin configuration)


def block_variants(model) -> str:
    """The total for each denoiser block composition (model.denoiser_mlp) and mixer (model.denoiser_backbone) at
    this config's sizes, against the paper's 44.3 M; the config's own marked."""

    lines = [
        f"denoiser blocks (model.denoiser_backbone, model.denoiser_mlp): total, vs the paper's {PAPER_PARAMS / 1e6:.1f} M"
    ]
    for backbone in ("mamba", "transformer"):
        for mlp in ("none", "gated", "dit"):
            variant = dataclasses.replace(model, denoiser_backbone=backbone, denoiser_mlp=mlp)
            total = sum(p.numel() for p in meta_policy(variant).parameters())
            mark = "  <- this config" if (backbone, mlp) == (model.denoiser_backbone, model.denoiser_mlp) else ""
            lines.append(
                f"  {backbone:<11} {mlp:<5} {total / 1e6:7.2f} M  {100 * (total / PAPER_PARAMS - 1):+6.1f} %{mark}"
            )
    return "\n".join(lines)


def meta_policy(model):
    """The policy built on the meta device: every parameter's shape, no memory (any width can be counted)."""
    import torch  # deferred: loads torch, tqdm

    from dssp_train.model.policy import DSSPPolicy  # deferred: loads torch, tqdm

    with torch.device("meta"):
        return DSSPPolicy(model)


if __name__ == "__main__":
    sys.exit(main())
