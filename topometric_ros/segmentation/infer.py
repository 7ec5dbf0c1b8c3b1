"""Run the shipped (or a given) range-image network on scans: per-point labels and confidence.

Weights come through checkpoint.py (safe load, key/shape/digest checks, SegmentationError with the reason).

CPU backends: ``onnxruntime`` (default) exports the checked network (BatchNorm folded; class scores out) to
ONNX in memory at load time and runs it with ONNX Runtime; the export is verified against PyTorch on a fixed
input and any failure (or a missing onnxruntime) falls back to ``eager`` PyTorch with a warning. Both
backends' scores are read out (arg-max, confidence) by one numpy/numba function, :func:`read_out`. The
shipped weights stay one ``.pt`` file; no ONNX file is written or read.
"""
from __future__ import annotations

import io
import logging
import warnings
from pathlib import Path
from typing import Sequence

import numba
import numpy as np
import torch

from torch import nn

from .. import classes as C
from ..config import SegmentationConfig
from .model import RangeNet, fold_batchnorm
from .projection import CHANNELS, Projection, beam_stride, checked, nearest_strided, project, strided
from .checkpoint import (SHIPPED, SegmentationError, beside, build_model, load_weights, one_line_reason, state_digest,
                         torch_device)
from .floor import lift_off_floor, snap_to_floor
from .knn import knn_vote
from .norm_stats import NORM_NAME, load_stats, with_stats
from .objects import unify_objects
from .quantize import cpu_runs_int8, load_ranges, quantize

BACKENDS = ("onnxruntime", "eager")
#: Largest |logit| difference between the ONNX Runtime export and PyTorch accepted at load time.
EXPORT_TOLERANCE = 1e-3
#: Image shape (rows, columns) the ONNX export is first made and checked for: a 32-beam, 1800-column grid.
PROBE_SHAPE = (32, 1800)
#: Least share of the probe image's labels the int8 network must give as PyTorch does (float32) at load time.
INT8_AGREEMENT = 0.95

log = logging.getLogger(__name__)

Scan = tuple  # (points (N, 3) float32, grid.ScanGrid | beam ids (N,) | None, intensity (N,) | None)


#: Most network passes per scan (config segmentation.passes): the image, its mirror, the image shifted.
MAX_PASSES = 3
Y_CHANNEL = CHANNELS.index("y")  # negated in the mirror image


class Scorer(nn.Module):
    """The network as the backends run it: (B, 6, H, W) range images -> class scores (B, classes, fold, H, W /
    fold) float32, log-probabilities up to a per-pixel constant; column j * fold + i of the image is
    [..., i, :, j]. :func:`read_out` turns them into labels and confidence, the same for every backend.

    ``passes`` 1: the network's folded logits. ``passes`` > 1 averages the softmax of several views of each
    image, each mapped back to the image's pixels, and scores its log (fold 1): 2 adds the mirror image
    (azimuth a -> -a, y -> -y; the labels are then mirror-invariant), 3 also the image turned by half a fold
    (the network folds ``fold`` columns into one pixel, so the shifted view groups them differently; no longer
    exactly mirror-invariant). The confidence is then the MEAN softmax's top value, lower than one pass's: the
    same segmentation.min_confidence drops more points."""

    def __init__(self, net: RangeNet, passes: int = 1):
        super().__init__()
        if passes != int(passes) or not 1 <= int(passes) <= MAX_PASSES:
            raise SegmentationError(f"segmentation.passes must be 1 to {MAX_PASSES}, got {passes}")
        if passes > 1 and net.spec.in_channels != len(CHANNELS):
            raise SegmentationError(f"segmentation.passes {passes} needs the {len(CHANNELS)} projection channels; "
                                    f"this network takes {net.spec.in_channels}")
        self.net = net
        self.passes = int(passes)
        self.shift = max(1, net.spec.fold // 2)
        sign = torch.ones(1, net.spec.in_channels, 1, 1)
        sign[:, Y_CHANNEL] = -1.0
        self.register_buffer("mirror_sign", sign, persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.passes == 1:
            return self.net.folded_logits(x)
        prob = torch.softmax(self.net(x), 1)
        prob = prob + _mirror(torch.softmax(self.net(_mirror(x) * self.mirror_sign), 1))  # its own inverse
        if self.passes > 2:
            turned = torch.softmax(self.net(torch.roll(x, self.shift, -1)), 1)
            prob = prob + torch.roll(turned, -self.shift, -1)
        return torch.log(prob / self.passes).unsqueeze(2)  # (b, k, 1, h, w)


def read_out(scores: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(labels (B, H, W) uint8, confidence (B, H, W) float32: the softmax probability of the label) of
    Scorer scores (B, classes, fold, H, W / fold) float32, with the azimuth unfolded. Overwrites ``scores``."""
    b, k, f, h, wf = scores.shape
    flat = scores.reshape(b, k, f * h * wf)
    top, labels = _top_class(flat)
    np.subtract(flat, top[:, None], out=flat)
    conf = np.reciprocal(np.exp(flat, out=flat).sum(1))  # max softmax = 1 / sum exp(score - top score)
    unfold = lambda a: a.reshape(b, f, h, wf).transpose(0, 2, 3, 1).reshape(b, h, wf * f)  # noqa: E731
    return unfold(labels), unfold(conf)


@numba.njit(cache=True, nogil=True)
def _top_class(scores: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(top score (B, N), its class (B, N) uint8) of scores (B, classes, N); ties go to the lower class."""
    b, k, n = scores.shape
    top = scores[:, 0].copy()
    labels = np.zeros((b, n), np.uint8)
    for i in range(b):
        for c in range(1, k):
            for j in range(n):
                if scores[i, c, j] > top[i, j]:
                    top[i, j] = scores[i, c, j]
                    labels[i, j] = c
    return top, labels


def _spread(labels: np.ndarray, conf: np.ndarray, source: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Per-point (labels, confidence) of the points the network saw, given to every point by ``source`` (None:
    they are every point); a point with no source (−1) is OTHER at confidence 0."""
    if source is None:
        return labels, conf
    found = source >= 0
    at = np.maximum(source, 0)
    return (np.where(found, labels.take(at), np.uint8(C.OTHER)).astype(np.uint8),
            np.where(found, conf.take(at), np.float32(0)).astype(np.float32))


def _mirror(t: torch.Tensor) -> torch.Tensor:
    """Column c -> column -c (mod width) of (..., W) images: the azimuth mirrored about the x axis."""
    return torch.roll(torch.flip(t, (-1,)), 1, -1)


def export_onnx(scorer: Scorer, height: int, width: int) -> bytes:
    """The Scorer as ONNX bytes for (B, 6, height, width) images (batch size free)."""
    buf = io.BytesIO()
    with warnings.catch_warnings():  # the TorchScript-based exporter warns that it is deprecated
        warnings.simplefilter("ignore")
        torch.onnx.export(scorer, (_probe_input(height, width),), buf, dynamo=False, input_names=["image"],
                          output_names=["scores"], opset_version=17,
                          dynamic_axes={"image": {0: "batch"}, "scores": {0: "batch"}})
    return buf.getvalue()


class _OnnxRunner:
    """A Scorer exported to ONNX in memory and run by ONNX Runtime on the CPU with ``threads`` threads, its
    scores read out by :func:`read_out`; with ``ranges`` (quantize.load_ranges) its body runs int8."""

    def __init__(self, scorer: Scorer, height: int, width: int, threads: int, ranges: dict | None = None):
        import onnxruntime as ort  # ImportError -> the caller falls back to eager

        model = export_onnx(scorer, height, width)
        if ranges is not None:
            model = quantize(model, ranges)
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        opts.log_severity_level = 3
        self.session = ort.InferenceSession(model, opts, providers=["CPUExecutionProvider"])
        self._check(scorer, _probe_input(height, width), ranges is not None)

    def _check(self, scorer: Scorer, x: torch.Tensor, int8: bool) -> None:
        """The export must give PyTorch's labels and confidence on a fixed input (float32: to EXPORT_TOLERANCE
        and 99.9 % of labels; int8: INT8_AGREEMENT of labels)."""
        with torch.no_grad():
            want_labels, want_conf = read_out(scorer(x).numpy())
        labels, conf = self(x.numpy())
        diff = float(np.abs(conf - want_conf).max())
        agree = float((labels == want_labels).mean())
        if agree < (INT8_AGREEMENT if int8 else 0.999) or (diff > EXPORT_TOLERANCE and not int8):
            raise RuntimeError(f"{'int8' if int8 else 'ONNX'} export differs from PyTorch: confidence {diff:.2e}, "
                               f"labels agree {agree:.4%}")

    def __call__(self, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return read_out(self.session.run(None, {"image": np.ascontiguousarray(images, np.float32)})[0])


def _probe_input(height: int, width: int) -> torch.Tensor:
    """A fixed (1, 6, H, W) range image of plausible values (ranges 0.5..30 m, a few empty pixels)."""
    g = torch.Generator().manual_seed(0)
    rng = 0.5 + 29.5 * torch.rand(height, width, generator=g)
    az = torch.linspace(0, 2 * np.pi, width + 1)[:-1].expand(height, width)
    el = torch.linspace(-0.45, 0.27, height).unsqueeze(1).expand(height, width)
    valid = (torch.rand(height, width, generator=g) > 0.05).float()
    xyz = torch.stack([rng * el.cos() * az.cos(), rng * el.cos() * az.sin(), rng * el.sin()])
    inten = 255 * torch.rand(height, width, generator=g)
    return (torch.cat([rng[None], xyz, inten[None], valid[None]]) * valid)[None].contiguous()


class Segmenter:
    """Per-point semantic labels of LiDAR scans with the range-image network, for any grid (projection.py).

    Use :meth:`from_config`; :meth:`predict` one scan, :meth:`predict_batch` several (same result as one
    at a time). CPU inference uses ``threads`` threads (1 by default) and ``backend`` onnxruntime (default;
    eager PyTorch when onnxruntime is missing or its export fails the check) or eager. ONNX Runtime runs one
    export per image shape, made (and checked) the first time a shape is seen. ``self.backend`` says which
    one runs. ``passes`` (1-3) averages the network over views of each image (Scorer): more accurate,
    ``passes`` times the network's time. ``max_beams`` (> 0): a scan of more rows has only every k-th row
    segmented (projection.beam_stride), the rows between take the labels of their nearest neighbours in the
    rows segmented (projection.nearest_strided): about 1/k of the network's time. ``knn`` (> 0): every point
    then takes the majority label of its ``knn`` nearest points within ``knn_distance`` m (knn.knn_vote).
    ``floor_band`` (> 0, m): then floor-labelled points standing more than that above the floor take their
    non-floor neighbours' label (floor.lift_off_floor). ``object_gap`` (> 0, m): then desk and chair points
    joined within that gap take their object's majority label (objects.unify_objects). ``floor_snap`` (> 0, m):
    last, in a non-repetitive scan (a grid with per-point azimuths), other, wall, desk and chair points within that
    of the floor plane become floor (floor.snap_to_floor). The constructor's defaults leave the vote, the check,
    the objects and the snap off; :meth:`from_config` takes the config's (all on).
    ``pattern_stats`` (norm_stats.py): BatchNorm statistics the network uses for non-repetitive scans (grids
    with per-point azimuths); every other scan runs with the weights' own. ``self.has_pattern_stats`` says
    whether there are some.
    """

    def __init__(self, model: RangeNet, card: dict, device: str = "cpu", threads: int = 1,
                 backend: str = "onnxruntime", passes: int = 1, max_beams: int = 0, knn: int = 0,
                 knn_distance: float = 0.5, int8_ranges: dict | None = None, floor_band: float = 0.0,
                 object_gap: float = 0.0, pattern_stats: dict | None = None, floor_snap: float = 0.0):
        self.device = torch_device(device)
        if backend not in BACKENDS:
            raise SegmentationError(f"unknown segmentation backend {backend!r}; use {' or '.join(BACKENDS)}")
        if max_beams != int(max_beams) or max_beams < 0:
            raise SegmentationError(f"segmentation.max_beams must be a whole number >= 0, got {max_beams}")
        if knn != int(knn) or knn < 0:
            raise SegmentationError(f"segmentation.knn must be a whole number >= 0, got {knn}")
        if not floor_band >= 0:
            raise SegmentationError(f"segmentation.floor_band must be >= 0 m, got {floor_band}")
        if not object_gap >= 0:
            raise SegmentationError(f"segmentation.object_gap must be >= 0 m, got {object_gap}")
        if not floor_snap >= 0:
            raise SegmentationError(f"segmentation.floor_snap must be >= 0 m, got {floor_snap}")
        self.threads = threads
        self.floor_band, self.object_gap, self.floor_snap = float(floor_band), float(object_gap), float(floor_snap)
        self.max_beams = int(max_beams)
        self.knn, self.knn_distance = int(knn), float(knn_distance)
        self.card = card
        self.has_pattern_stats = pattern_stats is not None
        patterned = with_stats(model, pattern_stats) if pattern_stats is not None else None
        self.model = fold_batchnorm(model).to(self.device)  # same outputs, no BatchNorm passes
        self.scorer = Scorer(self.model, passes).to(self.device).eval()
        self._scorers = {False: self.scorer, True: self.scorer if patterned is None else
                         Scorer(fold_batchnorm(patterned).to(self.device), passes).to(self.device).eval()}
        if self.device.type == "cpu":
            torch.set_num_threads(threads)  # process-wide: torch has one CPU thread pool
        self.backend = "onnxruntime" if backend == "onnxruntime" and self.device.type == "cpu" else "eager"
        self._int8_ranges = int8_ranges if self.backend == "onnxruntime" and passes == 1 else None
        self.precision = "float32" if self._int8_ranges is None else "int8"
        self._onnx: dict[tuple[int, int, bool], _OnnxRunner | None] = {}  # None: that shape runs eager
        self._pattern_float32 = False  # the int8 check failed for non-repetitive scans: they run float32
        if self.backend == "onnxruntime":
            self._runner(*PROBE_SHAPE, probe=True)  # fail over to eager now, not on the first scan

    @classmethod
    def from_config(cls, cfg: SegmentationConfig) -> "Segmenter":
        """The network of ``cfg.weights`` ("" = the shipped weights) on ``cfg.device`` with ``cfg.threads``."""
        path = Path(cfg.weights) if cfg.weights else SHIPPED
        card, state = load_weights(path)
        digest = state_digest(state)
        stats, why = load_stats(path, digest, state)
        if stats is None:  # a file there but refused (made for other weights, damaged): a warning; no file: info
            (log.warning if beside(path, NORM_NAME).is_file() else log.info)(
                "segmentation: non-repetitive scans use the shared BatchNorm statistics: %s", why)
        return cls(build_model(card, state, str(path)), card, cfg.device, cfg.threads, cfg.backend, cfg.passes,
                   cfg.max_beams, cfg.knn, cfg.knn_distance, _int8_ranges(cfg, path, digest), cfg.floor_band,
                   cfg.object_gap, stats, cfg.floor_snap)

    def predict(self, points: np.ndarray, grid=None, intensity: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
        """(labels (N,) uint8 class ids, confidence (N,) float32 softmax probability of that label) of one
        scan: points (N, 3) float32 in the sensor frame, its grid.ScanGrid (or the cloud's (N,) beam ids, or
        None) and optional intensity (N,)."""
        return self.predict_batch([(points, grid, intensity)])[0]

    def predict_batch(self, scans: Sequence[Scan]) -> list[tuple[np.ndarray, np.ndarray]]:
        """:meth:`predict` for each (points, grid, intensity) of ``scans``; scans whose images have the same
        shape run as one batch."""
        scans = [(*checked(points, grid, intensity), intensity) for points, grid, intensity in scans]
        prepared = [self._project(points, grid, intensity) for points, grid, intensity in scans]
        out: list = [None] * len(prepared)
        shapes: dict[tuple, list[int]] = {}
        for i, (image, _, _) in enumerate(prepared):
            shapes.setdefault((*image.shape[1:], scans[i][1].azimuth is not None), []).append(i)
        for (*_, non_repetitive), members in shapes.items():
            images = np.concatenate([prepared[i][0] for i in members])
            labels, conf = self._run(images, non_repetitive)
            start = 0
            for i in members:
                _, proj, source = prepared[i]
                stop = start + proj.images
                out[i] = _spread(proj.unproject(labels[start:stop]), proj.unproject(conf[start:stop]), source)
                if self.knn:
                    out[i] = knn_vote(*scans[i][:2], *out[i], self.knn, self.knn_distance)
                if self.floor_band:
                    out[i] = lift_off_floor(*scans[i][:2], *out[i], self.floor_band)
                if self.object_gap:
                    out[i] = unify_objects(*scans[i][:2], *out[i], self.object_gap)
                if self.floor_snap and non_repetitive:
                    out[i] = snap_to_floor(scans[i][0], *out[i], self.floor_snap)
                start = stop
        return out

    def _project(self, points: np.ndarray, grid, intensity: np.ndarray | None
                 ) -> tuple[np.ndarray, Projection, np.ndarray | None]:
        """(images, projection, source) of one checked scan (projection.checked): with max_beams, only the rows the
        network sees are projected and ``source`` (N,) says whose label each point takes
        (projection.nearest_strided), else None."""
        stride = beam_stride(grid, self.max_beams)
        if stride == 1:
            return *project(points, grid, intensity), None
        keep, sub = strided(grid, stride)
        images, proj = project(points[keep], sub, None if intensity is None else np.asarray(intensity)[keep])
        return images, proj, nearest_strided(points, grid, keep, stride)

    def _run(self, images: np.ndarray, non_repetitive: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(B, H, W) uint8 labels and float32 confidence of (B, 6, H, W) range images (of a non-repetitive
        scan: with its BatchNorm statistics when there are some)."""
        if self.backend == "onnxruntime":
            runner = self._runner(images.shape[2], images.shape[3], non_repetitive)
            if runner is not None:
                return runner(images)
        return self._run_eager(images, non_repetitive)

    def _runner(self, height: int, width: int, non_repetitive: bool = False, probe: bool = False
                ) -> "_OnnxRunner | None":
        """The ONNX Runtime export for images of this shape (and pattern), made and checked once: int8 when the
        Segmenter runs int8, else float32; None: this shape runs eager. A failed export warns and falls back
        for that shape alone (int8 -> float32 -> eager), except at the ``probe`` (construction), where it
        switches the whole Segmenter (``precision``, ``backend``); a failed int8 export of a non-repetitive
        scan (its own statistics, ranges calibrated without them) makes all such scans float32."""
        key = (int(height), int(width), bool(non_repetitive) and self.has_pattern_stats)
        if key in self._onnx:
            return self._onnx[key]
        scorer, shape = self._scorers[key[2]], f"{key[0]}x{key[1]} images"
        if self.precision == "int8" and not (key[2] and self._pattern_float32):
            try:
                self._onnx[key] = _OnnxRunner(scorer, *key[:2], self.threads, self._int8_ranges)
                return self._onnx[key]
            except Exception as e:  # an ONNX Runtime without calibration caches, a failed check, ...
                why = one_line_reason(e)
                if probe:
                    log.warning("segmentation: int8 network unavailable (%s); using float32", why)
                    self.precision = "float32"
                elif key[2]:
                    log.warning("segmentation: int8 network unavailable for non-repetitive scans (%s); float32 "
                                "for them", why)
                    self._pattern_float32 = True
                else:
                    log.warning("segmentation: int8 network unavailable for %s (%s); float32 for them", shape, why)
        try:
            self._onnx[key] = _OnnxRunner(scorer, *key[:2], self.threads)
        except Exception as e:  # no onnxruntime, an export the runtime rejects, or a failed check
            why = one_line_reason(e)
            if probe:
                log.warning("segmentation: onnxruntime backend unavailable (%s); using eager PyTorch", why)
                self.backend, self.precision = "eager", "float32"
                return None
            log.warning("segmentation: onnxruntime export failed for %s (%s); eager PyTorch for them", shape, why)
            self._onnx[key] = None
        return self._onnx[key]

    @torch.inference_mode()
    def _run_eager(self, images: np.ndarray, non_repetitive: bool = False) -> tuple[np.ndarray, np.ndarray]:
        x = torch.from_numpy(np.ascontiguousarray(images, np.float32)).to(self.device, non_blocking=True)
        return read_out(self._scorers[bool(non_repetitive)](x).float().cpu().numpy())


def _int8_ranges(cfg: SegmentationConfig, weights: Path, digest: str) -> dict | None:
    """The activation ranges to run the network int8 with (segmentation.precision: int8, or auto on an x86 CPU
    with VNNI or AVX2), else None; why an int8 request falls back to float32 is logged (a warning when int8 was
    asked for by name)."""
    if cfg.precision == "float32" or (cfg.precision == "auto" and not cpu_runs_int8()):
        return None
    if cfg.backend != "onnxruntime" or cfg.device != "cpu":
        ranges, why = None, "int8 runs on the onnxruntime CPU backend only"
    elif cfg.passes != 1:
        ranges, why = None, "int8 runs one pass only (segmentation.passes 1)"
    else:
        ranges, why = load_ranges(weights, digest)
    if ranges is None:
        (log.warning if cfg.precision == "int8" else log.info)("segmentation: float32 network: %s", why)
    return ranges


def segment_frame(frame, cfg: SegmentationConfig, segmenter: Segmenter | None = None, grid=None
                  ) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(labels (N,) uint8, confidence (N,) float32 or None) of a window.Frame (on ``grid``, its grid.ScanGrid
    when already built) as ``cfg.mode`` says.

    network: ``segmenter`` predicts (points below ``cfg.min_confidence`` become OTHER); labels: the frame's
    own label field (e.g. simulator ground truth; confidence None); none: (None, None), every point static.
    """
    if cfg.mode == "none":
        return None, None
    if cfg.mode == "labels":
        if frame.labels is None:
            raise SegmentationError("segmentation mode 'labels' but the cloud has no label field")
        return np.asarray(frame.labels, np.uint8), None
    if cfg.mode != "network":
        raise SegmentationError(f"unknown segmentation mode {cfg.mode!r}; use network, labels or none")
    if segmenter is None:
        raise SegmentationError("segmentation mode 'network' needs a Segmenter (Segmenter.from_config)")
    labels, conf = segmenter.predict(frame.points, grid if grid is not None else frame.ring, frame.intensity)
    if cfg.min_confidence > 0:
        labels = np.where(conf < cfg.min_confidence, np.uint8(C.OTHER), labels)
    return labels, conf
