"""Radius-neighbourhood statistics shared by MME, MPV and MOM, computed for all query points at once.

For every query point q the sources x with ‖x − q‖ < r (strict, as Open3D's radius search) are found and
their count and unbiased covariance are returned. Instead of one radius search per point, the queries are
grouped in small cubes ("chunks", side r); each chunk gets the sources that can lie within r of its bounding
box (a grid of columns of side r/4, pruned column by column), and the exact neighbour masks and moment sums
of the whole chunk come from dense matrix products (BLAS). When the queries are the sources (MME, MPV),
a chunk meets only its own and the later chunks' points and every pair is added to both of its ends, so
each unordered pair is tested once. The mask columns are computed once per point, about the centre of the
queries' box (boxes wider than _TILE radii are halved first, which bounds their rounding); the moment sums
are taken about each query's chunk centre, so that E[xxᵀ] − μμᵀ loses no precision. Sources may be
weighted points carrying their own scatter (voxel summaries): the sums then use the parallel-axis rule,
which is how the fast approximation reuses this code.
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
#: chunks whose candidate runs are found together
_BATCH = 256
#: most candidate indices held at once, and most mask elements per dense product (bound the memory)
_MAX_INDEX = 1 << 23
_MAX_ELEMENTS = 1 << 21

#: widest query box (in radii) summed about one origin (see _tile_sums)
_TILE = 256

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
    same = queries is sources  # every pair is then found once and counted at both ends
    q = np.asarray(queries, dtype=np.float64).reshape(-1, 3)
    src = q if same else np.asarray(sources, dtype=np.float64).reshape(-1, 3)
    if radius <= 0:
        raise ValueError(f"radius must be positive, got {radius}")
    w = None if weights is None else np.asarray(weights, np.float64)
    sc = None if scatter is None else np.asarray(scatter, np.float64)
    sums = np.zeros((len(q), 10))
    if len(q) and len(src):
        _tile_sums(q, src, w, sc, float(radius), sums, same)
    n, cov = _covariances(sums)
    return n, cov


def _tile_sums(q, src, w, sc, r, out, same=False) -> None:
    """Moment sums of the sources within r of each query, into out (K, 10), each about the centre of its
    query's chunk. The masks are computed about the centre of the queries' box; boxes wider than _TILE radii
    are halved first, which bounds their rounding (about eps · (_TILE / 2)² of r²)."""
    qlo, qhi = q.min(axis=0), q.max(axis=0)
    axis = int(np.argmax(qhi - qlo))
    if same and qhi[axis] - qlo[axis] <= _TILE * r:
        origin = 0.5 * (qlo + qhi)
        out[:] = _self_sums(q - origin, w, sc, r)
        return
    near = np.all((src > qlo - r) & (src < qhi + r), axis=1)
    if not near.any():
        return
    if not near.all():
        src = src[near]
        w = None if w is None else w[near]
        sc = None if sc is None else sc[near]
    if qhi[axis] - qlo[axis] > _TILE * r:
        left = q[:, axis] < 0.5 * (qlo[axis] + qhi[axis])
        for part in (left, ~left):
            sub = np.zeros((int(part.sum()), 10))
            _tile_sums(q[part], src, w, sc, r, sub)
            out[part] = sub
        return
    origin = 0.5 * (qlo + qhi)
    out[:] = _centred_sums(q - origin, src - origin, w, sc, r)


def _grid(points, r):
    """Fine grid of the points (origin, cell indices (N, 3), dims) and the column-major cell keys."""
    h = r / _FINE
    lo = points.min(axis=0)
    cell = np.floor((points - lo) / h).astype(np.int64)
    dims = cell.max(axis=0) + 1
    return lo, cell, dims, (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]


def _column_z_keys(points, lo, cell, dims, r):
    """Float keys column · span + (z − lo_z + 2r) that sort the points by grid column, then by z (so also by
    cell key), with span > every z range a query asks for; and the margin that covers their rounding."""
    span = float(points[:, 2].max() - lo[2]) + 4 * r
    keys = (cell[:, 0] * dims[1] + cell[:, 1]) * span + (points[:, 2] - lo[2] + 2 * r)
    return keys, span, 8 * float(np.spacing(np.abs(keys).max())) + 1e-9 * r


def _mask_rows(pts, r):
    """(N, 5) mask rows [a, 1, r²/2 − ‖a‖²/2]: with a mask column, > 0 exactly when ‖a − b‖ < r."""
    rows = np.empty((len(pts), 5))
    rows[:, :3] = pts
    rows[:, 3] = 1.0
    rows[:, 4] = 0.5 * r * r - 0.5 * np.einsum("ij,ij->i", pts, pts)
    return rows


def _mask_columns(pts, w, sc):
    """(5, N) mask columns [b, −‖b‖²/2, 1] (one per point, stored as rows so that a gather of candidates
    is row-contiguous), then the source weight and scatter when given ((12, N))."""
    cols = np.empty((5 if w is None and sc is None else 12, len(pts)))
    cols[:3] = pts.T
    cols[3] = -0.5 * np.einsum("ij,ij->i", pts, pts)
    cols[4] = 1.0
    if len(cols) > 5:
        cols[5] = 1.0 if w is None else w
        cols[6:] = 0.0 if sc is None else sc.T
    return cols


def _local_features(cols, centre):
    """(10, n) moment features [w, w·y, w·yyᵀ (+ scatter) unique entries] of gathered mask columns (see
    _mask_columns) at y = b − centre."""
    f = np.empty((10, cols.shape[1]))
    local = np.subtract(cols[:3], centre[:, None], out=f[1:4])
    np.multiply(local, local[0], out=f[4:7])  # SYM6 order: xx, xy, xz, yy, yz, zz
    np.multiply(local[1:], local[1], out=f[7:9])
    np.multiply(local[2], local[2], out=f[9])
    if len(cols) == 5:
        f[0] = 1.0
        return f
    f[0] = cols[5]
    f[1:] *= cols[5]
    f[4:] += cols[6:]
    return f


def _shift_sums(sums, e):
    """Moment sums (K, 10) about a centre c -> about c − d, in place; each row its own d, given as the three
    coordinate arrays e (K,). Column by column: fastest with column-major sums."""
    s0 = sums[:, 0]
    s1 = [sums[:, 1 + a] for a in range(3)]
    s0e = [s0 * e[a] for a in range(3)]
    for j, (a, b) in enumerate(SYM6):
        sums[:, 4 + j] += s1[a] * e[b] + (s1[b] + s0e[b]) * e[a]
    for a in range(3):
        s1[a] += s0e[a]


def _chunks(cell, pts_s):
    """Chunks (cubes of _CHUNK cells) of points: (members: positions of each chunk's points, grouped,
    first, last, chunk cell of each chunk (C, 3) in fine cells, box min, box max)."""
    ccell = cell // _CHUNK
    cdims = ccell.max(axis=0) + 1
    ckey = (ccell[:, 0] * cdims[1] + ccell[:, 1]) * cdims[2] + ccell[:, 2]
    members = np.argsort(ckey, kind="stable")
    bounds = np.flatnonzero(np.diff(ckey[members])) + 1
    first = np.concatenate(([0], bounds))
    last = np.concatenate((bounds, [len(ckey)]))
    grouped = pts_s[members]
    return (members, first, last, ccell[members[first]] * _CHUNK, np.minimum.reduceat(grouped, first, axis=0),
            np.maximum.reduceat(grouped, first, axis=0))


def _centred_sums(q, src, w, sc, r) -> np.ndarray:
    """(K, 10) moment sums of the sources within r of each query (about its chunk's centre); coordinates
    near the origin."""
    h = r / _FINE
    lo = np.minimum(q.min(axis=0), src.min(axis=0))
    # sources sorted by grid cell; a column (x, y) of cells is one run of keys
    cell = np.floor((src - lo) / h).astype(np.int64)
    dims = np.maximum(cell.max(axis=0), np.floor((q.max(axis=0) - lo) / h).astype(np.int64)) + 1
    key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    order = np.argsort(key, kind="stable")
    key = key[order]
    cols = _mask_columns(src[order], None if w is None else w[order], None if sc is None else sc[order])
    members, first, last, chunk_cell, bmin, bmax = _chunks(np.floor((q - lo) / h).astype(np.int64), q)
    rows = _mask_rows(q[members], r)
    stencil = np.arange(-_FINE, _CHUNK + _FINE)
    out = np.empty((len(q), 10))
    for b0 in range(0, len(first), _BATCH):
        b1 = min(b0 + _BATCH, len(first))
        starts, ends, per_chunk = _candidate_ranges(bmin[b0:b1], bmax[b0:b1], chunk_cell[b0:b1], stencil, lo, h,
                                                    r, dims, key)
        range_offs = np.concatenate(([0], np.cumsum(per_chunk[1])))
        # index arrays for groups of chunks holding at most _MAX_INDEX candidates together
        c0 = 0
        while c0 < b1 - b0:
            total = np.cumsum(per_chunk[0][c0:])
            c1 = c0 + max(1, int(np.searchsorted(total, _MAX_INDEX, side="right")))
            idx = _ranges_index(starts[range_offs[c0]:range_offs[c1]], ends[range_offs[c0]:range_offs[c1]])
            offs = np.concatenate(([0], total[:c1 - c0]))
            for j in range(c1 - c0):
                c = b0 + c0 + j
                _chunk_moments(rows[first[c]:last[c]], cols, idx[offs[j]:offs[j + 1]], 0.5 * (bmin[c] + bmax[c]),
                               out[first[c]:last[c]])
            c0 = c1
    sums = np.empty_like(out)
    sums[members] = out
    return sums


def _chunk_moments(rows, cols, cand, centre, out) -> None:
    """Moment sums (about centre) of the candidates within r of each query row of one chunk, into out."""
    if len(cand) == 0:
        out[:] = 0.0
        return
    c = np.take(cols, cand, axis=1)
    b, f = c[:5], _local_features(c, centre).T
    step = max(8, min(_ROWS, _MAX_ELEMENTS // len(cand)))
    for r0 in range(0, len(rows), step):
        g = rows[r0:r0 + step] @ b
        np.greater(g, 0.0, out=g)  # the mask, as 0.0 / 1.0 in place
        out[r0:r0 + step] = g @ f


def _self_sums(pts, w, sc, r) -> np.ndarray:
    """(N, 10) moment sums of the points within r of each point (the sources are the queries), each about
    its chunk's centre: a chunk meets its own points and the later chunks' points once, and each pair is
    added to both of its ends."""
    lo, cell, dims, key = _grid(pts, r)
    zkey = _column_z_keys(pts, lo, cell, dims, r)
    order = np.argsort(zkey[0], kind="stable")
    key = key[order]
    zkey = (zkey[0][order],) + zkey[1:]
    pts_s = pts[order]
    rows = _mask_rows(pts_s, r)
    cols = _mask_columns(pts_s, None if w is None else w[order], None if sc is None else sc[order])
    members, first, last, chunk_cell, bmin, bmax = _chunks(cell[order], pts_s)
    centres = 0.5 * (bmin + bmax)
    centre_of = np.empty((3, len(pts)))  # of each point's chunk, in key order
    centre_of[:, members] = np.repeat(centres, last - first, axis=0).T
    position = np.empty_like(members)
    position[members] = np.arange(len(members))
    stencil = np.arange(-_FINE, _CHUNK + _FINE)
    h = r / _FINE
    sums = np.zeros((len(pts), 10))  # in members order
    for b0 in range(0, len(first), _BATCH):
        b1 = min(b0 + _BATCH, len(first))
        starts, ends, (per_chunk, _) = _candidate_ranges(bmin[b0:b1], bmax[b0:b1], chunk_cell[b0:b1], stencil, lo,
                                                         h, r, dims, key, later_only=True, zkey=zkey)
        later = _ranges_index(starts, ends)
        back = np.empty((len(later), 10), order="F")  # contiguous columns for the shift and bincount
        offs = np.concatenate(([0], np.cumsum(per_chunk)))
        for j in range(b1 - b0):
            c = b0 + j
            _pair_moments(rows, cols, members[first[c]:last[c]], later[offs[j]:offs[j + 1]], centres[c],
                          sums[first[c]:last[c]], back[offs[j]:offs[j + 1]])
        # the later points' sums are about the meeting chunk's centre: move them to their own chunk's
        _shift_sums(back, [np.repeat(centres[b0:b1, a], per_chunk) - np.take(centre_of[a], later) for a in range(3)])
        if len(later):
            later = position[later]
            p0 = int(later.min())
            later -= p0
            span = int(later.max()) + 1
            for k in range(10):
                sums[p0:p0 + span, k] += np.bincount(later, back[:, k], minlength=span)
    out = np.empty_like(sums)
    out[order[members]] = sums
    return out


def _pair_moments(rows, cols, own, later, centre, own_out, later_out) -> None:
    """Moments (about centre) of the pairs (own point, own or later point) within r: own_out is added each
    own point's sums (own and later partners), later_out is set to each later point's sums over the own
    partners."""
    n0 = len(own)
    c = np.take(cols, np.concatenate((own, later)), axis=1)
    ft = _local_features(c, centre)
    b, f = c[:5], ft.T
    step = max(8, min(_ROWS, _MAX_ELEMENTS // c.shape[1]))
    if n0 <= step:  # one block (the common case)
        g = np.take(rows, own, axis=0) @ b
        np.greater(g, 0.0, out=g)
        own_out += (ft @ g.T).T  # faster than g @ ft.T
        if later_out.flags.f_contiguous:
            np.matmul(ft[:, :n0], g[:, n0:], out=later_out.T)
        else:
            later_out[:] = g[:, n0:].T @ f[:n0]
        return
    later_out[:] = 0.0
    for r0 in range(0, n0, step):
        r1 = min(r0 + step, n0)
        g = np.take(rows, own[r0:r1], axis=0) @ b
        np.greater(g, 0.0, out=g)  # the mask, as 0.0 / 1.0 in place
        own_out[r0:r1] += g @ f
        if len(later):
            later_out += g[:, n0:].T @ f[r0:r1]


def _candidate_ranges(bmin, bmax, chunk_cell, stencil, lo, h, r, dims, key, later_only=False, zkey=None):
    """Runs [start, end) of sorted sources that may lie within r of each chunk's box: one run per (x, y)
    column of cells, pruned by the exact box distance (to whole cells in z, or to the points' z when the
    sources are sorted by z in each column and zkey = (column, z) keys, see _column_z_keys). later_only
    keeps the sources of later chunks only. Returns (starts, ends, (candidates per chunk, runs per chunk)),
    runs in chunk order."""
    gx = chunk_cell[:, 0, None] + stencil[None, :]  # (C, S)
    gy = chunk_cell[:, 1, None] + stencil[None, :]
    dx = np.maximum(np.maximum(lo[0] + gx * h - bmax[:, 0, None], bmin[:, 0, None] - (lo[0] + (gx + 1) * h)), 0)
    dy = np.maximum(np.maximum(lo[1] + gy * h - bmax[:, 1, None], bmin[:, 1, None] - (lo[1] + (gy + 1) * h)), 0)
    d2 = dx[:, :, None] ** 2 + dy[:, None, :] ** 2  # (C, S, S)
    inside = ((gx >= 0) & (gx < dims[0]))[:, :, None] & ((gy >= 0) & (gy < dims[1]))[:, None, :] & (d2 <= r * r)
    dz = np.sqrt(np.maximum(r * r - d2, 0.0))
    z0 = np.clip(np.floor((bmin[:, 2, None, None] - dz - lo[2]) / h).astype(np.int64), 0, dims[2])
    z1 = np.clip(np.floor((bmax[:, 2, None, None] + dz - lo[2]) / h).astype(np.int64) + 1, 0, dims[2])
    if later_only:  # only the points of later chunks (chunk keys are column-major too)
        cx, cy = (gx // _CHUNK)[:, :, None], (gy // _CHUNK)[:, None, :]
        ox, oy = (chunk_cell[:, 0] // _CHUNK)[:, None, None], (chunk_cell[:, 1] // _CHUNK)[:, None, None]
        same = (cx == ox) & (cy == oy)
        inside &= (cx > ox) | ((cx == ox) & (cy > oy)) | same
        z0 = np.where(same, np.maximum(z0, chunk_cell[:, 2, None, None] + _CHUNK), z0)
        z1 = np.maximum(z0, z1)
    base = (gx[:, :, None] * dims[1] + gy[:, None, :]) * dims[2]
    starts = np.searchsorted(key, (base + z0)[inside])
    ends = np.searchsorted(key, (base + z1)[inside])
    if zkey is not None:
        keys, span, margin = zkey
        column = (base // dims[2] * span)[inside]
        z_lo = (bmin[:, 2, None, None] - dz - lo[2] + 2 * r)[inside]  # as in _column_z_keys
        z_hi = (bmax[:, 2, None, None] + dz - lo[2] + 2 * r)[inside]
        starts = np.maximum(starts, np.searchsorted(keys, column + z_lo - margin))
        ends = np.maximum(starts, np.minimum(ends, np.searchsorted(keys, column + z_hi + margin, side="right")))
    chunk_of_run = np.nonzero(inside)[0]
    per_chunk = np.bincount(chunk_of_run, ends - starts, minlength=len(bmin)).astype(np.int64)
    runs = np.bincount(chunk_of_run, minlength=len(bmin))
    return starts, ends, (per_chunk, runs)


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
