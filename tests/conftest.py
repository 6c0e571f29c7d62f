"""Test-wide settings: one intra-op thread, so results do not depend on the machine's core count
and small tensor ops do not stall when another process shares the cores."""

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

try:
    import torch
except ImportError:  # a deploy-only environment
    torch = None

if torch is not None:
    torch.set_num_threads(1)


import pytest  # noqa: E402


@pytest.fixture(scope="session")
def tiny_export(tmp_path_factory):
    """A briefly trained tiny DSSP run and its exported model directory: (run_dir, model_dir, data_path)."""
    from dssp_train.cli.train import main as train_main
    from dssp_train.data.synthetic import write_tap_count_dataset
    from export.to_onnx import main as export_main

    root = tmp_path_factory.mktemp("tiny_export")
    data = write_tap_count_dataset(root / "tap.zarr", 6, seed=0, n_points=32)
    run_dir, model_dir = root / "run", root / "model"
    assert train_main(["--data", str(data), "--out", str(run_dir), "--preset", "tiny", "--steps", "30",
                       "--set", "train.val_every=30", "--no-progress"]) == 0
    assert export_main([str(run_dir), "-o", str(model_dir), "--skip-verify"]) == 0
    return run_dir, model_dir, data
