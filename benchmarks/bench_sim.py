"""Simulator speed on one core: one VLP-32C scan (57,600 rays) and a 600-frame garage bag.

Goals (issue 2): scan <= 15 ms median, 600-frame bag <= 30 s.
"""
from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import median_ms, record, single_core


def main(frames: int = 600, repeats: int = 3) -> dict:
    single_core()
    from topometric_ros import geometry
    from topometric_ros.sim.drift import DriftSpec
    from topometric_ros.sim.lidar import Lidar
    from topometric_ros.sim.scenes import make_scene
    from topometric_ros.sim.trajectory import random_trajectory
    from topometric_ros.sim.writer import SimConfig, simulate

    results = {}
    for name in ("garage", "floor2"):
        scene = make_scene(name)
        rng = np.random.default_rng(0)
        poses = random_trajectory(scene, 60, 1.2, 0, rng).poses_at(np.linspace(1, 59, 40))
        poses = poses @ geometry.make_pose(np.eye(3), [0, 0, 1.0])
        lidar = Lidar(scene)
        it = iter(range(10**9))
        med, _ = median_ms(lambda: lidar.scan(poses[next(it) % len(poses)], rng), repeats=100)
        results[f"scan_ms_median[{name}]"] = round(med, 2)
    times = []
    for _ in range(repeats):
        out = Path(tempfile.mkdtemp()) / "bag"
        t = time.perf_counter()
        simulate(SimConfig(scene="garage", frames=frames, drift=DriftSpec.parse("rt:1.5")), out, progress=False)
        times.append(time.perf_counter() - t)
        shutil.rmtree(out.parent)
    results[f"bag_{frames}_frames_s_median"] = round(sorted(times)[len(times) // 2], 2)
    results[f"bag_{frames}_frames_s_all"] = [round(t, 2) for t in times]
    return record("sim", results)


if __name__ == "__main__":
    main()
