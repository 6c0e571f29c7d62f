"""More bad input at the door: JSON that parses only with surprises, flags that argparse rejects, recordings
and model directories that do not fit — one line, exit 2, nothing opened or written."""

from __future__ import annotations

import json
import os
import shutil
import subprocess

import pytest
from conftest import refusal

from dssp_core.errors import ConfigError
from dssp_core.schema import read_json_object


@pytest.mark.parametrize(
    "text, words",
    [
        ('{"max_joint_step": 0.05, "max_joint_step": 5}', "gives the key max_joint_step twice"),
        ("[" * 100_000 + "]" * 100_000, "nested more than 64 levels deep"),
        ('{"a": ' + "1" * 5000 + "}", "not a usable JSON object"),
        ("\xff\xfe garbage", "not a text file"),
    ],
)
def test_json_that_parses_only_with_surprises_is_refused(tmp_path, text, words):
    path = tmp_path / "s.json"
    path.write_bytes(text.encode("latin-1"))
    with pytest.raises(ConfigError) as info:
        read_json_object(path, "safety")
    assert words in str(info.value) and "\n" not in str(info.value)


def test_a_huge_integer_in_a_number_field(tmp_path, capsys):
    from hardware.cli.run import main as run_main

    path = tmp_path / "safety.json"
    path.write_text('{"max_joint_step": ' + "1" * 400 + "}")
    code = run_main(["--model", str(tmp_path / "m"), "--safety", str(path), "--quiet"])
    line = refusal((code, *capsys.readouterr()))
    assert "safety.max_joint_step must be a finite number" in line


@pytest.mark.parametrize(
    "argv",
    [
        ["dssp-run", "--model", "m", "--control-rate", "abc"],
        ["dssp-sim", "collect", "--task", "tap", "--episodes", "1", "--out", "x.zarr", "--seed", "-1"],
        ["dssp-sim", "eval", "--model", "m", "--task", "tap", "--seed", "-1"],
        ["dssp-record", "--out", "x.zarr", "--max-steps", "x"],
    ],
)
def test_argparse_errors_are_one_line(tmp_path, argv):
    exe = shutil.which(argv[0])
    assert exe is not None, f"{argv[0]} is not installed"
    done = subprocess.run(
        [exe, *argv[1:]],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: "), done.stderr
    assert "--help" in lines[0]
    assert list(tmp_path.iterdir()) == []


def test_sim_eval_refuses_a_non_finite_noise(tmp_path, capsys):
    from dssp_sim.sim_cli import main as sim_main

    code = sim_main(["eval", "--model", str(tmp_path / "m"), "--task", "tap", "--noise", "nan", "--no-progress"])
    assert "--noise must be a number in [0, 10]" in refusal((code, *capsys.readouterr()))


def test_dssp_run_names_a_missing_recording(tmp_path, capsys):
    from hardware.cli.run import main as run_main

    code = run_main(["--model", str(tmp_path / "m"), "--camera", f"file:{tmp_path / 'none.bag'}", "--quiet"])
    line = refusal((code, *capsys.readouterr()))
    assert "none.bag does not exist" in line


def test_dssp_record_will_not_write_into_another_recording_s_can_logs(tmp_path, capsys):
    from dssp_sim.teleop import record_main

    logs = tmp_path / "rec.zarr.can"
    logs.mkdir()
    (logs / "episode_000000.sim.blf").write_text("another recording")
    code = record_main(["--out", str(tmp_path / "rec.zarr"), "--quiet", "--auto", "--episodes", "1"])
    assert "holds CAN logs of a dataset that is not there" in refusal((code, *capsys.readouterr()))
    assert (logs / "episode_000000.sim.blf").read_text() == "another recording"
    assert not (tmp_path / "rec.zarr").exists()


def test_collect_appends_from_the_seed_after_the_last_one(tmp_path):
    import numpy as np

    from dssp_core.errors import OutputError
    from dssp_data.dataset_layout import Episode
    from dssp_data.replay_buffer_writer import write_replay_buffer
    from dssp_sim.collect import first_seed

    assert first_seed(tmp_path / "new.zarr", None) == 0
    assert first_seed(tmp_path / "new.zarr", 7) == 7
    episode = Episode(
        point_cloud=np.zeros((2, 4, 3), np.float32),
        state=np.zeros((2, 7), np.float32),
        action=np.zeros((2, 7), np.float32),
    )
    write_replay_buffer(tmp_path / "a.zarr", [episode], attrs={"generator": "dssp_sim.collect", "next_seed": 12})
    assert first_seed(tmp_path / "a.zarr", None) == 12
    write_replay_buffer(tmp_path / "b.zarr", [episode], attrs={"generator": "dssp_sim.collect"})
    with pytest.raises(OutputError, match="give --seed"):
        first_seed(tmp_path / "b.zarr", None)


def test_a_reader_that_goes_away_is_not_a_traceback(tmp_path):
    """``dssp-data info DATA | head -1``: the pipe closes early; the command stops quietly."""
    from conftest import write_arm_dataset

    data = write_arm_dataset(tmp_path / "d.zarr", n_episodes=40, steps=5, n_points=8)
    exe = shutil.which("dssp-data")
    done = subprocess.run(
        f"'{exe}' info '{data}' | head -1",
        shell=True,
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    assert "Traceback" not in done.stderr and "BrokenPipe" not in done.stderr, done.stderr
    assert len(done.stdout.splitlines()) == 1


# ------------------------------------------------------------------------------ model directories
def _edited_copy(model_dir, tmp_path, edit):
    copy = tmp_path / "model"
    shutil.copytree(model_dir, copy)
    manifest = json.loads((copy / "dssp_model.json").read_text())
    edit(manifest)
    (copy / "dssp_model.json").write_text(json.dumps(manifest))
    return copy


@pytest.mark.parametrize(
    "edit, words",
    [
        (
            lambda m: m["contract"].update(ddim_timesteps=sorted(m["contract"]["ddim_timesteps"])),
            "must decrease strictly",
        ),
        (
            lambda m: m["contract"].update(n_action_steps=m["contract"]["horizon"] + 1),
            "n_action_steps (H_a) must be in [1, horizon",
        ),
        (lambda m: m["contract"].update(ddim_timesteps=[5000] + m["contract"]["ddim_timesteps"][1:]), "ddim_timesteps"),
    ],
)
def test_a_manifest_that_contradicts_itself(arm_export, tmp_path, edit, words):
    from dssp_core.errors import DSSPError
    from dssp_deploy.manifest import read_manifest

    with pytest.raises(DSSPError) as info:
        read_manifest(_edited_copy(arm_export, tmp_path, edit))
    assert words in str(info.value)
