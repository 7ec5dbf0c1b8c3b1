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
                  static: tuple = C.STATIC, plane_of: np.ndarray | None = None) -> dict:
    """Detected planes of one scan against the simulator's plane-instance (or surface) ids.

    assign: (N,) plane index per point (−1 none), as ``detect_planes(..., return_inliers=True)`` gives.
    labels, instance: (N,) ground-truth class and unit id per point (plane instances, or :func:`surfaces`).
    plane_of: (U,) optional id of the geometric plane each unit lies in; None = every unit its own.

    Definitions. Ground-truth planes: units (ids ≥ 0) with ≥ ``min_points`` points of a static class. A detected
    plane's majority is the geometric plane most of its inliers lie in (the unit itself without
    ``plane_of``); its purity is that fraction. A unit is recalled when some detected plane whose majority
    is the unit's geometric plane holds ≥ 50 % of the unit's points: a plane joining coplanar pieces seen
    apart (two pillar faces in a row) recalls each piece it mostly covers. Returns {'n_truth',
    'n_recalled', 'recall' (nan when n_truth = 0), 'purity' (list, one per detected plane), 'missed' (unit
    ids), 'n_planes'}.
    """
    assign = np.asarray(assign)
    instance = np.asarray(instance).astype(np.int64)
    plane_of = None if plane_of is None else np.asarray(plane_of, np.int64)
    geometric = instance if plane_of is None else np.where(instance >= 0, plane_of[np.maximum(instance, 0)], -1)
    keep = np.isin(labels, static) & (instance >= 0)
    ids, sizes = np.unique(instance[keep], return_counts=True)
    truth = ids[sizes >= min_points]
    det = np.flatnonzero(assign >= 0)
    _, plane_idx = np.unique(assign[det], return_inverse=True)
    majority, purity = {}, []
    if len(det):
        pairs, overlap = np.unique(np.stack([plane_idx, geometric[det]], 1), axis=0, return_counts=True)
        starts = np.flatnonzero(np.r_[True, np.diff(pairs[:, 0]) != 0])
        for start, stop in zip(starts, list(starts[1:]) + [len(pairs)]):
            k = start + int(np.argmax(overlap[start:stop]))
            purity.append(float(overlap[k] / overlap[start:stop].sum()))
            majority[int(pairs[k, 0])] = int(pairs[k, 1])
    recalled = set()
    if len(det):
        triples = np.stack([plane_idx, instance[det], geometric[det]], 1)  # geometric: a function of instance
        pairs, overlap = np.unique(triples, axis=0, return_counts=True)
        size_of = dict(zip(ids.tolist(), sizes.tolist()))
        for (plane, inst, own), n in zip(pairs.tolist(), overlap.tolist()):
            if n >= 0.5 * size_of.get(inst, np.inf) and majority[plane] == own:
                recalled.add(inst)
    hit = [int(i) for i in truth if int(i) in recalled]
    return {"n_truth": int(len(truth)), "n_recalled": len(hit),
            "recall": len(hit) / len(truth) if len(truth) else float("nan"), "purity": purity,
            "missed": [int(i) for i in truth if int(i) not in recalled], "n_planes": len(purity)}


def geometric_planes(planes: np.ndarray, classes: np.ndarray, angle_deg: float = 1.0,
                     distance: float = 0.03) -> np.ndarray:
    """(I,) geometric-plane id of each plane instance: instances of one class lying in one plane (normals
    within ``angle_deg``, same side, offsets within ``distance`` m) share an id, touching or not: the two wall
    pieces either side of a door, and the faces of a row of pillars."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n, d = planes[:, :3], planes[:, 3]
    same = ((classes[:, None] == classes[None]) & (n @ n.T >= np.cos(np.radians(angle_deg)))
            & (np.abs(d[:, None] - d[None]) <= distance))
    i, j = np.nonzero(same)
    return connected_components(coo_matrix((np.ones(len(i)), (i, j)), shape=(len(d), len(d))), directed=False)[1]


def surfaces(scene, touch: float = 0.05, spacing: float = 0.05, geometric: np.ndarray | None = None) -> np.ndarray:
    """(I,) surface id of each plane instance of ``scene``: static instances of one geometric plane
    (:func:`geometric_planes`) that touch (edges within ``touch`` m, sampled every ``spacing`` m) are one
    surface, as the two wall pieces either side of a door and the lintel joining them; coplanar pieces apart
    (the faces of a row of pillars) stay separate surfaces, each to be found in its own right. ``geometric``:
    :func:`geometric_planes` of the scene when the caller has it already."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    if geometric is None:
        geometric = geometric_planes(scene.planes, scene.instance_class)
    static = np.isin(scene.instance_class, C.STATIC)
    mine = static[scene.tri_instance]
    tri = scene.vertices[scene.triangles[mine]].astype(np.float64)  # (T, 3, 3), static triangles
    edges = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])  # (3T, 2, 3)
    owner = np.tile(scene.tri_instance[mine], 3)
    steps = np.maximum(np.ceil(np.linalg.norm(edges[:, 1] - edges[:, 0], axis=1) / spacing), 1).astype(int)
    which = np.repeat(np.arange(len(edges)), steps + 1)
    first = np.repeat(np.cumsum(steps + 1) - (steps + 1), steps + 1)
    frac = (np.arange(len(which)) - first) / steps[which]
    samples = edges[which, 0] + frac[:, None] * (edges[which, 1] - edges[which, 0])
    sample_owner = owner[which]
    order = np.argsort(geometric[sample_owner], kind="stable")
    groups = np.split(order, np.flatnonzero(np.diff(geometric[sample_owner][order])) + 1)
    pairs = []
    for group in groups:
        if len(group) == 0 or np.all(sample_owner[group] == sample_owner[group[0]]):
            continue  # one instance alone in its geometric plane
        close = cKDTree(samples[group]).query_pairs(touch, output_type="ndarray")
        own = sample_owner[group][close]
        pairs.append(own[own[:, 0] != own[:, 1]])
    i, j = np.concatenate(pairs).T if pairs else (np.zeros(0, int), np.zeros(0, int))
    n = len(scene.planes)
    return connected_components(coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n)), directed=False)[1]


def evaluate_detector(scenes, frames: int = 20, config=None, seed: int | Sequence[int] = 0, min_points: int = 200,
                      progress: bool = True, sensor: str = DEFAULT_SENSOR) -> dict:
    """Plane quality and speed of ``config.detector`` on simulated scans (labels and ring given).

    For each scene and each trajectory seed: ``frames`` scans of ``sensor`` (simulated_frames(scene, frames,
    seed=seed, sensor=sensor));
    per scene, pooled over the seeds, the recall (recalled / ground-truth planes over all scans, see
    :func:`plane_quality`; ``recall`` per instance, ``surface_recall`` the headline: per :func:`surfaces`, a
    plane's majority judged by geometric plane), the median purity over all detected planes, planes per
    scan and the median detection time per scan (ms, wall clock, this process; a first untimed call warms up); 'recall_per_seed' and
    'worst_recall' show the spread between trajectories.
    Returns {'detector', 'frames', 'seeds', 'scenes': {name: summary}, 'scans': [per-scan rows]}.
    """
    import time

    from tqdm import tqdm

    from ..config import PlaneConfig
    from ..sim.frames import simulated_frames
    from ..sim.scenes import make_scene

    cfg = config if config is not None else PlaneConfig()
    seeds = [seed] if isinstance(seed, (int, np.integer)) else list(seed)
    warmed = False
    out = {"detector": cfg.detector, "sensor": sensor, "frames": frames, "seeds": seeds, "min_points": min_points,
           "scenes": {}, "scans": []}
    for scene in scenes:
        truth = recalled = s_truth = s_recalled = 0
        purity, s_purity, n_planes, ms, per_seed = [], [], [], [], {}
        world = make_scene(scene)
        of_instance = geometric_planes(world.planes, world.instance_class)
        surface = surfaces(world, geometric=of_instance)
        geometric = np.zeros(surface.max() + 1, np.int64)
        geometric[surface] = of_instance  # of each surface
        for s in seeds:
            sim, instances = simulated_frames(world, frames, seed=s, sensor=sensor)
            seed_truth = seed_recalled = 0
            for i, (f, inst) in enumerate(tqdm(list(zip(sim, instances)), desc=f"{sensor} {scene} seed {s} ({cfg.detector})",
                                               disable=not progress, leave=False)):
                if not warmed:  # the first call loads the compiled kernels: untimed, as eval-seg leaves it out
                    detect_planes(f.points, f.labels, f.ring, cfg, frame=i)
                    warmed = True
                t = time.perf_counter()
                planes, assign = detect_planes(f.points, f.labels, f.ring, cfg, frame=i, return_inliers=True)
                ms.append(1000 * (time.perf_counter() - t))
                q = plane_quality(assign, f.labels, inst, min_points)
                qs = plane_quality(assign, f.labels, surface[inst], min_points, plane_of=geometric)
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
    a.set_title(f"plane quality, {res.get('sensor') or 'sensor?'} ({res['detector']} detector)")
    b.bar(list(x), [res["scenes"][s]["ms_per_scan"] for s in scenes])
    b.set_xticks(list(x), scenes)
    b.set_ylabel("ms per scan (median)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
