"""health.py: robust baseline, sigma and absolute alarms, STALE, and the diagnostics messages."""
import copy
from dataclasses import replace

import numpy as np
import pytest

from topometric_ros import bag
from topometric_ros.config import HealthConfig
from topometric_ros.health import (STATUS_NAME, Health, diagnostic_array, diagnostic_status, from_scale,
                                   status_name, window_values)
from topometric_ros.pipeline import WindowResult


def result(pne=1.0, cpv=0.01, n_planes=20, t=0.0):
    return WindowResult([t, t + 0.8], pne=pne, cpv=cpv, n_planes=n_planes, n_groups=5,
                        timings={"latency": 12.5})


def learned(cfg=None, rng=None, n=10):
    """A Health with a baseline from n windows (PNE ~ 1 ± 0.5 nats, CPV ~ 0.01 m² × e^(±0.6))."""
    rng = rng or np.random.default_rng(0)
    h = Health(cfg or HealthConfig(baseline_windows=n, warn_sigma=4.0, error_sigma=8.0, warn_persist=1))
    for _ in range(n):
        r = result(1.0 + 0.5 * rng.standard_normal(), 0.01 * np.exp(0.6 * rng.standard_normal()))
        h.assess(r)
    return h


def test_learning_then_ok():
    h = Health(HealthConfig(baseline_windows=3))
    r = result()
    h.assess(r)
    assert r.level == "OK" and "learning baseline (1/3" in r.message
    h = learned()
    r = result(1.1, 0.011)
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
    med, sigma = h.baseline("cpv")  # on the ln scale
    r = result(cpv=float(np.exp(med + 4.5 * sigma)))
    a = h.assess(r)
    assert r.level == "WARN" and r.message.startswith("translation drift: CPV 4.5σ")  # the alarm leads
    assert a.warn_at["cpv"] == pytest.approx(from_scale("cpv", med + 4 * sigma))


def test_alarm_level_is_monotonic_in_the_metric():
    h = learned()
    med, sigma = h.baseline("pne")
    levels = []
    for k in np.linspace(0, 12, 25):
        fresh = copy.deepcopy(h)
        levels.append({"OK": 0, "WARN": 1, "ERROR": 2}[fresh.assess(result(pne=med + k * sigma)).level])
    assert levels == sorted(levels) and levels[0] == 0 and levels[-1] == 2


def test_a_ramp_does_not_creep_into_the_baseline():
    """Drift that builds up over tens of windows is still caught: only calm windows (z < warn/2) teach."""
    h = learned()
    med, sigma = h.baseline("pne")
    levels = [h.assess(result(pne=med + 0.5 * k * sigma)).level for k in range(40)]  # up to 20σ in 40 windows
    assert levels[-1] == "ERROR" and h.baseline("pne")[0] < med + 2 * sigma


def test_alarms_do_not_teach_the_baseline():
    h = learned()
    before = h.baseline("pne")
    for _ in range(100):
        h.assess(result(pne=before[0] + 20 * before[1]))
    assert h.baseline("pne") == before
    assert h.assess(result(pne=before[0] + 20 * before[1])).level == "ERROR"  # drift never becomes normal


def test_a_metric_still_learning_does_not_let_the_other_learn_from_alarms():
    """CPV undefined in every other window (few co-planar planes) keeps CPV's baseline short while PNE's is in:
    PNE's alarmed windows still do not teach PNE's baseline, and CPV's calm values still teach CPV's."""
    h = Health(HealthConfig(baseline_windows=10, warn_sigma=4.0, error_sigma=8.0, warn_persist=1))
    rng = np.random.default_rng(1)
    for k in range(18):
        h.assess(result(1.0 + 0.5 * rng.standard_normal(), 0.01 if k % 2 else float("nan")))
    assert h.baseline("pne") is not None and h.baseline("cpv") is None  # 18 PNE values, 9 CPV of 10
    before = h.baseline("pne")
    for _ in range(5):
        assert h.assess(result(pne=before[0] + 13 * before[1], cpv=0.01)).level == "ERROR"
    assert h.baseline("pne") == before
    assert h.baseline("cpv") is not None  # 9 + 5 CPV values: CPV's own learning went on


def test_quiet_sites_get_a_floor_on_the_spread():
    """A perfectly constant baseline (MAD 0) must not make every tiny wobble an alarm."""
    h = Health(HealthConfig(baseline_windows=5, pne_min_sigma=0.2, cpv_min_sigma=0.3, warn_sigma=4.0, warn_persist=1))
    for _ in range(5):
        h.assess(result(-9.0, 1e-5))
    assert h.baseline("pne") == (-9.0, pytest.approx(0.2))
    assert h.baseline("cpv") == (pytest.approx(np.log(1e-5)), pytest.approx(0.3))
    assert h.assess(result(-8.5, 1.5e-5)).level == "OK"  # 2.5σ, ln 1.5 = 0.4 -> 1.4σ
    assert h.assess(result(-8.1, 1e-5)).level == "WARN"  # 4.5σ


def test_cpv_is_scale_free():
    """The same relative rise of CPV alarms the same, whatever the site's CPV level (log scale)."""
    levels = []
    for scale in (1e-6, 1e-3, 1.0):
        h = Health(HealthConfig(baseline_windows=10, warn_persist=1))
        for r in [result(1.0, 0.01 * scale * f) for f in (1, 1.2, 0.8, 1.1, 0.9)] * 2:
            h.assess(r)
        levels.append([h.assess(result(1.0, 0.01 * scale * f)).level for f in (1.5, 5, 100)])
    assert levels[0] == levels[1] == levels[2] and levels[0][-1] != "OK"


def test_absolute_limits_apply_from_the_first_window():
    h = Health(HealthConfig(pne_warn=2.0, pne_error=3.0, cpv_error=0.05))  # pne_warn 0 would mean off
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


def test_a_scan_that_lines_up_with_no_other_is_a_pose_jump_at_once():
    """agreement under agreement_warn: WARN from the first window, named; at the limit, NaN or with the rule
    off (0): no alarm."""
    def judged(agreement, **cfg):
        r = result()
        r.agreement = agreement
        Health(HealthConfig(**cfg)).assess(r)
        return r

    low = judged(0.3)
    assert low.level == "WARN" and low.message.startswith("pose jump") and "30%" in low.message
    for quiet in (judged(0.4), judged(float("nan")), judged(0.3, agreement_warn=0.0)):
        assert quiet.level == "OK" and "pose jump" not in quiet.message


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
    assert values["pne"] == "1.234567891" and values["dropped_windows"] == "2" and values["window_end"] == "0.8"
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


def test_key_values_keep_full_precision():
    """Stamps of today's clock (1.7e9 s) and every float read back bit for bit (6 digits would give 1.7e+09)."""
    r = result(pne=-2.718281828459045, cpv=1.0 / 3.0, t=1_700_000_012.2)
    r.timings["latency"] = float("nan")
    values = window_values(r, {"scans_in": 10})
    assert values["window_start"] == "1700000012.2" and float(values["window_end"]) == 1_700_000_012.2 + 0.8
    for key in ("pne", "cpv", "window_start", "window_end"):
        assert float(values[key]) == {"pne": r.pne, "cpv": r.cpv, "window_start": r.stamps[0],
                                      "window_end": r.stamps[-1]}[key]
    assert values["latency_ms"] == "nan" and values["scans_in"] == "10"
    assert window_values(result(pne=np.float32(0.1)))["pne"] == repr(float(np.float32(0.1)))


def test_status_names_follow_diagnostic_updater():
    assert STATUS_NAME == "topometric_monitor: map consistency"
    assert status_name("robot1_monitor") == "robot1_monitor: map consistency"


def test_failing_needs_every_scan_failing_for_fail_after_s():
    """Scans arrive but each one fails: ERROR once the streak lasts health.fail_after_s, with counters and
    the last error; a success ends the streak (the Monitor resets failing_since)."""
    h = Health(HealthConfig(fail_after_s=1.0))
    counters = {"scans_in": 7, "scan_errors": 6, "dropped_bad_scan": 0}
    assert h.failing(10.0, None, 5.0, "", counters) is None  # the newest scan succeeded
    assert h.failing(10.9, 10.0, 5.0, "boom", counters) is None  # not long enough yet
    level, why = h.failing(11.0, 10.0, 5.0, "labels mode: no label field", counters)
    assert level == "ERROR" and why == ("no scan processed for 6.0 s, every scan fails (scan_errors 6): "
                                        "labels mode: no label field")
    assert h.failing(11.0, 10.0, None, "x", counters)[1].startswith("no scan processed yet")


def test_persistence_ignores_one_odd_window_but_warns_on_the_second():
    """warn_persist 2 of 2: one window at 6σ (or even 9σ) stays OK (named as 'watch'), two in a row alarm on
    the second, at the level of the second."""
    cfg = HealthConfig(baseline_windows=10, warn_sigma=4.0, error_sigma=8.0, warn_persist=2, persist_windows=2,
                       pne_min_sigma=0.5)
    h = learned(cfg)
    med, sigma = h.baseline("pne")
    odd = result(pne=med + 6 * sigma)
    assert h.assess(odd).level == "OK" and "watch" in odd.message
    h.assess(result(pne=med))  # back to normal: the odd window is forgotten
    assert h.assess(result(pne=med + 6 * sigma)).level == "OK"
    second = result(pne=med + 6 * sigma)
    assert h.assess(second).level == "WARN" and "2 of the last 2" in second.message
    fresh = learned(cfg)
    assert fresh.assess(result(pne=med + 9 * sigma)).level == "OK"
    assert fresh.assess(result(pne=med + 9 * sigma)).level == "ERROR"
    limit = learned(HealthConfig(baseline_windows=10, warn_persist=2, pne_error=med + 1.0))
    assert limit.assess(result(pne=med + 2.0)).level == "ERROR"  # absolute limits act at once


def test_each_metric_counts_its_own_persistence():
    """One odd PNE window then one odd CPV window: neither metric was odd twice, so both stay 'watch' (OK);
    a second CPV window then alarms on CPV alone."""
    cfg = HealthConfig(baseline_windows=10, warn_sigma=4.0, error_sigma=8.0, warn_persist=2, persist_windows=2,
                       pne_min_sigma=0.5)
    h = learned(cfg)
    (pne_med, pne_sigma), (cpv_med, cpv_sigma) = h.baseline("pne"), h.baseline("cpv")
    cpv_at = lambda k: from_scale("cpv", cpv_med + k * cpv_sigma)  # noqa: E731
    assert h.assess(result(pne=pne_med + 6 * pne_sigma)).level == "OK"
    odd_cpv = result(pne=pne_med, cpv=cpv_at(9))
    assert h.assess(odd_cpv).level == "OK" and "watch: CPV 9.0σ above baseline in 1 of 2" in odd_cpv.message
    again = result(pne=pne_med, cpv=cpv_at(9))
    assert h.assess(again).level == "ERROR" and "CPV 9.0σ" in again.message and "PNE" not in again.message


def test_with_persistence_every_level_comes_one_window_later_for_a_steady_rise():
    """A steady rise (drift lasts): 2-of-2 persistence gives, from the second window on, the levels the
    single-window rule gave one window earlier."""
    single = learned(HealthConfig(baseline_windows=10, warn_sigma=4.0, error_sigma=8.0, warn_persist=1))
    double = learned(HealthConfig(baseline_windows=10, warn_sigma=4.0, error_sigma=8.0, warn_persist=2))
    med, sigma = single.baseline("pne")
    for k in np.linspace(0, 10, 21):
        a, b = single.assess(result(pne=med + k * sigma)).level, double.assess(result(pne=med + k * sigma)).level
        assert b == (a if k > 4.0 else "OK")  # the first window above 4σ (k = 4.0) is the one held back


def _moving(rot=0.0, trans=0.0, speed=0.0, turn=0.0, rot_se=float("nan"), trans_se=float("nan")):
    r = WindowResult([0.0, 0.8], pne=1.0, cpv=0.01, n_planes=40, n_groups=10, rot_rate=rot, trans_rate=trans,
                     speed=speed, turn_rate=turn, rot_rate_se=rot_se, trans_rate_se=trans_se)
    return r


def test_relative_limits_grow_with_speed_and_turning_like_kitti():
    """Limits = floor + share of the motion: rotation 0.5 °/s + 0.05 °/m × speed + 0.01 × turn rate, translation
    0.04 m/s + 1 % of speed (+ trans_per_deg × turn rate); ERROR at twice that. With no learning the configured
    floors hold."""
    c = HealthConfig(noise_windows=0, warn_persist=1, rate_persist=1, rot_per_m=0.05, rot_per_deg=0.01,
                     trans_per_m=0.01, trans_per_deg=0.0)
    h = Health(c)
    limits = h.rates.limits(_moving(speed=10.0, turn=50.0))
    assert limits["rot_rate"] == pytest.approx((0.5 + 0.5 + 0.5, 3.0))
    assert limits["trans_rate"] == pytest.approx((0.04 + 0.1, 0.28))
    # the same 0.12 m/s drift: ERROR standing still, WARN at 4 m/s, OK at 10 m/s (monotonic in speed)
    levels = [Health(c).assess(_moving(trans=0.12, speed=v)).level for v in (0.0, 4.0, 10.0)]
    assert levels == ["ERROR", "WARN", "OK"]
    r = _moving(rot=2.0, speed=1.0)
    Health(c).assess(r)
    assert r.level == "ERROR" and r.message.startswith("rotation drift: 2 °/s (limit 1.1 at 1 m/s")
    turning = replace(c, trans_per_deg=0.002)  # translation per degree turned: 0.04 + 0.1 + 0.002 x 50
    assert Health(turning).rates.limits(_moving(speed=10.0, turn=50.0))["trans_rate"] == pytest.approx((0.24, 0.48))
    assert Health(turning).rates.limits(_moving(speed=10.0))["trans_rate"] == pytest.approx((0.14, 0.28))


def test_the_noise_floor_is_learned_per_run_within_bounds():
    """A jittery SLAM: 0.35 °/s and 0.03 m/s standing still in its first windows. While learning, the floors
    are noise_max_factor × the configured ones; then 2 × the 0.75-quantile, clipped to [floor, 3 × floor]."""
    c = HealthConfig(noise_windows=15, warn_persist=1, rate_persist=1, noise_quantile=0.75, noise_margin=2.0,
                     noise_max_factor=3.0)
    h = Health(c)
    assert h.rates.limits(_moving())["rot_rate"][0] == pytest.approx(1.5)  # learning: 3 × 0.5
    rng = np.random.default_rng(0)
    for k in range(15):
        r = _moving(rot=0.35 + 0.01 * rng.standard_normal(), trans=0.03 + 0.001 * rng.standard_normal())
        h.assess(r)
        assert r.level == "OK" and (k == 14) != ("learning the rates' noise floor" in r.message)
    lim = h.rates.limits(_moving())
    assert lim["rot_rate"][0] == pytest.approx(0.7, abs=0.03)  # 2 × ~0.355: above the 0.5 configured
    assert lim["trans_rate"][0] == pytest.approx(0.06, abs=0.005)
    assert h.assess(_moving(rot=0.6)).level == "OK" and h.assess(_moving(rot=0.8)).level == "WARN"
    quiet = Health(c)
    for _ in range(15):
        quiet.assess(_moving(rot=0.01, trans=0.001))
    assert quiet.rates.limits(_moving())["rot_rate"][0] == pytest.approx(0.5)  # never below the configured floor
    noisy = Health(c)
    for _ in range(15):
        noisy.assess(_moving(rot=5.0, trans=1.0))
    assert noisy.rates.limits(_moving())["trans_rate"][0] == pytest.approx(0.12)  # never above 3 × it


def test_rate_persistence_needs_repeated_windows_between_warn_and_error():
    """rate_persist 2 of 2: one window above the WARN limit (1.0 °/s standing still here) stays OK, named as
    'watch'; the next one above it alarms; a window at the ERROR limit (2.0) alarms at once; rate_persist 1 is
    today's rule (WARN at once)."""
    c = HealthConfig(noise_windows=0, warn_persist=1, rot_floor=1.0, rate_persist=2, persist_windows=2)
    h = Health(c)
    r = _moving(rot=1.5)
    assert h.assess(r).level == "OK" and "watch: rotation drift 1.5 °/s above limit 1 in 1 of 2" in r.message
    r = _moving(rot=1.2)
    assert h.assess(r).level == "WARN" and "(2 of the last 2 windows)" in r.message
    assert h.assess(_moving(rot=0.5)).level == "OK"  # back under: the next single window waits again
    assert h.assess(_moving(rot=1.5)).level == "OK"
    assert Health(c).assess(_moving(rot=2.0)).level == "ERROR"
    assert Health(replace(c, rate_persist=1)).assess(_moving(rot=1.5)).level == "WARN"
    # absolute limits are a hard line: at once whatever rate_persist says
    absolute = Health(replace(c, rate_limits="absolute", rot_rate_warn=1.0, rot_rate_error=2.0))
    assert absolute.assess(_moving(rot=1.5)).level == "WARN"


def test_rate_sigma_judges_a_rate_by_its_lower_bound():
    """rate_sigma 2: 1.5 °/s ± 0.1 (lower bound 1.3) is over the 1.0 °/s WARN limit, 1.5 ± 0.4 (0.7) is not;
    2.5 ± 0.1 is at ERROR (limit 2.0), 2.5 ± 0.4 (1.7) only at WARN. rate_sigma 0 or no standard error: the
    rate itself, as before."""
    c = HealthConfig(noise_windows=0, warn_persist=1, rot_floor=1.0, rate_persist=1, rate_sigma=2.0)
    r = _moving(rot=1.5, rot_se=0.1)
    assert Health(c).assess(r).level == "WARN" and "rotation drift: 1.5 ± 0.1 °/s (limit 1" in r.message
    assert Health(c).assess(_moving(rot=1.5, rot_se=0.4)).level == "OK"
    assert Health(c).assess(_moving(rot=2.5, rot_se=0.1)).level == "ERROR"
    assert Health(c).assess(_moving(rot=2.5, rot_se=0.4)).level == "WARN"
    assert Health(c).assess(_moving(rot=1.5)).level == "WARN"  # no standard error: the rate itself
    assert Health(replace(c, rate_sigma=0.0)).assess(_moving(rot=1.5, rot_se=0.4)).level == "WARN"


def test_pose_noise_is_a_warn_of_its_own_when_the_rates_scatter_more_than_the_limit():
    """noise_warn 1: a rate whose standard error reaches its WARN limit (1.0 °/s here) is pose noise (WARN at
    once, named so), even with the rate itself under the limit; just under it, or noise_warn 0, stays OK."""
    c = HealthConfig(noise_windows=0, warn_persist=1, rot_floor=1.0, rate_persist=2, rate_sigma=1.5, noise_warn=1.0)
    r = _moving(rot=0.8, rot_se=1.1)
    assert Health(c).assess(r).level == "WARN" and r.message.startswith("pose noise: rotation drift 0.8 ± 1.1 °/s")
    assert Health(c).assess(_moving(rot=0.8, rot_se=0.9)).level == "OK"
    assert Health(replace(c, noise_warn=0.0)).assess(_moving(rot=0.8, rot_se=1.1)).level == "OK"


def test_the_baseline_spread_is_1_4826_mad():
    h = Health(HealthConfig(baseline_windows=5, pne_min_sigma=0.0, warn_persist=1))
    for pne in (1.0, 2.0, 3.0, 4.0, 5.0):
        h.assess(result(pne=pne))
    assert h.baseline("pne") == (3.0, pytest.approx(1.4826))  # MAD 1


def test_a_window_alarmed_for_another_reason_does_not_teach_the_baseline():
    """Too few planes (WARN) with a calm PNE (1σ): 30 such windows leave the baseline as it was."""
    h = learned()
    before = h.baseline("pne")
    for _ in range(30):
        assert h.assess(result(pne=before[0] + before[1], n_planes=1)).level == "WARN"
    assert h.baseline("pne") == before


def test_warn_at_and_error_at_are_the_lower_of_the_sigma_and_the_absolute_limit():
    h = learned(HealthConfig(baseline_windows=10, warn_sigma=4.0, error_sigma=8.0, warn_persist=1, pne_warn=1.2,
                             pne_error=50.0))
    med, sigma = h.baseline("pne")
    assert med + 4 * sigma > 1.2 and med + 8 * sigma < 50.0
    a = h.assess(result(pne=med))
    assert a.warn_at["pne"] == pytest.approx(1.2) and a.error_at["pne"] == pytest.approx(med + 8 * sigma)


def test_a_cpv_of_zero_is_taken_at_the_tiny_floor():
    """A noise-free window can give CPV 0 exactly: compared as ln 1e-12, not −∞."""
    h = Health(HealthConfig(baseline_windows=3, warn_persist=1))
    for _ in range(3):
        h.assess(result(cpv=0.0))
    assert h.baseline("cpv")[0] == pytest.approx(np.log(1e-12))
    a = h.assess(result(cpv=0.0))
    assert a.level == "OK" and a.z["cpv"] == 0.0


def test_persistence_counts_its_windows_over_the_last_persist_windows():
    """warn_persist 2 of persist_windows 3: odd, normal, odd alarms on the second odd window."""
    cfg = HealthConfig(baseline_windows=10, warn_sigma=4.0, error_sigma=8.0, warn_persist=2, persist_windows=3,
                       pne_min_sigma=0.5)
    h = learned(cfg)
    med, sigma = h.baseline("pne")
    assert h.assess(result(pne=med + 6 * sigma)).level == "OK"
    assert h.assess(result(pne=med)).level == "OK"
    second = result(pne=med + 6 * sigma)
    assert h.assess(second).level == "WARN" and "2 of the last 3" in second.message


def test_a_cpv_alarm_is_named_by_the_drift_rate_nearer_its_limit():
    """Rates under their limits (0.5 °/s, 0.04 m/s standing still): at 80 % of the rotation limit and 10 % of the
    translation one a CPV rise is rotation drift; the other way round, translation drift."""
    h = learned(HealthConfig(baseline_windows=10, warn_sigma=4.0, error_sigma=8.0, warn_persist=1, noise_windows=0,
                             rate_persist=1))
    (pne_med, _), (med, sigma) = h.baseline("pne"), h.baseline("cpv")

    def message(rot, trans):
        r = WindowResult([0.0, 0.8], pne=pne_med, cpv=float(np.exp(med + 5 * sigma)), n_planes=20, n_groups=5,
                         rot_rate=rot, trans_rate=trans, speed=0.0, turn_rate=0.0)
        copy.deepcopy(h).assess(r)
        return r.message

    assert message(0.4, 0.004).startswith("rotation drift: CPV 5.0σ")
    assert message(0.05, 0.032).startswith("translation drift: CPV 5.0σ")


def test_the_noise_floor_is_the_margin_times_the_quantile_of_the_rates_above_the_motion_share():
    """At 10 m/s the motion share of the rotation limit is 0.5 °/s; rates 0.5 + 0.3 .. 0.6 °/s: the floor is
    2 × the 0.75-quantile of 0.3 .. 0.6 = 1.05 °/s."""
    c = HealthConfig(noise_windows=15, warn_persist=1, rate_persist=1, noise_quantile=0.75, noise_margin=2.0,
                     noise_max_factor=3.0, rot_per_m=0.05, rot_per_deg=0.0)
    h = Health(c)
    for excess in np.linspace(0.3, 0.6, 15):
        h.assess(_moving(rot=0.5 + excess, speed=10.0))
    assert h.rates.limits(_moving())["rot_rate"][0] == pytest.approx(1.05)


def test_a_rate_at_its_warn_limit_warns():
    c = HealthConfig(noise_windows=0, warn_persist=1, rot_floor=1.0, rate_persist=1)
    assert Health(c).assess(_moving(rot=1.0)).level == "WARN"


def test_a_pose_jump_names_its_scan_counting_from_one():
    r = WindowResult([10.0, 10.2, 10.4, 10.6, 10.8], pne=1.0, cpv=0.01, n_planes=20, n_groups=5, agreement=0.3,
                     agreement_scan=2)
    Health(HealthConfig()).assess(r)
    assert r.level == "WARN" and "pose jump: scan 3 of 5 (stamp 10.40)" in r.message
