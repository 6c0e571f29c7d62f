"""``dssp-profile`` runs on ONNX Runtime and numpy only; the PyTorch comparison is benchmarks/torch_comparison.py."""

import importlib.util
import json
import os
import shutil
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from conftest import ROOT, cpu_flags

from dssp_deploy.manifest import file_kind, read_manifest


def load_comparison(name: str = "torch_comparison"):
    spec = importlib.util.spec_from_file_location(f"bench_{name}", ROOT / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_profile_runs_where_torch_cannot_be_imported(tiny_export, tmp_path):
    _, model_dir, _ = tiny_export
    json_path, png_path = tmp_path / "profile.json", tmp_path / "profile.png"
    code = textwrap.dedent(
        f"""
        import sys
        for name in ("torch", "dssp_train", "export", "onnx"):
            sys.modules[name] = None  # any import of these now fails
        from dssp_deploy.profile import main
        code = main([{str(model_dir)!r}, "--quick", "--threads", "1", "--json", {str(json_path)!r}, "--plot", {str(png_path)!r}])
        assert code == 0, code
        print("loaded:", sorted(m for m in ("torch", "dssp_train", "export", "onnx") if sys.modules.get(m) is not None))
        """
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    assert out.returncode == 0, out.stderr
    assert (
        "loaded: []" in out.stdout
        and "| history step (ORT) |" in out.stdout
        and "Chunk floor on this machine" in out.stdout
    )
    assert "PyTorch" not in out.stdout and "Transformer" not in out.stdout
    report = json.loads(json_path.read_text())
    assert "torch" not in report and 0 < report["latency_ms"]["denoiser_chunk"]["p50"]
    assert [r["length"] for r in report["history_sweep"]] == report["settings"]["sweep"]
    for key in ("history_step", "denoiser_chunk", "chunk_tick"):
        s = report["latency_ms"][key]
        assert 0 < s["p50"] <= s["p95"] <= s["p99"] <= s["max"]
    assert all(r["rss_mib"] > 0 for r in report["history_sweep"])
    assert report["machine"]["gemm_peak_gflops"] > 0 and report["achieved_gflops"]["denoiser_chunk"] > 0
    for graph in ("history_step", "denoiser_chunk"):  # ORT's own profiler explains where the time goes
        rows = report["op_breakdown"][graph]
        assert rows and abs(sum(r["share"] for r in rows) - 1) < 1e-6 and all(r["nodes"] >= 1 for r in rows)
    ops = {r["op"] for r in report["op_breakdown"]["denoiser_chunk"]}
    assert any("MatMul" in op for op in ops) and "MambaBlockQ8" in ops  # the int8 fused graph ran: a node per block
    assert "| denoiser chunk p50 ms |" in out.stdout and "Where the denoiser chunk goes" in out.stdout
    # the least a chunk can take here, from this machine's bandwidth (and its float32 GEMM peak for fp32 graphs only:
    # an int8 graph's products are not bounded by it)
    floor = report["chunk_floor"]
    stream = floor["weight_stream_ms"]
    assert report["precision"] == "int8" and floor["compute_ms"] is None and floor["read_gbs"] > 0
    assert floor["floor_ms"] == stream and "Chunk floor on this machine" in out.stdout
    assert "no compute term" in out.stdout and ("not known here" in out.stdout) == (stream is None)
    assert [int(k) for k in floor["read_gbs_by_mib"]] == [
        2,
        4,
        8,
        12,
        16,
        24,
        32,
        64,
        128,
    ]  # the cache this process gets
    assert floor["cpu_cache_mib"] is None or floor["cache_mib"] is None or floor["cache_mib"] <= floor["cpu_cache_mib"]
    ran = read_manifest(model_dir).graphs["denoiser"]["files"][
        file_kind(report["precision"], report["kernel"] == "fused")
    ]
    assert floor["weights_mib"] * 2**20 == (model_dir / ran).stat().st_size
    assert png_path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # both graph sets, each at 1 thread (--threads 1), and the prefetched tick on the same model
    assert report["kernel"] == "fused" and [(r["kernel"], r["threads"]) for r in report["paths_and_threads"]] == [
        ("fused", 1),
        ("standard", 1),
    ]
    assert all(r["chunk_p50"] > 0 and r["chunk_speedup_vs_1"] == 1.0 for r in report["paths_and_threads"])
    prefetch = report["prefetch"]
    assert prefetch["ticks"] == report["settings"]["prefetch_ticks"] and prefetch["lead_ticks"] >= 1
    assert prefetch["threads"] == {"history_step": 1, "denoiser": 1} and prefetch["tick_p99_over_history_p99"] > 0
    assert "| fused | 1 |" in out.stdout and "| standard | 1 |" in out.stdout and "Prefetch: " in out.stdout


def test_profile_has_no_checkpoint_flag(tmp_path, capsys):
    from dssp_deploy.profile import main

    with pytest.raises(SystemExit) as exc:
        main([str(tmp_path), "--checkpoint", str(tmp_path)])
    assert exc.value.code == 2 and "unrecognized arguments: --checkpoint" in capsys.readouterr().err


def test_torch_comparison_reports_medians_and_ratios_to_the_runtime(tiny_export, tmp_path, capsys):
    run_dir, model_dir, _ = tiny_export
    out = tmp_path / "comparison.json"
    bench = load_comparison()
    assert (
        bench.main([str(model_dir), "--checkpoint", str(run_dir), "--quick", "--threads", "1", "--json", str(out)]) == 0
    )
    text = capsys.readouterr().out
    assert (
        "| history step |" in text
        and "| denoiser chunk |" in text
        and "ONNX Runtime vs PyTorch eager per chunk" in text
    )
    report = json.loads(out.read_text())
    for backend in ("ort", "eager", "torchscript"):
        assert all(report["median_ms"][backend][k] > 0 for k in ("history_step", "denoiser_chunk"))
    for backend in ("eager", "torchscript"):
        ratios = report["ratio_to_ort"][backend]
        assert ratios["denoiser_chunk"] == pytest.approx(
            report["median_ms"][backend]["denoiser_chunk"] / report["median_ms"]["ort"]["denoiser_chunk"]
        )
    assert [r["length"] for r in report["history_sweep"]] == bench.QUICK["sweep"]
    assert all(r["dssp_ort_ms"] > 0 and r["transformer_torch_ms"] > 0 for r in report["history_sweep"])
    # without --checkpoint: TorchScript and the sweep only, and the table says why eager is missing
    assert bench.main([str(model_dir), "--quick", "--threads", "1"]) == 0
    text = capsys.readouterr().out
    assert "PyTorch eager: not measured (give --checkpoint" in text and "TorchScript ms" in text


def test_torch_comparison_refuses_a_checkpoint_the_model_was_not_exported_from(tiny_export, tmp_path, capsys):
    run_dir, model_dir, _ = tiny_export
    bench = load_comparison()
    other = tmp_path / "other_run"
    shutil.copytree(run_dir, other)
    weights = other / json.loads((model_dir / "dssp_model.json").read_text())["source"]["weights"]
    data = bytearray(weights.read_bytes())
    data[-1] ^= 1  # another run's weights
    weights.write_bytes(bytes(data))
    assert bench.main([str(model_dir), "--quick", "--checkpoint", str(other), "--threads", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is not the run" in err[0]
    assert bench.main([str(model_dir), "--quick", "--checkpoint", str(tmp_path / "none"), "--threads", "1"]) == 2
    assert "cannot be read" in capsys.readouterr().err


def test_cpu_targets_table_has_every_row_on_both_graph_sets(tiny_export, tmp_path, capsys):
    run_dir, model_dir, _ = tiny_export
    out = tmp_path / "targets.json"
    bench = load_comparison("cpu_targets")
    plot = tmp_path / "roofline.png"
    from export.to_onnx import main as export_main

    k1 = tmp_path / "k1"
    assert (
        export_main(
            [str(run_dir), "-o", str(k1), "--denoise-steps", "1", "--timestep-spacing", "trailing", "--skip-verify"]
        )
        == 0
    )
    capsys.readouterr()
    assert (
        bench.main(
            [str(model_dir), "--checkpoint", str(run_dir), "--quick", "--threads", "1", "--k1-model", str(model_dir)]
        )
        == 2
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "runs 10 DDIM steps, not 1" in err[0] and "--denoise-steps 1" in err[0]
    assert (
        bench.main(
            [
                str(model_dir),
                "--checkpoint",
                str(run_dir),
                "--quick",
                "--threads",
                "1",
                "--json",
                str(out),
                "--plot",
                str(plot),
                "--k1-model",
                str(k1),
            ]
        )
        == 0
    )
    text = capsys.readouterr().out
    assert "| chunk, K = 1, int8, p50 ms |" in text and "| history step, int8, p50 ms |" in text
    assert "| fused Mamba kernel | standard graphs | target |" in text and "| chunk, K = 10, int8, p50 ms |" in text
    report = json.loads(out.read_text())
    # the roofline: every chunk against the reads of its own graph's weights at the measured bandwidth: K in every
    # graph (its first step carries the prefix), 1 for K = 1
    manifest = json.loads((model_dir / "dssp_model.json").read_text())
    assert report["read_gbs"] > 0 and plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    k1_manifest = json.loads((k1 / "dssp_model.json").read_text())
    assert {"fused, K = 1"} <= set(report["roofline"]) and report["k1_model"] == str(k1)
    for kernel, by_precision in report["roofline"].items():
        for precision, r in by_precision.items():
            graph = (
                "denoiser" + {"int8": ".int8", "fp32": ""}[precision] + ".fused" * kernel.startswith("fused") + ".onnx"
            )
            passes, files = (1, k1_manifest["files"]) if kernel.endswith("K = 1") else (10, manifest["files"])
            assert files[graph]["weight_reads"] == passes
            assert r["weights_mib"] == pytest.approx(files[graph]["bytes"] / 2**20)
            assert r["passes"] == passes and r["floor_ms"] == pytest.approx(
                passes * files[graph]["bytes"] / report["read_gbs"] / 1e6
            )
            assert r["ratio"] == pytest.approx(r["chunk_ms"] / r["floor_ms"])
    vnni = bool({"avx512_vnni", "avx_vnni"} & cpu_flags())
    assert ("fused, avx2 forced" in report["roofline"]) == vnni == ("fused, avx2 forced, K = 1" in report["roofline"])
    assert "| chunk / floor, int8 |" in text and "Roofline: read bandwidth" in text
    assert set(report["runtime"]) == {"fused", "standard"} and report["machine"]["cores"] >= 1
    for kernel, r in report["runtime"].items():
        assert set(r["precision"]) == {"int8", "fp32"} and all(
            p["threads"] == 1 and p["chunk_p50"] > 0 for p in r["precision"].values()
        )
        assert r["prefetch"]["possible"] and r["prefetch"]["threads"] == {"history_step": 1, "denoiser": 1}
    table = bench.rows(report["runtime"], report["eager_torch"], report["precision"], report["roofline"])
    eager_ratio = next(row for row in table if row["figure"].startswith("ONNX Runtime vs eager"))["values"]
    assert eager_ratio["fused"] == pytest.approx(  # like for like: fp32 against fp32
        report["eager_torch"]["denoiser_chunk"]["p50"] / report["runtime"]["fused"]["precision"]["fp32"]["chunk_p50"]
    )
    assert "| ONNX Runtime vs eager PyTorch per chunk, both fp32 (eager / ORT) |" in text


def test_the_chunk_spins_only_while_it_runs_and_only_with_threads_to_spin(tiny_export):
    """The denoiser's threads spin during a run only (force_spinning_stop), by default when it has 2 threads or more;
    the actions are the same either way; the profile's thread rows add --no-spin when there are threads to spin."""
    from dssp_deploy.onnx_policy import OnnxPolicy
    from dssp_deploy.profile import paths_and_threads
    from dssp_deploy.sessions import session_options

    options = session_options(2, spinning=True)
    assert options.get_session_config_entry("session.intra_op.allow_spinning") == "1"
    assert options.get_session_config_entry("session.force_spinning_stop") == "1"
    assert session_options(2).get_session_config_entry("session.intra_op.allow_spinning") == "0"
    _, model_dir, _ = tiny_export
    chunks = []
    for threads, spinning, spins in ((2, None, True), (2, False, False), (1, None, False), (2, True, True)):
        policy = OnnxPolicy(model_dir, threads=threads, spinning=spinning)
        assert policy.spinning is spins
        policy.observe(np.zeros((32, 3), np.float32), np.zeros(policy.contract.state_dim, np.float32))
        chunks.append(policy.act(seed=0))
    assert all(np.array_equal(c, chunks[0]) for c in chunks)
    assert OnnxPolicy(model_dir, threads=2, background_chunks=True).spinning is False  # the chunk's one thread
    rows = paths_and_threads(
        model_dir, "int8", 2, {"matrix_iterations": 2, "matrix_chunks": 1}, np.random.default_rng(0)
    )
    assert [(r["kernel"], r["threads"], r["spinning"]) for r in rows] == [
        ("fused", 1, False),
        ("fused", 2, True),
        ("fused", 2, False),
        ("standard", 1, False),
        ("standard", 2, True),
        ("standard", 2, False),
    ]


def test_chunk_flops_count_each_denoiser_blocks_mixer_and_mlp():
    from dssp_deploy.flops import attention_token_flops, chunk_flops, mamba_token_flops, mlp_token_flops

    cfg = {
        "d_model": 64,
        "d_state": 16,
        "expand": 2,
        "d_conv": 4,
        "n_denoiser_layers": 2,
        "horizon": 4,
        "action_dim": 2,
        "n_obs_steps": 2,
        "use_history": True,
        "use_recent_states": True,
        "timestep_decoupled": True,
    }
    k, tokens = 10, 3 + 10 * 4  # the prefix (c_t and 2 z) once, then K passes over H action tokens
    none = chunk_flops(cfg, k)
    assert chunk_flops({**cfg, "denoiser_mlp": "none"}, k) == none  # an export without the field: Mamba-only blocks
    gated = chunk_flops({**cfg, "denoiser_mlp": "gated"}, k)
    assert mlp_token_flops({**cfg, "denoiser_mlp": "gated"}) == 2 * 64 * 2 * 256 + 2 * 256 * 64  # hidden 8d/3 -> 256
    assert gated - none == 2 * tokens * mlp_token_flops({**cfg, "denoiser_mlp": "gated"})
    attention = chunk_flops({**cfg, "denoiser_backbone": "transformer"}, k)
    assert attention - none == 2 * tokens * (attention_token_flops(cfg, 3 + 2.5) - mamba_token_flops(cfg))


def test_the_effective_cache_is_the_largest_size_read_twice_as_fast_as_memory():
    from dssp_deploy.latency import effective_cache_bytes

    shared_vm = [(2, 64.0), (4, 75.0), (8, 78.0), (12, 37.0), (16, 23.0), (128, 21.0)]  # measured on a shared 32 MiB L3
    assert effective_cache_bytes(shared_vm) == 8 * 2**20
    assert effective_cache_bytes([(2, 30.0), (128, 25.0)]) is None  # nothing read faster than memory


def test_the_chunk_floor_takes_the_float32_peak_for_fp32_graphs_only(tiny_export, monkeypatch):
    """The floor: the weights' stream (the graph's own reads at the measured bandwidth) where they do not stay in the
    cache, and for an fp32 graph the float32 GEMM peak's compute too; an int8 graph's products are not bounded by it."""
    from dssp_deploy import profile

    _, model_dir, _ = tiny_export
    manifest = read_manifest(model_dir)
    monkeypatch.setattr(profile, "read_bandwidth_by_size", lambda: [(2, 100.0), (4, 20.0)])
    monkeypatch.setattr(profile, "effective_cache_bytes", lambda probe: 1)  # nothing stays in the cache
    monkeypatch.setattr(profile, "last_level_cache_bytes", lambda: 2**21)
    monkeypatch.setattr(profile, "memory_read_gbs", lambda: 10.0)
    flops, peak = 4 * 10**9, 100.0  # 40 ms at the peak
    for precision in ("fp32", "int8"):
        fmt = file_kind(precision, fused=True)
        f = profile.chunk_floor(model_dir, manifest, flops, peak, fmt)
        size = (model_dir / manifest.graphs["denoiser"]["files"][fmt]).stat().st_size
        stream = manifest.files[manifest.graphs["denoiser"]["files"][fmt]]["weight_reads"] * size / 10e9 * 1e3
        assert f["weight_stream_ms"] == pytest.approx(stream)
        if precision == "fp32":
            assert f["compute_ms"] == pytest.approx(40.0) and f["floor_ms"] == pytest.approx(max(40.0, stream))
        else:
            assert f["compute_ms"] is None and f["floor_ms"] == pytest.approx(stream)
