"""Mutually Orthogonal Metric (Kornilova & Ferrer 2021), exactly as map-metrics computes it.

MOM looks only at points on three mutually orthogonal plane sets ("orthogonal subsets", map frame). For
each subset point with more than ``min_neighbours`` map points within ``radius`` (itself included when it
is a map point), λ_min of the unbiased covariance of those map points; per subset the median; MOM = sum
over the subsets (m²). The subsets come from the caller or from :func:`extract_orthogonal_subsets`, which
follows map-metrics' extraction on the FIRST cloud (sensor frame = map frame): normals (Open3D, hybrid
radius / 30 neighbours), points whose neighbourhood is planar (100 λ₀ < λ₁), Ward clustering of the
normals (distance threshold 0.1), clusters larger than ``min_cluster_size``, and the maximal clique of
mutually orthogonal cluster means (|n_i·n_j| < eps) holding the most points.
"""
from __future__ import annotations

import numpy as np

from ._neighbours import aggregate_map, ball_covariances, sym_eigvals

#: Ward clustering is O(n²) in memory: above this many planar points it clusters a seeded random subset
#: and gives every other point the label of the nearest cluster mean (map-metrics clusters all points).
MAX_CLUSTER_POINTS = 6000


def mom(clouds, poses, radius: float = 1.0, min_neighbours: int = 3, orth_subsets=None) -> float:
    """MOM (m²) of sensor-frame clouds (N_i, 3) with (K, 4, 4) sensor-to-map poses.

    orth_subsets: list of (n_i, 3) point arrays in the map frame (the first cloud's frame); extracted from
    the first cloud when None. NaN when no orthogonal triple of planes is found or a subset has no point
    with enough neighbours.
    """
    points = aggregate_map(clouds, poses)
    if orth_subsets is None:
        try:
            orth_subsets, _ = extract_orthogonal_subsets(np.asarray(clouds[0], np.float64), radius)
        except ValueError:
            return float("nan")
    return mom_from_subsets(points, orth_subsets, radius, min_neighbours)


def mom_from_subsets(points: np.ndarray, orth_subsets, radius: float = 1.0, min_neighbours: int = 3) -> float:
    """MOM of an aggregated map (M, 3) given orthogonal subsets (map frame)."""
    total = 0.0
    for subset in orth_subsets:
        counts, covs = ball_covariances(np.asarray(subset, np.float64).reshape(-1, 3), points, radius)
        keep = counts > min_neighbours
        if not keep.any():
            return float("nan")
        total += float(np.median(sym_eigvals(covs[keep])[:, 0]))
    return total


def extract_orthogonal_subsets(points: np.ndarray, radius: float = 1.0, max_nn: int = 30,
                               min_cluster_size: int = 5, eps: float = 0.1, seed: int = 0
                               ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Three (or more) mutually orthogonal plane point sets of one cloud, as map-metrics finds them.

    points (N, 3) in any frame (the subsets are in the same frame); radius (m) for normals and planarity.
    Returns (subsets: list of (n_i, 3) arrays, normals: list of (3,) unit cluster-mean normals).
    Raises ValueError when no three mutually orthogonal clusters exist.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    normals = _open3d_normals(pts, radius, max_nn)
    counts, covs = ball_covariances(pts, pts, radius)
    lam = np.zeros((len(pts), 3))
    enough = counts > 3
    lam[enough] = sym_eigvals(covs[enough])
    planar = enough & (100 * lam[:, 0] < lam[:, 1])
    pts, normals = pts[planar], normals[planar]
    if len(pts) < 3:
        raise ValueError("no planar points to extract orthogonal planes from")
    labels = _ward_labels(normals, 0.1, seed)
    ids, sizes = np.unique(labels, return_counts=True)
    big = ids[sizes > min_cluster_size]
    means = np.array([normals[labels == i].mean(axis=0) for i in big]).reshape(-1, 3)
    means /= np.linalg.norm(means, axis=1, keepdims=True)
    clique = _largest_orthogonal_clique(means, [int(np.sum(labels == i)) for i in big], eps)
    return [pts[labels == big[i]] for i in clique], [means[i] for i in clique]


def _open3d_normals(points: np.ndarray, radius: float, max_nn: int) -> np.ndarray:
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pc.estimate_normals(search_param=o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=max_nn))
    return np.asarray(pc.normals).copy()


def _ward_labels(normals: np.ndarray, threshold: float, seed: int) -> np.ndarray:
    """Cluster labels as sklearn's AgglomerativeClustering(distance_threshold, ward linkage) gives them
    (up to renumbering): merges closer than ``threshold`` are kept."""
    from scipy.cluster.hierarchy import fcluster, ward

    sample = normals
    if len(normals) > MAX_CLUSTER_POINTS:
        pick = np.random.default_rng(seed).choice(len(normals), MAX_CLUSTER_POINTS, replace=False)
        sample = normals[pick]
    z = ward(sample)
    n_clusters = int(np.count_nonzero(z[:, 2] >= threshold)) + 1
    labels = fcluster(z, n_clusters, criterion="maxclust")
    if sample is normals:
        return labels
    ids = np.unique(labels)
    centres = np.array([sample[labels == i].mean(axis=0) for i in ids])
    nearest = np.argmin(((normals[:, None, :] - centres[None, :, :]) ** 2).sum(axis=2), axis=1)
    return ids[nearest]


def _largest_orthogonal_clique(means: np.ndarray, sizes: list[int], eps: float) -> list[int]:
    """Indices of the maximal clique (> 2 members) of mutually orthogonal means holding the most points."""
    import networkx as nx

    graph = nx.Graph()
    graph.add_nodes_from(range(len(means)))
    dots = np.abs(means @ means.T)
    for i in range(len(means)):
        for j in range(i):
            if dots[i, j] < eps:
                graph.add_edge(i, j)
    best, best_size = None, -1
    for clique in nx.find_cliques(graph):
        if len(clique) > 2:
            amount = sum(sizes[j] for j in clique)
            if amount > best_size:
                best, best_size = clique, amount
    if best is None:
        raise ValueError("no three mutually orthogonal plane clusters found")
    return best
