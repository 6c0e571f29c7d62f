"""The fused Mamba operators (dssp_deploy/kernel): each implementation against PyTorch, and the runtime's
choice between the fused and the standard graphs (used when present, a clean fallback when not)."""

import json
import shutil

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from conftest import BLOCK_INPUTS, QGEMM_X86_PATHS, block_case, cpu_flags
from onnx import TensorProto, helper

from dssp_deploy import mamba_kernel
from dssp_deploy.manifest import MANIFEST_NAME, ModelDirError, read_manifest, sha256_hex
from dssp_deploy.onnx_policy import DEFAULT_PRECISION, OnnxPolicy
from dssp_deploy.sessions import session_options
from dssp_train.model.mamba import causal_conv
from dssp_train.model.selective_scan import linear_scan_unrolled, selective_scan

IMPLEMENTATIONS = ["avx512", "avx2", "portable"]


QGEMM_PATHS = ["portable", *QGEMM_X86_PATHS]  # dssp_deploy/kernel/qgemm.h's x86 paths


def qgemm_runs(path: str) -> bool:
    """Whether this CPU has the instructions of a qgemm path."""
    return path == "portable" or QGEMM_X86_PATHS[path] <= cpu_flags()


def cpu_runs(implementation: str) -> bool:
    """Whether this CPU has the instructions of a scan implementation."""
    return {"avx512": {"avx512f", "avx2", "fma"}, "avx2": {"avx2", "fma"}, "portable": set()}[
        implementation
    ] <= cpu_flags()


@pytest.fixture(scope="module", autouse=True)
def built_kernel():
    found = mamba_kernel.kernel()
    assert found.available, (
        f"the fused Mamba kernel is not built here ({found.reason}); run `make kernel` (make setup does)"
    )
    return found


def op_session(
    op: str,
    inputs: list[str],
    outputs: list[str],
    implementation: str,
    monkeypatch,
    threads: int | None = None,
    **attributes,
):
    """A one-node graph of ``ai.dssp::op`` with ``attributes`` (its implementation chosen by DSSP_SCAN_PATH when the
    session is made)."""
    monkeypatch.setenv("DSSP_SCAN_PATH", implementation)
    graph = helper.make_graph(
        [helper.make_node(op, inputs, outputs, domain=mamba_kernel.DOMAIN, **attributes)],
        "g",
        [helper.make_tensor_value_info(n, TensorProto.FLOAT, None) for n in inputs],
        [helper.make_tensor_value_info(n, TensorProto.FLOAT, None) for n in outputs],
    )
    model = helper.make_model(
        graph, opset_imports=[helper.make_opsetid("", 17), helper.make_opsetid(mamba_kernel.DOMAIN, 1)]
    )
    return ort.InferenceSession(
        model.SerializeToString(), session_options(threads, fused=True), providers=["CPUExecutionProvider"]
    )


# batch, tokens, channels E, state n: the model's shapes, and odd ones (n and E not multiples of 8, one token with
# n a multiple of 8 but not of 16)
SCAN_SHAPES = [(1, 8, 64, 16), (2, 3, 40, 12), (1, 1, 1024, 64), (2, 1, 40, 24), (3, 5, 20, 5)]


def scan_feeds(rng, b: int, length: int, e: int, n: int) -> dict[str, np.ndarray]:
    """Random SelectiveScan inputs (batch b, L = length, E = e, n), float32: dt around softplus's bend, A negative."""
    f32 = lambda *s, scale=1.0, shift=0.0: (rng.standard_normal(s) * scale + shift).astype(np.float32)  # noqa: E731
    return {
        "x": f32(b, length, e),
        "dt": f32(b, length, e, scale=2.0, shift=-3.0),
        "B": f32(b, length, n),
        "C": f32(b, length, n),
        "z": f32(b, length, e, scale=3.0),
        "A": -np.exp(rng.uniform(0, np.log(n), (e, n))).astype(np.float32),
        "D": f32(e),
        "h0": f32(b, e, n),
    }


@pytest.mark.parametrize("implementation", IMPLEMENTATIONS)
@pytest.mark.parametrize("shape", SCAN_SHAPES, ids=lambda s: "x".join(map(str, s)))
def test_selective_scan_matches_pytorch(implementation, shape, monkeypatch):
    b, length, e, n = shape
    feeds = scan_feeds(np.random.default_rng(sum(shape)), b, length, e, n)
    feeds["dt"][0, 0, :3] = [25.0, -40.0, 0.0]  # softplus's linear branch, its far tail, its middle
    if not cpu_runs(implementation):  # asking for it is a one-line error, not a crash or a silent fallback
        with pytest.raises(Exception, match=f"DSSP_SCAN_PATH={implementation}, but this CPU lacks"):
            op_session(mamba_kernel.SCAN_OP, list(feeds), ["y", "h"], implementation, monkeypatch)
        return
    session = op_session(mamba_kernel.SCAN_OP, list(feeds), ["y", "h"], implementation, monkeypatch)
    assert mamba_kernel.kernel().implementation == implementation
    y, h = session.run(None, feeds)
    t = {k: torch.from_numpy(v).double() for k, v in feeds.items()}
    y_ref, h_ref = selective_scan(
        t["x"], t["dt"], t["B"], t["C"], t["z"], t["A"], t["D"], t["h0"], linear_scan_unrolled
    )
    assert y.shape == (b, length, e) and h.shape == (b, e, n)
    assert np.abs(y - y_ref.numpy()).max() <= 2e-6 * max(1.0, float(y_ref.abs().max()))
    assert np.abs(h - h_ref.numpy()).max() <= 2e-6 * max(1.0, float(h_ref.abs().max()))


@pytest.mark.parametrize(
    "shape", [(1, 8, 1024, 4), (2, 3, 40, 4), (1, 1, 24, 4), (2, 6, 20, 3)], ids=lambda s: "x".join(map(str, s))
)
def test_causal_conv_matches_pytorch(shape, monkeypatch):
    b, length, e, w = shape
    rng = np.random.default_rng(sum(shape))
    feeds = {
        "x": rng.standard_normal((b, length, e)).astype(np.float32),
        "state": rng.standard_normal((b, e, w)).astype(np.float32),
        "weight": rng.standard_normal((w, e)).astype(np.float32),
        "bias": rng.standard_normal(e).astype(np.float32),
    }
    session = op_session(mamba_kernel.CONV_OP, list(feeds), ["y", "new_state"], "auto", monkeypatch)
    y, new_state = session.run(None, feeds)
    t = {k: torch.from_numpy(v).double() for k, v in feeds.items()}
    y_ref, state_ref = causal_conv(t["x"], t["state"], t["weight"].t().unsqueeze(1), t["bias"])
    assert np.abs(y - y_ref.numpy()).max() <= 1e-5 and np.array_equal(new_state, state_ref.numpy().astype(np.float32))


@pytest.mark.parametrize("implementation", [i for i in IMPLEMENTATIONS if cpu_runs(i)])  # the others: refused above
def test_the_state_after_a_prefix_comes_from_a_pass_over_more_tokens(implementation, monkeypatch):
    """The attribute state_at: the scan's and the conv's state out is the one after the first state_at tokens (the
    prefix's, in a pass over [prefix, action tokens]); the outputs over all tokens are unchanged. A state_at beyond the
    tokens is a one-line error."""
    b, length, e, n, w, at = 2, 7, 40, 12, 4, 3
    rng = np.random.default_rng(7)
    scan = scan_feeds(rng, b, length, e, n)
    conv = {
        k: rng.standard_normal(s).astype(np.float32)
        for k, s in (("x", (b, length, e)), ("state", (b, e, w)), ("weight", (w, e)), ("bias", (e,)))
    }
    t = {k: torch.from_numpy(v).double() for k, v in scan.items()}
    args = (t["x"], t["dt"], t["B"], t["C"], t["z"], t["A"], t["D"], t["h0"], linear_scan_unrolled)
    for op, feeds, outputs in ((mamba_kernel.SCAN_OP, scan, ["y", "h"]), (mamba_kernel.CONV_OP, conv, ["y", "s"])):
        whole = op_session(op, list(feeds), outputs, implementation, monkeypatch).run(None, feeds)
        y, state = op_session(op, list(feeds), outputs, implementation, monkeypatch, state_at=at).run(None, feeds)
        assert np.array_equal(y, whole[0]), op
        if op == mamba_kernel.SCAN_OP:
            reference = selective_scan(*args, state_at=at)[1].numpy()
            head = selective_scan(*(a[:, :at] for a in args[:5]), *args[5:])[1].numpy()  # the prefix alone
            assert np.abs(reference - head).max() <= 1e-12
            assert np.abs(state - reference).max() <= 2e-6 * max(1.0, float(np.abs(reference).max()))
            assert np.abs(whole[1] - reference).max() > 1e-3  # the state after all tokens differs: a real check
        else:
            reference = causal_conv(
                *(torch.from_numpy(conv[k]) for k in ("x", "state")),
                torch.from_numpy(conv["weight"]).t().unsqueeze(1),
                torch.from_numpy(conv["bias"]),
                state_at=at,
            )[1].numpy()
            assert np.array_equal(state, reference) and np.array_equal(reference[:, :, -1], conv["x"][:, at - 1])
        too_far = op_session(op, list(feeds), outputs, implementation, monkeypatch, state_at=length + 1)
        with pytest.raises(Exception, match=f"state_at = {length + 1} tokens, but the input has {length}"):
            too_far.run(None, feeds)


def test_a_wrong_shape_is_an_error_not_a_crash(monkeypatch):
    session = op_session(
        mamba_kernel.SCAN_OP, ["x", "dt", "B", "C", "z", "A", "D", "h0"], ["y", "h"], "auto", monkeypatch
    )
    z = lambda *s: np.zeros(s, np.float32)  # noqa: E731
    with pytest.raises(Exception, match="SelectiveScan: h0 has shape \\(1, 8, 3\\), expected \\(1, 8, 4\\)"):
        session.run(
            None,
            {
                "x": z(1, 2, 8),
                "dt": z(1, 2, 8),
                "B": z(1, 2, 4),
                "C": z(1, 2, 4),
                "z": z(1, 2, 8),
                "A": z(8, 4),
                "D": z(8),
                "h0": z(1, 8, 3),
            },
        )
    conv = op_session(mamba_kernel.CONV_OP, ["x", "state", "weight", "bias"], ["y", "new_state"], "auto", monkeypatch)
    with pytest.raises(Exception, match="CausalConv1d: bias has shape \\(7\\), expected \\(8\\)"):  # its own name
        conv.run(None, {"x": z(1, 2, 8), "state": z(1, 8, 4), "weight": z(4, 8), "bias": z(7)})


# ------------------------------------------------------------ the runtime's choice
def run_chunk(policy: OnnxPolicy, data_seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(data_seed)
    for _ in range(7):
        policy.observe(*policy.example_observation(rng, 32))  # inside the trained ranges (others are refused)
    return policy.act(seed=0)


def test_fused_graphs_run_by_default_and_match_the_standard_ones(tiny_export, monkeypatch):
    _, model_dir, _ = tiny_export
    monkeypatch.delenv("DSSP_SCAN_PATH", raising=False)  # the default (auto), whatever path the suite forces
    default = OnnxPolicy(model_dir, threads=1)
    assert default.kernel == "fused" and default.precision == DEFAULT_PRECISION
    widest = next(i for i in IMPLEMENTATIONS if cpu_runs(i))  # auto: the widest this CPU runs
    assert default.kernel_note == f"{DEFAULT_PRECISION}, fused Mamba kernel ({widest}, libdssp_mamba.so)"
    fused, standard = (
        OnnxPolicy(model_dir, threads=1, precision="fp32"),
        OnnxPolicy(model_dir, threads=1, precision="fp32", kernel="standard"),
    )
    assert fused.kernel == "fused" and standard.kernel_note == "fp32, standard ONNX graphs (asked for)"
    assert np.abs(run_chunk(fused) - run_chunk(standard)).max() <= 1e-4
    for implementation in [
        i for i in IMPLEMENTATIONS if i != widest and cpu_runs(i)
    ]:  # the others, through the whole runtime
        monkeypatch.setenv("DSSP_SCAN_PATH", implementation)
        other = OnnxPolicy(model_dir, threads=1, precision="fp32")
        assert other.kernel_note == f"fp32, fused Mamba kernel ({implementation}, libdssp_mamba.so)"
        assert np.abs(run_chunk(other) - run_chunk(standard)).max() <= 1e-4


def test_action_token_scans_do_not_write_the_state_nobody_reads(tiny_export, monkeypatch):
    """Export marks the denoiser's action-token scans state_out = 0 (all but the first step's, which carries the prefix
    and gives its state after it: state_at); the kernel then returns an empty state."""
    _, model_dir, _ = tiny_export
    manifest = json.loads((model_dir / MANIFEST_NAME).read_text())
    scans = [
        n
        for n in onnx.load(str(model_dir / manifest["graphs"]["denoiser"]["files"]["onnx_fused"])).graph.node
        if n.op_type == mamba_kernel.SCAN_OP
    ]
    marked = [n for n in scans if any(a.name == "state_out" and a.i == 0 for a in n.attribute)]
    layers = manifest["model_config"]["n_denoiser_layers"]
    m = manifest["model_config"]
    prefix = int(m["use_history"]) + int(m["use_recent_states"]) * manifest["contract"]["n_obs_steps"]
    first = [
        n for n in scans if n not in marked
    ]  # the first step's, over [prefix, actions]: the prefix's state is read
    assert len(scans) == len(manifest["contract"]["ddim_timesteps"]) * layers and len(first) == layers
    assert all({a.name: a.i for a in n.attribute} == {"state_at": prefix} for n in first), first
    history = onnx.load(str(model_dir / manifest["graphs"]["history_step"]["files"]["onnx_fused"])).graph.node
    assert not any(
        a.name == "state_out" for n in history for a in n.attribute
    )  # the history step's state is its output

    names = ["x", "dt", "B", "C", "z", "A", "D", "h0"]
    rng = np.random.default_rng(0)
    feeds = {
        "x": rng.normal(size=(1, 4, 16)),
        "dt": rng.normal(size=(1, 4, 16)),
        "B": rng.normal(size=(1, 4, 8)),
        "C": rng.normal(size=(1, 4, 8)),
        "z": rng.normal(size=(1, 4, 16)),
        "A": -rng.uniform(0.5, 4, (16, 8)),
        "D": rng.normal(size=16),
        "h0": rng.normal(size=(1, 16, 8)),
    }
    feeds = {k: v.astype(np.float32) for k, v in feeds.items()}
    graph = helper.make_graph(
        [helper.make_node(mamba_kernel.SCAN_OP, names, ["y", "h"], domain=mamba_kernel.DOMAIN, state_out=0)],
        "g",
        [helper.make_tensor_value_info(n, TensorProto.FLOAT, None) for n in names],
        [helper.make_tensor_value_info(n, TensorProto.FLOAT, None) for n in ("y", "h")],
    )
    model = helper.make_model(
        graph, opset_imports=[helper.make_opsetid("", 17), helper.make_opsetid(mamba_kernel.DOMAIN, 1)]
    )
    for implementation in [i for i in IMPLEMENTATIONS if cpu_runs(i)]:
        monkeypatch.setenv("DSSP_SCAN_PATH", implementation)
        y, h = ort.InferenceSession(
            model.SerializeToString(), session_options(1, fused=True), providers=["CPUExecutionProvider"]
        ).run(None, feeds)
        y_full, _ = op_session(mamba_kernel.SCAN_OP, names, ["y", "h"], implementation, monkeypatch).run(None, feeds)
        assert h.shape == (1, 0, 8) and np.array_equal(y, y_full)


def test_a_missing_or_broken_library_falls_back_to_the_standard_graphs(tiny_export, tmp_path, monkeypatch):
    _, model_dir, _ = tiny_export
    want = run_chunk(OnnxPolicy(model_dir, threads=1, kernel="standard"))  # int8, the default precision
    broken = tmp_path / "libdssp_mamba.so"
    broken.write_bytes(b"\x7fELF not really a library")
    older = tmp_path / "older.so"  # a library built before the operators knew what this runtime's graphs ask of them
    shutil.copy(mamba_kernel.kernel().path, older)
    monkeypatch.setattr(mamba_kernel, "KERNEL_REVISION", mamba_kernel.KERNEL_REVISION + 1)
    for library, reason in (
        (tmp_path / "missing.so", "is missing (build it with `make kernel`)"),
        (broken, "failed to load"),
        (older, f"is older than this runtime (revision {mamba_kernel.KERNEL_REVISION - 1}, "),
    ):
        monkeypatch.setenv(mamba_kernel.LIBRARY_ENV, str(library))
        policy = OnnxPolicy(model_dir, threads=1)
        assert policy.kernel == "standard" and reason in policy.kernel_note and "\n" not in policy.kernel_note
        assert np.array_equal(run_chunk(policy), want)
        with pytest.raises(ModelDirError, match="kernel fused: the fused Mamba kernel is unavailable") as err:
            OnnxPolicy(model_dir, threads=1, kernel="fused")
        assert "\n" not in str(err.value)
    monkeypatch.setenv(mamba_kernel.LIBRARY_ENV, "off")
    assert OnnxPolicy(model_dir, threads=1).kernel_note == (
        f"{DEFAULT_PRECISION}, standard ONNX graphs (the fused Mamba kernel is unavailable: DSSP_KERNEL=off)"
    )


def test_a_model_without_fused_graphs_runs_the_standard_ones(tiny_export, tmp_path):
    _, model_dir, _ = tiny_export
    plain = tmp_path / "model"
    shutil.copytree(model_dir, plain)
    manifest = json.loads((plain / MANIFEST_NAME).read_text())
    for spec in manifest["graphs"].values():  # as exported with --no-fused, or where the kernel was not built
        spec["files"] = {kind: name for kind, name in spec["files"].items() if not kind.endswith("_fused")}
    (plain / MANIFEST_NAME).write_text(json.dumps(manifest))
    policy = OnnxPolicy(plain, threads=1)
    assert policy.kernel == "standard" and f"has no {DEFAULT_PRECISION} fused graphs" in policy.kernel_note
    with pytest.raises(ModelDirError, match="has no int4 fused graphs"):
        OnnxPolicy(plain, threads=1, precision="int4", kernel="fused")


def test_a_fused_graph_the_runtime_cannot_load_falls_back(tiny_export, tmp_path):
    """A library without the operators a graph names (an older build): the session fails, the standard graphs run."""
    _, model_dir, _ = tiny_export
    model = tmp_path / "model"
    shutil.copytree(model_dir, model)
    manifest = json.loads((model / MANIFEST_NAME).read_text())
    name = manifest["graphs"]["denoiser"]["files"]["onnx_fused"]
    graph = onnx.load(str(model / name))
    for node in graph.graph.node:
        if node.op_type == "SelectiveScan":
            node.op_type = "SelectiveScanV9"
    data = graph.SerializeToString()
    (model / name).write_bytes(data)
    manifest["files"][name].update(bytes=len(data), sha256=sha256_hex(data))
    (model / MANIFEST_NAME).write_text(json.dumps(manifest))
    policy = OnnxPolicy(model, threads=1, precision="fp32")
    assert policy.kernel == "standard" and policy.kernel_note.startswith(
        "fp32, standard ONNX graphs (the fused graphs failed to load:"
    )
    with pytest.raises(ModelDirError, match="could not be loaded by ONNX Runtime") as err:
        OnnxPolicy(model, threads=1, precision="fp32", kernel="fused")
    assert "\n" not in str(err.value)


# ------------------------------------------------------------ a whole denoiser block, int8
def block_session(values: dict, eps: float, threads: int = 1, state_out: int = 0, plain: int = 0):
    """A one-node graph of ``ai.dssp::MambaBlockQ8``, the weights as initializers (as an exported graph has them)."""
    feeds = ["a", "conv_state", "ssm_state", "mod"]
    initializers = [
        onnx.numpy_helper.from_array(values[name].numpy(), name) for name in BLOCK_INPUTS if name not in feeds
    ]
    node = helper.make_node(
        mamba_kernel.BLOCK_OP,
        BLOCK_INPUTS,
        ["out", "conv", "ssm"],
        domain=mamba_kernel.DOMAIN,
        eps=eps,
        state_out=state_out,
        plain=plain,
    )
    graph = helper.make_graph(
        [node],
        "g",
        [helper.make_tensor_value_info(n, TensorProto.FLOAT, None) for n in feeds],
        [helper.make_tensor_value_info(n, TensorProto.FLOAT, None) for n in ("out", "conv", "ssm")],
        initializer=initializers,
    )
    model = helper.make_model(
        graph, opset_imports=[helper.make_opsetid("", 17), helper.make_opsetid(mamba_kernel.DOMAIN, 1)]
    )
    session = ort.InferenceSession(
        model.SerializeToString(), session_options(threads, fused=True), providers=["CPUExecutionProvider"]
    )
    return session, {name: values[name].numpy() for name in feeds}


@pytest.mark.parametrize(
    "mlp, batch, part",
    [
        ("gated", 1, "actions"),
        ("gated", 2, "actions"),
        ("none", 1, "actions"),
        ("gated", 2, "prefix"),
        ("gated", 2, "joint"),
        ("gated", 2, "joint, state out"),
    ],
)
def test_a_whole_int8_block_matches_its_pytorch_reference(mlp, batch, part, monkeypatch):
    """One denoiser block: the operator against ``export.fused_ops.block_reference`` (the same per-row quantization,
    the integer sums exact) on the action tokens (AdaLN, from a prefix's state), on the prefix (no AdaLN, from
    zeros, its state out) and on both in one pass (the first 3 tokens plain; with the state out, the state after
    them: what the prefix alone gives), on every scan path and thread count; every qgemm path this CPU runs gives the
    same result bit for bit (their integer sums are exact and their epilogue the same)."""
    from export.fused_ops import block_reference

    fused, values = block_case(mlp, batch)
    state_out, plain = int(part in ("prefix", "joint, state out")), 3 if part.startswith("joint") else 0
    if part == "prefix":  # from zeros given, and from zeros as the exported graphs say it (empty states)
        values.update(
            conv_state=torch.zeros_like(values["conv_state"]), ssm_state=torch.zeros_like(values["ssm_state"])
        )
        values.update(mod=torch.zeros(0, values["a"].shape[-1]))
    if plain:
        values.update(conv_state=values["conv_state"][:, :0], ssm_state=values["ssm_state"][:, :0])
    with torch.no_grad():
        want = [t.numpy() for t in block_reference(*values.values(), fused.eps, plain)]
        if plain and state_out:  # the reference's states after the prefix: those of the prefix alone
            alone = {**values, "a": values["a"][:, :plain], "mod": values["mod"][:0]}
            _, conv, ssm = block_reference(*alone.values(), fused.eps, 0)
            assert np.array_equal(conv.numpy(), want[1]) and np.allclose(ssm.numpy(), want[2], rtol=0, atol=1e-6)
    if not state_out:
        want = [want[0], want[1][:, :0], want[2][:, :0]]
    outputs = {}
    for scan in [i for i in IMPLEMENTATIONS if cpu_runs(i)]:
        for threads in (1, 2):
            monkeypatch.setenv("DSSP_SCAN_PATH", scan)
            session, feeds = block_session(values, fused.eps, threads, state_out, plain)
            got = session.run(None, feeds)
            for g, w in zip(got, want):
                assert g.shape == w.shape
                assert np.abs(g - w).max(initial=0) <= 1e-3 * np.abs(w).max(initial=1), (scan, threads)
            outputs[(scan, threads)] = got
    monkeypatch.setenv("DSSP_SCAN_PATH", "portable")
    reference = outputs[("portable", 1)]
    for path in QGEMM_PATHS:
        monkeypatch.setenv("DSSP_QGEMM_PATH", path)
        if not qgemm_runs(path):
            with pytest.raises(Exception, match=path):
                block_session(values, fused.eps, 1, state_out, plain)[0].run(None, feeds)
            continue
        session, feeds = block_session(values, fused.eps, 1, state_out, plain)
        for g, r in zip(session.run(None, feeds), reference):
            assert np.array_equal(g, r), path


def test_the_int8_fused_denoiser_runs_each_block_as_one_node(tiny_export):
    """The int8 fused denoiser: every block one MambaBlockQ8 node at each DDIM step, the first step's with the
    prefix's tokens plain and its state out (the prefix needs no pass of its own: K reads of the weights, not K + 1,
    as the manifest counts them), the blocks' weights stored once (int8, read by the K steps alike), and its chunks
    as close to the fp32 graphs' as the standard int8 graphs' are."""
    from collections import Counter

    _, model_dir, _ = tiny_export
    manifest = json.loads((model_dir / MANIFEST_NAME).read_text())
    layers, steps = manifest["model_config"]["n_denoiser_layers"], len(manifest["contract"]["ddim_timesteps"])
    model = onnx.load(str(model_dir / "denoiser.int8.fused.onnx"))
    ops = Counter(node.op_type for node in model.graph.node)
    assert ops[mamba_kernel.BLOCK_OP] == layers * steps, ops
    m = manifest["model_config"]
    prefix = int(m["use_history"]) + int(m["use_recent_states"]) * manifest["contract"]["n_obs_steps"]
    kinds = Counter(
        (a["plain"], a["state_out"])
        for a in (
            {a.name: onnx.helper.get_attribute_value(a) for a in node.attribute}
            for node in model.graph.node
            if node.op_type == mamba_kernel.BLOCK_OP
        )
    )
    assert kinds == {(prefix, 1): layers, (0, 0): layers * (steps - 1)}, kinds
    reads = {
        n: f["weight_reads"] for n, f in manifest["files"].items() if n.startswith("denoiser.") and n.endswith(".onnx")
    }
    assert set(reads.values()) == {steps}, reads  # every graph's first step carries the prefix
    assert ops[mamba_kernel.SCAN_OP] == ops[mamba_kernel.CONV_OP] == 0
    int8 = {t.name: int(np.prod(t.dims)) for t in model.graph.initializer if t.data_type == TensorProto.INT8}
    blocks = {name: size for name, size in int8.items() if ".fused_block." in name and size}
    assert len(blocks) == layers * 4, sorted(blocks)  # in_proj, x_proj, dt_proj, out_proj (the tiny preset: no MLP)
    others = sum(size for name, size in int8.items() if name not in blocks)  # the actions' in and out projections
    assert others < 0.1 * sum(blocks.values()), int8
    standard = onnx.load(str(model_dir / "denoiser.int8.onnx"))
    assert len(model.graph.node) < len(standard.graph.node) / 4
    fp32 = run_chunk(OnnxPolicy(model_dir, threads=1, precision="fp32", kernel="standard"))
    fused_error, standard_error = (
        np.abs(run_chunk(OnnxPolicy(model_dir, threads=1, precision="int8", kernel=kernel)) - fp32).max()
        for kernel in ("fused", "standard")
    )
    assert fused_error <= 1.5 * standard_error, (fused_error, standard_error)


def test_one_ddim_step_runs_prefix_and_actions_as_one_node_per_block(tiny_export, tmp_path):
    """K = 1 (the distilled samplers' shape): the prefix and the action tokens in one pass, each block one
    MambaBlockQ8 node with the prefix's tokens plain, the tokens kept whole between blocks (one split, after the last)
    and the zero states built once; its chunks as close to fp32's as the standard int8 graphs'."""
    from collections import Counter

    from export.to_onnx import main as export_main

    run_dir, _, _ = tiny_export
    model_dir = tmp_path / "k1"
    assert (
        export_main(
            [
                str(run_dir),
                "-o",
                str(model_dir),
                "--denoise-steps",
                "1",
                "--timestep-spacing",
                "trailing",
                "--skip-verify",
            ]
        )
        == 0
    )
    manifest = json.loads((model_dir / MANIFEST_NAME).read_text())
    model = onnx.load(str(model_dir / "denoiser.int8.fused.onnx"))
    ops = Counter(node.op_type for node in model.graph.node)
    assert (
        ops[mamba_kernel.BLOCK_OP] == manifest["model_config"]["n_denoiser_layers"] and ops[mamba_kernel.SCAN_OP] == 0
    )
    assert ops["Slice"] == 1 and ops["ConstantOfShape"] == 2, ops
    m = manifest["model_config"]
    prefix = int(m["use_history"]) + int(m["use_recent_states"]) * manifest["contract"]["n_obs_steps"]
    for node in model.graph.node:
        if node.op_type == mamba_kernel.BLOCK_OP:
            attributes = {a.name: onnx.helper.get_attribute_value(a) for a in node.attribute}
            assert attributes["plain"] == prefix and attributes["state_out"] == 0, attributes
    fp32 = run_chunk(OnnxPolicy(model_dir, threads=1, precision="fp32", kernel="standard"))
    fused_error, standard_error = (
        np.abs(run_chunk(OnnxPolicy(model_dir, threads=1, precision="int8", kernel=kernel)) - fp32).max()
        for kernel in ("fused", "standard")
    )
    assert fused_error <= 1.5 * standard_error, (fused_error, standard_error)


@pytest.mark.parametrize("shape", [(1, 1024, 256), (2, 1, 70), (3, 300, 5)], ids=lambda s: "x".join(map(str, s)))
def test_layer_norm_max_over_points_matches_pytorch_and_replaces_three_nodes(shape, tiny_export, monkeypatch):
    """ai.dssp::LayerNormMaxOverPoints (batch, P, F) → (batch, F) equals torch's layer_norm then amax over the points
    (to float rounding), on one thread and two (300 points: three runs of 128 combined); the fused history graph pools
    with it (no LayerNormalization, Transpose or GlobalMaxPool left around the pooling), the standard one does not."""
    rng = np.random.default_rng(sum(shape))
    x = (rng.standard_normal(shape) * 3 + 1).astype(np.float32)
    weight, bias = (rng.standard_normal(shape[-1]).astype(np.float32) for _ in range(2))
    want = (
        torch.nn.functional.layer_norm(
            torch.from_numpy(x).double(),
            (shape[-1],),
            torch.from_numpy(weight).double(),
            torch.from_numpy(bias).double(),
            1e-5,
        )
        .amax(dim=1)
        .numpy()
    )
    graph = helper.make_graph(
        [helper.make_node(mamba_kernel.POOL_OP, ["x", "w", "b"], ["y"], domain=mamba_kernel.DOMAIN, eps=1e-5)],
        "g",
        [helper.make_tensor_value_info(n, TensorProto.FLOAT, None) for n in ("x", "w", "b")],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, None)],
    )
    model = helper.make_model(
        graph, opset_imports=[helper.make_opsetid("", 17), helper.make_opsetid(mamba_kernel.DOMAIN, 1)]
    )
    outputs = []
    for threads in (1, 2):
        session = ort.InferenceSession(
            model.SerializeToString(), session_options(threads, fused=True), providers=["CPUExecutionProvider"]
        )
        (y,) = session.run(None, {"x": x, "w": weight, "b": bias})
        assert y.shape == want.shape and np.abs(y - want).max() <= 1e-5 * max(1.0, float(np.abs(want).max()))
        outputs.append(y)
    assert np.array_equal(*outputs)
    with pytest.raises(Exception, match="P >= 1"):
        session.run(None, {"x": np.zeros((1, 0, shape[-1]), np.float32), "w": weight, "b": bias})
    _, model_dir, _ = tiny_export
    ops = {
        kind: [n.op_type for n in onnx.load(str(model_dir / f"history_step{kind}.onnx")).graph.node]
        for kind in (".fused", "")
    }
    assert mamba_kernel.POOL_OP in ops[".fused"] and "GlobalMaxPool" not in ops[".fused"]
    assert ops[".fused"].count("LayerNormalization") == ops[""].count("LayerNormalization") - 1
    assert mamba_kernel.POOL_OP not in ops[""] and "GlobalMaxPool" in ops[""]


@pytest.mark.parametrize("sample", [True, False], ids=["predicts-sample", "predicts-noise"])
@pytest.mark.parametrize("clip", [True, False], ids=["clip", "no-clip"])
def test_ddim_step_matches_its_reference_and_ends_every_step_of_the_fused_graphs(sample, clip, tiny_export):
    """ai.dssp::DdimStep (the readout, the DDIM update and the next step's action tokens) equals its PyTorch reference
    (export.fused_ops.ddim_step_reference) to float rounding, for either prediction, clipped or not, with the tokens
    and without (the chunk's last step: (batch, H, 0)); a weight of the wrong shape is refused with its name; the fused
    denoiser graphs end each of their K steps with one, the standard graph has none."""
    from export.fused_ops import ddim_step_reference

    rng = np.random.default_rng(int(sample) + 2 * int(clip))
    B, H, d, A = 2, 5, 21, 6  # noqa: N806 — d and A not multiples of the vector widths or of the four outputs a pass
    shapes = {"h": (B, H, d), "x": (B, H, A), "norm_w": (d,), "mod": (2, d), "out_w": (A, d), "out_b": (A,)}
    shapes |= {"in_w": (A, d), "in_b": (d,), "pos": (H, d)}
    feeds = {name: (rng.standard_normal(shape) * 0.7).astype(np.float32) for name, shape in shapes.items()}
    a_t, a_prev = 0.37, 0.81
    for tokens in (True, False):
        want_x, want_a = (
            t.numpy()
            for t in ddim_step_reference(
                *(torch.from_numpy(v) for v in feeds.values()), 1e-5, a_t, a_prev, sample, clip, tokens
            )
        )
        node = helper.make_node(
            mamba_kernel.STEP_OP,
            list(shapes),
            ["x_next", "a_next"],
            domain=mamba_kernel.DOMAIN,
            eps=1e-5,
            c_t=a_t**0.5,
            s_t=(1 - a_t) ** 0.5,
            c_prev=a_prev**0.5,
            s_prev=(1 - a_prev) ** 0.5,
            sample=int(sample),
            clip=int(clip),
            tokens=int(tokens),
        )
        graph = helper.make_graph(
            [node],
            "g",
            [helper.make_tensor_value_info(n, TensorProto.FLOAT, None) for n in shapes],
            [helper.make_tensor_value_info(n, TensorProto.FLOAT, None) for n in ("x_next", "a_next")],
        )
        model = helper.make_model(
            graph, opset_imports=[helper.make_opsetid("", 17), helper.make_opsetid(mamba_kernel.DOMAIN, 1)]
        )
        session = ort.InferenceSession(
            model.SerializeToString(), session_options(1, fused=True), providers=["CPUExecutionProvider"]
        )
        x_next, a_next = session.run(None, feeds)
        assert x_next.shape == want_x.shape and a_next.shape == want_a.shape == ((B, H, d) if tokens else (B, H, 0))
        assert np.abs(x_next - want_x).max() <= 1e-5 * max(1.0, float(np.abs(want_x).max()))
        assert a_next.size == 0 or np.abs(a_next - want_a).max() <= 1e-5 * max(1.0, float(np.abs(want_a).max()))
    with pytest.raises(Exception, match=r"DdimStep: pos has shape \(4, 21\), expected \(5, 21\)"):
        session.run(None, {**feeds, "pos": feeds["pos"][:4]})
    _, model_dir, _ = tiny_export
    steps = read_manifest(model_dir).contract.denoise_steps
    for name in ("denoiser.fused.onnx", "denoiser.int8.fused.onnx", "denoiser.onnx"):
        ops = [n.op_type for n in onnx.load(str(model_dir / name), load_external_data=False).graph.node]
        assert ops.count(mamba_kernel.STEP_OP) == (0 if name == "denoiser.onnx" else steps), name


def test_the_first_ddim_step_carries_the_prefix_where_every_block_is_one_node():
    """With every denoiser block fused (export's int8 graphs), a chunk's first step runs [prefix, actions] in one pass
    and gives the prefix's states, each block one node: the same x0 and states as the prefix's own pass and then the
    step, which read every weight twice; the K-step chain takes that way and gives the same chunk."""
    import dataclasses

    from dssp_train.config import load_preset
    from dssp_train.model.policy import DSSPPolicy
    from export.fused_ops import use_fused_blocks

    torch.manual_seed(0)
    cfg = load_preset("sim")
    cfg = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, state_dim=7, action_dim=7))
    policy = DSSPPolicy(cfg.model).eval()
    den = policy.denoiser
    assert den.joins_prefix and not den.fused_blocks
    with torch.no_grad():
        for p in den.parameters():
            p.add_(torch.randn_like(p) * 0.05)
        chained = {}
        for fused in (False, True):
            if fused:
                assert use_fused_blocks(den) == len(den.layers) and den.joins_prefix and den.fused_blocks
            prefix = torch.randn(2, 3, cfg.model.d_model, generator=torch.Generator().manual_seed(1))
            noise = torch.randn(2, cfg.model.horizon, 7, generator=torch.Generator().manual_seed(2))
            chained[fused] = policy.sample_normalized(prefix, noise, 3, unrolled=True)
        mod = den.modulation(torch.tensor([500])).at(0)
        x0, states = den.joint_step(prefix, noise, mod)
        apart = den.encode_prefix(prefix, unrolled=True)
        assert torch.equal(x0, den.denoise_modulated(apart, noise, mod, unrolled=True))
        for (conv, ssm), (conv_apart, ssm_apart) in zip(states, apart):
            assert torch.equal(conv, conv_apart) and torch.allclose(ssm, ssm_apart, rtol=0, atol=1e-6)
    assert torch.allclose(chained[True], chained[False], atol=0.05)  # int8 against fp32 blocks
