"""The robot runtime: no torch, same chunks as the PyTorch streaming API, control-loop semantics, profiler."""

import json
import subprocess
import sys
import textwrap
import warnings

import numpy as np
import pytest

from dssp_deploy import OnnxPolicy
from dssp_deploy.control_loop import ChunkedControl
from dssp_deploy.manifest import MANIFEST_NAME, ModelDirError
from dssp_deploy.schedules import MeasuredDelay, Plain


def long_trajectory(data_path, length=1000):
    from dssp_data.replay_buffer import ReplayBuffer

    buf = ReplayBuffer.load(data_path)
    reps = -(-length // buf.n_steps)
    return np.tile(buf.point_cloud, (reps, 1, 1))[:length], np.tile(buf.state, (reps, 1))[:length]


def test_importing_the_runtime_never_imports_torch(tiny_export):
    _, model_dir, _ = tiny_export
    code = textwrap.dedent(
        f"""
        import sys
        sys.modules["torch"] = None  # any import of torch now fails
        import numpy as np
        from dssp_deploy import OnnxPolicy
        from dssp_deploy.control_loop import ChunkedControl
        p = OnnxPolicy({str(model_dir)!r}, threads=1)
        loop = ChunkedControl(p, seed=0)
        for t in range(7):
            action, info = loop.tick(np.zeros((32, 3), np.float32), np.zeros(2, np.float32))
        assert action.shape == (1, 2) and np.isfinite(action).all()
        assert "torch" not in [m for m in sys.modules if sys.modules[m] is not None]
        print("ok")
        """
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"


def test_runtime_chunks_equal_pytorch_streaming_over_1000_steps(tiny_export):
    import torch

    from dssp_train.model.streaming import StreamingPolicy
    from dssp_train.training.checkpoint import load_policy

    run_dir, model_dir, data = tiny_export
    runtime = OnnxPolicy(model_dir, threads=1, precision="fp32")  # the graphs held to the parity bound
    policy, config = load_policy(run_dir)
    stream = StreamingPolicy(policy)
    pcs, states = long_trajectory(data)
    rng = np.random.default_rng(0)
    worst_chunk = worst_context = 0.0
    for t in range(len(states)):
        runtime.observe(pcs[t], states[t])
        c_ref = stream.observe(pcs[t], states[t])
        worst_context = max(worst_context, float(np.abs(runtime.context - c_ref.numpy()).max()))
        if t % config.model.n_action_steps == 0:
            noise = rng.standard_normal((1, config.model.horizon, config.model.action_dim)).astype(np.float32)
            worst_chunk = max(
                worst_chunk, float(np.abs(runtime.act(noise=noise) - stream.act(noise=torch.from_numpy(noise))).max())
            )
    assert worst_context <= 1e-4 and worst_chunk <= 1e-4, (worst_context, worst_chunk)


def test_quantized_graphs_run_on_request_and_their_absence_is_named(tiny_export, tmp_path):
    from export.to_onnx import main as export_main

    run_dir, model_dir, data = tiny_export
    with pytest.raises(ModelDirError, match="precision must be one of"):
        OnnxPolicy(model_dir, precision="fp16")
    int8_dir = tmp_path / "int8"
    assert (
        export_main(
            [str(run_dir), "-o", str(int8_dir), "--skip-verify", "--quantize", "int8", "--format", "onnx", "--no-fused"]
        )
        == 0
    )
    with pytest.raises(ModelDirError, match="--quantize int4"):
        OnnxPolicy(int8_dir, precision="int4")
    fp32, int8 = OnnxPolicy(int8_dir, threads=1, precision="fp32"), OnnxPolicy(int8_dir, threads=1)  # int8: the default
    for graph, session in int8.sessions.items():  # the int8 files, which carry their quantization in the metadata
        assert "int8" in session.get_modelmeta().custom_metadata_map["quantization"]
        assert "quantization" not in fp32.sessions[graph].get_modelmeta().custom_metadata_map
    pcs, states = long_trajectory(data)
    noise = (
        np.random.default_rng(0)
        .standard_normal((1, fp32.contract.horizon, fp32.contract.action_dim))
        .astype(np.float32)
    )
    for t in range(20):
        fp32.observe(pcs[t], states[t])
        int8.observe(pcs[t], states[t])
    a, b = fp32.act(noise=noise), int8.act(noise=noise)
    assert a.shape == b.shape and np.all(np.isfinite(b)) and not np.array_equal(a, b)
    assert np.abs(a - b).max() <= 0.25 * (np.abs(a).max() + 1e-6)  # quantized, not a different policy


def test_recent_tokens_pad_with_the_first_and_reset_forgets(tiny_export):
    _, model_dir, data = tiny_export
    p = OnnxPolicy(model_dir, threads=1)
    pcs, states = long_trajectory(data, 5)
    z0 = p.observe(pcs[0], states[0])
    assert p.recent.shape == (1, p.contract.n_obs_steps, p.manifest.model.d_model)
    assert np.array_equal(p.recent, np.repeat(z0[:, None], p.contract.n_obs_steps, axis=1))
    first = p.act(seed=1)
    before = p.recent.copy()
    z1 = p.observe(pcs[1], states[1])
    assert np.array_equal(p.recent[:, -1], z1) and np.array_equal(p.recent[:, :-1], before[:, 1:])
    p.reset()
    p.observe(pcs[0], states[0])
    assert np.array_equal(p.act(seed=1), first)  # a fresh episode: the same history, the same chunk


@pytest.mark.parametrize("library", ["numpy", "torch"])
def test_the_streaming_history_state_machine(library):
    """Zero state at the start, the first token repeated until N exist, the last N kept, a failed step or a
    batch change leaves everything as it was, reset starts over: with numpy arrays and with torch tensors."""
    if library == "torch":
        torch = pytest.importorskip("torch")
        array, stack = torch.as_tensor, lambda ts: torch.stack(ts, dim=1)
    else:
        array, stack = np.asarray, lambda ts: np.stack(ts, axis=1)
    from dssp_data.streaming_history import StreamingHistory

    seen = []

    def step(obs, state):  # obs (B, 1) → z_t = obs (B, 1), c_t = running sum, state = the sum
        seen.append(state)
        if float(obs.sum()) < 0:
            raise ValueError("refused")
        total = state + obs
        return obs, total, total

    history = StreamingHistory(3, step, stack, zero_state=lambda b: array(np.zeros((b, 1))))
    assert history.recent is None and history.context is None and history.steps == 0
    history.observe(array([[1.0], [2.0]]))
    assert float(seen[0].sum()) == 0.0 and tuple(history.recent.shape) == (2, 3, 1)
    assert np.asarray(history.recent)[:, :, 0].tolist() == [[1, 1, 1], [2, 2, 2]]
    history.observe(array([[3.0], [4.0]]))
    history.observe(array([[5.0], [6.0]]))
    history.observe(array([[7.0], [8.0]]))
    assert np.asarray(history.recent)[0, :, 0].tolist() == [3, 5, 7] and np.asarray(history.context)[:, 0].tolist() == [
        16,
        20,
    ]
    kept = (history.steps, np.asarray(history.recent).copy(), np.asarray(history.state).copy())
    with pytest.raises(ValueError, match="refused"):
        history.observe(array([[-100.0], [0.0]]))
    with pytest.raises(ValueError, match="batch size 1 within an episode of batch size 2; call reset"):
        history.observe(array([[1.0]]))
    assert history.steps == kept[0] and np.array_equal(np.asarray(history.recent), kept[1])
    assert np.array_equal(np.asarray(history.state), kept[2])
    history.reset()
    history.observe(array([[9.0]]))  # a new episode may have another batch size
    assert float(seen[-1].sum()) == 0.0 and np.asarray(history.recent)[0, :, 0].tolist() == [9, 9, 9]


def test_non_finite_values_are_named_and_refused():
    from dssp_core.errors import NonFiniteObservation
    from dssp_data.streaming_history import check_finite

    check_finite("agent_pos", np.zeros((1, 3)))
    bad = np.zeros((1, 8, 3), np.float32)
    bad[0, 2, 1], bad[0, 5] = np.nan, np.inf
    with pytest.raises(
        NonFiniteObservation,
        match=r"^point_cloud \[1, 8, 3\] has 4 non-finite value\(s\) at \(0, 2, 1\)=nan, "
        r"\(0, 5, 0\)=inf, \(0, 5, 1\)=inf, \(0, 5, 2\)=inf; the observation was not used",
    ):
        check_finite("point_cloud", bad)
    assert issubclass(NonFiniteObservation, ValueError)


def test_colour_channels_are_cut_and_bad_shapes_refused(tiny_export):
    _, model_dir, data = tiny_export
    p = OnnxPolicy(model_dir, threads=1)
    pcs, states = long_trajectory(data, 1)
    rgb = np.concatenate([pcs[0], np.ones_like(pcs[0])], axis=-1)
    z_rgb = p.observe(rgb, states[0])
    p.reset()
    assert np.array_equal(z_rgb, p.observe(pcs[0], states[0]))
    with pytest.raises(ValueError, match="agent_pos"):
        p.observe(pcs[0], np.zeros(5, np.float32))
    with pytest.raises(ValueError, match="channels"):
        p.observe(pcs[0][:, :2], states[0])
    with pytest.raises(ValueError, match="noise must have shape"):
        p.act(noise=np.zeros((1, 1, 1), np.float32))


def copy_model(model_dir, tmp_path):
    import shutil

    dst = tmp_path / "model"
    shutil.copytree(model_dir, dst)
    return dst


def test_manifest_that_does_not_fit_the_graphs_is_refused(tiny_export, tmp_path):
    import hashlib

    _, model_dir, _ = tiny_export
    bad = copy_model(model_dir, tmp_path)
    good = json.loads((bad / MANIFEST_NAME).read_text())
    manifest = json.loads(json.dumps(good))
    manifest["graphs"]["denoiser"]["inputs"][-1]["name"] = "eps"
    (bad / MANIFEST_NAME).write_text(json.dumps(manifest))
    with pytest.raises(ModelDirError, match="denoiser.inputs are .*'eps'.* give"):
        OnnxPolicy(bad)
    manifest["graphs"]["denoiser"]["inputs"][-1]["name"] = "noise"
    manifest["graphs"]["denoiser"]["inputs"][-1]["shape"][1] = 99
    (bad / MANIFEST_NAME).write_text(json.dumps(manifest))
    with pytest.raises(ModelDirError, match="noise"):
        OnnxPolicy(bad)
    # each graph's file named as the other's (sizes and sha256 match the files): the sessions tell
    manifest = json.loads(json.dumps(good))
    files = {g: manifest["graphs"][g]["files"] for g in ("history_step", "denoiser")}
    for kind in files["history_step"]:
        files["history_step"][kind], files["denoiser"][kind] = files["denoiser"][kind], files["history_step"][kind]
    (bad / MANIFEST_NAME).write_text(json.dumps(manifest))
    for kernel in ("auto", "standard"):  # a mismatch is refused, never a reason to fall back to the standard graphs
        with pytest.raises(ModelDirError, match="inputs are .* says"):
            OnnxPolicy(bad, kernel=kernel)
    manifest = json.loads(json.dumps(good))
    manifest["format_version"] = "0"
    (bad / MANIFEST_NAME).write_text(json.dumps(manifest))
    with pytest.raises(ModelDirError, match="format version"):
        OnnxPolicy(bad)
    with pytest.raises(ModelDirError, match="does not exist"):
        OnnxPolicy(tmp_path / "nowhere")
    (bad / "denoiser.onnx").write_bytes(b"not a graph")
    (bad / MANIFEST_NAME).write_text(json.dumps(good))
    with pytest.raises(ModelDirError, match="denoiser.onnx is not the file this manifest was written for"):
        OnnxPolicy(bad, kernel="standard")  # the files that run are checked
    manifest = json.loads(json.dumps(good))
    manifest["files"]["denoiser.onnx"].update(bytes=11, sha256=hashlib.sha256(b"not a graph").hexdigest())
    (bad / MANIFEST_NAME).write_text(json.dumps(manifest))
    with pytest.raises(ModelDirError, match="could not be loaded"):
        OnnxPolicy(bad, precision="fp32", kernel="standard")


def test_control_loop_updates_history_every_tick_and_chunks_every_h_a(tiny_export):
    _, model_dir, data = tiny_export
    p = OnnxPolicy(model_dir, threads=1)
    loop = ChunkedControl(p, seed=0)
    pcs, states = long_trajectory(data, 12)
    ha = p.contract.n_action_steps
    infos = [loop.tick(pcs[t], states[t])[1] for t in range(12)]
    assert p.steps == 12
    assert [i.new_chunk for i in infos] == [t % ha == 0 for t in range(12)]
    assert [i.chunk_index for i in infos] == [t % ha for t in range(12)]


def test_prefetch_starts_early_drops_passed_actions_and_matches_its_history(tiny_export):
    _, model_dir, data = tiny_export
    p = OnnxPolicy(model_dir, threads=1)
    ha, lead = p.contract.n_action_steps, 1
    loop = ChunkedControl(
        p, Plain(prefetch=True, delay=MeasuredDelay(50.0)), control_rate_hz=10, seed=0
    )  # 50 ms at 10 Hz: 1 tick
    assert loop.schedule.lead == lead
    pcs, states = long_trajectory(data, 2 * ha + 1)
    actions = [loop.tick(pcs[t], states[t]) for t in range(2 * ha + 1)]
    # Reference: the chunk for ticks [ha, 2 ha) computed from the history at tick ha - lead, actions from index lead.
    ref = OnnxPolicy(model_dir, threads=1, warmup=0)
    for t in range(ha - lead + 1):
        ref.observe(pcs[t], states[t])
    expected = ref.act(seed=0 + ha - lead)
    for j in range(ha):
        action, info = actions[ha + j]
        assert info.chunk_index == lead + j
        np.testing.assert_allclose(action, expected[:, lead + j], atol=1e-6)
    with pytest.raises(ValueError, match="H - action_offset - H_a = 1 predicted actions can be dropped"):
        ChunkedControl(p, Plain(prefetch=True, delay=MeasuredDelay(1000.0)), control_rate_hz=10)


def test_over_budget_chunks_are_reported_not_silent(tiny_export):
    _, model_dir, data = tiny_export
    p = OnnxPolicy(model_dir, threads=1)
    with pytest.warns(UserWarning, match="trained on data at 10 Hz"):
        loop = ChunkedControl(p, control_rate_hz=1e5, seed=0)  # a 10 us budget: every chunk tick is over it
    pcs, states = long_trajectory(data, 1)
    _, info = loop.tick(pcs[0], states[0])
    assert info.over_budget and any("over budget" in e for e in info.events)


def test_running_at_another_rate_than_trained_warns(tiny_export):
    _, model_dir, _ = tiny_export
    p = OnnxPolicy(model_dir, threads=1)
    assert p.contract.control_rate_hz == 10.0
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ChunkedControl(p, control_rate_hz=30)
        ChunkedControl(p, control_rate_hz=10)
    assert len(caught) == 1 and "10 Hz" in str(caught[0].message)


def test_int8_state_tokens_track_fp32_on_this_cpu(tiny_export):
    """The int8 observation encoder stays close to fp32 on any x86-64 CPU. Without VNNI (AVX2 only) ONNX Runtime's
    uint8 x int8 products add in int16 and saturate with full-range weights (z_t off by ~10 % of its scale);
    export.quantize keeps the weights to 7 bits so that no CPU saturates."""
    _, model_dir, data = tiny_export
    fp32, int8 = OnnxPolicy(model_dir, threads=1, precision="fp32"), OnnxPolicy(model_dir, threads=1, precision="int8")
    pcs, states = long_trajectory(data, 60)
    z32 = np.concatenate([fp32.observe(pc, s) for pc, s in zip(pcs, states)])
    z8 = np.concatenate([int8.observe(pc, s) for pc, s in zip(pcs, states)])
    assert np.abs(z8 - z32).max() <= 0.05 * np.abs(z32).max(), np.abs(z8 - z32).max() / np.abs(z32).max()


@pytest.mark.parametrize("error, runs", [(0.2, "fp32"), (0.01, "int8"), (None, "int8")])
def test_int8_measured_too_far_off_at_export_is_not_the_default(tiny_export, tmp_path, error, runs):
    import shutil

    _, model_dir, _ = tiny_export
    copy = tmp_path / "model"
    shutil.copytree(model_dir, copy)
    manifest = json.loads((copy / MANIFEST_NAME).read_text())
    if error is not None:
        manifest["verification"] = {
            "quantized": {
                "onnx_int8": {"action_max_abs_over_range": 0.01},
                "onnx_int8_fused": {"action_max_abs_over_range": error},
            }
        }
    (copy / MANIFEST_NAME).write_text(json.dumps(manifest))
    policy = OnnxPolicy(copy, threads=1)
    assert policy.precision == runs
    if runs == "fp32":
        assert "20.0 % of the action range" in policy.kernel_note and "--precision int8" in policy.kernel_note
    assert OnnxPolicy(copy, threads=1, precision="int8").precision == "int8"  # asked for, it runs
