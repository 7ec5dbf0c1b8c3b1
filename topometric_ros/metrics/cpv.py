"""Co-Plane Variance (CPV): how thick the same physical plane looks when the window's scans are stacked.

Input: per plane, already in the WINDOW frame: class id, scan index, unit normal (oriented toward its own
sensor), inlier count, mean and scatter Σ (x − mean)(x − mean)ᵀ over ALL inliers (planes.Plane's exact
sufficient statistics, so no point is touched here).

Co-plane graph (paper Eq. 10): planes i, j are joined when they have the same class,
nᵢ·nⱼ ≥ cos(``angle_deg``) (same side: the normals are oriented toward the sensor, so the two faces of a
thin wall never join) and |Dⱼ − Dᵢ| < ``epsilon`` with D = −n·mean the offset in n·x + D = 0.
Planes of the SAME scan are joined by the same test: a wall that a door or pillar splits into s segments
per scan would otherwise make the graph complete K-partite with s^K maximal cliques (millions for a
15-scan window); they are one physical plane anyway. Maximal cliques (Bron–Kerbosch with pivoting,
stopped after ``MAX_CLIQUES`` as a guard) are the co-plane candidates. Each plane counts in ONE group:
cliques are taken largest first (ties: more inlier points); a later clique loses the planes already taken
and is kept while it still spans ≥ 2 scans (what remains of a clique is still a clique). A group must
span at least 2 scans: co-planarity within one rigid scan says nothing about the poses.

Per group: pooled covariance of all its points, C = (Σ Sₖ + Σ cₖ (mₖ − m)(mₖ − m)ᵀ) / Σ cₖ (parallel-axis
theorem, population form), and λ_min(C), the variance along the common normal (m²). CPV = point-weighted
mean of λ_min over groups. Expected value for K equal-sized scans of one plane with per-point noise σ along
the normal and per-scan offset noise τ: σ² + τ²·(K − 1)/K.

Defaults: angle 10°, ε 0.3 m: per-pose translation noise of σ_t = 0.1 m (the noise experiment at scale 2)
gives offset differences of σ ≈ 0.14 m, and 0.3 m keeps such a plane in its group; walls of the
simulated scenes that face the same way are much farther apart than that. Drift larger than ε across
the window (episodes: 0.2 m/s × scale, 2.8 s per 15-scan window) splits a plane's stack into runs of
consecutive scans, each about ε thick, so CPV then saturates around ε²/12 ≈ 0.0075 m² instead of growing;
measured on office1 (15 scans, oracle planes, linear drift 0.2 m/s × scale): 4e-5 m² at scale 0,
8e-4 at 0.25, 3.0e-3 at 0.5, 3.4e-3 at 1, 5.2e-3 at 1.5, 4.8e-3 at 2 — still 100× the clean value.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

ANGLE_DEG = 10.0  # largest angle between normals of co-planar planes
EPSILON = 0.3  # m, largest |D2 − D1| of co-planar planes
MAX_CLIQUES = 20000  # enumeration guard; a real window has a few dozen


@dataclass
class CoPlaneGroup:
    """Members (plane indices), total inlier count, λ_min of the pooled covariance (m²), common normal."""

    members: np.ndarray
    count: float
    variance: float
    normal: np.ndarray


def coplane_graph(classes, normals, offsets, angle_deg: float = ANGLE_DEG, epsilon: float = EPSILON) -> np.ndarray:
    """(M, M) bool adjacency of the co-plane graph (no self loops)."""
    classes = np.asarray(classes)
    normals, offsets = np.asarray(normals, np.float64), np.asarray(offsets, np.float64)
    adj = ((classes[:, None] == classes[None, :]) & (normals @ normals.T >= math.cos(math.radians(angle_deg)))
           & (np.abs(offsets[:, None] - offsets[None, :]) < epsilon))
    np.fill_diagonal(adj, False)
    return adj


def _bits(mask: int):
    while mask:
        low = mask & -mask
        yield low.bit_length() - 1
        mask ^= low


def _row_masks(adjacency: np.ndarray) -> list[int]:
    """Each row of a bool matrix as an int bitmask (bit j = column j)."""
    packed = np.packbits(adjacency, axis=1, bitorder="little")
    return [int.from_bytes(row.tobytes(), "little") for row in packed]


def maximal_cliques(adjacency: np.ndarray, limit: int = MAX_CLIQUES) -> list[int]:
    """Maximal cliques (as int bitmasks over vertex indices) of a symmetric bool adjacency with ≥ 2 vertices:
    Bron–Kerbosch with pivoting (Tomita), per connected component (a component that is a clique is taken
    as it is). Isolated vertices give no clique. Stops after ``limit`` cliques."""
    from scipy.sparse.csgraph import connected_components

    adjacency = np.asarray(adjacency, bool)
    adj = _row_masks(adjacency)
    out: list[int] = []

    def expand(r: int, p: int, x: int) -> None:
        if len(out) >= limit:
            return
        if not p:
            if not x:
                out.append(r)
            return
        pivot = max(_bits(p | x), key=lambda u: (p & adj[u]).bit_count())
        for v in _bits(p & ~adj[pivot]):
            expand(r | (1 << v), p & adj[v], x & adj[v])
            p &= ~(1 << v)
            x |= 1 << v

    if not len(adj):
        return out
    _, component = connected_components(adjacency, directed=False)
    for c in np.unique(component):
        members = np.flatnonzero(component == c)
        if len(members) < 2:
            continue
        mask = sum(1 << int(i) for i in members)
        if adjacency[np.ix_(members, members)].sum() == len(members) * (len(members) - 1):
            out.append(mask)
        else:
            expand(0, mask, 0)
    return out[:limit]


def pooled_covariance(counts, means, scatters) -> tuple[np.ndarray, np.ndarray]:
    """(mean, population covariance) of the union of point sets given by (K,) counts, (K, 3) means and
    (K, 3, 3) scatters."""
    c = np.asarray(counts, np.float64)
    mean = c @ means / c.sum()
    d = means - mean
    return mean, (scatters.sum(axis=0) + (d * c[:, None]).T @ d) / c.sum()


def coplane_groups(classes, scans, normals, means, scatters, counts, angle_deg: float = ANGLE_DEG,
                   epsilon: float = EPSILON) -> list[CoPlaneGroup]:
    """The co-plane groups of a window's planes (see the module docstring), largest clique first."""
    normals, means = np.asarray(normals, np.float64).reshape(-1, 3), np.asarray(means, np.float64).reshape(-1, 3)
    scatters, counts = np.asarray(scatters, np.float64).reshape(-1, 3, 3), np.asarray(counts, np.float64)
    scans = np.asarray(scans)
    offsets = -np.einsum("ij,ij->i", normals, means)
    cliques = maximal_cliques(coplane_graph(classes, normals, offsets, angle_deg, epsilon))
    members = [np.fromiter(_bits(c), int) for c in cliques]
    order = sorted(range(len(cliques)), key=lambda k: (-len(members[k]), -counts[members[k]].sum(), k))
    taken = np.zeros(len(counts), bool)
    chosen = []
    for k in order:
        m = members[k][~taken[members[k]]]
        if len(np.unique(scans[m])) >= 2:
            taken[m] = True
            chosen.append(m)
    if not chosen:
        return []
    vals, vecs = np.linalg.eigh(np.stack([pooled_covariance(counts[m], means[m], scatters[m])[1] for m in chosen]))
    return [CoPlaneGroup(m, float(counts[m].sum()), float(max(v[0], 0.0)), e[:, 0])
            for m, v, e in zip(chosen, vals, vecs)]


MIN_SCAN_PLANES = 3  # a scan with fewer planes is not judged by its agreement (a truncated cloud, a blank view)


def scan_agreement(groups: list[CoPlaneGroup], scans, counts, n_scans: int,
                   min_planes: int = MIN_SCAN_PLANES) -> np.ndarray:
    """(n_scans,) share of each scan's plane inliers that lie in a co-plane group, i.e. on a plane that
    another scan of the window sees in the same place: about 1 when the poses agree (a big plane is seen
    by the neighbouring scans), low for a scan placed off by more than the gates (angle, ε) while the
    others agree with each other (a pose jump, a SLAM that lost track). NaN for a scan with fewer than
    ``min_planes`` planes."""
    counts, scans = np.asarray(counts, np.float64), np.asarray(scans)
    grouped = np.zeros(len(counts), bool)
    for g in groups:
        grouped[g.members] = True
    total = np.bincount(scans, counts, n_scans)
    inside = np.bincount(scans, counts * grouped, n_scans)
    judged = (np.bincount(scans, minlength=n_scans) >= max(min_planes, 1)) & (total > 0)
    return np.divide(inside, total, out=np.full(n_scans, np.nan), where=judged)


def window_agreement(groups: list[CoPlaneGroup], scans, counts, n_scans: int) -> tuple[float, int]:
    """A window's agreement and which scan gives it: the lowest :func:`scan_agreement` of its scans and that
    scan's position. (NaN, −1) without a co-plane group (no two scans share a plane: CPV is undefined and
    says so) or without a judged scan."""
    shares = scan_agreement(groups, scans, counts, n_scans) if groups else np.full(1, np.nan)
    if not np.isfinite(shares).any():
        return float("nan"), -1
    worst = int(np.nanargmin(shares))
    return float(shares[worst]), worst


def cpv_of_groups(groups: list[CoPlaneGroup]) -> float:
    """Point-weighted mean of the groups' λ_min (m²); NaN when there is no group."""
    if not groups:
        return float("nan")
    w = np.array([g.count for g in groups])
    return float(w @ np.array([g.variance for g in groups]) / w.sum())


def cpv(classes, scans, normals, means, scatters, counts, angle_deg: float = ANGLE_DEG,
        epsilon: float = EPSILON) -> float:
    """CPV (m²) of a window's planes given as arrays in the window frame; NaN when no co-plane group exists."""
    return cpv_of_groups(coplane_groups(classes, scans, normals, means, scatters, counts, angle_deg, epsilon))
