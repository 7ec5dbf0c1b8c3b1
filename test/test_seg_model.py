"""The network, the Segmenter and its weight loading (untrained nets; the shipped weights in test_seg_shipped).
The network's own labels: the neighbour vote after it (segmentation.knn) is off here; test_seg_knn covers it."""
from __future__ import annotations

import copy
import os
import pickle
import sys

import numpy as np
import pytest
import torch

from topometric_ros import classes as C
from topometric_ros.config import SegmentationConfig, load_config
from topometric_ros.grid import scan_grid
from topometric_ros.segmentation.checkpoint import (SegmentationError, build_model, load_weights, save_weights,
                                                   state_digest)
from topometric_ros.segmentation.infer import Scorer, Segmenter, _mirror, _spread, read_out
from topometric_ros.segmentation.metrics import confusion
from topometric_ros.segmentation.model import ModelSpec, RangeNet, fold_batchnorm
from topometric_ros.segmentation.projection import ProjectionError, nearest_strided, strided
from topometric_ros.segmentation.train import (TrainConfig, augment, class_weights, confusion_on, lovasz_softmax,
                                               model_card, sample_crops, sensor_strata, strata_summary,
                                               validation_entry)
from topometric_ros.sim.frames import simulated_frames


@pytest.fixture(scope="module")
def frames():
    return simulated_frames("garage", 2, seed=5)[0]


def _random_weights(path, seed=0):
    torch.manual_seed(seed)
    model = RangeNet(ModelSpec())
    for m in model.modules():  # non-trivial running stats, so eval mode is not the identity normalisation
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.1, 0.1)
            m.running_var.uniform_(0.5, 1.5)
    card = model_card(model.spec, TrainConfig(), [], [], "test", [], 0, 0, 0.0)
    return model.eval(), save_weights(model, card, path)


def _save(path, card, state):
    """A weights file with a valid digest of ``state`` (so only the shape/key checks can object)."""
    torch.save({"model_card": card, "state_dict": state, "state_sha256": state_digest(state)}, path)


def test_circular_padding_makes_the_net_equivariant_to_azimuth_rolls():
    torch.manual_seed(0)
    model = RangeNet(ModelSpec()).eval()
    x = torch.randn(1, 6, 32, 96)
    step = 2 * model.spec.fold  # the net's azimuth stride
    with torch.no_grad():
        y = model(x)
        for k in (1, 5):
            torch.testing.assert_close(model(x.roll(k * step, -1)), y.roll(k * step, -1), atol=1e-4, rtol=1e-4)
        model.set_circular(False)  # zero padding breaks the wrap-around
        assert not torch.allclose(model(x.roll(step, -1)), y.roll(step, -1), atol=1e-3)


def test_folding_batchnorm_keeps_the_outputs(tmp_path):
    model, _ = _random_weights(tmp_path)
    x = torch.randn(2, 6, 32, 64)
    folded = fold_batchnorm(copy.deepcopy(model))
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in folded.modules())
    with torch.no_grad():
        torch.testing.assert_close(folded(x), model(x), atol=1e-4, rtol=1e-4)


def test_read_out_gives_the_softmax_arg_max_and_its_probability_per_unfolded_column():
    torch.manual_seed(1)
    model = RangeNet(ModelSpec()).eval()
    x = torch.randn(2, 6, 32, 64)
    with torch.no_grad():
        conf, labels = torch.softmax(model(x), 1).max(1)  # model(x): the azimuth already unfolded
        got_labels, got_conf = read_out(model.folded_logits(x).numpy())
    assert got_labels.dtype == np.uint8 and got_conf.dtype == np.float32
    np.testing.assert_array_equal(got_labels, labels.numpy())
    np.testing.assert_allclose(got_conf, conf.numpy(), rtol=1e-5)
    tie = np.zeros((1, 3, 1, 1, 2), np.float32)  # three classes scored equally: the lowest wins, at 1/3
    assert read_out(tie)[0].tolist() == [[[0, 0]]] and np.allclose(read_out(tie)[1], 1 / 3)


def test_segmenter_predicts_one_label_and_confidence_per_point(tmp_path, frames):
    _, path = _random_weights(tmp_path)
    seg = Segmenter.from_config(SegmentationConfig(knn=0, floor_band=0, object_gap=0, weights=str(path)))
    f = frames[0]
    labels, conf = seg.predict(f.points, f.ring, f.intensity)
    assert labels.shape == conf.shape == (len(f.points),)
    assert labels.dtype == np.uint8 and conf.dtype == np.float32
    assert labels.max() < C.NUM_CLASSES and (conf > 1 / C.NUM_CLASSES - 1e-6).all() and (conf <= 1).all()
    batch = seg.predict_batch([(g.points, g.ring, g.intensity) for g in frames])
    for g, (lab, cf) in zip(frames, batch):
        one = seg.predict(g.points, g.ring, g.intensity)
        np.testing.assert_array_equal(lab, one[0])
        np.testing.assert_allclose(cf, one[1], atol=1e-5)
    no_ring = seg.predict(f.points, None, f.intensity)  # rings from elevation: the same image
    np.testing.assert_array_equal(no_ring[0], labels)


def test_onnxruntime_backend_agrees_with_eager_pytorch(tmp_path, frames):
    pytest.importorskip("onnxruntime")
    _, path = _random_weights(tmp_path)
    fast = Segmenter.from_config(SegmentationConfig(knn=0, floor_band=0, object_gap=0, weights=str(path), backend="onnxruntime"))
    eager = Segmenter.from_config(SegmentationConfig(knn=0, floor_band=0, object_gap=0, weights=str(path), backend="eager"))
    assert (fast.backend, eager.backend) == ("onnxruntime", "eager")
    for f in frames:
        (la, ca), (lb, cb) = fast.predict(f.points, f.ring, f.intensity), eager.predict(f.points, f.ring, f.intensity)
        assert la.dtype == lb.dtype == np.uint8 and ca.dtype == cb.dtype == np.float32
        assert (la == lb).mean() >= 0.999
        np.testing.assert_allclose(ca, cb, atol=1e-4)
    batch = fast.predict_batch([(g.points, g.ring, g.intensity) for g in frames])  # dynamic batch axis
    np.testing.assert_array_equal(batch[1][0], fast.predict(frames[1].points, frames[1].ring, frames[1].intensity)[0])


def test_two_passes_make_labels_invariant_to_mirroring_the_scan(tmp_path, frames):
    """segmentation.passes 2 averages the network over the image and its mirror, so a scan and its mirror
    (y -> -y) get the same label at every point, exactly (one pass: the net alone is not symmetric); 3 passes
    (a shifted view too) run in ONNX Runtime and agree with eager PyTorch."""
    pytest.importorskip("onnxruntime")
    _, path = _random_weights(tmp_path)
    f = frames[0]
    mirrored = f.points * np.array([1.0, -1.0, 1.0], np.float32)
    for passes in (1, 2):
        seg = Segmenter.from_config(SegmentationConfig(knn=0, floor_band=0, object_gap=0, weights=str(path), passes=passes))
        assert seg.backend == "onnxruntime"
        (a, ca), (b, cb) = seg.predict(f.points, f.ring, f.intensity), seg.predict(mirrored, f.ring, f.intensity)
        if passes == 1:
            assert (a != b).sum() > 100
        else:
            np.testing.assert_array_equal(a, b)
            np.testing.assert_allclose(ca, cb, atol=1e-6)
    fast = Segmenter.from_config(SegmentationConfig(knn=0, floor_band=0, object_gap=0, weights=str(path), passes=3))
    eager = Segmenter.from_config(SegmentationConfig(knn=0, floor_band=0, object_gap=0, weights=str(path), passes=3, backend="eager"))
    (la, ca), (lb, cb) = fast.predict(f.points, f.ring, f.intensity), eager.predict(f.points, f.ring, f.intensity)
    assert fast.backend == "onnxruntime" and (la == lb).mean() >= 0.999
    np.testing.assert_allclose(ca, cb, atol=1e-4)
    with pytest.raises(SegmentationError, match="passes must be 1 to 3"):
        Segmenter.from_config(SegmentationConfig(knn=0, floor_band=0, object_gap=0, weights=str(path), passes=4))
    with pytest.raises(SegmentationError, match="passes must be 1 to 3"):
        Segmenter.from_config(SegmentationConfig(knn=0, floor_band=0, object_gap=0, weights=str(path), passes=2.5))


def test_three_passes_add_the_view_turned_by_half_a_fold_mapped_back_to_the_images_pixels():
    """Scorer passes 3 = the mean softmax of the image, its mirror and the image turned by ``shift`` columns; the
    turned view's scores are turned back, so its share is the turned image's softmax at the same pixels."""
    torch.manual_seed(2)
    net = RangeNet(ModelSpec()).eval().set_circular(True)
    x = torch.randn(1, 6, 32, 64)
    two, three = Scorer(net, 2).eval(), Scorer(net, 3).eval()
    with torch.no_grad():
        # scores are log-probabilities up to a per-pixel constant: their softmax is the views' mean softmax
        third = 3 * torch.softmax(three(x), 1) - 2 * torch.softmax(two(x), 1)  # (1, k, 1, h, w): the third view's
        turned = torch.softmax(net(torch.roll(x, three.shift, -1)), 1)
        mirrored = torch.softmax(net(_mirror(x) * two.mirror_sign), 1)
        both = (torch.softmax(net(x), 1) + _mirror(mirrored)) / 2
    assert three.shift >= 1
    torch.testing.assert_close(third[:, :, 0], torch.roll(turned, -three.shift, -1), atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(torch.softmax(two(x), 1)[:, :, 0], both, atol=1e-5, rtol=1e-5)


def test_a_batch_of_scans_of_several_images_each_gives_every_scan_its_own_labels(tmp_path):
    """An OS1-64 scan is two interleaved 32-row images: in a batch, each scan reads its labels back from its own
    two images (the same labels and confidence as alone; eager: the grouping is the same for every backend)."""
    _, path = _random_weights(tmp_path)
    seg = Segmenter.from_config(SegmentationConfig(knn=0, floor_band=0, object_gap=0, weights=str(path),
                                                   backend="eager"))
    scans, _ = simulated_frames("office1", 2, seed=3, sensor="OS1-64")
    batch = seg.predict_batch([(f.points, f.ring, f.intensity) for f in scans])
    for f, (labels, conf) in zip(scans, batch):
        one = seg.predict(f.points, f.ring, f.intensity)
        np.testing.assert_array_equal(labels, one[0])
        np.testing.assert_allclose(conf, one[1], atol=1e-5)
    assert not np.array_equal(batch[0][0][:1000], batch[1][0][:1000])


def test_a_point_with_no_segmented_neighbour_is_other_at_confidence_zero():
    """max_beams: a point whose nearest_strided source is -1 (no segmented neighbour in range) takes OTHER at
    confidence 0, not the label and confidence of the first segmented point."""
    labels, conf = np.array([3, 5], np.uint8), np.array([0.9, 0.6], np.float32)
    got_labels, got_conf = _spread(labels, conf, np.array([1, -1, 0, 1]))
    assert got_labels.dtype == np.uint8 and got_conf.dtype == np.float32
    assert got_labels.tolist() == [5, C.OTHER, 3, 5]
    np.testing.assert_array_equal(got_conf, np.array([0.6, 0.0, 0.9, 0.6], np.float32))


def test_max_beams_segments_every_kth_beam_and_gives_the_rest_their_neighbours_labels(tmp_path, frames):
    """segmentation.max_beams 16 on a 32-beam scan: the network sees rows 0, 2, 4, ... alone (their labels are
    those of that 16-row scan, exactly), every other point takes the label and confidence of its
    projection.nearest_strided neighbour; max_beams >= the rows changes nothing; a bad value is an error."""
    _, path = _random_weights(tmp_path)
    f = frames[0]
    grid = scan_grid(f.points, f.ring)
    every = Segmenter.from_config(SegmentationConfig(knn=0, floor_band=0, object_gap=0, weights=str(path)))
    half = Segmenter.from_config(SegmentationConfig(knn=0, floor_band=0, object_gap=0, weights=str(path), max_beams=16))
    labels, conf = half.predict(f.points, grid, f.intensity)
    keep, sub = strided(grid, 2)
    seen, seen_conf = every.predict(f.points[keep], sub, f.intensity[keep])
    np.testing.assert_array_equal(labels[keep], seen)
    source = nearest_strided(f.points, grid, keep, 2)
    assert (source >= 0).mean() > 0.999
    np.testing.assert_array_equal(labels[source >= 0], seen[source[source >= 0]])
    np.testing.assert_array_equal(conf[source >= 0], seen_conf[source[source >= 0]])
    assert np.all(labels[source < 0] == C.OTHER)
    same = Segmenter.from_config(SegmentationConfig(knn=0, floor_band=0, object_gap=0, weights=str(path), max_beams=32))
    np.testing.assert_array_equal(same.predict(f.points, grid, f.intensity)[0],
                                  every.predict(f.points, grid, f.intensity)[0])
    with pytest.raises(ProjectionError, match="grid / ring must have"):  # a bad cloud says so, as without max_beams
        half.predict(f.points, f.ring[:-1], f.intensity)
    with pytest.raises(SegmentationError, match="max_beams must be a whole number"):
        Segmenter.from_config(SegmentationConfig(knn=0, floor_band=0, object_gap=0, weights=str(path), max_beams=-1))


def test_without_onnxruntime_the_segmenter_falls_back_to_eager(tmp_path, frames, monkeypatch, caplog):
    _, path = _random_weights(tmp_path)
    monkeypatch.setitem(sys.modules, "onnxruntime", None)  # the package is absent: import raises ImportError
    seg = Segmenter.from_config(SegmentationConfig(knn=0, floor_band=0, object_gap=0, weights=str(path)))
    assert seg.backend == "eager" and "using eager PyTorch" in caplog.text
    labels, _ = seg.predict(frames[0].points, frames[0].ring, frames[0].intensity)
    assert labels.shape == (len(frames[0].points),)


def test_unknown_backend_is_a_clear_error(tmp_path):
    _, path = _random_weights(tmp_path)
    with pytest.raises(SegmentationError, match="unknown segmentation backend"):
        Segmenter.from_config(SegmentationConfig(knn=0, floor_band=0, object_gap=0, weights=str(path), backend="tensorrt"))
    with pytest.raises(ValueError, match="segmentation.backend"):
        load_config(overrides={"segmentation.backend": "tensorrt"})
    assert load_config(overrides={"segmentation.backend": "eager"}).segmentation.backend == "eager"


def test_missing_weights_raise_segmentation_error(tmp_path):
    with pytest.raises(SegmentationError, match="not found"):
        Segmenter.from_config(SegmentationConfig(weights=str(tmp_path / "none.pt")))


def test_garbage_bytes_raise_segmentation_error(tmp_path):
    bad = tmp_path / "garbage.pt"
    bad.write_bytes(os.urandom(4096))
    with pytest.raises(SegmentationError, match="not a safe torch weights file"):
        load_weights(bad)


class _Exploit:
    def __init__(self, target):
        self.target = target

    def __reduce__(self):
        return (os.mkdir, (self.target,))


def test_malicious_pickle_is_refused_without_running_code(tmp_path):
    target = tmp_path / "pwned"
    evil = tmp_path / "evil.pt"
    torch.save({"model_card": {}, "state_dict": {"x": _Exploit(str(target))}}, evil)
    with pytest.raises(SegmentationError, match="not a safe torch weights file"):
        load_weights(evil)
    raw = tmp_path / "raw.pt"
    raw.write_bytes(pickle.dumps(_Exploit(str(target))))
    with pytest.raises(SegmentationError):
        load_weights(raw)
    assert not target.exists()


def test_wrong_shapes_and_keys_raise_segmentation_error(tmp_path, frames):
    model, path = _random_weights(tmp_path / "ok")
    card, state = load_weights(path)
    key = "stem.conv.weight"
    wrong = dict(state, **{key: torch.zeros(3, 3, 3, 3)})
    _save(tmp_path / "shape.pt", card, wrong)
    with pytest.raises(SegmentationError, match="stem.conv.weight"):
        Segmenter.from_config(SegmentationConfig(weights=str(tmp_path / "shape.pt")))
    missing = {k: v for k, v in state.items() if k != key}
    _save(tmp_path / "missing.pt", card, missing)
    with pytest.raises(SegmentationError, match="missing"):
        Segmenter.from_config(SegmentationConfig(weights=str(tmp_path / "missing.pt")))
    _save(tmp_path / "card.pt", {**card, "model": {**card["model"], "widths": [8, 8, 8]}}, state)
    with pytest.raises(SegmentationError, match="needs"):
        Segmenter.from_config(SegmentationConfig(weights=str(tmp_path / "card.pt")))
    torch.save([1, 2, 3], tmp_path / "list.pt")
    with pytest.raises(SegmentationError, match="expected"):
        load_weights(tmp_path / "list.pt")


def test_modified_weights_fail_the_checksums(tmp_path):
    _, path = _random_weights(tmp_path)
    card, state = load_weights(path)
    state["head.bias"] = state["head.bias"] + 1  # a valid file, but not the one the card describes
    _save(path, card, state)
    with pytest.raises(SegmentationError, match="sha256"):  # model_card.json beside it names the file's hash
        load_weights(path)
    (tmp_path / "model_card.json").unlink()
    load_weights(path)  # consistent digest, no card beside it: loads
    doc = torch.load(path, weights_only=True)
    doc["state_dict"]["head.bias"][0] += 1e-3  # tensors changed after the digest was taken
    torch.save(doc, path)
    with pytest.raises(SegmentationError, match="checksum mismatch"):
        load_weights(path)
    del doc["state_sha256"]
    torch.save(doc, path)
    with pytest.raises(SegmentationError, match="no state_sha256"):
        load_weights(path)


def test_weights_with_non_finite_values_or_another_dtype_are_refused(tmp_path):
    """A file whose digest is right but whose tensors are NaN, or float64 where the network holds float32, is
    refused naming the tensor (NaN weights would give every point a meaningless label, silently)."""
    _, path = _random_weights(tmp_path)
    card, state = load_weights(path)
    nan = dict(state, **{"head.bias": torch.full_like(state["head.bias"], float("nan"))})
    with pytest.raises(SegmentationError, match="'head.bias' has non-finite values"):
        build_model(card, nan)
    double = dict(state, **{"head.bias": state["head.bias"].double()})
    with pytest.raises(SegmentationError, match="'head.bias' is .*torch.float64, the network needs .*torch.float32"):
        build_model(card, double)
    build_model(card, state)  # the file as saved builds


def test_bad_device_is_a_clear_error(tmp_path):
    _, path = _random_weights(tmp_path)
    with pytest.raises(SegmentationError, match="device"):
        Segmenter.from_config(SegmentationConfig(knn=0, floor_band=0, object_gap=0, weights=str(path), device="tpu"))


def test_augment_keeps_labels_and_builds_consistent_channels():
    g = torch.Generator().manual_seed(0)
    rng = np.random.default_rng(0)
    xyz = torch.from_numpy(rng.normal(0, 5, (4, 3, 32, 48)).astype(np.float32))
    y = torch.from_numpy(rng.integers(0, 7, (4, 32, 48)))
    y[:, :4] = 255  # rows without returns
    xyz[:, :, :4] = 0
    x = torch.cat([xyz, torch.full((4, 1, 32, 48), 100.0)], 1)
    cfg = TrainConfig(max_dropout=0.0)
    inp, y2 = augment(x, y.clone(), cfg, g)
    counts = lambda t: np.bincount(t[t != 255].numpy().ravel(), minlength=7)  # noqa: E731
    np.testing.assert_array_equal(counts(y2), counts(y))  # yaw / mirror / jitter move labels, never change them
    valid = inp[:, 5] > 0
    assert torch.equal(valid, y2 != 255)
    torch.testing.assert_close(inp[:, 0], torch.linalg.vector_norm(inp[:, 1:4], dim=1))
    assert inp[:, :5][~valid.unsqueeze(1).expand(-1, 5, -1, -1)].abs().max() == 0


def test_class_weights_favour_rare_classes():
    labels = np.array([C.WALL] * 900 + [C.CHAIR] * 100 + [255] * 50, np.uint8)
    w = class_weights(labels)
    assert w[C.CHAIR] > w[C.WALL] > 0 and w[C.FLOOR] == 0


def test_crops_give_every_sensor_model_an_equal_share_however_its_images_are_grouped():
    def group(sensors, width):
        n = len(sensors)
        fill = np.array([SENSOR_CODES[s] for s in sensors], np.float16)[:, None, None, None]
        return {"images": np.broadcast_to(fill, (n, 4, 8, width)).copy(), "labels": np.zeros((n, 8, width), np.uint8),
                "sensor": np.array(sensors)}

    # the Mid-360 fills three widths (one of them a single odd scan); three Ouster models share one shape,
    # the OS1-128 with four images a scan
    groups = [group(["Mid-360"] * n, w) for n, w in ((6, 576), (1, 640), (1, 704))]
    groups += [group(["OS1-128"] * 8 + ["OS0-32", "OS1-64", "OS1-64"], 1024), group(["VLP-32C"], 1800)]
    strata, chances = sensor_strata(groups)
    assert [(st.group, st.sensor, len(st.images)) for st in strata] == [
        (0, "Mid-360", 6), (1, "Mid-360", 1), (2, "Mid-360", 1), (3, "OS0-32", 1), (3, "OS1-128", 8),
        (3, "OS1-64", 2), (4, "VLP-32C", 1)]
    assert np.allclose(chances, [6 / 40, 1 / 40, 1 / 40, 1 / 5, 1 / 5, 1 / 5, 1 / 5])
    rng = np.random.default_rng(0)
    drawn = []
    for _ in range(3000):
        x, _ = sample_crops(groups, 2, 480, rng)
        assert len(torch.unique(x[:, 0])) == 1  # one sensor model per batch
        drawn.append(int(x[0, 0, 0, 0]))
    share = np.bincount(drawn, minlength=len(SENSOR_CODES)) / len(drawn)
    assert np.allclose(share, 1 / 5, atol=0.03), share  # by shape, the three Ouster models would share 1/3
    summary = strata_summary(groups, strata, chances).splitlines()
    assert summary[0] == "training batches by sensor model (5):"
    assert "20.0 %       8 images (8x576, 8x640, 8x704): Mid-360" in summary[1]
    assert summary[3].endswith("8 images (8x1024): OS1-128")


def test_validation_is_the_mean_of_each_sensor_models_miou_not_the_pooled_pixels():
    perfect = np.diag([0, 100, 100, 100, 100, 100, 0]).astype(np.int64)  # the five paper classes right
    poor = perfect.copy()
    poor[C.FLOOR, C.FLOOR], poor[C.FLOOR, C.WALL] = 50, 50  # floor IoU 0.5, wall 100 / 150
    entry = validation_entry({"OS1-128": 8 * perfect, "VLP-16": poor})
    poor_miou = (0.5 + 100 / 150 + 3) / 5
    assert entry["val_miou_by_sensor"] == {"OS1-128": 1.0, "VLP-16": round(poor_miou, 4)}
    assert entry["val_miou"] == pytest.approx((1 + poor_miou) / 2, abs=1e-4)
    pooled = (850 / 900 + 900 / 950 + 3) / 5  # the 128-beam model's pixels would hide the VLP-16's floor
    assert entry["val_iou"]["floor"] == pytest.approx(850 / 900, abs=1e-4) and pooled > entry["val_miou"] + 0.05


SENSOR_CODES = {"Mid-360": 0, "OS0-32": 1, "OS1-128": 2, "OS1-64": 3, "VLP-32C": 4}


def test_a_share_set_for_one_model_leaves_the_rest_equal_shares_and_is_what_batches_draw():
    def group(sensors, width):
        fill = np.array([SENSOR_CODES[s] for s in sensors], np.float16)[:, None, None, None]
        return {"images": np.broadcast_to(fill, (len(sensors), 4, 8, width)).copy(),
                "labels": np.zeros((len(sensors), 8, width), np.uint8), "sensor": np.array(sensors)}

    groups = [group(["Mid-360"] * 3, 576), group(["Mid-360"], 640), group(["OS1-128"] * 4 + ["OS0-32"], 1024),
              group(["VLP-32C"] * 2, 1800)]
    strata, chances = sensor_strata(groups, {"Mid-360": 0.4})
    per_model = {}
    for st, p in zip(strata, chances):
        per_model[st.sensor] = per_model.get(st.sensor, 0) + p
    assert per_model == pytest.approx({"Mid-360": 0.4, "OS0-32": 0.2, "OS1-128": 0.2, "VLP-32C": 0.2})
    assert chances[:2] == pytest.approx([0.3, 0.1])  # the Mid-360's share split over its widths by image count
    rng = np.random.default_rng(3)
    drawn = [int(sample_crops(groups, 1, 480, rng, (strata, chances))[0][0, 0, 0, 0]) for _ in range(4000)]
    assert np.bincount(drawn, minlength=5)[SENSOR_CODES["Mid-360"]] / 4000 == pytest.approx(0.4, abs=0.03)
    assert np.allclose(sensor_strata(groups, {})[1], sensor_strata(groups)[1])
    for bad in ({"HDL-64E": 0.2}, {"Mid-360": 0.7, "VLP-32C": 0.5}, {"Mid-360": 1.0}, {"Mid-360": -0.1}):
        with pytest.raises(ValueError, match="--share"):
            sensor_strata(groups, bad)
    every = {"Mid-360": 0.25, "OS0-32": 0.25, "OS1-128": 0.25, "VLP-32C": 0.25}
    assert np.allclose(sensor_strata(groups, every)[1], sensor_strata(groups)[1])


def test_crops_are_the_images_columns_wrapping_around_on_any_device():
    rng = np.random.default_rng(1)
    images = rng.normal(0, 5, (3, 4, 8, 64)).astype(np.float16)
    labels = rng.integers(0, 7, (3, 8, 64)).astype(np.uint8)
    groups = [{"images": images, "labels": labels, "sensor": np.array(["VLP-32C"] * 3)}]
    x, y = sample_crops(groups, 5, 48, np.random.default_rng(2))
    assert x.dtype == torch.float32 and y.dtype == torch.int64 and x.shape == (5, 4, 8, 48) and y.shape == (5, 8, 48)
    draw = np.random.default_rng(2)  # the same draws, cut with numpy
    draw.choice(1, p=[1.0])
    idx, start = draw.integers(3, size=5), draw.integers(64, size=5)
    for k in range(5):
        cols = (start[k] + np.arange(48)) % 64
        np.testing.assert_array_equal(x[k].numpy(), images[idx[k]][..., cols].astype(np.float32))
        np.testing.assert_array_equal(y[k].numpy(), labels[idx[k]][..., cols])
    on_torch = [{**groups[0], "images": torch.from_numpy(images), "labels": torch.from_numpy(labels)}]
    x2, y2 = sample_crops(on_torch, 5, 48, np.random.default_rng(2))
    assert torch.equal(x, x2) and torch.equal(y, y2)
    wide = sample_crops(groups, 2, 480, np.random.default_rng(3))[0]
    assert wide.shape == (2, 4, 8, 64)  # a narrower image is cut at its own width


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_crops_cut_on_the_gpu_equal_those_cut_on_the_cpu():
    rng = np.random.default_rng(5)
    images = rng.normal(0, 5, (3, 4, 8, 64)).astype(np.float16)
    labels = rng.integers(0, 7, (3, 8, 64)).astype(np.uint8)
    cpu = [{"images": images, "labels": labels, "sensor": np.array(["VLP-32C"] * 3)}]
    gpu = [{**cpu[0], "images": torch.from_numpy(images).cuda(), "labels": torch.from_numpy(labels).cuda()}]
    x, y = sample_crops(cpu, 5, 48, np.random.default_rng(6))
    xg, yg = sample_crops(gpu, 5, 48, np.random.default_rng(6))
    assert xg.is_cuda and torch.equal(x, xg.cpu()) and torch.equal(y, yg.cpu())
    truth, pred = y.cuda(), yg.flip(-1)
    assert torch.equal(confusion_on(truth, pred).cpu(), confusion_on(y, pred.cpu()))


def test_confusion_on_the_device_counts_as_metrics_confusion():
    rng = np.random.default_rng(4)
    truth = rng.integers(0, 9, (4, 16, 32))
    truth[truth == 8] = 255
    pred = rng.integers(0, 7, (4, 16, 32))
    np.testing.assert_array_equal(confusion_on(torch.from_numpy(truth), torch.from_numpy(pred)).numpy(),
                                  confusion(truth, pred))


def test_lovasz_is_zero_for_a_perfect_prediction_and_grows_with_errors():
    labels = torch.tensor([0, 1, 1, 2, 2, 2])
    perfect = torch.nn.functional.one_hot(labels, 3).float()
    assert lovasz_softmax(perfect, labels).item() == pytest.approx(0.0)
    worse = perfect.clone()
    worse[0] = torch.tensor([0.5, 0.5, 0.0])
    worst = perfect.clone()
    worst[:2] = torch.tensor([0.0, 0.0, 1.0])
    assert 0 < lovasz_softmax(worse, labels).item() < lovasz_softmax(worst, labels).item()


def test_segment_frame_follows_the_configured_mode(tmp_path, frames):
    from topometric_ros.segmentation.infer import segment_frame

    f = frames[0]
    labels, conf = segment_frame(f, SegmentationConfig(mode="labels"))
    np.testing.assert_array_equal(labels, f.labels)
    assert conf is None
    assert segment_frame(f, SegmentationConfig(mode="none")) == (None, None)
    _, path = _random_weights(tmp_path)
    cfg = SegmentationConfig(knn=0, floor_band=0, object_gap=0, weights=str(path))
    seg = Segmenter.from_config(cfg)
    labels, conf = segment_frame(f, cfg, seg)
    np.testing.assert_array_equal(labels, seg.predict(f.points, f.ring, f.intensity)[0])
    low = float(np.median(conf))
    strict, _ = segment_frame(f, SegmentationConfig(knn=0, floor_band=0, object_gap=0, weights=str(path),
                                                    min_confidence=low), seg)
    assert (strict == C.OTHER).sum() > (labels == C.OTHER).sum()
    np.testing.assert_array_equal(strict, np.where(conf < low, C.OTHER, labels))  # the confident keep their labels
    with pytest.raises(SegmentationError, match="no label field"):
        segment_frame(type(f)(points=f.points, pose=f.pose, stamp=0.0), SegmentationConfig(mode="labels"))
    with pytest.raises(SegmentationError, match="needs a Segmenter"):
        segment_frame(f, cfg)


def test_blend_is_linear_between_the_parent_and_the_tuned_weights(tmp_path):
    from topometric_ros.segmentation.checkpoint import blend_weights

    _, parent = _random_weights(tmp_path / "parent", seed=1)
    _, tuned = _random_weights(tmp_path / "tuned", seed=2)
    sp, st = load_weights(parent)[1], load_weights(tuned)[1]
    ends = [load_weights(blend_weights(parent, tuned, a, tmp_path / f"b{a}"))[1] for a in (0.0, 1.0)]
    for k in st:
        assert torch.equal(ends[0][k], sp[k] if st[k].is_floating_point() else st[k]) and torch.equal(ends[1][k], st[k])
    card, quarter = load_weights(blend_weights(parent, tuned, 0.25, tmp_path / "q", "topometric blend ..."))
    for k, v in st.items():
        if v.is_floating_point():
            torch.testing.assert_close(quarter[k], 0.75 * sp[k] + 0.25 * v)
    assert card["training"]["blend"]["alpha"] == 0.25
    assert card["training"]["blend"]["parent_state_sha256"] == state_digest(sp)
    assert not card["training"]["blend"]["tuned_from_parent"]  # two unrelated random networks
    model = RangeNet(ModelSpec())
    model.load_state_dict(st)
    from_parent = save_weights(model, model_card(model.spec, TrainConfig(), [], [], "test", [], 0, 0, 0.0,
                                                 init={"state_sha256": state_digest(sp)}), tmp_path / "ft")
    assert load_weights(blend_weights(parent, from_parent, 0.5, tmp_path / "h"))[0]["training"]["blend"]["tuned_from_parent"]
    assert card["metrics"]["val"] == {}  # the tuned run's validation result is not the blend's
    other = RangeNet(ModelSpec(widths=(16, 24, 32)))
    wrong = save_weights(other, model_card(other.spec, TrainConfig(), [], [], "test", [], 0, 0, 0.0), tmp_path / "w")
    with pytest.raises(SegmentationError, match="different networks"):
        blend_weights(parent, wrong, 0.5, tmp_path / "x")
    with pytest.raises(SegmentationError, match=r"within \[0, 1\]"):
        blend_weights(parent, tuned, 1.5, tmp_path / "x")
