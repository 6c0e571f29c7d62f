"""What the runtime refuses to act on or to load.

- observations outside the trained ranges (plus the margin of ``dssp_deploy.ranges``) and chunks outside the
  action range, on every precision: refused, the history unchanged, the control loops holding;
- ONNX external data: only files of the model directory with their own size and sha256 in the manifest,
  handed to ONNX Runtime as the checked bytes (never read from the current directory);
- a truncated fused-kernel library: not loaded (it would kill the process with SIGBUS), the standard graphs run.
"""

import json
import os
import shutil
import subprocess
import sys
import textwrap

import numpy as np
import onnx
import pytest
from conftest import assert_policy_state_kept, one_line_message, policy_state, rig_loop
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dssp_core.errors import DSSPError, NonFiniteObservation
from dssp_deploy import mamba_kernel
from dssp_deploy.control_loop import ChunkedControl
from dssp_deploy.manifest import MANIFEST_NAME, ModelDirError, sha256_hex
from dssp_deploy.onnx_policy import OnnxPolicy
from dssp_deploy.ranges import MARGIN, ChunkOutOfRange, ObservationOutOfRange
from dssp_deploy.schedules import MeasuredDelay, Plain
from dssp_deploy.sessions import open_session

PRECISIONS = ["fp32", "int8", "int4"]


def trajectory(data_path, length: int):
    """``length`` observations of the training data: clouds (T, P, C), states (T, S)."""
    from dssp_data.replay_buffer import ReplayBuffer

    buf = ReplayBuffer.load(data_path)
    return buf.point_cloud[:length], buf.state[:length]


class Corrupted:
    """A denoiser session whose chunks get ``value`` at ``index``."""

    def __init__(self, session, index: tuple[int, ...], value: float):
        self.session, self.index, self.value = session, index, value

    def run(self, names, feeds):
        out = self.session.run(names, feeds)
        out[0] = out[0].copy()
        out[0][self.index] = self.value
        return out

    def __getattr__(self, name):
        return getattr(self.session, name)


# ------------------------------------------------------------------------ observations and chunks
@pytest.mark.parametrize("precision", PRECISIONS)
def test_far_out_observations_are_refused_on_every_precision(tiny_export, precision):
    _, model_dir, data = tiny_export
    p, ref = (
        OnnxPolicy(model_dir, threads=1, precision=precision),
        OnnxPolicy(model_dir, threads=1, precision=precision, warmup=0),
    )
    clouds, states = trajectory(data, 7)
    for t in range(3):
        p.observe(clouds[t], states[t])
        ref.observe(clouds[t], states[t])
    kept = policy_state(p)
    pos_upper, cloud_lower = p.ranges["agent_pos"].upper, p.ranges["point_cloud"].lower
    bad_cases = []
    for value, where in ((1e30, "(0, 1)=1e+30 > "), (-1e30, "(0, 1)=-1e+30 < ")):
        state = states[3].copy()
        state[1] = value
        bad_cases.append((clouds[3], state, ObservationOutOfRange, ("agent_pos [1, 2]", where)))
    cloud = clouds[3].copy()
    cloud[5, 2] = 1e3  # a millimetre reading among metres
    cloud[7, 0] = -1e6
    bad_cases.append(
        (
            cloud,
            states[3],
            ObservationOutOfRange,
            ("point_cloud [1, 32, 3] has 2 value(s)", "(0, 5, 2)=1000 > ", f"(0, 7, 0)=-1e+06 < {cloud_lower[0]:.6g}"),
        )
    )
    state = states[3].copy()
    state[0] = pos_upper[0] + 1e-3  # just past the bound
    bad_cases.append(
        (
            clouds[3],
            state,
            ObservationOutOfRange,
            ("(0, 0)=", f"> {pos_upper[0]:.6g}", "channel 0: training range [0, 1]"),
        )
    )
    for bad in (np.nan, np.inf):
        state = states[3].copy()
        state[0] = bad
        bad_cases.append((clouds[3], state, NonFiniteObservation, ("agent_pos",)))
        cloud = clouds[3].copy()
        cloud[2, 1] = -bad
        bad_cases.append((cloud, states[3], NonFiniteObservation, ("point_cloud", "(0, 2, 1)")))
    for cloud, state, error, tokens in bad_cases:
        with pytest.raises(error) as info:
            p.observe(cloud, state)
        one_line_message(info, *tokens, "the observation was not used")
        assert_policy_state_kept(p, kept)  # refused before any graph ran
    assert issubclass(ObservationOutOfRange, DSSPError)
    for t in range(3, 7):  # in range: accepted, the episode goes on as if the refused ones never came
        p.observe(clouds[t], states[t])
        ref.observe(clouds[t], states[t])
        assert np.array_equal(p.act(seed=t), ref.act(seed=t))


@pytest.fixture(scope="module")
def fp32_policy(tiny_export):
    return OnnxPolicy(tiny_export[1], threads=1, precision="fp32", warmup=0)


@settings(max_examples=40, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(
    name=st.sampled_from(["point_cloud", "agent_pos"]),
    channel=st.integers(0, 2),
    inside=st.booleans(),
    where=st.floats(1e-3, 0.999),
    beyond=st.floats(1e-3, 1e12),
    above=st.booleans(),
)
def test_the_accepted_range_is_the_training_range_widened_by_the_margin(
    fp32_policy, tiny_export, name, channel, inside, where, beyond, above
):
    """Inside each channel's bounds — the manifest's input_min/max (what the normaliser maps to [-1, 1]) widened
    by MARGIN x the widest span — accepted; outside, refused naming the entry."""
    p = fp32_policy
    clouds, states = trajectory(tiny_export[2], 1)
    stats = json.loads((tiny_export[1] / MANIFEST_NAME).read_text())["normalizers"][name]
    low, high = np.asarray(stats["input_min"]), np.asarray(stats["input_max"])
    scale, offset = np.asarray(stats["scale"]), np.asarray(stats["offset"])
    np.testing.assert_allclose(low * scale + offset, -1.0, atol=1e-6)  # no constant channel here: min → -1, max → 1
    np.testing.assert_allclose(high * scale + offset, 1.0, atol=1e-6)
    slack = MARGIN * (high - low).max()
    channel %= len(low)
    lower, upper = low[channel] - slack, high[channel] + slack
    np.testing.assert_allclose(
        [p.ranges[name].lower[channel], p.ranges[name].upper[channel]], [lower, upper], rtol=1e-6
    )
    span = upper - lower
    value = lower + where * span if inside else (upper + beyond * span if above else lower - beyond * span)
    cloud, state = clouds[0].copy(), states[0].copy()
    index = (0, 4, channel) if name == "point_cloud" else (0, channel)
    (cloud if name == "point_cloud" else state)[index[1:]] = value
    p.reset()
    if inside:
        p.observe(cloud, state)
        assert p.steps == 1
    else:
        with pytest.raises(ObservationOutOfRange) as info:
            p.observe(cloud, state)
        one_line_message(info, f"{name} ", f"{index}=", ">" if above else "<")
        assert p.steps == 0


@pytest.mark.parametrize("precision", PRECISIONS)
def test_a_chunk_outside_the_action_range_is_never_returned(tiny_export, precision):
    _, model_dir, data = tiny_export
    p = OnnxPolicy(model_dir, threads=1, precision=precision)
    clouds, states = trajectory(data, 2)
    p.observe(clouds[0], states[0])
    good = p.act(seed=0)
    actions = p.ranges["action"]
    assert np.all(good >= actions.lower) and np.all(good <= actions.upper)
    session = p.sessions["denoiser"]
    for index, value, tokens in (
        ((0, 2, 1), np.nan, ("(0, 2, 1)=nan (not finite)",)),
        ((0, 0, 0), -np.inf, ("(0, 0, 0)=-inf (not finite)",)),
        ((0, 3, 1), actions.upper[1] + 1.0, ("(0, 3, 1)=", f"> {actions.upper[1]:.6g}")),
        ((0, 1, 0), actions.lower[0] - 1e-3, ("(0, 1, 0)=", f"< {actions.lower[0]:.6g}")),
    ):
        p.sessions["denoiser"] = Corrupted(session, index, value)
        with pytest.raises(ChunkOutOfRange) as info:
            p.act(seed=0)
        one_line_message(
            info, "action chunk [1, 4, 2] has 1 value(s) outside the model's range", *tokens, "the chunk was not used"
        )
    p.sessions["denoiser"] = Corrupted(session, (0, 0, 0), actions.upper[0])  # on the bound: accepted
    assert p.act(seed=0)[0, 0, 0] == np.float32(actions.upper[0])


@pytest.mark.parametrize("prefetch", [False, True], ids=["in the tick", "prefetched"])
def test_a_refused_chunk_undoes_its_tick_and_the_next_tick_takes_a_new_one(tiny_export, prefetch):
    _, model_dir, data = tiny_export
    p, q = OnnxPolicy(model_dir, threads=1), OnnxPolicy(model_dir, threads=1, warmup=0)
    options = (
        dict(schedule=Plain(prefetch=True, delay=MeasuredDelay(50.0)), control_rate_hz=10) if prefetch else {}
    )  # lead: 1 tick
    loop = ChunkedControl(p, seed=0, **options)
    ha, lead = p.contract.n_action_steps, loop.schedule.lead
    clouds, states = trajectory(data, 3 * ha)
    session = p.sessions["denoiser"]
    corrupted = Corrupted(session, (0, 0, 0), np.nan)
    for t in range(ha):
        if t == ha - lead:  # prefetched: the chunk for tick ha starts now, in the background
            p.sessions["denoiser"] = corrupted
        loop.tick(clouds[t], states[t])
    p.sessions["denoiser"] = corrupted  # in the tick: computed at tick ha
    with pytest.raises(ChunkOutOfRange, match=r"^action chunk .*=nan \(not finite\)"):
        loop.tick(clouds[ha], states[ha])
    assert (
        loop.tick_count == p.steps == ha and loop.schedule.in_flight is None
    )  # the tick undone: its observation not kept
    p.sessions["denoiser"] = session
    # The next tick is tick ha again: a new chunk, in the tick, from the history without the refused observation.
    for t in [*range(ha), *range(ha + 1, 2 * ha + 1)]:
        q.observe(clouds[t], states[t])
        if t == ha + 1:
            expected = q.act(seed=ha)
    action, info = loop.tick(clouds[ha + 1], states[ha + 1])
    assert (
        info.new_chunk
        and info.chunk_index == p.contract.action_offset
        and np.array_equal(action, expected[:, p.contract.action_offset])
    )
    for t in range(ha + 2, 2 * ha + 1):
        action, info = loop.tick(clouds[t], states[t])
        assert np.isfinite(action).all()
    assert loop.tick_count == p.steps == 2 * ha


def test_the_robot_loop_holds_on_a_refused_observation_or_chunk(arm_export, tmp_path, monkeypatch):
    far = {"on": False}

    def cloud_far_out(cloud):
        if far["on"]:
            cloud = cloud.copy()
            cloud[3, 1] = 50.0  # 50 m: no table is that wide
        return cloud

    def assert_held(records, prefix, token):
        for r in records:
            assert r["held"] and r["action"] is None and r["command"] is not None
            assert any(e.startswith(prefix) and token in e for e in r["events"]), r["events"]
            assert any(e["kind"] == "hold" for e in r["safety"])
        assert all(np.array_equal(r["command"], records[0]["command"]) for r in records)  # the last safe target

    with rig_loop(arm_export, tmp_path, monkeypatch, cloud_far_out) as (policy, runner, ticks):
        assert all(r["action"] is not None for r in ticks(4))
        steps, count = policy.steps, runner.source.control.tick_count
        far["on"] = True
        assert_held(ticks(3), "no observation: point_cloud", "(0, 3, 1)=50 >")
        assert policy.steps == steps and runner.source.control.tick_count == count  # the history was not fed
        assert runner.event_counts["observation_out_of_range"] == 3 and runner.fault is None
        far["on"] = False
        # the next chunk comes out NaN: refused at every tick it is due, the tick undone, held
        ha = policy.contract.n_action_steps
        while runner.source.control.tick_count % ha:  # up to the tick that takes the next chunk
            ticks(1)
        session = policy.sessions["denoiser"]
        policy.sessions["denoiser"] = Corrupted(session, (0, 1, 2), np.nan)
        steps = policy.steps
        assert_held(ticks(3), "no action: action chunk", "(0, 1, 2)=nan (not finite)")
        assert policy.steps == steps and runner.event_counts["chunk_out_of_range"] == 3 and runner.fault is None
        policy.sessions["denoiser"] = session
        after = ticks(2)
        assert all(r["action"] is not None for r in after) and policy.steps == steps + 2


# -------------------------------------------------------------------------- ONNX external data
GRAPH = "history_step.onnx"
DATA = "history_step.onnx.data"


def rehash(model_dir, *names, drop=()):
    """Record the size and sha256 of ``names`` in the manifest (and forget ``drop``)."""
    manifest = json.loads((model_dir / MANIFEST_NAME).read_text())
    for name in names:
        data = (model_dir / name).read_bytes()
        manifest["files"][name] = {"bytes": len(data), "sha256": sha256_hex(data)}
    for name in drop:
        manifest["files"].pop(name)
    (model_dir / MANIFEST_NAME).write_text(json.dumps(manifest))


def set_locations(model_dir, location: str) -> None:
    """Point every external tensor of the graph at ``location`` (its manifest entry updated)."""
    model = onnx.load(str(model_dir / GRAPH), load_external_data=False)
    for tensor in model.graph.initializer:
        for entry in tensor.external_data:
            if entry.key == "location":
                entry.value = location
    (model_dir / GRAPH).write_bytes(model.SerializeToString())
    rehash(model_dir, GRAPH)


@pytest.fixture
def external(tiny_export, tmp_path):
    """A copy of the tiny model whose fp32 history graph keeps its weights in ``history_step.onnx.data``, both
    listed in the manifest; (model directory, the original chunk after three observations)."""
    _, model_dir, data = tiny_export
    dst = tmp_path / "model"
    shutil.copytree(model_dir, dst)
    onnx.save(
        onnx.load(str(model_dir / GRAPH)),
        str(dst / GRAPH),
        save_as_external_data=True,
        all_tensors_to_one_file=True,
        location=DATA,
        size_threshold=0,
    )
    rehash(dst, GRAPH, DATA)
    return dst, first_chunk(model_dir, data), data


def first_chunk(model_dir, data):
    p = OnnxPolicy(model_dir, threads=1, precision="fp32", kernel="standard", warmup=0)
    clouds, states = trajectory(data, 3)
    for t in range(3):
        p.observe(clouds[t], states[t])
    return p.act(seed=0)


def test_listed_external_data_is_loaded_from_the_checked_bytes_not_the_current_directory(external, tmp_path):
    model_dir, want, data = external
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / DATA).write_bytes(bytes((model_dir / DATA).stat().st_size))  # zeros, where ONNX Runtime used to look
    os.chdir(elsewhere)
    assert np.array_equal(first_chunk(model_dir, data), want)
    with pytest.raises(
        ModelDirError, match="external data at 'history_step.onnx.data', which was not read and checked"
    ):
        open_session((model_dir / GRAPH).read_bytes())  # its bytes alone: the file it names is not taken from anywhere


def outside_location(model_dir, tmp_path):
    shutil.copyfile(model_dir / DATA, tmp_path / "outside.data")
    set_locations(model_dir, "../outside.data")
    return "'../outside.data', which is not a file name inside the model directory"


def absolute_location(model_dir, tmp_path):
    shutil.copyfile(model_dir / DATA, tmp_path / "outside.data")
    set_locations(model_dir, str(tmp_path / "outside.data"))
    return "which is not a file name inside the model directory (absolute paths and '..' are refused)"


def link_out(model_dir, tmp_path):
    shutil.move(model_dir / DATA, tmp_path / "outside.data")
    (model_dir / DATA).symlink_to(tmp_path / "outside.data")  # same bytes, same sha256
    return "is a symbolic link to"


def unlisted(model_dir, tmp_path):
    rehash(model_dir, drop=[DATA])
    return "history_step.onnx.data, which has no size and sha256 in dssp_model.json files"


def changed(model_dir, tmp_path):
    data = bytearray((model_dir / DATA).read_bytes())
    data[100] ^= 1
    (model_dir / DATA).write_bytes(bytes(data))
    return "history_step.onnx.data is not the file this manifest was written for"


def missing(model_dir, tmp_path):
    (model_dir / DATA).unlink()
    return "history_step.onnx.data (the external data of history_step.onnx) is missing"


@pytest.mark.parametrize(
    "damage", [outside_location, absolute_location, link_out, unlisted, changed, missing], ids=lambda f: f.__name__
)
def test_external_data_outside_the_model_directory_or_its_manifest_is_refused(external, tmp_path, damage):
    model_dir, _, _ = external
    token = damage(model_dir, tmp_path)
    for precision, kernel in (
        ("fp32", "standard"),
        ("int8", "auto"),
    ):  # the graph that runs, or one a fallback would take
        with pytest.raises(ModelDirError) as info:
            OnnxPolicy(model_dir, threads=1, precision=precision, kernel=kernel, warmup=0)
        one_line_message(info, token)


# ------------------------------------------------------------------------------ the kernel library
def test_a_truncated_kernel_library_is_not_loaded_and_the_standard_graphs_run(tiny_export, tmp_path):
    _, model_dir, _ = tiny_export
    built = mamba_kernel.DEFAULT_LIBRARY
    assert mamba_kernel.elf_problem(built) is None
    data = built.read_bytes()
    truncated = tmp_path / "libdssp_mamba.so"
    for size, token in (
        (len(data) // 2, "is truncated (its segment"),
        (len(data) - 1, "is truncated (its section header table"),
        (40, "is truncated (40 bytes, shorter than its ELF header)"),
        (3, "is not an ELF shared library"),
    ):
        truncated.write_bytes(data[:size])
        assert token in mamba_kernel.elf_problem(truncated)
    truncated.write_bytes(data[: len(data) // 2])
    # In a process of its own: were the library loaded, SIGBUS would kill it.
    script = textwrap.dedent(f"""
        import numpy as np
        from dssp_deploy import OnnxPolicy
        policy = OnnxPolicy({str(model_dir)!r}, threads=1)
        standard = OnnxPolicy({str(model_dir)!r}, threads=1, kernel="standard")
        obs = policy.example_observation(np.random.default_rng(0))
        policy.observe(*obs)
        standard.observe(*obs)
        assert np.array_equal(policy.act(seed=0), standard.act(seed=0))
        print(policy.kernel_note)
    """)
    env = {**os.environ, mamba_kernel.LIBRARY_ENV: str(truncated)}
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, env=env)
    assert out.returncode == 0, out.stderr
    note = out.stdout.strip()
    assert "\n" not in note and note.startswith("int8, standard ONNX graphs (the fused Mamba kernel is unavailable: ")
    assert (
        f"{truncated.resolve()} failed to load: it is truncated (its segment" in note
        and "rebuild it with `make kernel`" in note
    )
