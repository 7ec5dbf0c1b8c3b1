"""BatchNorm statistics for non-repetitive scans (segmentation/norm_stats.py) and their use by the Segmenter."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from topometric_ros import classes as C
from topometric_ros.config import SegmentationConfig
from topometric_ros.segmentation.checkpoint import SHIPPED, build_model, load_weights, save_weights, state_digest
from topometric_ros.segmentation.infer import Segmenter
from topometric_ros.segmentation.metrics import confusion, miou
from topometric_ros.segmentation.model import ModelSpec, RangeNet
from topometric_ros.segmentation.norm_stats import NORM_NAME, estimate, load_stats, with_stats, write_stats
from topometric_ros.grid import ScanGrid, azimuth_cells
from topometric_ros.segmentation.projection import checked, project
from topometric_ros.sim.frames import simulated_frames


@pytest.fixture(scope="module")
def mid360():
    frames, _ = simulated_frames("office1", 2, seed=11, sensor="Mid-360")
    return frames


@pytest.fixture(scope="module")
def shipped():
    card, state = load_weights(SHIPPED)
    return card, state


def _images(frames):
    return [project(*checked(f.points, f.ring, f.intensity), f.intensity)[0] for f in frames]


def test_estimated_statistics_are_the_average_of_each_scans_own_batch_statistics(mid360):
    """The first BatchNorm's input does not depend on any statistics: its running mean and variance must be the
    plain average over the scans of each scan's channel mean and (unbiased) variance of that input."""
    torch.manual_seed(0)
    model = RangeNet(ModelSpec()).eval()
    images = _images(mid360)
    first = next(m for m in model.modules() if isinstance(m, torch.nn.BatchNorm2d))
    seen = []
    hook = first.register_forward_hook(lambda m, inp, out: seen.append(inp[0].detach()))
    with torch.no_grad():
        for im in images:
            model(torch.from_numpy(im))
    hook.remove()
    name = next(k for k, m in model.named_modules() if m is first)
    stats, n = estimate(model, images)
    assert n == len(images) == 2
    mean = torch.stack([x.mean((0, 2, 3)) for x in seen]).mean(0)
    var = torch.stack([x.transpose(0, 1).reshape(x.shape[1], -1).var(1, unbiased=True) for x in seen]).mean(0)
    np.testing.assert_allclose(stats[f"{name}.running_mean"], mean.numpy(), rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(stats[f"{name}.running_var"], var.numpy(), rtol=1e-4, atol=1e-5)
    assert first.running_mean.abs().sum() == 0  # the model given is left as it was (a fresh net: zeros)
    expected = {k for k in model.state_dict() if k.endswith(("running_mean", "running_var"))}
    assert set(stats) == expected
    swapped = with_stats(model, stats)
    assert torch.equal(swapped.state_dict()[f"{name}.running_mean"], torch.tensor(stats[f"{name}.running_mean"]))


def test_statistics_are_refused_unless_they_were_made_for_these_weights(tmp_path, shipped):
    card, state = shipped
    weights = save_weights(build_model(card, state), card, tmp_path)
    digest = state_digest(state)
    assert load_stats(weights, digest, state)[0] is None
    assert "make them with topometric norm-stats" in load_stats(weights, digest, state)[1]
    stats = {k: v.tolist() for k, v in state.items() if k.endswith(("running_mean", "running_var"))}
    path = write_stats(stats, weights, digest, "test", 3)
    assert path == tmp_path / NORM_NAME
    assert load_stats(weights, digest, state) == (stats, "")
    assert "made for other weights" in load_stats(weights, "0" * 64, state)[1]
    doc = json.loads(path.read_text())
    path.write_text(json.dumps({**doc, "format_version": 2}))  # a later format is not read as this one
    assert load_stats(weights, digest, state)[0] is None
    assert "not a file of non-repetitive statistics of format 1" in load_stats(weights, digest, state)[1]
    doc["statistics"].pop(next(iter(stats)))
    path.write_text(json.dumps(doc))
    assert "do not match the network" in load_stats(weights, digest, state)[1]
    path.write_text("{")
    assert "not readable JSON" in load_stats(weights, digest, state)[1]


def test_the_segmenter_uses_the_statistics_for_non_repetitive_scans_only(mid360, shipped):
    card, state = shipped
    stats, _ = estimate(build_model(card, state), _images(mid360))
    plain = Segmenter(build_model(card, state), card, backend="eager")
    patterned = Segmenter(build_model(card, state), card, backend="eager", pattern_stats=stats)
    swapped = Segmenter(with_stats(build_model(card, state), stats), card, backend="eager")
    assert patterned.has_pattern_stats and not plain.has_pattern_stats
    spinning, _ = simulated_frames("office1", 1, seed=11, sensor="VLP-16")
    for f in spinning:  # a spinning scan: the weights' own statistics, labels and confidence unchanged
        for a, b in zip(patterned.predict(f.points, f.ring, f.intensity), plain.predict(f.points, f.ring, f.intensity)):
            np.testing.assert_array_equal(a, b)
    f = mid360[0]
    got = patterned.predict(f.points, f.ring, f.intensity)
    np.testing.assert_array_equal(got[0], swapped.predict(f.points, f.ring, f.intensity)[0])
    assert (got[0] != plain.predict(f.points, f.ring, f.intensity)[0]).mean() > 0.05
    # the same points on a grid without per-point azimuths (as a spinning sensor's) and of the same image shape:
    # one batch of both kinds, each with its own statistics
    grid = checked(f.points, f.ring)[1]
    cols = azimuth_cells(grid.azimuth, 640)
    as_spinning = ScanGrid(grid.row, cols.astype(grid.col.dtype), grid.height, 640, grid.elevation_deg, "test")
    assert project(f.points, grid)[0].shape == project(f.points, as_spinning)[0].shape == (1, 6, 32, 640)
    mixed = patterned.predict_batch([(f.points, grid, f.intensity), (f.points, as_spinning, f.intensity)])
    np.testing.assert_array_equal(mixed[0][0], got[0])
    np.testing.assert_array_equal(mixed[1][0], plain.predict(f.points, as_spinning, f.intensity)[0])


def test_int8_with_the_statistics_leaves_spinning_scans_as_they_were_and_follows_float32_on_the_mid360(mid360):
    from topometric_ros.segmentation.quantize import load_ranges

    card, state = load_weights(SHIPPED)
    ranges, why = load_ranges(SHIPPED, state_digest(state))
    assert why == ""
    stats, _ = load_stats(SHIPPED, state_digest(state), state)
    int8 = Segmenter(build_model(card, state), card, int8_ranges=ranges, pattern_stats=stats)
    int8_shared = Segmenter(build_model(card, state), card, int8_ranges=ranges)
    float32 = Segmenter(build_model(card, state), card, pattern_stats=stats)
    spinning, _ = simulated_frames("office1", 1, seed=11, sensor="VLP-16")
    f = spinning[0]
    np.testing.assert_array_equal(int8.predict(f.points, f.ring)[0], int8_shared.predict(f.points, f.ring)[0])
    f = mid360[0]
    agree = (int8.predict(f.points, f.ring, f.intensity)[0] == float32.predict(f.points, f.ring, f.intensity)[0]).mean()
    assert int8.precision == "int8" and not int8._pattern_float32 and agree > 0.95, agree


def test_the_shipped_statistics_load_and_lift_the_mid360_over_the_shared_ones(mid360):
    """The shipped weights come with statistics for non-repetitive scans (estimated on the Mid-360's training
    layouts); on these simulated Mid-360 scans they beat the shared statistics by a wide margin."""
    with_file = Segmenter.from_config(SegmentationConfig(precision="float32", knn=0, floor_band=0, object_gap=0))
    assert with_file.has_pattern_stats
    card, state = load_weights(SHIPPED)
    shared = Segmenter(build_model(card, state), card)
    scores = []
    for seg in (with_file, shared):
        conf = np.zeros((C.NUM_CLASSES, C.NUM_CLASSES), np.int64)
        for f in mid360:
            conf += confusion(f.labels, seg.predict(f.points, f.ring, f.intensity)[0])
        scores.append(miou(conf))
    assert scores[0] > scores[1] + 0.05, scores


def test_norm_stats_command_writes_the_file_and_refuses_bags_without_a_non_repetitive_scan(tmp_path, shipped):
    card, state = shipped
    weights = save_weights(build_model(card, state), card, tmp_path / "w")
    for sensor in ("Mid-360", "VLP-16"):
        res = subprocess.run([sys.executable, "-m", "topometric_ros.cli", "simulate", "--sensor", sensor, "--scene",
                              "office1", "--frames", "2", "--out", str(tmp_path / sensor)], capture_output=True, text=True)
        assert res.returncode == 0, res.stderr
    eval_seg = [sys.executable, "-m", "topometric_ros.cli", "eval-seg", str(tmp_path / "Mid-360"), "--weights",
                str(weights), "--out", str(tmp_path / "eval")]
    res = subprocess.run(eval_seg, capture_output=True, text=True)
    assert res.returncode == 0 and "non-repetitive scans: 2, with the shared BatchNorm statistics" in res.stdout
    res = subprocess.run([sys.executable, "-m", "topometric_ros.cli", "norm-stats", str(tmp_path / "VLP-16"),
                          "--weights", str(weights)], capture_output=True, text=True)
    assert res.returncode == 2 and "no non-repetitive scan" in res.stderr and "Traceback" not in res.stderr
    res = subprocess.run([sys.executable, "-m", "topometric_ros.cli", "norm-stats", str(tmp_path / "Mid-360"),
                          str(tmp_path / "VLP-16"), "--weights", str(weights)], capture_output=True, text=True)
    assert res.returncode == 0 and "of 2 non-repetitive range images from 1 of 2 bag(s)" in res.stdout, res.stderr
    doc = json.loads((tmp_path / "w" / NORM_NAME).read_text())
    assert doc["images"] == 2 and doc["state_sha256"] == state_digest(state)
    assert doc["command"].startswith("topometric norm-stats ")
    assert Segmenter.from_config(SegmentationConfig(weights=str(weights))).has_pattern_stats
    res = subprocess.run(eval_seg, capture_output=True, text=True)
    assert res.returncode == 0 and "non-repetitive scans: 2, with their own BatchNorm statistics" in res.stdout
