"""A real LiDAR odometry beside the monitor: KISS-ICP (PyPI kiss-icp) run on a bag's clouds.

``kiss_odometry`` registers every cloud of a bag with KISS-ICP (its own deskewing, from the clouds' per-point
times or, without them, azimuth-derived ones) and returns the sensor poses it estimates, stamped at the
time each pose stands for (KISS-ICP deskews every sweep to its LAST point, so a pose is the sensor at the
sweep's end). ``write_odometry_bag`` writes poses as a small sidecar bag (nav_msgs/Odometry, child frame = the
cloud frame, so no extrinsic is needed) that replay reads beside the original bag; drift episodes can be
injected on top of the estimate (sim/drift.py), exactly as on the simulator's own odometry.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .. import bag
from ..cloud import read_scan
from ..deskew import azimuth_times
from ..reports import written_whole
from ..sensors import LAYOUTS

ODOM_TOPIC = "/odom_kiss"
ODOM_FRAME = "kiss_odom"


#: m, KISS-ICP's voxel size here: its own rule (max range / 100) gives 0.1 m indoors, 4-8x slower than this
#: for about 1.5x the per-scan error on our simulated scenes (measured on office1 and garage, 10 Hz VLP-32C).
VOXEL_SIZE = 0.25


def kiss_odometry(path: str | Path, topic: str = "/points", voxel_size: float = VOXEL_SIZE,
                  progress: bool = True) -> tuple[np.ndarray, np.ndarray, str, dict]:
    """(stamps (K,) s, poses (K, 4, 4) sensor-to-odom, cloud frame id, info) of KISS-ICP over the clouds of
    ``topic``. voxel_size 0 = KISS-ICP's own choice (max_range / 100). info: scans, seconds, Hz."""
    import time

    from kiss_icp.config import KISSConfig
    from kiss_icp.kiss_icp import KissICP
    from tqdm import tqdm

    cfg = KISSConfig()
    stamps, poses, frame_id, odom = [], [], "", None
    t0 = time.perf_counter()
    n_msgs = bag.topics(path).get(topic, ("", None))[1]
    for _, _, msg in tqdm(bag.read_messages(path, [topic]), total=n_msgs, desc="kiss-icp", unit="scan",
                          disable=not progress, leave=False):
        scan = read_scan(msg)
        if len(scan.points) < 100:
            continue
        frame_id = scan.frame_id
        layout = LAYOUTS.get(scan.layout)
        times = scan.time if scan.time is not None else azimuth_times(
            scan.points, 0.1, layout.stamp if layout is not None else "first")
        if odom is None:
            cfg.data.max_range = float(np.percentile(np.linalg.norm(scan.points, axis=1), 99))
            cfg.mapping.voxel_size = voxel_size or cfg.data.max_range / 100.0
            odom = KissICP(cfg)
        odom.register_frame(scan.points.astype(np.float64), times.astype(np.float64))
        stamps.append(scan.stamp + float(times.max()))  # the pose stands for the sweep's last point
        poses.append(odom.last_pose.copy())
    elapsed = time.perf_counter() - t0
    info = {"scans": len(stamps), "seconds": round(elapsed, 1), "hz": round(len(stamps) / max(elapsed, 1e-9), 1),
            "voxel_size": cfg.mapping.voxel_size}
    return np.asarray(stamps), np.asarray(poses).reshape(-1, 4, 4), frame_id, info


def write_odometry_bag(out: str | Path, stamps: np.ndarray, poses: np.ndarray, child_frame: str,
                       topic: str = ODOM_TOPIC) -> Path:
    """A bag at ``out`` holding only ``topic``: one nav_msgs/Odometry per pose (frame ODOM_FRAME, child
    ``child_frame``), received at its own stamp."""
    out = Path(out)
    with bag.BagWriter(out) as w:
        for t, pose in zip(stamps, poses):
            w.write(topic, float(t), bag.make_odometry(float(t), pose, ODOM_FRAME, child_frame))
    return out


def cached_kiss(path: str | Path, cache: str | Path, topic: str = "/points", voxel_size: float = VOXEL_SIZE,
                progress: bool = True) -> tuple[np.ndarray, np.ndarray, str, dict]:
    """kiss_odometry of a bag, computed once: kept as ``cache`` (.npz + .json) keyed by the bag's truth.json
    (simulated bags) and the voxel_size asked for, so a changed bag or setting is registered again."""
    cache = Path(cache)
    key = json.dumps(bag.load_truth(path) or str(path), sort_keys=True)
    meta = cache.with_suffix(".json")
    if cache.with_suffix(".npz").exists() and meta.exists():
        doc = json.loads(meta.read_text())
        if doc.get("key") == key and doc.get("voxel_setting", VOXEL_SIZE) == voxel_size:  # older caches: VOXEL_SIZE
            z = np.load(cache.with_suffix(".npz"))
            return z["stamps"], z["poses"], doc["frame_id"], doc["info"]
    stamps, poses, frame_id, info = kiss_odometry(path, topic, voxel_size, progress=progress)
    cache.parent.mkdir(parents=True, exist_ok=True)
    with written_whole(cache.with_suffix(".npz")) as tmp:
        np.savez(tmp, stamps=stamps, poses=poses)
    with written_whole(meta) as tmp:  # written last: the cache counts only when both are whole
        tmp.write_text(json.dumps({"key": key, "voxel_setting": voxel_size, "frame_id": frame_id, "info": info}))
    return stamps, poses, frame_id, info
