"""health.py: robust baseline, sigma and absolute alarms, STALE, and the diagnostics messages."""
import numpy as np
import pytest

from topometric_ros import bag
from topometric_ros.config import HealthConfig
from topometric_ros.health import (STATUS_NAME, Health, diagnostic_array, diagnostic_status, window_values)
from topometric_ros.pipeline import WindowResult


def result(pne=1.0, cpv=0.01, n_planes=20, t=0.0):
    return WindowResult([t, t + 0.8], pne=pne, cpv=cpv, n_planes=n_planes, n_groups=5,
                        timings={"latency_ms": 12.5})


def learned(cfg=None, rng=None, n=10):
    """A Health with a baseline from n quiet windows (PNE ~ 1 ± 0.02, CPV ~ 0.01 ± 0.0005)."""
    rng = rng or np.random.default_rng(0)
    h = Health(cfg or HealthConfig(baseline_windows=n))
    for _ in range(n):
        r = result(1.0 + 0.02 * rng.standard_normal(), 0.01 + 0.0005 * rng.standard_normal())
        h.assess(r)
    return h


def test_learning_then_ok():
    h = Health(HealthConfig(baseline_windows=3))
    r = result()
    h.assess(r)
    assert r.level == "OK" and "learning baseline (1/3" in r.message
    h = learned()
    r = result(1.01, 0.0101)
    assert h.assess(r).level == "OK"
    assert r.message.startswith("consistent")


def test_rotation_drift_raises_pne_alarm_with_sigma_reason():
    h = learned()
    med, sigma = h.baseline("pne")
    r = result(pne=med + 5 * sigma)
    a = h.assess(r)
    assert r.level == "WARN" and a.z["pne"] == pytest.approx(5.0)
    assert r.message == "rotation drift: PNE 5.0σ above baseline"
    r = result(pne=med + 9 * sigma)
    assert h.assess(r).level == "ERROR"


def test_translation_drift_raises_cpv_alarm():
    h = learned()
    med, sigma = h.baseline("cpv")
    r = result(cpv=med + 4.5 * sigma)
    h.assess(r)
    assert r.level == "WARN" and "translation drift: CPV 4.5σ" in r.message


def test_alarm_level_is_monotonic_in_the_metric():
    h = learned()
    med, sigma = h.baseline("pne")
    levels = []
    for k in np.linspace(0, 12, 25):
        levels.append({"OK": 0, "WARN": 1, "ERROR": 2}[h.assess(result(pne=med + k * sigma)).level])
    assert levels == sorted(levels) and levels[0] == 0 and levels[-1] == 2


def test_alarms_do_not_teach_the_baseline():
    h = learned()
    before = h.baseline("pne")
    for _ in range(100):
        h.assess(result(pne=before[0] + 20 * before[1]))
    assert h.baseline("pne") == before
    assert h.assess(result(pne=before[0] + 20 * before[1])).level == "ERROR"  # drift never becomes normal


def test_quiet_sites_get_a_relative_floor():
    """A perfectly constant baseline (MAD 0) must not make every tiny wobble an alarm."""
    h = Health(HealthConfig(baseline_windows=5, rel_floor=0.05))
    for _ in range(5):
        h.assess(result(1.0, 0.01))
    assert h.baseline("pne") == (1.0, pytest.approx(0.05))
    assert h.assess(result(1.1, 0.0102)).level == "OK"
    assert h.assess(result(1.25, 0.01)).level == "WARN"


def test_absolute_limits_apply_from_the_first_window():
    h = Health(HealthConfig(pne_warn=2.0, pne_error=3.0, cpv_error=0.05))
    r = result(pne=2.5)
    h.assess(r)
    assert r.level == "WARN" and "above limit 2" in r.message
    r = result(cpv=0.06)
    assert h.assess(r).level == "ERROR"


def test_undefined_metrics_and_few_planes_warn():
    h = learned()
    r = result(pne=float("nan"))
    assert h.assess(r).level == "WARN" and "undefined" in r.message
    r = result(n_planes=1)
    assert h.assess(r).level == "WARN" and "too few planes" in r.message


def test_stale_in_any_clock():
    h = Health(HealthConfig(stale_after_s=5.0))
    assert h.stale(100.0, 99.0, 99.5) is None
    level, why = h.stale(106.0, 100.0, 105.9)
    assert level == "STALE" and why == "no scans for 6.0 s"
    assert h.stale(50.0, 100.0, 100.0) is None  # sim clock jumped back: not stale
    assert "no odometry yet" in h.stale(0.0, 0.0, None)[1]


def test_diagnostics_messages_round_trip_through_cdr():
    types = bag.msg_types()
    r = result(pne=1.234567891, cpv=0.0123)
    r.level, r.message = "WARN", "rotation drift: PNE 5.0σ above baseline"
    values = window_values(r, {"dropped_windows": 2, "scans_in": 10}, {"rpe_estimate": 0.5})
    assert values["pne"] == "1.23457" and values["dropped_windows"] == "2" and values["window_end"] == "0.8"
    status = diagnostic_status(types, r.level, r.message, values, hardware_id="velodyne")
    arr = diagnostic_array(types, 1_700_000_000.25, [status])
    store = bag.typestore()
    back = store.deserialize_cdr(store.serialize_cdr(arr, arr.__msgtype__), arr.__msgtype__)
    assert back.header.stamp.sec == 1_700_000_000 and abs(back.header.stamp.nanosec - 250_000_000) < 1000
    s = back.status[0]
    assert s.level == 1 and s.name == STATUS_NAME and s.hardware_id == "velodyne"
    assert {kv.key: kv.value for kv in s.values}["rpe_estimate"] == "0.5"
    with pytest.raises(ValueError):
        diagnostic_status(types, "BAD", "", {})
