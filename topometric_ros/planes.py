"""Planes of one scan: the Plane record, least-squares fits, and per-class detection.

Everything here is in the SENSOR frame of the scan. A plane keeps the sufficient statistics of ALL its
inliers (count, mean, scatter matrix), which transform exactly under a rigid motion, so a window can put
a cached plane into its own frame without touching points again (see :meth:`Plane.transformed_stats`).

Detection (:func:`detect_planes`), per static class, two detectors (config.planes.detector):
- ``ring`` (default): the organised scan (ring × azimuth grid). Moments of tiles of the grid, a quadtree
  that keeps the coarsest planar tile, region growing over neighbouring tiles that agree, merging of
  coplanar segments; every point to the nearest plane of its own or a neighbouring tile. Vectorised numpy,
  with numba kernels where a loop over points or cells is faster (moments, the quadtree's block sums, the
  nearest plane of each point, a plane's fit and its smallest rectangle).
- ``open3d``: ``PointCloud.detect_planar_patches`` (Araújo & Oliveira 2020, the paper's detector) on each
  class, points in each patch box, coplanar patches of one surface merged.
Both then split near-vertical planes at openings the scan sees through (doors: coplanar wall pieces
joined by a lintel) and refit every plane on all its inliers with :func:`fit_plane`.
experiments/plane_quality.py scores detections against the simulator's plane-instance ids.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from . import classes as C
from .grid import as_grid, cell_points

# Rows of (N, k) arrays are gathered with .take(i, axis=0) / .compress(mask, axis=0): the same as a[i] /
# a[mask], several times faster in numpy for large N.


@dataclass
class Plane:
    """One detected plane of one scan (sensor frame, metres).

    cls: class id (classes.py). normal: (3,) unit, oriented toward the sensor (so offset > 0 for a plane
    not through the origin). offset: d in n·x + d = 0. count: number of inliers. mean: (3,) inlier
    centroid. scatter: (3, 3) Σ (x − mean)(x − mean)ᵀ over all inliers. sample: (≤K, 3) float32 inlier
    points for display (every k-th inlier, scan order). frame: index of the scan in its stream (−1 when
    unknown). extent: (3, 3) m, the smallest rectangle in the plane that holds every inlier: rows centre,
    half side along its long axis, half side along its short axis (vectors, sensor frame; None for planes
    made without fit_plane).
    """

    cls: int
    normal: np.ndarray
    offset: float
    count: int
    mean: np.ndarray
    scatter: np.ndarray
    sample: np.ndarray
    frame: int = -1
    extent: np.ndarray | None = None

    def transformed_stats(self, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(normal, mean, scatter) after the rigid 4×4 ``pose`` (sensor -> some frame); exact."""
        r, t = pose[:3, :3], pose[:3, 3]
        return r @ self.normal, r @ self.mean + t, r @ self.scatter @ r.T

    def box(self, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(centre (3,), axes (3, 3), size (2,)) of the inliers' rectangle after the rigid ``pose``: axes are
        columns long side, short side, normal (right-handed), size the side lengths (m). Without an extent,
        ±√3 σ along the principal axes (exact for a uniform rectangle only)."""
        if self.extent is not None:
            centre, half = self.extent[0], self.extent[1:].T
        else:
            vals, vecs = np.linalg.eigh(self.scatter / max(self.count, 1))
            centre, half = self.mean, vecs[:, [2, 1]] * np.sqrt(3.0 * np.maximum(vals[[2, 1]], 0.0))
        size = np.linalg.norm(half, axis=0)
        long = half[:, 0] / size[0] if size[0] > 0 else np.linalg.eigh(self.scatter)[1][:, 2]
        axes = np.column_stack([long, np.cross(self.normal, long), self.normal])  # right-handed
        r, t = pose[:3, :3], pose[:3, 3]
        return r @ centre + t, r @ axes, 2 * size


def fit_plane(points: np.ndarray, cls: int, frame: int = -1, max_sample: int = 256) -> Plane:
    """Least-squares plane through (K ≥ 3, 3) sensor-frame points; normal oriented toward the sensor origin."""
    return _fit_plane(points, cls, frame, max_sample)[0]


def _fit_plane(points: np.ndarray, cls: int, frame: int, max_sample: int) -> tuple[Plane, np.ndarray]:
    """(fit_plane's plane, the eigenvalues (3,) ascending of its scatter matrix)."""
    if len(points) < 3:
        raise ValueError(f"a plane needs at least 3 points, got {len(points)}")
    pts = np.ascontiguousarray(points)
    if pts.dtype not in (np.float32, np.float64):
        pts = pts.astype(np.float64)
    mean, scatter, lam, vecs, extent = _fit_kernel(pts, _OCTAGON)
    normal = vecs[:, 0].copy()
    offset = -float(normal @ mean)
    if offset < 0:  # sensor origin on the positive side: n·0 + d > 0
        normal, offset = -normal, -offset
    sample = points[::-(-len(points) // max_sample)]  # evenly spread over the inliers (scan order)
    plane = Plane(int(cls), normal, offset, len(points), mean, scatter, np.asarray(sample, np.float32), frame, extent)
    return plane, lam


@numba.njit(cache=True, nogil=True)
def _fit_kernel(points, octagon):
    """Least squares and extent of (K, 3) points, in float64: (mean (3,), scatter (3, 3), its eigenvalues (3,)
    ascending and eigenvectors (3, 3) as columns, the extent (3, 3) of Plane: the min_area_rectangle of the
    points in the plane of the two largest principal axes)."""
    xyz = points.astype(np.float64)
    mean, scatter = mean_scatter(xyz)
    lam, vecs = np.linalg.eigh(scatter)
    basis = np.empty((3, 2))  # in-plane principal axes, the longest first
    basis[:, 0], basis[:, 1] = vecs[:, 2], vecs[:, 1]
    centre, half = _rectangle(_in_plane(xyz, mean, basis), octagon)
    extent = np.empty((3, 3))
    for a in range(3):
        extent[0, a] = mean[a] + basis[a, 0] * centre[0] + basis[a, 1] * centre[1]
        for side in range(2):
            extent[1 + side, a] = basis[a, 0] * half[0, side] + basis[a, 1] * half[1, side]
    return mean, scatter, lam, vecs, extent


@numba.njit(cache=True, nogil=True)
def mean_scatter(points):
    """(mean (3,), Σ (x − mean)(x − mean)ᵀ (3, 3)) of (K, 3) points, in float64, two passes."""
    mean = np.zeros(3)
    for i in range(len(points)):
        for a in range(3):
            mean[a] += points[i, a]
    mean /= len(points)
    scatter = np.zeros((3, 3))
    for i in range(len(points)):
        dx, dy, dz = points[i, 0] - mean[0], points[i, 1] - mean[1], points[i, 2] - mean[2]
        scatter[0, 0] += dx * dx
        scatter[0, 1] += dx * dy
        scatter[0, 2] += dx * dz
        scatter[1, 1] += dy * dy
        scatter[1, 2] += dy * dz
        scatter[2, 2] += dz * dz
    scatter[1, 0], scatter[2, 0], scatter[2, 1] = scatter[0, 1], scatter[0, 2], scatter[1, 2]
    return mean, scatter


@numba.njit(cache=True, nogil=True)
def _in_plane(points, mean, basis):
    """(K, 2) coordinates of (K, 3) points about ``mean`` along the two columns of ``basis`` (3, 2), float64."""
    out = np.empty((len(points), 2))
    for i in range(len(points)):
        dx, dy, dz = points[i, 0] - mean[0], points[i, 1] - mean[1], points[i, 2] - mean[2]
        out[i, 0] = dx * basis[0, 0] + dy * basis[1, 0] + dz * basis[2, 0]
        out[i, 1] = dx * basis[0, 1] + dy * basis[1, 1] + dz * basis[2, 1]
    return out


def min_area_rectangle(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smallest-area rectangle holding (K >= 1, 2) points: (centre (2,), half sides (2, 2) as columns, long
    first). Exact: the smallest rectangle has a side along an edge of the points' convex hull (Freeman &
    Shapira 1975), so each hull edge's box is measured over the hull's corners. Points strictly inside the
    octagon of the extremes in 8 directions are dropped first (Akl–Toussaint: they are on no hull), so most
    of a plane's inliers cost 8 small products. Collinear points: zero width. One numba kernel (_rectangle)."""
    xy = np.ascontiguousarray(xy, np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2 or len(xy) == 0:
        raise ValueError(f"a rectangle needs (K >= 1, 2) points, got shape {xy.shape}")
    return _rectangle(xy, _OCTAGON)


_OCTAGON = np.stack([np.cos(np.arange(8) * np.pi / 4), np.sin(np.arange(8) * np.pi / 4)], 1)  # unit directions


@numba.njit(cache=True, nogil=True)
def _rectangle(xy, octagon):
    """min_area_rectangle of (K >= 1, 2) float64 points, with the (8, 2) unit directions of the octagon."""
    hull = _convex_hull(_outside(xy, _extremes(xy, octagon)))
    h = len(hull)
    best, best_k = np.inf, -1
    bu = np.zeros(2)
    lo_u = hi_u = lo_v = hi_v = 0.0
    for k in range(h):
        ux, uy = hull[(k + 1) % h, 0] - hull[k, 0], hull[(k + 1) % h, 1] - hull[k, 1]
        length = np.sqrt(ux * ux + uy * uy)
        if length <= 0:
            continue
        ux, uy = ux / length, uy / length
        a_lo, a_hi, b_lo, b_hi = np.inf, -np.inf, np.inf, -np.inf
        for i in range(h):
            pu = hull[i, 0] * ux + hull[i, 1] * uy
            pv = hull[i, 0] * -uy + hull[i, 1] * ux  # along u turned by +90°
            a_lo, a_hi, b_lo, b_hi = min(a_lo, pu), max(a_hi, pu), min(b_lo, pv), max(b_hi, pv)
        area = (a_hi - a_lo) * (b_hi - b_lo)
        if area < best:
            best, best_k = area, k
            bu[0], bu[1] = ux, uy
            lo_u, hi_u, lo_v, hi_v = a_lo, a_hi, b_lo, b_hi
    halves = np.zeros((2, 2))
    if best_k < 0:  # every point the same
        return hull[0].copy(), halves
    vx, vy = -bu[1], bu[0]
    halves[0, 0], halves[1, 0] = bu[0] * (hi_u - lo_u) / 2, bu[1] * (hi_u - lo_u) / 2
    halves[0, 1], halves[1, 1] = vx * (hi_v - lo_v) / 2, vy * (hi_v - lo_v) / 2
    if hi_v - lo_v > hi_u - lo_u:
        halves = halves[:, ::-1].copy()
    cu, cv = (lo_u + hi_u) / 2, (lo_v + hi_v) / 2
    return np.array([bu[0] * cu + vx * cv, bu[1] * cu + vy * cv]), halves


@numba.njit(cache=True, nogil=True)
def _convex_hull(xy):
    """Corners of the convex hull of (K >= 1, 2) points, counter-clockwise, without collinear corners
    (Andrew's monotone chain; all points the same: one or two equal corners)."""
    order = np.argsort(xy[:, 1], kind="mergesort")
    order = order[np.argsort(xy[order, 0], kind="mergesort")]  # by x, then y (both sorts stable)
    p = xy[order]
    n = len(p)
    hull = np.empty((2 * n, 2))
    k = 0
    for i in range(n):  # lower chain, left to right
        while k >= 2 and _turn(hull[k - 2], hull[k - 1], p[i]) <= 0:
            k -= 1
        hull[k] = p[i]
        k += 1
    lower = k + 1
    for i in range(n - 2, -1, -1):  # upper chain, right to left
        while k >= lower and _turn(hull[k - 2], hull[k - 1], p[i]) <= 0:
            k -= 1
        hull[k] = p[i]
        k += 1
    return hull[:max(k - 1, 1)]  # the last corner is the first again


@numba.njit(cache=True, nogil=True, inline="always")
def _turn(a, b, c):
    """(b − a) × (c − a): > 0 when a, b, c turn counter-clockwise."""
    return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])


@numba.njit(cache=True, nogil=True)
def _extremes(xy, directions):
    """The points of (K, 2) ``xy`` farthest along each of the (D, 2) ``directions`` (counter-clockwise; the
    first of equals), consecutive repeats dropped (cyclically): the polygon of the extremes, (<= D, 2)."""
    d = len(directions)
    idx = np.zeros(d, np.int64)
    far = np.full(d, -np.inf)
    for i in range(len(xy)):
        x, y = xy[i, 0], xy[i, 1]
        for k in range(d):
            t = directions[k, 0] * x + directions[k, 1] * y
            if t > far[k]:
                far[k], idx[k] = t, i
    keep = np.empty(d, np.bool_)
    for k in range(d):
        keep[k] = idx[k] != idx[k - 1]
    if not keep.any():
        keep[0] = True
    return xy[idx[keep]]


@numba.njit(cache=True, nogil=True)
def _outside(xy, poly):
    """The points of (K, 2) ``xy`` not strictly inside the counter-clockwise polygon ``poly`` (all of them when
    it has fewer than 3 corners): a superset of the convex hull's vertices when poly's corners are points."""
    m = len(poly)
    if m < 3:
        return xy
    inward = np.empty((m, 2))  # each edge's inward normal (the edge turned by +90°) and its offset
    level = np.empty(m)
    for k in range(m):
        ex, ey = poly[(k + 1) % m, 0] - poly[k, 0], poly[(k + 1) % m, 1] - poly[k, 1]
        inward[k, 0], inward[k, 1] = -ey, ex
        level[k] = -ey * poly[k, 0] + ex * poly[k, 1] + 1e-9
    keep = np.empty(len(xy), np.bool_)
    for i in range(len(xy)):
        x, y = xy[i, 0], xy[i, 1]
        inside = True
        for k in range(m):
            if inward[k, 0] * x + inward[k, 1] * y <= level[k]:
                inside = False
                break
        keep[i] = not inside
    return xy[keep]


def planes_from_instances(points: np.ndarray, labels: np.ndarray, instance: np.ndarray, min_points: int = 50,
                          frame: int = -1, static: tuple = C.STATIC) -> list[Plane]:
    """Oracle planes from the simulator's plane-instance ids: one fit per instance of a static class with at
    least ``min_points`` points. For tests and for measuring detectors, never for real data."""
    keep = np.isin(labels, static)
    out = []
    ids, counts = np.unique(instance[keep], return_counts=True)
    for inst in ids[counts >= min_points]:
        m = keep & (instance == inst)
        out.append(fit_plane(points[m], int(np.bincount(labels[m]).argmax()), frame))
    return out


# --------------------------------------------------------------------------------------------------------
# Detection. Both detectors produce "parts" (a class, summed inlier statistics and anchor points), merge the
# coplanar parts of one surface, assign every static point to the nearest merged plane within
# inlier_distance, and refit each plane on all its inliers with fit_plane.
# --------------------------------------------------------------------------------------------------------

_NCLS = C.NUM_CLASSES
#: |normal · sensor z| of a plane facing up or down (45°): no wall or pillar plane does, and the floor check's
#: floor plane must (segmentation/floor.py): the sensor is taken as mounted within 45° of level. Floor and
#: ceiling planes are not held to it: on real scans the network calls some facades "ceiling", and those are
#: still planes that scans share.
UPRIGHT = float(np.cos(np.radians(45.0)))


def detect_planes(points: np.ndarray, labels: np.ndarray, grid=None, config=None,
                  frame: int = -1, return_inliers: bool = False):
    """Planes of one scan, per static class (classes.STATIC), in the sensor frame.

    points: (N, 3) sensor frame, metres. labels: (N,) uint8 class ids. grid: the scan's grid.ScanGrid, or
    the cloud's (N,) beam ids, or None (both found from the points, grid.as_grid). config: PlaneConfig.
    Every plane: unit normal toward the sensor (offset > 0), stats from all its inliers, class, ``frame``.
    Planes with fewer than config.min_points inliers are dropped.

    Returns the list of planes, or with ``return_inliers`` (planes, (N,) int32 index of each point's plane,
    −1 for none).
    """
    from .config import PlaneConfig

    cfg = config if config is not None else PlaneConfig()
    pts = np.asarray(points, np.float32).reshape(-1, 3)
    lab = np.asarray(labels).reshape(-1)
    if lab.dtype.kind not in "iu":
        raise ValueError(f"labels must be integer class ids, got dtype {lab.dtype}")
    if len(lab) != len(pts):
        raise ValueError(f"{len(pts)} points but {len(lab)} labels")
    if grid is not None and len(getattr(grid, "row", grid)) != len(pts):
        raise ValueError(f"{len(pts)} points but {len(getattr(grid, 'row', grid))} grid cells / ring ids")
    if cfg.detector not in ("ring", "open3d"):
        raise ValueError(f"unknown plane detector {cfg.detector!r}; choose ring or open3d")
    if len(pts) == 0:
        return ([], np.zeros(0, np.int32)) if return_inliers else []
    grid = as_grid(pts, grid)
    if cfg.detector == "ring":
        assign, normal, offset = _assign_ring(pts, lab, grid, cfg)
    else:
        assign, normal, offset = _assign_open3d(pts, lab, cfg)
    groups = _groups(assign)
    groups = _split_at_openings(pts, groups, normal, offset, grid, cfg)
    planes, assign = _refit(pts, lab, groups, cfg, frame)
    return (planes, assign) if return_inliers else planes


# ---- shared pieces -------------------------------------------------------------------------------------

def _moments(pts: np.ndarray, group: np.ndarray, n_groups: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(count (G,), sum (G, 3), Σ x xᵀ (G, 3, 3)) of float64 points per group id (0..G−1)."""
    count, s, outer = np.zeros(n_groups), np.zeros((n_groups, 3)), np.zeros((n_groups, 3, 3))
    _add_moments(np.asarray(pts), np.asarray(group), count, s, outer)
    return count, s, outer


@numba.njit(cache=True, nogil=True)
def _add_moments(pts, group, count, s, outer):
    """Add each point's moments to its group's, in point order (as np.bincount sums: the same floats)."""
    for i in range(len(group)):
        g = group[i]
        x, y, z = np.float64(pts[i, 0]), np.float64(pts[i, 1]), np.float64(pts[i, 2])
        count[g] += 1.0
        s[g, 0] += x
        s[g, 1] += y
        s[g, 2] += z
        outer[g, 0, 0] += x * x
        outer[g, 0, 1] += x * y
        outer[g, 0, 2] += x * z
        outer[g, 1, 1] += y * y
        outer[g, 1, 2] += y * z
        outer[g, 2, 2] += z * z
    outer[:, 1, 0] = outer[:, 0, 1]
    outer[:, 2, 0] = outer[:, 0, 2]
    outer[:, 2, 1] = outer[:, 1, 2]


def _planes_of(count, s, outer):
    """Least-squares planes from summed moments: (normal (G, 3) toward the origin, offset (G,), mean (G, 3),
    eigenvalues (G, 3) ascending of the scatter matrix)."""
    n = np.maximum(count, 1.0)
    mean = s / n[:, None]
    scatter = outer - n[:, None, None] * mean[:, :, None] * mean[:, None, :]
    lam, vec = np.linalg.eigh(scatter)
    normal = vec[:, :, 0]
    offset = -np.einsum("ij,ij->i", normal, mean)
    flip = offset < 0
    normal[flip] *= -1
    offset[flip] *= -1
    return normal, offset, mean, lam


def _merge_groups(cls, normal, offset, mean, i: np.ndarray, j: np.ndarray, cfg) -> np.ndarray:
    """Merged group id for each part: parts of one class whose planes agree (normals within
    normal_angle_deg, each centroid within merge_distance of the other plane) and that are adjacent (the
    index pairs i, j) are joined, transitively."""
    if len(cls) == 0:
        return np.zeros(0, np.int64)
    ok = _coplanar(cls, normal, offset, mean, i, j, cfg.normal_angle_deg, cfg.merge_distance)
    return _components(len(cls), i[ok], j[ok])[1]


def _all_pairs(members: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every pair (i < j) of the given indices."""
    a, b = np.triu_indices(len(members), 1)
    return members[a], members[b]


def _coplanar(cls, normal, offset, mean, i, j, angle_deg, distance):
    """For index pairs (i, j): same class, normals within angle_deg, each centroid within distance of the
    other's plane (normals oriented toward the sensor, so no sign ambiguity)."""
    cos = np.einsum("ij,ij->i", normal[i], normal[j])
    d_ij = np.abs(np.einsum("ij,ij->i", normal[i], mean[j]) + offset[i])
    d_ji = np.abs(np.einsum("ij,ij->i", normal[j], mean[i]) + offset[j])
    return (cls[i] == cls[j]) & (cos >= np.cos(np.radians(angle_deg))) & (d_ij <= distance) & (d_ji <= distance)


class _Rays:
    """Every ray of the scan on its grid (grid.ScanGrid): a point, or nothing (an empty cell; its direction
    from the row's median elevation and the cell's azimuth centre, grid.azimuth_cells). One point per cell is enough here."""

    def __init__(self, pts: np.ndarray, grid):
        self.grid = cell_points(grid.row, grid.col, grid.height, grid.width).reshape(grid.height, grid.width)
        self.ring_seen = np.isfinite(grid.elevation_deg)
        self.ring_elev = np.radians(np.nan_to_num(grid.elevation_deg))
        self.pts, self.col, self.bins = pts, grid.col, grid.width

    def between(self, c0: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
        """(points, unit directions of empty rays) strictly between azimuth cells c0 and c1 (shorter arc)."""
        w = self.bins
        if (c1 - c0) % w > w // 2:
            c0, c1 = c1, c0
        if (c1 - c0) % w <= 1:
            return self.pts[:0], np.zeros((0, 3))
        cols = (c0 + 1 + np.arange((c1 - c0) % w - 1)) % w
        block = self.grid[:, cols]
        er, ec = np.nonzero((block < 0) & self.ring_seen[:, None])
        e, az = self.ring_elev[er], cols[ec] * (2 * np.pi / w)
        empty = np.stack([np.cos(e) * np.cos(az), np.cos(e) * np.sin(az), np.sin(e)], 1)
        return self.pts.take(block[block >= 0], axis=0), empty


def _groups(assign: np.ndarray) -> dict[int, np.ndarray]:
    """{group id: indices of its points, ascending} for the ids >= 0 in ``assign``."""
    if not (assign >= 0).any():
        return {}
    order, sizes = _counting_sort(assign, int(assign.max()) + 1)
    ids = np.flatnonzero(sizes)
    return dict(zip(ids.tolist(), np.split(order, np.cumsum(sizes[ids])[:-1])))


@numba.njit(cache=True, nogil=True)
def _counting_sort(assign, n):
    """(indices of the entries of ``assign`` in 0..n−1 ordered by value, stably; (n,) count of each value)."""
    sizes = np.zeros(n, np.int64)
    for i in range(len(assign)):
        if assign[i] >= 0:
            sizes[assign[i]] += 1
    start = np.zeros(n, np.int64)
    for g in range(1, n):
        start[g] = start[g - 1] + sizes[g - 1]
    order = np.empty(start[n - 1] + sizes[n - 1], np.int64)
    for i in range(len(assign)):
        g = assign[i]
        if g >= 0:
            order[start[g]] = i
            start[g] += 1
    return order, sizes


def _split_at_openings(pts: np.ndarray, groups: dict, normal: np.ndarray, offset: np.ndarray, grid,
                       cfg) -> list[np.ndarray]:
    """Split near-vertical planes at openings (doors): a gap wider than opening_width in the plane's inliers
    within opening_band of its lowest inlier, through which the scan sees BEHIND the plane (of the rays
    through the gap, at least opening_min_points and a fraction opening_through returned behind the plane
    or not at all; the rest hit an occluder in front). An occluder alone leaves a gap but no ray through it, so it splits
    nothing. Coplanar wall pieces joined only by a lintel become separate planes. Sensor z is taken as up.
    groups: {plane id: point indices}; normal, offset: each plane id's plane (toward the sensor); grid: the
    scan's grid.ScanGrid. Returns the point indices per plane."""
    out = []
    rays = None
    for g, members in groups.items():
        n, d = normal[g], offset[g]
        if cfg.opening_width <= 0 or len(members) < cfg.min_points or abs(n[2]) > 0.3:
            out.append(members)
            continue
        along = np.array([-n[1], n[0], 0.0]) / np.hypot(n[0], n[1])
        u, v = _along_and_up(pts, members, along)
        floor = np.partition(v, len(v) // 100)[len(v) // 100]
        low = np.flatnonzero(v < floor + cfg.opening_band)
        gaps = np.flatnonzero(np.diff(np.sort(u[low])) > cfg.opening_width)  # np.sort: 2x faster than argsort
        if len(gaps) == 0:
            out.append(members)
            continue
        low = low[np.argsort(u[low])]  # the points on either side of each gap
        if rays is None:
            rays = _Rays(pts, grid)
        cuts = []
        for k in gaps:
            x, e = rays.between(rays.col[members[low[k]]], rays.col[members[low[k + 1]]])
            if len(x) + len(e) < cfg.opening_min_points:
                continue
            side = x @ n + d  # > 0 in front of the plane (sensor side), < 0 behind
            hit = np.abs(side) > cfg.inlier_distance
            x, side = x[hit], side[hit]
            t = d / (d - side)  # the ray meets the plane at t * x
            toward = e @ n
            e = e[toward < -1e-6]
            z = np.concatenate([t * x[:, 2], e[:, 2] * (d / -toward[toward < -1e-6])])
            through = np.concatenate([side < 0, np.ones(len(e), bool)])
            ok = (np.concatenate([t > 0, np.ones(len(e), bool)]) & (z >= floor) & (z < floor + cfg.opening_band))
            n_through = np.count_nonzero(through & ok)
            if n_through >= cfg.opening_min_points and n_through >= cfg.opening_through * np.count_nonzero(ok):
                cuts.append((u[low[k]] + u[low[k + 1]]) / 2)
        if cuts:
            part = np.searchsorted(np.sort(cuts), u)
            out += [members[part == i] for i in range(len(cuts) + 1)]
        else:
            out.append(members)
    return out


@numba.njit(cache=True, nogil=True)
def _along_and_up(pts, members, along):
    """(u, v) of the points ``members`` of (N, 3) ``pts``: u = x · along (float64, m; ``along`` horizontal),
    v = z (as stored)."""
    u = np.empty(len(members))
    v = np.empty(len(members), pts.dtype)
    for k in range(len(members)):
        i = members[k]
        u[k] = np.float64(pts[i, 0]) * along[0] + np.float64(pts[i, 1]) * along[1]
        v[k] = pts[i, 2]
    return u, v


def _refit(pts, lab, groups: list[np.ndarray], cfg, frame) -> tuple[list[Plane], np.ndarray]:
    """Fit each group of point indices with fit_plane on all its inliers; drop groups below min_points, narrower
    than min_width, or of walls and pillars facing up or down (UPRIGHT).
    Returns the planes and each point's plane index (−1 none)."""
    out = np.full(len(pts), -1, np.int32)
    planes = []
    for members in groups:
        if len(members) < max(cfg.min_points, 3):
            continue
        cls = int(lab[members[0]])
        plane, lam = _fit_plane(pts.take(members, axis=0), cls, frame, cfg.max_sample_points)
        if lam[1] < len(members) * cfg.min_width ** 2:
            continue  # a line (e.g. where a spurious plane crosses a real one), not a plane
        if cls in (C.WALL, C.PILLAR) and abs(plane.normal[2]) >= UPRIGHT:
            continue  # a "wall" facing up or down. E.g. a beam near 0° elevation sweeps a nearly flat cone, so
            # its points across a corner or several walls fit a horizontal plane whatever they hit
        planes.append(plane)
        out[members] = len(planes) - 1
    return planes, out


# ---- ring detector -------------------------------------------------------------------------------------

def tile_size(grid, cfg) -> tuple[int, int]:
    """(rows, columns) of a base tile on ``grid``: config.planes' tile_rings per 32 rows and tile_columns per
    1800 columns, so a tile covers about the same solid angle on every sensor."""
    return (max(1, round(cfg.tile_rings * grid.height / 32)), max(1, round(cfg.tile_columns * grid.width / 1800)))


_STATIC_INDEX = np.full(256, -1, np.int64)
_STATIC_INDEX[list(C.STATIC)] = np.arange(len(C.STATIC))


def _assign_ring(pts, lab, grid, cfg) -> np.ndarray:
    """Plane group per point (−1 none) on the scan grid (grid.ScanGrid).

    Static points go into tiles of the grid per class (tile_size: tile_rings × tile_columns cells scaled from a
    32 × 1800 grid to this one, and coarser levels of 2×2 tiles). A quadtree keeps the coarsest planar tile over each cell (large tiles give
    good normals at short range and on sparse rings; small tiles separate surfaces). Neighbouring planar tiles
    that agree grow into segments; coplanar segments that touch are merged; every point goes to the nearest
    plane of its own or a neighbouring tile within inlier_distance."""
    assign = np.full(len(pts), -1, np.int64)
    index = _STATIC_INDEX.take(lab, mode="clip")  # class index; −1 not static (ids outside 0..255 clip to 0 or 255: neither is)
    static = np.flatnonzero(index >= 0)
    if len(static) < 3:
        return assign, np.zeros((0, 3)), np.zeros(0)
    p = pts.take(static, axis=0)
    ci = index.take(static)
    row, col = grid.row[static], grid.col[static]
    tile_rows, tile_cols = tile_size(grid, cfg)
    tr, tc = row // tile_rows, col // tile_cols
    tiles = _quadtree_tiles(p, ci, tr, tc, -(-grid.width // tile_cols), cfg)
    if tiles is None:
        return assign, np.zeros((0, 3)), np.zeros(0)
    count, s, outer, normal, offset, mean, spread, tcls, grid = tiles
    # grow segments over neighbouring tiles that agree and are near in space too (not just in the image:
    # a surface seen past an occluder or at a grazing angle can be far from its image neighbour)
    a, b = _neighbour_pairs(grid)
    near = np.linalg.norm(mean[a] - mean[b], axis=1) <= 3.5 * (spread[a] + spread[b]) + cfg.merge_gap
    a, b = a[near], b[near]
    ok = _coplanar(tcls, normal, offset, mean, a, b, cfg.tile_angle_deg, cfg.merge_distance)
    n_seg, seg = _components(len(count), a[ok], b[ok])
    scount, ss, souter = _sum_moments(seg, n_seg, count, s, outer)
    snormal, soffset, smean, _ = _planes_of(scount, ss, souter)
    scls = np.zeros(n_seg, np.int64)
    scls[seg] = tcls
    # merge coplanar segments that touch (or nearly touch; floors and ceilings whatever the gap)
    i, j = [seg[a]], [seg[b]]
    near = _near_pairs(mean, cfg.merge_gap)
    i.append(seg[near[0]])
    j.append(seg[near[1]])
    for c in C.STATIC:
        if (cfg.merge_floor_ceiling and c in (C.FLOOR, C.CEILING)) or (cfg.merge_across_gaps and c in (C.WALL, C.PILLAR)):
            hi, hj = _all_pairs(np.flatnonzero((scls == _STATIC_INDEX[c]) & (scount >= cfg.min_points)))
            i.append(hi)
            j.append(hj)
    i, j = np.concatenate(i), np.concatenate(j)
    pair = i != j
    merged = _merge_groups(scls, snormal, soffset, smean, i[pair], j[pair], cfg)
    n_m = int(merged.max()) + 1
    mnormal, moffset, _, _ = _planes_of(*_sum_moments(merged, n_m, scount, ss, souter))
    plane_of_tile = merged[seg]
    # each point: its own tile's plane if near enough, else the nearest plane of the 8 neighbouring tiles
    plane_grid = np.where(grid >= 0, plane_of_tile[np.maximum(grid, 0)], -1)
    best = _nearest_candidate(p, ci, tr, tc, plane_grid, mnormal, moffset, cfg.inlier_distance)
    assign[static] = best
    return assign, mnormal, moffset


def _quadtree_tiles(p, ci, tr, tc, tcols, cfg):
    """Planar tiles chosen coarsest-first. Returns per tile (count, sum, Σxxᵀ, normal, offset, mean, RMS
    extent, class index) and the (classes, rows, cols) grid of tile ids at the finest level (−1: no planar
    tile); None when no tile is planar."""
    levels = max(int(cfg.tile_levels), 1)
    f = 2 ** (levels - 1)
    trows = -(-(int(tr.max()) + 1) // f) * f
    pcols = -(-tcols // f) * f
    ncls = len(C.STATIC)
    cell = (ci * trows + tr) * pcols + tc
    shape = (ncls, trows, pcols)
    count, s, outer = _moments(p, cell, ncls * trows * pcols)
    count, s, outer = count.reshape(shape), s.reshape(shape + (3,)), outer.reshape(shape + (3, 3))
    covered = np.zeros((ncls, trows // f, pcols // f), bool)
    chosen = []  # per level: (flat indices at that level, count, s, outer, normal, offset, mean)
    for k in range(levels - 1, -1, -1):
        m = 2 ** k
        lc, ls, lo = _pool(count, s, outer, m) if m > 1 else (count, s, outer)
        cand = np.flatnonzero((lc >= cfg.tile_min_points).reshape(-1) & ~covered.reshape(-1))
        cc, cs, co = lc.reshape(-1)[cand], ls.reshape(-1, 3)[cand], lo.reshape(-1, 3, 3)[cand]
        nrm, off, mean, lam = _planes_of(cc, cs, co)
        good = ((lam[:, 0] <= cc * cfg.tile_max_rms ** 2) & (lam[:, 1] >= cfg.tile_min_flatness ** 2 * lam[:, 0])
                & (lam[:, 1] >= cc * 1e-6))
        spread = np.sqrt(lam[:, 2] / cc)  # RMS extent along the tile's longest direction
        chosen.append((k, cand[good], cc[good], cs[good], co[good], nrm[good], off[good], mean[good], spread[good]))
        used = np.zeros(covered.size, bool)
        used[cand[good]] = True
        covered = covered | used.reshape(covered.shape)
        if k:
            covered = covered.repeat(2, axis=1).repeat(2, axis=2)
    n_tiles = sum(len(c[1]) for c in chosen)
    if n_tiles == 0:
        return None
    grid = np.full(shape, -1, np.int64)
    start = 0
    for k, idx, *_ in chosen:
        m = 2 ** k
        ids = np.full(ncls * (trows // m) * (pcols // m), -1, np.int64)
        ids[idx] = np.arange(start, start + len(idx))
        ids = ids.reshape(ncls, trows // m, pcols // m).repeat(m, axis=1).repeat(m, axis=2)
        grid = np.maximum(grid, ids)
        start += len(idx)
    cat = [np.concatenate([c[j] for c in chosen]) for j in range(2, 9)]
    tcls = np.concatenate([idx // ((trows // 2 ** k) * (pcols // 2 ** k)) for k, idx, *_ in chosen])
    grid = grid[:, :, :tcols]  # drop padding so that azimuth wraps around
    return (*cat, tcls, grid)


@numba.njit(cache=True, nogil=True)
def _pool(count, s, outer, m):
    """Moments of (classes, rows, cols) cells summed over blocks of m × m cells (rows and cols multiples of m),
    each block's cells in row-major order: (count, sum (..., 3), Σ x xᵀ (..., 3, 3)) on the coarser grid."""
    ncls, rows, cols = count.shape
    lc = np.zeros((ncls, rows // m, cols // m))
    ls = np.zeros((ncls, rows // m, cols // m, 3))
    lo = np.zeros((ncls, rows // m, cols // m, 3, 3))
    for c in range(ncls):
        for r in range(rows):
            for q in range(cols):
                if count[c, r, q] == 0.0:
                    continue
                br, bq = r // m, q // m
                lc[c, br, bq] += count[c, r, q]
                for i in range(3):
                    ls[c, br, bq, i] += s[c, r, q, i]
                    for j in range(3):
                        lo[c, br, bq, i, j] += outer[c, r, q, i, j]
    return lc, ls, lo


def _sum_moments(group, n, count, s, outer):
    """Moments summed per group id."""
    return (np.bincount(group, count, n), np.stack([np.bincount(group, s[:, k], n) for k in range(3)], 1),
            np.stack([np.bincount(group, outer[:, i, j], n) for i in range(3) for j in range(3)],
                     1).reshape(n, 3, 3))


def _components(n: int, a: np.ndarray, b: np.ndarray) -> tuple[int, np.ndarray]:
    """Connected components of n nodes joined by edges (a, b): (count, component of each node), numbered in
    the order of their lowest node (as scipy's connected_components; hooking and pointer jumping in numpy,
    several times faster than scipy's sparse-matrix set-up on these few hundred nodes)."""
    label = np.arange(n)
    a, b = np.asarray(a, np.int64), np.asarray(b, np.int64)
    while True:
        la, lb = label[a], label[b]
        if np.array_equal(la, lb):
            break
        low = np.minimum(la, lb)
        np.minimum.at(label, la, low)  # hook each root onto the lowest root it touches
        np.minimum.at(label, lb, low)
        while True:  # point every node at its root
            up = label[label]
            if np.array_equal(up, label):
                break
            label = up
    roots, component = np.unique(label, return_inverse=True)
    return len(roots), component


def _neighbour_pairs(grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct (a, b) ids (a < b, sorted) of 8-neighbouring cells of a (..., rows, cols) id grid (−1 empty;
    columns wrap around, rows do not)."""
    n = max(int(grid.max()) + 1, 1)
    keys = np.unique(_pair_keys(np.ascontiguousarray(grid).reshape(-1, *grid.shape[-2:]), n))
    return keys // n, keys % n


@numba.njit(cache=True, nogil=True)
def _pair_keys(grid, n):
    """lo · n + hi of every pair of different ids in cells that touch (right, down-left, down, down-right) of
    (layers, rows, cols) id grids; repeats kept."""
    layers, rows, cols = grid.shape
    keys = np.empty(4 * grid.size, np.int64)
    k = 0
    for g in range(layers):
        for r in range(rows):
            for c in range(cols):
                a = grid[g, r, c]
                if a < 0:
                    continue
                for dr, dc in ((0, 1), (1, -1), (1, 0), (1, 1)):
                    if r + dr >= rows:
                        continue
                    b = grid[g, r + dr, (c + dc) % cols]
                    if b >= 0 and b != a:
                        keys[k] = min(a, b) * n + max(a, b)
                        k += 1
    return keys[:k]


def _near_pairs(where: np.ndarray, gap: float) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs of the points ``where`` (K, 3) closer than ``gap`` metres."""
    if gap <= 0 or len(where) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    from scipy.spatial import cKDTree

    pairs = cKDTree(where).query_pairs(gap, output_type="ndarray")
    return pairs[:, 0], pairs[:, 1]


def _nearest_candidate(p, ci, tr, tc, plane_grid, normal, offset, max_dist) -> np.ndarray:
    """Per point (class index ci, tile row tr, tile column tc in the (classes, rows, cols) ``plane_grid`` of plane
    ids): its own tile's plane when within max_dist, else the nearest plane among the 8 neighbouring tiles'
    planes of its class within max_dist (the last of equals, rows then columns −1..1), else −1."""
    return _nearest_kernel(p, ci, tr, tc, plane_grid, normal.astype(np.float32), offset.astype(np.float32),
                           np.float32(max_dist))


@numba.njit(cache=True, nogil=True)
def _nearest_kernel(p, ci, tr, tc, plane_grid, nrm, off, max_dist):
    """_nearest_candidate on float32 planes; point-to-plane distances in float32."""
    trows, tcols = plane_grid.shape[1], plane_grid.shape[2]
    best = np.full(len(p), -1, np.int64)
    for i in range(len(p)):
        x, y, z = p[i, 0], p[i, 1], p[i, 2]
        cls, r, col = ci[i], tr[i], tc[i]
        own = plane_grid[cls, r, col]
        if own >= 0 and abs(x * nrm[own, 0] + y * nrm[own, 1] + z * nrm[own, 2] + off[own]) <= max_dist:
            best[i] = own
            continue
        best_d = max_dist
        for dr in range(-1, 2):
            rr = r + dr
            if rr < 0 or rr >= trows:
                continue
            for dc in range(-1, 2):
                if dr == 0 and dc == 0:
                    continue
                cand = plane_grid[cls, rr, (col + dc) % tcols]
                if cand < 0:
                    continue
                d = abs(x * nrm[cand, 0] + y * nrm[cand, 1] + z * nrm[cand, 2] + off[cand])
                if d <= best_d:
                    best[i], best_d = cand, d
    return best


# ---- open3d detector -----------------------------------------------------------------------------------

def _assign_open3d(pts, lab, cfg) -> np.ndarray:
    """Plane group per point (−1 none) from Open3D detect_planar_patches per static class: the points in each
    patch's box, coplanar patches of one surface merged, then every point of the class to the nearest merged
    plane within inlier_distance."""
    import open3d as o3d

    assign = np.full(len(pts), -1, np.int64)
    parts = []  # (class, member indices)
    for cls in C.STATIC:
        idx = np.flatnonzero(lab == cls)
        if len(idx) < max(cfg.min_points, cfg.o3d_knn, 3):
            continue
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[idx].astype(np.float64)))
        search = o3d.geometry.KDTreeSearchParamKNN(cfg.o3d_knn)
        pcd.estimate_normals(search)
        patches = pcd.detect_planar_patches(normal_variance_threshold_deg=cfg.o3d_normal_variance_deg,
                                            coplanarity_deg=cfg.o3d_coplanarity_deg,
                                            outlier_ratio=cfg.o3d_outlier_ratio,
                                            search_param=search)
        for box in patches:
            box.extent = np.maximum(np.asarray(box.extent), [0, 0, 2 * cfg.inlier_distance])
            inside = np.asarray(box.get_point_indices_within_bounding_box(pcd.points), np.int64)
            if len(inside) >= 3:
                parts.append((cls, idx[inside]))
    if not parts:
        return assign, np.zeros((0, 3)), np.zeros(0)
    member = np.concatenate([m for _, m in parts])
    part_id = np.repeat(np.arange(len(parts)), [len(m) for _, m in parts])
    count, s, outer = _moments(pts[member], part_id, len(parts))
    normal, offset, mean, _ = _planes_of(count, s, outer)
    cls = np.array([c for c, _ in parts], np.int64)
    i, j = _all_pairs(np.arange(len(parts)))
    ok = _coplanar(cls, normal, offset, mean, i, j, cfg.normal_angle_deg, cfg.merge_distance)
    i, j = i[ok], j[ok]
    any_gap = ((np.isin(cls[i], [C.FLOOR, C.CEILING]) & cfg.merge_floor_ceiling)
               | (np.isin(cls[i], [C.WALL, C.PILLAR]) & cfg.merge_across_gaps))
    near = np.array([h or _sets_within(pts[parts[a][1]], pts[parts[b][1]], cfg.merge_gap)
                     for a, b, h in zip(i, j, any_gap)], bool)
    merged = _merge_groups(cls, normal, offset, mean, i[near], j[near], cfg)
    n_m = int(merged.max()) + 1
    mnormal, moffset, _, _ = _planes_of(np.bincount(merged, count, n_m),
                                        np.stack([np.bincount(merged, s[:, k], n_m) for k in range(3)], 1),
                                        np.stack([np.bincount(merged, outer[:, a, b], n_m) for a in range(3)
                                                  for b in range(3)], 1).reshape(n_m, 3, 3))
    mcls = np.zeros(n_m, np.int64)
    mcls[merged] = cls
    # every point of a class to the nearest merged plane of that class within inlier_distance (patch boxes
    # cover only parts of a surface, e.g. a floor seen on sparse rings); openings split planes later
    for c in np.unique(mcls):
        idx = np.flatnonzero(lab == c)
        ids = np.flatnonzero(mcls == c)
        d = np.abs(pts[idx].astype(np.float64) @ mnormal[ids].T + moffset[ids])
        best = np.argmin(d, axis=1)
        ok = d[np.arange(len(idx)), best] <= cfg.inlier_distance
        assign[idx[ok]] = ids[best[ok]]
    return assign, mnormal, moffset


def _sets_within(a: np.ndarray, b: np.ndarray, gap: float) -> bool:
    """Whether some point of a and some point of b are within ``gap`` metres."""
    from scipy.spatial import cKDTree

    small, large = (a, b) if len(a) <= len(b) else (b, a)
    d, _ = cKDTree(large).query(small, k=1, distance_upper_bound=gap)
    return bool(np.isfinite(d).any())
