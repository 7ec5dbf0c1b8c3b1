"""Points <-> range image of a spinning LiDAR (rings × azimuth columns), the network's input.

Rows are rings (row 0 = lowest beam, the velodyne_driver convention), taken from the ``ring`` field when
the cloud has one, else from each point's elevation matched to the nearest beam of the VLP-32C table.
Columns are azimuth bins of 2π / width, column 0 at azimuth 0 (the sensor's +x axis), counter-clockwise,
wrapping around. Each pixel holds one point (when several fall in one pixel, one of them); every point
reads its label back from its own pixel, so no point is left without a label.

Channels (``CHANNELS``): range (m), x, y, z (m, sensor frame), intensity (0..255), valid (0/1).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..sim.lidar import RING_ELEVATION_DEG

CHANNELS = ("range", "x", "y", "z", "intensity", "valid")
HEIGHT, WIDTH = len(RING_ELEVATION_DEG), 1800  # VLP-32C: 32 rings, 0.2° azimuth steps


class ProjectionError(ValueError):
    """Points or ring ids that do not fit the range image."""


@dataclass
class Projection:
    """Where each point of a scan went: ``row``/``col`` (N,) pixel of every point; image size."""

    row: np.ndarray
    col: np.ndarray
    height: int = HEIGHT
    width: int = WIDTH

    def __post_init__(self):
        self.flat = self.row.astype(np.int64) * self.width + self.col  # (N,) flat pixel index of every point

    def unproject(self, image: np.ndarray) -> np.ndarray:
        """Per-point values read back from an (..., height, width) image: shape (..., N)."""
        flat = image.reshape(*image.shape[:-2], self.height * self.width)
        return flat[..., self.flat]


def rows_from_elevation(points: np.ndarray, elevation_deg: np.ndarray = RING_ELEVATION_DEG) -> np.ndarray:
    """(N,) ring id of each sensor-frame point: the beam whose elevation (sorted ascending, deg) is nearest."""
    el = np.degrees(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1])))
    edges = (elevation_deg[1:] + elevation_deg[:-1]) / 2  # midpoints between neighbouring beams
    return np.searchsorted(edges, el).astype(np.int32)


def project(points: np.ndarray, ring: np.ndarray | None = None, intensity: np.ndarray | None = None,
            height: int = HEIGHT, width: int = WIDTH) -> tuple[np.ndarray, Projection]:
    """Range image (len(CHANNELS), height, width) float32 of sensor-frame points (N, 3) and where each went.

    ``ring`` (N,) beam ids 0..height-1 (else from elevation); ``intensity`` (N,) 0..255 (else 0).
    Raises ProjectionError for a ring id outside the image or arrays of mismatched length.
    """
    points = np.asarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ProjectionError(f"points must be (N, 3), got {points.shape}")
    n = len(points)
    if ring is None:
        if height != HEIGHT:
            raise ProjectionError(f"without a ring field the image has the VLP-32C's {HEIGHT} rows, not {height}")
        row = rows_from_elevation(points)
    else:
        ring = np.asarray(ring)
        if ring.shape != (n,):
            raise ProjectionError(f"ring must be ({n},), got {ring.shape}")
        if n and int(ring.max()) >= height:
            raise ProjectionError(f"ring id {int(ring.max())} does not fit a {height}-ring image")
        row = ring.astype(np.int32)
    az = np.arctan2(points[:, 1], points[:, 0])
    col = np.rint(az * np.float32(width / (2 * np.pi))).astype(np.int64)
    col[col < 0] += width
    col[col >= width] -= width
    proj = Projection(row=row, col=col, height=height, width=width)
    flat = proj.flat
    image = np.zeros((len(CHANNELS), height * width), np.float32)
    image[0][flat] = np.sqrt(np.einsum("ij,ij->i", points, points))
    for c in range(3):
        image[1 + c][flat] = points[:, c]
    if intensity is not None:
        intensity = np.asarray(intensity, dtype=np.float32)
        if intensity.shape != (n,):
            raise ProjectionError(f"intensity must be ({n},), got {intensity.shape}")
        image[4][flat] = intensity
    image[5][flat] = 1.0
    return image.reshape(len(CHANNELS), height, width), proj


def project_labels(proj: Projection, labels: np.ndarray, ignore: int = 255) -> np.ndarray:
    """(height, width) uint8 label image of per-point labels; empty pixels get ``ignore``."""
    image = np.full(proj.height * proj.width, ignore, np.uint8)
    image[proj.flat] = labels
    return image.reshape(proj.height, proj.width)

