"""Points <-> range images of a scan's grid (grid.py), the network's input, for any LiDAR.

The grid's rows (0 = lowest beam) and azimuth columns are the image's (a non-repetitive pattern's image has
finer columns than its grid: grid.image_columns). A grid of more than MAX_ROWS rows is
split into ``k`` = ceil(rows / MAX_ROWS) interleaved images (image s holds rows s, s + k, s + 2k, ...), so every
sensor shows the network images of at most 32 beams spanning its whole field of view: 16 rows for a VLP-16,
32 for 32 beams, two of 32 for 64 beams, four of 32 for 128. Rows are padded to a multiple of 4 (the
network halves them twice). Each pixel holds one point (when several fall in one pixel, one of them); every
point reads its label back from its own pixel, so no point is left without a label.

Channels (``CHANNELS``): range (m), x, y, z (m, sensor frame), intensity (0..255), valid (0/1).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..grid import ScanGrid, as_grid, azimuth_cells, image_columns

CHANNELS = ("range", "x", "y", "z", "intensity", "valid")
MAX_ROWS = 32  # beams per network image


class ProjectionError(ValueError):
    """Points or per-point arrays that do not fit the scan's grid."""


def image_shape(grid: ScanGrid) -> tuple[int, int, int]:
    """(images, rows, columns) of the interleaved images of a grid."""
    k = -(-grid.height // MAX_ROWS)
    rows = -(-(-(-grid.height // k)) // 4) * 4
    return k, rows, grid.width if grid.azimuth is None else image_columns(len(grid.row), grid.height)


@dataclass
class Projection:
    """Where each point went: ``flat`` (N,) index into the stacked (images, rows, width) pixels."""

    flat: np.ndarray
    images: int
    height: int
    width: int

    def unproject(self, image: np.ndarray) -> np.ndarray:
        """Per-point values read back from (..., images, height, width) images: shape (..., N)."""
        flat = image.reshape(*image.shape[:-3], self.images * self.height * self.width)
        return flat[..., self.flat]


def project(points: np.ndarray, grid=None, intensity: np.ndarray | None = None) -> tuple[np.ndarray, Projection]:
    """Range images (images, len(CHANNELS), rows, width) float32 of (N, 3) sensor-frame points on their grid
    (a grid.ScanGrid, or the cloud's beam ids, or None: see grid.as_grid), and where each point went.
    ``intensity`` (N,) 0..255, else 0. ProjectionError for arrays that do not fit."""
    points = np.asarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ProjectionError(f"points must be (N, 3), got {points.shape}")
    n = len(points)
    if grid is not None and len(getattr(grid, "row", grid)) != n:
        raise ProjectionError(f"grid / ring must have {n} entries, got {len(getattr(grid, 'row', grid))}")
    if intensity is not None and np.shape(intensity) != (n,):
        raise ProjectionError(f"intensity must be ({n},), got {np.shape(intensity)}")
    grid = as_grid(points, grid)
    k, rows, width = image_shape(grid)
    row = grid.row.astype(np.int64)
    col = grid.col if grid.azimuth is None else azimuth_cells(grid.azimuth, width)  # finer: where it fired
    sub, pixel = row % k, (row // k) * width + col
    proj = Projection(sub * (rows * width) + pixel, k, rows, width)
    channel = rows * width
    image = np.zeros(k * len(CHANNELS) * channel, np.float32)
    at = sub * (len(CHANNELS) * channel) + pixel  # flat index of each point's pixel in channel 0 (1-D: faster)
    image[at] = np.sqrt(np.einsum("ij,ij->i", points, points))
    for c in range(3):
        image[at + (1 + c) * channel] = points[:, c]
    if intensity is not None:
        image[at + 4 * channel] = np.asarray(intensity, np.float32)
    image[at + 5 * channel] = 1.0
    return image.reshape(k, len(CHANNELS), rows, width), proj


def project_labels(proj: Projection, labels: np.ndarray, ignore: int = 255) -> np.ndarray:
    """(images, rows, width) uint8 label images of per-point labels; empty pixels get ``ignore``."""
    image = np.full(proj.images * proj.height * proj.width, ignore, np.uint8)
    image[proj.flat] = labels
    return image.reshape(proj.images, proj.height, proj.width)
