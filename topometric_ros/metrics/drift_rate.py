"""Drift rates of a window from its co-plane groups: how fast the poses drift, in deg/s and m/s.

A pose error that grows during the window (SLAM drifting) moves each physical plane from scan to scan.
With scan i's error in the WINDOW frame x -> R_i x + p_i, R_i ≈ I + [ω t_i]×, p_i ≈ p_0 + v t_i (t_i in s
since the window's first scan), a plane (n, d) becomes, to first order,
    n_i ≈ n + t_i (ω × n),        d_i ≈ d − t_i (n · v).
So inside a co-plane group (cpv.CoPlaneGroup: one physical plane seen by several scans) the members' normals
and their offsets along the group normal (the members' mean normal) change linearly with time. One weighted least-squares fit over
all groups, each group's own means removed, gives the angular rate ω (rad/s) from the normals and the linear
rate v (m/s) from the offsets. Members weigh √(inlier count): many points make a precise plane, but a big
floor must not hide every wall. Directions no group constrains (v along a direction no plane faces, ω about
the only normal seen) stay zero (minimum-norm solution): the rates are the part of the drift planes can see.

Constant pose errors (a window shifted as a whole) give no rate; pose noise without a trend gives a small
one. The rates are in physical units, so their alarm limits do not depend on the site. Valid while the
drift stays inside the co-plane gates across the window (cpv: ε in offset, the angle gate in normals).

``rpe_estimate`` turns the rates into the paper's RPE (Eq. 4) over consecutive scan pairs, for small errors:
‖E − I‖_F² = ‖ΔR − I‖_F² + |Δp|² ≈ 2 (|ω| Δt)² + (|v| Δt)², leaving out the lever arm of the rotation
(ω Δt × the distance between the sensor and the window origin; a few % for a 1 s window).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from .cpv import CoPlaneGroup

RCOND = 1e-3  # singular values below this fraction of the largest count as unconstrained directions
TUKEY_C = 4.685  # Tukey biweight cut-off in robust scale units (95 % efficiency for Gaussian residuals)
OFFSET_SCALE_FLOOR = 0.005  # m, smallest robust scale of offset residuals (sub-cm plane fits)
NORMAL_SCALE_FLOOR = np.radians(0.2)  # rad, smallest robust scale of normal residuals
ITERATIONS = 8
TOLERANCE = 1e-6  # rad/s or m/s: a change of the rate this small ends the iterations


def _skew(n: np.ndarray) -> np.ndarray:
    x, y, z = n
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def drift_rates(groups: Sequence[CoPlaneGroup], scans, normals, means, counts, times) -> tuple[float, float]:
    """(rotation rate deg/s, translation rate m/s) of a window's co-plane groups.

    scans (M,) scan position of each plane, normals (M, 3) and means (M, 3, m) in the window frame, counts
    (M,) inliers, times (K,) s of each scan position (any origin). NaN, NaN when there is no group."""
    if not groups:
        return float("nan"), float("nan")
    normals, means = np.asarray(normals, np.float64).reshape(-1, 3), np.asarray(means, np.float64).reshape(-1, 3)
    counts, times, scans = np.asarray(counts, np.float64), np.asarray(times, np.float64), np.asarray(scans)
    members = np.concatenate([g.members for g in groups])
    group = np.repeat(np.arange(len(groups)), [len(g.members) for g in groups])
    onehot = np.eye(len(groups))[group]
    t, w = times[scans[members]], np.sqrt(counts[members])
    n = np.stack([_mean_direction(normals[g.members], np.sqrt(counts[g.members])) for g in groups])[group]
    offsets = -np.einsum("ij,ij->i", means[members], n)[:, None]
    # offsets: d_k = a_g − t_k n_g·v;  normals: n_k = c_g − t_k [n_g]× ω  (a_g, c_g per group)
    v = _robust_rate(-t[:, None, None] * n[:, None, :], offsets, onehot, w, OFFSET_SCALE_FLOOR)
    skews = np.stack([_skew(x) for x in n])
    omega = _robust_rate(-t[:, None, None] * skews, normals[members], onehot, w, NORMAL_SCALE_FLOOR)
    return float(np.degrees(np.linalg.norm(omega))), float(np.linalg.norm(v))


def _mean_direction(normals: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Unit weighted mean of a group's member normals (all on one side: the co-plane gate ensures it)."""
    m = weight @ normals
    return m / np.linalg.norm(m)


def _robust_rate(design: np.ndarray, obs: np.ndarray, group: np.ndarray, weight: np.ndarray,
                 scale_floor: float) -> np.ndarray:
    """The rate x (3,) of obs_k ≈ c_group(k) + design_k x with per-group intercepts c: a robust fit, so that one
    group joining two different surfaces (a step inside the group, not a trend) is rejected instead of
    bending the rate. design (M, R, 3), obs (M, R), group (M, G) one-hot membership, weight (M,) prior weights.

    Iteratively reweighted least squares (Tukey's biweight on each member's residual norm) from two starts,
    x = 0 (no drift: a step group stands out and is dropped) and plain least squares (a real drift, which
    from x = 0 could look like outliers itself); the result that leaves the smaller Tukey loss at the noise
    floor ``scale_floor`` wins."""
    best, best_loss = np.zeros(3), np.inf
    for start in (np.zeros(3), _weighted_fit(design, obs, group, weight)):
        x = _irls(design, obs, group, weight, scale_floor, start)
        if best_loss < np.inf and np.allclose(x, best, rtol=0, atol=TOLERANCE):
            continue  # both starts led to the same rate
        loss = float(weight @ _tukey_loss(_residuals(design, obs, group, weight, x) / (TUKEY_C * scale_floor)))
        if loss < best_loss - 1e-12:
            best, best_loss = x, loss
    return best


def _irls(design, obs, group, weight, scale_floor, x):
    keep = weight
    for _ in range(ITERATIONS):
        res = _residuals(design, obs, group, keep, x)
        scale = max(1.4826 * float(np.median(res)), scale_floor)
        keep = weight * (1.0 - np.clip(res / (TUKEY_C * scale), 0.0, 1.0) ** 2) ** 2
        new_x = _weighted_fit(design, obs, group, keep)
        if np.allclose(new_x, x, rtol=0, atol=TOLERANCE):
            return new_x
        x = new_x
    return x


def _tukey_loss(u: np.ndarray) -> np.ndarray:
    """Tukey's biweight loss scaled to [0, 1] (1 beyond the cut-off) of residuals u in cut-off units."""
    return 1.0 - (1.0 - np.clip(np.abs(u), 0.0, 1.0) ** 2) ** 3


def _residuals(design, obs, group, weight, x) -> np.ndarray:
    """(M,) residual norm of each member about its group's weighted fit."""
    a, b = _centred(design, obs, group, weight)
    return np.linalg.norm(b - a @ x, axis=1)


def _weighted_fit(design, obs, group, weight) -> np.ndarray:
    """Weighted least-squares x with the per-group intercepts eliminated (minimum norm; zero without rows)."""
    a, b = _centred(design, obs, group, weight)
    sw = np.sqrt(weight)[:, None, None]
    rows, rhs = (a * sw).reshape(-1, 3), (b * sw[..., 0]).reshape(-1)
    return np.linalg.lstsq(rows, rhs, rcond=RCOND)[0] if np.any(rows) else np.zeros(3)


def _centred(design: np.ndarray, obs: np.ndarray, group: np.ndarray, weight: np.ndarray):
    """design and obs minus their weighted means per group (removes the per-group intercepts); ``group`` is
    the (M, G) one-hot membership matrix."""
    m, r = obs.shape
    both = np.concatenate([design.reshape(m, 3 * r), obs], axis=1)
    total = group.T @ weight
    means = (group.T @ (weight[:, None] * both)) / np.where(total > 0, total, 1.0)[:, None]
    both = both - group @ means
    return both[:, :3 * r].reshape(m, r, 3), both[:, 3 * r:]


def rpe_estimate(rot_rate_deg_s: float, trans_rate_m_s: float, times) -> float:
    """RPE (Eq. 4, mean ‖E − I‖_F over consecutive pairs) that drift at these rates gives over scans at
    ``times`` (s): small-error form √(2 (ω Δt)² + (v Δt)²)."""
    dt = np.diff(np.sort(np.asarray(times, np.float64)))
    if not len(dt) or not np.isfinite(rot_rate_deg_s) or not np.isfinite(trans_rate_m_s):
        return float("nan")
    return float(np.mean(dt) * np.hypot(np.sqrt(2.0) * np.radians(rot_rate_deg_s), trans_rate_m_s))
