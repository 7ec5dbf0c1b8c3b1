"""SE(3) helpers, all vectorised over leading axes.

Conventions: quaternions are (x, y, z, w) as in ROS messages; a pose is a 4×4 float64 matrix that maps
points from its own frame (sensor) into the parent frame (map): p_map = T @ p_sensor.
"""
from __future__ import annotations

import numpy as np


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions (x, y, z, w), normalised here, -> (..., 3, 3) rotation matrices."""
    q = np.asarray(q, dtype=np.float64)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(norm == 0) or not np.all(np.isfinite(norm)):
        raise ValueError("quaternion with zero or non-finite norm")
    x, y, z, w = np.moveaxis(q / norm, -1, 0)
    r = np.empty(q.shape[:-1] + (3, 3))
    r[..., 0, 0] = 1 - 2 * (y * y + z * z)
    r[..., 0, 1] = 2 * (x * y - z * w)
    r[..., 0, 2] = 2 * (x * z + y * w)
    r[..., 1, 0] = 2 * (x * y + z * w)
    r[..., 1, 1] = 1 - 2 * (x * x + z * z)
    r[..., 1, 2] = 2 * (y * z - x * w)
    r[..., 2, 0] = 2 * (x * z - y * w)
    r[..., 2, 1] = 2 * (y * z + x * w)
    r[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return r


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions (x, y, z, w) with w >= 0."""
    r = np.asarray(r, dtype=np.float64)
    m = r.reshape(-1, 3, 3)
    # Each of the four candidate formulas is stable where its component is the largest.
    diag = np.stack([m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], axis=1)
    trace = diag.sum(axis=1)
    cand = np.stack([1 + 2 * diag[:, 0] - trace, 1 + 2 * diag[:, 1] - trace,
                     1 + 2 * diag[:, 2] - trace, 1 + trace], axis=1)
    k = np.argmax(cand, axis=1)
    s = np.sqrt(np.maximum(cand[np.arange(len(m)), k], 1e-300)) * 2  # s = 4 * |largest component|
    q = np.empty((len(m), 4))
    a = lambda i, j: m[:, i, j]  # noqa: E731
    # x largest
    q0 = np.stack([s / 4, (a(0, 1) + a(1, 0)) / s, (a(0, 2) + a(2, 0)) / s, (a(2, 1) - a(1, 2)) / s], 1)
    q1 = np.stack([(a(0, 1) + a(1, 0)) / s, s / 4, (a(1, 2) + a(2, 1)) / s, (a(0, 2) - a(2, 0)) / s], 1)
    q2 = np.stack([(a(0, 2) + a(2, 0)) / s, (a(1, 2) + a(2, 1)) / s, s / 4, (a(1, 0) - a(0, 1)) / s], 1)
    q3 = np.stack([(a(2, 1) - a(1, 2)) / s, (a(0, 2) - a(2, 0)) / s, (a(1, 0) - a(0, 1)) / s, s / 4], 1)
    for i, qi in enumerate((q0, q1, q2, q3)):
        q[k == i] = qi[k == i]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0] *= -1
    return q.reshape(r.shape[:-2] + (4,))


def make_pose(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations and (..., 3) translations -> (..., 4, 4) poses."""
    rotation = np.asarray(rotation, dtype=np.float64)
    translation = np.asarray(translation, dtype=np.float64)
    shape = np.broadcast_shapes(rotation.shape[:-2], translation.shape[:-1])
    t = np.zeros(shape + (4, 4))
    t[..., :3, :3] = rotation
    t[..., :3, 3] = translation
    t[..., 3, 3] = 1.0
    return t


def pose_from_quat(q: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions (x, y, z, w) and (..., 3) translations -> (..., 4, 4) poses."""
    return make_pose(quat_to_matrix(q), translation)


def pose_to_quat(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 4, 4) poses -> ((..., 4) quaternions (x, y, z, w), (..., 3) translations)."""
    t = np.asarray(t, dtype=np.float64)
    return matrix_to_quat(t[..., :3, :3]), t[..., :3, 3].copy()


def inverse(t: np.ndarray) -> np.ndarray:
    """Exact inverse of (..., 4, 4) rigid transforms (R^T, -R^T t)."""
    t = np.asarray(t, dtype=np.float64)
    rt = np.swapaxes(t[..., :3, :3], -1, -2)
    return make_pose(rt, -np.einsum("...ij,...j->...i", rt, t[..., :3, 3]))


def relative_to_first(poses: np.ndarray) -> np.ndarray:
    """(N, 4, 4) sensor-to-map poses -> poses in the frame of the first one (T_1^-1 T_i)."""
    return inverse(poses[0]) @ poses


def transform_points(t: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply one 4×4 transform to (N, 3) points; keeps the points' float dtype."""
    t = np.asarray(t)
    out = points @ t[:3, :3].T.astype(points.dtype, copy=False)
    out += t[:3, 3].astype(points.dtype, copy=False)
    return out


def rotvec_to_matrix(v: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors (axis × angle, rad) -> (..., 3, 3) matrices (Rodrigues)."""
    v = np.asarray(v, dtype=np.float64)
    theta = np.linalg.norm(v, axis=-1)[..., None, None]
    k = np.zeros(v.shape[:-1] + (3, 3))
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    k = k - np.swapaxes(k, -1, -2)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24, (1 - np.cos(safe)) / safe**2)
    return np.eye(3) + a * k + b * (k @ k)


def matrix_to_rotvec(r: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 3) rotation vectors, angle in [0, pi]."""
    q = matrix_to_quat(r)
    s = np.linalg.norm(q[..., :3], axis=-1, keepdims=True)
    angle = 2 * np.arctan2(s, q[..., 3:4])
    scale = np.where(s < 1e-12, 2.0, angle / np.where(s < 1e-12, 1.0, s))
    return q[..., :3] * scale


def rotation_angle(r: np.ndarray) -> np.ndarray:
    """Angle (rad) of (..., 3, 3) rotations, robust near 0 and pi."""
    return np.linalg.norm(matrix_to_rotvec(r), axis=-1)


def slerp(q0: np.ndarray, q1: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Spherical interpolation of (..., 4) unit quaternions at fractions u (...,), shortest path."""
    q0, q1 = np.asarray(q0, float), np.asarray(q1, float).copy()
    u = np.asarray(u, float)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    dot = np.abs(dot)
    omega = np.arccos(np.clip(dot, -1.0, 1.0))
    so = np.sin(omega)
    near = so < 1e-9
    w0 = np.where(near, 1 - u, np.sin((1 - u) * omega) / np.where(near, 1, so))
    w1 = np.where(near, u, np.sin(u * omega) / np.where(near, 1, so))
    q = w0 * q0 + w1 * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def interpolate_poses(stamps: np.ndarray, poses: np.ndarray, query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Poses at query stamps (s) from a sorted pose stream: slerp on rotation, linear on translation.

    Returns ((K, 4, 4) poses, (K,) bool valid): a query outside [stamps[0], stamps[-1]] is invalid and
    gets the nearest end pose.
    """
    stamps = np.asarray(stamps, float)
    query = np.atleast_1d(np.asarray(query, float))
    if len(stamps) == 0:
        raise ValueError("no poses to interpolate from")
    valid = (query >= stamps[0]) & (query <= stamps[-1])
    if len(stamps) == 1:
        return np.repeat(poses[:1], len(query), axis=0), valid & (query == stamps[0])
    i = np.clip(np.searchsorted(stamps, query, side="right") - 1, 0, len(stamps) - 2)
    span = stamps[i + 1] - stamps[i]
    u = np.clip((query - stamps[i]) / np.where(span > 0, span, 1.0), 0.0, 1.0)
    q, t = pose_to_quat(poses)
    q_out = slerp(q[i], q[i + 1], u)
    t_out = t[i] + u[:, None] * (t[i + 1] - t[i])
    return pose_from_quat(q_out, t_out), valid


def random_unit_vectors(n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) directions uniform on the sphere."""
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def noise_transforms(n: int, rot_sigma: float, trans_sigma: float, rng: np.random.Generator) -> np.ndarray:
    """(n, 4, 4) random rigid perturbations.

    Rotation: about a uniformly random axis by an angle ~ N(0, rot_sigma) (rad).
    Translation: ~ N(0, trans_sigma^2 I) (m per axis).
    """
    angles = rng.normal(0.0, rot_sigma, size=n) if rot_sigma > 0 else np.zeros(n)
    rot = rotvec_to_matrix(random_unit_vectors(n, rng) * angles[:, None])
    trans = rng.normal(0.0, trans_sigma, size=(n, 3)) if trans_sigma > 0 else np.zeros((n, 3))
    return make_pose(rot, trans)


def yaw_pose(x, y, z, yaw, roll=0.0, pitch=0.0) -> np.ndarray:
    """(..., 4, 4) poses from positions (m) and ZYX Euler angles (rad); arguments broadcast."""
    x, y, z, yaw, roll, pitch = np.broadcast_arrays(*(np.asarray(a, float) for a in (x, y, z, yaw, roll, pitch)))
    cy, sy, cp, sp, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    r = np.stack([np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
                  np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
                  np.stack([-sp, cp * sr, cp * cr], -1)], -2)
    return make_pose(r, np.stack([x, y, z], -1))
