"""Temporal ensembling of overlapping chunks (``ChunkedControl(policy, Ensemble())``, ACT): the action of a tick is
the weighted mean of every kept chunk's prediction for it, oldest first with weight exp(-decay * i).

The loop's arithmetic is checked on a stand-in for the runtime whose chunks are known numbers (chunk k, computed at
the k-th chunk tick, holds 100 k + j at index j, negated in the second action dimension), so every expected action
is written out by hand; ``dssp-run --smoothing ensemble`` then runs end to end on the embedded simulation (real
time, as the other dssp-run tests: nothing asserted depends on how fast the machine is).
"""

import dataclasses
import json
import math

import numpy as np
import pytest
from conftest import one_error_line, run_dssp

from dssp_data.model_contract import ModelContract
from dssp_deploy.control_loop import ChunkedControl
from dssp_deploy.ranges import ChunkOutOfRange
from dssp_deploy.schedules import Ensemble, Plain, config_for
from hardware.policies.exported_model import ModelPolicy
from hardware.run_log import read_ticks


class FakePolicy:
    """What ChunkedControl uses of OnnxPolicy. The history is a tuple of the observed agent_pos[0] values (each
    observation replaces it, as the real history's fields are replaced); ``act`` returns chunk k = the k-th chunk
    it gave: (1, H, 2), [100 k + j, -(100 k + j)] at index j. ``refuse``: which act() calls (0-based, counting
    refused ones) raise ChunkOutOfRange instead."""

    def __init__(self, horizon=4, n_action_steps=2, action_offset=1, refuse=()):
        self.horizon = horizon
        self.contract = ModelContract(
            n_obs_steps=action_offset + 1,
            horizon=horizon,
            n_action_steps=n_action_steps,
            action_offset=action_offset,
            ddim_timesteps=[2, 1, 0],
            control_rate_hz=10.0,
        )
        self.refuse = set(refuse)
        self.calls = 0
        self.seeds: list = []  # the seed of each chunk given
        self.history: tuple = ()

    def reset(self):
        self.history = ()

    def observe(self, point_cloud, agent_pos):
        self.history = (*self.history, float(np.asarray(agent_pos).ravel()[0]))

    def act(self, seed=None):
        call, self.calls = self.calls, self.calls + 1
        if call in self.refuse:
            raise ChunkOutOfRange("action chunk refused by the test; the chunk was not used")
        k = len(self.seeds)
        self.seeds.append(seed)
        values = 100.0 * k + np.arange(self.horizon, dtype=np.float32)
        return np.stack([values, -values], axis=-1)[None].astype(np.float32)


def tick(loop, t):
    """One tick with observation t (agent_pos [t])."""
    return loop.tick(np.zeros((4, 3), np.float32), np.array([float(t)], np.float32))


def blend(*values, decay):
    """The weighted mean of predictions given oldest first, weights exp(-decay * i)."""
    w = [math.exp(-decay * i) for i in range(len(values))]
    return sum(wi * v for wi, v in zip(w, values)) / sum(w)


@pytest.mark.parametrize("decay", [0.01, 0.0, 0.7])
def test_every_tick_the_action_is_the_weighted_mean_of_the_kept_predictions(decay):
    # H = 4, offset 1: a chunk covers 3 ticks (indices 1, 2, 3); a new chunk every tick (the default).
    p = FakePolicy()
    loop = ChunkedControl(p, Ensemble(decay=decay), seed=10)
    expected = {
        0: [1.0],  # chunk 0 at index 1: the only one, its own action
        1: [2.0, 101.0],  # chunk 0 index 2, chunk 1 index 1
        2: [3.0, 102.0, 201.0],  # chunk 0 index 3 (its last), chunk 1 index 2, chunk 2 index 1
        3: [103.0, 202.0, 301.0],  # chunk 0 covers no more ticks: dropped
        4: [203.0, 302.0, 401.0],
    }
    for t, predictions in expected.items():
        action, info = tick(loop, t)
        want = blend(*predictions, decay=decay)
        assert action.shape == (1, 2) and action.dtype == np.float32
        np.testing.assert_allclose(action, [[want, -want]], rtol=1e-6)
        assert info.new_chunk and info.chunk_ms is not None and info.predictions == len(predictions)
        assert info.chunk_index == p.contract.action_offset  # of the newest chunk, computed on this tick
        assert [s for s, _ in loop.schedule.kept] == list(range(max(0, t - 2), t + 1))
    assert action[0, 0] != pytest.approx(np.mean(expected[4])) or decay == 0.0  # the weights matter
    if decay == 0.0:
        np.testing.assert_allclose(action, [[np.mean(expected[4]), -np.mean(expected[4])]], rtol=1e-6)
    assert p.seeds == [10 + t for t in range(5)]  # a chunk's seed: seed + the tick it is computed at
    assert p.history == tuple(float(t) for t in range(5))  # the history step ran every tick
    loop.reset()
    assert loop.schedule.kept == [] and loop.tick_count == 0 and p.history == ()


def test_the_oldest_prediction_weighs_most():
    p = FakePolicy()
    loop = ChunkedControl(p, Ensemble(decay=5.0))  # weights 1, e^-5: nearly chunk 0's alone
    tick(loop, 0)
    action, _ = tick(loop, 1)
    assert abs(action[0, 0] - 2.0) < abs(action[0, 0] - 101.0)
    assert action[0, 0] == pytest.approx((2.0 + 101.0 * math.exp(-5.0)) / (1 + math.exp(-5.0)), rel=1e-6)


def test_a_chunk_every_h_a_ticks_blends_only_where_chunks_overlap():
    # H = 8, offset 1, H_a = 4: a chunk covers 7 ticks, one every 4 ticks overlaps the next for 3.
    p = FakePolicy(horizon=8, n_action_steps=4, action_offset=1)
    loop = ChunkedControl(p, Ensemble(every=4, decay=0.0), seed=0)
    seen = [tick(loop, t) for t in range(12)]
    assert [info.new_chunk for _, info in seen] == [t % 4 == 0 for t in range(12)]
    assert [info.chunk_ms is not None for _, info in seen] == [t % 4 == 0 for t in range(12)]
    for t, (action, info) in enumerate(seen):
        newest = t // 4
        own = 100.0 * newest + 1 + t % 4  # the newest chunk's prediction for t
        if t >= 4 and t % 4 < 3:  # the previous chunk (computed 4 ticks earlier) still covers t: index 5 + t % 4
            previous = 100.0 * (newest - 1) + 5 + t % 4
            want, n = (own + previous) / 2, 2
        else:
            want, n = own, 1
        assert info.predictions == n and info.chunk_index == 1 + t % 4, t
        np.testing.assert_allclose(action, [[want, -want]], rtol=1e-6, err_msg=f"tick {t}")
    assert p.seeds == [0, 4, 8]


def test_a_refused_chunk_leaves_the_kept_chunks_and_the_history_and_the_next_tick_recomputes():
    p = FakePolicy(refuse={2})  # the third act() call: the chunk of tick 2
    loop = ChunkedControl(p, Ensemble(decay=0.0), seed=0)
    tick(loop, 0)
    tick(loop, 1)
    kept = [(s, c.copy()) for s, c in loop.schedule.kept]
    history = p.history
    with pytest.raises(ChunkOutOfRange):
        tick(loop, 99)  # refused: this observation must not stay in the history
    assert loop.tick_count == 2 and p.history is history == (0.0, 1.0)
    assert [s for s, _ in loop.schedule.kept] == [s for s, _ in kept]
    assert all(np.array_equal(c, k) for (_, c), (_, k) in zip(loop.schedule.kept, kept))
    # The next tick is tick 2 again: a new chunk (the third one given, with tick 2's seed) joins the same two.
    action, info = tick(loop, 2)
    assert info.new_chunk and info.predictions == 3 and p.seeds == [0, 1, 2]
    want = (3.0 + 102.0 + 201.0) / 3
    np.testing.assert_allclose(action, [[want, -want]], rtol=1e-6)
    assert p.history == (0.0, 1.0, 2.0) and loop.tick_count == 3


def test_ensembling_does_not_combine_with_prefetch_and_bad_settings_are_refused():
    p = FakePolicy()
    with pytest.raises(TypeError, match="prefetch"):  # ensembling has no prefetch setting
        Ensemble(prefetch=True)
    with pytest.raises(ValueError, match="does not combine with smoothing ensemble"):  # named as a command line does
        config_for("ensemble", prefetch=True)
    for options, words in (
        ({"every": 0}, "at least 1 \\(ticks between chunks\\), got 0"),
        ({"every": 1.5}, "whole number"),
        ({"decay": -0.1}, "finite number >= 0"),
        ({"decay": float("nan")}, "finite number >= 0"),
    ):
        with pytest.raises(ValueError, match=words):
            Ensemble(**options)
    with pytest.raises(ValueError, match="Ensemble.every 3: the model executes H_a = 2 actions .* \\(1 to 2\\)"):
        ChunkedControl(p, Ensemble(every=3))  # checked against the policy's H_a
    with pytest.raises(ValueError, match="smoothing must be one of none, ensemble"):
        config_for("average")


def test_none_is_the_default_loop():
    a, b = FakePolicy(refuse={1}), FakePolicy(refuse={1})
    default, none = ChunkedControl(a, seed=3), ChunkedControl(b, Plain(), seed=3)
    for t in range(7):
        results = []
        for loop in (default, none):
            try:
                results.append(tick(loop, t))
            except ChunkOutOfRange:
                results.append(None)
        if results[0] is None:
            assert results[1] is None
            continue
        (x, i), (y, j) = results
        assert np.array_equal(x, y) and (i.new_chunk, i.chunk_index, i.predictions) == (j.new_chunk, j.chunk_index, 1)
    assert a.seeds == b.seeds and a.history == b.history and not hasattr(none.schedule, "kept")  # keeps no chunks
    assert none.schedule.settings() == {
        "smoothing": "none",
        "ensemble_every": None,
        "ensemble_decay": None,
        "rtc_delay_ticks": None,
        "injected_delay_ticks": None,
    }


def test_the_model_source_shows_the_newest_chunk_and_logs_its_smoothing():
    p = FakePolicy()
    source = ModelPolicy(p, 10.0, seed=0, schedule=Ensemble(decay=0.0))
    assert source.describe() == {
        "policy": "model",
        "denoise_steps": 3,
        "smoothing": "ensemble",
        "ensemble_every": 1,
        "ensemble_decay": 0.0,
        "rtc_delay_ticks": None,
        "injected_delay_ticks": None,
    }
    source.reset(np.zeros(1))
    cloud = np.zeros((4, 3), np.float32)
    source.act(cloud, np.zeros(1))
    act = source.act(cloud, np.ones(1))
    assert act.action.dtype == np.float64 and np.allclose(act.action, [(2.0 + 101.0) / 2, -(2.0 + 101.0) / 2])
    np.testing.assert_array_equal(act.chunk, [[101.0, -101.0], [102.0, -102.0], [103.0, -103.0]])  # chunk 1's to come
    assert act.chunk_ms is not None


# ----------------------------------------------------------------------------- dssp-run


def test_dssp_run_with_temporal_ensembling_on_the_embedded_simulation(arm_export, tmp_path, capsys):
    log_dir = tmp_path / "log"
    code, out, err = run_dssp(
        capsys,
        "--model",
        arm_export,
        "--smoothing",
        "ensemble",
        "--camera",
        "tabletop",
        "--can",
        "sim",
        "--max-steps",
        "20",
        "--seed",
        "0",
        "--threads",
        "1",
        "--quiet",
        "--log-dir",
        log_dir,
    )
    assert code == 0, out + err
    assert "ticks 20" in out and "ended by: max steps" in out
    run = json.loads((log_dir / "run.json").read_text())
    policy = run["settings"]["policy"]
    assert (policy["smoothing"], policy["ensemble_every"], policy["ensemble_decay"]) == ("ensemble", 1, 0.01)
    assert run["summary"]["policy_ticks"] > 0
    acted = [t for t in read_ticks(log_dir) if t["action"] is not None]
    assert len(acted) == run["summary"]["policy_ticks"]
    assert all(t.get("chunk_ms") is not None for t in acted)  # a chunk on every tick the model acted


@pytest.mark.parametrize(
    "argv, line",
    [
        (
            ["--smoothing", "ensemble", "--prefetch"],
            "error: --prefetch does not combine with --smoothing ensemble: ensembling computes each chunk in the tick that "
            "first uses it; run one or the other",
        ),
        (
            ["--smoothing", "ensemble", "--ensemble-every", "0"],
            "error: --ensemble-every must be at least 1 (ticks between chunks), got 0",
        ),
        (
            ["--smoothing", "ensemble", "--ensemble-decay", "-1"],
            "error: --ensemble-decay must be a finite number >= 0 (0: the plain mean), got -1.0",
        ),
        (
            ["--ensemble-every", "2"],
            "error: --ensemble-every is a setting of temporal ensembling: it goes with --smoothing ensemble",
        ),
    ],
)
def test_bad_smoothing_flags_are_one_line_before_anything_opens(tmp_path, capsys, monkeypatch, argv, line):
    monkeypatch.chdir(tmp_path)
    code, _, err = run_dssp(capsys, "--model", tmp_path / "no-model", *argv, "--log-dir", tmp_path / "log")
    assert code == 2 and one_error_line(err) == line
    assert not (tmp_path / "log").exists()


def test_smoothing_is_a_models_setting(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, _, err = run_dssp(capsys, "--policy", "hold", "--smoothing", "ensemble", "--log-dir", tmp_path / "log")
    assert code == 2
    assert one_error_line(err) == "error: --smoothing is a model's setting: it goes with --model, not --policy hold"
    assert not (tmp_path / "log").exists()


def test_a_chunk_every_more_than_h_a_ticks_is_refused_with_the_model(arm_export, tmp_path, capsys):
    code, _, err = run_dssp(
        capsys,
        "--model",
        arm_export,
        "--smoothing",
        "ensemble",
        "--ensemble-every",
        "99",
        "--threads",
        "1",
        "--log-dir",
        tmp_path / "log",
    )
    assert code == 2 and "--ensemble-every 99: " in one_error_line(err) and "(1 to " in err
    assert not (tmp_path / "log").exists()


def test_metaworlds_direct_loop_ensembles_too():
    """dssp-sim eval on a MetaWorld task runs its own ChunkedControl (run_direct_episode): the smoothing reaches it,
    a chunk every tick over a whole (held-still) episode."""
    from dssp_sim import metaworld_env as mw
    from dssp_sim.evaluate import run_direct_episode

    class Still(FakePolicy):  # MetaWorld's 4 action values, zero: the hand stays
        def act(self, seed=None):
            self.seeds.append(seed)
            return np.zeros((1, self.horizon, 4), np.float32)

    p = Still()
    p.contract = dataclasses.replace(
        p.contract, control_rate_hz=None
    )  # made for no rate: the loop runs at the env's without a warning
    with mw.MetaWorldEnv("metaworld/reach", seed=0) as env:
        outcome = run_direct_episode(p, env, 0, mw.cloud_config(512), schedule=Ensemble())
    assert outcome.holds == 0 and outcome.steps == len(p.seeds) == len(p.history) > 1
    assert p.seeds == list(range(len(p.seeds)))  # the episode's seed (0) + the tick
