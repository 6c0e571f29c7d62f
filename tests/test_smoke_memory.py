"""Smoke test of the whole training package: on a task with observation aliasing, the history model
beats the reactive baseline trained on the same data with the same budget (what ``dssp-demo`` runs)."""

import json

from dssp_train.cli.demo import format_results, run_demo


def test_history_model_beats_reactive_baseline_on_memory_task(tmp_path):
    results = run_demo(tmp_path, steps=None, episodes=40, seed=0, progress=False)
    print(format_results(results))
    dssp, reactive = results["dssp"], results["reactive"]
    # Validation losses on held-out episodes: clearly lower with memory.
    assert dssp["val_diffusion"] < 0.5 * reactive["val_diffusion"]
    assert dssp["val_action_mse"] < 0.5 * reactive["val_action_mse"]
    # At the aliased step only memory can tell "tap again" from "park".
    assert dssp["decision_accuracy"] >= 0.9
    assert reactive["decision_accuracy"] <= 0.7
    assert json.loads((tmp_path / "results.json").read_text()) == results
    for name in ("dssp", "reactive"):
        run = tmp_path / name
        assert (run / "model.safetensors").is_file() and (run / "loss.png").is_file()
    assert json.loads((tmp_path / "reactive" / "config.json").read_text())["model"]["use_history"] is False
