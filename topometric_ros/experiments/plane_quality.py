"""Plane-detection quality against the simulator's plane instances (``topometric plane-quality``).

Recall and purity of the detected planes of simulated scans, per scene, pooled over trajectory seeds.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .. import classes as C
from ..planes import detect_planes
from ..sensors import DEFAULT_SENSOR


def plane_quality(assign: np.ndarray, labels: np.ndarray, instance: np.ndarray, min_points: int = 200,
                  static: tuple = C.STATIC) -> dict:
    """Detected planes of one scan against the simulator's plane-instance ids.

    assign: (N,) plane index per point (−1 none), as ``detect_planes(..., return_inliers=True)`` gives.
    labels, instance: (N,) ground-truth class and plane-instance id per point.

    Definitions. Ground-truth planes: instances with ≥ ``min_points`` points of a static class. A detected
    plane's majority instance is the instance most of its inliers come from; its purity is that fraction.
    A ground-truth plane is recalled when some detected plane has it as majority instance AND holds ≥ 50 %
    of its points. Returns {'n_truth', 'n_recalled', 'recall' (nan when n_truth = 0), 'purity' (list, one
    per detected plane), 'missed' (instance ids), 'n_planes'}.
    """
    assign = np.asarray(assign)
    instance = np.asarray(instance).astype(np.int64)
    keep = np.isin(labels, static)
    ids, sizes = np.unique(instance[keep], return_counts=True)
    truth = ids[sizes >= min_points]
    size_of = dict(zip(ids.tolist(), sizes.tolist()))
    det = assign >= 0
    pairs, overlap = np.unique(np.stack([assign[det].astype(np.int64), instance[det]], 1), axis=0,
                               return_counts=True)
    recalled, purity = set(), []
    if len(pairs):
        planes, starts = np.unique(pairs[:, 0], return_index=True)
        for start, stop in zip(starts, list(starts[1:]) + [len(pairs)]):
            k = start + int(np.argmax(overlap[start:stop]))
            purity.append(float(overlap[k] / overlap[start:stop].sum()))
            inst = int(pairs[k, 1])
            if overlap[k] >= 0.5 * size_of.get(inst, np.inf):
                recalled.add(inst)
    hit = [int(i) for i in truth if int(i) in recalled]
    return {"n_truth": int(len(truth)), "n_recalled": len(hit),
            "recall": len(hit) / len(truth) if len(truth) else float("nan"), "purity": purity,
            "missed": [int(i) for i in truth if int(i) not in recalled], "n_planes": len(purity)}


def coplanar_surfaces(planes: np.ndarray, classes: np.ndarray, angle_deg: float = 1.0,
                      distance: float = 0.03) -> np.ndarray:
    """(I,) surface id of each plane instance: instances of one class lying in one plane (normals within
    ``angle_deg``, same side, offsets within ``distance`` m) share an id. Two wall pieces either side of a door
    are two instances but one surface, which the detector rightly gives as one plane (merge_across_gaps)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n, d = planes[:, :3], planes[:, 3]
    same = ((classes[:, None] == classes[None]) & (n @ n.T >= np.cos(np.radians(angle_deg)))
            & (np.abs(d[:, None] - d[None]) <= distance))
    i, j = np.nonzero(same)
    return connected_components(coo_matrix((np.ones(len(i)), (i, j)), shape=(len(d), len(d))), directed=False)[1]


def evaluate_detector(scenes, frames: int = 20, config=None, seed: int | Sequence[int] = 0, min_points: int = 200,
                      progress: bool = True, sensor: str = DEFAULT_SENSOR) -> dict:
    """Plane quality and speed of ``config.detector`` on simulated scans (labels and ring given).

    For each scene and each trajectory seed: ``frames`` scans of ``sensor`` (simulated_frames(scene, frames,
    seed=seed, sensor=sensor));
    per scene, pooled over the seeds, the recall (recalled / ground-truth planes over all scans, see
    :func:`plane_quality`), the median purity over all detected planes, planes per scan and the median
    detection time per scan (ms, wall clock, this process); 'recall_per_seed' and 'worst_recall' show the
    spread between trajectories.
    Returns {'detector', 'frames', 'seeds', 'scenes': {name: summary}, 'scans': [per-scan rows]}.
    """
    import time

    from tqdm import tqdm

    from ..config import PlaneConfig
    from ..sim.frames import simulated_frames
    from ..sim.scenes import make_scene

    cfg = config if config is not None else PlaneConfig()
    seeds = [seed] if isinstance(seed, (int, np.integer)) else list(seed)
    out = {"detector": cfg.detector, "sensor": sensor, "frames": frames, "seeds": seeds, "min_points": min_points,
           "scenes": {}, "scans": []}
    for scene in scenes:
        truth = recalled = s_truth = s_recalled = 0
        purity, s_purity, n_planes, ms, per_seed = [], [], [], [], {}
        world = make_scene(scene)
        surface = coplanar_surfaces(world.planes, world.instance_class)
        for s in seeds:
            sim, instances = simulated_frames(world, frames, seed=s, sensor=sensor)
            seed_truth = seed_recalled = 0
            for i, (f, inst) in enumerate(tqdm(list(zip(sim, instances)), desc=f"{sensor} {scene} seed {s} ({cfg.detector})",
                                               disable=not progress, leave=False)):
                t = time.perf_counter()
                planes, assign = detect_planes(f.points, f.labels, f.ring, cfg, frame=i, return_inliers=True)
                ms.append(1000 * (time.perf_counter() - t))
                q = plane_quality(assign, f.labels, inst, min_points)
                qs = plane_quality(assign, f.labels, surface[inst], min_points)
                seed_truth, seed_recalled = seed_truth + q["n_truth"], seed_recalled + q["n_recalled"]
                s_truth, s_recalled = s_truth + qs["n_truth"], s_recalled + qs["n_recalled"]
                purity += q["purity"]
                s_purity += qs["purity"]
                n_planes.append(len(planes))
                out["scans"].append({"scene": scene, "seed": s, "frame": i, "points": len(f.points),
                                     "planes": len(planes), "truth": q["n_truth"], "recalled": q["n_recalled"],
                                     "missed": q["missed"],
                                     "median_purity": float(np.median(q["purity"])) if q["purity"] else None,
                                     "ms": round(ms[-1], 3)})
            per_seed[s] = seed_recalled / seed_truth if seed_truth else float("nan")
            truth, recalled = truth + seed_truth, recalled + seed_recalled
        out["scenes"][scene] = {"recall": recalled / truth if truth else float("nan"), "truth": truth,
                                "recalled": recalled, "recall_per_seed": per_seed,
                                "worst_recall": float(np.nanmin(list(per_seed.values()))),
                                "median_purity": float(np.median(purity)) if purity else float("nan"),
                                "min_purity": float(np.min(purity)) if purity else float("nan"),
                                "surface_recall": s_recalled / s_truth if s_truth else float("nan"),
                                "surface_truth": s_truth,
                                "surface_purity": float(np.median(s_purity)) if s_purity else float("nan"),
                                "planes_per_scan": float(np.mean(n_planes)), "ms_per_scan": float(np.median(ms))}
    return out


def plot_plane_quality(res: dict, path) -> None:
    """Recall and median purity per scene (bars) and detection time per scan, as a PNG at ``path``."""
    from ..reports import pyplot

    plt = pyplot()

    scenes = list(res["scenes"])
    x = range(len(scenes))
    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.5))
    a.bar([i - 0.2 for i in x], [res["scenes"][s]["recall"] for s in scenes], 0.4, label="recall")
    a.bar([i + 0.2 for i in x], [res["scenes"][s]["median_purity"] for s in scenes], 0.4, label="median purity")
    a.axhline(0.95, color="k", lw=0.8, ls="--")
    a.set_ylim(0.8, 1.0)
    a.set_xticks(list(x), scenes)
    a.legend(loc="lower right")
    a.set_title(f"plane quality ({res['detector']})")
    b.bar(list(x), [res["scenes"][s]["ms_per_scan"] for s in scenes])
    b.set_xticks(list(x), scenes)
    b.set_ylabel("ms per scan (median)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
