"""The whole per-scan pipeline per sensor on one pinned core: the cloud read (cloud.read_scan), grid, deskew,
network segmentation (shipped weights, ONNX Runtime) and planes — everything a scan costs before the window.

For every sensors.py model: a few motion-distorted sweeps of office1 written in the model's driver layout
(sim/writer.driver_cloud), then per sweep the median wall time of each step and of the sum, and scans/s.
``python -m benchmarks sensors`` (``TOPOMETRIC_BENCH_SENSORS=VLP-16,OS1-128`` picks models). Sensors of more than
FEW_BEAMS beams are also run with ``segmentation.max_beams`` FEW_BEAMS, side by side (keys ``*_ms_mb64``), and every
sensor with the float32 network (``segmentation.precision`` float32, keys ``*_ms_f32``; the default, auto, runs
int8 on an x86 CPU with VNNI or AVX2: ``precision`` says which ran).
"""
from __future__ import annotations

import os
import time

import numpy as np

from benchmarks.common import record, single_core

SCANS, REPEATS = 4, 5
FEW_BEAMS = 64


def _clouds(name: str) -> list:
    """SCANS motion-distorted sweeps of ``name`` (1.5 m/s) as its driver's PointCloud2 (rosbags)."""
    from topometric_ros import bag, geometry
    from topometric_ros.cloud import rosbags_types
    from topometric_ros.sensors import sensor
    from topometric_ros.sim.lidar import Lidar, firings_per_sweep
    from topometric_ros.sim.scenes import make_scene
    from topometric_ros.sim.trajectory import random_trajectory
    from topometric_ros.sim.writer import driver_cloud

    scene, model = make_scene("office1"), sensor(name)
    rng = np.random.default_rng(0)
    traj = random_trajectory(scene, 4.0, 1.5, 0.0, rng)
    lidar, types = Lidar(scene, model), rosbags_types(bag.typestore())
    lift = geometry.make_pose(np.eye(3), [0, 0, 1.0])
    out = []
    for k in range(SCANS):
        n = firings_per_sweep(model)
        t0 = 1.0 + 0.5 * k
        times = t0 + np.arange(n) * (model.period_s / n)
        sweep = lidar.sweep(traj.poses_at(times) @ lift, rng, k, returns_only=False)
        stamp = times[-1] if model.layout.stamp == "last" else t0
        out.append((driver_cloud(sweep, model, float(stamp), t0, types), traj, lift))
    return out


def _steps(msg, traj, lift, config, segmenter, model) -> dict[str, float]:
    """ms of each per-scan step for one cloud (pose and sweep motion from the true trajectory)."""
    from topometric_ros.cloud import read_scan
    from topometric_ros.deskew import sweep_motion, sweep_to_deskew
    from topometric_ros.pipeline import plane_scan, segment_scan
    from topometric_ros.window import Frame

    t = time.perf_counter()
    scan = read_scan(msg)
    read = 1000 * (time.perf_counter() - t)
    motion, sweep = None, sweep_to_deskew(scan.time, scan.layout, model, config.sensor.deskew)  # as the monitor
    if sweep is not None:
        motion = sweep_motion(lambda s: traj.poses_at(s) @ lift, scan.stamp, *sweep)
    frame = Frame(scan.points, np.eye(4), scan.stamp, None, scan.beam, scan.intensity, scan.time, scan.columns,
                  motion)
    seg = segment_scan(frame, config, segmenter)
    processed = plane_scan(seg, config)
    steps = {"read": read, **{k: v for k, v in processed.timings.items() if k != "total"}}
    steps["total"] = sum(steps.values())
    return steps


def main() -> None:
    from dataclasses import replace

    from topometric_ros.config import Config
    from topometric_ros.pipeline import default_segmenter
    from topometric_ros.sensors import SENSORS, sensor

    single_core()
    config = Config()
    few = replace(config, segmentation=replace(config.segmentation, max_beams=FEW_BEAMS))
    f32 = replace(config, segmentation=replace(config.segmentation, precision="float32"))
    setups = {"": (config, default_segmenter(config.segmentation)),
              f"_mb{FEW_BEAMS}": (few, default_segmenter(few.segmentation)),
              "_f32": (f32, default_segmenter(f32.segmentation))}
    names = [n for n in os.environ.get("TOPOMETRIC_BENCH_SENSORS", ",".join(SENSORS)).split(",") if n]
    results = {}
    for name in names:
        clouds, model = _clouds(name), sensor(name)
        results[name] = {"points": int(np.median([len(m.data) // m.point_step for m, _, _ in clouds])),
                         "precision": setups[""][1].precision}
        for suffix, (cfg, segmenter) in setups.items():
            if suffix.startswith("_mb") and model.beams <= FEW_BEAMS:
                continue
            for msg, traj, lift in clouds[:1]:
                _steps(msg, traj, lift, cfg, segmenter, model)  # warm-up: the ONNX export for this image shape
            samples = [_steps(msg, traj, lift, cfg, segmenter, model) for _ in range(REPEATS)
                       for msg, traj, lift in clouds]
            med = {k: float(np.median([s[k] for s in samples])) for k in samples[0]}
            results[name].update({f"{k}_ms{suffix}": round(v, 2) for k, v in med.items()})
            results[name][f"scans_per_s{suffix}"] = round(1000 / med["total"], 1)
    record("sensors", results)


if __name__ == "__main__":
    main()
