"""The shipped weights: the output of `topometric train`, and good on a simulated scan."""
from __future__ import annotations

import json

import numpy as np

from topometric_ros import classes as C
from topometric_ros.config import SegmentationConfig
from topometric_ros.segmentation.checkpoint import SHIPPED
from topometric_ros.segmentation.infer import Segmenter
from topometric_ros.segmentation.metrics import confusion, miou
from topometric_ros.sim.frames import simulated_frames


def test_shipped_model_card_records_the_training_command_and_seed():
    card = json.loads((SHIPPED.parent / "model_card.json").read_text())
    assert card["training"]["command"].startswith("topometric train ")
    assert isinstance(card["training"]["seed"], int)
    assert card["weights"]["file"] == SHIPPED.name and SHIPPED.stat().st_size < 5_000_000
    assert card["classes"] == list(C.NAMES)


def test_shipped_weights_segment_a_simulated_scan():
    seg = Segmenter.from_config(SegmentationConfig())  # weights "" = shipped; sha256 checked on load
    frames, _ = simulated_frames("office2", 2, seed=4242)
    conf = np.zeros((C.NUM_CLASSES, C.NUM_CLASSES), np.int64)
    for f in frames:
        labels, confidence = seg.predict(f.points, f.ring, f.intensity)
        conf += confusion(f.labels, labels)
    assert miou(conf) >= 0.90
    assert confidence.min() > 0 and confidence.max() <= 1
