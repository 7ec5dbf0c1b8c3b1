"""Motion compensation of one sweep: every point moved to where the sensor was at the scan's header stamp.

A spinning LiDAR fires its columns over ~100 ms; a robot moving 1.5 m/s smears a sweep by 15 cm and a
90 °/s turn by 9°. With each point's time t (s, relative to the header stamp; from the cloud's time field,
else from its azimuth for a spinning sensor) and the odometry interpolated at those times, a point p fired
at t is mapped to T(stamp)⁻¹ T(stamp + t) p: sensor frame at t -> sensor frame at the stamp.

The poses used are the SLAM estimate the monitor judges. Deskewing with them moves each point by the
estimated intra-sweep motion; a drift of ω rad/s in that estimate bends one sweep by at most ω · sweep
length (0.2° per sweep at 2 °/s), the same small warp in every scan, while PNE, CPV and the drift rates
compare planes BETWEEN scans, where the drift accumulates window-long. So deskewing removes the large,
real smear and cannot hide drift; it cannot undo it either.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numba
import numpy as np

from . import geometry
from .sensors import LAYOUTS

KNOTS = 17  # poses sampled across a sweep; between them the motion is interpolated linearly (rotation vector)


@dataclass
class SweepMotion:
    """The sensor's motion over one sweep: knot times (K,) s relative to the scan stamp (ascending) and, at
    each, the pose of the sensor at that time in the sensor frame AT THE STAMP as a rotation vector (K, 3)
    rad and a translation (K, 3) m. ``period_s`` and ``stamp_at`` ('first' | 'last') tell azimuth_times how
    to time points of a cloud without per-point times."""

    times: np.ndarray
    rotvecs: np.ndarray
    translations: np.ndarray
    period_s: float = 0.1
    stamp_at: str = "first"


def sweep_span(period_s: float, stamp_at: str) -> tuple[float, float]:
    """(t_min, t_max) s of a sweep relative to its header stamp: [0, T] when the stamp is the first point's
    time, [-T, 0] when it is the last one's."""
    return (-period_s, 0.0) if stamp_at == "last" else (0.0, period_s)


def sweep_to_deskew(time: np.ndarray | None, layout: str, model, mode: str,
                    rate_hz: float = 0.0) -> tuple[float, float, float, str] | None:
    """(t_min, t_max, period_s, stamp_at) of the sweep to deskew by ``mode`` (config sensor.deskew), or None:
    per-point times (s, relative to the stamp) when the cloud has them; else azimuth-derived times for a
    spinning sensor whose driver (``layout`` or the named sensors.SensorModel ``model``) is known ('auto') or
    assumed ('on': clockwise, stamp at the first point); a non-repetitive sensor without per-point times is
    not deskewed. ``rate_hz`` (0: the model's, else 10 Hz) gives the sweep period."""
    if mode == "off":
        return None
    period = 1.0 / (rate_hz or (model.rate_hz if model is not None else 10.0))
    if time is not None:
        return float(time.min()), float(time.max()), period, "first"
    known = LAYOUTS.get(layout) or (model.layout if model is not None else None)
    pattern = model.pattern if model is not None else (known.pattern if known is not None else "")
    if pattern == "non_repetitive" or (known is None and mode != "on"):  # no azimuth order of firing
        return None
    stamp_at = known.stamp if known is not None else "first"
    return (*sweep_span(period, stamp_at), period, stamp_at)


def sweep_motion(poses_at: Callable[[np.ndarray], np.ndarray | None], stamp: float, t_min: float, t_max: float,
                 period_s: float = 0.1, stamp_at: str = "first", knots: int = KNOTS) -> SweepMotion | None:
    """The motion over [stamp + t_min, stamp + t_max] from ``poses_at(times)`` ((K,) s -> (K, 4, 4)
    sensor-to-map poses, or None when one is unknown); None when a pose is missing."""
    times = np.linspace(min(t_min, 0.0), max(t_max, 0.0), knots)
    poses = poses_at(np.concatenate([[stamp], stamp + times]))
    if poses is None:
        return None
    rel = geometry.inverse(poses[0]) @ poses[1:]
    return SweepMotion(times, geometry.matrix_to_rotvec(rel[:, :3, :3]), rel[:, :3, 3].copy(), period_s, stamp_at)


def azimuth_times(points: np.ndarray, period_s: float, stamp_at: str = "first") -> np.ndarray:
    """(N,) s relative to the stamp of a clockwise-spinning sensor's points in firing order: the sweep starts
    at the first point's azimuth; azimuth falls with time (clockwise seen from above)."""
    az = np.arctan2(points[:, 1], points[:, 0])
    frac = np.mod(az[0] - az, 2 * np.pi) / (2 * np.pi)
    t0, _ = sweep_span(period_s, stamp_at)
    return (t0 + frac * period_s).astype(np.float32)


def deskew(points: np.ndarray, times: np.ndarray, motion: SweepMotion) -> np.ndarray:
    """(N, 3) float32 points moved to the sensor frame at the stamp: p' = R(t) p + T(t), with R, T
    interpolated between the knots (rotation vector and translation, linearly; times outside the knots take
    the end knots). One pass in a numba kernel, in float64, stored as float32 like the points."""
    out = np.empty((len(points), 3), np.float32)
    t = np.ascontiguousarray(times, np.float64)
    _deskew(np.asarray(points, np.float32), t, t.view(np.uint64), np.asarray(motion.times, np.float64),
            np.asarray(motion.rotvecs, np.float64), np.asarray(motion.translations, np.float64), out)
    return out


_CACHE_BITS = 12  # the motion at up to 4096 distinct point times kept (a sweep has ~1000-4000)


@numba.njit(cache=True, nogil=True)
def _motion_at(t, knots, rotvecs, translations, into):
    """into[:] = (unit rotation axis (3), cos, sin, translation (3)) at time t, the rotation vector and
    translation interpolated linearly between the knots (times outside take the end knots)."""
    last = len(knots) - 1
    t = min(max(t, knots[0]), knots[last])
    k = 0
    while k < last - 1 and knots[k + 1] <= t:
        k += 1
    dt = knots[k + 1] - knots[k]
    a = (t - knots[k]) / dt if dt > 0 else 0.0
    b = 1.0 - a
    rx = b * rotvecs[k, 0] + a * rotvecs[k + 1, 0]
    ry = b * rotvecs[k, 1] + a * rotvecs[k + 1, 1]
    rz = b * rotvecs[k, 2] + a * rotvecs[k + 1, 2]
    theta = np.sqrt(rx * rx + ry * ry + rz * rz)
    inv = 1.0 / max(theta, 1e-12)
    into[0], into[1], into[2] = rx * inv, ry * inv, rz * inv
    into[3], into[4] = np.cos(theta), np.sin(theta)
    for j in range(3):
        into[5 + j] = b * translations[k, j] + a * translations[k + 1, j]


@numba.njit(cache=True, nogil=True)
def _deskew(points, times, time_bits, knots, rotvecs, translations, out):
    """out[i] = R(t_i) p_i + T(t_i), Rodrigues (see deskew). Points share their firing's time (an Ouster column,
    a Velodyne firing), so the motion is computed once per distinct time: a direct-mapped cache on the time's
    bits (a collision only recomputes)."""
    size = 1 << _CACHE_BITS
    cached = np.full(size, np.nan)
    motion = np.empty((size, 8))
    for i in range(len(points)):
        h = np.uint64(time_bits[i] ^ (time_bits[i] >> np.uint64(29))) * np.uint64(0x9E3779B97F4A7C15)
        slot = np.int64(h >> np.uint64(64 - _CACHE_BITS))
        if cached[slot] != times[i]:  # NaN never equals: a NaN time is computed every time
            _motion_at(times[i], knots, rotvecs, translations, motion[slot])
            cached[slot] = times[i]
        m = motion[slot]
        kx, ky, kz, c, s = m[0], m[1], m[2], m[3], m[4]
        px, py, pz = np.float64(points[i, 0]), np.float64(points[i, 1]), np.float64(points[i, 2])
        dot = (kx * px + ky * py + kz * pz) * (1.0 - c)
        out[i, 0] = px * c + (ky * pz - kz * py) * s + kx * dot + m[5]
        out[i, 1] = py * c + (kz * px - kx * pz) * s + ky * dot + m[6]
        out[i, 2] = pz * c + (kx * py - ky * px) * s + kz * dot + m[7]
