"""Clock faults: clouds stamped against another clock than the odometry are reported as such, not as drift."""
from __future__ import annotations

import numpy as np
import pytest

from topometric_ros.config import load_config
from topometric_ros.monitor import ClockWatch


def test_the_clock_watch_flags_a_jump_either_way_and_only_a_jump():
    w = ClockWatch(0.5)
    for k in range(10):  # odometry stamped at arrival, clouds 0.12 s before it, a few ms of jitter
        assert w.odometry(100.0 + 0.05 * k, 100.0 + 0.05 * k + 0.003 * (k % 3)) == ""
    for k in range(5):
        assert w.cloud(100.0 + 0.2 * k, 100.12 + 0.2 * k + 0.004 * (k % 2)) == ""
    assert "jumped +1.00 s" in w.cloud(102.0, 101.12)  # stamped a second ahead
    assert "jumped -1.00 s" in w.cloud(100.0, 101.12)  # a second behind
    assert w.cloud(101.2, 101.32) == ""  # back on the clock: fine again
    assert "odometry stamps jumped" in w.odometry(110.0, 104.0)
    assert ClockWatch(0.5).cloud(5.0, None) == ""  # no receive times: nothing to compare


def test_a_clock_step_that_stays_becomes_the_odometry_clock_and_clouds_are_judged_against_it():
    """The robot's clock steps 1000 s (both streams' stamps, not their receive times): RELEARN odometry
    messages are faults, then the new offset is the stream's clock, and clouds on it fit again. A cloud
    stream left on the old clock stays a fault (it cannot be paired); a short burst of odometry faults never
    moves the clock."""
    w = ClockWatch(0.5)
    t = 100.0
    for k in range(10):
        assert w.odometry(t + 0.05 * k, t + 0.05 * k) == "" and w.cloud(t + 0.05 * k - 0.1, t + 0.05 * k) == ""
    for k in range(3):  # a burst: faults, and the clock stays
        assert "jumped +5.00 s" in w.odometry(105.5 + 0.05 * k, 100.5 + 0.05 * k)
    assert w.odometry(100.7, 100.7) == ""
    results = [w.odometry(1100.8 + 0.05 * k, 100.8 + 0.05 * k) for k in range(ClockWatch.RELEARN + 5)]
    assert all("jumped +1000.00 s" in r for r in results[:ClockWatch.RELEARN - 1]), results
    assert results[ClockWatch.RELEARN - 1:] == [""] * 6
    assert w.cloud(1102.0 - 0.1, 102.0) == ""  # a cloud on the stepped clock fits
    assert "cloud stamps jumped -1000.00 s" in w.cloud(102.1 - 0.1, 102.1)  # one left on the old clock does not


@pytest.mark.parametrize("offset", [1.0, -1.0, 5.0])
def test_a_cloud_clock_jump_is_a_clock_fault_within_two_windows_and_no_drift_alarm(tmp_path, offset):
    from topometric_ros.replay import ReplayOptions, replay
    from topometric_ros.sim.drift import DriftSpec
    from topometric_ros.sim.writer import START_TIME, SimConfig, simulate

    path = tmp_path / "bag"
    simulate(SimConfig(scene="office1", frames=120, clock_jump=(12.0, offset, 6.0), drift=DriftSpec("none")),
             path, progress=False)
    res = replay(path, tmp_path / "out", load_config(overrides={"segmentation.mode": "labels"}),
                 ReplayOptions(plot=False, progress=False))
    faults = res.summary["clock_faults"]
    window_s = 5 / 5.0  # five scans at 5 Hz
    assert faults and faults[0]["received"] - (START_TIME + 12.0) <= 2 * window_s
    assert f"jumped {offset:+.2f} s" in faults[0]["message"]
    assert [w["level"] for w in res.windows] == ["OK"] * len(res.windows)  # no drift alarm, before or after
    assert res.summary["counters"]["dropped_clock"] == pytest.approx(6.0 * 5.0, abs=1)
    assert np.isfinite([w["pne"] for w in res.windows]).all()


def test_a_cloud_clock_jump_shows_through_a_sidecar_odometry_bag_on_another_clock(tmp_path, split_off_odometry):
    """The odometry in a sidecar bag written at its stamps, the recording's receive times 1000 s later: each
    topic's receive times are put on one clock, so the clouds' 1 s jump is still a clock fault, and no STALE or
    'odometry ends' note comes from comparing the two recordings' clocks."""
    from topometric_ros.replay import ReplayOptions, replay
    from topometric_ros.sim.drift import DriftSpec
    from topometric_ros.sim.writer import START_TIME, SimConfig, simulate

    path = tmp_path / "bag"
    simulate(SimConfig(scene="office1", frames=120, clock_jump=(12.0, 1.0, 6.0), drift=DriftSpec("none")),
             path, progress=False)
    recording, sidecar = split_off_odometry(path, tmp_path / "recording", tmp_path / "sidecar")
    res = replay(recording, tmp_path / "out", load_config(overrides={"segmentation.mode": "labels"}),
                 ReplayOptions(beside=(sidecar,), plot=False, progress=False))
    faults = res.summary["clock_faults"]
    assert faults and "cloud stamps jumped +1.00 s" in faults[0]["message"], faults
    assert faults[0]["received"] - (START_TIME + 12.0) <= 2.0
    assert [w["level"] for w in res.windows] == ["OK"] * len(res.windows)
    assert not any(k in n for n in res.summary["notes"] for k in ("odometry ends", "STALE")), res.summary["notes"]


def _steady(w: ClockWatch, t: float = 100.0) -> None:
    """Odometry stamped at arrival and clouds 0.1 s before theirs: both fit."""
    for k in range(10):
        assert w.odometry(t + 0.05 * k, t + 0.05 * k) == "" and w.cloud(t + 0.05 * k - 0.1, t + 0.05 * k) == ""


def test_odometry_stamps_that_jump_back_are_a_clock_fault():
    w = ClockWatch(0.5)
    _steady(w)
    assert "odometry stamps jumped -6.00 s" in w.odometry(95.0, 101.0)


def test_odometry_faults_that_scatter_never_become_the_clock():
    """Twice RELEARN odometry faults, 5 s and 10 s ahead by turns: no one new clock, so all stay faults."""
    w = ClockWatch(0.5)
    _steady(w)
    t = 101.0 + 0.05 * np.arange(2 * ClockWatch.RELEARN)
    results = [w.odometry(s + (5.0 if k % 2 else 10.0), s) for k, s in enumerate(t)]
    assert all("odometry stamps jumped" in r for r in results), results


def test_clouds_on_another_clock_stay_faults_however_many_come():
    w = ClockWatch(0.5)
    _steady(w)
    results = [w.cloud(101.0 + 0.2 * k + 0.9, 101.0 + 0.2 * k) for k in range(30)]  # 1 s ahead of the others
    assert all("cloud stamps jumped +1.00 s" in r for r in results), results
    assert w.cloud(108.0 - 0.1, 108.0) == ""  # back on the clock


def test_right_after_a_clock_step_is_learned_the_old_clock_is_a_fault():
    """The RELEARN-th odometry message on the stepped clock makes it the clock: the very next cloud or odometry
    message on the old one is a fault."""
    w = ClockWatch(0.5)
    _steady(w)
    results = [w.odometry(1101.0 + 0.05 * k, 101.0 + 0.05 * k) for k in range(ClockWatch.RELEARN)]
    assert results[-1] == "" and all("jumped" in r for r in results[:-1])
    assert "cloud stamps jumped -1000.00 s" in w.cloud(102.0 - 0.1, 102.0)
    assert "odometry stamps jumped -1000.00 s" in w.odometry(102.05, 102.05)
