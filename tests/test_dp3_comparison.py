"""benchmarks/dp3_comparison.py: the DP3 head's shapes, its ONNX graphs against PyTorch, and a quick run."""

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
SMALL = [32, 64, 128]


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_dp3_comparison", ROOT / "benchmarks" / "dp3_comparison.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_small_dp3_maps_observations_and_noise_to_a_chunk(bench):
    encoder, unet, cfg = bench.build_dp3(state_dim=5, action_dim=6, down_dims=SMALL)
    t, h = cfg["n_obs_steps"], cfg["horizon"]
    assert (t, h) == (3, 8) and encoder.feature_dim == 192
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        cond = encoder(torch.randn(2, t, 40, 3, generator=gen), torch.randn(2, t, 5, generator=gen))
        assert cond.shape == (2, t * 192)
        noise = torch.randn(2, h, 6, generator=gen)
        out = unet(noise, torch.tensor([90, 90]), cond)
        assert out.shape == (2, h, 6)
        # the timestep and the condition reach the output
        assert not torch.allclose(out, unet(noise, torch.tensor([0, 0]), cond))
        assert not torch.allclose(out, unet(noise, torch.tensor([90, 90]), cond.roll(1, dims=0)))
        # a whole chunk: K DDIM steps
        chunk = bench.dp3_chunk_torch(encoder, unet, bench.ddim_steps(4), torch.randn(1, t, 40, 3), torch.randn(1, t, 5),
                                      torch.randn(1, h, 6))
    assert chunk.shape == (1, h, 6) and torch.isfinite(chunk).all()
    big = bench.n_params(bench.DP3UNet(14, 3 * 192))  # RoboTwin widths: DP3's ~255M-parameter UNet
    assert 240e6 < big < 280e6


def test_ddim_update_is_the_project_schedule(bench):
    from dssp_train.config import DiffusionConfig
    from dssp_train.model.scheduler import DiffusionSchedule

    steps = bench.ddim_steps(10)
    assert [s[0] for s in steps] == list(range(90, -1, -10))
    schedule = DiffusionSchedule(DiffusionConfig())
    x, x0 = torch.randn(2, 8, 3), 1.5 * torch.randn(2, 8, 3)
    for t, a_t, a_prev in steps:
        expected = schedule.ddim_step(x0, t, x, 10)
        assert torch.allclose(bench.ddim_update(x0, x, a_t, a_prev), expected, atol=1e-6)
        got = bench.ddim_update(x0.numpy(), x.numpy(), a_t, a_prev)
        assert got.dtype == np.float32 and np.allclose(got, expected.numpy(), atol=1e-6)


def test_onnx_graphs_match_pytorch(bench, tmp_path):
    encoder, unet, cfg = bench.build_dp3(state_dim=5, action_dim=6, down_dims=SMALL)
    steps = bench.ddim_steps(3)
    chunk = bench.DP3OnnxChunk(encoder, unet, cfg, 40, steps, threads=1, folder=tmp_path)
    rng = np.random.default_rng(1)
    pc = rng.standard_normal((2, 3, 40, 3), dtype=np.float32)  # batch 2: the exported batch axis is dynamic
    pos = rng.standard_normal((2, 3, 5), dtype=np.float32)
    noise = rng.standard_normal((2, 8, 6), dtype=np.float32)
    with torch.no_grad():
        cond = encoder(torch.from_numpy(pc), torch.from_numpy(pos))
        x0 = unet(torch.from_numpy(noise), torch.tensor([60, 60]), cond).numpy()
        expected = bench.dp3_chunk_torch(encoder, unet, steps, *(torch.from_numpy(a) for a in (pc, pos, noise))).numpy()
    ort_cond = chunk.encoder.run(None, {"point_cloud": pc, "agent_pos": pos})[0]
    np.testing.assert_allclose(ort_cond, cond.numpy(), atol=1e-4)
    ort_x0 = chunk.unet.run(None, {"sample": noise, "timestep": np.array([60, 60], np.int64), "global_cond": ort_cond})[0]
    np.testing.assert_allclose(ort_x0, x0, atol=1e-4)
    np.testing.assert_allclose(chunk(pc, pos, noise), expected, atol=1e-4)


def test_quick_run_writes_timings_and_ratios(bench, tiny_export, tmp_path, capsys):
    _, model_dir, _ = tiny_export
    out = tmp_path / "dp3.json"
    args = [str(model_dir), "--quick", "--threads", "1", "--dp3-dims", *map(str, SMALL), "--json", str(out)]
    assert bench.main(args) == 0
    text = capsys.readouterr().out
    assert "| DP3 (ONNX Runtime) |" in text and "| DP3 (PyTorch eager) |" in text and "| DSSP (ONNX Runtime) |" in text
    report = json.loads(out.read_text())
    med = report["median_ms"]
    assert all(med[k] > 0 for k in ("dssp_ort_chunk", "dp3_ort_chunk", "dp3_torch_chunk", "dssp_ort_history_step"))
    assert all(v["n"] == bench.QUICK_REPEATS and v["p90"] >= v["median"] for v in report["latency_ms"].values())
    assert report["ratio"]["dp3_ort_over_dssp_ort"] == pytest.approx(med["dp3_ort_chunk"] / med["dssp_ort_chunk"])
    assert report["ratio"]["dp3_torch_over_dssp_ort"] == pytest.approx(med["dp3_torch_chunk"] / med["dssp_ort_chunk"])
    assert report["dp3"]["config"]["down_dims"] == SMALL and report["dp3"]["params"]["unet"] > 0
    assert len(report["dp3"]["ddim_timesteps"]) == report["problem"]["denoise_steps"]
    assert report["dp3"]["ort_vs_torch_max_abs_diff"] < 1e-3
    # an existing --json is kept unless --force
    before = out.read_text()
    assert bench.main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "--force" in err[0]
    assert out.read_text() == before


@pytest.mark.parametrize("extra", [[], ["--dp3-dims", "30", "60"], ["--dp3-dims", "32", "64", "128", "256", "512"],
                                   ["--repeats", "0"]])
def test_bad_input_is_one_error_line(bench, tiny_export, tmp_path, capsys, extra):
    _, model_dir, _ = tiny_export
    target = tmp_path / "missing" if not extra else model_dir
    assert bench.main([str(target), "--quick", "--threads", "1", *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
