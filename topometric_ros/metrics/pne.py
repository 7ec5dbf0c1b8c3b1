"""Plane Normal Entropy (PNE): how much the normals of the same wall direction disagree across a window.

Input: plane normals already in the WINDOW frame (unit, either sign) and their inlier counts.

Clustering (sign-invariant, greedy): take the heaviest unassigned normal as a seed; every unassigned normal
within ``cluster_deg`` of the seed's LINE (|n·seed| ≥ cos) joins its cluster; repeat. A cluster's mean
direction is the principal eigenvector of Σ wᵢ nᵢnᵢᵀ (so n and −n count alike). Clusters of fewer than
``min_planes`` planes carry no spread and are skipped.

Per cluster: each normal, flipped to the mean's side, is written in an orthonormal basis of the mean's
tangent plane (2 coordinates, rad for small angles). Σ = inlier-weighted population covariance of those
coordinates + floor² I (floor = ``floor_deg`` in rad, default 0.1°, so a perfect cluster stays finite), and
h = ½ ln((2πe)² det Σ) (differential entropy of a 2-D Gaussian, nats). PNE = Σ W_c h_c / Σ W_c with W_c
the cluster's inlier count. Only rotations move normals, so PNE ignores translation error exactly.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

CLUSTER_DEG = 15.0  # half-angle of a normal cluster around its seed
FLOOR_DEG = 0.1  # isotropic floor on the tangent spread (deg), keeps h finite
MIN_PLANES = 2  # planes a cluster needs to count


@dataclass
class NormalCluster:
    """One direction cluster: member indices, mean unit direction, 2×2 tangent covariance (rad²),
    entropy h (nats), total inlier weight."""

    members: np.ndarray
    direction: np.ndarray
    covariance: np.ndarray
    entropy: float
    weight: float


def cluster_normals(normals: np.ndarray, weights: np.ndarray, cluster_deg: float = CLUSTER_DEG) -> list[np.ndarray]:
    """Greedy sign-invariant clusters of (M, 3) unit normals: index arrays, heaviest seed first."""
    normals = np.asarray(normals, np.float64)
    cos_max = math.cos(math.radians(cluster_deg))
    free = np.ones(len(normals), bool)
    clusters = []
    for seed in np.argsort(-np.asarray(weights, np.float64), kind="stable"):
        if not free[seed]:
            continue
        members = np.flatnonzero(free & (np.abs(normals @ normals[seed]) >= cos_max))
        free[members] = False
        clusters.append(members)
    return clusters


def tangent_basis(direction: np.ndarray) -> np.ndarray:
    """(2, 3) orthonormal rows spanning the plane perpendicular to unit ``direction``."""
    helper = np.eye(3)[int(np.argmin(np.abs(direction)))]
    u = np.cross(direction, helper)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(direction, u)])


def cluster_entropy(normals: np.ndarray, weights: np.ndarray, floor_deg: float = FLOOR_DEG
                    ) -> tuple[np.ndarray, np.ndarray, float]:
    """(direction, 2×2 tangent covariance incl. floor, entropy in nats) of one cluster of normals."""
    w = np.asarray(weights, np.float64)
    n = np.asarray(normals, np.float64)
    _, vecs = np.linalg.eigh((n * w[:, None]).T @ n)
    direction = vecs[:, -1]
    n = n * np.where(n @ direction < 0, -1.0, 1.0)[:, None]
    coords = n @ tangent_basis(direction).T
    centred = coords - (w @ coords) / w.sum()
    cov = (centred * w[:, None]).T @ centred / w.sum() + math.radians(floor_deg) ** 2 * np.eye(2)
    entropy = math.log(2 * math.pi * math.e) + 0.5 * math.log(float(np.linalg.det(cov)))
    return direction, cov, entropy


def pne_clusters(normals: np.ndarray, weights: np.ndarray, cluster_deg: float = CLUSTER_DEG,
                 floor_deg: float = FLOOR_DEG, min_planes: int = MIN_PLANES) -> list[NormalCluster]:
    """The clusters PNE averages over (those with at least ``min_planes`` planes)."""
    weights = np.asarray(weights, np.float64)
    out = []
    for members in cluster_normals(normals, weights, cluster_deg):
        if len(members) < min_planes:
            continue
        direction, cov, h = cluster_entropy(normals[members], weights[members], floor_deg)
        out.append(NormalCluster(members, direction, cov, h, float(weights[members].sum())))
    return out


def pne_of_clusters(clusters: list[NormalCluster]) -> float:
    """Inlier-weighted mean entropy of clusters (nats); NaN for no cluster."""
    if not clusters:
        return float("nan")
    w = np.array([c.weight for c in clusters])
    return float(w @ np.array([c.entropy for c in clusters]) / w.sum())


def pne(normals: np.ndarray, weights: np.ndarray, cluster_deg: float = CLUSTER_DEG, floor_deg: float = FLOOR_DEG,
        min_planes: int = MIN_PLANES) -> float:
    """PNE (nats) of (M, 3) window-frame normals weighted by (M,) inlier counts; NaN when no cluster counts."""
    normals = np.asarray(normals, np.float64).reshape(-1, 3)
    return pne_of_clusters(pne_clusters(normals, weights, cluster_deg, floor_deg, min_planes))
