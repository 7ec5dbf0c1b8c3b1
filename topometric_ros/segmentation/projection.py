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

import numba
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


def checked(points: np.ndarray, grid=None, intensity: np.ndarray | None = None) -> tuple[np.ndarray, ScanGrid]:
    """(float32 (N, 3) points, their grid.ScanGrid) of a scan as :func:`project` takes it; ProjectionError for
    arrays that do not fit."""
    points = np.asarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ProjectionError(f"points must be (N, 3), got {points.shape}")
    n = len(points)
    if grid is not None and len(getattr(grid, "row", grid)) != n:
        raise ProjectionError(f"grid / ring must have {n} entries, got {len(getattr(grid, 'row', grid))}")
    if intensity is not None and np.shape(intensity) != (n,):
        raise ProjectionError(f"intensity must be ({n},), got {np.shape(intensity)}")
    return points, as_grid(points, grid)


def project(points: np.ndarray, grid=None, intensity: np.ndarray | None = None) -> tuple[np.ndarray, Projection]:
    """Range images (images, len(CHANNELS), rows, width) float32 of (N, 3) sensor-frame points on their grid
    (a grid.ScanGrid, or the cloud's beam ids, or None: see grid.as_grid), and where each point went.
    ``intensity`` (N,) 0..255, else 0. ProjectionError for arrays that do not fit."""
    points, grid = checked(points, grid, intensity)
    k, rows, width = image_shape(grid)
    col = grid.col if grid.azimuth is None else azimuth_cells(grid.azimuth, width)  # finer: where it fired
    image = np.zeros(k * len(CHANNELS) * rows * width, np.float32)
    flat = np.empty(len(points), np.int64)
    no_intensity = np.zeros(0, np.float32)
    _fill(points, no_intensity if intensity is None else np.asarray(intensity, np.float32), grid.row, col, k, rows,
          width, image, flat)
    return image.reshape(k, len(CHANNELS), rows, width), Projection(flat, k, rows, width)


@numba.njit(cache=True, nogil=True)
def _fill(points, intensity, row, col, k, rows, width, image, flat):
    """Write each point's CHANNELS into its pixel of the zeroed (k, channels, rows, width) ``image`` (flat; the
    last point of a pixel wins) and its pixel's index in the stacked (k, rows, width) images into ``flat``.
    Grid row r is row r // k of image r % k; intensity of length 0: none (0)."""
    channel = rows * width
    for i in range(len(points)):
        sub, pixel = row[i] % k, (row[i] // k) * width + col[i]
        flat[i] = sub * channel + pixel
        at = sub * (6 * channel) + pixel
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        image[at] = np.sqrt(x * x + y * y + z * z)
        image[at + channel] = x
        image[at + 2 * channel] = y
        image[at + 3 * channel] = z
        if len(intensity):
            image[at + 4 * channel] = intensity[i]
        image[at + 5 * channel] = 1.0


def project_labels(proj: Projection, labels: np.ndarray, ignore: int = 255) -> np.ndarray:
    """(images, rows, width) uint8 label images of per-point labels; empty pixels get ``ignore``."""
    image = np.full(proj.images * proj.height * proj.width, ignore, np.uint8)
    image[proj.flat] = labels
    return image.reshape(proj.images, proj.height, proj.width)


def beam_stride(grid: ScanGrid, max_beams: int) -> int:
    """Every how many-th row of ``grid`` the network sees so that it sees at most ``max_beams`` rows
    (config segmentation.max_beams; 0 = every row): ceil(rows / max_beams), at least 1."""
    return 1 if max_beams <= 0 or grid.height <= max_beams else -(-grid.height // max_beams)


def strided(grid: ScanGrid, stride: int) -> tuple[np.ndarray, ScanGrid]:
    """(indices of the points on rows 0, stride, 2·stride, ..., the grid of those rows alone: row r -> r / stride)."""
    keep = np.flatnonzero(grid.row % stride == 0)
    sub = ScanGrid((grid.row[keep] // stride).astype(np.int32), grid.col[keep], -(-grid.height // stride), grid.width,
                   grid.elevation_deg[::stride], grid.source, None if grid.azimuth is None else grid.azimuth[keep])
    return keep, sub


def nearest_strided(points: np.ndarray, grid: ScanGrid, keep: np.ndarray, stride: int) -> np.ndarray:
    """For every point, the index into ``keep`` (the points of the strided rows) of the point whose values it
    takes: itself for the points of ``keep``; for a point of a row in between, of the points of the strided rows
    just below and just above it in its own column (else in the next columns), the one nearest to it in range
    (so a point on a wall does not take the label of a chair edge in front of it); −1 when those cells are
    all empty. points: (N, 3) sensor frame, m."""
    h, w = grid.height, grid.width
    at = np.full(h * w, -1, np.int64)
    at[grid.row[keep].astype(np.int64) * w + grid.col[keep]] = np.arange(len(keep))
    out = np.full(len(points), -1, np.int64)
    out[keep] = np.arange(len(keep))
    skip = np.flatnonzero(grid.row % stride != 0)
    if len(skip) == 0 or len(keep) == 0:
        return out
    rng = np.sqrt(np.einsum("ij,ij->i", points, points))
    kept_rng = rng.take(keep)
    row, col = grid.row.take(skip).astype(np.int64), grid.col.take(skip).astype(np.int64)
    below = row - row % stride
    above = np.minimum(below + stride, h - 1)  # the top rows have no strided row above: below twice
    for dc in (0, -1, 1):
        left = np.flatnonzero(out.take(skip) < 0)
        if len(left) == 0:
            break
        c = (col.take(left) + dc) % w
        lo, hi = at.take(below.take(left) * w + c), at.take(above.take(left) * w + c)
        target = rng.take(skip.take(left))
        d_lo = np.where(lo >= 0, np.abs(kept_rng.take(np.maximum(lo, 0)) - target), np.inf)
        d_hi = np.where(hi >= 0, np.abs(kept_rng.take(np.maximum(hi, 0)) - target), np.inf)
        out[skip.take(left)] = np.where(d_hi < d_lo, hi, lo)
    return out
