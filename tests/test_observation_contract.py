"""The observation contract travels with the model: dataset attributes → run config → ``dssp_model.json`` →
``dssp-run``, which refuses a contradicting setup before anything moves (``--allow-mismatch`` overrides it,
and the override is logged). Data that records no contract (DP3 / RoboTwin files) trains as before and the
manifest says "unknown"."""

import json

import pytest
from conftest import FAST_EXPORT

from dssp_core.errors import ConfigError
from dssp_data.observation import (
    FRAME_ROBOT_BASE,
    UNKNOWN,
    ObservationContract,
    PointCloudConfig,
    check_contract,
    contract_mismatches,
    piper_layout,
)

# A crop the simulation does not use by default (its own: (0.05, -0.35, 0.005) .. (0.60, 0.35, 0.10)).
CROP = {
    "n_points": 48,
    "depth_near": 0.1,
    "depth_far": 2.0,
    "crop_min": [0.05, -0.3, 0.005],
    "crop_max": [0.55, 0.3, 0.12],
    "voxel_size": 0.01,
}


@pytest.fixture(scope="module")
def recorded_model(tmp_path_factory):
    """A simulated recording with a non-default crop, trained briefly and exported: (model_dir, run_dir)."""
    from dssp_sim.teleop import record_main
    from dssp_train.cli.train import main as train_main
    from export.to_onnx import main as export_main

    root = tmp_path_factory.mktemp("contract")
    crop = root / "crop.json"
    crop.write_text(json.dumps(CROP))
    data, run_dir, model_dir = root / "rec.zarr", root / "run", root / "model"
    assert (
        record_main(
            [
                "--out",
                str(data),
                "--pointcloud",
                str(crop),
                "--auto",
                "--episodes",
                "2",
                "--max-steps",
                "12",
                "--no-depth",
                "--quiet",
            ]
        )
        == 0
    )
    assert (
        train_main(
            [
                "--data",
                str(data),
                "--out",
                str(run_dir),
                "--preset",
                "tiny",
                "--steps",
                "2",
                "--set",
                "train.val_every=2",
                "--no-progress",
            ]
        )
        == 0
    )
    assert export_main([str(run_dir), "-o", str(model_dir), *FAST_EXPORT]) == 0
    return model_dir, run_dir


def test_the_contract_goes_from_the_dataset_into_the_run_and_the_manifest(recorded_model):
    model_dir, run_dir = recorded_model
    config = json.loads((run_dir / "config.json").read_text())
    manifest = json.loads((model_dir / "dssp_model.json").read_text())
    for observation in (config["observation"], manifest["contract"]["observation"]):
        assert observation["pointcloud"]["crop_min"] == CROP["crop_min"]
        assert observation["pointcloud"]["crop_max"] == CROP["crop_max"]
        assert observation["pointcloud"]["n_points"] == 48
        assert observation["state"] == observation["action"] == piper_layout(1).to_dict()
    assert manifest["contract"]["control_rate_hz"] == 10.0


def run(model_dir, log_dir, *extra):
    from hardware.cli.run import main as run_main

    return run_main(
        [
            "--model",
            str(model_dir),
            "--camera",
            "tabletop",
            "--can",
            "sim",
            "--max-steps",
            "3",
            "--log-dir",
            str(log_dir),
            "--threads",
            "1",
            "--quiet",
            "--no-can-log",
            *extra,
        ]
    )


def test_dssp_run_refuses_another_crop_before_motion_and_runs_with_the_models_own(
    recorded_model, tmp_path, capsys, monkeypatch
):
    from hardware.piper import piper_robot

    model_dir, _ = recorded_model
    other = tmp_path / "other.json"
    other.write_text(json.dumps({**CROP, "crop_max": [0.8, 0.4, 0.5]}))
    opened = []
    real_open = piper_robot.PiperRobot.__enter__
    monkeypatch.setattr(piper_robot.PiperRobot, "__enter__", lambda self: opened.append(self) or real_open(self))

    code = run(model_dir, tmp_path / "refused", "--pointcloud", str(other))
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert err[0].startswith("error: --pointcloud ") and "pointcloud.crop_max = [0.8, 0.4, 0.5]" in err[0]
    assert "[0.55, 0.3, 0.12]" in err[0] and "--allow-mismatch pointcloud.crop_max" in err[0]
    assert opened == [] and not (tmp_path / "refused").exists()  # no arm connected, nothing logged

    assert run(model_dir, tmp_path / "own") == 0  # the model's own settings: no flag needed
    settings = json.loads((tmp_path / "own" / "run.json").read_text())["settings"]
    assert settings["pointcloud"]["crop_max"] == CROP["crop_max"] and settings["allowed_mismatches"] == []
    assert opened, "the run connected the arm"
    capsys.readouterr()

    assert (
        run(model_dir, tmp_path / "allowed", "--pointcloud", str(other), "--allow-mismatch", "pointcloud.crop_max") == 0
    )
    assert "warning: running with pointcloud.crop_max" in capsys.readouterr().err
    settings = json.loads((tmp_path / "allowed" / "run.json").read_text())["settings"]
    assert settings["allowed_mismatches"] == [
        {"field": "pointcloud.crop_max", "trained": CROP["crop_max"], "given": [0.8, 0.4, 0.5]}
    ]


def test_dssp_run_refuses_another_rate_and_another_number_of_arms(recorded_model, tmp_path, capsys):
    model_dir, _ = recorded_model
    assert run(model_dir, tmp_path / "a", "--control-rate", "20") == 2
    line = capsys.readouterr().err.strip()
    assert (
        "control_rate_hz = 20 but the model" in line and "has 10" in line and "--allow-mismatch control_rate_hz" in line
    )
    assert run(model_dir, tmp_path / "b", "--allow-mismatch", "crop") == 2
    assert "--allow-mismatch crop: not a field" in capsys.readouterr().err


def test_data_without_a_contract_trains_and_the_manifest_says_unknown(tiny_export):
    run_dir, model_dir, _ = tiny_export
    assert json.loads((run_dir / "config.json").read_text())["observation"] == {
        "pointcloud": None,
        "frame": None,
        "state": None,
        "action": None,
    }
    assert set(json.loads((model_dir / "dssp_model.json").read_text())["contract"]["observation"].values()) == {UNKNOWN}


def test_contract_checks_compare_only_what_both_sides_know():
    trained = ObservationContract(pointcloud=PointCloudConfig(voxel_size=0.02), state=piper_layout(1))
    assert contract_mismatches(trained, ObservationContract()) == []
    given = ObservationContract(pointcloud=PointCloudConfig(), state=piper_layout(2), action=piper_layout(2))
    assert [m[0] for m in contract_mismatches(trained, given)] == ["pointcloud.voxel_size", "state.arms"]
    with pytest.raises(ConfigError, match=r"^--can can0,can1 gives state.arms = 2 but the model m has 1"):
        check_contract(
            trained,
            given,
            trained_by="the model m",
            allow=["pointcloud.voxel_size"],
            given_by={"pointcloud": "--pointcloud p.json", "state": "--can can0,can1"},
        )


def test_dssp_record_refuses_appending_with_other_settings(tmp_path, capsys):
    from dssp_sim.teleop import record_main

    crop, other = tmp_path / "crop.json", tmp_path / "other.json"
    crop.write_text(json.dumps(CROP))
    other.write_text(json.dumps({**CROP, "voxel_size": 0.02}))
    out = tmp_path / "rec.zarr"
    args = ["--out", str(out), "--auto", "--episodes", "1", "--max-steps", "5", "--no-depth", "--quiet"]
    assert record_main([*args, "--pointcloud", str(crop)]) == 0
    capsys.readouterr()
    assert record_main([*args, "--pointcloud", str(other)]) == 2
    line = capsys.readouterr().err.strip()
    assert "pointcloud.voxel_size = 0.02" in line and "has 0.01" in line and "new dataset" in line


def test_a_dataset_names_its_clouds_frame_when_it_is_not_the_robots_base():
    base = ObservationContract(pointcloud=PointCloudConfig(), frame=FRAME_ROBOT_BASE, state=piper_layout(1))
    assert "pointcloud_frame" not in base.attrs()
    assert ObservationContract.from_attrs(base.attrs(), "d.zarr").frame == FRAME_ROBOT_BASE
    other = ObservationContract(pointcloud=PointCloudConfig(), frame="camera: DP3's frame", state=piper_layout(1))
    assert other.attrs()["pointcloud_frame"] == "camera: DP3's frame"
    assert ObservationContract.from_attrs(other.attrs(), "d.zarr") == other
    with pytest.raises(ConfigError, match=r"^d.zarr's pointcloud_frame attribute must be a non-empty string, got 3"):
        ObservationContract.from_attrs({**other.attrs(), "pointcloud_frame": 3}, "d.zarr")
