"""The pipeline: per-scan processing by segmentation mode, window scoring, the per-stamp cache, the facade."""
from __future__ import annotations


import numpy as np
import pytest

import topometric_ros.pipeline as pipeline
from topometric_ros import classes as C
from topometric_ros import geometry
from topometric_ros.config import load_config
from topometric_ros.pipeline import ProcessedScan, process_scan, score_window, window_planes
from topometric_ros.sim.frames import simulated_frames
from topometric_ros.window import Frame


@pytest.fixture(scope="module")
def frames():
    """Five consecutive garage scans with ground-truth labels and poses."""
    return simulated_frames("garage", 5, seed=2)[0]


@pytest.fixture(scope="module")
def labels_config():
    return load_config(overrides={"segmentation.mode": "labels"})


@pytest.fixture(scope="module")
def processed(frames, labels_config):
    return [process_scan(f, labels_config, index=k) for k, f in enumerate(frames)]


class GroundTruthSegmenter:
    """A segmenter with the network's interface that answers with known labels (records its calls)."""

    def __init__(self, labels_by_size):
        self.labels_by_size = labels_by_size
        self.calls = 0

    def predict(self, points, ring, intensity):
        self.calls += 1
        labels = self.labels_by_size[len(points)]
        return labels, np.ones(len(points), np.float32)


def test_labels_mode_keeps_the_given_labels_and_finds_static_planes(frames, processed):
    scan = processed[0]
    assert scan.labels is frames[0].labels and scan.stamp == frames[0].stamp and scan.index == 0
    assert np.array_equal(scan.pose, frames[0].pose)
    assert len(scan.planes) >= 3 and {p.cls for p in scan.planes} <= set(C.STATIC)
    assert {p.cls for p in scan.planes} >= {C.FLOOR, C.WALL}
    assert scan.points is None  # baselines off: no points kept
    assert {"segment", "planes", "total"} <= set(scan.timings) and all(v >= 0 for v in scan.timings.values())


def test_labels_mode_without_labels_is_a_clear_error(frames, labels_config):
    bare = Frame(frames[0].points, frames[0].pose, frames[0].stamp)
    with pytest.raises(ValueError, match="label"):
        process_scan(bare, labels_config)
    short = Frame(frames[0].points, frames[0].pose, 0.0, labels=frames[0].labels[:10])
    with pytest.raises(ValueError, match="labels for"):
        process_scan(short, labels_config)


def test_none_mode_treats_every_point_as_one_static_class(frames):
    scan = process_scan(frames[0], load_config(overrides={"segmentation.mode": "none"}))
    assert np.all(scan.labels == pipeline.NONE_MODE_CLASS) and pipeline.NONE_MODE_CLASS in C.STATIC
    assert len(scan.planes) >= 3 and {p.cls for p in scan.planes} == {pipeline.NONE_MODE_CLASS}


def test_network_mode_uses_the_segmenter(frames, processed):
    seg = GroundTruthSegmenter({len(frames[0]): frames[0].labels})
    cfg = load_config(overrides={"segmentation.mode": "network"})
    scan = process_scan(frames[0], cfg, segmenter=seg)
    assert seg.calls == 1 and scan.labels.dtype == np.uint8
    assert np.array_equal(scan.labels, frames[0].labels)
    assert {p.cls for p in scan.planes} == {p.cls for p in processed[0].planes}


def test_network_mode_with_missing_weights_says_which_file(frames, tmp_path):
    cfg = load_config(overrides={"segmentation.weights": str(tmp_path / "nope.pt")})
    with pytest.raises(ValueError, match="nope.pt"):
        process_scan(frames[0], cfg)


def test_unknown_mode_is_a_config_error():
    with pytest.raises(ValueError, match="must be one of network, labels, none"):
        load_config(overrides={"segmentation.mode": "oracle"})


def test_a_config_file_that_is_not_yaml_is_a_config_error(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("window: [\n")
    with pytest.raises(ValueError, match="bad.yaml: not valid YAML"):
        load_config(bad)


@pytest.mark.parametrize("key, value", [("window.size", -1), ("health.stale_after_s", -1.0), ("segmentation.knn", 99)])
def test_out_of_range_config_values_are_refused_as_the_node_refuses_them(key, value, tmp_path):
    """Not only the node: load_config (replay, audit, inspect, the Python API) refuses a value outside the
    range the node's parameter declares (a window of 0 scans used to replay to zero windows, exit 0)."""
    with pytest.raises(ValueError, match=key.replace(".", r"\.") + ".*out of range"):
        load_config(overrides={key: value})
    yaml_file = tmp_path / "c.yaml"
    yaml_file.write_text(f"{key.split('.')[0]}:\n  {key.split('.')[1]}: {value}\n")
    with pytest.raises(ValueError, match=f"^{yaml_file}: config key .*out of range"):  # the file named
        load_config(yaml_file)


def test_voxel_downsampling_thins_the_scan_before_segmentation(frames):
    cfg = load_config(overrides={"segmentation.mode": "labels", "window.voxel_size": 0.2,
                                 "metrics.baselines": True})
    scan = process_scan(frames[0], cfg)
    assert len(scan.points) < 0.7 * len(frames[0]) and len(scan.labels) == len(scan.points)
    cells = np.floor(scan.points / 0.2).astype(np.int64)
    assert len(np.unique(cells, axis=0)) == len(cells)  # one point per voxel
    assert "voxel" in scan.timings and {p.cls for p in scan.planes} >= {C.FLOOR, C.WALL}


def test_window_planes_equal_plane_transformed_stats(processed):
    poses = geometry.relative_to_first(np.stack([s.pose for s in processed]))
    wp = window_planes(processed, poses)
    row = 0
    for k, scan in enumerate(processed):
        for plane in scan.planes:
            n, m, s = plane.transformed_stats(poses[k])
            assert wp.scans[row] == k and wp.classes[row] == plane.cls and wp.counts[row] == plane.count
            np.testing.assert_allclose(wp.normals[row], n, atol=1e-12)
            np.testing.assert_allclose(wp.means[row], m, atol=1e-9)
            np.testing.assert_allclose(wp.scatters[row], s, rtol=1e-12, atol=1e-9)
            row += 1
    assert row == len(wp.counts)


def test_score_window_on_ground_truth_poses(processed, labels_config):
    result = score_window(processed, labels_config)
    assert result.stamps == [s.stamp for s in processed]
    assert result.n_planes == sum(len(s.planes) for s in processed)
    assert result.n_groups >= 3 and result.n_clusters >= 2
    assert np.isfinite(result.pne) and 0 < result.cpv < 0.01 ** 2 * 4  # lidar noise is ~1 cm
    assert 0.9 <= result.agreement <= 1.0  # right poses: every scan's planes are seen in place by another
    assert result.mme is None and {"transform", "pne", "cpv", "total"} <= set(result.timings)


def test_score_window_without_planes_gives_nan(frames, processed, labels_config):
    empty = [ProcessedScan(f.stamp, f.pose, []) for f in frames[:3]]
    result = score_window(empty, labels_config)
    assert np.isnan(result.pne) and np.isnan(result.cpv) and result.n_planes == result.n_groups == 0
    assert np.isnan(result.agreement)
    one = score_window(processed[:1], labels_config)  # planes, but no other scan to agree with: no group
    assert one.n_groups == 0 and np.isnan(one.agreement)
    with pytest.raises(ValueError):
        score_window([], labels_config)


def test_baselines_need_the_points(processed):
    cfg = load_config(overrides={"segmentation.mode": "labels", "metrics.baselines": True})
    with pytest.raises(ValueError, match="points"):
        score_window(processed, cfg)


def test_sliding_window_processes_each_scan_once(frames, labels_config, monkeypatch):
    calls, made = [], {}
    original = pipeline.process_scan

    def counting(frame, config, segmenter=None, index=-1):
        calls.append(frame.stamp)
        made[frame.stamp] = original(frame, config, segmenter, index)
        return made[frame.stamp]

    monkeypatch.setattr(pipeline, "process_scan", counting)
    cache: dict = {}
    size = 3
    results = [pipeline.evaluate_window(frames[i:i + size], labels_config, cache)
               for i in range(len(frames) - size + 1)]
    assert sorted(calls) == [f.stamp for f in frames]  # every scan once, none twice
    assert sorted(cache) == [f.stamp for f in frames[-size:]]  # older scans were dropped
    for i, result in enumerate(results):
        direct = score_window([made[f.stamp] for f in frames[i:i + size]], labels_config)
        assert (result.pne, result.cpv, result.n_groups) == (direct.pne, direct.cpv, direct.n_groups)
    assert [r.stamps[0] for r in results] == [f.stamp for f in frames[:len(results)]]


def test_facade_exports():
    from topometric_ros import Frame as F, WindowResult, evaluate_window, load_config as lc

    assert F is Frame and WindowResult is pipeline.WindowResult
    assert evaluate_window is pipeline.evaluate_window and lc is load_config


def test_window_motion_measures_each_step_in_the_sensors_own_frame():
    """1 m straight ahead, then a 90 deg turn on the spot: 1 m travelled in 2 s and 90 deg turned (a step taken
    in the map frame would add the lever arm of the turn, √2 m)."""
    from topometric_ros.pipeline import window_motion

    poses = np.stack([np.eye(4), geometry.yaw_pose(1.0, 0.0, 0.0, 0.0), geometry.yaw_pose(1.0, 0.0, 0.0, np.pi / 2)])
    speed, turn = window_motion(poses, [10.0, 11.0, 12.0])
    assert speed == pytest.approx(0.5) and turn == pytest.approx(45.0)
