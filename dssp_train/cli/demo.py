"""``dssp-demo``: the embedded default, end to end on a CPU in a few minutes, no hardware.

    dssp-demo [--out runs/demo] [--steps 1500] [--episodes 40] [--seed 0] [--force]

1. writes the synthetic "tap count" memory task (``dssp-synth``) to ``OUT/tap_count.zarr``;
2. trains the ``tiny`` DSSP preset on it (``OUT/dssp``) and, with the same data, budget and seed,
   the reactive baseline without the history encoder (``OUT/reactive``);
3. prints both validation results and the decision at the aliased moment — the step where the
   current observation is the same for one-tap and two-tap episodes and only memory tells
   whether to tap again or park.

``--out`` must be new or empty; a previous ``dssp-demo`` output there is replaced only with ``--force``
(moved aside while the new one runs, deleted when it is complete, put back if it fails); anything else
there is never touched (:mod:`dssp_train.output_guard`).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from dssp_train.cli.common import run_cli
from dssp_train.output_guard import OutputDir, OutputKind

DECISION_SEEDS = 8
DEMO_DIR = OutputKind("a demo directory", "dssp-demo", entries=("tap_count.zarr", "dssp", "reactive", "results.json"))
"""``dssp-demo --out``: the synthetic dataset, both runs, results.json."""


def decision_accuracy(run_dir: Path, data_path: Path) -> float:
    """Share of held-out episodes x noise seeds where the policy's chunk at the aliased step matches the expert."""
    import torch

    from dssp_train.data.replay_buffer import ReplayBuffer
    from dssp_train.data.synthetic import DECISION_STEP, chunk_decision, expert_decision
    from dssp_train.training.checkpoint import load_policy
    from dssp_train.training.trainer import split_episodes

    policy, config = load_policy(run_dir)
    data = ReplayBuffer.load(data_path)
    _, val_ids = split_episodes(data.n_episodes, config.train.val_ratio, config.train.seed)
    hits = total = 0
    gen = torch.Generator().manual_seed(0)
    for i in val_ids:
        ep = data.episode(i)
        pc, pos = torch.from_numpy(ep.point_cloud), torch.from_numpy(ep.state)
        starts = torch.full((DECISION_SEEDS,), DECISION_STEP)
        noise = torch.randn(DECISION_SEEDS, config.model.horizon, config.model.action_dim, generator=gen)
        chunks = policy.sample_trajectory_windows(pc, pos, starts, noise).numpy()
        want = expert_decision(ep)
        for chunk in chunks:
            hits += chunk_decision(chunk[: config.model.n_action_steps], ep.state[DECISION_STEP]) == want
            total += 1
    return hits / max(total, 1)


def run_demo(out: Path, steps: int | None, episodes: int, seed: int, progress: bool = True,
             force: bool = False) -> dict[str, dict[str, float]]:
    """Dataset, two trainings and their evaluation; returns {"dssp": {...}, "reactive": {...}}."""
    with OutputDir(out, DEMO_DIR, force=force, staged=False) as target:
        results = _run_demo(Path(out), steps, episodes, seed, progress)
        target.commit()
    return results


def _run_demo(out: Path, steps: int | None, episodes: int, seed: int, progress: bool) -> dict[str, dict[str, float]]:
    from dssp_train.config import apply_overrides, load_preset
    from dssp_train.data.synthetic import write_tap_count_dataset
    from dssp_train.atomic import atomic_write_text
    from dssp_train.training.trainer import Trainer

    data = write_tap_count_dataset(out / "tap_count.zarr", episodes, seed=seed)
    results = {}
    for name, extra in (("dssp", []), ("reactive", ["model.use_history=false"])):
        budget = [f"train.steps={steps}"] if steps is not None else []
        config = apply_overrides(load_preset("tiny"), [*budget, f"train.seed={seed}", "train.val_ratio=0.2", *extra])
        run_dir = out / name
        if progress:
            print(f"training {name} -> {run_dir}", flush=True)
        summary = Trainer(config, data, run_dir, progress=progress).run()
        results[name] = {
            "val_diffusion": summary["val_diffusion"],
            "val_action_mse": summary["val_action_mse"],
            "decision_accuracy": decision_accuracy(run_dir, data),
        }
    atomic_write_text(out / "results.json", json.dumps(results, indent=2) + "\n")
    return results


def format_results(results: dict[str, dict[str, float]]) -> str:
    lines = [
        "| model | val diffusion loss | val action MSE | decision at the aliased step |",
        "|---|---|---|---|",
    ]
    for name, label in (("dssp", "DSSP (full history)"), ("reactive", "reactive baseline (no history)")):
        r = results[name]
        lines.append(
            f"| {label} | {r['val_diffusion']:.4f} | {r['val_action_mse']:.4f} | {100 * r['decision_accuracy']:.0f} % |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="dssp-demo", description="Synthetic memory task: DSSP against the reactive baseline.")
    p.add_argument("--out", default="runs/demo", help="output directory, new or empty (dataset, two run directories, results.json)")
    p.add_argument("--steps", type=int, help="training steps for each model (default: the tiny preset's 1500)")
    p.add_argument("--episodes", type=int, default=40, help="demonstrations to generate (2 to 10000)")
    p.add_argument("--seed", type=int, default=0, help="seed for the data and both trainings (>= 0)")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--force", action="store_true", help="replace a previous dssp-demo output in --out")
    args = p.parse_args(argv)

    def _main() -> int:
        from dssp_train.cli.train import check_flag
        from dssp_train.data.synthetic import MAX_EPISODES, check_tap_count_size
        from dssp_train.schema import Spec, check_value

        if args.steps is not None:
            check_flag("--steps", "train.steps", args.steps)
        check_value(args.episodes, int, Spec(ge=2, le=MAX_EPISODES), "--episodes")  # 2: one is held out for validation
        check_tap_count_size(args.episodes, args.seed, 64, names=("--episodes", "--seed", "points"))
        results = run_demo(Path(args.out), args.steps, args.episodes, args.seed, progress=not args.no_progress,
                           force=args.force)
        print(format_results(results))
        print(f"results in {Path(args.out) / 'results.json'}; runs in {args.out}/dssp and {args.out}/reactive")
        return 0

    return run_cli(_main)


if __name__ == "__main__":
    sys.exit(main())
