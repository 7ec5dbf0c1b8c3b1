"""Range-image projection and segmentation metrics (no network)."""
from __future__ import annotations

import numpy as np
import pytest

from topometric_ros import classes as C
from topometric_ros.segmentation.metrics import confusion, iou_per_class, miou
from topometric_ros.grid import ScanGrid, scan_grid
from topometric_ros.segmentation.projection import (CHANNELS, ProjectionError, beam_stride, image_shape,
                                                    nearest_strided, project, project_labels, strided)
from topometric_ros.sensors import sensor
from topometric_ros.sim.frames import simulated_frames


@pytest.fixture(scope="module")
def scan():
    frames, _ = simulated_frames("office1", 1, seed=3)
    return frames[0]


def test_simulated_scan_fills_one_pixel_per_point_and_reads_back(scan):
    image, proj = project(scan.points, scan.ring, scan.intensity)
    assert image.shape == (1, len(CHANNELS), 32, 1800)  # a VLP-32C: one image of its 32 beams
    assert int(image[:, CHANNELS.index("valid")].sum()) == len(scan.points)  # no two points share a pixel
    np.testing.assert_array_equal(proj.unproject(np.moveaxis(image[:, 1:4], 1, 0)).T, scan.points)
    np.testing.assert_array_equal(proj.unproject(image[:, 4]), scan.intensity)
    np.testing.assert_allclose(proj.unproject(image[:, 0]), np.linalg.norm(scan.points, axis=1), rtol=1e-6)
    np.testing.assert_array_equal(proj.unproject(project_labels(proj, scan.labels)), scan.labels)


def test_rows_from_elevation_match_the_ring_field(scan):
    _, with_ring = project(scan.points, scan.ring)
    _, without = project(scan.points)  # rows from the scan's own elevation clusters
    np.testing.assert_array_equal(with_ring.flat, without.flat)


# 33 beams: image 0 holds beams 0, 2, ..., 32 (17 rows), padded to 20
@pytest.mark.parametrize("beams, images, rows", [(16, 1, 16), (32, 1, 32), (40, 2, 20), (64, 2, 32), (128, 4, 32),
                                                 (33, 2, 20)])
def test_many_beams_are_split_into_interleaved_images_of_at_most_32_rows(beams, images, rows):
    """Beam b of B goes to image b % k, row b // k: every image spans the whole field of view."""
    el = np.radians(np.linspace(-20, 20, beams))
    az = np.radians(np.arange(0, 360, 0.5))
    e, a = np.meshgrid(el, az, indexing="ij")
    pts = (10 * np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1)).reshape(-1, 3)
    beam = np.repeat(np.arange(beams), len(az))
    grid = scan_grid(pts.astype(np.float32), beam)
    assert image_shape(grid) == (images, rows, 720)
    image, proj = project(pts, grid)
    assert image.shape == (images, len(CHANNELS), rows, 720)
    valid = image[:, CHANNELS.index("valid")]
    assert int(valid.sum()) == len(pts)
    top = np.flatnonzero(beam == beams - 1)[0]
    k = images
    assert proj.flat[top] // (rows * 720) == (beams - 1) % k  # the image of the top beam
    np.testing.assert_allclose(proj.unproject(image[:, 3]), pts[:, 2], atol=1e-5)


@pytest.mark.parametrize("named", [True, False])
def test_a_non_repetitive_scan_gets_an_image_of_about_one_pixel_per_point(named):
    """The Mid-360's grid keeps square 1.8° cells (several points each, for the plane tiles); its network image
    has about one pixel per point: 640 columns for its ~19,700 points over 32 rows (rounded up to 64), 192 for
    a quarter of them (a voxel filter). Every point reads back its own pixel: its row, and the column of the
    azimuth it was fired at."""
    model = sensor("Mid-360")
    frames, _ = simulated_frames("office1", 1, seed=3, sensor="Mid-360")
    pts = frames[0].points
    grid = scan_grid(pts, model=model if named else None)
    assert grid.source.startswith("elevation bins") and (grid.height, grid.width) == (32, 200)
    assert 19_200 < len(pts) <= 20_480 and image_shape(grid) == (1, 32, 640)
    image, proj = project(pts, grid)
    assert image.shape == (1, len(CHANNELS), 32, 640)
    coarse = len(np.unique(grid.row.astype(np.int64) * grid.width + grid.col))
    fine = int(image[:, CHANNELS.index("valid")].sum())
    assert coarse < 0.4 * len(pts) and fine > 0.6 * len(pts)  # filled pixels: the grid's cells vs the image
    row, col = np.divmod(np.asarray(proj.flat), 640)
    np.testing.assert_array_equal(row, grid.row)
    az = np.degrees(np.arctan2(pts[:, 1], pts[:, 0]))
    off = (az - col * 360.0 / 640 + 180.0) % 360.0 - 180.0
    assert np.abs(off).max() <= 0.5 * 360.0 / 640 + 1e-3  # the column of its own azimuth
    quarter = grid.subset(np.arange(0, len(pts), 4))
    assert image_shape(quarter) == (1, 32, -(-len(quarter.row) // (32 * 64)) * 64) == (1, 32, 192)
    assert project(pts[::4], quarter)[0].shape == (1, len(CHANNELS), 32, 192)


def test_a_spinning_scan_keeps_no_azimuths_and_its_image_is_its_grid(scan):
    grid = scan_grid(scan.points, scan.ring)
    assert grid.azimuth is None and image_shape(grid) == (1, 32, grid.width)


def test_azimuth_wraps_around():
    az = np.radians([0.05, 359.95, -0.05, 180.05, 90.04, 0.25, -0.25])
    pts = np.stack([np.cos(az), np.sin(az), np.zeros_like(az)], 1).astype(np.float32) * 5
    grid = scan_grid(pts, np.zeros(len(pts), np.int64), columns=1800)
    assert grid.col.tolist() == [0, 0, 0, 900, 450, 1, 1799]


def test_empty_pixels_are_zero_and_ignored_in_labels(scan):
    grid = scan_grid(scan.points, scan.ring)
    image, proj = project(scan.points[:10], grid.subset(np.arange(10)))
    assert image[:, :, image[0, -1] == 0].max() == 0
    labels = project_labels(proj, np.full(10, C.WALL, np.uint8))
    assert (labels == C.WALL).sum() == 10 and (labels == 255).sum() == 32 * 1800 - 10


def test_bad_input_raises_projection_error(scan):
    with pytest.raises(ProjectionError, match="grid / ring must have"):
        project(scan.points[:3], np.array([0, 1], np.uint16))
    with pytest.raises(ProjectionError, match="intensity must be"):
        project(scan.points[:3], None, np.ones(4, np.float32))
    with pytest.raises(ProjectionError, match=r"\(N, 3\)"):
        project(np.zeros((3, 2), np.float32))


def test_rows_between_the_strided_ones_take_their_nearest_in_range_neighbour():
    """max_beams 2 on a 4-row grid: rows 0 and 2 are segmented; a point of row 1 takes the point below or above
    it nearer in range, in its own column first, else the next column; the top row (no strided row above) takes
    the one below; a point with only empty cells around it gets −1."""
    # (row, col, range m) per point; each point on the x axis turned by its column's azimuth (8 columns)
    cells = [(0, 0, 5.0), (2, 0, 9.0), (1, 0, 8.5),       # row 1, col 0: above (9.0) is nearer than below (5.0)
             (0, 3, 4.0), (2, 3, 7.0), (1, 3, 4.2),       # row 1, col 3: below
             (0, 5, 6.0), (1, 6, 6.1),                    # row 1, col 6: own column empty -> col 5 below
             (3, 3, 7.1),                                 # top row: only row 2 below it
             (1, 1, 3.0)]                                 # no point in columns 0-2 of rows 0 / 2 but col 0
    row, col, rng = (np.array(v) for v in zip(*cells))
    az = col * (2 * np.pi / 8)
    points = np.stack([rng * np.cos(az), rng * np.sin(az), np.zeros(len(rng))], 1).astype(np.float32)
    grid = ScanGrid(row.astype(np.int32), col.astype(np.int32), 4, 8, np.array([-3.0, -1.0, 1.0, 3.0]), "test")
    assert beam_stride(grid, 0) == 1 and beam_stride(grid, 4) == 1 and beam_stride(grid, 2) == 2
    assert beam_stride(grid, 3) == 2 and beam_stride(grid, 1) == 4
    keep, sub = strided(grid, 2)
    np.testing.assert_array_equal(keep, [0, 1, 3, 4, 6])
    assert sub.height == 2 and list(sub.row) == [0, 1, 0, 1, 0] and list(sub.elevation_deg) == [-3.0, 1.0]
    source = nearest_strided(points, grid, keep, 2)
    # index into keep: 0 = (0,0), 1 = (2,0), 2 = (0,3), 3 = (2,3), 4 = (0,5)
    np.testing.assert_array_equal(source, [0, 1, 1, 2, 3, 2, 4, 4, 3, 0])
    lonely = ScanGrid(np.array([0, 1], np.int32), np.array([0, 4], np.int32), 2, 8, np.zeros(2), "test")
    np.testing.assert_array_equal(nearest_strided(points[:2], lonely, np.array([0]), 2), [0, -1])


def test_iou_and_miou_analytic():
    truth = np.array([1, 1, 1, 2, 2, 3, 255])
    pred = np.array([1, 1, 2, 2, 2, 3, 1])
    conf = confusion(truth, pred)
    assert conf.sum() == 6  # the ignore label is dropped
    iou = iou_per_class(conf)
    assert iou[C.FLOOR] == pytest.approx(2 / 3) and iou[C.WALL] == pytest.approx(2 / 3) and iou[C.PILLAR] == 1.0
    assert np.isnan(iou[C.DESK])  # absent from truth and prediction: not counted
    assert miou(conf) == pytest.approx((2 / 3 + 2 / 3 + 1) / 3)


def test_a_row_just_below_a_strided_top_row_can_take_the_top_row():
    """max_beams on a 5-row grid, stride 2: rows 0, 2 and 4 (the top row) are segmented; a point of row 3 takes
    whichever of rows 2 and 4 is nearer it in range (row 4 here), and a point of row 1 likewise (row 0 here)."""
    row = np.array([0, 2, 4, 3, 1])
    rng = np.array([5.0, 9.0, 7.0, 7.2, 5.3])
    points = np.stack([rng, np.zeros(5), np.zeros(5)], 1).astype(np.float32)
    grid = ScanGrid(row.astype(np.int32), np.zeros(5, np.int32), 5, 8, np.linspace(-4.0, 4.0, 5), "test")
    keep, sub = strided(grid, 2)
    np.testing.assert_array_equal(keep, [0, 1, 2])
    assert sub.height == 3 and list(sub.row) == [0, 1, 2] and list(sub.elevation_deg) == [-4.0, 0.0, 4.0]
    np.testing.assert_array_equal(nearest_strided(points, grid, keep, 2), [0, 1, 2, 2, 0])
