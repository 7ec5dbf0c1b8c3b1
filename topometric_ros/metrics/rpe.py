"""Relative pose error over consecutive pairs of a window (paper Eq. 4, and evo's convention).

gt and est are (K, 4, 4) sensor-to-map poses of the same K scans (any map frames: only relative motions
ΔT_i = T_i⁻¹ T_{i+1} enter). convention="paper": E_i = ΔT_gt,i (ΔT_est,i)⁻¹; convention="evo":
E_i = ΔT_gt,i⁻¹ ΔT_est,i (evo's RPE, full transformation, delta = 1 frame). RPE = mean ‖E_i − I‖_F
(dimensionless: rotation and metres mixed, as in the paper).
"""
from __future__ import annotations

import numpy as np

from .. import geometry

CONVENTIONS = ("paper", "evo")


def _deltas(poses: np.ndarray) -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"poses must be (K, 4, 4), got {poses.shape}")
    return geometry.inverse(poses[:-1]) @ poses[1:]


def rpe_errors(gt: np.ndarray, est: np.ndarray, convention: str = "paper") -> np.ndarray:
    """(K−1, 4, 4) error transforms E_i of consecutive pairs."""
    if convention not in CONVENTIONS:
        raise ValueError(f"convention must be one of {CONVENTIONS}, got {convention!r}")
    d_gt, d_est = _deltas(gt), _deltas(est)
    if d_gt.shape != d_est.shape:
        raise ValueError(f"gt has {len(gt)} poses but est has {len(est)}")
    if convention == "paper":
        return d_gt @ geometry.inverse(d_est)
    return geometry.inverse(d_gt) @ d_est


def rpe(gt: np.ndarray, est: np.ndarray, convention: str = "paper") -> float:
    """Mean ‖E_i − I‖_F over consecutive pairs; 0.0 for fewer than two poses."""
    e = rpe_errors(gt, est, convention)
    if len(e) == 0:
        return 0.0
    return float(np.mean(np.linalg.norm(e - np.eye(4), axis=(1, 2))))


def rpe_parts(gt: np.ndarray, est: np.ndarray, convention: str = "evo") -> tuple[float, float]:
    """(mean rotation angle of E_i in degrees, mean ‖translation of E_i‖ in metres) over consecutive pairs.

    The angle is the same in both conventions; the translation is evo's (‖t_est − t_gt‖ of the relative
    motions, in the gt frame of scan i) by default.
    """
    e = rpe_errors(gt, est, convention)
    if len(e) == 0:
        return 0.0, 0.0
    angle = np.degrees(geometry.rotation_angle(e[:, :3, :3]))
    return float(np.mean(angle)), float(np.mean(np.linalg.norm(e[:, :3, 3], axis=1)))
