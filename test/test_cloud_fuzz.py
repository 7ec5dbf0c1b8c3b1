"""Fuzzed PointCloud2 messages (benchmarks/bench_fuzz.py's hypothesis strategy: driver-like layouts, values from
plausible to garbage, up to three corruptions, as rosbags message classes or SimpleNamespace duck types):
read_scan raises CloudError and nothing else; Monitor.add_cloud never raises, accepts the cloud or counts it,
and an accepted cloud goes through the real per-scan pipeline without an error. The 10,000-case run is
``python -m benchmarks fuzz``. Below it, the bugs the fuzz found, one test each."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings

from benchmarks.bench_fuzz import CASE_LIMIT_S, check_case, clouds, new_monitor, restamp
from topometric_ros.bag import msg_types
from topometric_ros.cloud import CloudError, make_cloud, read_scan

MONITOR = {}


@pytest.mark.timeout(120)
@settings(max_examples=300, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(clouds())
def test_fuzzed_clouds_raise_only_cloud_error_and_never_stop_the_monitor(case):
    msg, applied = case
    monitor = MONITOR.setdefault("m", new_monitor())  # one monitor for the run: windows fill and get scored
    MONITOR["k"] = MONITOR.get("k", 0) + 1
    if "stamp" not in applied:
        restamp(msg, MONITOR["k"])
    out = check_case(msg, monitor)
    assert out["read_scan"] in ("ok", "CloudError"), (out, applied)
    assert out["add_cloud"] in ("accepted", "counted"), (out, applied)
    assert (out["read_scan"] == "CloudError") <= (out["add_cloud"] == "counted"), (out, applied)
    assert "processing_error" not in out, (out, applied)
    assert out["ms"] < 1000 * CASE_LIMIT_S


def _cloud(**arrays):
    n = len(next(iter(arrays.values()), range(3)))
    base = {"x": np.linspace(1, 5, n), "y": np.linspace(-2, 2, n), "z": np.zeros(n)}
    return make_cloud({**base, **arrays}, 1.7e9, "lidar", msg_types())


def test_x_of_count_2_is_a_cloud_error_and_counted_not_raised():
    """The issue's case: x count 2, y and z count 1 (a ValueError escaped Monitor.add_cloud)."""
    msg = _cloud(x=np.ones(4, np.float64))
    msg.fields[0].count = 2
    msg.fields[0].datatype = 7  # two float32 where one float64 was: same bytes, a count-2 x
    with pytest.raises(CloudError, match="count 1"):
        read_scan(msg)
    monitor = new_monitor()
    assert monitor.add_cloud(msg) is False
    assert monitor.counters["dropped_bad_scan"] == 1 and "count 1" in monitor.last_error


def test_header_faults_are_cloud_errors():
    for header in (None, SimpleNamespace(stamp=None), SimpleNamespace(stamp=SimpleNamespace(sec="x", nanosec=0)),
                   SimpleNamespace(stamp=SimpleNamespace(sec=float("nan"), nanosec=0), frame_id="l")):
        msg = _cloud()
        msg.header = header
        with pytest.raises(CloudError):
            read_scan(msg)


def test_float64_points_beyond_float32_are_not_finite_points():
    x = np.array([1.0, 1e300, 2.0, -1e39])
    scan = read_scan(_cloud(x=x))
    assert np.isfinite(scan.points).all() and len(scan.points) == 2 and scan.dropped["nonfinite"] == 2


def test_nan_and_all_zero_points_are_dropped_and_counted_apart_and_the_rest_keep_their_fields():
    nan = np.nan
    x, y, z = (np.array(v, np.float32) for v in ([1, nan, 0, 0, 2, 0], [1, 0, 0, 3, 2, 0], [1, 0, 0, 0, nan, 0]))
    scan = read_scan(_cloud(x=x, y=y, z=z, intensity=np.arange(6, dtype=np.float32)))
    assert scan.dropped == {"nonfinite": 2, "no_return": 2}  # (0, 3, 0) is a return, (0, 0, 0) none
    np.testing.assert_array_equal(scan.points, [[1, 1, 1], [0, 3, 0]])
    np.testing.assert_array_equal(scan.intensity, [0, 3])


@pytest.mark.parametrize("t, note", [
    ([0.0, 0.01, np.nan, 0.03], "neither a time relative"),  # a NaN time: the field is not used
    ([0.0, 0.01, 1.5, 0.03], "not one sweep"),  # seconds after the stamp, but 1.5 s of them
    ([0.02] * 4, "constant"),
    ([0.0, 0.01, 0.02, 0.03], ""),
])
def test_a_time_field_is_used_only_when_the_kept_points_times_make_one_sweep(t, note):
    x = np.array([1.0, 2.0, 3.0, 4.0, np.nan])  # the last point is no return: its time (99 s) is not looked at
    scan = read_scan(_cloud(x=x, t=np.array(t + [99.0], np.float32)))
    if note:
        assert scan.time is None and note in scan.notes[0], scan.notes
    else:
        np.testing.assert_array_equal(scan.time, np.array(t, np.float32))
        assert not scan.notes


def test_negative_and_huge_beam_ids_are_bad_beams():
    ring = np.array([0, 1, -3, 2**31 - 1, 5], np.int32)
    scan = read_scan(_cloud(x=np.arange(1.0, 6.0), ring=ring))
    assert scan.dropped["bad_beam"] == 2 and sorted(scan.beam) == [0, 1, 5]


def test_a_float_or_out_of_range_label_field_is_not_used():
    for label in (np.array([1.0, np.nan, 3.0]), np.array([1, 300, 2], np.int32), np.array([1, -1, 2], np.int16)):
        scan = read_scan(_cloud(x=np.arange(1.0, 4.0), label=label))
        assert scan.labels is None and "label field" in scan.notes[-1]
    scan = read_scan(_cloud(x=np.arange(1.0, 4.0), label=np.array([1, 2, 3], np.uint8)))
    assert list(scan.labels) == [1, 2, 3]


def test_a_point_on_the_sensors_z_axis_is_a_return_only_all_zero_is_no_return():
    x, y, z = (np.array(v, np.float32) for v in ([0, 0, 0, 1], [0, 0, 0, 1], [2.5, -1, 0, 1]))
    scan = read_scan(_cloud(x=x, y=y, z=z))
    assert scan.dropped == {"nonfinite": 0, "no_return": 1}
    np.testing.assert_array_equal(scan.points, [[0, 0, 2.5], [0, 0, -1], [1, 1, 1]])


def test_a_beam_id_equal_to_the_beam_count_is_bad_and_one_below_it_is_not():
    from topometric_ros.grid import MAX_BEAMS

    ring = np.array([0, MAX_BEAMS - 1, MAX_BEAMS, 15, 16], np.int32)
    scan = read_scan(_cloud(x=np.arange(1.0, 6.0), ring=ring))
    assert scan.dropped["bad_beam"] == 1 and sorted(scan.beam) == [0, 15, 16, MAX_BEAMS - 1]
    scan16 = read_scan(_cloud(x=np.arange(1.0, 6.0), ring=ring), max_beams=16)
    assert scan16.dropped["bad_beam"] == 3 and sorted(scan16.beam) == [0, 15]


def test_the_points_left_after_bad_beams_keep_their_own_time_intensity_and_label():
    ring = np.array([0, 300, 1, 2, -1, 3], np.int32)
    t = np.linspace(0.0, 0.05, 6).astype(np.float32)
    scan = read_scan(_cloud(x=np.arange(1.0, 7.0), ring=ring, t=t, intensity=np.arange(6, dtype=np.float32) * 10,
                            label=np.arange(6, dtype=np.uint8)))
    kept = [0, 2, 3, 5]
    assert scan.dropped["bad_beam"] == 2
    np.testing.assert_array_equal(scan.points[:, 0], np.arange(1.0, 7.0)[kept])
    np.testing.assert_array_equal(scan.beam, ring[kept])
    np.testing.assert_array_equal(scan.time, t[kept])
    np.testing.assert_array_equal(scan.intensity, np.float32(kept) * 10)
    np.testing.assert_array_equal(scan.labels, kept)


def test_a_label_of_255_is_a_class_and_256_is_out_of_range():
    scan = read_scan(_cloud(x=np.arange(1.0, 4.0), label=np.array([1, 255, 2], np.uint16)))
    assert list(scan.labels) == [1, 255, 2]
    scan = read_scan(_cloud(x=np.arange(1.0, 4.0), label=np.array([1, 256, 2], np.uint16)))
    assert scan.labels is None and "outside 0..255" in scan.notes[-1]


def test_a_sparse_ring_cloud_gets_rows_inside_its_grid():
    """Beam ids missing from grid's every-5th-point sample got uninitialised ranks (rows in the millions and a
    36 GB allocation in plane detection)."""
    from topometric_ros.grid import scan_grid

    rng = np.random.default_rng(3)
    ring = rng.permutation(np.arange(70) % 60)  # 60 beams among 70 points, ids in no elevation order
    pts = rng.normal(0, 8, (70, 3)).astype(np.float32)
    grid = scan_grid(pts, ring)
    assert grid.row.min() >= 0 and grid.row.max() < grid.height == 60


def test_an_unnamed_sensor_grid_is_at_most_max_columns_wide():
    """Points at nearly one azimuth made the estimated width 2π / a tiny step: an int64 overflow."""
    from topometric_ros.grid import MAX_COLUMNS, scan_grid

    pts = np.stack([np.full(200, 5.0), np.linspace(0, 1e-6, 200), np.linspace(-1, 1, 200)], 1).astype(np.float32)
    grid = scan_grid(pts, np.arange(200) % 8)
    assert grid.width <= MAX_COLUMNS and grid.col.max() < grid.width
