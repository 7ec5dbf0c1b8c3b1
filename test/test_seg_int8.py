"""The int8 network (segmentation/quantize.py, config segmentation.precision): calibrated activation ranges
shipped beside the weights, the body quantized at load time, the same labels as float32 on nearly every point."""
from __future__ import annotations

import json
import logging
import shutil

import numpy as np
import onnx
import pytest

from topometric_ros.config import SegmentationConfig
from topometric_ros.segmentation.checkpoint import SHIPPED, load_weights, state_digest
from topometric_ros.segmentation.infer import Segmenter, export_onnx
from topometric_ros.segmentation.quantize import (RANGES_NAME, _merge, calibrate_scans, cpu_has_vnni, cpu_runs_int8,
                                                  load_ranges, quantize, write_ranges)
from topometric_ros.sim.frames import simulated_frames


@pytest.fixture(scope="module")
def frames():
    return simulated_frames("office2", 2, seed=4242)[0]


def _labels(seg, frames):
    return np.concatenate([seg.predict(f.points, f.ring, f.intensity)[0] for f in frames])


def test_vnni_is_read_off_the_cpu_flags(tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nflags\t\t: fpu sse avx2 avx512f avx512_vnni\n")
    assert cpu_has_vnni(info)
    info.write_text("processor\t: 0\nflags\t\t: fpu sse avx2 avx512f\n")  # avx512f alone is no VNNI
    assert not cpu_has_vnni(info)
    assert not cpu_has_vnni(tmp_path / "absent")


def test_auto_runs_int8_on_x86_cpus_with_vnni_or_avx2_only(tmp_path):
    """precision auto: int8 where the flags show VNNI or AVX2 (7-bit weights there), float32 on a CPU with neither
    (an old x86, or no x86 flags at all: other architectures are not measured)."""
    info = tmp_path / "cpuinfo"
    for flags, int8, vnni in (("fpu sse avx2 avx512f avx512_vnni", True, True), ("fpu sse avx avx2 fma", True, False),
                              ("fpu sse sse4_2 avx", False, False)):
        info.write_text(f"processor\t: 0\nflags\t\t: {flags}\n")
        assert (cpu_runs_int8(info), cpu_has_vnni(info)) == (int8, vnni), flags
    info.write_text("processor\t: 0\nFeatures\t: fp asimd asimddp\n")  # aarch64: no x86 flags line
    assert not cpu_runs_int8(info) and not cpu_runs_int8(tmp_path / "absent")


def test_the_shipped_ranges_fit_the_shipped_weights_and_no_others(tmp_path):
    _, state = load_weights(SHIPPED)
    ranges, why = load_ranges(SHIPPED, state_digest(state))
    assert why == "" and ranges["calibration_method"]
    doc = json.loads((SHIPPED.parent / RANGES_NAME).read_text())
    assert doc["command"].startswith("topometric quantize ") and doc["images"] > 100
    ranges, why = load_ranges(SHIPPED, "0" * 64)
    assert ranges is None and "made for other weights" in why
    ranges, why = load_ranges(tmp_path / "rangenet.pt", state_digest(state))
    assert ranges is None and "topometric quantize" in why


def test_only_the_body_runs_int8_the_stem_and_head_stay_float():
    seg = Segmenter.from_config(SegmentationConfig(precision="float32"))
    _, state = load_weights(SHIPPED)
    ranges, _ = load_ranges(SHIPPED, state_digest(state))
    model = onnx.load_from_string(quantize(export_onnx(seg.scorer, 32, 1024), ranges))
    convs = [n for n in model.graph.node if n.op_type == "Conv"]
    made = {o: n.op_type for n in model.graph.node for o in n.output}
    float_convs = [n.name for n in convs if made.get(n.input[0]) != "DequantizeLinear"]
    assert float_convs == ["/stem/conv/Conv", "/head/Conv"]
    assert len(convs) == 13  # the other 11 read int8 activations and weights


def test_int8_weights_take_all_8_bits_with_vnni_and_7_without():
    """ORT's reduce_range: on an AVX2 CPU without VNNI the body's weights take 7 bits (|q| <= 64), so the 16-bit
    sums of 8-bit products cannot saturate; with VNNI all 8 (|q| up to 127). Read off the quantized graph."""
    from onnx import numpy_helper

    from topometric_ros.segmentation.checkpoint import build_model
    from topometric_ros.segmentation.infer import Scorer
    from topometric_ros.segmentation.model import fold_batchnorm

    card, state = load_weights(SHIPPED)
    ranges, _ = load_ranges(SHIPPED, state_digest(state))
    scorer = Scorer(fold_batchnorm(build_model(card, state))).eval()
    model = onnx.load_from_string(quantize(export_onnx(scorer, 32, 64), ranges))
    weights = [numpy_helper.to_array(t) for t in model.graph.initializer if t.data_type == onnx.TensorProto.INT8]
    assert len(weights) >= 11
    largest = max(int(np.abs(w.astype(np.int32)).max()) for w in weights)
    assert (largest > 64) == cpu_has_vnni() and largest <= 127, largest


def test_auto_precision_runs_int8_exactly_where_the_cpu_runs_int8():
    """segmentation.precision auto (the default): int8 on this machine when its CPU has VNNI or AVX2 (the shipped
    ranges fit the shipped weights), float32 otherwise."""
    assert SegmentationConfig().precision == "auto"
    seg = Segmenter.from_config(SegmentationConfig())
    assert seg.precision == ("int8" if cpu_runs_int8() else "float32")


def test_int8_gives_the_float32_labels_on_nearly_every_point(frames):
    f32 = Segmenter.from_config(SegmentationConfig(precision="float32"))
    int8 = Segmenter.from_config(SegmentationConfig(precision="int8"))
    assert (f32.precision, int8.precision) == ("float32", "int8")
    a, b = _labels(f32, frames), _labels(int8, frames)
    assert 0.99 <= (a == b).mean() < 1.0  # not the same network, nearly the same labels


def test_int8_without_ranges_for_the_weights_falls_back_to_float32_and_says_why(tmp_path, caplog, frames):
    shutil.copy(SHIPPED, tmp_path / "rangenet.pt")
    with caplog.at_level(logging.INFO):
        seg = Segmenter.from_config(SegmentationConfig(weights=str(tmp_path / "rangenet.pt"), precision="int8"))
    assert seg.precision == "float32"
    assert any(r.levelno == logging.WARNING and "topometric quantize" in r.getMessage() for r in caplog.records)
    for cfg in (SegmentationConfig(precision="int8", passes=2), SegmentationConfig(precision="int8", backend="eager")):
        assert Segmenter.from_config(cfg).precision == "float32"


def test_a_segmenter_of_several_passes_runs_float32_even_when_given_ranges(caplog):
    """int8 is calibrated for one pass: a Segmenter built with ranges and passes 2 (not only via from_config,
    which gives it no ranges then) runs its multi-pass network float32 without trying (and failing) int8."""
    from topometric_ros.segmentation.checkpoint import build_model

    card, state = load_weights(SHIPPED)
    ranges, _ = load_ranges(SHIPPED, state_digest(state))
    with caplog.at_level(logging.WARNING):
        seg = Segmenter(build_model(card, state), card, passes=2, int8_ranges=ranges)
    assert (seg.backend, seg.precision) == ("onnxruntime", "float32") and "int8" not in caplog.text


def _calibrated(folder, frames):
    """A copy of the shipped weights in ``folder`` with ranges calibrated on ``frames``; its Segmenter."""
    shutil.copy(SHIPPED, folder / "rangenet.pt")
    ranges, images, digest = calibrate_scans(folder / "rangenet.pt", [(f.points, f.ring, f.intensity) for f in frames])
    assert images == len(frames)  # one 32-row image per VLP-32C scan
    write_ranges(ranges, folder / "rangenet.pt", digest, "test", images)
    return Segmenter.from_config(SegmentationConfig(weights=str(folder / "rangenet.pt"), precision="int8"))


def test_an_image_shape_the_network_cannot_read_falls_back_alone_not_the_whole_segmenter(frames, caplog):
    """A grid narrower than the network's circular padding allows (56 columns: grids are never built so narrow,
    see grid.MIN_COLUMNS) fails to export int8, then float32, and fails in eager PyTorch too: that scan raises,
    with a warning naming the shape, and the next scans still run int8 in ONNX Runtime."""
    from topometric_ros.grid import ScanGrid, scan_grid

    seg = Segmenter.from_config(SegmentationConfig(precision="int8"))
    f = frames[0]
    grid = scan_grid(f.points, f.ring)
    narrow = ScanGrid(grid.row, grid.col % 56, grid.height, 56, grid.elevation_deg, grid.source)
    with caplog.at_level(logging.WARNING), pytest.raises(RuntimeError, match="[Pp]adding"):
        seg.predict(f.points, narrow, f.intensity)
    assert "int8 network unavailable for 32x56 images" in caplog.text
    assert "onnxruntime export failed for 32x56 images" in caplog.text
    assert (seg.backend, seg.precision) == ("onnxruntime", "int8")
    labels, _ = seg.predict(f.points, grid, f.intensity)
    assert seg._onnx[(grid.height, grid.width, False)] is not None  # this shape's own int8 export
    want = Segmenter.from_config(SegmentationConfig(precision="int8")).predict(f.points, grid, f.intensity)[0]
    assert np.array_equal(labels, want)


def test_calibration_round_trip_ranges_written_beside_the_weights_run_int8(tmp_path, frames):
    garage = simulated_frames("garage", 2, seed=4242)[0]
    seg = _calibrated(tmp_path, frames + garage)
    assert seg.precision == "int8"
    f32 = Segmenter.from_config(SegmentationConfig(precision="float32"))
    assert (_labels(seg, frames) == _labels(f32, frames)).mean() >= 0.99


def test_ranges_too_narrow_for_the_load_time_check_give_float32_with_the_reason(tmp_path, frames, caplog):
    """Two scans of one office: activations of farther ranges saturate; the check on the probe image
    (ranges to 30 m) refuses the int8 network."""
    with caplog.at_level(logging.WARNING):
        seg = _calibrated(tmp_path, frames)
    assert seg.precision == "float32"
    assert any("int8 network unavailable" in r.getMessage() and "labels agree" in r.getMessage()
               for r in caplog.records)


def test_ranges_of_several_image_shapes_merge_to_the_widest():
    def cache(lo, hi):
        arr = lambda v: {"data": [v], "dtype": "float32", "CLS": "numpy.array"}  # noqa: E731
        return {"CLS": "TensorsData", "calibration_method": "MinMax",
                "data": {"t": {"lowest": arr(lo), "highest": arr(hi), "CLS": "TensorData"}}}
    merged = _merge(cache(-1.0, 2.0), cache(-3.0, 1.0))
    assert merged["data"]["t"]["lowest"]["data"] == [-3.0] and merged["data"]["t"]["highest"]["data"] == [2.0]
    only_second = cache(-5.0, 5.0)
    only_second["data"]["u"] = only_second["data"].pop("t")  # a tensor the first shape's cache lacks is kept
    assert set(_merge(cache(-1.0, 2.0), only_second)["data"]) == {"t", "u"}
    assert _merge({}, cache(0.0, 1.0)) == cache(0.0, 1.0)


def test_quantizing_at_load_time_says_nothing_of_onnx_runtime_internals(caplog):
    """ONNX Runtime's quantizer advises pre-processing on the root logger; a user should not see that."""
    with caplog.at_level(logging.INFO):
        seg = Segmenter.from_config(SegmentationConfig(precision="int8"))
    assert seg.precision == "int8"
    assert [r.getMessage() for r in caplog.records if "onnxruntime" in r.pathname] == []
