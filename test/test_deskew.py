"""Deskewing: exact on an analytic sweep, azimuth-derived times, the Monitor waiting for the sweep's odometry,
and on simulated motion-distorted bags planes get thinner than without it."""
from __future__ import annotations

import numpy as np
import pytest

from topometric_ros import geometry
from topometric_ros.config import load_config
from topometric_ros.deskew import azimuth_times, deskew, sweep_motion, sweep_span
from topometric_ros.monitor import Monitor


def _moving(t: np.ndarray) -> np.ndarray:
    """Sensor-to-map poses of a sensor driving 1.5 m/s along x while turning 90 °/s and pitching a little."""
    return geometry.yaw_pose(1.5 * t, 0.2 * t, 0.0, np.radians(90.0) * t, 0.0, np.radians(5.0) * t)


def test_deskew_puts_every_point_where_the_sensor_at_the_stamp_sees_it():
    rng = np.random.default_rng(0)
    world = rng.uniform(-20, 20, (5000, 3))
    stamp, times = 100.0, rng.uniform(0.0, 0.1, 5000)
    fired = _moving(stamp + times)  # the sensor's pose at each point's firing
    raw = np.einsum("nij,nj->ni", geometry.inverse(fired)[:, :3, :3], world) + geometry.inverse(fired)[:, :3, 3]

    motion = sweep_motion(_moving, stamp, 0.0, 0.1)
    fixed = deskew(raw.astype(np.float32), times, motion)
    truth = geometry.transform_points(geometry.inverse(_moving(np.array([stamp]))[0]), world)
    assert np.abs(raw - truth).max() > 0.1  # the sweep really is smeared (15 cm, 9°)
    np.testing.assert_allclose(fixed, truth, atol=2e-3)  # float32 points 20 m out, linear between 17 knots


def test_no_motion_is_the_identity_and_a_missing_pose_gives_none():
    pts = np.random.default_rng(1).normal(size=(100, 3)).astype(np.float32)
    still = sweep_motion(lambda t: np.tile(np.eye(4), (len(t), 1, 1)), 5.0, -0.1, 0.0, stamp_at="last")
    np.testing.assert_allclose(deskew(pts, np.full(100, -0.05), still), pts, atol=1e-6)
    assert sweep_motion(lambda t: None if t.max() > 5.05 else np.tile(np.eye(4), (len(t), 1, 1)), 5.0, 0.0, 0.1) is None
    # a sweep of zero length (every per-point time at the stamp): nothing to move, no NaN
    moving = sweep_motion(lambda t: geometry.make_pose(np.eye(3), np.stack([t, 0 * t, 0 * t], 1)), 5.0, 0.0, 0.0)
    np.testing.assert_allclose(deskew(pts, np.zeros(100), moving), pts, atol=1e-6)


def test_azimuth_times_follow_a_clockwise_sweep_from_the_first_point():
    az = np.radians(30.0) - np.linspace(0, 2 * np.pi, 361)[:-1]  # firing order: azimuth falls
    pts = np.stack([np.cos(az), np.sin(az), np.zeros_like(az)], 1) * 5
    np.testing.assert_allclose(azimuth_times(pts, 0.1, "first"), np.arange(360) / 360 * 0.1, atol=1e-6)
    np.testing.assert_allclose(azimuth_times(pts, 0.1, "last"), np.arange(360) / 360 * 0.1 - 0.1, atol=1e-6)
    assert sweep_span(0.1, "last") == (-0.1, 0.0) and sweep_span(0.1, "first") == (0.0, 0.1)


def test_a_non_repetitive_drivers_cloud_without_times_is_not_deskewed_by_azimuth():
    """No sensor named: a livox_ros_driver2 cloud whose time field is unusable has no azimuth order of firing
    (not deskewed), a Velodyne one has (clockwise, velodyne_driver stamps the last point)."""
    from topometric_ros.deskew import sweep_to_deskew
    from topometric_ros.sensors import sensor

    assert sweep_to_deskew(None, "livox", None, "auto") is None
    assert sweep_to_deskew(None, "livox", None, "on") is None
    assert sweep_to_deskew(None, "livox", sensor("Mid-360"), "auto") is None
    assert sweep_to_deskew(None, "velodyne", None, "auto") == (-0.1, 0.0, 0.1, "last")  # stamped at its end


def test_the_monitor_waits_for_odometry_past_the_sweep_before_it_deskews():
    cfg = load_config(overrides={"segmentation.mode": "none", "window.size": 2, "window.pose_wait_s": 0.0})
    m = Monitor(cfg)
    pts = np.random.default_rng(2).uniform(-5, 5, (2000, 3)).astype(np.float32)
    times = np.linspace(0.0, 0.1, 2000)
    m.add_pose(10.0, np.eye(4))
    m.add_pose(10.05, np.eye(4))
    m.add_scan(10.0, pts, time=times)  # its sweep runs to 10.1: not ready yet
    assert m.pending_length == 1
    m.add_pose(10.1, np.eye(4))
    assert m.pending_length == 0 and m.counters["scans_deskewed"] == 1
    off = Monitor(load_config(overrides={"segmentation.mode": "none", "window.size": 2, "sensor.deskew": "off"}))
    off.add_pose(10.0, np.eye(4))
    off.add_pose(10.2, np.eye(4))
    off.add_scan(10.0, pts, time=times)
    off.flush()
    assert off.counters["scans_deskewed"] == 0 and off.counters["scans_processed"] == 1


def test_per_point_times_are_checked_with_their_points():
    """add_scan's times go through the scan's checks: an empty scan with an empty time array is counted, not
    raised; a NaN time on a point that is dropped (non-finite) does not hold the scan up; a NaN time on a kept
    point leaves the times unused (said in last_note), so the scan is not deskewed by them."""
    cfg = load_config(overrides={"segmentation.mode": "none", "window.size": 2, "window.pose_wait_s": 0.0})
    m = Monitor(cfg)
    assert not m.add_scan(10.0, np.zeros((0, 3)), time=np.zeros(0)) and m.counters["dropped_bad_scan"] == 1
    pts = np.random.default_rng(3).uniform(-5, 5, (2000, 3)).astype(np.float32)
    times = np.linspace(0.0, 0.1, 2000)
    pts[5], times[5] = np.nan, np.nan
    m.add_pose(10.0, np.eye(4))
    m.add_pose(10.1, np.eye(4))
    assert m.add_scan(10.0, pts, time=times)
    assert m.pending_length == 0 and m.counters["scans_deskewed"] == 1  # its sweep ends at 10.1: ready
    pts[5], times[7] = 1.0, np.nan
    m.add_pose(10.3, np.eye(4))
    assert m.add_scan(10.2, pts, time=times) and "non-finite" in m.last_note
    assert m.pending_length == 0 and m.counters["scans_processed"] == 2 and m.counters["scans_deskewed"] == 1


def test_scans_waiting_for_odometry_that_stopped_are_released_once_it_is_stale():
    """The last scans of a stream wait for odometry past their sweep; when the odometry has stopped for
    health.stale_after_s (receive clock) they are scored with what came (the last motion continued over
    their sweep), not held: nothing waits unseen. Before that, nothing is released."""
    cfg = load_config(overrides={"segmentation.mode": "none", "window.size": 2, "health.stale_after_s": 3.0})
    m = Monitor(cfg)
    pts = np.random.default_rng(4).uniform(-5, 5, (2000, 3)).astype(np.float32)
    times = np.linspace(0.0, 0.1, 2000)
    for k in range(3):
        m.add_pose(10.0 + 0.1 * k, geometry.make_pose(np.eye(3), [0.15 * k, 0, 0]), received=100.0 + 0.1 * k)
    m.add_scan(10.0, pts, time=times, received=100.05)
    m.add_scan(10.2, pts, time=times, received=100.25)  # its sweep runs to 10.3: the odometry ends at 10.2
    assert m.pending_length == 1 and m.counters["scans_processed"] == 1
    assert m.release_waiting(102.0) == 0 and m.pending_length == 1  # 1.8 s without odometry: not yet stale
    assert m.release_waiting(104.0) == 1 and m.pending_length == 0
    assert m.counters["scans_processed"] == 2 and m.counters["scans_deskewed"] == 2
    assert m.counters["windows"] == 1 and m.counters["dropped_scans"] == 0


@pytest.mark.parametrize("sensor", ["VLP-16", "OS1-64", "HDL-64E"])
def test_deskew_thins_the_planes_of_a_fast_turning_robot(tmp_path, sensor):
    """A drift-free bag at 2 m/s with 90 °/s turns: CPV (plane thickness across scans) is smaller with deskew
    than without, whichever way the driver gives times (velodyne relative s, ouster ns, HDL-64E none:
    azimuth-derived)."""
    from topometric_ros.replay import ReplayOptions, replay
    from topometric_ros.sim.writer import SimConfig, simulate

    path = tmp_path / sensor
    simulate(SimConfig(scene="office1", frames=40, speed=2.0, seed=4, sensor=sensor), path, progress=False)
    cpv = {}
    for mode in ("auto", "off"):
        cfg = load_config(overrides={"segmentation.mode": "labels", "sensor.deskew": mode})
        res = replay(path, tmp_path / f"out_{mode}", cfg, ReplayOptions(plot=False, progress=False))
        cpv[mode] = np.nanmedian([w["cpv"] for w in res.windows])
        assert (res.summary["counters"]["scans_deskewed"] > 0) == (mode == "auto")
    assert cpv["auto"] < 0.7 * cpv["off"], cpv


def test_points_sharing_a_firing_time_move_as_if_each_were_computed_alone():
    """deskew computes the motion once per distinct time (a cache on the time's bits): an Ouster-like sweep
    (row-major, 64 rows x 2048 columns: every time recurs 2048 points later, and times collide in its slots)
    gives what the interpolation written plainly per point gives."""
    rng = np.random.default_rng(3)
    rows, cols = 64, 2048
    times = np.tile(np.arange(cols, dtype=np.float32) * np.float32(0.1 / cols), rows)  # as ouster-ros' t, in s
    pts = rng.uniform(-30, 30, (rows * cols, 3)).astype(np.float32)
    motion = sweep_motion(_moving, 100.0, 0.0, 0.1)
    r = np.stack([np.interp(times, motion.times, motion.rotvecs[:, k]) for k in range(3)], 1)
    t = np.stack([np.interp(times, motion.times, motion.translations[:, k]) for k in range(3)], 1)
    plain = np.einsum("nij,nj->ni", geometry.rotvec_to_matrix(r), pts.astype(np.float64)) + t
    np.testing.assert_allclose(deskew(pts, times, motion), plain, atol=2e-5)  # float32 points 50 m out
    shuffled = rng.permutation(len(pts))  # any order: the same result per point
    np.testing.assert_array_equal(deskew(pts[shuffled], times[shuffled], motion), deskew(pts, times, motion)[shuffled])


def test_a_time_outside_the_sweeps_knots_takes_the_motion_of_the_end_knot():
    """Times past the last knot take the last knot's motion, times before the first the first's (here the
    stamp's: no motion), not the motion extrapolated."""
    motion = sweep_motion(_moving, 100.0, 0.0, 0.1)
    pts = np.random.default_rng(5).uniform(-10, 10, (50, 3)).astype(np.float32)
    np.testing.assert_array_equal(deskew(pts, np.full(50, 0.3), motion), deskew(pts, np.full(50, 0.1), motion))
    np.testing.assert_allclose(deskew(pts, np.full(50, -0.2), motion), pts, atol=1e-5)


def test_the_sweep_to_deskew_follows_the_rate_and_the_mode():
    """A per-point time field gives the sweep its own span; without one, the rate sets the period (20 Hz:
    50 ms), and an unknown driver is deskewed only when told to ('on': clockwise, stamped at the first point)."""
    from topometric_ros.deskew import sweep_to_deskew

    assert sweep_to_deskew(np.array([0.01, 0.04, 0.07]), "", None, "auto") == (0.01, 0.07, 0.1, "first")
    assert sweep_to_deskew(None, "velodyne", None, "auto", rate_hz=20.0) == (-0.05, 0.0, 0.05, "last")
    assert sweep_to_deskew(None, "", None, "on") == (0.0, 0.1, 0.1, "first")
    assert sweep_to_deskew(None, "", None, "auto") is None
    assert sweep_to_deskew(np.array([0.01, 0.07]), "velodyne", None, "off") is None


def test_the_monitor_deskews_with_the_sensors_own_motion_through_the_extrinsic():
    """Odometry of a base turning on the spot at 90 °/s with the LiDAR 1 m ahead of it (window.extrinsic): the
    sensor itself sweeps a 16 cm arc in a 0.1 s scan. Deskewed, each point is where the sensor at the stamp sees
    it (within 2 mm); a deskew with the base's motion (a pure turn) would leave it up to 16 cm off."""
    cfg = load_config(overrides={"segmentation.mode": "none", "window.size": 2, "window.pose_wait_s": 0.0,
                                 "metrics.baselines": True, "window.extrinsic": [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]})
    windows = []
    m = Monitor(cfg, on_window=lambda result, scans: windows.append(scans))
    extrinsic = geometry.make_pose(np.eye(3), [1.0, 0.0, 0.0])

    def base(t):
        return geometry.yaw_pose(0.0 * t, 0.0, 0.0, np.radians(90.0) * t)

    rng = np.random.default_rng(6)
    direction = rng.normal(size=(400, 3))
    world = direction / np.linalg.norm(direction, axis=1, keepdims=True) * rng.uniform(3, 10, (400, 1))
    times = rng.uniform(0.0, 0.1, 400)
    for t in np.arange(0.0, 0.45, 0.05):
        m.add_pose(10.0 + t, base(np.array([t]))[0])
    for stamp in (10.0, 10.2):
        fired = geometry.inverse(base(stamp - 10.0 + times) @ extrinsic)
        raw = np.einsum("nij,nj->ni", fired[:, :3, :3], world) + fired[:, :3, 3]
        assert m.add_scan(stamp, raw.astype(np.float32), time=times)
    m.flush()
    assert m.counters["scans_deskewed"] == 2 and len(windows) == 1
    for scan in windows[0]:
        at_stamp = geometry.transform_points(geometry.inverse(base(np.array([scan.stamp - 10.0]))[0] @ extrinsic),
                                             world)
        nearest = np.linalg.norm(scan.points[:, None, :] - at_stamp[None], axis=2).min(axis=1)
        assert len(scan.points) > 300 and nearest.max() < 2e-3, nearest.max()
