"""The simulator: labels, geometry against ground truth, determinism, drift, trajectories, split."""
import json

import numpy as np
import pytest

from topometric_ros import bag, classes as C, geometry
from topometric_ros.cli import main
from topometric_ros.cloud import read_scan
from topometric_ros.sim.drift import (BASE_DRIFT_ROT_DEG_S, BASE_DRIFT_TRANS_M_S, BASE_NOISE_ROT_DEG, DriftSpec,
                                      Episode, estimated_poses, plan_episodes)
from topometric_ros.sensors import DEFAULT_SENSOR, sensor
from topometric_ros.sim.lidar import Lidar
from topometric_ros.sim.scenes import make_scene
from topometric_ros.sim.trajectory import free_space, random_trajectory
from topometric_ros.sim.writer import SimConfig, simulate

SENSOR_HEIGHT = 1.0


def scans_along_route(name, n=15, seed=0):
    scene = make_scene(name)
    rng = np.random.default_rng(seed)
    traj = random_trajectory(scene, 60.0, 1.2, 0.0, rng)
    poses = traj.poses_at(np.linspace(1, 59, n)) @ geometry.make_pose(np.eye(3), [0, 0, SENSOR_HEIGHT])
    lidar = Lidar(scene)
    return scene, poses, [lidar.scan(p, rng) for p in poses]


@pytest.mark.parametrize("name", ["garage", "floor2", "office1", "office2"])
def test_every_class_appears_and_labels_match_instances(name):
    scene, _, scans = scans_along_route(name)
    labels = np.concatenate([s.label for s in scans])
    counts = np.bincount(labels, minlength=C.NUM_CLASSES)
    assert (counts > 0).all(), dict(zip(C.NAMES, counts))
    inst = np.concatenate([s.instance for s in scans])
    np.testing.assert_array_equal(scene.instance_class[inst], labels)


@pytest.mark.parametrize("name", ["garage", "floor2"])
def test_wall_points_lie_on_their_plane_instance(name):
    scene, poses, scans = scans_along_route(name)
    sigma = sensor(DEFAULT_SENSOR).range_noise
    for pose, scan in zip(poses, scans):
        wall = scan.label == C.WALL
        assert wall.sum() > 100
        p_map = geometry.transform_points(pose, scan.points[wall].astype(np.float64))
        plane = scene.planes[scan.instance[wall]]
        dist = np.abs(np.einsum("ij,ij->i", p_map, plane[:, :3]) + plane[:, 3])
        assert dist.max() <= 0.03 + 3 * sigma
        # Noise really is there (a simulator without range noise would make this test vacuous).
        assert 0.5 * sigma < dist.mean() < 1.5 * sigma


def test_bag_points_agree_with_scene_at_ground_truth_pose(office_bag):
    """Scans from the bag, each point placed with /odom_gt interpolated at ITS OWN time (header stamp + the
    driver's per-point time: the sweep is motion-distorted) and /tf_static, land on the scene's surfaces with
    the label the scene has there: bag time, per-point times, poses, extrinsic and labels all agree."""
    import open3d as o3d

    path, summary = office_bag
    scene = make_scene("office1")
    lidar = Lidar(scene)
    stamps, gt = bag.read_odometry(path, "/odom_gt")
    (_, _, tf), = bag.read_messages(path, ["/tf_static"])
    tr = tf.transforms[0].transform
    extrinsic = geometry.pose_from_quat([tr.rotation.x, tr.rotation.y, tr.rotation.z, tr.rotation.w],
                                        [tr.translation.x, tr.translation.y, tr.translation.z])
    sigma = sensor(DEFAULT_SENSOR).range_noise
    for k, (_, _, msg) in enumerate(bag.read_messages(path, ["/points"])):
        if k % 10:
            continue
        scan = read_scan(msg)
        assert scan.time is not None and 0.09 < np.ptp(scan.time) <= 0.1  # one 10 Hz sweep
        assert scan.time.max() <= 0  # velodyne_pointcloud stamps the last packet: times before it
        pose = geometry.interpolate_poses(stamps, gt, scan.stamp + scan.time.astype(np.float64))[0] @ extrinsic
        pts = scan.points.astype(np.float64)
        dirs = np.einsum("nij,nj->ni", pose[:, :3, :3], pts / np.linalg.norm(pts, axis=1, keepdims=True))
        rays = np.hstack([pose[:, :3, 3], dirs]).astype(np.float32)
        hit = lidar._rc.cast_rays(o3d.core.Tensor(rays))
        err = np.abs(hit["t_hit"].numpy() - np.linalg.norm(pts, axis=1))
        prim = hit["primitive_ids"].numpy()
        assert np.median(err) < 0.8 * sigma + 0.002 and np.quantile(err, 0.99) < 0.03 + 3 * sigma
        agree = scene.tri_class[prim[err < 0.05]] == scan.labels[err < 0.05]
        assert agree.mean() > 0.999


def test_same_config_gives_same_bag(tmp_path):
    cfg = SimConfig(scene="office1", frames=4, seed=3, drift=DriftSpec.parse("r:2", "noise"))
    for d in ("a", "b"):
        simulate(cfg, tmp_path / d, progress=False)
    msgs = [[(t, m) for _, t, m in bag.read_messages(tmp_path / d, ["/points", "/odom"])] for d in ("a", "b")]
    assert len(msgs[0]) == len(msgs[1]) > 4
    for (ta, ma), (tb, mb) in zip(*msgs):
        assert ta == tb
        if hasattr(ma, "data"):
            np.testing.assert_array_equal(ma.data, mb.data)
        else:
            assert ma.pose.pose.orientation.z == mb.pose.pose.orientation.z


def straight_line(n=401, dt=0.05):
    stamps = np.arange(n) * dt
    return stamps, geometry.yaw_pose(stamps * 1.0, 0.0 * stamps, 0.0, 0.01 * stamps)


def test_drift_episode_accumulates_at_its_rate_and_only_inside():
    stamps, gt = straight_line()
    spec = DriftSpec("rt", 1.5)
    ep = Episode(5.0, 12.0, np.radians(BASE_DRIFT_ROT_DEG_S) * 1.5, BASE_DRIFT_TRANS_M_S * 1.5, (0, 0, 1.0), (0, 1.0, 0))
    est = estimated_poses(stamps, gt, spec, [ep], np.random.default_rng(0))
    err = geometry.inverse(gt) @ est
    before, after = stamps <= 5.0, stamps >= 12.0
    np.testing.assert_allclose(err[before], np.broadcast_to(np.eye(4), err[before].shape), atol=1e-12)
    # total rotation error at the end = rate × duration
    assert geometry.rotation_angle(err[-1][:3, :3]) == pytest.approx(ep.rot_rate * 7.0, rel=1e-6)
    # after the episode the estimate moves exactly like ground truth (no new drift)
    rel_gt = geometry.inverse(gt[after][:-1]) @ gt[after][1:]
    rel_est = geometry.inverse(est[after][:-1]) @ est[after][1:]
    np.testing.assert_allclose(rel_est, rel_gt, atol=1e-9)


def test_episodes_planned_after_warmup_with_modes():
    rng = np.random.default_rng(0)
    eps = plan_episodes(0.0, 300.0, DriftSpec("t", 2.0), rng)
    assert len(eps) >= 5 and eps[0].start >= 20.0 and eps[-1].end <= 300.0
    assert all(e.rot_rate == 0 and e.trans_rate == pytest.approx(2 * BASE_DRIFT_TRANS_M_S) for e in eps)
    assert all(b.start - a.end >= 15.0 for a, b in zip(eps, eps[1:]))
    assert plan_episodes(0.0, 300.0, DriftSpec("none"), rng) == []


def test_noise_kind_perturbs_each_pose_with_scaled_sigma():
    stamps, gt = straight_line(n=4000)
    est = estimated_poses(stamps, gt, DriftSpec("r", 2.0, "noise"), [], np.random.default_rng(0))
    err = geometry.inverse(gt) @ est
    angles = geometry.rotation_angle(err[:, :3, :3])
    assert angles.mean() == pytest.approx(np.radians(2 * BASE_NOISE_ROT_DEG) * np.sqrt(2 / np.pi), rel=0.05)
    np.testing.assert_allclose(err[:, :3, 3], 0, atol=1e-12)


@pytest.mark.parametrize("name", ["floor2", "garage"])
def test_trajectory_stays_in_free_space(name):
    scene = make_scene(name)
    space = free_space(scene, resolution=0.2)
    traj = random_trajectory(scene, 120.0, 1.2, 0.0, np.random.default_rng(5))
    xy = traj.poses[:, :2, 3]
    cells = np.round((xy - space.origin) / space.resolution).astype(int)
    clearance = space.clearance[cells[:, 1], cells[:, 0]]
    assert clearance.min() > 0.3  # planned with 0.45 m clearance, a little lost to smoothing
    speed = np.linalg.norm(np.diff(xy, axis=0), axis=1) / np.diff(traj.stamps)
    assert speed[-100:].mean() == pytest.approx(1.2, rel=0.02)


@pytest.mark.parametrize("name, layout", [("floor2", 3), ("floor2", 7), ("office2", 0)])
def test_a_fast_route_never_passes_through_a_thin_wall(name, layout):
    """Walls are 0.15 m thick, free-space cells 0.2 m: a wall between two rows of cell centres was once not
    rasterised, and 4 m/s routes drove along inside it (floor2 layout 7: base inside a wall 1.8 % of the
    time). Distances here are to the footprints themselves, not to the raster."""
    scene = make_scene(name, layout)
    boxes = np.array(scene.footprints)
    lo, hi = boxes.min(1), boxes.max(1)  # floor2 and office walls are axis-aligned: the box is the footprint
    traj = random_trajectory(scene, 60.5, 4.0, 0.0, np.random.default_rng(5203))
    xy = traj.poses[:, :2, 3]
    outside = np.maximum(np.maximum(lo[None] - xy[:, None], xy[:, None] - hi[None]), 0.0)
    assert np.linalg.norm(outside, axis=-1).min() > 0.25  # planned 0.45 m clear on 0.2 m cells


def test_cli_split_writes_disjoint_train_and_test(tmp_path, capsys):
    rc = main(["simulate", "--scene", "office1,office2", "--frames", "3", "--split", "--train", "1", "--test", "1",
               "--out", str(tmp_path / "set")])
    assert rc == 0
    index = json.loads((tmp_path / "set" / "split.json").read_text())
    assert sorted((s["split"], s["config"]["scene"]) for s in index) == [
        ("test", "office1"), ("test", "office2"), ("train", "office1"), ("train", "office2")]
    for scene in ("office1", "office2"):
        starts = [bag.read_odometry(tmp_path / "set" / split / f"{scene}_0", "/odom_gt")[1][0, :3, 3]
                  for split in ("train", "test")]
        assert np.linalg.norm(starts[0] - starts[1]) > 0.5
    assert "wrote 4 bags" in capsys.readouterr().out
    assert main(["simulate", "--scene", "office1", "--frames", "3", "--quiet", "--out", str(tmp_path / "q")]) == 0
    assert "simulate office1" not in capsys.readouterr().err  # --quiet: no progress bar


def test_cli_rejects_bad_arguments(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["simulate", "--scene", "moon", "--out", str(tmp_path / "x")])
    assert main(["simulate", "--scene", "office1", "--drift", "q:1", "--out", str(tmp_path / "y")]) == 2
    assert "drift mode" in capsys.readouterr().err


def test_heading_turns_at_a_bounded_smooth_rate_so_odometry_interpolates_well():
    """Routes double back; the robot's heading must still turn at a physical rate, or poses interpolated from
    20 Hz odometry at scan stamps are off by tens of degrees (drift alarms on drift-free bags)."""
    from topometric_ros.sim.trajectory import MAX_YAW_RATE_DEG

    worst = 0.0
    for seed in range(3):
        traj = random_trajectory(make_scene("office1"), 150.0, 1.2, 0.0, np.random.default_rng(seed))
        yaw = np.unwrap(np.arctan2(traj.poses[:, 1, 0], traj.poses[:, 0, 0]))
        rate = np.degrees(np.abs(np.diff(yaw))) / np.diff(traj.stamps)
        assert rate.max() <= MAX_YAW_RATE_DEG * 1.001
        odom_t = np.arange(0.013, 149.0, 0.05)  # 20 Hz odometry, offset from the scans as the writer does
        scan_t = np.arange(0.5, 148.5, 0.2)
        interp = geometry.interpolate_poses(odom_t, traj.poses_at(odom_t), scan_t)[0]
        rel = np.linalg.inv(traj.poses_at(scan_t)) @ interp
        ang = np.degrees(np.arccos(np.clip((np.trace(rel[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1)))
        worst = max(worst, ang.max())
    assert worst < 0.1  # degrees (it was up to 133 before the turn rate was bounded)


def test_follow_heading_limits_the_rate_and_reaches_the_target():
    from topometric_ros.sim.trajectory import follow_heading

    wanted = np.r_[np.zeros(100), np.full(400, np.pi)]  # a U-turn asked for at once, 100 Hz
    got = follow_heading(wanted, 0.01, max_rate_deg=90.0, smooth_s=0.0)
    assert np.degrees(np.abs(np.diff(got))).max() == pytest.approx(0.9)  # 90 deg/s at 100 Hz
    assert got[100 + 199] == pytest.approx(np.pi, abs=1e-9) and got[100 + 198] < np.pi  # 2 s for 180 deg


def test_a_drift_bag_too_short_for_an_episode_says_so(tmp_path):
    """Episodes start after 20 s: a 4 s bag asked for episode drift has none, and its summary says so (and
    what to do); a bag without drift, or with drift noise, says nothing of the kind."""
    from topometric_ros.sim.writer import SimConfig, format_summary, simulate

    short = simulate(SimConfig(scene="office1", frames=20, rate=5.0, drift=DriftSpec.parse("rt:1.5")),
                     tmp_path / "short", progress=False)
    assert short["episodes"] == [] and "NO EPISODE FITS" in format_summary(short)
    noise = simulate(SimConfig(scene="office1", frames=20, rate=5.0, drift=DriftSpec.parse("rt:1.5", "noise")),
                     tmp_path / "noise", progress=False)
    assert "NO EPISODE FITS" not in format_summary(noise)
