import numpy as np
import pytest

from topometric_ros import geometry as g


def random_poses(rng, n):
    return g.make_pose(g.rotvec_to_matrix(rng.normal(size=(n, 3))), rng.normal(size=(n, 3)) * 5)


def test_quaternion_matrix_round_trip(rng):
    q = rng.normal(size=(500, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0] *= -1
    r = g.quat_to_matrix(q)
    np.testing.assert_allclose(r @ np.swapaxes(r, 1, 2), np.broadcast_to(np.eye(3), r.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-12)
    np.testing.assert_allclose(g.matrix_to_quat(r), q, atol=1e-12)


def test_quaternion_known_value():
    # 90 degrees about z maps x to y
    r = g.quat_to_matrix([0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)])
    np.testing.assert_allclose(r @ [1, 0, 0], [0, 1, 0], atol=1e-15)


def test_non_unit_quaternion_is_normalised_and_zero_rejected():
    np.testing.assert_allclose(g.quat_to_matrix([0, 0, 0, 7.0]), np.eye(3))
    with pytest.raises(ValueError):
        g.quat_to_matrix([0, 0, 0, 0])


def test_inverse_and_compose(rng):
    t = random_poses(rng, 100)
    np.testing.assert_allclose(g.inverse(t) @ t, np.broadcast_to(np.eye(4), t.shape), atol=1e-12)
    rel = g.relative_to_first(t)
    np.testing.assert_allclose(rel[0], np.eye(4), atol=1e-12)


def test_rotvec_round_trip_including_small_and_near_pi(rng):
    v = rng.normal(size=(300, 3))
    v *= (rng.uniform(0, np.pi - 1e-6, 300) / np.linalg.norm(v, axis=1))[:, None]
    v[:5] *= 1e-10
    np.testing.assert_allclose(g.matrix_to_rotvec(g.rotvec_to_matrix(v)), v, atol=1e-9)


def test_interpolation_hits_samples_and_midpoints(rng):
    stamps = np.array([0.0, 1.0, 3.0])
    poses = random_poses(rng, 3)
    out, valid = g.interpolate_poses(stamps, poses, stamps)
    np.testing.assert_allclose(out, poses, atol=1e-12)
    assert valid.all()
    # Midpoint: rotation halfway (angle to both ends equal), translation the mean.
    mid, _ = g.interpolate_poses(stamps, poses, [0.5])
    np.testing.assert_allclose(mid[0, :3, 3], poses[:2, :3, 3].mean(0), atol=1e-12)
    a0 = g.rotation_angle(mid[0, :3, :3].T @ poses[0, :3, :3])
    a1 = g.rotation_angle(mid[0, :3, :3].T @ poses[1, :3, :3])
    assert a0 == pytest.approx(a1, abs=1e-9)
    _, valid = g.interpolate_poses(stamps, poses, [-0.1, 3.1, 2.0])
    assert valid.tolist() == [False, False, True]


def test_noise_transforms_have_requested_spread(rng):
    n = g.noise_transforms(20000, 0.01, 0.05, rng)
    angles = g.rotation_angle(n[:, :3, :3])
    # |N(0, s)| has mean s * sqrt(2/pi)
    assert angles.mean() == pytest.approx(0.01 * np.sqrt(2 / np.pi), rel=0.03)
    assert n[:, :3, 3].std() == pytest.approx(0.05, rel=0.03)
    zero = g.noise_transforms(10, 0.0, 0.0, rng)
    np.testing.assert_allclose(zero, np.broadcast_to(np.eye(4), zero.shape))


def test_transform_points_keeps_dtype(rng):
    t = random_poses(rng, 1)[0]
    p = rng.normal(size=(50, 3)).astype(np.float32)
    out = g.transform_points(t, p)
    assert out.dtype == np.float32
    np.testing.assert_allclose(out, (t[:3, :3] @ p.T).T + t[:3, 3], atol=1e-5)


def test_interpolation_turns_the_short_way_round():
    """From yaw +170° to yaw −170° is a 20° turn through 180°, not a 340° one through 0° (the quaternions of the
    two have a negative dot product)."""
    poses = g.yaw_pose(0.0, 0.0, 0.0, np.radians([170.0, -170.0]))
    out, _ = g.interpolate_poses(np.array([0.0, 1.0]), poses, [0.25, 0.5])
    assert g.rotation_angle(out[1, :3, :3]) == pytest.approx(np.pi, abs=1e-9)
    assert g.rotation_angle(poses[0, :3, :3].T @ out[0, :3, :3]) == pytest.approx(np.radians(5.0), abs=1e-9)


def test_a_query_outside_the_pose_stream_gets_the_nearest_end_pose_and_is_invalid(rng):
    stamps = np.array([0.0, 1.0, 3.0])
    poses = random_poses(rng, 3)
    out, valid = g.interpolate_poses(stamps, poses, [-0.5, 3.5])
    np.testing.assert_allclose(out, poses[[0, 2]], atol=1e-12)
    assert valid.tolist() == [False, False]
