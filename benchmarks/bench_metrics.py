"""PNE + CPV speed on one core: a window of 5, 10, 15 VLP-32C scans whose planes are already cached.

Times score_window (window transform of the cached plane stats + PNE + CPV, baselines off) on ground-truth
poses and on poses with the noise experiment's rt noise at scale 1 (0.5° and 0.05 m per pose).
Planes come from process_scan: the scans segmented with their ground-truth labels (segmentation.mode
labels), planes from planes.detect_planes with the default detector (config planes.detector, ring).
Goal (metrics issue): 15-scan window ≤ 20 ms median.
"""
from __future__ import annotations

import math

import numpy as np

from benchmarks.common import median_ms, record, single_core


def cached_scans(scene: str, n: int):
    """(scans with planes, plane source) for n consecutive simulated scans."""
    from topometric_ros.config import load_config
    from topometric_ros.pipeline import process_scan
    from topometric_ros.sim.frames import simulated_frames

    frames, _ = simulated_frames(scene, n, seed=0)
    cfg = load_config(overrides={"segmentation.mode": "labels"})
    return [process_scan(f, cfg, index=k) for k, f in enumerate(frames)], f"detect_planes ({cfg.planes.detector})"


def main(repeats: int = 30) -> dict:
    single_core()
    from topometric_ros import geometry
    from topometric_ros.config import Config
    from topometric_ros.pipeline import ProcessedScan, score_window

    cfg = Config()
    results = {}
    for scene in ("office1", "garage"):
        scans, source = cached_scans(scene, 15)
        results[f"plane_source[{scene}]"] = source
        results[f"planes_per_scan[{scene}]"] = round(float(np.mean([len(s.planes) for s in scans])), 1)
        noise = geometry.noise_transforms(15, math.radians(0.5), 0.05, np.random.default_rng(0))
        noisy = [ProcessedScan(s.stamp, s.pose @ t, s.planes) for s, t in zip(scans, noise)]
        for size in (5, 10, 15):
            for label, window in (("gt", scans[:size]), ("rt1", noisy[:size])):
                for s in window:
                    s.plane_arrays()  # stacked once per scan, as a cached scan has them
                med, _ = median_ms(lambda: score_window(window, cfg), repeats=repeats)
                parts = score_window(window, cfg)
                key = f"{scene}/N={size}/{label}"
                results[f"{key} pne+cpv ms median"] = round(med, 2)
                results[f"{key} groups"] = parts.n_groups
    return record("metrics", results)


if __name__ == "__main__":
    main()
