"""Range-image projection and segmentation metrics (no network)."""
from __future__ import annotations

import numpy as np
import pytest

from topometric_ros import classes as C
from topometric_ros.segmentation.metrics import confusion, iou_per_class, miou
from topometric_ros.segmentation.projection import (CHANNELS, HEIGHT, WIDTH, ProjectionError, project,
                                                     project_labels, rows_from_elevation)
from topometric_ros.sim.frames import simulated_frames


@pytest.fixture(scope="module")
def scan():
    frames, _ = simulated_frames("office1", 1, seed=3)
    return frames[0]


def test_simulated_scan_fills_one_pixel_per_point_and_reads_back(scan):
    image, proj = project(scan.points, scan.ring, scan.intensity)
    assert image.shape == (len(CHANNELS), HEIGHT, WIDTH)
    assert int(image[CHANNELS.index("valid")].sum()) == len(scan.points)  # no two points share a pixel
    np.testing.assert_array_equal(proj.unproject(image[1:4]).T, scan.points)
    np.testing.assert_array_equal(proj.unproject(image[4]), scan.intensity)
    np.testing.assert_allclose(proj.unproject(image[0]), np.linalg.norm(scan.points, axis=1), rtol=1e-6)
    np.testing.assert_array_equal(proj.unproject(project_labels(proj, scan.labels)), scan.labels)


def test_rows_from_elevation_match_the_ring_field(scan):
    np.testing.assert_array_equal(rows_from_elevation(scan.points), scan.ring)
    _, with_ring = project(scan.points, scan.ring)
    _, without = project(scan.points)
    np.testing.assert_array_equal(with_ring.flat, without.flat)


def test_azimuth_wraps_around():
    az = np.radians([0.0, 359.95, -0.05, 180.0, 90.0, 0.2, -0.2])
    pts = np.stack([np.cos(az), np.sin(az), np.zeros_like(az)], 1).astype(np.float32) * 5
    _, proj = project(pts, np.zeros(len(pts), np.uint16))
    assert proj.col.tolist() == [0, 0, 0, 900, 450, 1, WIDTH - 1]


def test_empty_pixels_are_zero_and_ignored_in_labels(scan):
    image, proj = project(scan.points[:10], scan.ring[:10])
    assert image[:, image[-1] == 0].max() == 0
    labels = project_labels(proj, np.full(10, C.WALL, np.uint8))
    assert (labels == C.WALL).sum() == 10 and (labels == 255).sum() == HEIGHT * WIDTH - 10


def test_bad_input_raises_projection_error(scan):
    with pytest.raises(ProjectionError, match="ring id 40"):
        project(scan.points[:3], np.array([0, 1, 40], np.uint16))
    with pytest.raises(ProjectionError, match="ring must be"):
        project(scan.points[:3], np.array([0, 1], np.uint16))
    with pytest.raises(ProjectionError, match="intensity must be"):
        project(scan.points[:3], None, np.ones(4, np.float32))
    with pytest.raises(ProjectionError, match=r"\(N, 3\)"):
        project(np.zeros((3, 2), np.float32))


def test_iou_and_miou_analytic():
    truth = np.array([1, 1, 1, 2, 2, 3, 255])
    pred = np.array([1, 1, 2, 2, 2, 3, 1])
    conf = confusion(truth, pred)
    assert conf.sum() == 6  # the ignore label is dropped
    iou = iou_per_class(conf)
    assert iou[C.FLOOR] == pytest.approx(2 / 3) and iou[C.WALL] == pytest.approx(2 / 3) and iou[C.PILLAR] == 1.0
    assert np.isnan(iou[C.DESK])  # absent from truth and prediction: not counted
    assert miou(conf) == pytest.approx((2 / 3 + 2 / 3 + 1) / 3)
