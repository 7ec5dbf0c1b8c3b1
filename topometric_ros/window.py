"""Frames and the sliding window of scans.

A Frame is one scan with the pose SLAM gave it. (The sliding window, pose buffer and interpolation by
stamp arrive with the monitor.)
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Frame:
    """One LiDAR scan and its pose.

    points: (N, 3) float32, sensor frame, metres, all finite.
    pose: (4, 4) float64, sensor-to-map.
    stamp: seconds (header stamp of the cloud).
    labels: optional (N,) uint8 class ids (classes.py), e.g. the simulator's ground truth.
    ring: optional (N,) uint16 beam index (0 = lowest), intensity: optional (N,) float32.
    """

    points: np.ndarray
    pose: np.ndarray
    stamp: float
    labels: np.ndarray | None = None
    ring: np.ndarray | None = None
    intensity: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.points)
