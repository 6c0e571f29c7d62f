"""Export to ONNX / TorchScript: parity, the manifest, metadata, bad input, variants, a torch-free runtime."""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from conftest import one_error_line

from dssp_deploy.mamba_kernel import STEP_OP
from dssp_deploy.manifest import read_manifest
from dssp_deploy.sessions import session_options
from dssp_train.cli.train import main as train_main
from dssp_train.config import apply_overrides, load_preset
from dssp_train.data.synthetic import write_tap_count_dataset
from dssp_train.model.policy import DSSPPolicy
from dssp_train.model.streaming import StreamingPolicy
from dssp_train.training import checkpoint as ckpt
from dssp_train.training.checkpoint import load_policy
from export import verify as verify_module
from export import verify_report
from export.to_onnx import export_model
from export.to_onnx import main as export_main
from export.verify import main as verify_main

SMALL = [
    "model.d_model=32",
    "model.d_state=8",
    "model.n_denoiser_layers=2",
    "train.batch_size=4",
    "train.val_windows=4",
    "train.warmup_steps=1",
]
ONNX_TYPES = {"tensor(float)": "float32"}
pytestmark = pytest.mark.filterwarnings("ignore:`torch.jit.load` is deprecated:DeprecationWarning")


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """Tiny tensors: one intra-op thread is fastest and does not stall on a busy machine."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def leftovers(folder: Path) -> list[str]:
    """Temporary directories an export may have left next to its output."""
    return [p.name for p in folder.iterdir() if ".partial-" in p.name or ".old-" in p.name]


def save_run(run_dir: Path, *overrides: str, seed: int = 0) -> Path:
    """A run directory with an untrained small policy (S = 3, A = 2), normalisers fitted on random data."""
    config = apply_overrides(load_preset("tiny"), [*SMALL, *overrides])
    config.model.state_dim, config.model.action_dim, config.model.n_points = 3, 2, 24
    torch.manual_seed(seed)
    policy = DSSPPolicy(config.model)
    with torch.no_grad():  # AdaLN is zero at init; make it matter, so folding it is tested
        for p in policy.denoiser.parameters():
            p.add_(0.02 * torch.randn_like(p))
    rng = np.random.default_rng(seed)
    policy.fit_normalizers(rng.normal(size=(8, 24, 3)), rng.normal(size=(50, 3)), rng.uniform(-2, 3, (50, 2)))
    run_dir.mkdir(parents=True)
    ckpt.save_config(run_dir, config)
    ckpt.save_tensors(run_dir / "model.safetensors", policy.state_dict(), {"step": "0"})
    return run_dir


# ------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def trained_run(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("trained")
    data = write_tap_count_dataset(root / "tap.zarr", 6, seed=0, n_points=24)
    args = ["--data", str(data), "--out", str(root / "run"), "--preset", "tiny", "--steps", "5", "--no-progress"]
    assert train_main(args + [a for item in SMALL for a in ("--set", item)]) == 0
    return root / "run"


@pytest.fixture(scope="module")
def exported(trained_run, tmp_path_factory) -> tuple[Path, dict]:
    """The trained run exported in every format (fused graphs, int8 and int4 included: the defaults), with the
    1000-step parity check."""
    out = tmp_path_factory.mktemp("models") / "tiny"
    summary = export_model(trained_run, out, verify_steps=1000, threads=1, progress=lambda _: None)
    return out, summary


# ---------------------------------------------------------------- happy path
def test_export_passes_parity_over_1000_steps(exported, trained_run):
    out, summary = exported
    report = summary["verification"]
    assert report["passed"] and report["steps"] == 1000 and report["chunk_ticks_total"] == 334
    assert (
        report["chunks"] == verify_module.CHUNKS and report["chunk_ticks"][0] == 0 and report["chunk_ticks"][-1] == 999
    )
    quantized = ["onnx_int8", "onnx_int8_fused", "onnx_int4", "onnx_int4_fused"]
    assert set(report["errors"]) == {"onnx", "onnx_fused", "torchscript"}
    assert sorted(report["streamed"]) == sorted(["onnx", "onnx_fused", *quantized])
    assert report["batch_checked"] == {"torchscript": [0, report["chunk_ticks"][4], 999]}
    for figures in report["errors"].values():
        assert all(value <= 1e-4 for value in figures.values() if value is not None), figures
    assert report["errors"]["torchscript"]["state"] is None  # checked through its c_t
    assert report["units"]["action"].startswith("normalised") and report["worst_at"]["backend"] in report["errors"]
    assert sorted(report["quantized"]) == sorted(quantized)
    for name, q in report["quantized"].items():  # each against the fp32 graphs of its own path, not bounded
        assert (
            q["against"] == ("onnx_fused" if name.endswith("_fused") else "onnx")
            and 0 < q["action_max_abs_vs_fp32"] < 1.0
        )
    manifest = read_manifest(out)
    assert manifest.verification["passed"]
    assert sorted(os.listdir(out)) == sorted(
        ["dssp_model.json", "history_step.pt", "denoiser.pt"]
        + [
            f"{g}{suffix}.onnx"
            for g in ("history_step", "denoiser")
            for suffix in ("", ".fused", ".int8", ".int8.fused", ".int4", ".int4.fused")
        ]
    )
    assert leftovers(out.parent) == []
    assert manifest.source.sha256 == verify_module.file_sha256(trained_run / "model.safetensors")
    # the run's identity, not where it lived on the training machine
    assert manifest.source.run == trained_run.name and "run_dir" not in manifest.data["source"]
    assert str(trained_run.parent) not in (out / "dssp_model.json").read_text()
    for name, info in manifest.files.items():
        assert info["bytes"] == (out / name).stat().st_size and info["sha256"] == verify_module.file_sha256(out / name)


def test_graphs_match_the_manifest_and_carry_metadata(exported):
    out, _ = exported
    manifest = read_manifest(out)
    m, c = manifest.model, manifest.contract
    assert c.denoise_steps == 10 and c.ddim_timesteps == [90, 80, 70, 60, 50, 40, 30, 20, 10, 0]
    assert (c.n_obs_steps, c.horizon, c.n_action_steps) == (2, 4, 3)
    assert c.control_rate_hz == 10.0
    assert set(manifest.normalizers) == {"point_cloud", "agent_pos", "action"}
    assert set(manifest.data["versions"]) >= {"dssp", "torch", "onnx", "onnxruntime"}
    assert manifest.history_state == ["conv_state_0", "ssm_state_0", "conv_state_1", "ssm_state_1"]
    # each fact once: the contract's fields are not repeated at the top or in model_config
    assert not set(manifest.data) & set(c.to_dict()) and not set(manifest.data["model_config"]) & set(c.model_fields())
    inner = 2 * m.d_model
    history_inputs = manifest.graphs["history_step"]["inputs"]
    assert history_inputs[2] == {"name": "conv_state_0", "shape": ["B", inner, 4], "dtype": "float32"}
    assert history_inputs[3] == {"name": "ssm_state_0", "shape": ["B", inner, m.d_state], "dtype": "float32"}
    for graph, spec in manifest.graphs.items():
        for kind in ("onnx", "onnx_int8", "onnx_int4", "onnx_fused", "onnx_int4_fused"):
            path = out / spec["files"][kind]
            onnx.checker.check_model(str(path), full_check=True)
            options = session_options(1, fused=kind.endswith("_fused"))
            session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
            for got, want in ((session.get_inputs(), spec["inputs"]), (session.get_outputs(), spec["outputs"])):
                assert [(g.name, g.shape, ONNX_TYPES[g.type]) for g in got] == [
                    (w["name"], w["shape"], w["dtype"]) for w in want
                ]
            props = {p.key: p.value for p in onnx.load(str(path), load_external_data=False).metadata_props}
            assert props["graph"] == graph and props["format_version"] == manifest.data["format_version"]
            assert props["source_sha256"] == manifest.source.sha256
            assert props["contract_sha256"] == c.digest() and "n_action_steps" not in props
            assert json.loads(props["inputs"]) == spec["inputs"]
    ops = {n.op_type for n in onnx.load(str(out / "history_step.onnx")).graph.node}
    assert "GlobalMaxPool" in ops and "ReduceMax" not in ops  # the fast form of the point max-pool
    # int8: the products quantized, Mamba's depthwise causal convolution kept fp32 (a full one would be ConvInteger)
    int8 = onnx.load(str(out / manifest.graphs["denoiser"]["files"]["onnx_int8"]))
    int8_ops = {n.op_type for n in int8.graph.node}
    assert "DynamicQuantizeMatMul" in int8_ops or "MatMulInteger" in int8_ops
    assert "Conv" in int8_ops and "ConvInteger" not in int8_ops
    assert "MatMul/Gemm weights" in {p.key: p.value for p in int8.metadata_props}["quantization"]


def test_batch_and_point_count_are_dynamic(exported, trained_run):
    """B = 3 and P = 17 (the graphs were traced with B = 2, P = 24): ORT and TorchScript match PyTorch."""
    out, _ = exported
    manifest = read_manifest(out)
    policy, _ = load_policy(trained_run)
    rng = np.random.default_rng(1)
    pc, pos = rng.normal(size=(3, 17, 3)).astype(np.float32), rng.uniform(0, 1, (3, 2)).astype(np.float32)
    noise = rng.standard_normal((3, 4, 2)).astype(np.float32)
    stream = StreamingPolicy(policy)
    stream.observe(pc, pos)
    want_chunk = stream.act(noise=noise)
    states = {
        s["name"]: np.zeros([3, *s["shape"][1:]], np.float32) for s in manifest.graphs["history_step"]["inputs"][2:]
    }
    feeds = {"point_cloud": pc, "agent_pos": pos, **states}
    history = ort.InferenceSession(str(out / "history_step.onnx"), providers=["CPUExecutionProvider"])
    z_t, c_t, *_ = history.run(None, feeds)
    denoiser = ort.InferenceSession(str(out / "denoiser.onnx"), providers=["CPUExecutionProvider"])
    chunk = denoiser.run(None, {"c_t": c_t, "z_recent": np.repeat(z_t[:, None], 2, axis=1), "noise": noise})[0]
    assert np.abs(c_t - stream.context.numpy()).max() <= 1e-4
    assert np.abs(chunk - want_chunk).max() <= 1e-4
    history_ts, denoiser_ts = (torch.jit.load(str(out / f"{g}.pt")) for g in ("history_step", "denoiser"))
    with torch.no_grad():
        ts_out = history_ts(*[torch.from_numpy(v) for v in feeds.values()])
        ts_chunk = denoiser_ts(ts_out[1], ts_out[0][:, None].repeat(1, 2, 1), torch.from_numpy(noise))
    assert torch.equal(ts_out[1], stream.context)
    assert np.abs(ts_chunk.numpy() - want_chunk).max() <= 1e-5


def test_graphs_run_where_torch_cannot_be_imported(exported, trained_run):
    out, _ = exported
    script = textwrap.dedent(
        f"""
        import sys
        sys.modules["torch"] = None  # any import of torch now fails
        import json
        import numpy as np
        import onnxruntime as ort
        from dssp_data.streaming_history import StreamingHistory
        try:
            import torch
        except ImportError:
            pass
        else:
            raise SystemExit("torch imported")
        model = {str(out)!r}
        manifest = json.load(open(model + "/dssp_model.json"))
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = 1
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
        graphs = {{g: ort.InferenceSession(model + "/" + s["files"]["onnx"], opts, providers=["CPUExecutionProvider"])
                  for g, s in manifest["graphs"].items()}}
        specs = manifest["graphs"]["history_step"]["inputs"][2:]

        def step(point_cloud, agent_pos, states):
            feeds = {{"point_cloud": point_cloud, "agent_pos": agent_pos, **dict(zip([s["name"] for s in specs], states))}}
            z_t, c_t, *states = graphs["history_step"].run(None, feeds)
            return z_t, c_t, states

        history = StreamingHistory(manifest["contract"]["n_obs_steps"], step, lambda ts: np.stack(ts, axis=1),
                                   lambda b: [np.zeros([b] + s["shape"][1:], np.float32) for s in specs])
        rng = np.random.default_rng(0)
        for t in range(5):
            history.observe(rng.normal(size=(1, 24, 3)).astype(np.float32), rng.uniform(size=(1, 2)).astype(np.float32))
        noise = rng.standard_normal((1, manifest["contract"]["horizon"], manifest["contract"]["action_dim"])).astype(np.float32)
        chunk = graphs["denoiser"].run(None, {{"c_t": history.context, "z_recent": history.recent, "noise": noise}})[0]
        print(json.dumps({{"chunk": chunk.tolist(), "torch_loaded": "torch" in sys.modules and sys.modules["torch"] is not None}}))
        """
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    got = json.loads(result.stdout)
    assert not got["torch_loaded"]

    policy, _ = load_policy(trained_run)
    stream = StreamingPolicy(policy)
    rng = np.random.default_rng(0)
    for _ in range(5):
        stream.observe(rng.normal(size=(1, 24, 3)).astype(np.float32), rng.uniform(size=(1, 2)).astype(np.float32))
    noise = rng.standard_normal((1, 4, 2)).astype(np.float32)
    assert np.abs(np.asarray(got["chunk"]) - stream.act(noise=noise)).max() <= 1e-4


# ------------------------------------------------------------------ variants
@pytest.mark.parametrize(
    "overrides",
    [["model.use_history=false"], ["model.timestep_decoupled=false"], ["model.use_recent_states=false"]],
    ids=["reactive-baseline", "no-timestep-decoupling", "no-recent-states"],
)
def test_variants_export_and_verify(tmp_path, overrides):
    run = save_run(tmp_path / "run", *overrides)
    summary = export_model(
        run, tmp_path / "model", fmt="onnx", quantize=(), verify_steps=60, threads=1, progress=lambda _: None
    )
    assert summary["verification"]["passed"] and set(summary["verification"]["errors"]) == {"onnx", "onnx_fused"}
    manifest = read_manifest(tmp_path / "model")
    names = lambda graph, io: [s["name"] for s in manifest.graphs[graph][io]]  # noqa: E731
    if "model.use_history=false" in overrides:
        assert names("history_step", "inputs") == ["point_cloud", "agent_pos"]
        assert names("history_step", "outputs") == ["z_t"]
        assert names("denoiser", "inputs") == ["z_recent", "noise"]
        assert manifest.history_state == []
    elif "model.use_recent_states=false" in overrides:
        assert names("denoiser", "inputs") == ["c_t", "noise"]
    else:
        assert names("denoiser", "inputs") == ["c_t", "z_recent", "noise"]
    assert sorted(os.listdir(tmp_path / "model")) == [
        "denoiser.fused.onnx",
        "denoiser.onnx",
        "dssp_model.json",
        "history_step.fused.onnx",
        "history_step.onnx",
    ]


@pytest.mark.parametrize("mlp", ["gated", "dit"])
def test_every_graph_reads_each_weight_once_per_ddim_step(tmp_path, mlp):
    """The first DDIM step carries the prefix, its mixer and its MLP in one pass with the action tokens: each weight
    matrix of the fp32 graphs (standard and fused) is read by K nodes, not K + 1, the manifest counts K, and the
    graphs still verify against PyTorch. A matrix is its values in either layout (the fused graph's DdimStep nodes
    take the action input layer's weight transposed, the first step's MatMul the exporter's copy), read by a product:
    a MatMul or Gemm, or a DdimStep's output layer, and its input layer where it makes the next step's tokens."""
    run = save_run(tmp_path / "run", f"model.denoiser_mlp={mlp}")
    summary = export_model(
        run, tmp_path / "model", fmt="onnx", quantize=(), verify_steps=60, threads=1, progress=lambda _: None
    )
    assert summary["verification"]["passed"]
    manifest = read_manifest(tmp_path / "model")
    steps = manifest.contract.denoise_steps
    assert steps > 1
    for name in ("denoiser.onnx", "denoiser.fused.onnx"):
        graph = onnx.load(str(tmp_path / "model" / name)).graph
        matrix = {}  # initializer name → its values, one layout for both
        for t in graph.initializer:
            if len(t.dims) == 2:
                a = onnx.numpy_helper.to_array(t)
                a = a if a.shape[0] <= a.shape[1] else a.T
                matrix[t.name] = (a.shape, a.tobytes())
        reads = dict.fromkeys(matrix.values(), 0)
        for node in graph.node:
            if node.op_type in ("MatMul", "Gemm"):
                products = list(node.input)
            elif node.op_type == STEP_OP:
                tokens = next((a.i for a in node.attribute if a.name == "tokens"), 1)
                products = [node.input[4]] + ([node.input[6]] if tokens else [])  # out_w, in_w
            else:
                continue
            for w in products:
                if w in matrix:
                    reads[matrix[w]] += 1
        counts = sorted(r for r in reads.values() if r)
        assert len(counts) >= 4 * 2 and set(counts) == {steps}, (name, counts)
        assert manifest.files[name]["weight_reads"] == steps
    fused = onnx.load(str(tmp_path / "model" / "denoiser.fused.onnx")).graph
    assert [n.op_type for n in fused.node].count(STEP_OP) == steps


def test_raw_weights_and_other_step_count(trained_run, tmp_path, capsys):
    out = tmp_path / "raw"
    args = [
        str(trained_run),
        "-o",
        str(out),
        "--no-ema",
        "--denoise-steps",
        "4",
        "--format",
        "torchscript",
        "--skip-verify",
    ]
    assert export_main(args) == 0
    manifest = read_manifest(out)
    assert manifest.source.weights == "checkpoint/model.safetensors" and not manifest.source.ema
    assert manifest.contract.ddim_timesteps == [75, 50, 25, 0] and manifest.verification is None
    assert sorted(os.listdir(out)) == ["denoiser.pt", "dssp_model.json", "history_step.pt"]
    assert verify_main([str(out), "--checkpoint", str(trained_run), "--steps", "30", "--threads", "1"]) == 0
    assert "PASS" in capsys.readouterr().out


def test_float64_check_measures_distances_to_float64_in_normalised_units(tmp_path):
    """Chunks above the bound are re-evaluated in float64 on each one's own inputs: PyTorch's and each
    graph's distance to it, in normalised action units (raw error times the normaliser's scale)."""
    policy, _ = load_policy(save_run(tmp_path / "run"))
    rng = np.random.default_rng(0)
    context, recent = rng.normal(size=(1, 32)).astype(np.float32), rng.normal(size=(1, 2, 32)).astype(np.float32)
    other = recent + np.float32(0.5)  # the graph's own inputs differ from the reference's
    noise = rng.standard_normal((1, 4, 2)).astype(np.float32)
    with torch.no_grad():
        exact = {}
        for name, r in (("torch", recent), ("onnx", other)):
            prefix = policy.double().build_prefix(torch.from_numpy(context).double(), torch.from_numpy(r).double())
            x = policy.sample_normalized(prefix, torch.from_numpy(noise).double(), 10)
            exact[name] = policy.normalizers["action"].unnormalize(x).numpy()
        policy.float()
    scale = policy.normalizers["action"].scale.numpy().astype(np.float64)  # (A,)
    flagged = [
        {
            "step": 6,
            "inputs": {"torch": (context, recent, noise), "onnx": (context, other, noise)},
            "chunks": {"torch": exact["torch"] + 3e-4, "onnx": exact["onnx"] - 5e-3},
        }
    ]
    check = verify_module._float64_check(policy, 10, scale, flagged)
    assert check["chunks_checked"] == 1 and check["steps"] == [6] and check["units"].startswith("normalised")
    assert check["torch_fp32_vs_float64"] == pytest.approx(3e-4 * scale.max(), rel=1e-3)
    assert check["graphs_vs_float64"]["onnx"] == pytest.approx(5e-3 * scale.max(), rel=1e-3)


def test_action_errors_are_judged_in_normalised_units():
    """A raw error of 4.4e-4 on a channel spanning [-12, 12] is 3.7e-5 normalised units: within the bound."""
    scale = np.array([2 / 24, 2 / 2])  # the action normaliser: [-12, 12] and [-1, 1] → [-1, 1]
    got, want = np.zeros((3, 1, 4, 2)), np.zeros((3, 1, 4, 2))
    got[1, 0, 2, 0] = 4.4e-4  # the wide channel
    got[2, 0, 1, 1] = 2e-5  # the narrow one
    value, index = verify_module.worst(got, want, scale)
    assert value == pytest.approx(4.4e-4 / 12) and index == (1, 0, 2, 0)
    assert verify_module.worst(got, want * np.nan, scale) == (float("inf"), (0, 0, 0, 0))
    assert verify_module.chunk_ticks(1000, 6, 4) == ([0, 330, 666, 996], 167)
    assert verify_module.chunk_ticks(10, 3, 0) == ([0, 3, 6, 9], 4)


def fake_report(torch64: float, graph64: float) -> dict:
    errors = {"onnx": {"z_t": 1e-6, "c_t": 2e-6, "state": 1e-6, "action": 4.4e-4}}
    return {
        "passed": False,
        "bound": 1e-4,
        "worst": 4.4e-4,
        "errors": errors,
        "worst_at": {"backend": "onnx", "figure": "action", "step": 417, "horizon": 2, "channel": 3},
        "action_float64_check": {
            "chunks_checked": 1,
            "steps": [417],
            "torch_fp32_vs_float64": torch64,
            "graphs_vs_float64": {"onnx": graph64},
        },
    }


def test_the_failure_says_what_it_measured():
    with pytest.raises(verify_module.ParityError) as info:
        verify_report.check_report(fake_report(6.8e-5, 4.4e-4))
    message = str(info.value)
    assert message.startswith(
        "onnx action differs from PyTorch fp32 by 4.40e-04 normalised action units at step 417, "
        "horizon 2, action channel 3, above the bound 0.0001; "
    )
    assert "PyTorch fp32 is 6.8e-05 away and onnx 4.4e-04 (6.5x): the exported graph loses precision" in message
    assert "alike" not in message and "\n" not in message
    with pytest.raises(
        verify_module.ParityError, match=r"\(1\.1x\): the model amplifies fp32 rounding as much in PyTorch"
    ):
        verify_report.check_report(fake_report(4.0e-4, 4.4e-4))


# ---------------------------------------------------------------- bad input
def test_parity_failure_exits_1_and_leaves_nothing(trained_run, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(verify_module, "BOUND", 0.0)
    out = tmp_path / "models" / "fails"
    fp32_standard = ["--format", "onnx", "--quantize", "none", "--no-fused", "--threads", "1"]
    assert export_main([str(trained_run), "-o", str(out), *fp32_standard, "--verify-steps", "10"]) == 1
    line = one_error_line(capsys.readouterr().err)
    assert "differs from PyTorch fp32 by" in line and "above the bound 0;" in line and " at step " in line
    assert "nothing was written" in line
    assert not out.exists() and not (tmp_path / "models").exists()


def corrupt_weights(run: Path) -> None:
    (run / "model.safetensors").write_bytes(b"\x00" * 64)


def wrong_config(run: Path) -> None:
    data = json.loads((run / "config.json").read_text())
    data["model"]["d_model"] = 48
    (run / "config.json").write_text(json.dumps(data))


def remove_config(run: Path) -> None:
    (run / "config.json").unlink()


@pytest.mark.parametrize(
    "damage, extra, message",
    [
        (remove_config, [], "is not a DSSP run directory"),
        (corrupt_weights, [], "is not a readable safetensors file"),
        (wrong_config, [], "does not fit its config"),
        (None, ["--opset", "11"], "--opset 11 is not supported; use 17..20"),
        (None, ["--denoise-steps", "101"], "--denoise-steps must be in [1, 100]"),
        (None, ["--no-ema"], "drop --no-ema"),  # saved by hand: no checkpoint/ folder
    ],
    ids=["missing-config", "corrupt-weights", "config-mismatch", "opset", "denoise-steps", "no-checkpoint"],
)
def test_bad_run_directory_or_option(tmp_path, capsys, damage, extra, message):
    run = save_run(tmp_path / "run")
    if damage is not None:
        damage(run)
    out = tmp_path / "out" / "model"
    assert export_main([str(run), "-o", str(out), "--skip-verify", *extra]) == 2
    assert message in one_error_line(capsys.readouterr().err)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "prefix, value",
    [("history_encoder.", float("nan")), ("denoiser.", float("inf")), ("normalizers.action.", float("-inf"))],
    ids=["nan", "inf", "normaliser"],
)
def test_non_finite_weights_are_named_and_nothing_is_written(tmp_path, capsys, prefix, value):
    from safetensors import safe_open
    from safetensors.torch import load_file, save_file

    run = save_run(tmp_path / "run")
    weights = run / "model.safetensors"
    with safe_open(str(weights), "pt") as f:
        metadata = f.metadata()
    tensors = load_file(str(weights))
    name = next(k for k in sorted(tensors) if k.startswith(prefix) and tensors[k].is_floating_point())
    tensors[name].view(-1)[-1] = value
    save_file(tensors, str(weights), metadata=metadata)
    before = sorted(p.name for p in tmp_path.iterdir())
    out = tmp_path / "out" / "model"
    assert export_main([str(run), "-o", str(out), "--skip-verify"]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert f"tensor {name} [" in line and "holds 1 non-finite value(s)" in line and "nothing was exported" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == before and leftovers(tmp_path) == []


def test_missing_run_directory(tmp_path, capsys):
    assert export_main([str(tmp_path / "nowhere"), "-o", str(tmp_path / "model")]) == 2
    assert "run directory" in one_error_line(capsys.readouterr().err) and not (tmp_path / "model").exists()


def test_unsupported_history_variant(tmp_path, capsys):
    run = save_run(tmp_path / "run", 'model.history_backbone="transformer"')
    assert export_main([str(run), "-o", str(tmp_path / "model")]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert "history_backbone=transformer" in line and "export supports the Mamba history encoder" in line
    assert leftovers(tmp_path) == [] and not (tmp_path / "model").exists()


def test_output_path_rules(tmp_path, capsys):
    run = save_run(tmp_path / "run")
    fast = ["--format", "onnx", "--skip-verify", "--quantize", "none", "--no-fused"]
    (tmp_path / "a_file").write_text("x")
    assert export_main([str(run), "-o", str(tmp_path / "a_file" / "model"), *fast]) == 2
    assert "is a file, not a folder" in one_error_line(capsys.readouterr().err)

    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("keep me")
    assert export_main([str(run), "-o", str(other), "--force", *fast]) == 2
    assert "is not a DSSP model directory" in one_error_line(capsys.readouterr().err)
    assert (other / "notes.txt").read_text() == "keep me"

    model = tmp_path / "model"
    assert export_main([str(run), "-o", str(model), *fast]) == 0
    first = read_manifest(model).files
    assert export_main([str(run), "-o", str(model), *fast]) == 2
    assert "pass --force" in one_error_line(capsys.readouterr().err)
    assert (
        export_main(
            [
                str(run),
                "-o",
                str(model),
                "--force",
                "--format",
                "both",
                "--skip-verify",
                "--quantize",
                "none",
                "--no-fused",
            ]
        )
        == 0
    )
    assert set(read_manifest(model).files) == set(first) | {"history_step.pt", "denoiser.pt"}
    assert leftovers(tmp_path) == []


def test_verify_bad_input(exported, tmp_path, capsys):
    out, _ = exported
    assert verify_main([str(tmp_path / "nothing"), "--checkpoint", str(tmp_path)]) == 2
    assert "does not exist" in one_error_line(capsys.readouterr().err)
    other = save_run(tmp_path / "other")
    assert verify_main([str(out), "--checkpoint", str(other), "--steps", "5"]) == 2
    assert "is not the checkpoint this model was exported from" in one_error_line(capsys.readouterr().err)
