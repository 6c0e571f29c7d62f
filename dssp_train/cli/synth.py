"""``dssp-synth``: write the synthetic "tap count" memory task as a DP3 zarr dataset.

    dssp-synth --out data/tap_count.zarr [--episodes 40] [--seed 0] [--points 64] [--force]

``--out`` must be new or empty; a dataset dssp-synth wrote before (its ``generator`` attribute) is replaced
only with ``--force``, all at once; any other dataset, folder or file there is never touched.
"""

from __future__ import annotations

import argparse
import sys

from dssp_core.cli_runner import ArgumentParser, run_cli
from dssp_core.output_guard import OutputKind, check_output
from dssp_data.attributes import ZARR_ENTRIES, made_by

SYNTH_DATASET = OutputKind(
    "a synthetic dataset",
    "dssp-synth",
    entries=ZARR_ENTRIES,
    marker=False,
    signature=lambda p: made_by(p, ("dssp_train.data.synthetic",)),
)
"""``dssp-synth --out``: a zarr dataset whose ``generator`` attribute is ``dssp_train.data.synthetic``."""


def build_parser() -> argparse.ArgumentParser:
    p = ArgumentParser(prog="dssp-synth", description="Write the synthetic tap-count dataset (DP3 zarr format).")
    p.add_argument("--out", required=True, help="dataset path to write (.zarr directory)")
    p.add_argument("--episodes", type=int, default=40, help="demonstrations to generate (1 to 10000)")
    p.add_argument("--seed", type=int, default=0, help="seed (>= 0)")
    p.add_argument("--points", type=int, default=64, help="points per cloud (24 to 100000)")
    p.add_argument("--force", action="store_true", help="replace a dataset dssp-synth wrote before at --out")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)

    def _main() -> int:
        from dssp_train.data.synthetic import check_tap_count_size  # deferred: loads msgpack, numcodecs, numpy, …

        check_tap_count_size(args.episodes, args.seed, args.points, names=("--episodes", "--seed", "--points"))
        check_output(args.out, force=args.force, kind=SYNTH_DATASET, flag="--out")

        from dssp_data.replay_buffer import ReplayBuffer  # deferred: loads msgpack, numcodecs, numpy, …
        from dssp_train.data.synthetic import write_tap_count_dataset  # deferred: loads msgpack, numcodecs, numpy, …

        path = write_tap_count_dataset(args.out, args.episodes, seed=args.seed, n_points=args.points)
        print(f"wrote {ReplayBuffer.load(path)!r} to {path}")
        return 0

    return run_cli(_main)


if __name__ == "__main__":
    sys.exit(main())
