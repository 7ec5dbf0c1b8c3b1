"""Drift rates of a window from its co-plane groups: how fast the poses drift, in deg/s and m/s.

A pose error that grows during the window (SLAM drifting) moves each physical plane from scan to scan.
SLAM drifts where the sensor is and as the sensor sees it: each odometry step adds a small error in the
SENSOR frame, a rotation ω dt and a translation v dt (ω, v: the body-frame drift rates, what this module
reports). With the sensor's window-frame pose (R(t), s(t)) from the SLAM poses (the first scan's pose defines
the window frame), scan i's error in the WINDOW frame, x -> R_i x + p_i (R_0 = I, p_0 = 0), is to first order
    R_i ≈ I + [A_i ω]×,   p_i ≈ A_i v + B_i ω,   A_i = ∫ R dt,   B_i = ∫ [s]× R dt
from the first scan to scan i (drift_integrals). Standing still, A_i = t_i I and B_i = 0. Driving, B_i ω is
the sideways shift a heading error makes where the sensor has gone (at 10 m/s a 2 °/s drift moves the later
scans 0.16 m in a 1 s window, quadratic in time), and turning, A_i turns a body-frame drift with the sensor
(a sideways drift of a car that turns 90° in the window is not a straight line in the window frame).
A patch of plane with unit normal n and centroid m moves to first order as
    normal:  n_i ≈ n + (A_i ω) × n
    offset along the group normal n̄:  −n̄·m_i ≈ d − ω·(A_i − Ā)ᵀ(m_i × n̄) − ω·B_iᵀn̄ − v·A_iᵀn̄,
with n̄ the members' weighted mean normal and Ā their weighted mean A (the plane as seen at their mean time).
So v is the translation drift itself, not the sideways shift a rotation drift makes at speed.
Inside a co-plane group (cpv.CoPlaneGroup: one physical plane seen by several scans) both change with time.
One weighted least-squares fit of the six rates (ω rad/s, v m/s) over all groups, each group's own means
removed, uses both: normals see ω, offsets see v and, through the lever arm m × n̄ of patches away from the
frame origin, ω too (without that term a rotation about the origin read as translation).
Rows are scaled by their noise floors (offsets 5 mm, normals 0.2°) and members weigh √(inlier count): many
points make a precise plane, but a big floor must not hide every wall. Directions no group constrains (v
along a direction no plane faces, ω about the only normal seen) stay zero (minimum-norm solution): the
rates are the part of the drift planes can see. Which directions those are is judged with the sensor's
rotation left out (A_i = t_i I, B_i = [S_i]× with S_i = ∫ s dt): a rotation inside the window would otherwise lend such a direction a trace
of a constraint (a direction turned by 1° is 2 % seen), which noise then fills.

Constant pose errors (a window shifted as a whole) give no rate; pose noise without a trend gives a small
one, and the rates' standard errors (a jackknife over the window's scans) say how small. The rates are in
physical units, so their alarm limits do not depend on the site. Valid while the drift stays inside the
co-plane gates across the window (cpv: ε in offset, the angle gate in normals).

``rpe_estimate`` turns the rates into the paper's RPE (Eq. 4) over consecutive scan pairs, for small errors:
‖E − I‖_F² = ‖ΔR − I‖_F² + |Δp|² ≈ 2 (|ω| Δt)² + (|v| Δt)².
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from .cpv import CoPlaneGroup

RCOND = 1e-3  # singular values below this fraction of the largest count as unconstrained directions
TUKEY_C = 4.685  # Tukey biweight cut-off in robust scale units (95 % efficiency for Gaussian residuals)
OFFSET_SCALE_FLOOR = 0.005  # m, noise floor of plane offsets (sub-cm plane fits): the unit of offset rows
NORMAL_SCALE_FLOOR = np.radians(0.2)  # rad, noise floor of plane normals: the unit of normal rows
ITERATIONS = 8
TOLERANCE = 1e-6  # rad/s or m/s: a change of the rates this small ends the iterations


def _skew(v: np.ndarray) -> np.ndarray:
    """(..., 3, 3) cross-product matrices [v]× of vectors v (..., 3): [v]× u = v × u."""
    x, y, z = np.moveaxis(np.asarray(v, np.float64), -1, 0)
    o = np.zeros_like(x)
    return np.stack([np.stack([o, -z, y], -1), np.stack([z, o, -x], -1), np.stack([-y, x, o], -1)], -2)


def drift_rates(groups: Sequence[CoPlaneGroup], scans, normals, means, counts, times, poses=None):
    """(rotation rate deg/s, translation rate m/s, their standard errors) of a window's co-plane groups: the
    body-frame drift rates of the module docstring.

    scans (M,) scan position of each plane, normals (M, 3) and means (M, 3, m) in the window frame, counts
    (M,) inliers, times (K,) s of each scan position (any origin: the first scan is time 0), poses (K, 4, 4)
    each scan's sensor pose in the window frame (the SLAM poses; None: the sensor stood still). The standard
    errors count each scan's planes as one sample (_scan_jackknife_covariance). NaNs when there is no group."""
    if not groups:
        return float("nan"), float("nan"), float("nan"), float("nan")
    normals, means = np.asarray(normals, np.float64).reshape(-1, 3), np.asarray(means, np.float64).reshape(-1, 3)
    counts, times, scans = np.asarray(counts, np.float64), np.asarray(times, np.float64), np.asarray(scans)
    members = np.concatenate([g.members for g in groups])
    group = np.repeat(np.arange(len(groups)), [len(g.members) for g in groups])
    w = np.sqrt(counts[members])
    n = np.stack([_mean_direction(normals[g.members], np.sqrt(counts[g.members])) for g in groups])[group]
    m, onehot = means[members], np.eye(len(groups))[group]
    design = _design(n, m, *drift_integrals(times, poses), scans[members], onehot, w)
    # The directions the planes see are those of the same fit with the sensor's rotation left out (a drift that
    # keeps its window-frame direction): a small rotation inside the window must not lend a direction no plane
    # faces a trace of a constraint, which noise would then fill (a jackknife replicate read 2 m/s that way).
    seen = None if poses is None else _design(n, m, *drift_integrals(times, _unrotated(poses)), scans[members],
                                              onehot, w)
    obs = np.concatenate([-np.einsum("ij,ij->i", m, n)[:, None] / OFFSET_SCALE_FLOOR,
                          normals[members] / NORMAL_SCALE_FLOOR], axis=1)
    x, keep = _robust_rate(design, obs, onehot, w, seen)
    rot, trans = float(np.degrees(np.linalg.norm(x[:3]))), float(np.linalg.norm(x[3:]))
    cov = _scan_jackknife_covariance(design, obs, onehot, keep, scans[members], seen)
    return rot, trans, float(np.degrees(_norm_se(x[:3], cov[:3, :3]))), _norm_se(x[3:], cov[3:, 3:])


def _design(n, m, turned, swept, scan, group, w) -> np.ndarray:
    """(M, 4, 6) design of the members (rows: offset, normal x y z in noise-floor units; columns: ω, v) for
    group normals n (M, 3), patch centroids m (M, 3), the window's drift integrals A, B (K, 3, 3), each
    member's ``scan`` (M,), one-hot ``group`` (M, G) and weights w (M,). n̄ is the plane's normal at the
    members' weighted mean A (Ā): the lever arm of a patch at m moves its offset along n̄ by −ω·(A − Ā)ᵀ(m × n̄)."""
    a, b = turned[scan], swept[scan]
    a_mean = (group @ ((group.T @ (w[:, None] * a.reshape(-1, 9))) / (group.T @ w)[:, None])).reshape(-1, 3, 3)
    design = np.zeros((len(scan), 4, 6))
    design[:, 0, :3] = -(np.einsum("kji,kj->ki", b, n) + np.einsum("kji,kj->ki", a - a_mean, np.cross(m, n)))
    design[:, 0, 3:] = -np.einsum("kji,kj->ki", a, n)
    design[:, 0] /= OFFSET_SCALE_FLOOR
    design[:, 1:, :3] = -_skew(n) @ a / NORMAL_SCALE_FLOOR
    return design


def _unrotated(poses) -> np.ndarray:
    """(K, 4, 4) copies of ``poses`` with the identity rotation: the sensor's path alone."""
    out = np.asarray(poses, np.float64).reshape(-1, 4, 4).copy()
    out[:, :3, :3] = np.eye(3)
    return out


def drift_integrals(times, poses=None) -> tuple[np.ndarray, np.ndarray]:
    """(A, B), each (K, 3, 3): A_k = ∫ R dt (s) and B_k = ∫ [s]× R dt (m·s) from the first scan (in time) to scan
    k of the sensor's window-frame rotation R and position s (``poses`` (K, 4, 4) in the window frame), by the
    trapezoid rule over the scans in time order. Without poses the sensor stood still: A_k = t_k I, B_k = 0."""
    from scipy.integrate import cumulative_trapezoid

    times = np.asarray(times, np.float64)
    if poses is None:
        poses = np.repeat(np.eye(4)[None], len(times), axis=0)
    poses = np.asarray(poses, np.float64).reshape(-1, 4, 4)
    rot = poses[:, :3, :3]
    moment = _skew(poses[:, :3, 3]) @ rot
    order = np.argsort(times, kind="stable")
    turned, swept = np.empty_like(rot), np.empty_like(rot)
    for f, integral in ((rot, turned), (moment, swept)):
        integral[order] = cumulative_trapezoid(f[order], times[order], axis=0, initial=0)
    return turned, swept


def _scan_jackknife_covariance(design, obs, group, weight, scan, seen=None) -> np.ndarray:
    """(P, P) jackknife covariance of the rates over scans, (K−1)/K Σ_s (x_s − x̄)(x_s − x̄)ᵀ, x_s the weighted fit
    again without scan s, with the robust fit's final ``weight`` (one solve per scan). A scan's own pose error
    moves every plane it sees, so its planes are one sample, not many; under per-scan pose noise this matches
    the rates' real spread (test_drift_rate). NaN with fewer than three scans: two scans fix a trend exactly and
    leave no spread to measure (zero would claim certainty)."""
    used = np.unique(scan[weight > 0])
    p = design.shape[2]
    if len(used) < 3:
        return np.full((p, p), np.nan)
    xs = np.stack([_weighted_fit(design, obs, group, np.where(scan == s, 0.0, weight), seen) for s in used])
    d = xs - xs.mean(axis=0)
    return d.T @ d * (len(used) - 1) / len(used)


def _norm_se(v: np.ndarray, cov: np.ndarray) -> float:
    """Standard error of |v| from v's covariance (first order along v; the largest spread when v = 0); NaN for
    an unknown covariance."""
    if np.isnan(cov).any():
        return float("nan")
    length = np.linalg.norm(v)
    if length > 0:
        u = v / length
        return float(np.sqrt(max(u @ cov @ u, 0.0)))
    return float(np.sqrt(max(np.linalg.eigvalsh(cov)[-1], 0.0)))


def _mean_direction(normals: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Unit weighted mean of a group's member normals (all on one side: the co-plane gate ensures it)."""
    m = weight @ normals
    return m / np.linalg.norm(m)


def _robust_rate(design: np.ndarray, obs: np.ndarray, group: np.ndarray, weight: np.ndarray, seen=None):
    """(rates x (P,), final weights (M,)) of obs_k ≈ c_group(k) + design_k x with per-group intercepts c: a robust
    fit, so that one group joining two different surfaces (a step inside the group, not a trend) is rejected
    instead of bending the rates. design (M, R, P) and obs (M, R) in noise-floor units, group (M, G) one-hot
    membership, weight (M,) prior weights, ``seen`` (M, R, P) the design that decides which directions are
    constrained (_weighted_fit; None: design itself).

    Iteratively reweighted least squares (Tukey's biweight on each member's residual norm) from two starts,
    x = 0 (no drift: a step group stands out and is dropped) and plain least squares (a real drift, which
    from x = 0 could look like outliers itself); the result that leaves the smaller Tukey loss at the noise
    floor (residual 1) wins, each judged with its own final weights."""
    best, best_keep, best_loss = np.zeros(design.shape[2]), weight, np.inf
    for start in (np.zeros(design.shape[2]), _weighted_fit(design, obs, group, weight, seen)):
        x, keep = _irls(design, obs, group, weight, start, seen)
        if best_loss < np.inf and np.allclose(x, best, rtol=0, atol=TOLERANCE):
            continue  # both starts led to the same rates
        loss = float(weight @ _tukey_loss(_residuals(design, obs, group, keep, x) / TUKEY_C))
        if loss < best_loss - 1e-12:
            best, best_keep, best_loss = x, keep, loss
    return best, best_keep


def _irls(design, obs, group, weight, x, seen=None):
    """(rates, final weights) of Tukey-biweight IRLS from ``x``; robust scale max(1.4826 MAD, 1 floor unit)."""
    keep = weight
    for _ in range(ITERATIONS):
        res = _residuals(design, obs, group, keep, x)
        scale = max(1.4826 * float(np.median(res)), 1.0)
        keep = weight * (1.0 - np.clip(res / (TUKEY_C * scale), 0.0, 1.0) ** 2) ** 2
        new_x = _weighted_fit(design, obs, group, keep, seen)
        if np.allclose(new_x, x, rtol=0, atol=TOLERANCE):
            return new_x, keep
        x = new_x
    return x, keep


def _tukey_loss(u: np.ndarray) -> np.ndarray:
    """Tukey's biweight loss scaled to [0, 1] (1 beyond the cut-off) of residuals u in cut-off units."""
    return 1.0 - (1.0 - np.clip(np.abs(u), 0.0, 1.0) ** 2) ** 3


def _residuals(design, obs, group, weight, x) -> np.ndarray:
    """(M,) residual norm of each member about its group's weighted fit."""
    a, b = _centred(design, obs, group, weight)
    return np.linalg.norm(b - a @ x, axis=1)


def _weighted_fit(design, obs, group, weight, seen=None) -> np.ndarray:
    """Weighted least-squares x with the per-group intercepts eliminated (zero without rows), inside the
    directions that ``seen`` (a design like ``design``; None: design itself) constrains with these weights, and
    of minimum norm there."""
    a, b = _centred(design, obs, group, weight)
    sw = np.sqrt(weight)[:, None, None]
    p = design.shape[2]
    rows, rhs = (a * sw).reshape(-1, p), (b * sw[..., 0]).reshape(-1)
    if not np.any(rows):
        return np.zeros(p)
    basis = _constrained(_centred(seen, obs, group, weight)[0] * sw if seen is not None else a * sw)
    return basis @ np.linalg.lstsq(rows @ basis, rhs, rcond=RCOND)[0]


def _constrained(rows: np.ndarray) -> np.ndarray:
    """(P, r) orthonormal basis of the directions weighted design ``rows`` (..., P) constrains: right singular
    vectors with singular values above RCOND × the largest (from the P × P Gram matrix: squared values)."""
    rows = rows.reshape(-1, rows.shape[-1])
    power, vectors = np.linalg.eigh(rows.T @ rows)
    return vectors[:, power > RCOND ** 2 * power[-1]] if power[-1] > 0 else np.zeros((rows.shape[1], 0))


def _centred(design: np.ndarray, obs: np.ndarray, group: np.ndarray, weight: np.ndarray):
    """design and obs minus their weighted means per group (removes the per-group intercepts); ``group`` is
    the (M, G) one-hot membership matrix."""
    m, r, p = design.shape
    both = np.concatenate([design.reshape(m, r * p), obs], axis=1)
    total = group.T @ weight
    means = (group.T @ (weight[:, None] * both)) / np.where(total > 0, total, 1.0)[:, None]
    both = both - group @ means
    return both[:, :r * p].reshape(m, r, p), both[:, r * p:]


def rpe_estimate(rot_rate_deg_s: float, trans_rate_m_s: float, times) -> float:
    """RPE (Eq. 4, mean ‖E − I‖_F over consecutive pairs) that drift at these rates gives over scans at
    ``times`` (s): small-error form √(2 (ω Δt)² + (v Δt)²)."""
    dt = np.diff(np.sort(np.asarray(times, np.float64)))
    if not len(dt) or not np.isfinite(rot_rate_deg_s) or not np.isfinite(trans_rate_m_s):
        return float("nan")
    return float(np.mean(dt) * np.hypot(np.sqrt(2.0) * np.radians(rot_rate_deg_s), trans_rate_m_s))


def true_drift_rates(gt: np.ndarray, est: np.ndarray, times) -> tuple[float, float]:
    """(rotation deg/s, translation m/s) a window's poses truly drifted at, from ground truth: what
    :func:`drift_rates` estimates, all of it (drift_rates sees only the directions its planes constrain).
    gt, est (K, 4, 4) sensor poses of the window's scans at ``times`` (s); NaN, NaN for < 2 scans or no span.

    Each scan's error in the WINDOW frame (the first scan's), E_i = (est_0⁻¹ est_i)(gt_0⁻¹ gt_i)⁻¹, maps a
    true point to where the estimate puts it: x -> R_i x + p_i. The body-frame rates of the module docstring's
    model are least-squares fits (with an intercept, as the estimator's per-group means) of R_i's rotation
    vector ≈ c + A_i ω, then of p_i − B_i ω ≈ c' + A_i v (A, B from the true poses: drift_integrals), so
    per-scan jitter averages out instead of deciding the rate as it would through the first and last scan."""
    from ..geometry import inverse, matrix_to_rotvec, relative_to_first

    gt, est = np.asarray(gt, np.float64), np.asarray(est, np.float64)
    t = np.asarray(times, np.float64)
    if len(t) < 2 or np.ptp(t) <= 0:
        return float("nan"), float("nan")
    truth = relative_to_first(gt)
    err = relative_to_first(est) @ inverse(truth)
    turned, swept = drift_integrals(t, truth)
    omega = _slope(turned, matrix_to_rotvec(err[:, :3, :3]))
    v = _slope(turned, err[:, :3, 3] - swept @ omega)
    return float(np.degrees(np.linalg.norm(omega))), float(np.linalg.norm(v))


def _slope(a: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(3,) x of the least-squares fit y_k ≈ c + a_k x with a free intercept c; a (K, 3, 3), y (K, 3)."""
    a_c, y_c = a - a.mean(axis=0), y - y.mean(axis=0)
    return np.linalg.lstsq(a_c.reshape(-1, 3), y_c.reshape(-1), rcond=None)[0]
