"""KISS-ICP as the SLAM beside the monitor (experiments/odometry.py): its poses of a simulated bag follow the
ground truth, and a sidecar bag of them replays beside the recording with drift injected on top."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("kiss_icp", reason="kiss-icp is a test dependency (pip install -e '.[test]')")


def test_kiss_poses_follow_the_truth_and_replay_beside_the_bag(tmp_path):
    from topometric_ros import bag, geometry
    from topometric_ros.config import load_config
    from topometric_ros.experiments.odometry import ODOM_TOPIC, kiss_odometry, write_odometry_bag
    from topometric_ros.replay import ReplayOptions, replay
    from topometric_ros.sim.writer import SimConfig, simulate

    path = tmp_path / "bag"
    simulate(SimConfig(scene="office1", frames=40, rate=10.0, seed=2), path, progress=False)
    stamps, poses, frame, info = kiss_odometry(path, progress=False)
    assert info["scans"] == 40 and frame == "velodyne"
    gs, gp = bag.read_odometry(path, "/odom_gt")
    lift = geometry.make_pose(np.eye(3), [0, 0, 1.0])
    gt = geometry.interpolate_poses(gs, gp, stamps)[0] @ lift
    walked = np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum()
    err = geometry.inverse(geometry.inverse(gt[0]) @ gt[-1]) @ (geometry.inverse(poses[0]) @ poses[-1])
    assert walked > 3.0 and np.linalg.norm(err[:3, 3]) < 0.1 * walked  # a working odometry: < 10 % of the path
    side = write_odometry_bag(tmp_path / "kiss", stamps, poses, frame)
    cfg = load_config(overrides={"segmentation.mode": "labels", "window.size": 10})
    res = replay(path, tmp_path / "out", cfg, ReplayOptions(odom_topic=ODOM_TOPIC, beside=(side,), progress=False,
                                                           plot=False))
    assert res.summary["windows"] == 4 and res.summary["counters"]["dropped_scans"] <= 1  # the last may lack a pose
    # (KISS poses are of the cloud frame itself: the extrinsic found is the identity)
    # the monitor's drift rates follow the true drift of KISS's poses (the ground truth in the bag)
    w = [x for x in res.windows if np.isfinite(x["rot_rate"])]
    assert w and all(abs(x["trans_rate"] - x["true_trans_rate"]) < 0.05 + 0.3 * x["true_trans_rate"] for x in w)


def test_the_kiss_cache_is_kept_per_voxel_size(tmp_path):
    """cached_kiss registers a bag once per voxel size: the same size reads the cache back (the same poses,
    the cache file untouched), another size registers again and says so in its info."""
    from topometric_ros.experiments.odometry import VOXEL_SIZE, cached_kiss
    from topometric_ros.sim.writer import SimConfig, simulate

    path = tmp_path / "bag"
    simulate(SimConfig(scene="office1", frames=12, rate=10.0, seed=3), path, progress=False)
    cache = tmp_path / "kiss" / "bag.npz"
    _, poses, _, info = cached_kiss(path, cache, progress=False)
    written = cache.stat().st_mtime_ns
    _, again, _, info_again = cached_kiss(path, cache, progress=False)
    assert cache.stat().st_mtime_ns == written and np.array_equal(poses, again) and info_again == info
    assert info["voxel_size"] == VOXEL_SIZE
    _, _, _, coarse = cached_kiss(path, cache, voxel_size=0.5, progress=False)
    assert coarse["voxel_size"] == 0.5 and cache.stat().st_mtime_ns != written
