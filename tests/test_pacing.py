"""The loops' shared timing (hardware.pacing): pacing on the clock, overruns and resync, the measured rate, the
latency statistics; and that dssp-run's loop, the recording session and dssp-replay pace with it."""

import math

import numpy as np
import pytest

from hardware.clock import FakeClock
from hardware.pacing import Pacer, RateMeter, latency_stats


def test_on_time_ticks_sleep_to_the_next_tick_and_count_no_overrun():
    clock = FakeClock(5.0)
    pacer = Pacer(clock, 0.1)
    pacer.start()
    for k in range(1, 6):
        clock.advance(0.03)  # the tick's work
        assert pacer.wait() is True
        assert clock.now() == pytest.approx(5.0 + 0.1 * k)
    assert pacer.overruns == 0


def test_an_overrun_is_counted_and_the_control_loop_starts_again_from_now():
    clock = FakeClock()
    pacer = Pacer(clock, 0.1)
    pacer.start()
    clock.advance(0.25)  # 0.15 s late
    assert pacer.wait() is False and pacer.overruns == 1
    assert clock.now() == pytest.approx(0.25)  # nothing slept
    clock.advance(0.01)
    assert pacer.wait() is True
    assert clock.now() == pytest.approx(0.35)  # one period after the late tick, not back on the old grid


def test_the_recorder_keeps_its_grid_through_a_lag_of_up_to_one_period():
    clock = FakeClock()
    pacer = Pacer(clock, 0.1, resync=0.1)
    pacer.start()
    clock.advance(0.15)  # 0.05 s late: within one period
    assert pacer.wait() is False and pacer.overruns == 1
    clock.advance(0.01)
    assert pacer.wait() is True
    assert clock.now() == pytest.approx(0.2)  # back on the grid 0.1, 0.2, ...
    clock.advance(0.35)  # now 0.55, due at 0.3: 0.25 s late, more than a period
    assert pacer.wait() is False
    clock.advance(0.01)
    pacer.wait()
    assert clock.now() == pytest.approx(0.65)  # the schedule started again at 0.55


def test_a_tick_exactly_on_time_is_an_overrun_that_changes_nothing():
    clock = FakeClock()
    pacer = Pacer(clock, 0.5)
    clock.advance(0.5)
    assert pacer.wait() is False and pacer.overruns == 1 and pacer.next_tick == pytest.approx(0.5)


@pytest.mark.parametrize("period, resync", [(0.0, 0.0), (-1.0, 0.0), (float("nan"), 0.0), (0.1, -0.1)])
def test_a_period_or_resync_that_is_not_a_time_is_refused(period, resync):
    with pytest.raises(ValueError):
        Pacer(FakeClock(), period, resync)


def test_the_rate_is_measured_over_the_last_ticks():
    meter = RateMeter(window=5)
    assert meter.rate() == 0.0
    meter.mark(0.0)
    assert meter.rate() == 0.0
    for t in (0.1, 0.2, 0.3, 0.4):
        meter.mark(t)
    assert meter.rate() == pytest.approx(10.0)
    for t in (0.6, 0.8, 1.0, 1.2):  # the window now holds 0.4 .. 1.2 only
        meter.mark(t)
    assert meter.rate() == pytest.approx(5.0)


def test_latency_stats_of_the_finite_values():
    values = [3.0, 1.0, 2.0, float("nan"), float("inf"), 4.0]
    s = latency_stats(values)
    finite = np.array([3.0, 1.0, 2.0, 4.0])
    assert s == {"p50": float(np.median(finite)), "p95": float(np.percentile(finite, 95)), "max": 4.0, "n": 4}
    assert latency_stats([]) is None and latency_stats([math.nan]) is None
    assert latency_stats([1.23456, 2.34567], digits=3) == {"p50": 1.79, "p95": 2.29, "max": 2.346, "n": 2}


def test_the_replay_reads_its_times_from_its_clock(tmp_path, monkeypatch):
    """dssp-replay without an arm on a fake clock: the control loop paces on that clock, so every action goes
    through the safety layer one period after the one before on the clock's timeline, never at the machine's."""
    from dssp_data.dataset_layout import Episode
    from dssp_data.replay_buffer_writer import write_replay_buffer
    from hardware import run_loop
    from hardware.episode_replay import replay_episode

    steps = 12
    action = np.zeros((steps, 7), np.float32)
    action[:, 0] = np.linspace(0.0, 0.1, steps)
    path = tmp_path / "ep.zarr"
    write_replay_buffer(
        path, [Episode(np.zeros((steps, 4, 3), np.float32), action.copy(), action)], attrs={"control_rate_hz": 20.0}
    )
    seen = []
    real_decide = run_loop.Safety.decide

    def decide(self, action, **kw):
        seen.append(kw["now"])
        return real_decide(self, action, **kw)

    monkeypatch.setattr(run_loop.Safety, "decide", decide)
    result = replay_episode(path, 0, None, events=lambda _: None, clock=FakeClock(100.0))
    assert result["steps"] == result["ticks"] == steps and result["ended_by"] == "done" and result["sent"] == 0
    assert seen == pytest.approx([100.0 + k / 20.0 for k in range(steps)], abs=1e-9)
