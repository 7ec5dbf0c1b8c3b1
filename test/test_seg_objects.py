"""One label per object (segmentation/objects.py, config segmentation.object_gap)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from topometric_ros import classes as C
from topometric_ros.config import SegmentationConfig
from topometric_ros.grid import ScanGrid
from topometric_ros.segmentation import objects as O
from topometric_ros.segmentation.checkpoint import SegmentationError
from topometric_ros.segmentation.infer import Segmenter

GAP = 0.2
ROWS, COLS = 10, 60


def _office():
    """A 10 x 60 grid seen from the origin along +x: a wall at x 5 m everywhere, a desk front at x 3 m (rows 1-7,
    columns 10-25) and a chair at x 2 m (rows 1-5, columns 26-31), points 5 cm apart across and 10 cm up. Labels
    as drawn, confidence 0.8 (wall 0.9). Points, grid, labels, confidence and the (row, col) of each point."""
    r, c = np.meshgrid(np.arange(ROWS), np.arange(COLS), indexing="ij")
    r, c = r.ravel(), c.ravel()
    points = np.stack([np.full(r.size, 5.0), 0.05 * (c - COLS / 2), 0.1 * r - 0.5], 1)
    labels = np.full(r.size, C.WALL, np.uint8)
    conf = np.full(r.size, 0.9, np.float32)
    desk = (r >= 1) & (r <= 7) & (c >= 10) & (c <= 25)
    chair = (r >= 1) & (r <= 5) & (c >= 26) & (c <= 31)
    points[desk, 0], labels[desk], conf[desk] = 3.0, C.DESK, 0.8
    points[chair, 0], labels[chair], conf[chair] = 2.0, C.CHAIR, 0.8
    grid = ScanGrid(r.astype(np.int32), c.astype(np.int32), ROWS, COLS, np.zeros(ROWS), "test")
    return points.astype(np.float32), grid, labels, conf, r, c


def test_a_desk_partly_labelled_chair_becomes_all_desk_and_the_chair_in_front_stays_a_chair():
    points, grid, labels, conf, r, c = _office()
    wrong = np.flatnonzero((labels == C.DESK) & (c >= 20))  # 6 of the desk's 16 columns: 37.5 % called chair
    labels[wrong], conf[wrong] = C.CHAIR, 0.5
    chair = np.flatnonzero((c >= 26) & (c <= 31) & (r >= 1) & (r <= 5))
    labels[chair[:8]] = C.DESK  # 8 of the chair's 30 points called desk
    out, out_conf = O.unify_objects(points, grid, labels, conf, GAP)
    desk = (c >= 10) & (c <= 25) & (r >= 1) & (r <= 7)
    assert np.all(out[desk] == C.DESK)
    assert np.allclose(out_conf[wrong], 0.8)  # the mean confidence of the points that were desk already
    assert np.all(out[chair] == C.CHAIR)  # 1 m in front of the desk: its own object, not merged into the desk
    assert np.array_equal(out[labels == C.WALL], labels[labels == C.WALL])
    assert np.array_equal(out_conf[labels == C.WALL], conf[labels == C.WALL])


def test_an_object_without_a_clear_majority_keeps_its_labels():
    points, grid, labels, conf, r, c = _office()
    split = (labels == C.DESK) & (c >= 18)  # 8 of 16 columns: 50 %
    labels[split] = C.CHAIR
    out, out_conf = O.unify_objects(points, grid, labels, conf, GAP)
    assert np.array_equal(out, labels) and np.array_equal(out_conf, conf)
    assert np.count_nonzero(O.unify_objects(points, grid, labels, conf, GAP, share=0.5)[0] != labels) > 0


def test_structure_between_two_objects_does_not_join_them():
    points, grid, labels, conf, r, c = _office()
    labels[(labels == C.DESK) & (c >= 14) & (c <= 16)] = C.PILLAR  # at the desk's range, 3 columns wide
    small = (labels == C.DESK) & (c <= 13)  # columns 10-13 now stand apart
    labels[small] = C.CHAIR
    out, _ = O.unify_objects(points, grid, labels, conf, GAP)
    assert np.all(out[small] == C.CHAIR)
    assert np.all(out[labels == C.PILLAR] == C.PILLAR)
    labels[(labels == C.PILLAR)] = C.DESK  # the same points as desk: one object, the desk's majority wins
    assert np.all(O.unify_objects(points, grid, labels, conf, GAP)[0][small] == C.DESK)


def test_the_gap_decides_what_touches():
    points, grid, labels, conf, r, c = _office()
    desk = (labels == C.DESK).copy()
    labels[desk & (c >= 20)] = C.CHAIR
    assert np.all(O.unify_objects(points, grid, labels, conf, 0.06)[0][desk] == C.DESK)  # each row joins along
    assert np.array_equal(O.unify_objects(points, grid, labels, conf, 0.04)[0], labels)  # 5 cm apart: nothing joins
    assert np.array_equal(O.unify_objects(points, grid, labels, conf, 0.0)[0], labels)  # off


def test_an_object_across_the_azimuth_seam_is_one_object():
    cols, radius = 60, 1.5  # neighbouring columns 16 cm apart
    r, c = np.meshgrid(np.arange(4), np.arange(cols), indexing="ij")
    r, c = r.ravel(), c.ravel()
    az = 2 * np.pi * c / cols
    points = np.stack([radius * np.cos(az), radius * np.sin(az), 0.1 * r], 1).astype(np.float32)
    labels = np.full(r.size, C.WALL, np.uint8)
    labels[c >= cols - 5] = C.DESK
    labels[c <= 2] = C.CHAIR  # 3 columns of chair against 5 of desk across the seam
    grid = ScanGrid(r.astype(np.int32), c.astype(np.int32), 4, cols, np.zeros(4), "test")
    out, _ = O.unify_objects(points, grid, labels, np.ones(r.size, np.float32), GAP)
    assert np.all(out[c <= 2] == C.DESK)


def test_points_with_nan_coordinates_join_nothing_and_keep_their_label():
    points, grid, labels, conf, r, c = _office()
    odd = np.flatnonzero((labels == C.DESK) & (r == 4) & (c == 15))
    labels[odd] = C.CHAIR
    points[odd, 1] = np.nan
    out, _ = O.unify_objects(points, grid, labels, conf, GAP)
    assert np.all(out[odd] == C.CHAIR)
    assert np.all(out[(labels == C.DESK)] == C.DESK)


def _reference(points, grid, labels, conf, gap, share):
    """The rule written plainly: desk and chair points joined to the last such point of their own cell and of the
    cells one column on, one row up (columns -1, 0, +1), two columns on and two rows up, when nearer than gap;
    scipy's connected components; each object's commonest label at >= share of it."""
    obj = np.flatnonzero(np.isin(labels, (C.DESK, C.CHAIR)) & np.isfinite(points).all(1))
    last = {}
    for k, i in enumerate(obj):
        last[(grid.row[i], grid.col[i])] = k
    a, b = [], []
    for k, i in enumerate(obj):
        for dr, dc in ((0, 0), (0, 1), (1, -1), (1, 0), (1, 1), (0, 2), (2, 0)):
            j = last.get((grid.row[i] + dr, (grid.col[i] + dc) % grid.width))
            if j is not None and j != k and np.linalg.norm(points[i] - points[obj[j]]) < gap:
                a.append(k)
                b.append(j)
    graph = coo_matrix((np.ones(len(a)), (a, b)), shape=(len(obj), len(obj)))
    component = connected_components(graph, directed=False)[1]
    out_labels, out_conf = labels.copy(), conf.copy()
    for comp in np.unique(component):
        members = obj[component == comp]
        counts = np.bincount(labels[members], minlength=C.NUM_CLASSES)
        best = counts.argmax()
        if counts[best] >= share * len(members):
            change = members[labels[members] != best]
            out_labels[change] = best
            out_conf[change] = conf[members[labels[members] == best]].mean()
    return out_labels, out_conf


def test_the_objects_match_the_rule_written_plainly_on_random_scans():
    rng = np.random.default_rng(7)
    changed = 0
    for trial in range(9):
        rows, cols, n = 8, 40, (500, 120)[trial % 3 == 2]
        row, col = rng.integers(0, rows, n), rng.integers(0, cols, n)  # some cells hold several points
        points = np.stack([2 + 0.3 * rng.random(n), 0.05 * col, 0.1 * row], 1).astype(np.float32)
        labels = rng.choice([C.DESK, C.CHAIR, C.WALL, C.OTHER], n, p=[0.45, 0.3, 0.15, 0.1]).astype(np.uint8)
        conf = rng.random(n).astype(np.float32)
        if trial % 2:
            points[rng.integers(0, n, 5), 0] = np.nan
        grid = ScanGrid(row.astype(np.int32), col.astype(np.int32), rows, cols, np.zeros(rows), "test")
        for gap, share in ((0.15, 0.6), (0.25, 0.5), (0.4, 0.8)):
            want = _reference(points, grid, labels, conf, gap, share)
            got = O.unify_objects(points, grid, labels, conf, gap, share)
            assert np.array_equal(got[0], want[0])
            assert np.allclose(got[1], want[1], atol=1e-5)
            changed += np.count_nonzero(got[0] != labels)
    assert changed > 100  # the rule had work to do


def test_a_negative_gap_is_refused():
    with pytest.raises(SegmentationError, match="segmentation.object_gap"):
        Segmenter.from_config(replace(SegmentationConfig(), object_gap=-0.1))


def test_points_exactly_gap_apart_do_not_join_and_just_nearer_ones_do():
    """One row: a chair point and three desk points 0.25 m apart (exact in binary, so the distance is exactly the
    gap). 'Less than gap' joins nothing at gap 0.25; at 0.2501 they are one object, 3 desk of 4: all desk."""
    points = np.array([[3.0, 0.25 * k, 0.0] for k in range(4)], np.float32)
    grid = ScanGrid(np.zeros(4, np.int32), np.arange(4, dtype=np.int32), 1, 40, np.zeros(1), "test")
    labels = np.array([C.CHAIR, C.DESK, C.DESK, C.DESK], np.uint8)
    conf = np.full(4, 0.8, np.float32)
    assert np.array_equal(O.unify_objects(points, grid, labels, conf, 0.25)[0], labels)
    assert np.all(O.unify_objects(points, grid, labels, conf, 0.2501)[0] == C.DESK)
