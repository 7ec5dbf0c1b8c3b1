"""map-metrics' depth reference data (shared/peer/map-metrics-depth): loader and reference values.

The folder is found from TOPOMETRIC_MAPMETRICS_DATA, else ``../shared/peer/map-metrics-depth`` beside the
repository checkout. Clouds are sensor-frame (N, 3) float64; poses (K, 4, 4) sensor-to-world.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .. import geometry

# map-metrics 0.0.4/0.0.5 on its depth test data, radius 0.2 m (the folder's README.md)
REF_MME, REF_MPV, REF_MOM = -3.6144387057257523, 0.0025390347963358565, 0.0061830823367133685
RADIUS = 0.2


def folder() -> Path:
    default = Path(__file__).resolve().parents[2].parent / "shared" / "peer" / "map-metrics-depth"
    return Path(os.environ.get("TOPOMETRIC_MAPMETRICS_DATA", default))


def read_ply(path: Path) -> np.ndarray:
    """Binary little-endian PLY with float64 x, y, z only -> (N, 3)."""
    with open(path, "rb") as f:
        n = 0
        while (raw := f.readline()).strip() != b"end_header":
            if not raw:
                raise ValueError(f"{path}: PLY header without end_header")
            line = raw.decode().strip()
            if line.startswith("element vertex"):
                n = int(line.split()[-1])
        return np.frombuffer(f.read(24 * n), dtype="<f8").reshape(n, 3).copy()


def load() -> tuple[list[np.ndarray], np.ndarray, list[np.ndarray]] | None:
    """(clouds in name order, poses, MOM's orthogonal subsets in the first cloud's frame), or None when absent."""
    root = folder()
    if not (root / "pcs").is_dir():
        return None
    names = sorted(p.stem[3:] for p in (root / "pcs").glob("PC-*.ply"))
    clouds = [read_ply(root / "pcs" / f"PC-{n}.ply") for n in names]
    poses = np.stack([np.loadtxt(root / "poses" / f"pose-{n}.txt") for n in names])
    t = geometry.inverse(poses[0]) @ poses[names.index("0091")]
    orth = [geometry.transform_points(t, np.asarray(s, np.float64))
            for s in np.load(root / "orth-0091.npy", allow_pickle=True)]
    return clouds, poses, orth
