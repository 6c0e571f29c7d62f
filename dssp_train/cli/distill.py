"""``dssp-distill``: a few-step student of a trained DSSP run (K = 1 or 2 denoising steps per chunk).

    dssp-distill --teacher runs/tap --steps 1 --out runs/tap_k1 [--method consistency|trajectory] [--data PATH.zarr]
                 [--train-steps N] [--teacher-steps M] [--fine-tune-encoders] [--batch-size B] [--lr LR] [--seed S]
                 [--log tensorboard|wandb|none]
    dssp-distill --out runs/tap_k1 --resume              # continue where it stopped (dssp-train --resume works too)

The student starts as the teacher (weights, normalisers, observation settings) and samples in ``--steps`` DDIM
steps at trailing timesteps; ``--method`` picks its objective (:mod:`dssp_train.training.distillation`). Its run
directory is an ordinary run — ``python -m export.to_onnx`` writes its K into the manifest and the runtime
runs it unchanged. Data: the teacher's dataset unless ``--data`` names another with the same dimensions.
Budget: ``--train-steps`` (default a third of the teacher's steps, at least 100); learning rate and windows per
step: the teacher's unless given. Output, ``--force``, ``--resume``, ``--log`` and Ctrl-C behave as in ``dssp-train``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from dssp_core.cli_runner import ArgumentParser
from dssp_core.errors import ConfigError, DSSPError
from dssp_train.cli.train import add_log_flag, given_flags, run_training, with_flags
from dssp_train.config import DISTILL_METHODS, RunConfig

# dssp-train's config flags a student does not take (its architecture is the teacher's).
TRAIN_ONLY = (
    "epochs",
    "val_ratio",
    "history_backbone",
    "history_window",
    "denoiser_backbone",
    "no_holdout",
    "no_history",
    "no_timestep_decoupling",
    "no_recent_states",
    "no_dynamics_loss",
    "preset",
    "control_rate",
)


def build_parser() -> argparse.ArgumentParser:
    p = ArgumentParser(prog="dssp-distill", description=__doc__.split("\n\n")[0].strip("`"))
    p.add_argument("--teacher", help="the trained run directory to distil (dssp-train's --out)")
    p.add_argument(
        "--steps",
        type=int,
        dest="denoise_steps",
        help="the student's denoising steps per chunk (K; 1 or 2 is what distillation is for)",
    )
    p.add_argument("--out", required=True, help="the student's run directory (or the one to continue with --resume)")
    p.add_argument("--method", choices=DISTILL_METHODS, help="trajectory (default) or consistency")
    p.add_argument("--data", help="dataset (default: the teacher's)")
    p.add_argument(
        "--train-steps",
        type=int,
        dest="steps",
        help="optimisation steps (default: a third of the teacher's, at least 100; with --resume: the new total)",
    )
    p.add_argument(
        "--teacher-steps",
        type=int,
        help="the teacher's DDIM steps whose trajectories are distilled (default: the teacher's own K)",
    )
    p.add_argument(
        "--fine-tune-encoders",
        action="store_true",
        help="train the observation and history encoders too (default: frozen, only the denoiser trains)",
    )
    p.add_argument("--batch-size", type=int, help="windows per step (default: the teacher's)")
    p.add_argument("--lr", type=float, help="peak learning rate (default: the teacher's)")
    p.add_argument(
        "--seed",
        type=int,
        help="seed for windows, noise and timesteps (default: the teacher's, and its validation split)",
    )
    p.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"], help="default: cuda when available")
    p.add_argument("--resume", action="store_true", help="continue the student in --out from its last checkpoint")
    p.add_argument("--force", action="store_true", help="replace a previous run in --out (once the new one completes)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_log_flag(p)
    return p


def teacher_dataset(teacher: Path, config: RunConfig) -> str:
    """The dataset the teacher trained on: the resolved path its checkpoint records, else its config's."""
    from dssp_train.training.checkpoint import read_trainer_state  # deferred: loads safetensors, torch, tqdm

    state = read_trainer_state(teacher) or {}
    recorded = state.get("dataset") if isinstance(state.get("dataset"), dict) else {}
    path = recorded.get("path") or config.dataset
    if not path:
        raise DSSPError(f"{teacher} does not record its dataset; pass --data")
    return str(path)


def student_config(args, run_config: RunConfig | None) -> RunConfig:
    """The student's config: the teacher's, sampling in --steps trailing DDIM steps, with the distillation section
    and the budget; on --resume the run's own (only --train-steps may change)."""
    if args.resume:
        given = [
            f"--{name.replace('_', '-')}"
            for name in ("teacher", "denoise_steps", "method", "data", "teacher_steps")
            if getattr(args, name) is not None
        ] + (["--fine-tune-encoders"] if args.fine_tune_encoders else [])
        given += [typed.split()[0] for typed, key, _ in given_flags(args) if key != "train.steps"]
        if given:
            raise DSSPError(
                f"--resume keeps the student's config; only --train-steps may change (got {', '.join(given)})"
            )
        if not run_config.distill.teacher:
            raise DSSPError(
                f"{args.out} holds an ordinary run, not a distilled student; continue it with dssp-train --resume"
            )
        if args.data is None:
            args.data = run_config.dataset
        config = run_config.to_dict()
        if args.steps is not None:
            config["train"]["steps"] = args.steps
        return RunConfig.from_dict(config)
    from dssp_train.training.checkpoint import load_config  # deferred: loads safetensors, torch, tqdm

    if args.teacher is None or args.denoise_steps is None:
        raise DSSPError(
            "dssp-distill needs --teacher RUN_DIR and --steps K (the student's denoising steps), or --resume"
        )
    teacher = Path(args.teacher)
    teacher_config = load_config(teacher)
    if teacher_config.distill.teacher:
        raise DSSPError(
            f"{teacher} is itself a distilled student; distil its teacher {teacher_config.distill.teacher} instead"
        )
    if args.data is None:
        args.data = teacher_dataset(teacher, teacher_config)
    data = teacher_config.to_dict()
    k_teacher = teacher_config.model.diffusion.num_inference_steps
    data["model"]["diffusion"].update(num_inference_steps=args.denoise_steps, timestep_spacing="trailing")
    steps = args.steps if args.steps is not None else max(100, teacher_config.train.steps // 3)
    data["train"].update(steps=steps, epochs=0, warmup_steps=min(teacher_config.train.warmup_steps, steps // 10))
    data["distill"] = {
        "teacher": str(teacher.resolve()),
        "method": args.method or "trajectory",
        "teacher_steps": args.teacher_steps or k_teacher,
        "freeze_encoders": not args.fine_tune_encoders,
    }
    data["dataset"] = None
    config = with_flags(
        RunConfig.from_dict(data), given_flags(args)
    )  # a bad --steps or --teacher-steps names its field
    if config.model.diffusion.num_inference_steps >= config.distill.teacher_steps:
        raise ConfigError(
            f"--steps {config.model.diffusion.num_inference_steps} is not fewer than the teacher's "
            f"{config.distill.teacher_steps}: a student samples in fewer steps than its teacher"
        )
    return config


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    for name in TRAIN_ONLY:
        setattr(
            args,
            name,
            None
            if name
            not in ("no_holdout", "no_history", "no_timestep_decoupling", "no_recent_states", "no_dynamics_loss")
            else False,
        )
    args.set = []
    args.steps_flag = "--train-steps"
    return run_training(args, student_config)


if __name__ == "__main__":
    sys.exit(main())
