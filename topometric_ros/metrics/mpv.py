"""Mean Plane Variance (Razlaw et al. 2015), exactly as map-metrics computes it.

For every point of the map aggregated in the first cloud's frame with more than ``min_neighbours``
neighbours within ``radius`` (itself included), the smallest eigenvalue λ_min of the unbiased neighbourhood
covariance; MPV = mean λ_min (m²; 0.0 when no point counts). Lower is sharper.
"""
from __future__ import annotations

import numpy as np

from ._neighbours import aggregate_map, map_covariances, sym_eigvals
from .mme import mme_from_covariances


def mpv_from_covariances(counts: np.ndarray, covs: np.ndarray, weights: np.ndarray, min_neighbours: int = 5) -> float:
    """MPV from neighbourhood statistics (see _neighbours.map_covariances)."""
    keep = counts > min_neighbours
    if not keep.any():
        return 0.0
    lam_min = sym_eigvals(covs[keep])[:, 0]
    w = weights[keep]
    return float(np.sum(w * lam_min) / np.sum(w))


def mpv(clouds, poses, radius: float = 1.0, min_neighbours: int = 5, exact: bool = True,
        max_queries: int | None = None, seed: int = 0, voxel_ratio: float = 0.05) -> float:
    """Mean Plane Variance (m²) of sensor-frame clouds (N_i, 3) with (K, 4, 4) sensor-to-map poses.

    Parameters as mme().
    """
    counts, covs, weights = map_covariances(aggregate_map(clouds, poses), radius, exact, max_queries, seed,
                                            voxel_ratio)
    return mpv_from_covariances(counts, covs, weights, min_neighbours)


def mme_mpv(clouds, poses, radius: float = 1.0, min_neighbours: int = 5, exact: bool = True,
            max_queries: int | None = None, seed: int = 0, voxel_ratio: float = 0.05) -> tuple[float, float]:
    """(MME, MPV) from one neighbourhood pass: the same numbers as mme() and mpv(), half the time."""
    counts, covs, weights = map_covariances(aggregate_map(clouds, poses), radius, exact, max_queries, seed,
                                            voxel_ratio)
    return (mme_from_covariances(counts, covs, weights, min_neighbours),
            mpv_from_covariances(counts, covs, weights, min_neighbours))
