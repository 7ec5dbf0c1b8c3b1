"""Planes of one scan: the Plane record, least-squares fits, and per-class detection.

Everything here is in the SENSOR frame of the scan. A plane keeps the sufficient statistics of ALL its
inliers (count, mean, scatter matrix), which transform exactly under a rigid motion, so a window can put
a cached plane into its own frame without touching points again (see :meth:`Plane.transformed_stats`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import classes as C


@dataclass
class Plane:
    """One detected plane of one scan (sensor frame, metres).

    cls: class id (classes.py). normal: (3,) unit, oriented toward the sensor (so offset > 0 for a plane
    not through the origin). offset: d in n·x + d = 0. count: number of inliers. mean: (3,) inlier
    centroid. scatter: (3, 3) Σ (x − mean)(x − mean)ᵀ over all inliers. sample: (≤K, 3) float32 inlier
    points for display. frame: index of the scan in its stream (−1 when unknown).
    """

    cls: int
    normal: np.ndarray
    offset: float
    count: int
    mean: np.ndarray
    scatter: np.ndarray
    sample: np.ndarray
    frame: int = -1

    def transformed_stats(self, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(normal, mean, scatter) after the rigid 4×4 ``pose`` (sensor -> some frame); exact."""
        r, t = pose[:3, :3], pose[:3, 3]
        return r @ self.normal, r @ self.mean + t, r @ self.scatter @ r.T


def fit_plane(points: np.ndarray, cls: int, frame: int = -1, max_sample: int = 256,
              rng: np.random.Generator | None = None) -> Plane:
    """Least-squares plane through (K ≥ 3, 3) sensor-frame points; normal oriented toward the sensor origin."""
    pts = np.asarray(points, np.float64)
    if len(pts) < 3:
        raise ValueError(f"a plane needs at least 3 points, got {len(pts)}")
    mean = pts.mean(axis=0)
    centred = pts - mean
    scatter = centred.T @ centred
    _, vecs = np.linalg.eigh(scatter)
    normal = vecs[:, 0]
    offset = -float(normal @ mean)
    if offset < 0:  # sensor origin on the positive side: n·0 + d > 0
        normal, offset = -normal, -offset
    if len(pts) > max_sample:
        rng = rng or np.random.default_rng(0)
        sample = points[rng.choice(len(pts), max_sample, replace=False)]
    else:
        sample = points
    return Plane(int(cls), normal, offset, len(pts), mean, scatter, np.asarray(sample, np.float32), frame)


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
