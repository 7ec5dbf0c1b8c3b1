"""Floor labels checked against the floor around them (segmentation/floor.py, config segmentation.floor_band)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from topometric_ros import classes as C
from topometric_ros.config import SegmentationConfig
from topometric_ros.geometry import rotvec_to_matrix
from topometric_ros.grid import ScanGrid
from topometric_ros.segmentation import floor as F
from topometric_ros.segmentation.checkpoint import SegmentationError
from topometric_ros.segmentation.infer import Segmenter

BAND = 0.04
ROWS, COLS = 12, 60


def _room():
    """A scan 1 m above a flat floor, as a 12 x 60 grid: rows 0-5 floor (x 2-2.5 m, y every 5 cm), with a chair's
    foot (rows 3-4, columns 28-32) 6 cm above the floor that the network called floor, and the chair itself
    (rows 6-8, columns 26-34) just behind it; rows 9-11 a wall at x 4 m. Points, grid, labels, confidence 0.9
    (the chair's 0.7) and the foot's indices."""
    r, c = np.meshgrid(np.arange(ROWS), np.arange(COLS), indexing="ij")
    r, c = r.ravel(), c.ravel()
    y = 0.05 * (c - COLS / 2)
    points = np.stack([2 + 0.1 * r, y, np.full(r.size, -1.0)], 1)
    labels = np.full(r.size, C.FLOOR, np.uint8)
    conf = np.full(r.size, 0.9, np.float32)
    foot = np.flatnonzero((r >= 3) & (r <= 4) & (c >= 28) & (c <= 32))
    points[foot, 2] += 0.06
    chair = (r >= 6) & (r <= 8)
    keep = ~chair | ((c >= 26) & (c <= 34))  # the chair's rows hold only the chair
    points[chair, 0], points[chair, 2] = 2.3, -0.9 + 0.1 * (r[chair] - 6)
    labels[chair], conf[chair] = C.CHAIR, 0.7
    wall = r >= 9
    points[wall, 0], points[wall, 2] = 4.0, -1.0 + 0.3 * (r[wall] - 9)
    labels[wall] = C.WALL
    index = np.cumsum(keep) - 1
    grid = ScanGrid(r[keep].astype(np.int32), c[keep].astype(np.int32), ROWS, COLS, np.zeros(ROWS), "test")
    return points[keep].astype(np.float32), grid, labels[keep], conf[keep], index[foot]


def test_a_chair_foot_labelled_floor_takes_the_chair_label_and_the_floor_stays_floor():
    points, grid, labels, conf, foot = _room()
    out, out_conf = F.lift_off_floor(points, grid, labels, conf, BAND)
    assert np.all(out[foot] == C.CHAIR)
    assert np.allclose(out_conf[foot], 0.7)  # its voters' confidence
    rest = np.setdiff1d(np.arange(len(points)), foot)
    assert np.array_equal(out[rest], labels[rest]) and np.array_equal(out_conf[rest], conf[rest])
    normal, offset = F.floor_plane(points, labels)
    assert np.allclose(normal, [0, 0, 1], atol=1e-6) and offset == pytest.approx(-1.0, abs=1e-6)  # trimmed: the foot is out


def test_a_foot_lower_than_the_band_or_beyond_reach_stays_floor():
    points, grid, labels, conf, foot = _room()
    points[foot, 2] = -1.0 + 0.03
    assert np.array_equal(F.lift_off_floor(points, grid, labels, conf, BAND)[0], labels)
    points[foot, 2] = -1.0 + F.REACH + 0.05  # another level
    assert np.array_equal(F.lift_off_floor(points, grid, labels, conf, BAND)[0], labels)


@pytest.mark.parametrize("rotvec", [(0.1, np.radians(15.0), 0.3), (0.1, np.radians(-30.0), 0.3), (np.pi, 0.0, 0.0)])
def test_a_tilted_or_upside_down_sensor_gets_the_same_labels(rotvec):
    points, grid, labels, conf, foot = _room()
    turned = (points.astype(np.float64) @ rotvec_to_matrix(np.array(rotvec)).T).astype(np.float32)
    out = F.lift_off_floor(turned, grid, labels, conf, BAND)[0]
    assert np.array_equal(out, F.lift_off_floor(points, grid, labels, conf, BAND)[0])
    assert np.all(out[foot] == C.CHAIR)
    points[foot, 2] = -1.0 - 0.06  # a dip, not a foot: stays floor either way up
    turned = (points.astype(np.float64) @ rotvec_to_matrix(np.array(rotvec)).T).astype(np.float32)
    assert np.array_equal(F.lift_off_floor(turned, grid, labels, conf, BAND)[0], labels)


def test_points_without_coordinates_are_ignored():
    points, grid, labels, conf, foot = _room()
    points[[0, 7, 100]] = np.nan  # floor points with no return
    out, _ = F.lift_off_floor(points, grid, labels, conf, BAND)
    assert np.all(out[foot] == C.CHAIR) and np.array_equal(np.delete(out, foot), np.delete(labels, foot))


def test_the_window_wraps_around_in_azimuth_once_on_a_narrow_grid():
    """A ring of 8 columns (a 15-column window would wrap it twice): a foot 6 cm up in column 0, across the seam
    two chair points in column 7 (0.45 and 0.50 m from it) and three wall points in column 6 (0.60-0.70 m), a
    floor point beside it in column 1 and 60 floor points in columns 3-4. Each neighbour votes once: wall 3,
    chair 2. (Counted twice, the five nearest slots would be both chair points twice and a wall: chair.)"""
    foot = [3.0, 0.0, -0.94]
    chairs = [[3.0, -0.45, -0.9], [3.0, -0.5, -0.9]]
    walls = [[3.0, -0.6, -0.9], [3.0, -0.65, -0.9], [3.0, -0.7, -0.9]]
    floor = [[3.0, 0.5, -1.0]] + [[3.0 + 0.1 * k, 2.0 + k % 3, -1.0] for k in range(60)]
    points = np.array([foot, *chairs, *walls, *floor], np.float32)
    col = np.array([0, 7, 7, 6, 6, 6, 1] + [3 + k % 2 for k in range(60)], np.int32)
    labels = np.array([C.FLOOR] + [C.CHAIR] * 2 + [C.WALL] * 3 + [C.FLOOR] * 61, np.uint8)
    grid = ScanGrid(np.zeros(len(points), np.int32), col, 1, 8, np.zeros(1), "test")
    out, _ = F.lift_off_floor(points, grid, labels, np.ones(len(points), np.float32), BAND)
    assert out[0] == C.WALL
    assert np.array_equal(out[1:], labels[1:])


def test_a_floor_tilted_beyond_45_degrees_from_the_sensor_or_too_few_floor_points_change_nothing():
    points, grid, labels, conf, _ = _room()
    steep = (points.astype(np.float64) @ rotvec_to_matrix(np.array([0.0, np.radians(50.0), 0.0])).T).astype(np.float32)
    assert F.floor_plane(steep, labels) is None
    assert np.array_equal(F.lift_off_floor(steep, grid, labels, conf, BAND)[0], labels)
    few = labels.copy()
    few[np.flatnonzero(few == C.FLOOR)[F.MIN_FLOOR_POINTS - 1:]] = C.WALL
    assert F.floor_plane(points, few) is None
    out, out_conf = F.lift_off_floor(points, grid, labels, conf, 0.0)
    assert out is labels and out_conf is conf


def test_floor_that_rises_gently_beside_a_wall_stays_floor_the_step_must_be_local():
    """A floor rising 5 % from x = 6 m (up to 9 cm above the flat part) next to a wall: every floor point stays
    floor. Judged against the floor plane alone (the flat part's), the rising points by the wall would go to the
    wall; within 1 m (the grid window's 0.6 m along x here) the floor rises less than the band."""
    r, c = np.meshgrid(np.arange(40), np.arange(40), indexing="ij")
    r, c = r.ravel(), c.ravel()
    x = 0.2 * r
    wall = c >= 36
    points = np.stack([x, 0.1 * c, -1.0 + 0.05 * np.clip(x - 6.0, 0, None)], 1)
    points[wall, 1], points[wall, 2] = 3.6, -1.0 + 0.2 * (c[wall] - 35)
    labels = np.where(wall, C.WALL, C.FLOOR).astype(np.uint8)
    grid = ScanGrid(r.astype(np.int32), c.astype(np.int32), 40, 40, np.zeros(40), "test")
    conf = np.ones(len(points), np.float32)
    points = points.astype(np.float32)
    normal, offset = F.floor_plane(points, labels)
    above = (labels == C.FLOOR) & (points @ normal - offset > BAND)
    assert above.sum() > 50 and np.allclose(normal, [0, 0, 1], atol=0.01)  # about the flat part's plane
    assert np.array_equal(F.lift_off_floor(points, grid, labels, conf, BAND)[0], labels)
    points[:, 2] = np.where(wall, points[:, 2], -1.0 + np.where(r >= 34, 0.09, 0.0))  # a 9 cm step instead:
    by_the_step = (r >= 34) & (r <= 36) & (c >= 30) & ~wall  # its top by the wall goes to the wall
    assert (F.lift_off_floor(points, grid, labels, conf, BAND)[0][by_the_step] == C.WALL).all()


def _reference(points, grid, labels, conf, band, distance, window):
    """lift_off_floor's rule written plainly, on the same floor plane."""
    normal, offset = F.floor_plane(points, labels)
    p = points.astype(np.float64)
    h = p @ normal - offset
    at = {}
    for i, cell in enumerate(zip(grid.row, grid.col)):
        at.setdefault(cell, []).append(i)
    out, out_conf = labels.copy(), conf.copy()
    rows, cols = window
    for i in np.flatnonzero((labels == C.FLOOR) & (h > band) & (h <= F.REACH)):
        near = []
        for dr in range(-(rows // 2), rows - rows // 2):
            for dc in range(-(cols // 2), cols - cols // 2):
                if 0 <= grid.row[i] + dr < grid.height:
                    near += at.get((grid.row[i] + dr, (grid.col[i] + dc) % grid.width), [])
        near = [j for j in near if np.sum((p[j] - p[i]) ** 2) <= distance ** 2]
        lowest = min([h[i]] + [h[j] for j in near if labels[j] == C.FLOOR])
        voters = sorted((np.sum((p[j] - p[i]) ** 2), j) for j in near if labels[j] != C.FLOOR)[:F.VOTERS]
        if not voters or h[i] - lowest <= band:
            continue
        classes = [labels[j] for _, j in voters]
        top = max(classes.count(k) for k in classes)
        win = next(k for k in classes if classes.count(k) == top)
        out[i] = win
        out_conf[i] = np.mean([conf[j] for _, j in voters if labels[j] == win])
    return out, out_conf


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_check_matches_its_rule_written_plainly_on_random_scans(seed):
    """Random points on a small grid (cells empty, some shared): a floor near z = -1 with bumps labelled floor,
    and chair / wall / other points above: the compiled check gives the plain rule's labels and confidence."""
    rng = np.random.default_rng(seed)
    height, width, n = 8, 30, 600
    row, col = rng.integers(0, height, n).astype(np.int32), rng.integers(0, width, n).astype(np.int32)
    az = 2 * np.pi * col / width
    dist = 1.5 + 0.3 * row + 0.2 * rng.random(n)
    labels = rng.choice([C.FLOOR, C.WALL, C.CHAIR, C.OTHER], n, p=[0.7, 0.1, 0.1, 0.1]).astype(np.uint8)
    z = np.where(labels == C.FLOOR, -1.0 + 0.01 * rng.standard_normal(n), -1.0 + rng.random(n))
    bumps = (labels == C.FLOOR) & (rng.random(n) < 0.2)
    z[bumps] += 0.02 + 0.25 * rng.random(bumps.sum())
    points = np.stack([dist * np.cos(az), dist * np.sin(az), z], 1).astype(np.float32)
    conf = rng.random(n).astype(np.float32)
    grid = ScanGrid(row, col, height, width, np.zeros(height), "test")
    for distance, window in ((1.0, F.WINDOW), (0.5, (3, 5)), (2.0, (5, 3))):
        want = _reference(points, grid, labels, conf, BAND, distance, window)
        got = F.lift_off_floor(points, grid, labels, conf, BAND, distance, window)
        assert np.array_equal(got[0], want[0])
        assert np.allclose(got[1], want[1], atol=1e-6)
    assert (F.lift_off_floor(points, grid, labels, conf, BAND)[0] != labels).any()  # the check had work to do


def test_a_negative_band_is_refused():
    with pytest.raises(SegmentationError, match="segmentation.floor_band"):
        Segmenter.from_config(replace(SegmentationConfig(), floor_band=-0.01))


def test_the_snap_makes_floor_of_what_lies_on_the_floor_plane_and_nothing_else():
    """snap_to_floor: other / wall / desk / chair points within the band of the floor plane become floor with the
    floor points' mean confidence; a point just outside the band, a pillar on the plane, and every floor point keep
    their labels."""
    points, grid, labels, conf, foot = _room()
    points[foot, 2] = -1.0  # the foot flat again: a plain floor
    points[labels == C.WALL, 2] += 0.05  # the wall's foot off the floor plane (on it, it would snap)
    rng = np.random.default_rng(3)
    floor = np.flatnonzero(labels == C.FLOOR)
    misread = rng.choice(floor, 12, replace=False)
    labels[misread] = np.array([C.WALL, C.OTHER, C.DESK, C.CHAIR] * 3)
    conf[misread] = 0.4
    pillar = np.setdiff1d(floor, misread)[:2]
    labels[pillar] = C.PILLAR
    above = np.flatnonzero(labels == C.WALL)[-1]  # a wall point 1 cm above the band
    points[above, 2] = -1.0 + 0.03
    out, out_conf = F.snap_to_floor(points, labels, conf, 0.02)
    assert np.all(out[misread] == C.FLOOR)
    assert np.allclose(out_conf[misread], conf[labels == C.FLOOR].mean())
    rest = np.setdiff1d(np.arange(len(points)), misread)
    assert np.array_equal(out[rest], labels[rest]) and np.array_equal(out_conf[rest], conf[rest])
    assert out[above] == C.WALL and np.all(out[pillar] == C.PILLAR)
    assert np.array_equal(F.snap_to_floor(points, labels, conf, 0.0)[0], labels)  # off
    few = labels.copy()
    few[few == C.FLOOR] = C.OTHER  # no floor labels: no plane, nothing changes
    assert np.array_equal(F.snap_to_floor(points, few, conf, 0.02)[0], few)


def test_the_segmenter_snaps_non_repetitive_scans_only():
    """The same Segmenter with and without segmentation.floor_snap: a spinning scan comes out identical, a Mid-360
    scan gains floor points and loses none."""
    from topometric_ros.sim.frames import simulated_frames

    off = Segmenter.from_config(replace(SegmentationConfig(), floor_snap=0.0))
    on = Segmenter.from_config(SegmentationConfig())
    assert on.floor_snap == 0.02
    (spinning,), _ = simulated_frames("office2", 1, seed=5)
    a, b = off.predict(spinning.points, spinning.ring), on.predict(spinning.points, spinning.ring)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    (mid,), _ = simulated_frames("garage", 1, seed=2, sensor="Mid-360")  # 942 floor points in view
    (a, _), (b, _) = off.predict(mid.points, mid.ring), on.predict(mid.points, mid.ring)
    assert np.all(b[a == C.FLOOR] == C.FLOOR) and np.count_nonzero(b == C.FLOOR) > np.count_nonzero(a == C.FLOOR)
    with pytest.raises(SegmentationError, match="segmentation.floor_snap"):
        Segmenter.from_config(replace(SegmentationConfig(), floor_snap=-0.01))


def _flat_floor(n_cols: int = 40, rows: int = 10, z: float = -1.0):
    """A flat floor z = ``z`` m as a rows x n_cols grid (x 2 m + 0.1 m per row, y 5 cm per column), all floor."""
    r, c = np.meshgrid(np.arange(rows), np.arange(n_cols), indexing="ij")
    r, c = r.ravel(), c.ravel()
    points = np.stack([2 + 0.1 * r, 0.05 * (c - n_cols / 2), np.full(r.size, z)], 1).astype(np.float32)
    grid = ScanGrid(r.astype(np.int32), c.astype(np.int32), rows, n_cols, np.zeros(rows), "test")
    return points, grid, np.full(r.size, C.FLOOR, np.uint8), np.full(r.size, 0.9, np.float32)


def test_exactly_min_floor_points_floor_points_give_a_plane():
    points, _, labels, _ = _flat_floor()
    labels[F.MIN_FLOOR_POINTS:] = C.WALL
    normal, offset = F.floor_plane(points, labels)
    assert np.allclose(np.abs(normal), [0, 0, 1], atol=1e-6) and offset == pytest.approx(-1.0, abs=1e-6)
    labels[F.MIN_FLOOR_POINTS - 1] = C.WALL
    assert F.floor_plane(points, labels) is None


def test_the_floor_plane_of_many_floor_points_is_fitted_to_an_even_sample_of_all_of_them():
    """2 x 1200 floor points, the first 1200 (in scan order) at z = -1.00 m, the next 1200 on the same x-y
    places at -1.02 m (a floor 2 cm lower further on): every point is within the fit's tolerance of the plane
    between them, so the plane lies halfway, -1.01 m; a fit to the first FIT_POINTS alone would say -1.00."""
    points, _, labels, _ = _flat_floor(n_cols=120)
    lower = points.copy()
    lower[:, 2] = -1.02
    points, labels = np.concatenate([points, lower]), np.concatenate([labels, labels])
    assert len(points) > 2 * F.FIT_POINTS
    normal, offset = F.floor_plane(points, labels)
    assert np.allclose(normal, [0, 0, 1], atol=1e-4) and offset == pytest.approx(-1.01, abs=1e-3)


def test_the_floor_fit_keeps_every_point_within_its_tolerance_of_the_plane():
    """A floor of 600 points (z = -1 m within 2 mm) of which 90 (15 %) stand 2 cm higher (a rug): all within
    FIT_TOLERANCE of the plane, so all count, and the plane is their least-squares plane, 3 mm up
    (0.15 x 2 cm); trimming the highest 20 % regardless would drop the rug (-1.000)."""
    points, _, labels, _ = _flat_floor(n_cols=60)
    rng = np.random.default_rng(0)
    points[:, 2] += rng.uniform(-0.002, 0.002, len(points)).astype(np.float32)
    rug = np.arange(len(points)) % 20 < 3  # 3 of every 20 points, spread over the floor
    points[rug, 2] += 0.02
    normal, offset = F.floor_plane(points, labels)
    p = points.astype(np.float64)
    ls_normal = np.linalg.svd(p - p.mean(0))[2][2]  # the least-squares plane of every point
    ls_normal *= np.sign(ls_normal[2])
    assert np.allclose(normal, ls_normal, atol=1e-5) and offset == pytest.approx(ls_normal @ p.mean(0), abs=1e-5)
    assert offset == pytest.approx(-0.997, abs=1e-3)


def test_the_snap_takes_points_within_the_band_either_side_of_the_plane_and_nothing_far_below_it():
    """snap_to_floor with band 2 cm on a flat floor at z = -1 m: a wall point 1 cm below the plane and one 1 cm
    above become floor; an 'other' point 10 cm below (a pit, a reflection) and a chair point 10 cm above stay."""
    points, _, labels, conf = _flat_floor()
    near_below, near_above, far_below, far_above = 5, 6, 7, 8
    points[[near_below, near_above, far_below, far_above], 2] = [-1.01, -0.99, -1.10, -0.90]
    labels[[near_below, near_above, far_below, far_above]] = [C.WALL, C.WALL, C.OTHER, C.CHAIR]
    out, _ = F.snap_to_floor(points, labels, conf, 0.02)
    assert out[near_below] == out[near_above] == C.FLOOR
    assert out[far_below] == C.OTHER and out[far_above] == C.CHAIR


def test_a_foot_up_to_reach_is_lifted_and_one_higher_is_another_level():
    """REACH is 0.3 m (config segmentation.floor_band's documented limit): the chair's foot labelled floor 25 cm
    above the floor takes the chair's label; 35 cm above it is left floor (another level, a step)."""
    assert F.REACH == 0.3
    points, grid, labels, conf, foot = _room()
    points[foot, 2] = -1.0 + 0.25
    assert np.all(F.lift_off_floor(points, grid, labels, conf, BAND)[0][foot] == C.CHAIR)
    points[foot, 2] = -1.0 + 0.35
    assert np.array_equal(F.lift_off_floor(points, grid, labels, conf, BAND)[0], labels)
