"""Mean Map Entropy (Razlaw et al. 2015), exactly as map-metrics computes it.

For every point of the map aggregated in the first cloud's frame, Σ is the unbiased covariance of the
points within ``radius`` (itself included); the point counts when it has more than ``min_neighbours``
neighbours and det Σ > 0. h = ½ ln det(2πe Σ) = ½ ln((2πe)³ det Σ) (nats); MME = mean h (0.0 when no
point counts). Lower is sharper.
"""
from __future__ import annotations

import numpy as np

from ._neighbours import aggregate_map, map_covariances, sym_det

_LOG_2PIE3 = 3.0 * np.log(2.0 * np.pi * np.e)


def entropies(covs: np.ndarray) -> np.ndarray:
    """Differential entropies ½ ln((2πe)³ det Σ) (nats) of (K, 6) covariances; NaN where det Σ ≤ 0."""
    det = sym_det(covs)
    out = np.full(len(covs), np.nan)
    pos = det > 0
    out[pos] = 0.5 * (_LOG_2PIE3 + np.log(det[pos]))
    return out


def mme_from_covariances(counts: np.ndarray, covs: np.ndarray, weights: np.ndarray, min_neighbours: int = 5) -> float:
    """MME from neighbourhood statistics (see _neighbours.map_covariances)."""
    keep = counts > min_neighbours
    h = entropies(covs[keep])
    w = weights[keep]
    ok = np.isfinite(h)
    if not ok.any():
        return 0.0
    return float(np.sum(w[ok] * h[ok]) / np.sum(w[ok]))


def mme(clouds, poses, radius: float = 1.0, min_neighbours: int = 5, exact: bool = True,
        max_queries: int | None = None, seed: int = 0, voxel_ratio: float = 0.05) -> float:
    """Mean Map Entropy (nats) of sensor-frame clouds (N_i, 3) with (K, 4, 4) sensor-to-map poses.

    radius in metres. exact=False uses the voxel approximation (voxel side voxel_ratio · radius);
    max_queries evaluates a uniform random subset of the points (seeded). See map_covariances.
    """
    counts, covs, weights = map_covariances(aggregate_map(clouds, poses), radius, exact, max_queries, seed,
                                            voxel_ratio)
    return mme_from_covariances(counts, covs, weights, min_neighbours)
