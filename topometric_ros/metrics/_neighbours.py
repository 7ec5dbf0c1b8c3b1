"""Radius-neighbourhood statistics shared by MME, MPV and MOM, computed for all query points at once.

For every query point q the sources x with ‖x − q‖ < r (strict, as Open3D's radius search) are found and
their count and unbiased covariance are returned. Instead of one radius search per point, the queries are
grouped in small cubes ("chunks"); each chunk gets the sources that can lie within r of its bounding box
(a grid of cells of size r/4, pruned column by column), and the exact neighbour masks and moment sums of the
whole chunk come from two dense matrix products (BLAS). Coordinates are taken relative to the chunk centre
so that E[xxᵀ] − μμᵀ loses no precision. Sources may be weighted points carrying their own scatter (voxel
summaries): the sums then use the parallel-axis rule, which is how the fast approximation reuses this code.
"""
from __future__ import annotations

import numpy as np

from .. import geometry

#: source grid cells per radius (cell size r / _FINE)
_FINE = 4
#: chunk side in source cells (chunk = _CHUNK * r / _FINE)
_CHUNK = 4
#: query rows per dense product (keeps the masks in cache)
_ROWS = 256
#: chunks whose candidate lists are prepared together (bounds temporary memory)
_BATCH = 1024

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
    pts = np.asarray(points, dtype=np.float64)
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


def _ranges_index(starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """Concatenation of arange(s, e) for each (s, e), vectorised."""
    lens = np.maximum(ends - starts, 0)
    total = int(lens.sum())
    if total == 0:
        return np.empty(0, np.int64)
    keep = lens > 0
    starts, lens = starts[keep], lens[keep]
    first = np.cumsum(lens) - lens
    return np.repeat(starts - first, lens) + np.arange(total)


def _moment_features(local: np.ndarray, weight: np.ndarray | None, scatter: np.ndarray | None) -> np.ndarray:
    """(M, 10) columns [w, w·y, Σ(yyᵀ) unique entries] of sources at chunk-local positions y."""
    f = np.empty((len(local), 10))
    w = 1.0 if weight is None else weight
    f[:, 0] = w
    f[:, 1:4] = local * (w if weight is None else weight[:, None])
    for j, (a, b) in enumerate(SYM6):
        f[:, 4 + j] = local[:, a] * local[:, b] * w
    if scatter is not None:
        f[:, 4:] += scatter
    return f


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

    queries (K, 3), sources (M, 3), same frame, metres. Optional per-source weights (point counts) and
    (M, 6) internal scatter make each source a summary of several points (a voxel around its centroid).
    Returns (counts (K,) float, covariances (K, 6) in SYM6 order, m²; zero where the count is below 2).
    """
    q = np.asarray(queries, dtype=np.float64).reshape(-1, 3)
    src = np.asarray(sources, dtype=np.float64).reshape(-1, 3)
    if radius <= 0:
        raise ValueError(f"radius must be positive, got {radius}")
    counts = np.zeros(len(q))
    covs = np.zeros((len(q), 6))
    if len(q) == 0 or len(src) == 0:
        return counts, covs
    r = float(radius)
    h = r / _FINE
    lo = np.minimum(q.min(axis=0), src.min(axis=0))
    # sources sorted by grid cell; a column (x, y) of cells is one run of keys
    cell = np.floor((src - lo) / h).astype(np.int64)
    dims = np.maximum(cell.max(axis=0), np.floor((q.max(axis=0) - lo) / h).astype(np.int64)) + 1
    key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    order = np.argsort(key, kind="stable")
    key = key[order]
    src_s = src[order]
    w_s = None if weights is None else np.asarray(weights, np.float64)[order]
    sc_s = None if scatter is None else np.asarray(scatter, np.float64)[order]
    # queries sorted by chunk
    qcell = np.floor((q - lo) / (h * _CHUNK)).astype(np.int64)
    cdims = qcell.max(axis=0) + 1
    qkey = (qcell[:, 0] * cdims[1] + qcell[:, 1]) * cdims[2] + qcell[:, 2]
    qorder = np.argsort(qkey, kind="stable")
    q_s = q[qorder]
    bounds = np.flatnonzero(np.diff(qkey[qorder])) + 1
    first = np.concatenate(([0], bounds))
    last = np.concatenate((bounds, [len(q)]))
    bmin = np.minimum.reduceat(q_s, first, axis=0)
    bmax = np.maximum.reduceat(q_s, first, axis=0)
    chunk_cell = qcell[qorder][first] * _CHUNK
    stencil = np.arange(-_FINE, _CHUNK + _FINE)
    out = np.empty((len(q), 10))
    for b0 in range(0, len(first), _BATCH):
        sl = slice(b0, b0 + _BATCH)
        idx, offs = _candidates(bmin[sl], bmax[sl], chunk_cell[sl], stencil, lo, h, r, dims, key)
        for j in range(len(offs) - 1):
            rows = slice(first[b0 + j], last[b0 + j])
            cand = idx[offs[j]:offs[j + 1]]
            if len(cand) == 0:
                out[rows] = 0.0
                continue
            centre = 0.5 * (bmin[b0 + j] + bmax[b0 + j])
            local = src_s[cand] - centre
            feats = _moment_features(local, None if w_s is None else w_s[cand],
                                     None if sc_s is None else sc_s[cand])
            bh = np.empty((len(local), 4))
            bh[:, :3] = local
            bh[:, 3] = -0.5 * np.einsum("ij,ij->i", local, local)
            for r0 in range(rows.start, rows.stop, _ROWS):
                r1 = min(r0 + _ROWS, rows.stop)
                a = q_s[r0:r1] - centre
                ah = np.ones((len(a), 4))
                ah[:, :3] = a
                # ‖a − b‖² < r²  <=>  a·b − ‖b‖²/2 > ‖a‖²/2 − r²/2; the mask is written as 0.0 / 1.0 in place
                g = ah @ bh.T
                np.greater(g, (0.5 * np.einsum("ij,ij->i", a, a) - 0.5 * r * r)[:, None], out=g)
                out[r0:r1] = g @ feats
    n, cov = _covariances(out)
    counts[qorder] = n
    covs[qorder] = cov
    return counts, covs


def _candidates(bmin, bmax, chunk_cell, stencil, lo, h, r, dims, key):
    """Source indices (sorted order) that may lie within r of each chunk's box, as one index array and
    per-chunk offsets. Cells are pruned per (x, y) column by the exact box distance."""
    gx = chunk_cell[:, 0, None] + stencil[None, :]  # (C, S)
    gy = chunk_cell[:, 1, None] + stencil[None, :]
    dx = np.maximum(np.maximum(lo[0] + gx * h - bmax[:, 0, None], bmin[:, 0, None] - (lo[0] + (gx + 1) * h)), 0)
    dy = np.maximum(np.maximum(lo[1] + gy * h - bmax[:, 1, None], bmin[:, 1, None] - (lo[1] + (gy + 1) * h)), 0)
    d2 = dx[:, :, None] ** 2 + dy[:, None, :] ** 2  # (C, S, S)
    inside = ((gx >= 0) & (gx < dims[0]))[:, :, None] & ((gy >= 0) & (gy < dims[1]))[:, None, :] & (d2 <= r * r)
    dz = np.sqrt(np.maximum(r * r - d2, 0.0))
    z0 = np.floor((bmin[:, 2, None, None] - dz - lo[2]) / h).astype(np.int64)
    z1 = np.floor((bmax[:, 2, None, None] + dz - lo[2]) / h).astype(np.int64)
    z0 = np.clip(z0, 0, dims[2])
    z1 = np.clip(z1 + 1, 0, dims[2])
    base = (gx[:, :, None] * dims[1] + gy[:, None, :]) * dims[2]
    s = np.searchsorted(key, (base + z0)[inside])
    e = np.searchsorted(key, (base + z1)[inside])
    lens = np.zeros(inside.shape, np.int64)
    lens[inside] = e - s
    offs = np.concatenate(([0], np.cumsum(lens.reshape(len(bmin), -1).sum(axis=1))))
    return _ranges_index(s, e), offs


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
    counts, covs = ball_covariances(centres[used], centres, radius, weights, scatter)
    return counts, covs, query_weight[used]
