"""Monitor: pose lookup by stamp, waiting and dropping rules, bounded queue with a real worker thread, time
resets, bad input. The per-scan and per-window functions here are cheap real ones (a floor-height spread),
so the tests are about the plumbing, not the metrics."""
import gc
import os
import time

import numpy as np
import pytest

from topometric_ros import bag, geometry
from topometric_ros.cloud import make_cloud, rosbags_types
from topometric_ros.config import load_config
from topometric_ros.monitor import MAX_CLOUD_NOTES, OTHER_CLOUD_NOTES, Monitor, StaticTransforms
from topometric_ros.pipeline import ProcessedScan, WindowResult

SENSOR_HEIGHT = 1.0


def floor_scan(frame, config, segmenter=None, index=-1, delay=0.0):
    """Per-scan work: the scan's points in the MAP frame (uses the pose the monitor gave the scan)."""
    if delay:
        time.sleep(delay)
    world = geometry.transform_points(frame.pose, frame.points.astype(np.float64))
    return ProcessedScan(frame.stamp, frame.pose, [], points=world, index=index)


def floor_window(scans, config):
    """Per-window score: spread (m) of the floor height across the window; 0 when every pose is right."""
    heights = np.array([s.points[:, 2].mean() for s in scans])
    return WindowResult([s.stamp for s in scans], pne=0.0, cpv=float(heights.std()), n_planes=len(scans),
                        n_groups=1)


def floor_points(n=200, rng=None):
    """Points of the floor z = 0 seen from a sensor SENSOR_HEIGHT above it (sensor frame, float32)."""
    rng = rng or np.random.default_rng(0)
    xy = rng.uniform(-5, 5, size=(n, 2))
    return np.column_stack([xy, np.full(n, -SENSOR_HEIGHT)]).astype(np.float32)


def config(**over):
    base = {"window.size": 3, "window.pose_wait_s": 0.05, "window.max_pose_gap_s": 0.2,
            "window.extrinsic": [0.0, 0.0, SENSOR_HEIGHT, 0.0, 0.0, 0.0, 1.0], "health.baseline_windows": 2,
            "health.min_planes": 0}
    base.update(over)
    return load_config(overrides=base)


def base_pose(t):
    """Ground-truth base_link pose: moving along x at 1 m/s on the floor, climbing 0 m."""
    return geometry.yaw_pose(t, 0.5 * t, 0.0, 0.1 * t)


def feed(m, t_scans, odom_rate=20.0, pose_fn=base_pose, odom_offset=0.013):
    """Interleave odometry (at odom_rate, offset from scans) and scans as a driver would."""
    t_odom = np.arange(t_scans[0] - 0.5 + odom_offset, t_scans[-1] + 0.5, 1 / odom_rate)
    k = 0
    for t in t_scans:
        while k < len(t_odom) and t_odom[k] <= t + 0.06:
            m.add_pose(t_odom[k], pose_fn(t_odom[k]))
            k += 1
        m.add_scan(t, floor_points())
    for j in range(k, len(t_odom)):
        m.add_pose(t_odom[j], pose_fn(t_odom[j]))


def test_deterministic_windows_with_interpolated_poses_and_extrinsic():
    out = []
    m = Monitor(config(), floor_scan, floor_window, on_window=lambda r, s: out.append((r, s)))
    feed(m, 100.0 + np.arange(12) / 5.0)
    m.flush()
    assert len(out) == 4 and m.counters["windows"] == 4
    for result, scans in out:
        assert result.cpv < 1e-6  # right poses, right extrinsic: the floor stays at z = 0
        for s in scans:
            np.testing.assert_allclose(s.pose, base_pose(s.stamp) @ geometry.make_pose(np.eye(3), [0, 0, 1]),
                                       atol=1e-9)
    assert [r.stamps[0] for r, _ in out] == pytest.approx(100.0 + np.array([0, 3, 6, 9]) / 5.0)
    c = m.counters
    assert c["scans_in"] == 12 and c["scans_processed"] == 12 and c["dropped_scans"] == 0


def test_a_wrong_extrinsic_shows_as_inconsistency():
    """Control for the test above: without the 1 m sensor height the window still agrees (rigid), but
    a pose error in one scan does not."""
    bump = lambda t: base_pose(t) @ geometry.make_pose(np.eye(3), [0, 0, 0.3 if 100.55 < t < 100.65 else 0])
    out = []
    m = Monitor(config(), floor_scan, floor_window, on_window=lambda r, s: out.append(r))
    feed(m, 100.0 + np.arange(6) / 5.0, pose_fn=bump)
    m.flush()
    assert out[0].cpv < 1e-6 and out[1].cpv > 0.05  # scan at 100.6 s sits 0.3 m high


def test_scans_wait_for_odometry_and_are_dropped_without_it():
    m = Monitor(config(), floor_scan, floor_window)
    m.add_pose(0.0, base_pose(0.0))
    m.add_scan(0.1, floor_points())
    assert m.pending_length == 1 and m.counters["scans_processed"] == 0  # no odometry past 0.1 + wait yet
    m.add_pose(0.2, base_pose(0.2))
    assert m.pending_length == 0 and m.counters["scans_processed"] == 1
    m.add_pose(2.0, base_pose(2.0))  # 1.8 s hole in the odometry
    m.add_scan(1.0, floor_points())
    m.add_pose(2.1, base_pose(2.1))
    assert m.counters["dropped_no_pose"] == 1
    # odometry stops: scans wait until pose_timeout_s of scan time, then are dropped and counted
    for t in 3.0 + np.arange(15) / 5:
        m.add_scan(t, floor_points())
    assert m.counters["dropped_no_pose"] >= 1 + 15 - int(m.config.window.pose_timeout_s * 5) - 1
    assert m.pending_length <= m.config.window.pose_timeout_s * 5 + 1
    m.flush()
    assert m.pending_length == 0 and m.counters["dropped_no_pose"] == 16


def test_extrinsic_from_tf_static_wins_over_config():
    types = rosbags_types(bag.typestore())
    m = Monitor(config(**{"window.extrinsic": [0.0] * 6 + [1.0]}), floor_scan, floor_window)
    m.add_tf_static(bag.make_tf(0.0, geometry.make_pose(np.eye(3), [0, 0, SENSOR_HEIGHT]), "base_link", "velodyne"))
    assert m.extrinsic_source == "config"  # frames not known yet
    m.add_odometry(bag.make_odometry(0.0, base_pose(0.0), "map", "base_link"))
    pts = floor_points()
    m.add_cloud(make_cloud({"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]}, 0.05, "velodyne", types))
    assert m.extrinsic_source == "tf_static"
    np.testing.assert_allclose(m.extrinsic[:3, 3], [0, 0, SENSOR_HEIGHT])


def test_extrinsic_from_tf_static_between_sibling_frames():
    """Odometry of an IMU (child frame imu_link) beside the LiDAR, both under base_link (a LIO's usual tree):
    the extrinsic is the LiDAR's pose in imu_link through base_link, not the config's identity."""
    types = rosbags_types(bag.typestore())
    m = Monitor(config(**{"window.extrinsic": [0.0] * 6 + [1.0]}), floor_scan, floor_window)
    yaw = geometry.make_pose(geometry.rotvec_to_matrix(np.array([0.0, 0.0, np.pi / 2])), [0.2, 0.0, 0.1])
    m.add_tf_static(bag.make_tf(0.0, yaw, "base_link", "imu_link"))
    m.add_tf_static(bag.make_tf(0.0, geometry.make_pose(np.eye(3), [0.5, 0.0, SENSOR_HEIGHT]), "base_link", "velodyne"))
    m.add_odometry(bag.make_odometry(0.0, base_pose(0.0), "map", "imu_link"))
    pts = floor_points()
    m.add_cloud(make_cloud({"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]}, 0.05, "velodyne", types))
    assert m.extrinsic_source == "tf_static"
    # the LiDAR 0.3 m ahead of the IMU along base_link's x, which is the IMU's -y (the IMU is turned 90 deg)
    np.testing.assert_allclose(m.extrinsic[:3, 3], [0.0, -0.3, SENSOR_HEIGHT - 0.1], atol=1e-9)
    np.testing.assert_allclose(m.extrinsic[:3, :3], geometry.rotvec_to_matrix(np.array([0.0, 0.0, -np.pi / 2])), atol=1e-9)


def test_an_extrinsic_that_changes_after_scans_were_posed_is_named():
    """A /tf_static that arrives after scans took the config's extrinsic (a recorder started before
    robot_state_publisher): the monitor switches and says after how many scans; given first, nothing to say."""
    types = rosbags_types(bag.typestore())
    tf = bag.make_tf(0.0, geometry.make_pose(np.eye(3), [0, 0, SENSOR_HEIGHT]), "base_link", "velodyne")
    for late in (False, True):
        m = Monitor(config(**{"window.extrinsic": [0.0] * 6 + [1.0]}), floor_scan, floor_window)
        if not late:
            m.add_tf_static(tf)
        pts = floor_points()
        for k in range(4):
            m.add_odometry(bag.make_odometry(0.2 * k, base_pose(0.2 * k), "map", "base_link"))
            m.add_cloud(make_cloud({"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]}, 0.2 * k, "velodyne", types))
        m.add_odometry(bag.make_odometry(0.8, base_pose(0.8), "map", "base_link"))
        if late:
            m.add_tf_static(tf)
        m.flush()
        assert m.extrinsic_source == "tf_static" and m.counters["scans_processed"] == 4
        assert m.extrinsic_note == ("extrinsic changed after 4 scans (config -> /tf_static): a window spanning "
                                    "the change mixes the two" if late else "")


def test_the_last_cloud_says_why_its_points_or_fields_were_not_all_used():
    """last_note (the node's cloud_note): a ring id beyond the named model's beams asks whether sensor.model is
    right; a constant time field says the azimuth gives the times; a cloud that uses everything clears it."""
    types = rosbags_types(bag.typestore())
    m = Monitor(config(**{"sensor.model": "VLP-16"}), floor_scan, floor_window)
    pts = floor_points()[:40]
    ring = np.arange(40, dtype=np.uint16) % 20  # rings 16-19 are no VLP-16 beam: 8 points
    fields = {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2], "ring": ring}
    m.add_cloud(make_cloud({**fields, "time": np.zeros(40, np.float32)}, 0.05, "velodyne", types))
    assert m.last_note == ("time field 'time' is constant; times from the azimuth instead; 8 points dropped: beam id "
                           "outside 0..15, the 16 beams of sensor.model VLP-16; is sensor.model right?")
    assert m.counters["bad_beam_points"] == 8 and m.cloud_notes == {"time field 'time' is constant; times from the "
                                                                     "azimuth instead": 1}
    m.add_cloud(make_cloud({**fields, "ring": ring % 16}, 0.15, "velodyne", types))
    assert m.last_note == "" and m.counters["bad_beam_points"] == 8
    for k in range(10):  # time fields that span 1.1, 1.2, ... 2 s: ten distinct notes, every cloud counted
        span = np.linspace(0, 1.1 + 0.1 * k, 40)
        m.add_cloud(make_cloud({**fields, "ring": ring % 16, "time": span}, 0.25 + 0.1 * k, "velodyne", types))
    assert len(m.cloud_notes) == MAX_CLOUD_NOTES + 1 and sum(m.cloud_notes.values()) == 11
    assert m.cloud_notes[OTHER_CLOUD_NOTES] == 3 and "spans 2 s" in m.last_note


def test_static_transform_chains_compose():
    tf = StaticTransforms()
    a = geometry.yaw_pose(1.0, 0.0, 0.0, np.pi / 2)
    b = geometry.yaw_pose(0.0, 2.0, 0.5, 0.0)
    tf.add_message(bag.make_tf(0.0, a, "base_link", "mount"))
    tf.add_message(bag.make_tf(0.0, b, "/mount", "velodyne"))
    np.testing.assert_allclose(tf.lookup("base_link", "velodyne"), a @ b, atol=1e-12)
    assert tf.lookup("velodyne", "base_link") is None
    # between: any two linked frames, downward and through a common ancestor (a sibling), else None
    imu = geometry.yaw_pose(-0.3, 0.1, 0.2, 0.4)
    tf.add_message(bag.make_tf(0.0, imu, "base_link", "imu"))
    np.testing.assert_allclose(tf.between("base_link", "velodyne"), a @ b, atol=1e-12)
    np.testing.assert_allclose(tf.between("velodyne", "base_link"), geometry.inverse(a @ b), atol=1e-12)
    np.testing.assert_allclose(tf.between("imu", "velodyne"), geometry.inverse(imu) @ a @ b, atol=1e-12)
    np.testing.assert_allclose(tf.between("velodyne", "velodyne"), np.eye(4), atol=1e-12)
    assert tf.between("imu", "camera") is None


def test_backwards_stamps_reset_the_window_cleanly():
    out = []
    m = Monitor(config(), floor_scan, floor_window, on_window=lambda r, s: out.append(r))
    feed(m, 100.0 + np.arange(5) / 5.0)  # one window + 2 scans of a second
    feed(m, 10.0 + np.arange(6) / 5.0)  # bag loop / sim time reset
    m.flush()
    c = m.counters
    assert c["time_resets"] == 1 and c["windows_discarded"] == 1  # one loop, though both streams went back
    assert len(out) == 3
    assert all(np.all(np.diff(r.stamps) > 0) for r in out)  # no window mixes the two time lines
    assert all(r.cpv < 1e-6 for r in out)


def test_bad_input_is_counted_and_survived():
    m = Monitor(config(), floor_scan, floor_window)
    types = rosbags_types(bag.typestore())
    pts = floor_points()
    cloud = make_cloud({"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]}, 1.0, "velodyne", types)
    cloud.data = cloud.data[:-5]  # truncated buffer
    assert not m.add_cloud(cloud)
    assert not m.add_cloud(object())  # not a cloud at all
    assert not m.add_scan(1.0, np.zeros((0, 3)))  # empty
    assert not m.add_scan(1.0, np.full((10, 3), np.nan))  # nothing finite
    assert not m.add_scan(1.0, np.zeros((10, 2)))  # wrong shape
    assert not m.add_scan(1.0, pts, labels=np.zeros(3, np.uint8))  # misaligned labels
    assert not m.add_scan(float("nan"), pts)
    assert m.counters["dropped_bad_scan"] == 7
    with_nan = pts.copy()
    with_nan[:5] = np.inf
    with_nan[5:8, 1] = np.nan
    assert m.add_scan(2.0, with_nan)
    assert m.counters["nonfinite_points"] == 8 + 10
    assert not m.add_scan(2.0, pts)  # duplicate stamp
    assert m.counters["dropped_duplicate"] == 1
    odom = bag.make_odometry(2.0, base_pose(2.0))
    q = odom.pose.pose.orientation
    q.x, q.y, q.z, q.w = 2 * q.x, 2 * q.y, 2 * q.z, 2 * q.w  # non-unit quaternion: normalised, accepted
    assert m.add_odometry(odom)
    zero = bag.make_odometry(2.1, base_pose(2.1))
    zero.pose.pose.orientation.w = 0.0
    zero.pose.pose.orientation.x = zero.pose.pose.orientation.y = zero.pose.pose.orientation.z = 0.0
    assert not m.add_odometry(zero)
    assert not m.add_pose(2.2, np.full((4, 4), np.nan))
    assert not m.add_pose(2.3, np.diag([2.0, 1.0, 1.0, 1.0]))  # not a rotation
    assert m.counters["bad_poses"] == 3
    assert not m.add_pose(2.0, base_pose(2.0))  # duplicate odometry stamp
    assert m.counters["duplicate_poses"] == 1
    assert m.last_error


def test_scans_missing_by_their_stamps_are_counted_from_the_streams_own_period():
    """A 10 Hz stream with 2, then 3 scans gone (steps of 0.3 and 0.4 s): 5 missing. A 5 Hz stream (every second
    sweep recorded) misses none; a step over a cloud that came but was left out (bad, duplicate) is not judged:
    that cloud is counted where it failed; stamps going back start the period again."""
    m = Monitor(config(), floor_scan, floor_window)
    stamps = [round(0.1 * k, 3) for k in range(30) if k not in (10, 11, 20, 21, 22)]
    for t in stamps:
        m.add_scan(t, floor_points())
    assert m.counters["scans_missing"] == 5
    slow = Monitor(config(), floor_scan, floor_window)
    for k in range(20):
        slow.add_scan(0.2 * k, floor_points())
    assert slow.counters["scans_missing"] == 0
    left_out = Monitor(config(), floor_scan, floor_window)
    for k in range(12):
        if k == 6:
            assert not left_out.add_scan(0.6, np.zeros((0, 3)))  # came, but empty: dropped_bad_scan
            continue
        left_out.add_scan(0.1 * k, floor_points())
    assert left_out.counters["scans_missing"] == 0 and left_out.counters["dropped_bad_scan"] == 1
    for t in (0.05, 0.25, 0.45):  # back in time: a new stream; its first steps teach the period again
        left_out.add_scan(t, floor_points())
    assert left_out.counters["scans_missing"] == 0


def test_a_failing_scan_function_is_counted_not_raised():
    def flaky(frame, cfg, seg, index):
        if index % 2:
            raise RuntimeError("boom")
        return floor_scan(frame, cfg, seg, index)

    m = Monitor(config(), flaky, floor_window)
    feed(m, 100.0 + np.arange(8) / 5.0)
    m.flush()
    assert m.counters["scan_errors"] == 4 and m.counters["scans_processed"] == 4
    assert "boom" in m.last_error


def rss_bytes():
    """Resident set size of this process (Linux /proc)."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def test_live_worker_drops_oldest_keeps_memory_flat_and_never_blocks_the_feeder():
    """Feed scans at 4x the worker's speed with a real worker thread."""
    work_s = 0.02
    slow_scan = lambda f, c, s, i: floor_scan(f, c, s, i, delay=work_s)  # noqa: E731
    results = []
    m = Monitor(config(**{"window.queue_size": 4}), slow_scan, floor_window, live=True,
                on_window=lambda r, s: results.append(r))
    n = 400
    t_scans = 100.0 + np.arange(n) * 0.2  # stamps at 5 Hz, but fed at 4x the worker's rate
    big = np.random.default_rng(0).normal(size=(20000, 3)).astype(np.float32)
    big[:, 2] = -SENSOR_HEIGHT
    feed_times, mem, max_queue = [], [], 0
    k = 0
    t_odom = np.arange(t_scans[0] - 0.5, t_scans[-1] + 0.5, 0.05)
    gc.collect()
    gc.disable()  # in a full-suite run a gen-2 collection once stalled one add_scan 0.38 s: not the worker's doing
    try:
        start = time.perf_counter()
        for i, t in enumerate(t_scans):
            while t_odom[k] <= t + 0.1:
                m.add_pose(t_odom[k], base_pose(t_odom[k]))
                k += 1
            t0 = time.perf_counter()
            m.add_scan(t, big)
            feed_times.append(time.perf_counter() - t0)
            max_queue = max(max_queue, m.queue_length)
            if i in (100, n - 1):
                mem.append(rss_bytes())
            time.sleep(max(0.0, start + (i + 1) * work_s / 4 - time.perf_counter()))  # 4x the worker's rate
        fed_s = time.perf_counter() - start
    finally:
        gc.enable()
    m.flush(timeout=10)
    m.close()
    c = m.counters
    assert max_queue <= 4
    # the worker can only have done fed_s / work_s scans while fed; the rest were dropped and counted
    assert c["scans_processed"] <= fed_s / work_s + 4 + 2
    assert c["dropped_queue_full"] > 0
    assert c["scans_processed"] + c["dropped_queue_full"] + c["dropped_no_pose"] == n
    assert c["windows"] == len(results) >= 1
    assert mem[1] - mem[0] < 0.2 * (n - 100) * big.nbytes  # flat: 300 more scans fed, RSS about the same
    assert np.median(feed_times) < work_s / 4  # enqueueing never waits for the worker
    assert max(feed_times) < 10 * work_s


def split_floor_scan(delay=0.0):
    """floor_scan as two stages (like pipeline.SCAN_STAGES): stage 1 moves the points to the map frame,
    stage 2 wraps them; each sleeps ``delay`` s (sleep releases the GIL, as torch does)."""
    def first(frame, cfg, seg, index):
        time.sleep(delay)
        return frame, geometry.transform_points(frame.pose, frame.points.astype(np.float64)), index

    def second(item, cfg):
        time.sleep(delay)
        frame, world, index = item
        return ProcessedScan(frame.stamp, frame.pose, [], points=world, index=index)

    return first, second


@pytest.mark.parametrize("stages", [None, split_floor_scan()])
def test_live_close_drains_the_queue_and_stops_the_threads(stages):
    cfg = config(**{"window.queue_size": 16})  # room for all 9: none dropped however slowly the worker starts
    m = (Monitor(cfg, floor_scan, floor_window, live=True) if stages is None
         else Monitor(cfg, None, floor_window, live=True, stages=stages))
    feed(m, 100.0 + np.arange(9) / 5.0)
    assert m.flush(timeout=10)
    workers = list(m._threads)
    assert len(workers) == (1 if stages is None else 2) and all(w.is_alive() for w in workers)
    m.close()
    assert m.counters["dropped_queue_full"] == 0
    assert m.counters["scans_processed"] == 9 and m.counters["windows"] == 3
    assert not any(w.is_alive() for w in workers)


def test_two_stages_overlap_and_keep_scan_order():
    """Two stages of d seconds each: pipelined, n scans take about (n + 1)·d, not 2·n·d; windows in order,
    equal to the serial ones."""
    d, n = 0.02, 30
    serial = Monitor(config(), None, floor_window, stages=split_floor_scan(d))
    feed(serial, 100.0 + np.arange(n) / 5.0)
    serial.flush()
    out = []
    with Monitor(config(**{"window.queue_size": 2}), None, floor_window, live=True, block=True,
                 stages=split_floor_scan(d), on_window=lambda r, s: out.append(r)) as m:
        t0 = time.perf_counter()
        feed(m, 100.0 + np.arange(n) / 5.0)
        m.flush()
        took = time.perf_counter() - t0
    assert m.counters["scans_processed"] == n and m.counters["dropped_scans"] == 0
    assert [(r.stamps, r.cpv) for r in out] == [(r.stamps, r.cpv) for r in serial.results]
    assert took < 1.6 * n * d  # serial would need 2·n·d; sleeping stages overlap even on a busy machine


def test_pipelined_live_mode_drops_oldest_at_the_input_only():
    """Fed 4x faster than the slowest stage: drops are counted at the input queue, every scan is either
    processed or counted, and the scans in flight stay bounded."""
    d, n = 0.01, 200
    m = Monitor(config(**{"window.queue_size": 3}), None, floor_window, live=True, stages=split_floor_scan(d))
    t_scans = 100.0 + np.arange(n) * 0.2
    t_odom = np.arange(t_scans[0] - 0.5, t_scans[-1] + 0.5, 0.05)
    k, most, start = 0, 0, time.perf_counter()
    for i, t in enumerate(t_scans):
        while t_odom[k] <= t + 0.1:
            m.add_pose(t_odom[k], base_pose(t_odom[k]))
            k += 1
        m.add_scan(t, floor_points())
        most = max(most, m.in_flight)
        time.sleep(max(0.0, start + (i + 1) * d / 4 - time.perf_counter()))
    m.flush(timeout=10)
    m.close()
    c = m.counters
    assert c["dropped_queue_full"] > 0
    assert c["scans_processed"] + c["dropped_queue_full"] + c["dropped_no_pose"] == n
    assert most <= 3 + 2 * (2 + 1)  # input queue + per stage: its queue and the scan it works on
    assert c["windows"] >= 1


def test_blocking_live_mode_processes_every_scan_in_order():
    """replay's mode: the worker thread does the work, the feeder waits when the queue is full, no drops."""
    slow_scan = lambda f, c, s, i: floor_scan(f, c, s, i, delay=0.005)  # noqa: E731
    out = []
    with Monitor(config(**{"window.queue_size": 2}), slow_scan, floor_window, live=True, block=True,
                 on_window=lambda r, s: out.append(r)) as m:
        feed(m, 100.0 + np.arange(30) / 5.0)
        m.flush()
    c = m.counters
    assert c["scans_processed"] == 30 and c["dropped_scans"] == 0 and len(out) == 10
    assert [r.stamps[0] for r in out] == pytest.approx(100.0 + np.arange(0, 30, 3) / 5.0)


def test_stale_when_input_stops_in_the_callers_clock():
    m = Monitor(config(**{"health.stale_after_s": 2.0}), floor_scan, floor_window)
    assert m.stale(0.0)[0] == "STALE"  # nothing yet
    feed(m, 50.0 + np.arange(3) / 5.0)
    assert m.stale(51.0) is None
    level, why = m.stale(53.0)
    assert level == "STALE" and "scans" in why


def _a_cloud_ahead_of_its_clock(m: Monitor) -> bool:
    """Odometry and three clouds stamped on their receive clock (100-100.45 s), then a cloud received at 101 s
    stamped 1 s ahead: what add_scan says of it."""
    for k in range(10):
        m.add_pose(100.0 + 0.05 * k, base_pose(100.0 + 0.05 * k), received=100.0 + 0.05 * k)
    for t in (100.1, 100.2, 100.3):
        assert m.add_scan(t - 0.1, floor_points(), received=t)
    assert m.clock_status(100.4) is None
    return m.add_scan(101.9, floor_points(), received=101.0)


def test_a_clock_fault_is_an_error_status_for_stale_after_s_then_clears():
    m = Monitor(config(**{"health.stale_after_s": 2.0, "health.clock_jump_s": 0.5}), floor_scan, floor_window)
    assert not _a_cloud_ahead_of_its_clock(m)  # dropped
    level, why = m.clock_status(102.9)
    assert level == "ERROR" and "cloud stamps jumped +1.00 s" in why
    assert m.clock_status(103.5) is None  # 2.5 s after the fault


@pytest.fixture(scope="module")
def sim_frames():
    from topometric_ros.sim.frames import simulated_frames

    frames, _ = simulated_frames("office1", 10, seed=3, layout_seed=2)
    return frames


def run_real_pipeline(frames, cfg, **kw):
    """The default stages (pipeline.SCAN_STAGES or process_scan) over frames with exact odometry."""
    windows = []
    with Monitor(cfg, on_window=lambda r, s: windows.append((r, [s_.plane_arrays() for s_ in s])), **kw) as m:
        for f in frames:
            m.add_pose(f.stamp, f.pose)
            m.add_scan(f.stamp, f.points, f.labels, f.ring, f.intensity)
        m.add_pose(frames[-1].stamp + 0.2, frames[-1].pose)
        m.flush()
    assert m.counters["scans_processed"] == len(frames) and m.counters["dropped_scans"] == 0
    return windows


@pytest.mark.parametrize("mode", ["labels", "network"])
def test_pipelined_stages_give_exactly_the_serial_windows(sim_frames, mode):
    """Real segmentation + ring planes + PNE/CPV: two worker threads (segment | planes + window) give the
    same WindowResults and the same per-scan planes, bit for bit, as one serial pass of process_scan."""
    over = {"window.size": 5, "window.extrinsic": [0.0, 0, 0, 0, 0, 0, 1], "segmentation.mode": mode,
            "health.baseline_windows": 1}
    serial = run_real_pipeline(sim_frames, load_config(overrides={**over, "window.pipelined": False}))
    piped = run_real_pipeline(sim_frames, load_config(overrides={**over, "window.pipelined": True}),
                              live=True, block=True)
    assert len(serial) == len(piped) == 2
    for (a, pa), (b, pb) in zip(serial, piped):
        assert (a.stamps, a.pne, a.cpv, a.n_planes, a.n_groups, a.n_clusters, a.level) == \
               (b.stamps, b.pne, b.cpv, b.n_planes, b.n_groups, b.n_clusters, b.level)
        assert np.isfinite(a.pne) and a.n_planes > 10
        for x, y in zip(pa, pb):
            for u, v in zip(x, y):
                np.testing.assert_array_equal(u, v)


def scan_at(m, t, labels=None, received=None):
    """One floor scan at stamp t, with odometry around it (so only the scan itself can fail)."""
    for tp in (t - 0.05, t + 0.1):
        m.add_pose(tp, base_pose(tp), received=None if received is None else received + tp - t)
    return m.add_scan(t, floor_points(), labels=labels, received=received)


@pytest.mark.parametrize("live", [False, True])
def test_every_scan_failing_is_an_error_with_the_reason(live):
    """Never silent: labels mode on scans without labels (the real pipeline) fails every scan; after
    health.fail_after_s of the caller's clock the check says ERROR with the counters and the reason, while
    STALE stays quiet (scans do arrive). One good scan ends it."""
    cfg = config(**{"segmentation.mode": "labels", "health.fail_after_s": 1.0, "window.pose_wait_s": 0.0})
    with Monitor(cfg, live=live) as m:
        for k in range(8):
            scan_at(m, 100.0 + k / 5, received=500.0 + k / 5)
        m.flush()
        assert m.counters["scan_errors"] == 8 and m.counters["scans_processed"] == 0
        assert m.failing_since == 500.0 and m.check(500.9) is None
        level, why = m.check(501.4)
        assert level == "ERROR" and why.startswith("no scan processed yet, every scan fails (scan_errors 8)")
        assert "segmentation mode 'labels' but the cloud has no label field" in why
        scan_at(m, 102.0, labels=np.full(200, 1, np.uint8), received=502.0)
        m.flush()
        assert m.counters["scans_processed"] == 1 and m.failing_since is None and m.check(502.5) is None
        scan_at(m, 102.2, received=502.2)  # failing again: the streak restarts at this scan
        m.flush()
        assert m.check(503.1) is None and m.check(503.2)[1].startswith("no scan processed for 1.2 s")


def test_malformed_clouds_and_missing_poses_are_failures_too():
    types = rosbags_types(bag.typestore())
    m = Monitor(config(**{"health.fail_after_s": 0.5}), floor_scan, floor_window)
    bad = make_cloud({"x": np.zeros(3, np.float32), "y": np.zeros(3, np.float32)}, 10.0, "velodyne", types)
    for k in range(3):
        m.add_cloud(bad, received=20.0 + k / 10)
    level, why = m.check(20.6)  # no odometry either: STALE, and the scans' failure beside it
    assert level == "STALE" and why.startswith("no odometry yet; no scan processed yet") and "malformed" in why
    m.add_pose(10.0, base_pose(10.0), received=20.5)
    level, why = m.check(20.6)
    assert level == "ERROR" and "dropped_bad_scan 3" in why and "malformed cloud" in why
    m2 = Monitor(config(**{"health.fail_after_s": 0.5}), floor_scan, floor_window)
    for k in range(12):  # odometry stamped in another time base (received now): no pose for any scan
        m2.add_pose(k / 5, base_pose(k / 5), received=1000.0 + k / 5)
        m2.add_scan(1000.0 + k / 5, floor_points(), received=1000.0 + k / 5)
    m2.flush()
    assert m2.counters["dropped_no_pose"] == 12
    assert "no odometry within" in m2.check(1002.4)[1] and "dropped_no_pose 12" in m2.check(1002.4)[1]


def test_stamps_going_back_do_not_end_a_failure_streak_while_the_receive_clock_goes_on():
    """Odometry stamps that keep going backwards (time resets) while every scan fails: the receive clock
    (node clock) goes on, so the streak stands and the check says ERROR; a clock that goes back with
    them (sim time reset) forgets the streak."""
    m = Monitor(config(**{"segmentation.mode": "labels", "health.fail_after_s": 1.0}))
    for k in range(15):
        t, r = 100.0 + k / 10, 500.0 + k / 10
        m.add_pose(t - 0.05, base_pose(t), received=r)
        m.add_pose(t + 0.15, base_pose(t), received=r)
        m.add_scan(t, floor_points(), received=r)
    m.flush()
    assert m.counters["time_resets"] >= 10 and m.counters["scan_errors"] >= 1
    assert m.check(501.5)[0] == "ERROR"
    m.add_pose(50.0, base_pose(50.0), received=450.0)  # sim time jumped back with the stamps (same offset)
    assert m.failing_since is None


def test_an_internal_error_after_scoring_is_counted_and_the_live_threads_go_on():
    """A window function whose result health cannot read (here None: an internal bug) raises in the last
    stage's thread after scoring; the thread must survive it (else a blocking feeder waits forever), count
    it with its reason and keep processing."""
    import threading

    m = Monitor(config(**{"window.queue_size": 2}), None, lambda scans, cfg: None, live=True, block=True,
                stages=split_floor_scan())
    feeder = threading.Thread(target=feed, args=(m, 100.0 + np.arange(9) / 5.0), daemon=True)
    feeder.start()
    feeder.join(timeout=20)
    assert not feeder.is_alive(), "the feeder is stuck behind a dead stage thread"
    assert m.flush(timeout=20)
    assert all(t.is_alive() for t in m._threads)
    m.close()
    assert m.counters["scans_processed"] == 9 and m.counters["scan_errors"] == 3
    assert "internal error: AttributeError" in m.last_error


@pytest.mark.parametrize("model", ["", "OS1-128", "Mid-360"])
def test_warm_up_runs_its_synthetic_scans_to_a_scored_window(model):
    """The node's warm-up (compiled kernels, the network's export for the sensor's image shape) runs the
    whole pipeline: its three box-room scans of the named model (or a VLP-32C; the Mid-360 without rings)
    score windows, in the default mode (network segmentation), on the clouds' labels and without segmentation."""
    from topometric_ros.monitor import warm_up
    from topometric_ros.replay import load_segmenter

    for mode in ("none", "labels", "network"):
        cfg = load_config(overrides={"sensor.model": model, "segmentation.mode": mode})
        segmenter = load_segmenter(cfg) if mode == "network" else None
        seconds, windows = warm_up(cfg, segmenter)
        assert windows >= 1 and seconds > 0, (model, mode)


def test_close_without_a_flush_finishes_every_queued_scan_in_every_stage():
    """close() (drain) right after feeding: the scans still queued at the input and between the stages are
    processed before the threads stop; the second stage does not stop while the first still hands it scans."""
    import threading

    m = Monitor(config(**{"window.queue_size": 16}), None, floor_window, live=True, stages=split_floor_scan(0.01))
    feed(m, 100.0 + np.arange(9) / 5.0)
    closer = threading.Thread(target=m.close, daemon=True)
    closer.start()
    closer.join(timeout=20)
    assert not closer.is_alive(), "close() hangs: a stage stopped while the one before it still had scans for it"
    c = m.counters
    assert c["scans_processed"] == 9 and c["windows"] == 3 and c["dropped_scans"] == 0


def test_the_scans_in_flight_are_bounded_exactly_by_the_queues():
    """Live, two stages, the second held: the first stage fills the STAGE_QUEUE between them and waits with one
    more scan, the input queue holds queue_size, every other scan is dropped at the input and counted; once
    released, each scan is processed or counted."""
    import threading

    from topometric_ros.monitor import STAGE_QUEUE

    gate = threading.Event()
    first, second = split_floor_scan()
    held = lambda item, cfg: (gate.wait(10), second(item, cfg))[1]  # noqa: E731
    m = Monitor(config(**{"window.queue_size": 3}), None, floor_window, live=True, stages=(first, held))
    try:
        n, full = 20, 3 + STAGE_QUEUE + 2  # input queue, the queue between the stages, one scan in each stage
        stamps = 100.0 + np.arange(n) / 5.0
        for t in np.arange(99.5, stamps[-1] + 0.5, 0.05):
            m.add_pose(t, base_pose(t))
        for k, t in enumerate(stamps, 1):  # each scan is posed at once; wait for the stages to take what they can
            m.add_scan(t, floor_points())
            deadline = time.monotonic() + 5
            while m.queue_length > max(0, k - (STAGE_QUEUE + 2)) and time.monotonic() < deadline:
                time.sleep(0.002)
        time.sleep(0.05)
        assert m.queue_length == 3 and m.in_flight == full
        assert m.counters["dropped_queue_full"] == n - full
    finally:
        gate.set()
        m.close()
    c = m.counters
    assert c["scans_processed"] == full and c["scans_processed"] + c["dropped_queue_full"] == n


def test_scans_waiting_beyond_max_pending_drop_the_oldest_and_count_it():
    from topometric_ros.monitor import MAX_PENDING

    done = []
    record = lambda f, c, s, i: (done.append(f.stamp), floor_scan(f, c, s, i))[1]  # noqa: E731
    m = Monitor(config(**{"window.pose_timeout_s": 60.0}), record, floor_window)
    n = MAX_PENDING + 10
    stamps = 100.0 + np.arange(n) / 10.0  # 26.6 s of scans, within pose_timeout_s: none expires
    for t in stamps:
        m.add_scan(t, floor_points(20))
    assert m.pending_length == MAX_PENDING and m.counters["dropped_no_pose"] == 10
    for t in np.arange(99.0, stamps[-1] + 1.0, 0.05):
        m.add_pose(t, base_pose(t))
    m.flush()
    assert m.counters["scans_processed"] == MAX_PENDING and m.counters["dropped_no_pose"] == 10
    assert done == pytest.approx(list(stamps[10:]))  # the newest MAX_PENDING were kept


def test_scans_waiting_for_odometry_at_a_time_reset_are_counted_as_dropped():
    m = Monitor(config(), floor_scan, floor_window)
    m.add_pose(100.0, base_pose(100.0))
    for t in (100.1, 100.2, 100.3):
        m.add_scan(t, floor_points())  # no odometry past them: they wait
    assert m.pending_length == 3
    m.add_scan(10.0, floor_points())  # stamps went back: the three cannot be posed any more (nor this one:
    c = m.counters                    # the odometry is at 100 s)
    assert c["time_resets"] == 1 and c["dropped_no_pose"] == 4 and m.pending_length == 0
    assert c["scans_in"] == c["dropped_scans"] + m.pending_length + c["scans_processed"]


def test_waiting_scans_are_released_when_the_odometry_is_stale_though_scans_still_arrive():
    """release_waiting judges the odometry's receive clock, not the scans': scans arriving right up to ``now``
    do not keep scans waiting for odometry that stopped."""
    m = Monitor(config(**{"health.stale_after_s": 2.0}), floor_scan, floor_window)
    m.add_pose(100.0, base_pose(100.0), received=500.0)
    for k in range(4):
        m.add_scan(100.1 + k, floor_points(), received=500.1 + k)
    assert m.pending_length >= 1
    waiting = m.pending_length
    assert m.release_waiting(501.5) == 0  # odometry 1.5 s old: not stale yet
    assert m.release_waiting(503.2) == waiting and m.pending_length == 0  # 3.2 s old, a scan came 0.1 s ago


def test_the_extrinsic_is_applied_after_the_odometry_pose():
    """Sensor pose = odometry (child -> map) @ extrinsic (sensor -> child), with odometry that rolls and
    pitches, where the two orders differ."""
    tilt = lambda t: base_pose(t) @ geometry.make_pose(  # noqa: E731
        geometry.rotvec_to_matrix(np.array([0.3, -0.2, 0.0])), [0, 0, 0])
    ext = [0.4, -0.1, SENSOR_HEIGHT, 0.0, 0.0, np.sin(0.25), np.cos(0.25)]
    out = []
    m = Monitor(config(**{"window.extrinsic": ext}), floor_scan, floor_window, on_window=lambda r, s: out.extend(s))
    feed(m, 100.0 + np.arange(3) / 5.0, pose_fn=tilt)
    m.flush()
    assert len(out) == 3
    for s in out:
        np.testing.assert_allclose(s.pose, tilt(s.stamp) @ m.extrinsic, atol=1e-6)


def test_window_timings_add_up_the_stages_the_scans_and_the_wait():
    """scan.timings['monitor'] is the compute time of every stage, the window's scans_* timings sum its scans,
    latency runs from the last scan's arrival (queue waits included) to the result."""
    d = 0.02
    first, second = split_floor_scan(d)

    def timed(item, cfg):
        scan = second(item, cfg)
        scan.timings["total"] = 1.0 + scan.index
        return scan

    out = []
    with Monitor(config(**{"window.queue_size": 16}), None, floor_window, live=True, block=True,
                 stages=(first, timed), on_window=lambda r, s: out.append((r, s))) as m:
        feed(m, 100.0 + np.arange(3) / 5.0)
        m.flush()
    (result, scans), = out
    assert all(s.timings["monitor"] >= 2 * d * 1000 for s in scans)  # two stages of d s each
    assert result.timings["scans_monitor"] == pytest.approx(sum(s.timings["monitor"] for s in scans))
    assert result.timings["scans_total"] == pytest.approx(1.0 + 2.0 + 3.0)
    assert result.timings["latency"] >= 2 * d * 1000


def test_a_failing_window_consumer_is_told_in_last_error():
    def consumer(result, scans):
        raise RuntimeError("consumer broke")

    m = Monitor(config(), floor_scan, floor_window, on_window=consumer)
    feed(m, 100.0 + np.arange(3) / 5.0)
    m.flush()
    assert m.counters["windows"] == 1 and m.last_error == "on_window: RuntimeError: consumer broke"


def test_a_cloud_dropped_for_its_clock_is_one_of_the_dropped_scans():
    m = Monitor(config(**{"health.clock_jump_s": 0.5}), floor_scan, floor_window)
    assert not _a_cloud_ahead_of_its_clock(m)
    c = m.counters
    assert c["dropped_clock"] == 1 and c["dropped_scans"] == 1
