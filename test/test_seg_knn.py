"""The k-nearest-neighbour vote after the network (segmentation/knn.py, config segmentation.knn)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from topometric_ros import classes as C
from topometric_ros.config import SegmentationConfig
from topometric_ros.grid import ScanGrid
from topometric_ros.segmentation.checkpoint import SegmentationError
from topometric_ros.segmentation.infer import Segmenter
from topometric_ros.segmentation.knn import knn_vote


def _wall(rows: int = 5, cols: int = 40, x: float = 5.0, step: float = 0.05):
    """A flat wall x = ``x`` m seen as a rows × cols grid, one point per cell 5 cm apart (y along columns,
    z up the rows), every point WALL at confidence 0.9."""
    r, c = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    r, c = r.ravel(), c.ravel()
    points = np.stack([np.full(r.size, x), (c - cols / 2) * step, (r - rows / 2) * step], 1).astype(np.float32)
    grid = ScanGrid(r.astype(np.int32), c.astype(np.int32), rows, cols, np.zeros(rows), "test")
    return points, grid, np.full(r.size, C.WALL, np.uint8), np.full(r.size, 0.9, np.float32)


def test_a_point_labelled_unlike_the_surface_around_it_takes_the_surface_label_and_its_voters_confidence():
    points, grid, labels, conf = _wall(rows=1)
    lone = 20
    labels[lone], conf[lone] = C.CHAIR, 0.6
    conf[lone - 1], conf[lone + 1] = 0.7, 0.8  # its two nearest neighbours (5 cm; the next are 10 cm away)
    out, out_conf = knn_vote(points, grid, labels, conf, k=3, distance=0.5)
    assert out[lone] == C.WALL
    assert out_conf[lone] == pytest.approx(0.75)  # the mean of the two that voted wall
    assert np.array_equal(np.delete(out, lone), np.delete(labels, lone))
    assert np.array_equal(np.delete(out_conf, lone), np.delete(conf, lone))


def test_two_points_of_an_object_outvote_one_neighbour_and_a_tie_keeps_the_own_label():
    points, grid, labels, conf = _wall(rows=1)
    a = 20
    labels[[a, a + 1]] = C.CHAIR  # a pair: each sees itself and the other (chair) and one wall point
    out, _ = knn_vote(points, grid, labels, conf, k=3, distance=0.5)
    assert out[a] == out[a + 1] == C.CHAIR
    labels[:] = C.WALL
    labels[a], labels[a - 1], labels[a + 1] = C.CHAIR, C.DESK, C.PILLAR  # one vote each: the own label wins
    out, _ = knn_vote(points, grid, labels, conf, k=3, distance=0.5)
    assert out[a] == C.CHAIR


def test_neighbours_in_the_image_but_far_in_space_do_not_vote():
    points, grid, labels, conf = _wall()
    lone = 2 * 40 + 20
    points[lone, 0] = 3.0  # 2 m in front of the wall in its own cell: an edge seen past
    labels[lone] = C.CHAIR
    out, _ = knn_vote(points, grid, labels, conf, k=3, distance=0.5)
    assert out[lone] == C.CHAIR
    out, _ = knn_vote(points, grid, labels, conf, k=3, distance=2.5)  # let the wall vote: it wins
    assert out[lone] == C.WALL


def test_the_window_wraps_around_in_azimuth():
    # one ring of 360 columns at 5 m (8.7 cm apart); columns 1 and 2 empty, so only 358 and 359 are near column 0
    cols = np.array([0] + list(range(3, 360)))
    az = np.radians(cols)
    points = np.stack([5 * np.cos(az), 5 * np.sin(az), np.zeros(len(cols))], 1).astype(np.float32)
    grid = ScanGrid(np.zeros(len(cols), np.int32), cols.astype(np.int32), 1, 360, np.zeros(1), "test")
    labels = np.full(len(cols), C.WALL, np.uint8)
    labels[0] = C.CHAIR
    out, _ = knn_vote(points, grid, labels, np.ones(len(cols), np.float32), k=3, distance=0.5)
    assert out[0] == C.WALL


def test_k_zero_returns_the_input_and_a_uniform_scan_is_unchanged():
    points, grid, labels, conf = _wall()
    labels[7] = C.DESK
    out, out_conf = knn_vote(points, grid, labels, conf, k=0, distance=0.5)
    assert out is labels and out_conf is conf
    labels[7] = C.WALL
    out, out_conf = knn_vote(points, grid, labels, conf, k=5, distance=0.5)
    assert np.array_equal(out, labels) and np.array_equal(out_conf, conf)


def test_a_negative_or_fractional_k_is_refused():
    with pytest.raises(SegmentationError, match="segmentation.knn"):
        Segmenter.from_config(replace(SegmentationConfig(), knn=-1))


def _reference_vote(points, grid, labels, conf, k, distance, window):
    """The rule of knn_vote written plainly: the last point of each cell, the window's points within
    ``distance`` sorted by distance (stable), the k nearest vote, the own label wins ties."""
    occupant = {}
    for i, cell in enumerate(zip(grid.row, grid.col)):
        occupant[cell] = i
    out, out_conf = labels.copy(), conf.copy()
    rows, cols = window
    for i in range(len(points)):
        near = []
        for dr in range(-(rows // 2), rows - rows // 2):
            for dc in range(-(cols // 2), cols - cols // 2):
                j = occupant.get((grid.row[i] + dr, (grid.col[i] + dc) % grid.width))
                if j is not None and 0 <= grid.row[i] + dr < grid.height:
                    d = float(np.sum((points[j].astype(np.float64) - points[i]) ** 2))
                    if d < distance ** 2:
                        near.append((d, j))
        voters = [j for _, j in sorted(near, key=lambda t: t[0])[:k]]
        votes = np.zeros(C.NUM_CLASSES)
        votes[labels[i]] = 0.5
        for j in voters:
            votes[labels[j]] += 1
        win = int(np.argmax(votes))
        if win != labels[i]:
            out[i] = win
            out_conf[i] = np.mean([conf[j] for j in voters if labels[j] == win])
    return out, out_conf


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_vote_matches_its_rule_written_plainly_on_random_scans(seed):
    """Random points on a small grid (some cells empty, some shared), random labels of a few classes: the
    compiled vote (with its shortcut for windows of one class) gives the plain rule's labels and confidence."""
    rng = np.random.default_rng(seed)
    height, width, n = 6, 24, 150
    row, col = rng.integers(0, height, n).astype(np.int32), rng.integers(0, width, n).astype(np.int32)
    az = 2 * np.pi * col / width
    rng_m = 2.0 + rng.random(n)
    points = np.stack([rng_m * np.cos(az), rng_m * np.sin(az), 0.1 * row + 0.05 * rng.random(n)], 1).astype(np.float32)
    labels = rng.choice([C.FLOOR, C.WALL, C.CHAIR], n, p=[0.6, 0.3, 0.1]).astype(np.uint8)
    conf = rng.random(n).astype(np.float32)
    grid = ScanGrid(row, col, height, width, np.zeros(height), "test")
    for k, window, distance in ((3, (3, 5), 0.8), (5, (3, 5), 2.0), (1, (5, 3), 0.5)):
        want = _reference_vote(points, grid, labels, conf, k, distance, window)
        got = knn_vote(points, grid, labels, conf, k, distance, window)
        assert np.array_equal(got[0], want[0])
        assert np.allclose(got[1], want[1], atol=1e-6)
    assert (knn_vote(points, grid, labels, conf, 5, 2.0)[0] != labels).any()  # the vote had work to do


@pytest.mark.parametrize("side", [-2, 2])
def test_a_point_whose_only_other_class_neighbours_are_in_the_window_edge_column_is_still_voted_on(side):
    """A chair point at (row 1, col 20) of a 3 x 40 grid with the cells of columns 18-22 empty but for three wall
    points in column 20 + ``side`` (the 3 x 5 window's outer column), 5-7 cm away: the two nearest walls outvote
    it (2 against its own 1.5). The shortcut that skips windows of one class must see that column too."""
    points = np.array([[5.0, 0.0, 0.0], [5.0, 0.05 * side / 2, -0.04], [5.0, 0.05 * side / 2, 0.0],
                       [5.0, 0.05 * side / 2, 0.04]], np.float32)
    row = np.array([1, 0, 1, 2], np.int32)
    col = np.array([20, 20 + side, 20 + side, 20 + side], np.int32)
    grid = ScanGrid(row, col, 3, 40, np.zeros(3), "test")
    labels = np.array([C.CHAIR, C.WALL, C.WALL, C.WALL], np.uint8)
    conf = np.array([0.6, 0.7, 0.8, 0.9], np.float32)
    out, out_conf = knn_vote(points, grid, labels, conf, k=3, distance=0.5)
    assert out[0] == C.WALL
    assert np.array_equal(out[1:], labels[1:])


def test_equidistant_neighbours_vote_in_window_order():
    """Ties in distance go to the neighbour met first in the window (rows upward, then columns; the plain rule's
    stable sort): a chair point with three neighbours exactly 0.25 m away in the row below it (wall, wall, chair,
    met in that order) and k = 3 keeps itself and the two walls, which outvote it (2 against 1.5)."""
    points = np.array([[5.0, 0.0, 0.0], [5.0, 0.0, -0.25], [5.0, 0.25, 0.0], [5.0, -0.25, 0.0]], np.float32)
    row = np.array([1, 0, 0, 0], np.int32)
    col = np.array([20, 19, 20, 21], np.int32)
    grid = ScanGrid(row, col, 2, 40, np.zeros(2), "test")
    labels = np.array([C.CHAIR, C.WALL, C.WALL, C.CHAIR], np.uint8)
    conf = np.array([0.6, 0.7, 0.8, 0.9], np.float32)
    want = _reference_vote(points, grid, labels, conf, 3, 0.5, (3, 5))
    out, out_conf = knn_vote(points, grid, labels, conf, k=3, distance=0.5)
    assert out[0] == want[0][0] == C.WALL and out_conf[0] == pytest.approx(0.75)
