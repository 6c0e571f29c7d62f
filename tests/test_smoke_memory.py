"""Smoke test of the whole training package: on a task with observation aliasing (the synthetic tap-count
task), the history model beats the reactive baseline trained on the same data with the same budget."""

import pytest
import torch

from dssp_data.replay_buffer import ReplayBuffer
from dssp_train.config import apply_overrides, load_preset
from dssp_train.data.synthetic import DECISION_STEP, chunk_decision, expert_decision, write_tap_count_dataset
from dssp_train.training.checkpoint import load_policy
from dssp_train.training.trainer import Trainer, split_episodes

NOISE_SEEDS = 8


def decision_accuracy(run_dir, data_path) -> float:
    """Share of held-out episodes x noise seeds whose chunk at the aliased step matches the expert."""
    policy, config = load_policy(run_dir)
    data = ReplayBuffer.load(data_path)
    _, val_ids = split_episodes(data.n_episodes, config.train.val_ratio, config.train.seed)
    hits = total = 0
    gen = torch.Generator().manual_seed(0)
    for i in val_ids:
        ep = data.episode(i)
        pc, pos = torch.from_numpy(ep.point_cloud), torch.from_numpy(ep.state)
        starts = torch.full((NOISE_SEEDS,), DECISION_STEP)
        noise = torch.randn(NOISE_SEEDS, config.model.horizon, config.model.action_dim, generator=gen)
        want = expert_decision(ep)
        for chunk in policy.sample_trajectory_windows(pc, pos, starts, noise).numpy():
            hits += chunk_decision(chunk[: config.model.n_action_steps], ep.state[DECISION_STEP]) == want
            total += 1
    return hits / total


@pytest.mark.slow
def test_history_model_beats_reactive_baseline_on_memory_task(tmp_path):
    data = write_tap_count_dataset(tmp_path / "tap_count.zarr", 40, seed=0)
    results = {}
    for name, extra in (("dssp", []), ("reactive", ["model.use_history=false"])):
        config = apply_overrides(load_preset("tiny"), ["train.seed=0", "train.val_ratio=0.2", *extra])
        summary = Trainer(config, data, tmp_path / name, progress=False).run()
        results[name] = dict(summary, decision=decision_accuracy(tmp_path / name, data))
        assert (tmp_path / name / "model.safetensors").is_file() and (tmp_path / name / "loss.png").is_file()
    print(results)
    dssp, reactive = results["dssp"], results["reactive"]
    # Validation losses on held-out episodes: clearly lower with memory.
    assert dssp["val_diffusion"] < 0.5 * reactive["val_diffusion"]
    assert dssp["val_action_mse"] < 0.5 * reactive["val_action_mse"]
    # At the aliased step only memory can tell "tap again" from "park".
    assert dssp["decision"] >= 0.9
    assert reactive["decision"] <= 0.7
