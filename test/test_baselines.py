"""MME, MPV, MOM: map-metrics' reference values, brute-force neighbourhoods, analytic cases, invariances."""
from __future__ import annotations


import numpy as np
import pytest

from topometric_ros import geometry
from topometric_ros.metrics import _neighbours as nb
from topometric_ros.metrics.mme import entropies, mme
from topometric_ros.metrics.mom import extract_orthogonal_subsets, mom
from topometric_ros.metrics.mpv import mme_mpv, mpv
from topometric_ros.metrics import reference_data as ref
from topometric_ros.metrics.reference_data import REF_MME, REF_MOM, REF_MPV



@pytest.fixture(scope="module")
def reference():
    data = ref.load()
    if data is None:
        pytest.skip(f"map-metrics reference data not found at {ref.folder()}")
    return data


def test_reference_values_of_map_metrics(reference):
    clouds, poses, orth = reference
    assert mme(clouds, poses, radius=0.2) == pytest.approx(REF_MME, abs=1e-8)
    assert mpv(clouds, poses, radius=0.2) == pytest.approx(REF_MPV, rel=1e-8)
    assert mom(clouds, poses, radius=0.2, orth_subsets=orth) == pytest.approx(REF_MOM, rel=1e-8)


def _brute(queries, sources, radius):
    counts, covs = [], []
    for q in queries:
        near = sources[np.sum((sources - q) ** 2, axis=1) < radius**2]
        counts.append(len(near))
        c = np.cov(near.T) if len(near) > 1 else np.zeros((3, 3))
        covs.append([c[a, b] for a, b in nb.SYM6])
    return np.array(counts), np.array(covs)


def test_ball_covariances_equal_brute_force(rng):
    centres = rng.uniform(-3, 3, (6, 3))
    src = np.concatenate([c + rng.normal(0, 0.4, (300, 3)) for c in centres]) + [100.0, -50.0, 7.0]
    queries = np.concatenate([src[:400], rng.uniform(-3, 3, (100, 3)) + [100.0, -50.0, 7.0]])
    counts, covs = nb.ball_covariances(queries, src, 0.7)
    ref_counts, ref_covs = _brute(queries, src, 0.7)
    np.testing.assert_array_equal(counts, ref_counts)
    np.testing.assert_allclose(covs, ref_covs, rtol=1e-10, atol=1e-14)


def test_self_neighbourhoods_equal_brute_force(rng):
    """Queries that are the sources (each pair found once, added to both ends) and a map wider than one
    tile (halved until 64 radii): the same counts and covariances as one query at a time."""
    centres = rng.uniform(-3, 3, (6, 3))
    src = np.concatenate([c + rng.normal(0, 0.4, (300, 3)) for c in centres]) + [100.0, -50.0, 7.0]
    wide = np.c_[rng.uniform(0, 60, 1500), rng.uniform(0, 1.0, 1500), rng.normal(0, 0.05, 1500)]
    for pts, radius in ((src, 0.7), (wide, 0.4)):
        counts, covs = nb.ball_covariances(pts, pts, radius)
        ref_counts, ref_covs = _brute(pts, pts, radius)
        np.testing.assert_array_equal(counts, ref_counts)
        np.testing.assert_allclose(covs, ref_covs, rtol=1e-10, atol=1e-14)
        assert counts.min() >= 1  # every point is its own neighbour


def test_weighted_self_neighbourhoods_equal_the_one_sided_ones(rng):
    pts = rng.uniform(-2, 2, (2000, 3)) * [1.0, 1.0, 0.1]
    weights = rng.integers(1, 6, len(pts)).astype(float)
    scatter = rng.uniform(0, 1e-4, (len(pts), 6))
    counts, covs = nb.ball_covariances(pts, pts, 0.5, weights, scatter)
    ref_counts, ref_covs = nb.ball_covariances(pts, pts.copy(), 0.5, weights, scatter)
    np.testing.assert_array_equal(counts, ref_counts)
    np.testing.assert_allclose(covs, ref_covs, rtol=1e-10, atol=1e-15)


def test_weighted_sources_equal_their_points(rng):
    """A source that summarises a tight cluster (count, centroid, scatter) counts exactly as its points
    when the cluster is not cut by the ball boundary."""
    grid = np.stack(np.meshgrid(*[np.arange(6) * 0.1 + 0.088] * 3, indexing="ij"), -1).reshape(-1, 3)
    pts = (grid[:, None, :] + rng.uniform(-5e-4, 5e-4, (len(grid), 5, 3))).reshape(-1, 3)
    centres, weights, scatter, _ = nb.voxel_moments(pts, 0.1)
    assert len(centres) == len(grid) and np.all(weights == 5)
    counts, covs = nb.ball_covariances(grid, centres, 0.25, weights, scatter)  # grid distances avoid 0.25
    ref_counts, ref_covs = nb.ball_covariances(grid, pts, 0.25)
    np.testing.assert_array_equal(counts, ref_counts)
    np.testing.assert_allclose(covs, ref_covs, rtol=1e-9, atol=1e-15)


def test_closed_form_eigenvalues_and_determinant(rng):
    a = rng.normal(size=(500, 3, 3))
    mats = a @ np.swapaxes(a, 1, 2)
    mats[:100] = np.diag([2.0, 2.0, 1e-9])  # near-degenerate pairs
    thin = np.diag([1.0, 1.0, 1e-2])
    mats[100:200] = thin @ mats[100:200] @ thin  # plane-like: λ_min ~ 1e-4 λ_max
    c6 = np.stack([mats[:, i, j] for i, j in nb.SYM6], axis=1)
    lam, ref = nb.sym_eigvals(c6), np.linalg.eigvalsh(mats)
    np.testing.assert_allclose(lam[:, 0], ref[:, 0], rtol=1e-9, atol=1e-15)  # λ_min: what MPV uses
    np.testing.assert_allclose(lam, ref, rtol=0, atol=1e-7 * ref[:, 2:].max())  # double roots lose √eps
    np.testing.assert_allclose(nb.sym_det(c6), np.linalg.det(mats), rtol=1e-9, atol=1e-20)
    np.testing.assert_array_equal(nb.to_matrix(c6), mats)


def test_entropy_of_a_diagonal_covariance():
    h = entropies(np.array([[0.1, 0, 0, 0.2, 0, 0.3], [1.0, 0, 0, 1.0, 0, 0.0]]))
    assert h[0] == pytest.approx(0.5 * np.log((2 * np.pi * np.e) ** 3 * 0.006), rel=1e-12)
    assert np.isnan(h[1])  # det 0: skipped by MME


def _plane_scans(rng, tilt=0.0):
    """Two scans of the plane z = 0 (second one optionally tilted about x) with identity-ish poses."""
    pts = np.c_[rng.uniform(-2, 2, (3000, 2)), np.zeros(3000)]
    poses = np.stack([np.eye(4), geometry.make_pose(geometry.rotvec_to_matrix([tilt, 0, 0]), [0.3, 0, 0])])
    return [pts, pts[::2]], poses


def test_perfect_plane_gives_zero_variance_and_no_entropy(rng):
    clouds, poses = _plane_scans(rng)
    assert mpv(clouds, poses, radius=0.5) == pytest.approx(0.0, abs=1e-15)
    assert mme(clouds, poses, radius=0.5) == 0.0  # every det is 0: no point counts, as map-metrics
    tilted, poses_t = _plane_scans(rng, tilt=0.05)
    assert mpv(tilted, poses_t, radius=0.5) > 1e-5  # a rotation error thickens the plane


@pytest.fixture(scope="module")
def small_window():
    from topometric_ros.sim.frames import simulated_frames

    frames, _ = simulated_frames("office1", 3)
    return [f.points[::8] for f in frames], np.stack([f.pose for f in frames])


def test_rigid_transform_of_all_poses_changes_no_metric(small_window, rng):
    clouds, poses = small_window
    moved = geometry.noise_transforms(1, 1.0, 20.0, rng)[0] @ poses
    for fn in (mme, mpv):
        assert fn(clouds, moved, radius=0.5) == pytest.approx(fn(clouds, poses, radius=0.5), rel=1e-9)
        assert fn(clouds, moved, radius=0.5, exact=False) == pytest.approx(
            fn(clouds, poses, radius=0.5, exact=False), rel=1e-9)
    subsets, _ = extract_orthogonal_subsets(clouds[0], 0.5)
    assert mom(clouds, moved, 0.5, orth_subsets=subsets) == pytest.approx(
        mom(clouds, poses, 0.5, orth_subsets=subsets), rel=1e-9)


def test_fast_approximation_within_half_a_percent(small_window):
    clouds, poses = small_window
    exact = mme_mpv(clouds, poses, radius=0.5)
    fast = mme_mpv(clouds, poses, radius=0.5, exact=False)
    assert fast[0] == pytest.approx(exact[0], rel=5e-3)
    assert fast[1] == pytest.approx(exact[1], rel=5e-3)
    assert exact == (mme(clouds, poses, radius=0.5), mpv(clouds, poses, radius=0.5))


def test_query_subsample_is_seeded_and_close(small_window):
    clouds, poses = small_window
    full = mpv(clouds, poses, radius=0.5)
    a = mpv(clouds, poses, radius=0.5, max_queries=5000, seed=3)
    assert a == mpv(clouds, poses, radius=0.5, max_queries=5000, seed=3)
    assert a != mpv(clouds, poses, radius=0.5, max_queries=5000, seed=4)
    assert a == pytest.approx(full, rel=0.1)


def test_pose_error_raises_the_baselines(small_window, rng):
    clouds, poses = small_window
    noisy = poses @ geometry.noise_transforms(len(poses), np.radians(2.0), 0.05, rng)
    noisy[0] = poses[0]
    assert mme(clouds, noisy, radius=0.5) > mme(clouds, poses, radius=0.5)
    assert mpv(clouds, noisy, radius=0.5) > mpv(clouds, poses, radius=0.5)


def test_orthogonal_subsets_of_a_box_corner(rng):
    n = 1500
    floor = np.c_[rng.uniform(0, 3, (n, 2)), rng.normal(0, 0.002, n)]
    wall_x = np.c_[rng.normal(0, 0.002, n), rng.uniform(0, 3, (n, 2))]
    wall_y = np.c_[rng.uniform(0, 3, n), rng.normal(0, 0.002, n), rng.uniform(0, 3, n)]
    rot = geometry.rotvec_to_matrix([0.2, -0.1, 0.7])
    cloud = np.concatenate([floor, wall_x, wall_y]) @ rot.T
    subsets, normals = extract_orthogonal_subsets(cloud, radius=0.3)
    assert len(subsets) == 3
    axes = np.abs(np.array(normals) @ rot)  # normals in the box frame: a permutation of the axes
    np.testing.assert_allclose(np.sort(axes.max(axis=1)), 1.0, atol=1e-3)
    assert sorted(np.argmax(axes, axis=1)) == [0, 1, 2]
    # Open3D normals are unoriented and Ward distances grow with cluster size, so a plane is split in
    # several clusters (as in map-metrics) and the subset is the largest such part
    assert all(len(s) > 0.2 * n for s in subsets)
    value = mom([cloud], np.eye(4)[None], radius=0.3)
    assert 0 < value < 3 * 1e-5  # three planes of 2 mm noise: λ_min ≈ σ² each


def test_bad_input_is_a_clear_error():
    with pytest.raises(ValueError, match="poses"):
        mme([np.zeros((5, 3))], np.eye(4)[None].repeat(2, axis=0))
    with pytest.raises(ValueError, match="radius"):
        mpv([np.zeros((5, 3))], np.eye(4)[None], radius=0.0)


def test_an_empty_map_gives_the_same_baselines_on_both_paths(tmp_path):
    """A window whose scans kept no points: the fast approximation gives what the exact path gives (0, 0),
    not a crash; a PLY cut inside its header is a ValueError, not an endless read."""
    empty, poses = [np.zeros((0, 3))] * 2, np.stack([np.eye(4)] * 2)
    assert mme_mpv(empty, poses, 1.0, 5, False) == mme_mpv(empty, poses, 1.0, 5, True) == (0.0, 0.0)
    cut = tmp_path / "cut.ply"
    cut.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n")
    with pytest.raises(ValueError, match="without end_header"):
        ref.read_ply(cut)
