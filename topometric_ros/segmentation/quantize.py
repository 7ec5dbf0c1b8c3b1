"""The network in int8 on x86 CPUs with VNNI or AVX2: activation ranges calibrated once on simulated scans and
shipped beside the weights (``rangenet.int8.json``), the exported network quantized in memory at load time.

Only the body of the net runs int8 (ONNX Runtime QDQ, per-channel int8 weights, uint8 activations): the stem
(raw ranges and coordinates in), the head (scores out) and the read-out (infer.read_out, numpy) stay float32; quantizing those too
cost 13.5 mIoU (docs/results.md). Without VNNI, AVX2 multiplies 8-bit integers into 16-bit sums that can
saturate, so there the weights take 7 bits (ORT's reduce_range): measured on an AVX2 CPU without VNNI, the whole
per-scan pipeline 12-23 % faster, mIoU -0.28 to +0.02 of float32 on the unseen layout (docs/results.md, twenty-first session).
``segmentation.precision: auto`` runs int8 where the CPU has either (cpu_runs_int8), float32 elsewhere (other
architectures: not measured).
"""
from __future__ import annotations

import contextlib
import copy
import hashlib
import json
import logging
import tempfile
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np


log = logging.getLogger(__name__)

RANGES_NAME = "rangenet.int8.json"
FORMAT_VERSION = 1
#: RangeNet's modules that run int8 (its body); the stem and the head stay float32.
INT8_MODULES = ("enc2", "enc3", "fuse2", "fuse1", "refine")
#: ONNX operators quantized inside those modules (Slice + Concat are the circular azimuth padding).
INT8_OPS = ["Conv", "Concat", "Slice", "Relu", "Add", "Resize"]
VNNI_FLAGS = ("avx512_vnni", "avx_vnni", "amx_int8")
#: x86 flags of CPUs where ``precision: auto`` runs int8: VNNI, or AVX2 (7-bit weights there).
INT8_FLAGS = (*VNNI_FLAGS, "avx2")


def _cpu_flags(cpuinfo: str | Path) -> list[str]:
    """The x86 flags of ``cpuinfo`` (/proc/cpuinfo); none when it cannot be read (another OS or architecture)."""
    try:
        text = Path(cpuinfo).read_text()
    except OSError:
        return []
    return next((line.split(":", 1)[1].split() for line in text.splitlines() if line.startswith("flags")), [])


def cpu_has_vnni(cpuinfo: str | Path = "/proc/cpuinfo") -> bool:
    """Whether the CPU multiplies 8-bit integers with VNNI (x86 flags avx512_vnni, avx_vnni or amx_int8)."""
    return any(f in _cpu_flags(cpuinfo) for f in VNNI_FLAGS)


def cpu_runs_int8(cpuinfo: str | Path = "/proc/cpuinfo") -> bool:
    """Whether ``segmentation.precision: auto`` runs int8 here: an x86 CPU with VNNI or AVX2 (INT8_FLAGS)."""
    return any(f in _cpu_flags(cpuinfo) for f in INT8_FLAGS)


def int8_nodes(model) -> list[str]:
    """Names of the exported graph's nodes that run int8: those inside INT8_MODULES (torch names a node
    ``/module/.../Op``)."""
    return [n.name for n in model.graph.node if n.name.split("/")[1:2] and n.name.split("/")[1] in INT8_MODULES]


def make_ranges(bags: Sequence[str | Path], weights: str | Path, every: int = 2,
                command: str = "") -> tuple[Path, int]:
    """Calibrate the int8 network of ``weights`` on every ``every``-th scan of ``bags`` (any sensors) and save
    the ranges beside the weights (:func:`write_ranges`); returns (the path, the range images calibrated on)."""
    from tqdm import tqdm

    from .data import read_scans

    scans = ((s.points, s.grid, s.intensity) for bag in tqdm(bags, desc="calibration scans", unit="bag")
             for s in read_scans(bag, every=every))
    ranges, images, digest = calibrate_scans(weights, scans)
    return write_ranges(ranges, weights, digest, command, images), images


def calibrate_scans(weights: str | Path, scans: Iterable[tuple]) -> tuple[dict, int, str]:
    """(activation ranges, range images seen, the weights' state digest) of the network of ``weights`` run
    one pass on every beam of ``scans``: (points (N, 3) sensor frame, grid.ScanGrid or beam ids, intensity)."""
    from .checkpoint import build_model, load_weights, state_digest
    from .infer import Scorer, export_onnx
    from .model import fold_batchnorm
    from .projection import checked, project

    card, state = load_weights(weights)
    scorer = Scorer(fold_batchnorm(build_model(card, state, str(weights)))).eval()
    by_shape: dict[tuple, list[np.ndarray]] = {}
    for points, grid, intensity in scans:
        images, _ = project(*checked(points, grid, intensity), intensity)
        by_shape.setdefault(images.shape[2:], []).append(images.astype(np.float32))
    if not by_shape:
        raise ValueError("no scans to calibrate the int8 network on")
    ranges = calibrate((export_onnx(scorer, *shape), images) for shape, images in by_shape.items())
    n = sum(im.shape[0] for images in by_shape.values() for im in images)
    return ranges, n, state_digest(state)


def load_ranges(weights: str | Path, state_sha256: str) -> tuple[dict | None, str]:
    """(ORT calibration ranges, "") for the weights whose tensors hash to ``state_sha256``, or (None, why not)."""
    from .checkpoint import read_beside

    doc, why = read_beside(weights, RANGES_NAME, FORMAT_VERSION, "ranges", state_sha256, "activation ranges",
                           "topometric quantize")
    return (None, why) if doc is None else (doc["ranges"], "")


def quantize(model_bytes: bytes, ranges: dict) -> bytes:
    """The exported float32 network (ONNX bytes) with its body quantized to int8 using ``ranges``."""
    with tempfile.TemporaryDirectory(prefix="topometric-int8-") as tmp:
        cache = Path(tmp) / "ranges.json"
        cache.write_text(json.dumps(ranges))
        return _quantize_static(model_bytes, None, cache)


def _quantize_static(model_bytes: bytes, images, cache: Path) -> bytes:
    """ORT static QDQ quantization of the body (INT8_MODULES): ranges read from ``cache``, or measured on
    ``images`` (a CalibrationDataReader) and written there. Without VNNI the weights take 7 bits (ORT's
    reduce_range: no saturation in the 16-bit sums of AVX2's 8-bit products)."""
    import onnx
    from onnxruntime.quantization import QuantFormat, QuantType, quantize_static

    model = onnx.load_from_string(model_bytes)
    out = cache.with_suffix(".onnx")
    with _quiet_root_logger():
        quantize_static(model, out, images, quant_format=QuantFormat.QDQ, op_types_to_quantize=INT8_OPS,
                        nodes_to_quantize=int8_nodes(model), per_channel=True, reduce_range=not cpu_has_vnni(),
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                        calibration_cache_path=cache)
    return out.read_bytes()


def calibrate(exports: Iterable[tuple[bytes, list[np.ndarray]]]) -> dict:
    """ORT MinMax activation ranges of the exported network over range images: ``exports`` gives, per image
    shape, (the export for that shape, its (B, 6, H, W) float32 images); the ranges of all shapes merged."""
    from onnxruntime.quantization import CalibrationDataReader

    class _Images(CalibrationDataReader):
        def __init__(self, images):
            self._it = iter([{"image": im[i:i + 1]} for im in images for i in range(im.shape[0])])

        def get_next(self):
            return next(self._it, None)

    merged: dict = {}
    with tempfile.TemporaryDirectory(prefix="topometric-int8-") as tmp:
        for i, (model_bytes, images) in enumerate(exports):
            cache = Path(tmp) / f"ranges{i}.json"
            _quantize_static(model_bytes, _Images(images), cache)
            merged = _merge(merged, json.loads(cache.read_text()))
    return merged


def _merge(a: dict, b: dict) -> dict:
    """Two ORT MinMax range caches as one: per tensor the lower lowest and the higher highest."""
    if not a:
        return b
    out = copy.deepcopy(a)
    for name, rb in b["data"].items():
        if name not in out["data"]:
            out["data"][name] = rb
            continue
        ra = out["data"][name]
        ra["lowest"] = _reduce(ra["lowest"], rb["lowest"], np.minimum)
        ra["highest"] = _reduce(ra["highest"], rb["highest"], np.maximum)
    return out


def _reduce(x, y, op):
    """Elementwise ``op`` of two ORT-serialised ranges: floats, or arrays {"data": [...], "dtype", "CLS"}."""
    if not isinstance(x, dict):
        return float(op(x, y))
    return {**x, "data": op(np.asarray(x["data"], np.float32), np.asarray(y["data"], np.float32)).tolist()}


@contextlib.contextmanager
def _quiet_root_logger():
    """ONNX Runtime's quantizer advises pre-processing on the root logger at WARNING; not for our users. Only
    its own records are dropped (other threads keep logging)."""
    def not_from_ort(record: logging.LogRecord) -> bool:
        return "onnxruntime" not in record.pathname

    root = logging.getLogger()
    root.addFilter(not_from_ort)
    try:
        yield
    finally:
        root.removeFilter(not_from_ort)


def write_ranges(ranges: dict, weights: str | Path, state_sha256: str, command: str, images: int) -> Path:
    """Save the ranges beside the weights, tied to their tensors' digest; returns the path."""
    from .checkpoint import write_beside

    doc = {"format_version": FORMAT_VERSION, "state_sha256": state_sha256, "command": command, "images": images,
           "ranges_sha256": hashlib.sha256(json.dumps(ranges, sort_keys=True).encode()).hexdigest(),
           "ranges": ranges}
    return write_beside(weights, RANGES_NAME, doc, indent=1)
