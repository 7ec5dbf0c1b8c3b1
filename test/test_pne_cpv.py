"""PNE and CPV: analytic values, invariances, and monotonic response to pose noise on simulated windows."""
from __future__ import annotations

import itertools
import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.stats import spearmanr

from topometric_ros import geometry
from topometric_ros import classes as C
from topometric_ros.config import Config
from topometric_ros.metrics import cpv as cpv_mod
from topometric_ros.metrics import pne as pne_mod
from topometric_ros.pipeline import ProcessedScan, score_window
from topometric_ros.planes import fit_plane, planes_from_instances
from topometric_ros.sim.frames import simulated_frames

FLOOR = math.radians(pne_mod.FLOOR_DEG)


@pytest.fixture(scope="module")
def office_scans():
    """Six consecutive office1 scans with ground-truth poses and oracle planes (sensor frame)."""
    frames, instances = simulated_frames("office1", 6, seed=3)
    return [ProcessedScan(f.stamp, f.pose, planes_from_instances(f.points, f.labels, inst, frame=k))
            for k, (f, inst) in enumerate(zip(frames, instances))]


def perturbed(scans, rot_deg, trans_m, seed):
    noise = geometry.noise_transforms(len(scans), math.radians(rot_deg), trans_m, np.random.default_rng(seed))
    return [ProcessedScan(s.stamp, s.pose @ n, s.planes) for s, n in zip(scans, noise)]


def tilted(axis_angles):
    """Unit normals tilted from +z by (angle about x) in rad."""
    return np.array([[0.0, -math.sin(a), math.cos(a)] for a in axis_angles])


# ---------------------------------------------------------------- PNE
def test_pne_perfect_cluster_is_the_floor_entropy():
    h = pne_mod.pne(np.tile([0.0, 0.0, 1.0], (4, 1)), np.ones(4))
    assert h == pytest.approx(math.log(2 * math.pi * math.e) + math.log(FLOOR**2), abs=1e-12)


def test_pne_matches_analytic_two_normal_spread():
    a = math.radians(2.0)
    h = pne_mod.pne(tilted([a, -a]), np.array([10.0, 10.0]))
    det = (math.sin(a) ** 2 + FLOOR**2) * FLOOR**2  # population variance of ±sin a, floor on both axes
    assert h == pytest.approx(0.5 * math.log((2 * math.pi * math.e) ** 2 * det), abs=1e-9)


def test_pne_is_sign_invariant_and_rotation_invariant(rng):
    normals = np.concatenate([tilted(rng.normal(0, 0.02, 5)), tilted(rng.normal(0, 0.02, 4))[:, [2, 0, 1]]])
    weights = rng.integers(100, 5000, len(normals)).astype(float)
    ref = pne_mod.pne(normals, weights)
    flips = np.where(rng.random(len(normals)) < 0.5, -1.0, 1.0)[:, None]
    assert pne_mod.pne(normals * flips, weights) == pytest.approx(ref, abs=1e-9)
    rot = geometry.rotvec_to_matrix(rng.normal(size=3))
    assert pne_mod.pne(normals @ rot.T, weights) == pytest.approx(ref, abs=1e-9)


def test_pne_clusters_directions_and_skips_singletons(rng):
    z = tilted(rng.normal(0, 0.01, 6))
    x = z[:, [2, 0, 1]]
    lone = np.array([[math.sqrt(0.5), math.sqrt(0.5), 0.0]])  # 45° from both: its own singleton cluster
    normals = np.concatenate([z, -x, lone])
    clusters = pne_mod.pne_clusters(normals, np.ones(len(normals)))
    assert sorted(len(c.members) for c in clusters) == [6, 6]
    assert np.isnan(pne_mod.pne(lone, np.ones(1)))


def test_pne_weighted_mean_over_clusters():
    a, b = math.radians(1.0), math.radians(3.0)
    z = tilted([a, -a])
    x = tilted([b, -b])[:, [2, 0, 1]]
    hz = pne_mod.pne(z, np.ones(2))
    hx = pne_mod.pne(x, np.ones(2))
    both = pne_mod.pne(np.concatenate([z, x]), np.array([1.0, 1.0, 3.0, 3.0]))
    assert both == pytest.approx((2 * hz + 6 * hx) / 8, abs=1e-12)


def test_pne_matches_analytic_two_normal_spread_with_unequal_weights():
    """Weights 1 and 3: the mean direction is the principal axis at φ, tan 2φ = (w1 − w2) sin 2a / (W cos 2a),
    and the tangent variance the weighted population variance w1 w2 / W² (s1 − s2)² about the weighted mean."""
    a, (w1, w2) = math.radians(7.0), (1.0, 3.0)
    phi = 0.5 * math.atan2((w1 - w2) * math.sin(2 * a), (w1 + w2) * math.cos(2 * a))
    var = w1 * w2 / (w1 + w2) ** 2 * (math.sin(a - phi) - math.sin(-a - phi)) ** 2
    h = pne_mod.pne(tilted([a, -a]), np.array([w1, w2]))
    assert h == pytest.approx(0.5 * math.log((2 * math.pi * math.e) ** 2 * (var + FLOOR**2) * FLOOR**2), abs=1e-12)
    twice = pne_mod.pne(tilted([a, -a]), np.array([1.0, 2.0]))
    assert pne_mod.pne(tilted([a, -a, -a]), np.ones(3)) == pytest.approx(twice, abs=1e-12)  # weight 2: two copies


def test_the_heaviest_normal_seeds_its_cluster():
    """0°, 10°, 20° with the 0° one heaviest: its cluster (15°) takes 0° and 10°; 20° is left a singleton.
    A light seed at 10° would have swallowed all three."""
    normals, weights = tilted(np.radians([0.0, 10.0, 20.0])), np.array([10.0, 1.0, 1.0])
    clusters = pne_mod.pne_clusters(normals, weights)
    assert [sorted(c.members) for c in clusters] == [[0, 1]]
    assert pne_mod.pne(normals, weights) == pytest.approx(pne_mod.pne(normals[:2], weights[:2]), abs=1e-12)


# ---------------------------------------------------------------- CPV
def plane_points(rng, n, offset, sigma, normal=(0.0, 0.0, 1.0), extent=8.0):
    """n points on the plane normal·x = offset (in-plane square of side ``extent``) with N(0, σ²) noise."""
    normal = np.asarray(normal, float)
    basis = pne_mod.tangent_basis(normal)
    uv = rng.uniform(-extent / 2, extent / 2, (n, 2))
    return uv @ basis + (offset + rng.normal(0, sigma, n))[:, None] * normal


def planes_arrays(planes, scans):
    return (np.array([p.cls for p in planes]), np.asarray(scans), np.array([p.normal for p in planes]),
            np.array([p.mean for p in planes]), np.array([p.scatter for p in planes]),
            np.array([p.count for p in planes], float))


def test_cpv_equals_variance_of_all_points_along_the_normal(rng):
    pts = [plane_points(rng, 3000, 2.0 + o, 0.01) for o in (0.0, 0.03, -0.02, 0.05)]
    planes = [fit_plane(p, C.WALL) for p in pts]
    value = cpv_mod.cpv(*planes_arrays(planes, range(4)))
    assert value == pytest.approx(np.var(np.concatenate(pts)[:, 2]), rel=1e-3)


def test_cpv_matches_analytic_point_and_offset_noise(rng):
    """K scans of one plane, per-point σ and per-scan offset τ: E[CPV] = σ² + τ²(K − 1)/K (population form)."""
    k, sigma, tau = 5, 0.02, 0.02
    values = []
    for _ in range(150):
        offsets = 3.0 + rng.normal(0, tau, k)
        planes = [fit_plane(plane_points(rng, 400, o, sigma), C.FLOOR) for o in offsets]
        values.append(cpv_mod.cpv(*planes_arrays(planes, range(k))))
    assert np.mean(values) == pytest.approx(sigma**2 + tau**2 * (k - 1) / k, rel=0.1)


def test_cpv_needs_two_scans_and_separates_faces_and_far_planes(rng):
    one_scan = [fit_plane(plane_points(rng, 500, 2.0, 0.01), C.WALL) for _ in range(3)]
    assert np.isnan(cpv_mod.cpv(*planes_arrays(one_scan, [0, 0, 0])))
    # the two faces of a 0.15 m wall (opposite normals) and a parallel wall 1 m away never join
    front = [fit_plane(plane_points(rng, 500, 2.0, 0.01), C.WALL) for _ in range(2)]
    # the back face z = 2.15 as seen by a sensor beyond it: normal +z after orienting toward that sensor
    back = [replace(p, normal=-p.normal, offset=-p.offset)
            for p in (fit_plane(plane_points(rng, 500, 2.15, 0.01), C.WALL) for _ in range(2))]
    far = [fit_plane(plane_points(rng, 500, 3.0, 0.01), C.WALL) for _ in range(2)]
    planes = front + back + far
    groups = cpv_mod.coplane_groups(*planes_arrays(planes, [0, 1] * 3))
    assert sorted(tuple(sorted(g.members)) for g in groups) == [(0, 1), (2, 3), (4, 5)]
    assert all(g.variance == pytest.approx(1e-4, rel=0.3) for g in groups)
    # a different class never joins either
    other = [fit_plane(plane_points(rng, 500, 2.0, 0.01), cls) for cls in (C.WALL, C.PILLAR)]
    assert cpv_mod.coplane_groups(*planes_arrays(other, [0, 1])) == []


def test_cpv_segments_of_one_wall_form_one_group_without_blowup(rng):
    """15 scans × 3 co-planar segments: one group (a complete 15-partite graph would have 3^15 cliques)."""
    planes, scans = [], []
    for scan in range(15):
        for shift in (-6.0, 0.0, 6.0):
            pts = plane_points(rng, 200, 2.0, 0.01, extent=2.0)
            pts[:, 0] += shift
            planes.append(fit_plane(pts, C.WALL))
            scans.append(scan)
    groups = cpv_mod.coplane_groups(*planes_arrays(planes, scans))
    assert len(groups) == 1 and len(groups[0].members) == 45


def test_pooled_covariance_is_the_population_covariance_of_the_union(rng):
    sets = [rng.normal(size=(k, 3)) * [1.0, 2.0, 0.5] + rng.normal(size=3) for k in (3, 5, 4)]
    means = np.array([p.mean(axis=0) for p in sets])
    scatters = np.array([(p - p.mean(axis=0)).T @ (p - p.mean(axis=0)) for p in sets])
    mean, cov = cpv_mod.pooled_covariance([len(p) for p in sets], means, scatters)
    union = np.concatenate(sets)
    np.testing.assert_allclose(mean, union.mean(axis=0), atol=1e-12)
    np.testing.assert_allclose(cov, np.cov(union.T, bias=True), atol=1e-12)


def _flat_planes(offsets, scans, counts):
    """Horizontal wall patches at height z (normal +z, D = −z), a 4 m square of points each."""
    counts = np.asarray(counts, float)
    means = np.array([[0.0, 0.0, z] for z in offsets])
    scatters = counts[:, None, None] * np.diag([4.0 / 3, 4.0 / 3, 1e-4])
    return (np.full(len(offsets), C.WALL), np.asarray(scans), np.tile([0.0, 0.0, 1.0], (len(offsets), 1)), means,
            scatters, counts)


def test_the_largest_clique_takes_a_shared_plane_first():
    """Cliques {0, 1, 2} (z 0, 0, 0.2) and {2, 3} (z 0.2, 0.45) share plane 2: the larger takes it, and plane 3
    alone spans one scan, so it joins no group."""
    groups = cpv_mod.coplane_groups(*_flat_planes([0.0, 0.0, 0.2, 0.45], [0, 1, 2, 3], [100, 100, 100, 100]))
    assert [sorted(g.members.tolist()) for g in groups] == [[0, 1, 2]]


def test_between_cliques_of_one_size_the_one_with_more_points_takes_a_shared_plane():
    """{0, 1} and {1, 2} share plane 1; plane 2 has five times the points, so {1, 2} is taken and 0 is left out."""
    groups = cpv_mod.coplane_groups(*_flat_planes([0.0, 0.2, 0.4], [0, 1, 2], [100, 100, 500]))
    assert [sorted(g.members.tolist()) for g in groups] == [[1, 2]]


def test_cpv_of_several_groups_is_their_point_weighted_mean_and_each_group_keeps_its_normal(rng):
    floor = [plane_points(rng, 3000, 2.0, 0.01) for _ in range(2)]
    wall = [plane_points(rng, 200, o, 0.01, normal=(1.0, 0.0, 0.0)) for o in (5.0, 5.2)]
    planes = [fit_plane(p, C.FLOOR) for p in floor] + [fit_plane(p, C.WALL) for p in wall]
    arrays = planes_arrays(planes, [0, 1, 0, 1])
    groups = cpv_mod.coplane_groups(*arrays)
    assert sorted(sorted(g.members.tolist()) for g in groups) == [[0, 1], [2, 3]]
    points = floor + wall
    variances = []
    for g in groups:  # λ_min: the variance of the group's points along its normal, which is the planes' normal
        assert abs(g.normal @ arrays[2][g.members[0]]) == pytest.approx(1.0, abs=1e-4)
        variances.append(np.var(np.concatenate([points[i] for i in g.members]) @ g.normal))
        assert g.variance == pytest.approx(variances[-1], rel=1e-9)
    points_per_group = [sum(len(points[i]) for i in g.members) for g in groups]
    assert sorted(points_per_group) == [400, 6000] and variances[0] != pytest.approx(variances[1], rel=0.5)
    assert cpv_mod.cpv(*arrays) == pytest.approx(np.dot(points_per_group, variances) / 6400, rel=1e-9)


def brute_force_cliques(adj):
    n = len(adj)
    cliques = [set(s) for r in range(2, n + 1) for s in itertools.combinations(range(n), r)
               if all(adj[i, j] for i, j in itertools.combinations(s, 2))]
    return {frozenset(c) for c in cliques if not any(c < d for d in cliques)}


@pytest.mark.parametrize("seed", range(6))
def test_bron_kerbosch_finds_exactly_the_maximal_cliques(seed):
    rng = np.random.default_rng(seed)
    n = 9
    upper = np.triu(rng.random((n, n)) < 0.45, 1)
    adj = upper | upper.T
    found = {frozenset(int(i) for i in cpv_mod._bits(c)) for c in cpv_mod.maximal_cliques(adj)}
    assert found == brute_force_cliques(adj)


def test_each_plane_is_in_at_most_one_group_and_groups_span_two_scans(office_scans):
    noisy = perturbed(office_scans, 0.5, 0.1, seed=7)
    from topometric_ros.pipeline import window_planes

    wp = window_planes(noisy, geometry.relative_to_first(np.stack([s.pose for s in noisy])))
    groups = cpv_mod.coplane_groups(wp.classes, wp.scans, wp.normals, wp.means, wp.scatters, wp.counts)
    members = np.concatenate([g.members for g in groups])
    assert len(members) == len(set(members.tolist()))
    assert all(len(set(wp.scans[g.members].tolist())) >= 2 for g in groups)


# ---------------------------------------------------------------- windows
def test_metrics_unchanged_by_one_rigid_motion_of_all_poses(office_scans, rng):
    noisy = perturbed(office_scans, 0.5, 0.05, seed=1)
    ref = score_window(noisy, Config())
    g = geometry.make_pose(geometry.rotvec_to_matrix(rng.normal(size=3)), rng.normal(0, 20, 3))
    moved = score_window([ProcessedScan(s.stamp, g @ s.pose, s.planes) for s in noisy], Config())
    assert (moved.pne, moved.cpv, moved.n_groups) == (pytest.approx(ref.pne, abs=1e-9),
                                                      pytest.approx(ref.cpv, abs=1e-9), ref.n_groups)


def test_pne_unchanged_by_pure_translation_error(office_scans):
    clean = score_window(office_scans, Config())
    for seed in range(3):
        shifted = score_window(perturbed(office_scans, 0.0, 0.1, seed), Config())
        assert shifted.pne == pytest.approx(clean.pne, abs=1e-9)
        assert shifted.cpv > 2 * clean.cpv


def sweep(scans, levels, rot, seeds=3):
    """Mean (pne, cpv) per noise level over a few noise draws."""
    out = []
    for level in levels:
        rs = [score_window(perturbed(scans, level if rot else 0.0, 0.0 if rot else level, s), Config())
              for s in range(seeds)]
        out.append((np.mean([r.pne for r in rs]), np.mean([r.cpv for r in rs])))
    return np.array(out)


def test_pne_rises_with_rotation_noise(office_scans):
    levels = [0.0, 0.1, 0.25, 0.5, 1.0, 1.5]  # deg
    pne = sweep(office_scans, levels, rot=True)[:, 0]
    assert spearmanr(levels, pne).statistic >= 0.9


def test_cpv_rises_with_translation_noise(office_scans):
    levels = [0.0, 0.01, 0.02, 0.04, 0.07, 0.1]  # m (noise experiment: 0.05 m × scale 1..2)
    cpv = sweep(office_scans, levels, rot=False)[:, 1]
    assert spearmanr(levels, cpv).statistic >= 0.9


# ---------------------------------------------------------------- scan agreement
def _jumped(scans, k, rotvec_deg):
    """The scans with scan k's pose rotated by ``rotvec_deg`` about its own sensor origin (a pose jump)."""
    jump = geometry.make_pose(geometry.rotvec_to_matrix(np.radians(rotvec_deg)), np.zeros(3))
    return [ProcessedScan(s.stamp, s.pose @ jump if i == k else s.pose, s.planes) for i, s in enumerate(scans)]


def _shares(scans):
    """Each scan's agreement (cpv.scan_agreement) in the window of ``scans``."""
    from topometric_ros.pipeline import window_planes

    wp = window_planes(scans, geometry.relative_to_first(np.stack([s.pose for s in scans])))
    groups = cpv_mod.coplane_groups(wp.classes, wp.scans, wp.normals, wp.means, wp.scatters, wp.counts)
    return cpv_mod.scan_agreement(groups, wp.scans, wp.counts, len(scans))


def test_scan_agreement_is_the_share_a_jumped_scan_keeps_in_place(office_scans):
    """Right poses: every scan's planes are seen in place by another scan (agreement near 1, no alarm). A
    20° yaw of one scan about its sensor leaves exactly its horizontal planes (floor, ceiling) in place: its
    agreement is their share of its inliers (here 6 %: walls carry most of them; office1 is level, with no
    plane tilted 10-30° that a yaw would keep inside the angle gate). A 30° tilt and yaw leaves none: WARN
    "pose jump" at once."""
    from topometric_ros.health import Health

    right = score_window(office_scans, Config())
    assert right.agreement >= 0.9
    Health().assess(right)
    assert "pose jump" not in right.message
    planes = office_scans[2].planes
    horizontal = sum(p.count for p in planes if abs(p.normal[2]) > math.cos(math.radians(10)))
    yawed = score_window(_jumped(office_scans, 2, [0, 0, 20]), Config())
    assert 0 < yawed.agreement == pytest.approx(horizontal / sum(p.count for p in planes), abs=1e-9)
    assert yawed.agreement == pytest.approx(_shares(_jumped(office_scans, 2, [0, 0, 20]))[2], abs=1e-12)
    lost = score_window(_jumped(office_scans, 2, [30, 0, 30]), Config())
    assert lost.agreement < Config().health.agreement_warn
    assert Health().assess(lost).level == "WARN" and lost.agreement_scan == 2
    assert lost.message.startswith(f"pose jump: scan 3 of 6 (stamp {office_scans[2].stamp:.2f})")
    # the rate fit drops such a scan: the rates barely move
    assert lost.rot_rate < right.rot_rate + 0.5


def test_scan_agreement_counts_inliers_in_groups_per_scan_and_skips_scans_with_few_planes(rng):
    wall = [fit_plane(plane_points(rng, n, 2.0, 0.01), C.WALL) for n in (400, 300, 600)]
    far = fit_plane(plane_points(rng, 100, 5.0, 0.01), C.WALL)  # seen by scan 1 only
    planes, scans = wall + [far], [0, 1, 2, 1]
    arrays = planes_arrays(planes, scans)
    groups = cpv_mod.coplane_groups(*arrays)
    shares = cpv_mod.scan_agreement(groups, scans, arrays[-1], 4, min_planes=1)
    np.testing.assert_allclose(shares[:3], [1.0, 300 / 400, 1.0])
    assert np.isnan(shares[3])  # no planes
    # by default a scan needs 3 planes to be judged (a truncated cloud is not a pose jump): none here
    assert np.isnan(cpv_mod.scan_agreement(groups, scans, arrays[-1], 4)).all()
    assert cpv_mod.window_agreement(groups, scans, arrays[-1], 4)[1] == -1
    assert np.isnan(cpv_mod.window_agreement([], scans, arrays[-1], 4)[0])
