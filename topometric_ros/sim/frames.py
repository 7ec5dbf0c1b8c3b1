"""Simulated frames in memory (no bag): for tests, training and experiments that need no ROS I/O."""
from __future__ import annotations

import numpy as np

from .. import geometry
from ..window import Frame
from ..sensors import DEFAULT_SENSOR
from .lidar import Lidar
from .scenes import Scene, make_scene
from .trajectory import random_trajectory


def simulated_frames(scene: str | Scene, n: int, rate: float = 5.0, speed: float = 1.2, seed: int = 0,
                     layout_seed: int = 0, sensor_height: float = 1.0, start_time: float = 0.0,
                     sensor: str = DEFAULT_SENSOR) -> tuple[list[Frame], list[np.ndarray]]:
    """n consecutive instantaneous scans of ``sensor`` (sensors.SENSORS name) along a random trajectory, with
    ground-truth sensor-to-map poses.

    Returns (frames with labels, ring and intensity; per-frame (N,) plane-instance ids of the scene).
    """
    if isinstance(scene, str):
        scene = make_scene(scene, layout_seed)
    rng = np.random.default_rng(seed)
    traj = random_trajectory(scene, n / rate + 1.0, speed, start_time - 0.5, rng)
    stamps = start_time + np.arange(n) / rate
    poses = traj.poses_at(stamps) @ geometry.make_pose(np.eye(3), [0.0, 0.0, sensor_height])
    lidar = Lidar(scene, sensor)
    frames, instances = [], []
    for t, pose in zip(stamps, poses):
        s = lidar.scan(pose, rng, sweep=len(frames))
        frames.append(Frame(points=s.points, pose=pose, stamp=float(t), labels=s.label, ring=s.ring,
                            intensity=s.intensity))
        instances.append(s.instance)
    return frames, instances
