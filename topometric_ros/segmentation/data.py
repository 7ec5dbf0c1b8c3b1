"""Labelled scans from bags, and the cache of range images that training reads.

A bag's PointCloud2 must carry a ``label`` field (the simulator's ground truth); ``ring`` and
``intensity`` are used when present.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from .. import bag
from ..cloud import read_cloud, xyz
from .projection import project, project_labels


@dataclass
class LabelledScan:
    """One scan: points (N, 3) float32 sensor frame, ring (N,) or None, intensity (N,) or None, label (N,)."""

    points: np.ndarray
    ring: np.ndarray | None
    intensity: np.ndarray | None
    label: np.ndarray | None
    stamp_ns: int = 0


def read_scans(bag_path: str | Path, topic: str = "/points", every: int = 1, limit: int = 0) -> Iterator[LabelledScan]:
    """Every ``every``-th cloud of ``topic`` in a bag (at most ``limit`` when > 0), finite points only."""
    n = 0
    for i, (_, t_ns, msg) in enumerate(bag.read_messages(bag_path, [topic])):
        if i % every:
            continue
        fields = read_cloud(msg)
        points, finite = xyz(fields)

        def field(name, dtype):
            return np.asarray(fields[name])[finite].astype(dtype, copy=False) if name in fields else None

        yield LabelledScan(points, field("ring", np.uint16), field("intensity", np.float32), field("label", np.uint8),
                           t_ns)
        n += 1
        if limit and n >= limit:
            return


def scene_of(bag_path: str | Path) -> str:
    """The scene a bag shows: from its truth.json (simulated bags), else the folder name."""
    truth = Path(bag_path) / "truth.json"
    if truth.exists():
        cfg = json.loads(truth.read_text()).get("config", {})
        return f"{cfg.get('scene', Path(bag_path).name)}"
    return Path(bag_path).name


def scan_images(scan: LabelledScan) -> tuple[np.ndarray, np.ndarray]:
    """(4, H, W) float16 x, y, z, intensity image and (H, W) uint8 label image (255 = no point)."""
    image, proj = project(scan.points, scan.ring, scan.intensity)
    if scan.label is None:
        raise ValueError("the cloud has no label field: training and evaluation need ground-truth labels")
    return image[1:5].astype(np.float16), project_labels(proj, scan.label)


def cache_key(bags: Sequence[str | Path], every: int) -> str:
    """A short hash naming a cache: the bag paths, their truth.json and the subsampling."""
    h = hashlib.sha256(str(every).encode())
    for b in sorted(str(Path(p).resolve()) for p in bags):
        h.update(b.encode())
        truth = Path(b) / "truth.json"
        if truth.exists():
            h.update(truth.read_bytes())
    return h.hexdigest()[:12]


def build_cache(bags: Sequence[str | Path], path: str | Path, every: int = 1, topic: str = "/points",
                progress: bool = True) -> dict[str, np.ndarray]:
    """Project every ``every``-th labelled scan of ``bags`` once and save them as an .npz at ``path``.

    Arrays: images (S, 4, H, W) float16 (x, y, z, intensity), labels (S, H, W) uint8, scene (S,) str.
    """
    from tqdm import tqdm

    images, labels, scenes = [], [], []
    for b in tqdm(list(bags), desc="cache bags", unit="bag", disable=not progress):
        for scan in read_scans(b, topic, every):
            im, lab = scan_images(scan)
            images.append(im)
            labels.append(lab)
            scenes.append(scene_of(b))
    if not images:
        raise ValueError(f"no scans found on {topic} in {len(bags)} bag(s)")
    data = {"images": np.stack(images), "labels": np.stack(labels), "scene": np.array(scenes)}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **data)
    return data


def load_or_build_cache(bags: Sequence[str | Path], cache_dir: str | Path, every: int = 1,
                        topic: str = "/points", progress: bool = True) -> dict[str, np.ndarray]:
    """The cache for these bags under ``cache_dir`` (built on first use)."""
    path = Path(cache_dir) / f"seg_cache_{cache_key(bags, every)}.npz"
    if path.exists():
        with np.load(path) as z:
            return {k: z[k] for k in z.files}
    return build_cache(bags, path, every, topic, progress)



def expand_bags(paths: Sequence[str | Path]) -> list[Path]:
    """Bag folders from paths that are bags (have metadata.yaml) or folders of bags (one level down)."""
    bags: list[Path] = []
    for p in map(Path, paths):
        if (p / "metadata.yaml").is_file():
            bags.append(p)
        elif p.is_dir() and (found := sorted(d for d in p.iterdir() if (d / "metadata.yaml").is_file())):
            bags.extend(found)
        else:
            raise FileNotFoundError(f"no rosbag2 bag at {p} (a bag folder has metadata.yaml)")
    return bags
