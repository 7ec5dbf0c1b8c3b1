"""The scan grid of any LiDAR: each point's row (beam) and column (azimuth cell) of the sensor's range image.

The grid is what segmentation projects onto and what the ring plane detector tiles; it is built once per
scan from the SENSOR-frame points (before deskewing, so a point's cell is where the sensor fired it).

Rows, 0 = the lowest beam, from the first of:
1. the cloud's beam ids (``beam``: the ring field, else the row of an organised cloud), ordered by the
   elevation their points show (Velodyne counts rings upward, Ouster downward: both come out bottom-up);
2. a named sensor's beam table (sensors.py): each point to the beam of nearest elevation;
3. the scan's own elevation clusters (no sensor named, no ring field): beams are the gaps in the sorted
   elevations of the scan's far points;
4. a non-repetitive pattern (a sensor named so, else a cloud in a driver layout only such sensors use, e.g.
   livox_ros_driver2's, else a scan whose elevations form no beams): uniform
   elevation bins, no beams needed, and as many azimuth cells as make them square (a sparse pattern then
   puts a few points in each cell, which the tiles of the plane detector need). The network's image of such a
   grid has finer columns (image_columns: about one pixel per point, as a spinning sensor's image has), placed
   by each point's azimuth as fired (``azimuth``, kept for these grids only).
Columns: ``width`` azimuth cells of 2π / width, column 0 centred on the sensor's +x axis, counter-clockwise; width
is the sensor's firings per revolution (the organised cloud's width, else a named sensor's, else estimated
from the azimuth steps within rows), rounded up to a multiple of GRID_ALIGN so network and tiles fit, and at least MIN_COLUMNS.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from .sensors import layout_pattern

GRID_ALIGN = 8  # width multiple (the network folds 4 columns and halves them once)
MIN_COLUMNS = 64  # no LiDAR fires fewer times per revolution; the network's circular padding needs this many
MAX_BEAMS = 256  # beam ids at or above this are bad (no LiDAR has more beams)
MAX_COLUMNS = 4096  # firings per revolution an unnamed sensor's grid may have (2x the finest model; garbage beyond)
MIN_AZIMUTH_STEP = np.pi / MAX_COLUMNS  # rad, azimuth steps within a row finer than this are one firing's returns
NON_REPETITIVE_ROWS = 32  # elevation bins of a non-repetitive scan
IMAGE_COLUMN_STEP = 64  # a non-repetitive grid's image width is a multiple of this (few image shapes per sensor)
BEAM_GAP_DEG = 0.06  # deg, an empty elevation gap this wide between far points separates two beams
CLUSTER_MIN_RANGE = 2.0  # m, points nearer than this do not place beams (beam-origin offsets blur them)
MIN_BEAMS = 8  # fewer elevation clusters than this: no beam structure (non-repetitive)
MAX_BEAM_WIDTH_DEG = 1.0  # deg, a wider cluster is not one beam (non-repetitive)
SAMPLE = 5  # every 5th point is enough for a row's median elevation


@dataclass
class ScanGrid:
    """Cells of a scan's points: row (N,) int32 (0 = lowest), col (N,) int32, the grid size, each row's
    median elevation (deg, NaN when empty), how the rows were found (``source``) and, for a non-repetitive
    grid only, each point's azimuth as fired (``azimuth`` (N,) rad; the network image's columns, see
    image_columns), else None."""

    row: np.ndarray
    col: np.ndarray
    height: int
    width: int
    elevation_deg: np.ndarray
    source: str
    azimuth: np.ndarray | None = None

    def subset(self, keep: np.ndarray) -> "ScanGrid":
        """The grid of a subset of the points (index or mask array)."""
        return ScanGrid(self.row[keep], self.col[keep], self.height, self.width, self.elevation_deg, self.source,
                        None if self.azimuth is None else self.azimuth[keep])


def elevation_deg(points: np.ndarray) -> np.ndarray:
    """(N,) elevation of sensor-frame points above the x-y plane, degrees."""
    x, y, z = np.asarray(points).T.astype(np.float64)  # contiguous coordinate rows
    return np.degrees(np.arctan2(z, np.hypot(x, y)))


def azimuth_cells(azimuth: np.ndarray, width: int) -> np.ndarray:
    """(N,) cell of each azimuth (rad, atan2(y, x)): round(azimuth / 2π · width) mod width (cell c centred on
    azimuth c · 2π / width; column 0 at +x, counter-clockwise)."""
    azimuth = np.asarray(azimuth)
    return _cells(azimuth, np.float32(width / (2 * np.pi)).astype(azimuth.dtype), int(width))


@numba.njit(cache=True, nogil=True)
def _cells(azimuth, scale, width):
    """azimuth_cells in one pass (the product in the azimuth's own precision, as numpy's)."""
    out = np.empty(len(azimuth), np.int32)
    for i in range(len(azimuth)):
        out[i] = np.int64(np.rint(azimuth[i] * scale)) % width
    return out


@numba.njit(cache=True, nogil=True)
def cell_points(row, col, height, width):
    """(height · width,) index of the point in each grid cell, row-major (the last of several), −1 for none.
    Compiled into other numba kernels (knn._vote): after editing it, clear numba's cache (__pycache__/*.nbi)."""
    out = np.full(height * width, -1, np.int64)
    for i in range(len(row)):
        out[row[i] * width + col[i]] = i
    return out


def aligned(width: int) -> int:
    """``width`` rounded up to a multiple of GRID_ALIGN (at least MIN_COLUMNS)."""
    return max(MIN_COLUMNS, -(-int(width) // GRID_ALIGN) * GRID_ALIGN)


def as_grid(points: np.ndarray, grid_or_beam=None, model=None) -> ScanGrid:
    """``grid_or_beam`` when it is a ScanGrid, else the grid of the points with those (N,) beam ids (or none)."""
    if isinstance(grid_or_beam, ScanGrid):
        return grid_or_beam
    return scan_grid(points, grid_or_beam, model=model)


def scan_grid(points: np.ndarray, beam: np.ndarray | None = None, columns: int = 0, model=None,
              layout: str = "") -> ScanGrid:
    """The grid of one scan: (N, 3) sensor-frame points (m), optional (N,) beam ids from the cloud (ids must be
    < MAX_BEAMS; the Monitor drops points with bad ids), ``columns`` of an organised cloud (0 = unknown), an
    optional sensors.SensorModel and the cloud's driver layout name (sensors.LAYOUTS; '' unknown, a named model
    wins). See the module docstring for the order in which rows are found."""
    pts = np.asarray(points, np.float32).reshape(-1, 3)
    if len(pts) == 0:
        return ScanGrid(np.zeros(0, np.int32), np.zeros(0, np.int32), 1, aligned(0), np.full(1, np.nan), "empty")
    non_repetitive = (model.pattern if model is not None else layout_pattern(layout)) == "non_repetitive"
    az, azimuth = np.arctan2(pts[:, 1], pts[:, 0]), None  # azimuth: kept for a non-repetitive grid only
    row_el = None  # each row's median elevation (deg), when _rows_from_beams found it on the way
    if beam is not None and not non_repetitive:  # rows from the ids: elevations of a sample suffice
        row, height, source, row_el = _rows_from_beams(np.asarray(beam).astype(np.int64), pts, model)
    else:
        el = elevation_deg(pts)
        if model is not None and not non_repetitive:
            row, height, source = _nearest(el, np.asarray(model.elevation_deg)), model.beams, f"{model.name} beam table"
        else:
            centres = None if non_repetitive else beam_centres(pts, el)
            if centres is None:
                fov = model.fov_deg if model is not None else (float(el.min()), float(el.max()))
                rows = model.grid_rows if model is not None else NON_REPETITIVE_ROWS
                row, height, source = _bins(el, fov, rows), rows, "elevation bins (non-repetitive)"
                columns = square_cells(fov, rows)  # no firings per revolution: cells as wide as they are tall
                azimuth = az  # the network image's finer columns (image_columns)
            else:
                row, height, source = _nearest(el, centres), len(centres), "elevation clusters"
    width = aligned(min(_width(columns, model, non_repetitive) or _estimate_width(pts, row, height), MAX_COLUMNS))
    if row_el is None:
        row_el = _row_elevations(row[::SAMPLE], el[::SAMPLE], height)
    return ScanGrid(row.astype(np.int32), azimuth_cells(az, width), int(height), width, row_el, source, azimuth)


def _width(columns: int, model, non_repetitive: bool) -> int:
    """Azimuth cells when known without looking at the points (0 = estimate them): a non-repetitive grid's
    (the named model's, else square cells), else the organised cloud's width (the driver's real firings per
    revolution, whatever mode a named sensor runs in), else the named model's."""
    if non_repetitive:
        return model.columns if model is not None else columns
    return columns or (model.columns if model is not None else 0)


def square_cells(fov_deg: tuple[float, float], rows: int) -> int:
    """Columns that make a grid's cells as wide as they are tall: 360° over the row height."""
    return int(round(360.0 / max((fov_deg[1] - fov_deg[0]) / rows, 1e-3)))


def image_columns(points: int, rows: int) -> int:
    """Columns of the network's image of a non-repetitive grid of ``points`` points (those projected: after a
    voxel filter, fewer) on ``rows`` rows: about one pixel per point, rounded up to IMAGE_COLUMN_STEP. The
    grid's own square cells hold several points each (the plane detector's tiles need them); the network,
    which learned on images of about one point per pixel, reads coarser or sparser images poorly (Mid-360,
    validation floor plan: mIoU 41 at 200 columns, 46 at 512, 55 at 640, 45 at 1024). A sensor's scans thus
    take a few widths (each new one costs an ONNX export once: 0.2-0.4 s, about 0.7 s with 3 passes)."""
    return min(max(1, -(-int(points) // max(rows * IMAGE_COLUMN_STEP, 1))) * IMAGE_COLUMN_STEP, MAX_COLUMNS)


def _rows_from_beams(beam: np.ndarray, pts: np.ndarray, model) -> tuple[np.ndarray, int, str, np.ndarray]:
    """Rows from the cloud's beam ids, bottom-up: kept as they are when the ids rise with elevation, reversed
    when they fall (Ouster), else ranked by each id's median elevation. Returns (row, height, source, each row's
    median elevation (deg, NaN for none) over every SAMPLE-th point: _row_elevations)."""
    height = model.beams if model is not None else int(beam.max()) + 1
    sub = slice(None, None, SAMPLE)
    ids = unique_ids(beam)
    sampled = len(unique_ids(beam[sub])) == len(ids)  # a sparse cloud can hide a beam from the sample
    part = sub if sampled else slice(None)
    el = elevation_deg(pts[part])
    med = _medians(beam[part], el, ids)
    steps = np.diff(med)
    if len(steps) == 0 or np.all(steps > 0):
        row, row_of_ids, source = beam, ids, "ring field"
    elif np.all(steps < 0):
        row, row_of_ids, source = height - 1 - beam, height - 1 - ids, "ring field (top-down, reversed)"
    else:
        rank = np.empty(height, np.int64)
        rank[ids[np.argsort(med, kind="stable")]] = np.arange(len(ids))
        row, row_of_ids, source, height = rank[beam], rank[ids], "ring field (ranked by elevation)", len(ids)
    if not sampled:
        return row, height, source, _row_elevations(row[sub], el[sub], height)
    row_el = np.full(height, np.nan)  # the sample's median per id is its row's: the same points, grouped alike
    row_el[row_of_ids] = med
    return row, height, source, row_el


def unique_ids(ids: np.ndarray) -> np.ndarray:
    """np.unique of integer ids; by counting when they are small and non-negative (no sort)."""
    if len(ids) and 0 <= ids.min() and ids.max() < 2 ** 16:
        return np.flatnonzero(np.bincount(ids)).astype(ids.dtype)
    return np.unique(ids)


def argsort_ids(ids: np.ndarray) -> np.ndarray:
    """np.argsort(ids, kind="stable") of integer ids; a radix sort (~8x faster) when they fit 16 bits."""
    if len(ids) and 0 <= ids.min() and ids.max() < 2 ** 16:
        ids = ids.astype(np.uint16)
    return np.argsort(ids, kind="stable")


def _medians(beam: np.ndarray, el: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Median elevation per beam id, one sort instead of a mask per id."""
    order = np.argsort(el)
    order = order[argsort_ids(beam[order])]  # by beam, then elevation (as np.lexsort((el, beam)), faster)
    b, e = beam[order], el[order]
    start = np.searchsorted(b, ids, "left")
    stop = np.searchsorted(b, ids, "right")
    return e[(start + stop - 1) // 2]


def beam_centres(points: np.ndarray, el: np.ndarray | None = None) -> np.ndarray | None:
    """Elevations (deg, ascending) of the beams a spinning LiDAR's scan shows, or None when its elevations
    form no beams (a non-repetitive pattern: fewer than MIN_BEAMS or more than MAX_BEAMS clusters, or one
    wider than a beam): the sorted elevations of points beyond CLUSTER_MIN_RANGE split
    at gaps >= BEAM_GAP_DEG; near points far from every such beam (steep beams that only hit the floor close
    by) add beams of their own."""
    el = elevation_deg(points) if el is None else el
    far = np.linalg.norm(points, axis=1) >= CLUSTER_MIN_RANGE
    centres = _clusters(el[far] if far.sum() >= 100 else el)
    if centres is None or not MIN_BEAMS <= len(centres) <= MAX_BEAMS:
        return None
    spacing = float(np.median(np.diff(centres))) if len(centres) > 1 else 1.0
    near = el[~far]
    lone = near[np.abs(near[:, None] - centres[None]).min(axis=1) > max(BEAM_GAP_DEG, 0.4 * spacing)] if len(near) else near
    extra = _clusters(lone, min_size=max(3, int(0.001 * len(el)))) if len(lone) else None
    centres = centres if extra is None else np.sort(np.concatenate([centres, extra]))
    return centres if len(centres) <= MAX_BEAMS else None


def _clusters(el: np.ndarray, min_size: int = 0) -> np.ndarray | None:
    """Medians of the runs of sorted elevations split at gaps >= BEAM_GAP_DEG (runs below 2 % of the median
    run, or ``min_size``, dropped), or None when a run is wider than one beam can be."""
    e = np.sort(el)
    if len(e) < 2:
        return None
    parts = np.split(e, np.flatnonzero(np.diff(e) >= BEAM_GAP_DEG) + 1)
    sizes = np.array([len(p) for p in parts])
    parts = [p for p in parts if len(p) >= max(3, min_size, 0.02 * np.median(sizes))]
    if not parts or max(p[-1] - p[0] for p in parts) > MAX_BEAM_WIDTH_DEG:
        return None
    return np.array([np.median(p) for p in parts])


def _nearest(el: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Index of the nearest of ascending ``centres`` for each elevation."""
    return np.searchsorted((centres[1:] + centres[:-1]) / 2, el).astype(np.int64)


def _bins(el: np.ndarray, fov: tuple[float, float], rows: int) -> np.ndarray:
    lo, hi = fov
    return np.clip(np.floor((el - lo) / max(hi - lo, 1e-6) * rows), 0, rows - 1).astype(np.int64)


def _estimate_width(points: np.ndarray, row: np.ndarray, height: int) -> int:
    """Firings per revolution of an unorganised scan: 2π over the median azimuth step between neighbouring
    points of its three fullest rows (dropouts leave the median step alone)."""
    counts = np.bincount(row, minlength=height)
    steps = []
    for r in np.argsort(counts)[-3:]:
        p = points[row == r]
        if len(p) > 8:
            steps.append(np.diff(np.sort(np.arctan2(p[:, 1], p[:, 0]))))
    steps = np.concatenate(steps) if steps else np.zeros(0)
    steps = steps[steps >= MIN_AZIMUTH_STEP]  # finer: a second return of the same firing (dual-return scans)
    step = float(np.median(steps)) if len(steps) else 0.0
    return int(round(2 * np.pi / step)) if step > 0 else int(max(counts.max(), 1))


def _row_elevations(row_sample: np.ndarray, el_sample: np.ndarray, height: int) -> np.ndarray:
    """(height,) median elevation (deg) of each row, NaN for empty rows, from every SAMPLE-th point's row and
    elevation."""
    out = np.full(height, np.nan)
    present = unique_ids(row_sample)
    out[present] = _medians(row_sample, el_sample, present)
    return out
