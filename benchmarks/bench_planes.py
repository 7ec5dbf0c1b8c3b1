"""Per-scan plane detection on one core: segmented (labels given) VLP-32C scans of garage and floor2.

Goal (metrics issue): <= 60 ms median per scan for the default detector. Both detectors are timed.
"""
from __future__ import annotations

import numpy as np

from benchmarks.common import median_ms, record, single_core


def main(frames: int = 20, repeats: int = 3, open3d_frames: int = 3) -> dict:
    single_core()
    from topometric_ros.config import PlaneConfig
    from topometric_ros.planes import detect_planes
    from topometric_ros.sim.frames import simulated_frames

    results = {}
    for scene in ("garage", "floor2"):
        scans, _ = simulated_frames(scene, frames, seed=1)
        results[f"points_per_scan[{scene}]"] = int(np.median([len(f) for f in scans]))
        for detector, n in (("ring", frames), ("open3d", open3d_frames)):
            cfg = PlaneConfig(detector=detector)
            per_scan = []
            for f in scans[:n]:
                med, _ = median_ms(lambda: detect_planes(f.points, f.labels, f.ring, cfg), repeats=repeats,
                                   warmup=1)
                per_scan.append(med)
            results[f"{detector}_ms_median[{scene}]"] = round(float(np.median(per_scan)), 2)
            results[f"{detector}_ms_max[{scene}]"] = round(float(np.max(per_scan)), 2)
        f = scans[0]
        med, _ = median_ms(lambda: detect_planes(f.points, f.labels, None, PlaneConfig()), repeats=repeats)
        results[f"ring_no_ring_field_ms[{scene}]"] = round(med, 2)
    return record("planes", results)


if __name__ == "__main__":
    main()
