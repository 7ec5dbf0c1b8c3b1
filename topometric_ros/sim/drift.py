"""Estimated poses from ground truth: drift episodes or per-pose noise, modes r, t, rt and a scale.

Drift episodes imitate a SLAM front end losing track: inside an episode every odometry step gets an
extra body-frame rotation (about an axis fixed per episode) and translation (direction fixed per
episode) at a constant rate, so the error accumulates and stays after the episode ends. Per-pose noise
(kind ``noise``) perturbs each pose independently, as in the paper's noise experiment.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from .. import geometry

#: Drift rates at scale 1 (episodes): rotation deg/s and translation m/s.
BASE_DRIFT_ROT_DEG_S = 2.0
BASE_DRIFT_TRANS_M_S = 0.2
#: Per-pose noise at scale 1 (kind "noise"): rotation σ deg and translation σ m.
BASE_NOISE_ROT_DEG = 0.5
BASE_NOISE_TRANS_M = 0.05
MODES = ("none", "r", "t", "rt")


@dataclass(frozen=True)
class DriftSpec:
    """Which error (mode r / t / rt / none), how strong (scale), and its kind (episodes or noise)."""

    mode: str = "none"
    scale: float = 1.0
    kind: str = "episodes"

    @classmethod
    def parse(cls, text: str, kind: str = "episodes") -> "DriftSpec":
        """'rt:1.5' -> DriftSpec('rt', 1.5); 'none' or '' -> no drift."""
        mode, _, scale = (text or "none").partition(":")
        if mode not in MODES:
            raise ValueError(f"drift mode must be one of {MODES}, got {mode!r}")
        try:
            value = float(scale) if scale else 1.0
        except ValueError:
            raise ValueError(f"drift scale must be a number, got {scale!r}") from None
        if value < 0:
            raise ValueError(f"drift scale must be >= 0, got {value}")
        if kind not in ("episodes", "noise"):
            raise ValueError(f"drift kind must be 'episodes' or 'noise', got {kind!r}")
        return cls(mode, value, kind)

    @property
    def rotation(self) -> bool:
        return "r" in self.mode and self.mode != "none"

    @property
    def translation(self) -> bool:
        return "t" in self.mode


@dataclass(frozen=True)
class Episode:
    """A drift episode between stamps start and end (s), with its body-frame axis and direction."""

    start: float
    end: float
    rot_rate: float  # rad/s
    trans_rate: float  # m/s
    axis: tuple
    direction: tuple

    def as_dict(self) -> dict:
        return asdict(self)


def plan_episodes(t0: float, t1: float, spec: DriftSpec, rng: np.random.Generator, warmup: float = 20.0,
                  length: tuple = (6.0, 10.0), gap: tuple = (15.0, 25.0)) -> list[Episode]:
    """Episodes in [t0 + warmup, t1): random lengths and clean gaps (s). None for mode 'none' or kind noise."""
    if spec.mode == "none" or spec.kind != "episodes":
        return []
    out, t = [], t0 + warmup
    while True:
        dur = rng.uniform(*length)
        if t + dur > t1:
            return out
        axis = geometry.random_unit_vectors(1, rng)[0]
        direction = geometry.random_unit_vectors(1, rng)[0]
        out.append(Episode(t, t + dur, np.radians(BASE_DRIFT_ROT_DEG_S) * spec.scale * spec.rotation,
                           BASE_DRIFT_TRANS_M_S * spec.scale * spec.translation, tuple(axis), tuple(direction)))
        t += dur + rng.uniform(*gap)


def estimated_poses(stamps: np.ndarray, gt: np.ndarray, spec: DriftSpec, episodes: list[Episode],
                    rng: np.random.Generator) -> np.ndarray:
    """(M, 4, 4) estimated poses for ground-truth poses gt (M, 4, 4) at sorted stamps (s)."""
    if spec.mode == "none":
        return gt.copy()
    if spec.kind == "noise":
        noise = geometry.noise_transforms(len(gt), np.radians(BASE_NOISE_ROT_DEG) * spec.scale * spec.rotation,
                                          BASE_NOISE_TRANS_M * spec.scale * spec.translation, rng)
        return gt @ noise
    steps = geometry.inverse(gt[:-1]) @ gt[1:]
    drift = np.repeat(np.eye(4)[None], len(steps), axis=0)
    for ep in episodes:
        # Overlap (s) of each step interval with the episode.
        dt = np.clip(np.minimum(stamps[1:], ep.end) - np.maximum(stamps[:-1], ep.start), 0, None)
        on = dt > 0
        rot = geometry.rotvec_to_matrix(np.outer(dt[on] * ep.rot_rate, ep.axis))
        drift[on] = drift[on] @ geometry.make_pose(rot, np.outer(dt[on] * ep.trans_rate, ep.direction))
    est = np.empty_like(gt)
    est[0] = gt[0]
    increments = steps @ drift
    for i, inc in enumerate(increments):
        est[i + 1] = est[i] @ inc
    return est


def in_episode(stamps: np.ndarray, episodes: list[Episode]) -> np.ndarray:
    """(K,) index of the episode each stamp falls in, -1 outside all episodes."""
    out = -np.ones(len(stamps), int)
    for i, ep in enumerate(episodes):
        out[(stamps >= ep.start) & (stamps < ep.end)] = i
    return out
