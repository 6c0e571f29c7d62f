"""DP3's sampling (``train.sampling=windows``): windows drawn from anywhere in the data, the same loss as the
paper's trajectory-wise path on the same windows, refused for a model with history."""

import json

import pytest
import torch
from conftest import SET_SMALL, one_error_line

from dssp_core.errors import ConfigError
from dssp_train.config import apply_overrides, load_preset
from dssp_train.model.policy import DSSPPolicy
from dssp_train.training.trainer import Trainer, TrajectoryTensors

NO_HISTORY = ["model.use_history=false", "model.dynamics_weight=0", "model.state_dim=2", "model.action_dim=2"]
WINDOWS = ["train.sampling=windows", "model.use_history=false", "model.dynamics_weight=0"]


def test_the_window_loss_is_the_trajectory_loss_on_the_same_windows():
    torch.manual_seed(0)
    policy = DSSPPolicy(apply_overrides(load_preset("tiny"), NO_HISTORY).model)
    length, points = 9, policy.cfg.n_points
    cloud, state, action = torch.randn(length, points, 3), torch.randn(length, 2), torch.randn(length, 2)
    policy.fit_normalizers(cloud, state, action)
    starts = torch.tensor([0, 3, 8, 8])  # the first window repeats the first observation, the last the last action
    whole = policy.compute_loss(cloud, state, action, starts, torch.Generator().manual_seed(5))
    obs, act = policy.trajectory_windows(length, starts)
    windows = policy(cloud[obs], state[obs], action[act], torch.Generator().manual_seed(5), windows=True)
    assert windows["loss"].item() == pytest.approx(whole["loss"].item(), rel=1e-6)
    other = policy.compute_loss(cloud, state, action, starts, torch.Generator().manual_seed(6))
    assert windows["loss"].item() != pytest.approx(other["loss"].item())  # the loss depends on the draws


def test_a_model_with_history_cannot_train_on_scattered_windows(data, tmp_path, capsys):
    with pytest.raises(ConfigError, match="model.use_history=false") as err:
        apply_overrides(load_preset("tiny"), ["train.sampling=windows"])
    assert "\n" not in str(err.value)
    assert apply_overrides(load_preset("tiny"), ["train.sampling=windows", *NO_HISTORY]).train.sampling == "windows"
    policy = DSSPPolicy(apply_overrides(load_preset("tiny"), ["model.state_dim=2", "model.action_dim=2"]).model)
    with pytest.raises(ValueError, match="without history"):
        policy(torch.zeros(1, 2, 4, 3), torch.zeros(1, 2, 2), torch.zeros(1, 4, 2), windows=True)
    from dssp_train.cli.train import main as train_main

    argv = ["--data", str(data), "--out", str(tmp_path / "run"), "--steps", "2", "--set", "train.sampling=windows"]
    assert train_main(argv) == 2
    one_error_line(capsys.readouterr().err, "train.sampling=windows", "model.use_history=false")


def test_dssp_train_trains_on_windows_across_the_trajectories(data, tmp_path):
    from dssp_train.cli.train import main as train_main

    argv = ["--data", str(data), "--out", str(tmp_path / "run"), "--steps", "2", "--no-progress", *SET_SMALL]
    assert train_main([*argv, *[a for o in WINDOWS for a in ("--set", o)]]) == 0
    assert json.loads((tmp_path / "run" / "config.json").read_text())["train"]["sampling"] == "windows"


def test_each_window_of_every_trajectory_is_as_likely():
    trainer = Trainer.__new__(Trainer)  # only what _sample_windows reads
    trainer.config = apply_overrides(load_preset("tiny"), [*WINDOWS, "model.state_dim=1", "model.action_dim=1"])
    trainer.policy = DSSPPolicy(trainer.config.model)
    trainer.generator, trainer.device = torch.Generator().manual_seed(0), torch.device("cpu")
    lengths = [10, 30]

    def trajectory(tag: int, n: int) -> TrajectoryTensors:  # every value the trajectory's tag; the step in the state
        steps = torch.arange(n, dtype=torch.float32)[:, None]
        return TrajectoryTensors(torch.full((n, 4, 3), float(tag)), steps, torch.full((n, 1), float(tag)))

    trainer.train_eps = [trajectory(i, n) for i, n in enumerate(lengths)]
    cloud, state, action = trainer._sample_windows(4000)
    m = trainer.config.model
    assert cloud.shape == (4000, m.n_obs_steps, 4, 3) and state.shape == (4000, m.n_obs_steps, 1)
    assert action.shape == (4000, m.horizon, 1)
    windows = [n - m.n_action_steps + 1 for n in lengths]
    tag = cloud[:, 0, 0, 0]
    assert float((tag == 1).float().mean()) == pytest.approx(windows[1] / sum(windows), abs=0.03)
    assert torch.equal(action[:, :, 0], tag[:, None].expand(-1, m.horizon))  # a window never mixes trajectories
    latest = state[:, -1, 0]  # the window's start t: every start 0 ... T - H_a drawn, none past it
    for i, w in enumerate(windows):
        assert sorted(latest[tag == i].unique().tolist()) == list(range(w))


def test_overrides_may_come_in_any_order_and_a_bad_one_is_named():
    either = [apply_overrides(load_preset("tiny"), order) for order in (WINDOWS, WINDOWS[::-1])]
    assert either[0] == either[1] and either[0].train.sampling == "windows"
    with pytest.raises(ConfigError, match=r"^--set model.horizon=2: model.n_action_steps \(H_a\) must be in"):
        apply_overrides(load_preset("tiny"), ["model.use_history=false", "model.horizon=2", "train.lr=0.01"])
