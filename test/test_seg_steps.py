"""The steps after the network run in order, each on the labels of the ones before it: the kNN vote
(segmentation.knn), the floor check (segmentation.floor_band), one label per object (segmentation.object_gap),
the floor snap of non-repetitive scans (segmentation.floor_snap, on Mid-360 scans); none lowers mIoU on simulated
scans."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from topometric_ros import classes as C
from topometric_ros.config import SegmentationConfig
from topometric_ros.grid import as_grid
from topometric_ros.segmentation.floor import lift_off_floor, snap_to_floor
from topometric_ros.segmentation.infer import Segmenter
from topometric_ros.segmentation.knn import knn_vote
from topometric_ros.segmentation.metrics import confusion, miou
from topometric_ros.segmentation.objects import unify_objects
from topometric_ros.sim.frames import simulated_frames

STEPS = ("knn", "floor_band", "object_gap", "floor_snap")
SENSOR = {"floor_snap": "Mid-360"}  # the snap is for non-repetitive scans only


def _step(name: str, points, grid, labels, conf, cfg: SegmentationConfig):
    """The step ``name`` alone, called as the module that owns it."""
    if name == "knn":
        return knn_vote(points, grid, labels, conf, cfg.knn, cfg.knn_distance)
    if name == "floor_band":
        return lift_off_floor(points, grid, labels, conf, cfg.floor_band)
    if name == "object_gap":
        return unify_objects(points, grid, labels, conf, cfg.object_gap)
    return snap_to_floor(points, labels, conf, cfg.floor_snap)


@pytest.mark.parametrize("step", STEPS)
def test_each_step_runs_on_the_labels_of_the_steps_before_it_and_does_not_lower_miou(step):
    cfg = SegmentationConfig()
    assert getattr(cfg, step) > 0  # on by default
    later_off = {name: 0 for name in STEPS[STEPS.index(step) + 1:]}
    without = Segmenter.from_config(replace(cfg, **later_off, **{step: 0}))
    with_step = Segmenter.from_config(replace(cfg, **later_off))
    frames, _ = simulated_frames("office2", 2, seed=4242, **({"sensor": SENSOR[step]} if step in SENSOR else {}))
    before = np.zeros((C.NUM_CLASSES, C.NUM_CLASSES), np.int64)
    after = before.copy()
    for f in frames:
        points = np.asarray(f.points, np.float32)
        labels, conf = without.predict(f.points, f.ring, f.intensity)
        got, got_conf = with_step.predict(f.points, f.ring, f.intensity)
        want, want_conf = _step(step, points, as_grid(points, f.ring), labels, conf, cfg)
        assert np.array_equal(got, want) and np.array_equal(got_conf, want_conf)
        assert np.count_nonzero(got != labels) < 0.01 * len(labels)
        before += confusion(f.labels, labels)
        after += confusion(f.labels, got)
    assert (after != before).any()  # the step had work to do
    assert miou(after) >= miou(before)
