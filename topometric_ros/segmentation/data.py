"""Labelled scans from bags, and the cache of range images that training reads.

A bag's PointCloud2 must carry a ``label`` field (the simulator's ground truth); any driver layout
(cloud.read_scan), on the grid the monitor builds (grid.py).
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from .. import bag
from ..cloud import read_scan
from ..grid import ScanGrid, scan_grid
from ..reports import written_whole
from .projection import project, project_labels


@dataclass
class LabelledScan:
    """One scan: points (N, 3) float32 sensor frame, its grid.ScanGrid, intensity (N,) or None, label (N,)."""

    points: np.ndarray
    grid: ScanGrid
    intensity: np.ndarray | None
    label: np.ndarray | None
    stamp_ns: int = 0


def read_scans(bag_path: str | Path, topic: str = "", every: int = 1, limit: int = 0) -> Iterator[LabelledScan]:
    """Every ``every``-th cloud of ``topic`` in a bag ("": /points, else the bag's only PointCloud2 topic; at
    most ``limit`` when > 0), returns only, on the grid the monitor builds for it (no sensor named: the layout
    is read off the cloud)."""
    topic, _ = bag.pick_topic(bag.topics(bag_path), bag.POINTCLOUD2, topic, "/points")
    n = 0
    for i, (_, t_ns, msg) in enumerate(bag.read_messages(bag_path, [topic])):
        if i % every:
            continue
        scan = read_scan(msg)
        grid = scan_grid(scan.points, scan.beam, scan.columns, layout=scan.layout)
        yield LabelledScan(scan.points, grid, scan.intensity, scan.labels, t_ns)
        n += 1
        if limit and n >= limit:
            return


def scene_of(bag_path: str | Path) -> str:
    """The scene a bag shows: from its truth.json (simulated bags), else the folder name."""
    return str((bag.load_truth(bag_path) or {}).get("config", {}).get("scene", bag.bag_name(bag_path)))


def sensor_of(bag_path: str | Path) -> str:
    """The sensor model a simulated bag was made with (truth.json), else the folder name."""
    return str((bag.load_truth(bag_path) or {}).get("config", {}).get("sensor", bag.bag_name(bag_path)))


def scan_images(scan: LabelledScan) -> tuple[np.ndarray, np.ndarray]:
    """(k, 4, h, W) float16 x, y, z, intensity images and (k, h, W) uint8 label images (255 = no point) of a
    scan's grid (projection.py: k interleaved images of at most 32 rows)."""
    image, proj = project(scan.points, scan.grid, scan.intensity)
    if scan.label is None:
        raise ValueError("the cloud has no label field: training and evaluation need ground-truth labels")
    return image[:, 1:5].astype(np.float16), project_labels(proj, scan.label)


def cache_key(bags: Sequence[str | Path], every: int) -> str:
    """A short hash naming a cache: its format (the grid-based images), the bag paths, their truth.json and
    the subsampling."""
    h = hashlib.sha256(f"grid images v3|{every}".encode())  # v3: non-repetitive images of finer columns
    for b in sorted(str(Path(p).resolve()) for p in bags):
        h.update(b.encode())
        truth = bag.truth_path(b)
        if truth.exists():
            h.update(truth.read_bytes())
    return h.hexdigest()[:12]


def bag_images(bag_path: str | Path, topic: str = "", every: int = 1) -> list[tuple[np.ndarray, np.ndarray]]:
    """(images, labels) of :func:`scan_images` for every ``every``-th labelled scan of one bag."""
    return [scan_images(scan) for scan in read_scans(bag_path, topic, every)]


def build_cache(bags: Sequence[str | Path], path: str | Path, every: int = 1, topic: str = "",
                progress: bool = True, workers: int = 1) -> dict[tuple, dict[str, np.ndarray]]:
    """Project every ``every``-th labelled scan of ``bags`` once and save them as an .npz at ``path``;
    ``workers`` > 1 projects the bags in that many processes (the same cache, in the same order).

    Returns {(rows, width): {'images': (S, 4, rows, width) float16 (x, y, z, intensity), 'labels': (S, rows,
    width) uint8, 'scene': (S,) str, 'sensor': (S,) str}}: one group per image shape (a scan of many beams
    adds its k interleaved images to its group).
    """
    from concurrent.futures import ProcessPoolExecutor
    from contextlib import nullcontext
    from functools import partial

    from tqdm import tqdm

    bags = list(bags)
    read = partial(bag_images, topic=topic, every=every)
    groups: dict[tuple, dict[str, list]] = {}
    with ProcessPoolExecutor(workers) if workers > 1 else nullcontext() as pool:
        per_bag = pool.map(read, bags) if pool else map(read, bags)  # in bag order either way
        for b, scans in tqdm(zip(bags, per_bag), total=len(bags), desc="cache bags", unit="bag", disable=not progress):
            for images, labels in scans:
                g = groups.setdefault(images.shape[-2:], {"images": [], "labels": [], "scene": [], "sensor": []})
                g["images"] += list(images)
                g["labels"] += list(labels)
                g["scene"] += [scene_of(b)] * len(images)
                g["sensor"] += [sensor_of(b)] * len(images)
    if not groups:
        raise ValueError(f"no scans found on {topic} in {len(bags)} bag(s)")
    data = {shape: {k: np.stack(v) if k in ("images", "labels") else np.array(v) for k, v in g.items()}
            for shape, g in groups.items()}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with written_whole(path) as tmp:  # an interrupted build leaves no cache that loads as a whole one
        np.savez(tmp, **{f"{k}_{h}x{w}": v for (h, w), g in data.items() for k, v in g.items()})
    return data


def load_or_build_cache(bags: Sequence[str | Path], cache_dir: str | Path, every: int = 1,
                        topic: str = "", progress: bool = True,
                        workers: int = 1) -> dict[tuple, dict[str, np.ndarray]]:
    """The cache for these bags under ``cache_dir`` (built on first use, in ``workers`` processes), grouped
    by image shape."""
    path = Path(cache_dir) / f"seg_cache_{cache_key(bags, every)}.npz"
    if not path.exists():
        return build_cache(bags, path, every, topic, progress, workers)
    data: dict[tuple, dict[str, np.ndarray]] = {}
    with np.load(path) as z:
        for key in z.files:
            name, shape = key.rsplit("_", 1)
            h, w = map(int, shape.split("x"))
            data.setdefault((h, w), {})[name] = z[key]
    return data
