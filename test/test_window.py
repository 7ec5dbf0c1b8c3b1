"""PoseBuffer (interpolation by stamp, gaps, time jumps) and SlidingWindow (size, step, resets)."""
import numpy as np
import pytest

from topometric_ros import geometry
from topometric_ros.window import PoseBuffer, SlidingWindow


def _buffer(stamps, poses, horizon=30.0):
    b = PoseBuffer(horizon)
    for s, p in zip(stamps, poses):
        assert b.add(s, p) == "ok"
    return b


def test_lookup_interpolates_translation_linearly_and_yaw_by_slerp():
    poses = geometry.yaw_pose([0.0, 2.0], [0.0, 4.0], 0.0, [0.0, np.pi / 2])
    b = _buffer([10.0, 11.0], poses)
    mid = b.lookup(10.25, max_gap_s=1.0)
    np.testing.assert_allclose(mid[:3, 3], [0.5, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(geometry.rotation_angle(mid[:3, :3]), np.pi / 8, atol=1e-9)
    np.testing.assert_allclose(b.lookup(11.0, 1.0), poses[1])  # an exact stamp returns that pose


def test_lookup_outside_the_buffer_or_beyond_the_gap_is_none():
    poses = geometry.yaw_pose([0.0, 1.0, 2.0], 0.0, 0.0, 0.0)
    b = _buffer([0.0, 0.1, 2.0], poses)
    assert b.lookup(-0.01, 0.5) is None
    assert b.lookup(2.01, 0.5) is None
    assert b.lookup(0.05, 0.5) is not None
    assert b.lookup(1.0, 0.5) is None  # 0.9 s from both neighbours: no odometry within the gap
    assert b.lookup(1.0, 1.0) is not None


def test_lookup_many_gives_each_stamp_what_lookup_gives_it():
    """A sweep's knots in one call: interpolated, exact hits, extrapolated past the newest pose; None as soon
    as one stamp has no pose (outside, beyond the gap, too far ahead)."""
    rng = np.random.default_rng(4)
    stamps = np.cumsum(rng.uniform(0.005, 0.03, 60))
    b = _buffer(stamps, geometry.yaw_pose(rng.normal(size=60), rng.normal(size=60), 0.1 * rng.normal(size=60),
                                          rng.uniform(-3, 3, 60), 0.1 * rng.normal(size=60), 0.1 * rng.normal(size=60)))
    query = np.concatenate([np.linspace(stamps[3], stamps[-1] + 0.05, 17), stamps[[5, 9]]])
    many = b.lookup_many(query, max_gap_s=0.05, extrapolate_s=0.1)
    one = np.stack([b.lookup(t, 0.05, extrapolate_s=0.1) for t in query])
    np.testing.assert_allclose(many, one, atol=1e-12)
    np.testing.assert_array_equal(many[-2:], one[-2:])  # exact stamps: the stored poses themselves
    assert b.lookup_many(np.array([stamps[0] - 0.01, stamps[4]]), 0.05) is None  # before the buffer
    assert b.lookup_many(np.array([stamps[4], stamps[-1] + 0.2]), 0.05, extrapolate_s=0.1) is None  # too far ahead
    assert b.lookup_many(np.array([stamps[4] + 0.001]), 0.0005) is None  # beyond the gap
    assert b.lookup_many(np.array([]), 0.05) is None and PoseBuffer(1.0).lookup_many(query, 0.05) is None


def test_lookup_needs_both_neighbours_within_the_gap_and_a_gap_of_exactly_max_gap_is_fine():
    b = _buffer([0.0, 0.1, 2.0], geometry.yaw_pose([0.0, 1.0, 2.0], 0.0, 0.0, 0.0))
    assert b.lookup(0.15, 0.5) is None  # 0.05 s after one pose, but 1.85 s before the next
    assert b.lookup(1.95, 0.5) is None  # the other way round
    b = _buffer([0.0, 1.0], geometry.yaw_pose([0.0, 1.0], 0.0, 0.0, 0.0))
    np.testing.assert_allclose(b.lookup(0.5, 0.5)[:3, 3], [0.5, 0.0, 0.0], atol=1e-12)


def test_extrapolation_continues_the_last_steps_motion_at_constant_velocity():
    """The last step moved 0.2 m and turned 0.1 rad in 0.1 s: half a step later the pose is 0.1 m and 0.05 rad
    further on (in the pose's own frame), a whole step later (the extrapolation limit, included) 0.2 m and 0.1 rad."""
    poses = geometry.yaw_pose([0.0, 0.2], [0.0, 0.0], 0.0, [0.0, 0.1])
    b = _buffer([0.0, 0.1], poses)
    for ahead in (0.5, 1.0):
        expected = poses[1] @ geometry.make_pose(geometry.rotvec_to_matrix([0.0, 0.0, 0.1 * ahead]),
                                                 [0.2 * ahead, 0.0, 0.0])
        got = b.lookup(0.1 + 0.1 * ahead, 0.5, extrapolate_s=0.1)
        assert got is not None
        np.testing.assert_allclose(got, expected, atol=1e-9)
    far = _buffer([0.0, 1.0], geometry.yaw_pose([0.0, 0.2], 0.0, 0.0, 0.0))
    assert far.lookup(1.05, 0.5, extrapolate_s=0.1) is None  # its last two poses are 1 s apart: no motion to go on


def test_duplicate_is_ignored_and_backwards_restarts():
    b = _buffer([0.0, 1.0], geometry.yaw_pose([0.0, 1.0], 0.0, 0.0, 0.0))
    assert b.add(1.0, np.eye(4)) == "duplicate"
    assert len(b) == 2
    assert b.add(0.5, np.eye(4)) == "backwards"
    assert len(b) == 1 and b.newest == 0.5


def test_horizon_bounds_memory_but_keeps_a_bracket():
    stamps = np.arange(0, 100, 0.05)
    b = _buffer(stamps, np.repeat(np.eye(4)[None], len(stamps), 0), horizon=2.0)
    assert len(b) <= 2.0 / 0.05 + 3
    assert b.oldest >= stamps[-1] - 2.1
    assert b.lookup(stamps[-1] - 1.0, 0.1) is not None


@pytest.mark.parametrize("size,step", [(5, 5), (5, 2), (3, 5), (1, 1)])
def test_windows_have_size_and_start_every_step(size, step):
    w = SlidingWindow(size, step)
    out = [win for i in range(40) if (win := w.push(i, float(i))) is not None]
    assert all(len(win) == size for win in out)
    assert all(win == list(range(win[0], win[0] + size)) for win in out)
    assert [win[0] for win in out] == list(range(0, 40 - size + 1, step))


def test_step_zero_means_size():
    w = SlidingWindow(4, 0)
    out = [win for i in range(12) if (win := w.push(i, float(i))) is not None]
    assert out == [[0, 1, 2, 3], [4, 5, 6, 7], [8, 9, 10, 11]]


def test_backwards_or_repeated_stamp_restarts_the_window():
    w = SlidingWindow(3)
    assert w.push("a", 10.0) is None and w.push("b", 11.0) is None
    assert w.push("c", 5.0) is None  # bag loop: a, b discarded
    assert w.discarded == 1 and w.resets == 1
    assert w.push("d", 6.0) is None
    assert w.push("e", 7.0) == ["c", "d", "e"]
    w.push("f", 8.0)
    w.push("g", 8.0)  # duplicate stamp also restarts
    assert w.resets == 2 and len(w) == 1


def test_a_restart_counts_a_discarded_window_only_when_one_was_partly_filled():
    w = SlidingWindow(2)
    assert w.push("a", 0.0) is None and w.push("b", 1.0) == ["a", "b"]
    w.push("c", 0.5)  # backwards, nothing held: nothing thrown away
    assert w.resets == 1 and w.discarded == 0
    w.push("d", 0.2)  # backwards again, "c" held
    assert w.resets == 2 and w.discarded == 1


def test_bad_sizes_are_rejected():
    with pytest.raises(ValueError):
        SlidingWindow(-1)
    with pytest.raises(ValueError):
        SlidingWindow(3, -1)
    with pytest.raises(ValueError, match="duration"):
        SlidingWindow(0, 0, 0.0)


@pytest.mark.parametrize("rate_hz, duration_s, size", [(10, 1.0, 10), (5, 1.0, 5), (20, 1.0, 20), (10, 0.5, 5),
                                                        (1, 1.0, 3), (1000, 1.0, 200)])
def test_an_automatic_window_holds_duration_s_of_scans_at_the_streams_rate(rate_hz, duration_s, size):
    w = SlidingWindow(0, 0, duration_s)
    assert w.size is None and "automatic" in w.describe()
    out = [win for i in range(3 * size) if (win := w.push(i, 100.0 + i / rate_hz)) is not None]
    assert w.size == size and w.step == size and w.scan_period_s == pytest.approx(1 / rate_hz)
    assert out == [list(range(k * size, (k + 1) * size)) for k in range(3)]  # the probe's scans are the first window's
    bound = {3: ", at least 3", 200: ", at most 200"}.get(size, "") if size != rate_hz * duration_s else ""
    assert w.describe() == f"{size} scans (automatic: {duration_s:g} s at {rate_hz:.3g} Hz{bound})"


def test_an_automatic_window_reads_the_rate_through_a_dropped_scan_jitter_and_a_restart():
    w = SlidingWindow(0, 2)
    stamps = [0.0, 0.2, 0.3, 0.4, 0.5]  # the scan at 0.1 s never arrived: 0.2 s is not taken for a period
    assert [w.push(s, s) for s in stamps[:3]] == [None] * 3 and w.size is None  # uneven: it waits for more
    assert [w.push(s, s) for s in stamps[3:]] == [None] * 2 and w.size is None
    w.push(0.6, 0.6)
    assert w.size == 10 and w.step == 2 and w.describe() == "10 scans (automatic: 1 s at 10 Hz), one every 2 scans"
    w = SlidingWindow(0)
    for s in (0.0, 0.092, 0.2):  # stamps 8 ms early and on time: the median period, not the shortest (11 scans)
        w.push(s, s)
    assert w.size == 10 and w.scan_period_s == pytest.approx(0.1)
    w = SlidingWindow(0)
    w.push("a", 5.0)
    w.push("b", 5.1)
    w.push("c", 1.0)  # the bag looped before the size was set: the probe starts again with the window
    assert w.size is None and w.discarded == 1
    w.push("d", 1.25)
    w.push("e", 1.5)
    assert w.size == 4 and w.push("f", 1.75) == ["c", "d", "e", "f"]


def test_the_period_leaves_out_the_intervals_of_dropped_scans_before_taking_the_median():
    """10 Hz with two scans dropped and one interval 5 ms long: intervals 0.1 0.2 0.105 0.2 0.1; the median of all
    five would be 0.105 s (19 scans in 2 s), of those within 1.5 × the median 0.1 s (20 scans)."""
    w = SlidingWindow(0, duration_s=2.0)
    for s in (0.0, 0.1, 0.3, 0.405, 0.605, 0.705):
        w.push(s, s)
    assert w.scan_period_s == pytest.approx(0.1) and w.size == 20


@pytest.mark.parametrize("jitter", [0.03, -0.03])
def test_stamp_jitter_in_the_first_scans_is_not_read_as_a_dropped_scan(jitter):
    """10 Hz with 30 ms of jitter on the second stamp: three stamps look like 14 Hz with a dropped scan, so the
    window waits for six and reads 10 Hz; the scans it held all go into windows (size 10 > 6 held)."""
    w = SlidingWindow(0)
    stamps = [0.0, 0.1 + jitter, 0.2, 0.3, 0.41, 0.5]
    for k, s in enumerate(stamps):
        assert w.size is None
        w.push(k, s)
    assert w.size == 10 and w.scan_period_s == pytest.approx(0.1)
    windows = [w.push(k, 0.1 * k) for k in range(6, 10)]
    assert windows[-1] == list(range(10))
    small = SlidingWindow(0, duration_s=0.3)  # 3 scans a window: it starts at the newest of the six held
    assert [small.push(k, s) for k, s in enumerate(stamps)][-1] == [3, 4, 5] and small.size == 3
    assert [small.push(k, 0.1 * k) for k in range(6, 9)] == [None, None, [6, 7, 8]]
