"""Real-time chunking and inference delay: the inpainting denoiser (``export.to_onnx --inpainting``) against PyTorch,
the loop's schedules under a simulated delay (``SimulatedDelay(d)``) written out by hand on a stand-in
runtime whose chunks are known numbers, and ``dssp-sim eval --inject-delay --smoothing rtc`` end to end."""

import dataclasses
import json

import numpy as np
import pytest
import torch
from conftest import built_once, one_error_line, run_dssp

from dssp_data.model_contract import ModelContract
from dssp_deploy.control_loop import ChunkedControl
from dssp_deploy.onnx_policy import OnnxPolicy
from dssp_deploy.schedules import Ensemble, Plain, RealTimeChunking, SimulatedDelay, config_for, rtc_weights


def _inpainting_export(tmp_path_factory, request):
    from conftest import _arm_export

    from export.to_onnx import main as export_main

    plain = _arm_export(tmp_path_factory, request, 1)

    def build(root):
        model = root / "model"
        assert (
            export_main(
                [
                    str(plain.parent / "run"),
                    "-o",
                    str(model),
                    "--inpainting",
                    "--skip-verify",
                    "--quantize",
                    "none",
                    "--format",
                    "onnx",
                    "--no-fused",
                ]
            )
            == 0
        )
        return (model,)

    return plain, built_once(tmp_path_factory, request, "inpainting_export", build)[0]


@pytest.fixture(scope="module")
def exports(tmp_path_factory, request):
    """(the arm model exported plainly, the same run exported with --inpainting)."""
    return _inpainting_export(tmp_path_factory, request)


def test_the_inpainting_denoiser_is_the_pytorch_chain_and_zero_weights_are_the_plain_one(exports):
    from export.to_onnx import load_source

    plain_dir, model_dir = exports
    torch.set_num_threads(1)
    policy, _, _ = load_source(plain_dir.parent / "run", True)
    graph = OnnxPolicy(model_dir, threads=1, precision="fp32", kernel="standard")
    plain = OnnxPolicy(plain_dir, threads=1, precision="fp32", kernel="standard")
    assert graph.contract.inpainting and not plain.contract.inpainting
    rng = np.random.default_rng(0)
    pc, pos = graph.example_observation(rng)
    for p in (graph, plain):
        p.observe(pc, pos)
        p.observe(pc, pos)
    h, a = graph.contract.horizon, graph.contract.action_dim
    committed = rng.uniform(-0.5, 0.5, (1, h, a)).astype(np.float32)
    weight = np.linspace(1.0, 0.0, h, dtype=np.float32)[None, :, None]
    noise = graph.noise(1, seed=3)
    feeds = graph.denoiser_inputs(committed, weight)
    chunk = graph.denoise(feeds, noise=noise)
    with torch.no_grad():
        prefix = policy.build_prefix(torch.from_numpy(feeds["c_t"]), torch.from_numpy(feeds["z_recent"]))
        norm = policy.normalizers["action"]
        want = norm.unnormalize(
            policy.sample_normalized(
                prefix,
                torch.from_numpy(noise),
                graph.contract.denoise_steps,
                inpaint=(norm.normalize(torch.from_numpy(committed)), torch.from_numpy(weight)),
            )
        ).numpy()
    np.testing.assert_allclose(chunk, want, atol=1e-5)  # parity with the training code's chain
    np.testing.assert_allclose(chunk[0, 0], committed[0, 0], atol=1e-5)  # weight 1: the committed action itself
    zero = graph.denoise(graph.denoiser_inputs(), noise=noise)
    np.testing.assert_allclose(zero, plain.denoise(plain.denoiser_inputs(), noise=noise), atol=1e-5)
    assert np.abs(chunk - zero).max() > 1e-2  # the weights change the chunk
    with pytest.raises(ValueError, match="export it with --inpainting"):
        plain.denoiser_inputs(committed, weight)


def test_rtc_weights_freeze_the_past_and_the_delay_then_decay():
    w = rtc_weights(horizon=8, offset=1, covered=6, delay=2)
    assert w[:3].tolist() == [1.0, 1.0, 1.0] and w[6:].tolist() == [0.0, 0.0]
    assert 1.0 > w[3] > w[4] > w[5] > 0.0
    assert rtc_weights(8, 1, 2, 3).tolist() == [1.0, 1.0] + [0.0] * 6  # nothing committed beyond the old chunk's end
    assert not rtc_weights(8, 0, 0, 2).any()


class FakePolicy:
    """What ChunkedControl uses of OnnxPolicy for chunks with an inpainting denoiser: chunk k (the k-th computed) holds
    100 k + j at index j; each call's committed actions and weights are kept."""

    def __init__(self, horizon=8, n_action_steps=3, action_offset=1):
        self.horizon = horizon
        self.contract = ModelContract(
            n_obs_steps=action_offset + 1,
            horizon=horizon,
            n_action_steps=n_action_steps,
            action_offset=action_offset,
            ddim_timesteps=[2, 1, 0],
            inpainting=True,
            control_rate_hz=10.0,
        )
        self.calls: list[dict] = []
        self.history = ()

    def reset(self):
        self.history = ()

    def observe(self, point_cloud, agent_pos):
        self.history = (*self.history, float(np.asarray(agent_pos).ravel()[0]))

    def denoiser_inputs(self, committed=None, weight=None):
        return {"seen": len(self.history), "committed": committed, "weight": weight}

    def denoise(self, inputs, noise=None, seed=None):
        k = len(self.calls)
        self.calls.append(inputs)
        return (100.0 * k + np.arange(self.horizon, dtype=np.float32))[None, :, None]

    def act(self, seed=None):
        return self.denoise(self.denoiser_inputs(), seed=seed)


def run(loop, ticks):
    out = []
    for t in range(ticks):
        action, _ = loop.tick(np.zeros((4, 3), np.float32), np.array([float(t)], np.float32))
        out.append(None if action is None else float(action[0, 0]))
    return out


def test_without_smoothing_a_delay_is_a_stall_before_every_chunk():
    policy = FakePolicy(horizon=6, n_action_steps=2, action_offset=1)
    actions = run(ChunkedControl(policy, Plain(delay=SimulatedDelay(2))), 9)
    # hold 2 ticks, chunk 0's H_a actions from its first (index offset), a new chunk, hold 2 ticks, ...
    assert actions == [None, None, 1.0, 2.0, None, None, 101.0, 102.0, None]
    assert [c["seen"] for c in policy.calls] == [1, 5, 9]  # each from the observation of the tick it started at


def test_prefetch_under_a_delay_starts_each_chunk_that_many_ticks_early_and_drops_its_passed_actions():
    policy = FakePolicy(horizon=8, n_action_steps=3, action_offset=1)
    actions = run(ChunkedControl(policy, Plain(prefetch=True, delay=SimulatedDelay(2))), 9)
    # the first chunk is needed at once: a stall of 2 ticks; then each one starts 2 ticks before its first tick
    assert actions == [None, None, 1.0, 2.0, 3.0, 103.0, 104.0, 105.0, 203.0]
    assert [c["seen"] for c in policy.calls] == [1, 4, 7]


def test_ensembling_takes_each_chunk_in_late_at_the_actions_for_the_ticks_it_then_covers():
    policy = FakePolicy(horizon=8, n_action_steps=3, action_offset=1)
    loop = ChunkedControl(policy, Ensemble(every=1, decay=0.0, delay=SimulatedDelay(1)))
    actions = run(loop, 4)
    # tick t: chunk s (computed at s, usable from s + 1) predicts t with index 1 + t - s
    assert actions[0] is None
    assert actions[1] == 2.0  # chunk 0 only
    assert actions[2] == pytest.approx((3.0 + 102.0) / 2)  # chunks 0 and 1
    assert actions[3] == pytest.approx((4.0 + 103.0 + 202.0) / 3)


def test_real_time_chunking_starts_early_inpaints_what_is_committed_and_takes_over_after_the_delay():
    policy = FakePolicy(horizon=8, n_action_steps=3, action_offset=1)
    loop = ChunkedControl(policy, RealTimeChunking(delay=SimulatedDelay(2)))
    actions = run(loop, 9)
    # chunk 0 from tick 0 takes over at tick 2 (index 1 + 2); chunk 1 starts at tick 3, takes over at 5 (index 3), …
    assert actions == [None, None, 3.0, 4.0, 5.0, 103.0, 104.0, 105.0, 203.0]
    first, second = policy.calls[0], policy.calls[1]
    assert first["committed"] is None and first["weight"] is None  # nothing committed before the first chunk
    # chunk 1 (observation at tick 3): its index i is tick 3 + i - 1, chunk 0's index i + 3; chunk 0 covers 5 of them
    np.testing.assert_array_equal(second["committed"][0, :, 0], [3, 4, 5, 6, 7, 0, 0, 0])
    np.testing.assert_array_equal(second["weight"][0, :, 0], rtc_weights(8, 1, 5, 2))
    assert second["seen"] == 4 and policy.calls[2]["seen"] == 7


def test_real_time_chunking_with_no_delay_acts_from_the_first_tick():
    policy = FakePolicy(horizon=8, n_action_steps=3, action_offset=1)
    actions = run(ChunkedControl(policy, RealTimeChunking(delay=SimulatedDelay(0))), 7)
    assert actions == [1.0, 2.0, 3.0, 101.0, 102.0, 103.0, 201.0]
    np.testing.assert_array_equal(policy.calls[1]["weight"][0, :, 0], rtc_weights(8, 1, 5, 0))  # only the past frozen


def test_a_delay_beyond_what_the_horizon_covers_holds_the_ticks_no_chunk_has():
    policy = FakePolicy(horizon=8, n_action_steps=4, action_offset=1)  # H - offset = 7 < H_a + d = 8
    actions = run(ChunkedControl(policy, RealTimeChunking(delay=SimulatedDelay(4))), 13)
    assert actions[:4] == [None] * 4 and actions[4:8] == [5.0, 6.0, 7.0, None]  # chunk 0 runs out at index 8
    assert actions[8:12] == [105.0, 106.0, 107.0, None]


def test_rtc_needs_an_inpainting_model_and_no_prefetch():
    policy = FakePolicy()
    policy.contract = dataclasses.replace(policy.contract, inpainting=False)
    with pytest.raises(ValueError, match="export the model with python -m export.to_onnx --inpainting"):
        ChunkedControl(policy, RealTimeChunking(delay=SimulatedDelay(1)))
    with pytest.raises(TypeError, match="prefetch"):  # real-time chunking has no prefetch setting
        RealTimeChunking(prefetch=True)
    with pytest.raises(ValueError, match="real-time chunking computes the next chunk in the background itself"):
        config_for("rtc", prefetch=True)
    with pytest.raises(ValueError, match="SimulatedDelay.ticks must be a whole number of ticks >= 0"):
        SimulatedDelay(-1)


def test_dssp_sim_eval_refuses_rtc_without_an_inpainting_model_and_a_delay_for_the_expert(exports, capsys, tmp_path):
    """Refused before any output is opened: the refused run leaves no Rerun recording and no strips folder, so
    the corrected command runs with the same outputs."""
    from dssp_sim.sim_cli import main as sim_main

    plain_dir, _ = exports
    outputs = ["--rerun-save", str(tmp_path / "eval.rrd"), "--strips", str(tmp_path / "strips")]
    for refused, message in (
        (["--smoothing", "rtc"], "export the model with python -m export.to_onnx --inpainting"),
        (["--smoothing", "ensemble", "--ensemble-every", "99"], "--ensemble-every 99"),
        (["--inject-delay", "20000"], "--inject-delay must be in [0, 10000] ms"),
    ):
        code = sim_main(
            ["eval", "--model", str(plain_dir), "--task", "tap", "--episodes", "1", *refused, *outputs, "--no-progress"]
        )
        assert code == 2 and message in one_error_line(capsys.readouterr().err)
        assert list(tmp_path.iterdir()) == []
    code = sim_main(["eval", "--model", str(plain_dir), "--task", "tap", "--episodes", "1", *outputs, "--no-progress"])
    err = capsys.readouterr().err
    assert code == 0, err
    assert (tmp_path / "eval.rrd").is_file() and len(list((tmp_path / "strips").glob("*.png"))) == 1
    code = sim_main(["eval", "--expert", "--task", "tap", "--episodes", "1", "--inject-delay", "100", "--no-progress"])
    assert code == 2 and "--inject-delay is a model's setting" in one_error_line(capsys.readouterr().err)


def test_dssp_run_with_real_time_chunking_on_the_embedded_simulation(exports, tmp_path, capsys, monkeypatch):
    """On the robot's path the next chunk runs in a background thread; d comes from the chunk time measured when the
    loop is built. The measurement runs, and its figure is taken as at most one 50 Hz tick: this model covers one
    tick beyond its H_a, and a loaded machine must not turn the run into the refusal (the check prefetch makes too,
    held by test_run_startup). The run itself is real time; nothing asserted depends on how fast the machine is."""
    from dssp_deploy.control_loop import ChunkedControl
    from hardware.run_log import read_ticks

    measure, measured = ChunkedControl.measure_chunk_ms, []

    def at_most_a_tick(self, iterations=5):
        measured.append(measure(self, iterations))
        return min(measured[-1], 20.0)

    monkeypatch.setattr(ChunkedControl, "measure_chunk_ms", at_most_a_tick)
    _, model_dir = exports
    log_dir = tmp_path / "log"
    code, out, err = run_dssp(
        capsys,
        "--model",
        model_dir,
        "--smoothing",
        "rtc",
        "--camera",
        "tabletop",
        "--can",
        "sim",
        "--max-steps",
        "30",
        "--seed",
        "0",
        "--threads",
        "2",
        "--quiet",
        "--log-dir",
        log_dir,
    )
    assert code == 0, out + err
    assert "ticks 30" in out and "ended by: max steps" in out
    policy = json.loads((log_dir / "run.json").read_text())["settings"]["policy"]
    assert measured and policy["smoothing"] == "rtc" and policy["rtc_delay_ticks"] == 1
    assert policy["injected_delay_ticks"] is None
    ticks = read_ticks(log_dir)
    assert any(t.get("chunk_ms") is not None for t in ticks)
    code, _, err = run_dssp(
        capsys,
        "--model",
        model_dir,
        "--smoothing",
        "rtc",
        "--prefetch",
        "--camera",
        "tabletop",
        "--can",
        "sim",
        "--log-dir",
        tmp_path / "log2",
    )
    assert code == 2 and "--prefetch does not combine with --smoothing rtc" in one_error_line(err)
