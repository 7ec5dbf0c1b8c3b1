"""Co-Plane Variance (CPV): how thick the same physical plane looks when the window's scans are stacked.

Input: per plane, already in the WINDOW frame: class id, scan index, unit normal (oriented toward its own
sensor), inlier count, mean and scatter Σ (x − mean)(x − mean)ᵀ over ALL inliers (planes.Plane's exact
sufficient statistics, so no point is touched here).

Co-plane graph (paper Eq. 10): planes i, j of DIFFERENT scans are joined when they have the same class,
nᵢ·nⱼ ≥ cos(``angle_deg``) (same side: the normals are oriented toward the sensor, so the two faces of a
thin wall never join) and |Dⱼ − Dᵢ| < ``epsilon`` with D = −n·mean the offset in n·x + D = 0.
Maximal cliques (Bron–Kerbosch with pivoting) are the co-plane candidates. Each plane counts in ONE group:
cliques are taken largest first (ties: more inlier points); a later clique loses the planes already taken
and is kept while it still spans ≥ 2 scans (what remains of a clique is still a clique).

Per group: pooled covariance of all its points, C = (Σ Sₖ + Σ cₖ (mₖ − m)(mₖ − m)ᵀ) / Σ cₖ (parallel-axis
theorem, population form), and λ_min(C), the variance along the common normal (m²). CPV = point-weighted
mean of λ_min over groups. Expected value for K equal-sized scans of one plane with per-point noise σ along
the normal and per-scan offset noise τ: σ² + τ²·(K − 1)/K.

Defaults: angle 10°, ε 0.3 m: per-pose translation noise of σ_t = 0.1 m (the noise experiment at scale 2)
gives offset differences of σ ≈ 0.14 m, and 0.3 m keeps such a plane in its group; walls of the
simulated scenes that face the same way are much farther apart than that.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

ANGLE_DEG = 10.0  # largest angle between normals of co-planar planes
EPSILON = 0.3  # m, largest |D2 − D1| of co-planar planes


@dataclass
class CoPlaneGroup:
    """Members (plane indices), total inlier count, λ_min of the pooled covariance (m²), common normal."""

    members: np.ndarray
    count: float
    variance: float
    normal: np.ndarray


def coplane_graph(classes, scans, normals, offsets, angle_deg: float = ANGLE_DEG, epsilon: float = EPSILON
                  ) -> np.ndarray:
    """(M, M) bool adjacency of the co-plane graph (no self loops)."""
    classes, scans = np.asarray(classes), np.asarray(scans)
    normals, offsets = np.asarray(normals, np.float64), np.asarray(offsets, np.float64)
    return ((classes[:, None] == classes[None, :]) & (scans[:, None] != scans[None, :])
            & (normals @ normals.T >= math.cos(math.radians(angle_deg)))
            & (np.abs(offsets[:, None] - offsets[None, :]) < epsilon))


def _bits(mask: int):
    while mask:
        low = mask & -mask
        yield low.bit_length() - 1
        mask ^= low


def maximal_cliques(adjacency: np.ndarray) -> list[int]:
    """Maximal cliques (as int bitmasks over vertex indices) of a symmetric bool adjacency with ≥ 2 vertices:
    Bron–Kerbosch with pivoting (Tomita). Isolated vertices give no clique."""
    adj = [sum(1 << int(j) for j in np.flatnonzero(row)) for row in adjacency]
    out: list[int] = []

    def expand(r: int, p: int, x: int) -> None:
        if not p:
            if not x:
                out.append(r)
            return
        pivot = max(_bits(p | x), key=lambda u: (p & adj[u]).bit_count())
        for v in _bits(p & ~adj[pivot]):
            expand(r | (1 << v), p & adj[v], x & adj[v])
            p &= ~(1 << v)
            x |= 1 << v

    expand(0, sum(1 << i for i, a in enumerate(adj) if a), 0)
    return out


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
    cliques = maximal_cliques(coplane_graph(classes, scans, normals, offsets, angle_deg, epsilon))
    members = [np.fromiter(_bits(c), int) for c in cliques]
    order = sorted(range(len(cliques)), key=lambda k: (-len(members[k]), -counts[members[k]].sum(), k))
    taken = np.zeros(len(counts), bool)
    groups = []
    for k in order:
        m = members[k][~taken[members[k]]]
        if len(np.unique(scans[m])) < 2:
            continue
        taken[m] = True
        _, cov = pooled_covariance(counts[m], means[m], scatters[m])
        vals, vecs = np.linalg.eigh(cov)
        groups.append(CoPlaneGroup(m, float(counts[m].sum()), float(max(vals[0], 0.0)), vecs[:, 0]))
    return groups


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
