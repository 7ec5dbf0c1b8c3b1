"""pipeline's per-scan stages as the Monitor runs them: segment_scan | plane_scan == process_scan, and the
packed-key voxel downsampling picks the same points as a row-wise unique."""
import numpy as np
import pytest

from topometric_ros.config import load_config
from topometric_ros.pipeline import plane_scan, process_scan, segment_scan, voxel_indices


def rowwise_voxel_indices(points, size):
    keys = np.floor(points / size).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return np.sort(first)


@pytest.mark.parametrize("size", [0.05, 0.3, 2.0])
def test_packed_voxel_keys_pick_the_same_points_as_rowwise_unique(size):
    rng = np.random.default_rng(7)
    pts = np.concatenate([rng.uniform(-40, 40, (5000, 3)), rng.uniform(-0.2, 0.2, (3000, 3))]).astype(np.float32)
    got = voxel_indices(pts, size)
    np.testing.assert_array_equal(got, rowwise_voxel_indices(pts, size))
    keys = np.floor(pts[got] / size)
    assert len(np.unique(keys, axis=0)) == len(got)  # one point per voxel
    assert len(voxel_indices(pts[:0], size)) == 0


def test_the_two_stages_compose_to_process_scan():
    from topometric_ros.sim.frames import simulated_frames

    frames, _ = simulated_frames("garage", 2, seed=5)  # seed 4's second scan has 5 planes since simulator v4
    cfg = load_config(overrides={"segmentation.mode": "labels", "window.voxel_size": 0.1})
    for k, f in enumerate(frames):
        whole = process_scan(f, cfg, index=k)
        staged = plane_scan(segment_scan(f, cfg, index=k), cfg)
        assert staged.index == whole.index == k and len(staged.planes) == len(whole.planes) > 5
        for a, b in zip(staged.plane_arrays(), whole.plane_arrays()):
            np.testing.assert_array_equal(a, b)
        assert len(staged.labels) < len(f.points)  # the voxel step ran in stage 1
        assert set(staged.timings) == {"grid", "voxel", "segment", "planes", "total"}
        assert staged.timings["total"] == pytest.approx(sum(staged.timings[k] for k in ("grid", "voxel", "segment", "planes")))
