"""Estimated poses from ground truth: the SLAM front end's everyday error, then drift episodes or per-pose
noise (modes r, t, rt and a scale) on top.

Everyday error (``odometry_error``, SimConfig.odometry "lo"): what a LiDAR odometry makes while it is working
- drift rates per metre driven that wander slowly, a share of every turn, per-scan jitter that does not
accumulate, and, in degenerate corridors (straight runs between close walls), a slide of a few per cent
along the travel direction. The error grows with distance and turning, not with time.

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


EPISODE_WARMUP_S = 20.0  # s of a bag before its first drift episode (the monitor's baselines are learned there)
EPISODE_LENGTH_S = (6.0, 10.0)  # s, shortest and longest episode


def plan_episodes(t0: float, t1: float, spec: DriftSpec, rng: np.random.Generator, warmup: float = EPISODE_WARMUP_S,
                  length: tuple = EPISODE_LENGTH_S, gap: tuple = (15.0, 25.0)) -> list[Episode]:
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


@dataclass(frozen=True)
class OdometryError:
    """The everyday error of a working LiDAR odometry (KITTI-like magnitudes: ~0.5 % of distance, a few
    hundredths of a degree per metre), as drift RATES per metre that wander slowly with the distance driven
    (Ornstein-Uhlenbeck: stationary std ``*_rate``, correlation length ``wander_m``), a share of every turn
    (``turn_fraction``), per-pose jitter that does not accumulate, and a slide along the travel direction on
    straight runs in corridors (``corridor_slide``: std of the fraction of forward motion gained or lost;
    corridor: clearance below ``corridor_clearance_m``)."""

    trans_rate: float = 0.005  # m per m, each axis
    rot_rate_deg: float = 0.01  # deg per m, each axis
    turn_fraction: float = 0.003  # of each turn's angle, about the turn axis
    wander_m: float = 20.0
    jitter_m: float = 0.002
    jitter_deg: float = 0.02
    corridor_slide: float = 0.02
    corridor_clearance_m: float = 1.6


def odometry_error(stamps: np.ndarray, gt: np.ndarray, rng: np.random.Generator, err: OdometryError = OdometryError(),
                   corridor: np.ndarray | None = None) -> np.ndarray:
    """(M, 4, 4) poses of a working LiDAR odometry for ground-truth poses gt (M, 4, 4) at sorted stamps (s):
    each step's motion gets a body-frame error = the current drift rates × its distance + turn_fraction of its
    turn, the forward motion on ``corridor`` steps ((M - 1,) bool) slides by a per-run fraction, and each
    output pose gets independent jitter."""
    steps = geometry.inverse(gt[:-1]) @ gt[1:]
    dist = np.linalg.norm(steps[:, :3, 3], axis=1)
    turn = geometry.matrix_to_rotvec(steps[:, :3, :3])
    rates = _wander(dist, err.wander_m, rng) * np.array([err.trans_rate] * 3 + [np.radians(err.rot_rate_deg)] * 3)
    trans = rates[:, :3] * dist[:, None]
    rot = rates[:, 3:] * dist[:, None] + err.turn_fraction * turn
    if corridor is not None and corridor.any():
        trans += np.where(corridor[:, None], rng.normal(0.0, err.corridor_slide) * steps[:, :3, 3], 0.0)
    est = np.empty_like(gt)
    est[0] = gt[0]
    increments = steps @ geometry.make_pose(geometry.rotvec_to_matrix(rot), trans)
    for i, inc in enumerate(increments):
        est[i + 1] = est[i] @ inc
    jitter = geometry.noise_transforms(len(est), np.radians(err.jitter_deg), err.jitter_m, rng)
    return est @ jitter


def _wander(dist: np.ndarray, length: float, rng: np.random.Generator) -> np.ndarray:
    """(n, 6) unit-variance Ornstein-Uhlenbeck processes over the distance driven (correlation ``length`` m)."""
    out = np.empty((len(dist), 6))
    x = rng.standard_normal(6)
    for i, d in enumerate(dist):
        a = np.exp(-d / length)
        x = a * x + np.sqrt(1 - a * a) * rng.standard_normal(6)
        out[i] = x
    return out


def in_episode(stamps: np.ndarray, episodes: list[Episode]) -> np.ndarray:
    """(K,) index of the episode each stamp falls in, -1 outside all episodes."""
    out = -np.ones(len(stamps), int)
    for i, ep in enumerate(episodes):
        out[(stamps >= ep.start) & (stamps < ep.end)] = i
    return out
