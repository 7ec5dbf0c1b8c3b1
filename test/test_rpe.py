"""RPE: identity, hand values, evo's own RPE."""
from __future__ import annotations

import numpy as np
import pytest

from topometric_ros import geometry
from topometric_ros.metrics.rpe import rpe, rpe_errors, rpe_parts


def _trajectory(n, rng):
    return geometry.make_pose(geometry.rotvec_to_matrix(rng.normal(0, 0.5, (n, 3))), rng.normal(0, 3, (n, 3)))


def test_identical_trajectories_give_zero(rng):
    poses = _trajectory(6, rng)
    for conv in ("paper", "evo"):
        assert rpe(poses, poses, conv) == pytest.approx(0.0, abs=1e-12)
    assert rpe_parts(poses, poses) == pytest.approx((0.0, 0.0), abs=1e-6)


def test_same_motion_in_another_map_frame_gives_zero(rng):
    gt = _trajectory(5, rng)
    est = geometry.noise_transforms(1, 0.3, 2.0, rng)[0] @ gt  # same relative motions
    assert rpe(gt, est) == pytest.approx(0.0, abs=1e-12)


def test_single_step_rotation_error_hand_value():
    theta = 0.1
    gt = geometry.yaw_pose(np.arange(3.0), 0, 0, 0)  # straight line, 1 m steps
    est = gt.copy()
    est[2] = est[1] @ geometry.yaw_pose(1.0, 0, 0, theta)  # second step turns by theta
    # evo: E = ΔT_gt⁻¹ ΔT_est = [R_z(θ), 0] for the wrong pair; ‖R_z(θ) − I‖_F = 2√2 sin(θ/2)
    hand = 2 * np.sqrt(2) * np.sin(theta / 2)
    e = rpe_errors(gt, est, "evo")
    assert np.linalg.norm(e[1] - np.eye(4)) == pytest.approx(hand, rel=1e-12)
    assert rpe(gt, est, "evo") == pytest.approx(hand / 2, rel=1e-12)
    rot_deg, trans_m = rpe_parts(gt, est)
    assert rot_deg == pytest.approx(np.degrees(theta) / 2, rel=1e-9)
    assert trans_m == pytest.approx(0.0, abs=1e-12)


def test_single_step_translation_error_hand_value():
    gt = geometry.yaw_pose(np.arange(4.0), 0, 0, 0)
    est = gt.copy()
    est[3, :3, 3] += [0.0, 0.3, 0.4]  # last step off by 0.5 m
    for conv in ("paper", "evo"):
        assert rpe(gt, est, conv) == pytest.approx(0.5 / 3, rel=1e-12)
    assert rpe_parts(gt, est)[1] == pytest.approx(0.5 / 3, rel=1e-12)


def test_conventions_differ_but_agree_on_rotation(rng):
    gt = _trajectory(8, rng)
    est = gt @ geometry.noise_transforms(8, 0.05, 0.1, rng)
    assert rpe(gt, est, "paper") != pytest.approx(rpe(gt, est, "evo"), rel=1e-6)
    assert rpe_parts(gt, est, "paper")[0] == pytest.approx(rpe_parts(gt, est, "evo")[0], rel=1e-9)


def test_evo_convention_equals_evo_rpe(rng):
    from evo.core import metrics
    from evo.core.trajectory import PosePath3D

    gt = _trajectory(12, rng)
    est = gt @ geometry.noise_transforms(12, 0.05, 0.2, rng)
    rel = metrics.RPE(metrics.PoseRelation.full_transformation, delta=1, delta_unit=metrics.Unit.frames)
    rel.process_data((PosePath3D(poses_se3=list(gt)), PosePath3D(poses_se3=list(est))))
    assert rpe(gt, est, "evo") == pytest.approx(rel.get_statistic(metrics.StatisticsType.mean), rel=1e-10)
    ang = metrics.RPE(metrics.PoseRelation.rotation_angle_deg, delta=1, delta_unit=metrics.Unit.frames)
    ang.process_data((PosePath3D(poses_se3=list(gt)), PosePath3D(poses_se3=list(est))))
    tra = metrics.RPE(metrics.PoseRelation.translation_part, delta=1, delta_unit=metrics.Unit.frames)
    tra.process_data((PosePath3D(poses_se3=list(gt)), PosePath3D(poses_se3=list(est))))
    parts = rpe_parts(gt, est)
    assert parts[0] == pytest.approx(ang.get_statistic(metrics.StatisticsType.mean), rel=1e-8)
    assert parts[1] == pytest.approx(tra.get_statistic(metrics.StatisticsType.mean), rel=1e-10)


def test_bad_input_is_a_clear_error(rng):
    with pytest.raises(ValueError, match="convention"):
        rpe(_trajectory(3, rng), _trajectory(3, rng), "kitti")
    with pytest.raises(ValueError, match="poses"):
        rpe(_trajectory(3, rng), _trajectory(4, rng))
