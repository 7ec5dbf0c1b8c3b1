"""Radius-neighbourhood statistics shared by MME, MPV and MOM, computed for all query points at once.

For every query point q the sources x with ‖x − q‖ < r (strict, as Open3D's radius search) are found and
their count and unbiased covariance are returned. Sources are sorted into vertical columns of side r/2 and
by z inside each column. The queries of one column cell (a cube of side r/2) share their candidates: the
runs of the 25 neighbouring columns whose z lies within reach of the cell's queries, gathered once into
contiguous buffers; each query then sums the moments of the candidates inside its ball in one vectorised
pass (a compiled numba kernel, single thread, GIL released). Moments are taken about the query point
itself (offsets ≤ r), so E[yyᵀ] − μμᵀ loses no precision far from the origin. Sources may be weighted
points carrying their own scatter (voxel summaries): the sums then use the parallel-axis rule, which is how
the fast approximation reuses this code.
"""
from __future__ import annotations

import math

import numba
import numpy as np

from .. import geometry

#: column side in radii (1/_DIV): 2 measured fastest on map-metrics' depth data and on VLP-32 windows
_DIV = 2

#: voxel grid offset in voxel units (see voxel_moments)
_GRID_PHASE = 0.3819660112501051

#: index pairs of the 6 unique entries of a symmetric 3×3 matrix, in the order xx, xy, xz, yy, yz, zz
SYM6 = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def aggregate_map(clouds, poses) -> np.ndarray:
    """Sensor-frame clouds (N_i, 3) with (K, 4, 4) sensor-to-map poses -> (ΣN_i, 3) float64 points in the
    frame of the FIRST cloud (T_rel,i = T_1⁻¹ T_i), as map-metrics' aggregate_map."""
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"poses must be (K, 4, 4), got {poses.shape}")
    if len(clouds) != len(poses):
        raise ValueError(f"{len(clouds)} clouds but {len(poses)} poses")
    if len(clouds) == 0:
        return np.empty((0, 3))
    rel = geometry.relative_to_first(poses)
    parts = []
    for cloud, t in zip(clouds, rel):
        pts = np.asarray(cloud, dtype=np.float64).reshape(-1, 3)
        parts.append(geometry.transform_points(t, pts))
    return np.concatenate(parts)


def to_matrix(cov6: np.ndarray) -> np.ndarray:
    """(K, 6) unique entries -> (K, 3, 3) symmetric matrices."""
    out = np.empty(cov6.shape[:-1] + (3, 3))
    for j, (a, b) in enumerate(SYM6):
        out[..., a, b] = cov6[..., j]
        out[..., b, a] = cov6[..., j]
    return out


def sym_det(c: np.ndarray) -> np.ndarray:
    """Determinants of (K, 6) symmetric 3×3 matrices."""
    xx, xy, xz, yy, yz, zz = c.T
    return xx * (yy * zz - yz * yz) - xy * (xy * zz - yz * xz) + xz * (xy * yz - yy * xz)


def sym_eigvals(c: np.ndarray) -> np.ndarray:
    """Eigenvalues, ascending, of (K, 6) symmetric 3×3 matrices: closed form (trigonometric) plus one
    Newton step on the characteristic polynomial."""
    c = np.asarray(c, dtype=np.float64)
    xx, xy, xz, yy, yz, zz = c.T
    q = (xx + yy + zz) / 3.0
    p1 = xy * xy + xz * xz + yz * yz
    a, b, d = xx - q, yy - q, zz - q
    p2 = a * a + b * b + d * d + 2.0 * p1
    p = np.sqrt(p2 / 6.0)
    safe = np.where(p > 0, p, 1.0)
    det_b = (a * (b * d - yz * yz) - xy * (xy * d - yz * xz) + xz * (xy * yz - b * xz)) / safe**3
    phi = np.arccos(np.clip(det_b / 2.0, -1.0, 1.0)) / 3.0
    lam = np.stack([q + 2 * p * np.cos(phi + 2 * np.pi / 3), q + 2 * p * np.cos(phi + 4 * np.pi / 3),
                    q + 2 * p * np.cos(phi)], axis=-1)
    # Newton polish on det(A − λI) = −λ³ + tr λ² − c2 λ + det
    tr = 3 * q
    c2 = xx * yy + xx * zz + yy * zz - p1
    det = sym_det(c)
    for _ in range(1):
        f = ((-lam + tr[:, None]) * lam - c2[:, None]) * lam + det[:, None]
        df = (-3 * lam + 2 * tr[:, None]) * lam - c2[:, None]
        ok = np.abs(df) > 1e-12 * np.maximum(np.abs(tr[:, None]) ** 2, 1e-300)
        lam = np.where(ok, lam - f / np.where(ok, df, 1.0), lam)
    return np.sort(lam, axis=-1)


def voxel_moments(points: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Summaries of the points in each cubic voxel of side ``size`` (m).

    Returns (centroids (V, 3), counts (V,), scatter (V, 6) Σ (x − c)(x − c)ᵀ, voxel index of each point (N,)).
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:  # a map whose scans kept no points: no voxel
        return np.zeros((0, 3)), np.zeros(0), np.zeros((0, 6)), np.zeros(0, np.int64)
    # boundaries at (k + 0.382) · size: off the round coordinates (planes at z = −1.0 m, ...), so a
    # rounding-level change of the points does not move them across
    cell = np.floor(pts / size - _GRID_PHASE).astype(np.int64)
    cell -= cell.min(axis=0)
    dims = cell.max(axis=0) + 1
    key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    v = len(counts)
    centres = np.stack([np.bincount(inverse, pts[:, j], v) for j in range(3)], axis=1) / counts[:, None]
    local = pts - centres[inverse]
    scatter = np.stack([np.bincount(inverse, local[:, a] * local[:, b], v) for a, b in SYM6], axis=1)
    return centres, counts.astype(np.float64), scatter, inverse


def _covariances(sums: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K, 10) moment sums -> (counts (K,), unbiased covariances (K, 6)); zero where count < 2."""
    n = sums[:, 0]
    ok = n > 1
    nn = np.where(ok, n, 2.0)
    s1 = sums[:, 1:4]
    cov = np.empty((len(sums), 6))
    for j, (a, b) in enumerate(SYM6):
        cov[:, j] = (sums[:, 4 + j] - s1[:, a] * s1[:, b] / nn) / (nn - 1)
    cov[~ok] = 0.0
    return n, cov


def ball_covariances(queries: np.ndarray, sources: np.ndarray, radius: float, weights: np.ndarray | None = None,
                     scatter: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Count and unbiased covariance of the sources within ``radius`` (strict <) of each query point.

    queries (K, 3), sources (M, 3), same frame, metres, finite. Optional per-source weights (point counts)
    and (M, 6) internal scatter make each source a summary of several points (a voxel around its centroid).
    Returns (counts (K,) float, covariances (K, 6) in SYM6 order, m²; zero where the count is below 2).
    """
    same = queries is sources  # sorted once
    q = np.asarray(queries, dtype=np.float64).reshape(-1, 3)
    src = q if same else np.asarray(sources, dtype=np.float64).reshape(-1, 3)
    if radius <= 0:
        raise ValueError(f"radius must be positive, got {radius}")
    sums = np.zeros((len(q), 10))
    if len(q) and len(src):
        sums = _ball_sums(q, src, weights, scatter, float(radius), same)
    return _covariances(sums)


def _column_sort(points, lo, h, dims1):
    """Order that sorts points by column (x, y cells of side h), then z; the sorted column keys' distinct
    values, the first index of each (plus the end), and each sorted point's z cell."""
    cell = np.floor((points - lo) / h).astype(np.int64)
    column = cell[:, 0] * dims1 + cell[:, 1]
    order = np.lexsort((points[:, 2], column))
    column = column[order]
    starts = np.flatnonzero(np.diff(column)) + 1
    first = np.concatenate(([0], starts, [len(column)]))
    return order, column[first[:-1]], first, np.ascontiguousarray(cell[order, 2])


def _stencil(h, r):
    """Neighbouring columns (dx, dy) that can hold a point within r of a column, and for each the z reach
    (m) that a point of one column can have to a point of the other (plus a rounding margin)."""
    div = int(math.ceil(r / h))
    ox, oy, reach = [], [], []
    for dx in range(-div, div + 1):
        for dy in range(-div, div + 1):
            mx, my = max(abs(dx) - 1, 0) * h, max(abs(dy) - 1, 0) * h
            if mx * mx + my * my < r * r:
                ox.append(dx)
                oy.append(dy)
                reach.append(math.sqrt(r * r - mx * mx - my * my) * (1 + 1e-12) + 1e-12 * r)
    return np.array(ox, np.int64), np.array(oy, np.int64), np.array(reach)


def _ball_sums(q, src, w, sc, r, same) -> np.ndarray:
    """(K, 10) moment sums [n, Σy, Σyyᵀ (SYM6)] of the sources within r of each query, y = source − query
    (weighted: n = Σw, Σw·y, Σ(w·yyᵀ + scatter))."""
    h = r / _DIV
    lo = np.minimum(q.min(axis=0), src.min(axis=0))
    dims1 = int(np.floor((max(q[:, 1].max(), src[:, 1].max()) - lo[1]) / h)) + 1
    sorted_sources = _column_sort(src, lo, h, dims1)
    order, columns, first, _ = sorted_sources
    qorder, qcolumns, qfirst, qcell_z = sorted_sources if same else _column_sort(q, lo, h, dims1)
    x, y, z = (np.ascontiguousarray(src[order, a]) for a in range(3))
    qx, qy, qz = (np.ascontiguousarray(q[qorder, a]) for a in range(3))
    weighted = w is not None or sc is not None
    if weighted:
        ww = np.ones(len(src)) if w is None else np.asarray(w, np.float64)[order]
        ss = np.ascontiguousarray((np.zeros((len(src), 6)) if sc is None else np.asarray(sc, np.float64)[order]).T)
    else:
        ww, ss = np.ones(1), np.zeros((6, 1))
    ox, oy, reach = _stencil(h, r)
    out = np.empty((10, len(q)))
    _kernel(qx, qy, qz, qcell_z, qcolumns, qfirst, x, y, z, ww, ss, weighted, columns, first, dims1, ox, oy,
            reach, r, out)
    sums = np.empty((len(q), 10))
    sums[qorder] = out.T
    return sums


@numba.njit(cache=True, nogil=True, fastmath=True)
def _moments(bx, by, bz, n, xi, yi, zi, r2):
    """Sums [count, Σd, Σddᵀ] over the n buffered candidates with ‖d‖² < r2, d = candidate − (xi, yi, zi)."""
    s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = s8 = s9 = 0.0
    for t in range(n):
        dx, dy, dz = bx[t] - xi, by[t] - yi, bz[t] - zi
        m = 1.0 if dx * dx + dy * dy + dz * dz < r2 else 0.0
        mx, my, mz = m * dx, m * dy, m * dz
        s0 += m
        s1 += mx
        s2 += my
        s3 += mz
        s4 += mx * dx
        s5 += mx * dy
        s6 += mx * dz
        s7 += my * dy
        s8 += my * dz
        s9 += mz * dz
    return s0, s1, s2, s3, s4, s5, s6, s7, s8, s9


@numba.njit(cache=True, nogil=True, fastmath=True)
def _weighted_moments(bx, by, bz, bw, bs, n, xi, yi, zi, r2):
    """As _moments, each candidate weighted by bw and carrying its own scatter bs (6, n)."""
    s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = s8 = s9 = 0.0
    for t in range(n):
        dx, dy, dz = bx[t] - xi, by[t] - yi, bz[t] - zi
        inside = 1.0 if dx * dx + dy * dy + dz * dz < r2 else 0.0
        m = inside * bw[t]
        mx, my, mz = m * dx, m * dy, m * dz
        s0 += m
        s1 += mx
        s2 += my
        s3 += mz
        s4 += mx * dx + inside * bs[0, t]
        s5 += mx * dy + inside * bs[1, t]
        s6 += mx * dz + inside * bs[2, t]
        s7 += my * dy + inside * bs[3, t]
        s8 += my * dz + inside * bs[4, t]
        s9 += mz * dz + inside * bs[5, t]
    return s0, s1, s2, s3, s4, s5, s6, s7, s8, s9


@numba.njit(cache=True, nogil=True)
def _grow(buf, n, need):
    """buf with room for ``need`` entries along its last axis, its first n kept."""
    if buf.shape[-1] >= need:
        return buf
    bigger = np.empty(buf.shape[:-1] + (2 * need,))
    bigger[..., :n] = buf[..., :n]
    return bigger


@numba.njit(cache=True, nogil=True, fastmath=True)
def _kernel(qx, qy, qz, qcell_z, qcolumns, qfirst, x, y, z, w, sc, weighted, columns, first, dims1, ox, oy,
            reach, r, out):
    """out (10, K): moment sums of each query (sorted as _column_sort) over the sources (sorted likewise)."""
    ns = len(ox)
    lo_p = np.zeros(ns, np.int64)  # per neighbouring column: first candidate, end of candidates, column end
    hi_p = np.zeros(ns, np.int64)
    end_p = np.zeros(ns, np.int64)
    bx, by, bz = np.empty(4096), np.empty(4096), np.empty(4096)
    bw, bs = np.empty(4096 if weighted else 1), np.empty((6, 4096 if weighted else 1))
    for c in range(len(qcolumns)):
        cx, cy = qcolumns[c] // dims1, qcolumns[c] % dims1
        for k in range(ns):
            lo_p[k] = hi_p[k] = end_p[k] = 0
            if 0 <= cy + oy[k] < dims1 and cx + ox[k] >= 0:
                key = (cx + ox[k]) * dims1 + cy + oy[k]
                j = np.searchsorted(columns, key)
                if j < len(columns) and columns[j] == key:
                    lo_p[k] = hi_p[k] = first[j]
                    end_p[k] = first[j + 1]
        i0 = qfirst[c]
        while i0 < qfirst[c + 1]:  # the queries of one column cell, in z order
            i1 = i0 + 1
            while i1 < qfirst[c + 1] and qcell_z[i1] == qcell_z[i0]:
                i1 += 1
            n = 0
            for k in range(ns):  # candidates: sources with z in reach of the cell's queries
                a, e = lo_p[k], end_p[k]
                while a < e and z[a] < qz[i0] - reach[k]:
                    a += 1
                b = max(hi_p[k], a)
                while b < e and z[b] <= qz[i1 - 1] + reach[k]:
                    b += 1
                lo_p[k], hi_p[k] = a, b
                bx, by, bz = _grow(bx, n, n + b - a), _grow(by, n, n + b - a), _grow(bz, n, n + b - a)
                bx[n:n + b - a] = x[a:b]
                by[n:n + b - a] = y[a:b]
                bz[n:n + b - a] = z[a:b]
                if weighted:
                    bw, bs = _grow(bw, n, n + b - a), _grow(bs, n, n + b - a)
                    bw[n:n + b - a] = w[a:b]
                    bs[:, n:n + b - a] = sc[:, a:b]
                n += b - a
            for i in range(i0, i1):
                if weighted:
                    s = _weighted_moments(bx, by, bz, bw, bs, n, qx[i], qy[i], qz[i], r * r)
                else:
                    s = _moments(bx, by, bz, n, qx[i], qy[i], qz[i], r * r)
                for t in range(10):
                    out[t, i] = s[t]
            i0 = i1


def map_covariances(points: np.ndarray, radius: float, exact: bool = True, max_queries: int | None = None,
                    seed: int = 0, voxel_ratio: float = 0.05) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Neighbourhood count and covariance for the points of an aggregated map (MME / MPV).

    exact=True: every point (or ``max_queries`` points drawn uniformly with ``seed``) is a query against all
    points: exactly map-metrics' neighbourhoods. exact=False: the map is summarised in voxels of side
    ``voxel_ratio · radius``; each voxel's centroid stands for its points, both as query and as source
    (a voxel is inside a ball when its centroid is), which is much faster on dense LiDAR maps.
    Returns (counts (K,), covariances (K, 6), weights (K,)): weights are the number of map points each row
    stands for, so the metric is the weighted mean over rows.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    chosen = None
    if max_queries is not None and len(pts) > max_queries:
        chosen = np.random.default_rng(seed).choice(len(pts), int(max_queries), replace=False)
    if exact:
        queries = pts if chosen is None else pts[chosen]
        counts, covs = ball_covariances(queries, pts, radius)
        return counts, covs, np.ones(len(queries))
    if voxel_ratio <= 0:
        raise ValueError(f"voxel_ratio must be positive, got {voxel_ratio}")
    centres, weights, scatter, voxel_of = voxel_moments(pts, voxel_ratio * radius)
    query_weight = weights if chosen is None else np.bincount(voxel_of[chosen], minlength=len(weights)).astype(float)
    used = query_weight > 0
    queries = centres if used.all() else centres[used]  # the same array: each pair is found once
    counts, covs = ball_covariances(queries, centres, radius, weights, scatter)
    return counts, covs, query_weight[used]
