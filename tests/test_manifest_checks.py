"""``dssp_model.json`` is checked, not trusted, and non-finite observations never reach the history.

Every manifest field the runtime uses, set to a wrong type, an out-of-range or an inconsistent value, is
refused at load with one line naming it (a property test per field, on a copy of one exported model);
``dssp-run`` exits 2 on such a model before any arm is opened or enabled; a graph file from another export
and file names that leave the model directory are refused; NaN/inf observations are refused before any
graph runs, the state unchanged, and the control loop holds on them.
"""

import copy
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
from conftest import assert_policy_state_kept, one_line_message, policy_state, rig_loop
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dssp_core.errors import NonFiniteObservation
from dssp_deploy import OnnxPolicy
from dssp_deploy.control_loop import ChunkedControl
from dssp_deploy.manifest import MANIFEST_NAME, ModelDirError

EXAMPLES = 6  # per field: ~50 fields, each example rewrites the manifest of one copied model directory
FAST = settings(
    max_examples=EXAMPLES,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
DELETE = object()  # the key is removed
NAN, INF = float("nan"), float("inf")


# ------------------------------------------------------------------------------------ helpers
@pytest.fixture(scope="module")
def model(arm_export):
    """(model directory, its manifest as written by the exporter) — one simulated Piper: S = A = 7."""
    return arm_export, json.loads((arm_export / MANIFEST_NAME).read_text())


@pytest.fixture(scope="module")
def scratch(arm_export, tmp_path_factory):
    """A copy of the model directory whose manifest the property tests rewrite."""
    dst = tmp_path_factory.mktemp("scratch") / "model"
    shutil.copytree(arm_export, dst)
    return dst


def get(manifest, path):
    node = manifest
    for key in path:
        node = node[key]
    return node


def with_value(manifest, path, value):
    changed = copy.deepcopy(manifest)
    node = get(changed, path[:-1])
    if value is DELETE:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return changed


def write(model_dir, manifest):
    (model_dir / MANIFEST_NAME).write_text(json.dumps(manifest))


def refused(model_dir, manifest, token: str) -> str:
    """Write ``manifest`` into ``model_dir``; loading must raise one ModelDirError line that contains ``token``."""
    write(model_dir, manifest)
    with pytest.raises(ModelDirError) as info:
        OnnxPolicy(model_dir, threads=1, warmup=0)
    return one_line_message(info, token)


def copy_model(model_dir, dst, manifest=None):
    shutil.copytree(model_dir, dst)
    if manifest is not None:
        write(dst, manifest)
    return dst


# ---------------------------------------------------------------------- bad values, per field
NOT_INT = st.sampled_from(["7", 7.5, True, None, [7], {"v": 7}])
NOT_BOOL = st.sampled_from(["true", "false", 1, 0, None])


def outside(lo, hi):
    return st.integers(-(10**6), lo - 1) | st.integers(hi + 1, hi + 10**6)


def count(hi, lo=1, checked_against_graphs=True):
    """Not an integer, out of [lo, hi], missing, or — when the graphs or other facts pin it — another value in
    range (the test's filter drops the true one)."""
    bad = NOT_INT | outside(lo, hi) | st.just(DELETE)
    return lambda orig, m: (bad | st.integers(lo, min(hi, 64))) if checked_against_graphs else bad


def shape_dim(orig, m):
    return st.integers(1, 300) | st.sampled_from([3.5, None, True, "H", -1])


FIELDS = [
    # the contract
    (("contract", "point_dim"), "point_dim", lambda o, m: NOT_INT | st.integers(-5, 10) | st.just(DELETE)),
    (("contract", "state_dim"), "state_dim", count(4096)),
    (("contract", "action_dim"), "action_dim", count(4096)),
    (("contract", "n_obs_steps"), "n_obs_steps", count(4096)),
    (("contract", "horizon"), "horizon", count(4096)),
    (
        ("contract", "n_action_steps"),
        "n_action_steps",
        lambda o, m: (
            NOT_INT | st.integers(-5, 0) | st.integers(m["contract"]["horizon"] + 1, m["contract"]["horizon"] + 50)
        ),
    ),
    (
        ("contract", "ddim_timesteps"),
        "ddim_timesteps",
        lambda o, m: (
            st.sampled_from(["90", 5, None, {}, [], DELETE])
            | st.lists(st.integers(0, 99), min_size=2, max_size=20).filter(
                lambda v: any(a <= b for a, b in zip(v, v[1:]))
            )
            | st.sampled_from([[-1] + o[1:], [2.5] + o[1:], [True] + o[1:], [10**6] + o[1:]])
        ),
    ),
    (
        ("contract", "control_rate_hz"),
        "control_rate_hz",
        lambda o, m: (
            st.sampled_from(["50", True, [], {}, NAN, INF, -INF, DELETE])
            | st.floats(-1e6, 0)
            | st.floats(1000.001, 1e9)
        ),
    ),
    (("contract", "n_points"), "n_points", count(1_000_000, checked_against_graphs=False)),  # P is dynamic
    (("contract", "observation"), "observation", lambda o, m: st.sampled_from([3, "x", [], DELETE])),
    (("contract",), "contract", lambda o, m: st.sampled_from([None, [], "x", DELETE])),
    # model_config: dssp-profile reads the widths and layer counts; the graphs' interface follows from the rest
    (("model_config", "d_model"), "d_model", count(65536)),
    (("model_config", "use_history"), "use_history", lambda o, m: NOT_BOOL | st.just(not o)),
    (("model_config", "use_recent_states"), "use_recent_states", lambda o, m: NOT_BOOL | st.just(not o)),
    (("model_config", "d_state"), "d_state", count(65536)),
    (("model_config", "d_conv"), "d_conv", count(64)),
    (("model_config", "expand"), "expand", count(16)),
    (("model_config", "n_history_layers"), "n_history_layers", count(256)),
    (
        ("model_config", "n_denoiser_layers"),
        "n_denoiser_layers",
        lambda o, m: NOT_INT | outside(1, 256) | st.just(DELETE),
    ),
    (("model_config", "point_feature_dim"), "point_feature_dim", lambda o, m: NOT_INT | outside(1, 65536)),
    (
        ("model_config", "point_widths"),
        "point_widths",
        lambda o, m: st.sampled_from([[], "64", [0], [64.5], [True], None]),
    ),
    (
        ("model_config", "state_widths"),
        "state_widths",
        lambda o, m: st.sampled_from([[], "64", [0], [64.5], [True], None]),
    ),
    (("model_config", "timestep_decoupled"), "timestep_decoupled", lambda o, m: NOT_BOOL),
    (("model_config",), "model_config", lambda o, m: st.sampled_from([None, [], "tiny", DELETE])),
    # the graph interface, against the facts
    (("graphs", "denoiser", "inputs", -1, "shape", 1), "noise", shape_dim),
    (("graphs", "denoiser", "inputs", -1, "shape", 2), "noise", shape_dim),
    (
        ("graphs", "denoiser", "inputs", -1, "shape"),
        "noise",
        lambda o, m: st.sampled_from([["B", 4], ["B", 4, 7, 1], "B,4,7", None]),
    ),
    (
        ("graphs", "denoiser", "inputs", -1, "dtype"),
        "noise",
        lambda o, m: st.sampled_from(["float64", "int64", "tensor(float)", 3, None]),
    ),
    (
        ("graphs", "denoiser", "inputs", -1, "name"),
        "inputs",
        lambda o, m: st.text(max_size=10) | st.sampled_from([None, 3]),
    ),
    (("graphs", "denoiser", "inputs", 1, "shape", 1), "z_recent", shape_dim),
    (("graphs", "denoiser", "inputs", 0, "shape", 1), "c_t", shape_dim),
    (("graphs", "denoiser", "outputs", 0, "shape", 2), "action", shape_dim),
    (("graphs", "history_step", "inputs", 0, "shape", 2), "point_cloud", shape_dim),
    (("graphs", "history_step", "inputs", 1, "shape", 1), "agent_pos", shape_dim),
    (("graphs", "history_step", "inputs", 2, "shape", 1), "conv_state_0", shape_dim),
    (("graphs", "history_step", "inputs", 3, "shape", 2), "ssm_state_0", shape_dim),
    (
        ("graphs", "history_step", "inputs", 2, "name"),
        "inputs",
        lambda o, m: st.sampled_from(["ssm_state_0", "conv_state_9", "", None]),
    ),
    (("graphs", "history_step", "outputs", 1, "shape", 1), "c_t", shape_dim),
    (("graphs", "history_step", "outputs"), "outputs", lambda o, m: st.sampled_from([[], None, {}, o[:-1], "z_t"])),
    # graph files: inside the model directory, with a size and sha256 in files
    (
        ("graphs", "history_step", "files", "onnx"),
        "files.onnx",
        lambda o, m: (
            st.sampled_from(
                ["../history_step.onnx", "/etc/passwd", "missing.onnx", "", ".", "C:\\x.onnx", "a/../../x", 3, None]
            )
            | st.text(alphabet="abc./", min_size=1, max_size=12).filter(lambda v: v not in m["files"])
        ),
    ),
    (
        ("graphs", "denoiser", "files"),
        "graphs.denoiser",
        lambda o, m: st.sampled_from([None, "denoiser.onnx", ["denoiser.onnx"], DELETE]),
    ),
    (("graphs", "denoiser"), "denoiser", lambda o, m: st.sampled_from([None, [], DELETE])),
    (
        ("files", "denoiser.onnx", "sha256"),
        "sha256",
        lambda o, m: (
            st.text(alphabet="0123456789abcdef", min_size=64, max_size=64)
            | st.sampled_from(["", "xyz", 5, None, o.upper(), DELETE])
        ),
    ),
    (
        ("files", "history_step.onnx", "bytes"),
        "bytes",
        lambda o, m: st.integers(0, 10**8) | st.integers(-(10**6), -1) | st.sampled_from(["1", 1.5, None]),
    ),
    (("files", "history_step.onnx"), "sha256", lambda o, m: st.just(DELETE)),
    (("files",), "files", lambda o, m: st.sampled_from([None, [], "history_step.onnx", DELETE])),
    # normalisers (export.verify reads them)
    (
        ("normalizers", "action", "scale"),
        "normalizers.action.scale",
        lambda o, m: (
            st.sampled_from([None, "x", [1.0] * 3, [NAN] * 7, [INF] * 7, ["1"] * 7, DELETE])
            | st.lists(st.floats(-10, 10), max_size=12).filter(lambda v: len(v) != 7)
        ),
    ),
    (("normalizers", "agent_pos"), "agent_pos", lambda o, m: st.sampled_from([None, {}, DELETE])),
    # the training ranges the runtime refuses observations outside of: input_min <= input_max per channel
    (
        ("normalizers", "agent_pos", "input_min"),
        "normalizers.agent_pos",
        lambda o, m: (
            st.sampled_from([[NAN] * 7, [1e3] * 7, DELETE]) | st.lists(st.floats(2, 1e6), min_size=7, max_size=7)
        ),
    ),
    # where it came from: an identity, no path
    (("source", "sha256"), "source.sha256", lambda o, m: st.sampled_from(["", "abc", None, 3, o.upper(), DELETE])),
    (
        ("source", "weights"),
        "source.weights",
        lambda o, m: st.sampled_from(["../model.safetensors", "/abs/model.safetensors", "", None, DELETE]),
    ),
    (("source", "step"), "source.step", lambda o, m: st.sampled_from([-1, "30", 1.5, DELETE])),
    (("source", "ema"), "source.ema", lambda o, m: NOT_BOOL),
    (("source", "run"), "source.run", lambda o, m: st.sampled_from(["/home/me/runs/x", "a/b", "", "..", 3])),
]


def _same(value, original) -> bool:
    return value is not DELETE and json.dumps(value) == json.dumps(original)


def test_the_unchanged_copy_loads(model, scratch):
    _, good = model
    write(scratch, good)
    policy = OnnxPolicy(scratch, threads=1, warmup=0)
    c = policy.contract
    assert (c.state_dim, c.action_dim, c.n_points) == (7, 7, 64)
    assert c.control_rate_hz == 50.0 and 1 <= c.n_action_steps <= c.horizon
    assert len(c.ddim_timesteps) == c.denoise_steps
    assert policy.manifest.history_state == [s["name"] for s in good["graphs"]["history_step"]["inputs"][2:]]


@pytest.mark.parametrize("path, token, bad", FIELDS, ids=[".".join(map(str, f[0])) for f in FIELDS])
def test_a_wrong_manifest_field_is_refused_at_load(model, scratch, path, token, bad):
    """Wrong type, out of range, missing, or inconsistent with the other facts or the graphs: one line naming it."""
    _, good = model
    original = get(good, path)

    @FAST
    @given(value=bad(original, good).filter(lambda v: not _same(v, original)))
    def check(value):
        refused(scratch, with_value(good, path, value), token)

    check()


# ------------------------------------------------------------------------------------ dssp-run
@pytest.mark.parametrize(
    "change, token",
    [
        (
            lambda m: m["contract"].update(n_action_steps=m["contract"]["horizon"] + 2),
            "n_action_steps",
        ),  # a few commands, then IndexError
        (lambda m: m["contract"].update(n_action_steps=0), "n_action_steps"),  # modulo by zero
        (lambda m: m["graphs"]["denoiser"]["files"].update(onnx="/etc/passwd"), "files.onnx"),
        (lambda m: m["files"]["denoiser.onnx"].update(sha256="0" * 64), "sha256"),
    ],
    ids=["h_a-above-horizon", "h_a-zero", "absolute-path", "sha256"],
)
def test_dssp_run_exits_2_before_any_arm_is_opened_or_enabled(model, tmp_path, monkeypatch, capsys, change, token):
    from hardware.cli.run import main as run_main
    from hardware.piper import piper_robot

    model_dir, good = model
    manifest = copy.deepcopy(good)
    change(manifest)
    bad = copy_model(model_dir, tmp_path / "bad", manifest)
    opened, enabled = [], []
    real_connect = piper_robot.PiperRobot.connect  # a bus opens when the robot connects
    monkeypatch.setattr(piper_robot.PiperRobot, "connect", lambda self: opened.append(self) or real_connect(self))
    monkeypatch.setattr(piper_robot.PiperRobot, "enable", lambda self, *a, **k: enabled.append(self))
    log_dir = tmp_path / "log"
    code = run_main(
        [
            "--model",
            str(bad),
            "--camera",
            "tabletop",
            "--can",
            "sim",
            "--max-steps",
            "5",
            "--log-dir",
            str(log_dir),
            "--threads",
            "1",
            "--quiet",
        ]
    )
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("error:")]
    assert code == 2 and "Traceback" not in err, err
    assert len(errors) == 1 and token in errors[0], err
    assert opened == [] and enabled == [] and not log_dir.exists()  # no bus opened, no arm enabled, nothing logged


def test_dssp_run_command_exits_2_on_h_a_above_the_horizon(model, tmp_path):
    model_dir, good = model
    bad = copy_model(
        model_dir, tmp_path / "bad", with_value(good, ("contract", "n_action_steps"), good["contract"]["horizon"] + 1)
    )
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "hardware.cli.run",
            "--model",
            str(bad),
            "--camera",
            "tabletop",
            "--can",
            "sim",
            "--max-steps",
            "5",
            "--log-dir",
            str(tmp_path / "log"),
            "--threads",
            "1",
            "--quiet",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    assert out.returncode == 2, out.stderr
    assert "n_action_steps" in out.stderr and "Traceback" not in out.stderr
    assert not (tmp_path / "log").exists()


# -------------------------------------------------------------------------- the files themselves
@pytest.fixture(scope="module")
def other_export(arm_export, tmp_path_factory):
    """Another export of the same run (K = 4): graphs with the same interface, other bytes."""
    from export.to_onnx import main as export_main

    run_dir = arm_export.parent / "run"
    assert (run_dir / "config.json").is_file()
    out = tmp_path_factory.mktemp("other") / "model"
    assert (
        export_main(
            [
                str(run_dir),
                "-o",
                str(out),
                "--skip-verify",
                "--format",
                "onnx",
                "--quantize",
                "none",
                "--denoise-steps",
                "4",
            ]
        )
        == 0
    )
    return out


@pytest.mark.parametrize("graph", ["denoiser", "history_step"])
def test_a_graph_file_from_another_export_is_refused(model, other_export, tmp_path, graph):
    model_dir, good = model
    other = json.loads((other_export / MANIFEST_NAME).read_text())
    assert other["graphs"][graph]["inputs"] == good["graphs"][graph]["inputs"]  # it would run: only its bytes differ
    OnnxPolicy(other_export, threads=1, warmup=0)
    bad = copy_model(model_dir, tmp_path / "bad")
    shutil.copyfile(other_export / f"{graph}.onnx", bad / f"{graph}.onnx")
    with pytest.raises(ModelDirError) as info:
        OnnxPolicy(bad, threads=1, warmup=0)
    message = str(info.value)
    assert f"{graph}.onnx" in message and "sha256" in message and "another export" in message and "\n" not in message


def test_export_verify_checks_every_file_it_opens(model, tmp_path, capsys):
    from export.verify import main as verify_main

    model_dir, _ = model
    bad = copy_model(model_dir, tmp_path / "bad")
    (bad / "history_step.pt").write_bytes((bad / "denoiser.pt").read_bytes())
    assert verify_main([str(bad), "--checkpoint", str(model_dir.parent / "run"), "--steps", "2", "--threads", "1"]) == 2
    err = capsys.readouterr().err
    assert "history_step.pt" in err and "sha256" in err and "Traceback" not in err


def test_file_names_from_the_manifest_stay_inside_the_model_directory(model, tmp_path):
    model_dir, good = model
    root = tmp_path / "models"
    bad = copy_model(model_dir, root / "bad")
    shutil.copyfile(model_dir / "denoiser.onnx", root / "denoiser.onnx")  # a loadable graph just outside

    # "../denoiser.onnx" with its true size and sha256: the file would load; the name is refused
    m = copy.deepcopy(good)
    m["graphs"]["denoiser"]["files"]["onnx"] = "../denoiser.onnx"
    m["files"]["../denoiser.onnx"] = good["files"]["denoiser.onnx"]
    assert "'../denoiser.onnx'" in refused(bad, m, "not a file name inside the model directory")
    refused(bad, with_value(good, ("graphs", "history_step", "files", "onnx"), "/etc/passwd"), "'/etc/passwd'")

    # a symbolic link that leads out: same bytes, same sha256, still refused
    write(bad, good)
    (bad / "denoiser.onnx").unlink()
    (bad / "denoiser.onnx").symlink_to(root / "denoiser.onnx")
    assert "symbolic link" in refused(bad, good, "denoiser.onnx")

    # a symbolic link inside the directory is fine
    (bad / "denoiser.onnx").unlink()
    (bad / "graphs").mkdir()
    shutil.copyfile(model_dir / "denoiser.onnx", bad / "graphs" / "denoiser.onnx")
    (bad / "denoiser.onnx").symlink_to(bad / "graphs" / "denoiser.onnx")
    OnnxPolicy(bad, threads=1, warmup=0)


def test_the_manifest_records_the_run_not_its_path(model):
    model_dir, good = model
    source = good["source"]
    assert "run_dir" not in source and source["run"] == "run"
    assert set(source) == {"run", "weights", "ema", "sha256", "step"}
    assert str(model_dir.parent) not in (model_dir / MANIFEST_NAME).read_text()


# ---------------------------------------------------------------------- non-finite observations
def arm_observations(n: int, seed: int = 0):
    """n observations of the one-arm model: clouds (n, 64, 3), joint states (n, 7)."""
    rng = np.random.default_rng(seed)
    home = np.array([0.0, 0.6, -0.6, 0.0, 0.4, 0.0, 0.8])
    clouds = rng.uniform([-0.3, -0.3, 0.0], [0.3, 0.3, 0.3], (n, 64, 3)).astype(np.float32)
    states = (home + rng.uniform(-0.1, 0.1, (n, 7))).astype(np.float32)
    return clouds, states


@pytest.fixture(scope="module")
def policies(arm_export):
    return OnnxPolicy(arm_export, threads=1), OnnxPolicy(arm_export, threads=1)


@settings(max_examples=12, deadline=None, derandomize=True)
@given(
    where=st.sampled_from(["point_cloud", "agent_pos"]),
    value=st.sampled_from([NAN, INF, -INF]),
    index=st.integers(0, 10**6),
    before=st.integers(1, 4),
)
def test_a_non_finite_observation_is_refused_and_leaves_the_history_unchanged(policies, where, value, index, before):
    p, ref = policies
    clouds, states = arm_observations(before + 4, seed=before)
    p.reset()
    ref.reset()
    for t in range(before):
        p.observe(clouds[t], states[t])
        ref.observe(clouds[t], states[t])
    cloud, state = clouds[before].copy(), states[before].copy()
    target = cloud if where == "point_cloud" else state
    flat = index % target.size
    target.flat[flat] = value
    entry = (0, *np.unravel_index(flat, target.shape))
    kept = policy_state(p)
    with pytest.raises(NonFiniteObservation) as info:
        p.observe(cloud, state)
    message = str(info.value)
    assert message.startswith(where) and str(tuple(int(i) for i in entry)) in message and "\n" not in message
    assert_policy_state_kept(p, kept)
    for t in range(before, before + 4):  # the episode goes on as if the bad observation had never come
        p.observe(clouds[t], states[t])
        ref.observe(clouds[t], states[t])
        assert np.array_equal(p.act(seed=t), ref.act(seed=t))


def test_the_streaming_api_refuses_the_same(arm_export):
    torch = pytest.importorskip("torch")
    from dssp_train.model.streaming import StreamingPolicy
    from dssp_train.training.checkpoint import load_policy

    policy, _ = load_policy(arm_export.parent / "run")
    stream, ref = StreamingPolicy(policy), StreamingPolicy(policy)
    clouds, states = arm_observations(8, seed=3)
    for t in range(3):
        stream.observe(clouds[t], states[t])
        ref.observe(clouds[t], states[t])
    kept = (
        stream.steps,
        stream.recent.clone(),
        stream.context.clone(),
        [[s.clone() for s in layer] for layer in stream.history_state],
    )
    bad = states[3].copy()
    bad[2] = NAN
    with pytest.raises(NonFiniteObservation, match=r"agent_pos .* \(0, 2\)=nan"):
        stream.observe(clouds[3], bad)
    bad_cloud = torch.from_numpy(clouds[3].copy())
    bad_cloud[5, 1] = INF
    with pytest.raises(NonFiniteObservation, match="point_cloud"):
        stream.observe(bad_cloud, states[3])
    assert stream.steps == kept[0] and torch.equal(stream.recent, kept[1]) and torch.equal(stream.context, kept[2])
    for layer, old in zip(stream.history_state, kept[3]):
        assert all(torch.equal(a, b) for a, b in zip(layer, old))
    for t in range(3, 8):
        stream.observe(clouds[t], states[t])
        ref.observe(clouds[t], states[t])
        assert np.array_equal(stream.act(seed=t), ref.act(seed=t))


def test_the_chunked_loop_skips_a_non_finite_observation(arm_export):
    p, q = OnnxPolicy(arm_export, threads=1), OnnxPolicy(arm_export, threads=1)
    loop, ref = ChunkedControl(p, seed=0), ChunkedControl(q, seed=0)
    clouds, states = arm_observations(12, seed=1)
    for t in range(4):
        loop.tick(clouds[t], states[t])
        ref.tick(clouds[t], states[t])
    bad = clouds[4].copy()
    bad[0, 0] = NAN
    with pytest.raises(NonFiniteObservation):
        loop.tick(bad, states[4])
    assert loop.tick_count == ref.tick_count == 4 and p.steps == q.steps == 4
    for t in range(4, 12):
        a, info = loop.tick(clouds[t], states[t])
        b, ref_info = ref.tick(clouds[t], states[t])
        assert np.array_equal(a, b) and info.chunk_index == ref_info.chunk_index


def test_the_robot_loop_holds_on_a_non_finite_cloud_and_keeps_it_out_of_the_history(arm_export, tmp_path, monkeypatch):
    poisoned = {"on": False}

    def cloud_with_nan(cloud):
        if poisoned["on"]:
            cloud = cloud.copy()
            cloud[3, 1] = NAN
        return cloud

    with rig_loop(arm_export, tmp_path, monkeypatch, cloud_with_nan) as (policy, runner, ticks):
        assert all(r["action"] is not None for r in ticks(5))
        steps, count = policy.steps, runner.source.control.tick_count
        poisoned["on"] = True
        held = ticks(3)
        assert policy.steps == steps and runner.source.control.tick_count == count  # the history was not fed
        for r in held:
            assert r["held"] and r["action"] is None and r["command"] is not None
            assert any(e.startswith("no observation: point_cloud") and "(0, 3, 1)=nan" in e for e in r["events"])
            assert any(e["kind"] == "hold" for e in r["safety"])
        assert all(np.array_equal(r["command"], held[0]["command"]) for r in held)  # the last safe target, resent
        assert runner.event_counts["non_finite_observation"] == 3 and runner.fault is None
        poisoned["on"] = False
        after = ticks(3)
        assert policy.steps == steps + 3 and all(r["action"] is not None for r in after)
