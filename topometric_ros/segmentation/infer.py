"""Run the shipped (or a given) range-image network on scans: per-point labels and confidence.

Weights are a torch file {'model_card': dict, 'state_dict': tensors} read with
``torch.load(weights_only=True)`` (no arbitrary code runs), checked key by key and shape by shape
against the net the card describes. Any problem raises SegmentationError with the reason.

CPU backends: ``onnxruntime`` (default) exports the checked network (BatchNorm folded, softmax and arg-max
included) to ONNX in memory at load time and runs it with ONNX Runtime; the export is verified against
PyTorch on a fixed input and any failure (or a missing onnxruntime) falls back to ``eager`` PyTorch with a
warning. The shipped weights stay one ``.pt`` file; no ONNX file is written or read.
"""
from __future__ import annotations

import hashlib
import io
import json
import logging
import warnings
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from torch import nn

from .. import classes as C
from ..config import SegmentationConfig
from .model import ModelSpec, RangeNet, fold_batchnorm
from .projection import HEIGHT, WIDTH, Projection, project
from .train import CARD_NAME, FORMAT_VERSION, WEIGHTS_NAME, state_digest

SHIPPED = Path(__file__).resolve().parent / "weights" / WEIGHTS_NAME
BACKENDS = ("onnxruntime", "eager")
#: Largest |logit| difference between the ONNX Runtime export and PyTorch accepted at load time.
EXPORT_TOLERANCE = 1e-3

log = logging.getLogger(__name__)

Scan = tuple  # (points (N, 3) float32, ring (N,) | None, intensity (N,) | None)


class SegmentationError(ValueError):
    """Weights that are missing, unreadable, tampered with or do not fit the network; bad device."""


def load_weights(path: str | Path) -> tuple[dict, dict]:
    """(model card, state dict) of a weights file, loaded without executing code."""
    path = Path(path)
    if not path.is_file():
        raise SegmentationError(f"segmentation weights not found: {path}")
    try:
        doc = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # UnpicklingError, RuntimeError (zip), EOFError, ... for garbage or unsafe pickles
        raise SegmentationError(f"cannot load segmentation weights {path}: not a safe torch weights file "
                                f"({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("model_card"), dict) or not isinstance(doc.get("state_dict"), dict):
        raise SegmentationError(f"{path}: expected {{'model_card': dict, 'state_dict': dict}}, got {type(doc).__name__}"
                                + (f" with keys {sorted(map(str, doc))}" if isinstance(doc, dict) else ""))
    _check_checksum(path)
    state = doc["state_dict"]
    bad = [str(k) for k, v in state.items() if not isinstance(k, str) or not isinstance(v, torch.Tensor)]
    if bad:
        raise SegmentationError(f"{path}: state dict entries that are not named tensors: {bad[:5]}")
    _check_state_digest(state, doc.get("state_sha256"), str(path))
    return doc["model_card"], state


def _check_state_digest(state: dict, digest: object, source: str) -> None:
    """The tensors must hash to the digest saved with them (catches modified or corrupted weights)."""
    if not isinstance(digest, str):
        raise SegmentationError(f"{source}: no state_sha256 digest; not a weights file written by topometric train")
    if state_digest(state) != digest:
        raise SegmentationError(f"{source}: tensor checksum mismatch; the weights were modified or corrupted")


def _check_checksum(path: Path) -> None:
    """When a model_card.json next to the weights names their sha256, the file must match it."""
    card_path = path.parent / CARD_NAME
    if not card_path.is_file():
        return
    try:
        want = json.loads(card_path.read_text()).get("weights", {})
    except (json.JSONDecodeError, AttributeError):
        raise SegmentationError(f"{card_path}: not a valid model card (JSON)") from None
    if want.get("file") == path.name and want.get("sha256"):
        got = hashlib.sha256(path.read_bytes()).hexdigest()
        if got != want["sha256"]:
            raise SegmentationError(f"{path}: sha256 {got[:12]}… does not match {card_path} ({want['sha256'][:12]}…); "
                                    "the weights were modified")


def build_model(card: dict, state: dict, source: str = "weights") -> RangeNet:
    """The network the card describes with ``state`` loaded, after checking every key and shape."""
    if card.get("format_version") != FORMAT_VERSION:
        raise SegmentationError(f"{source}: model card format {card.get('format_version')!r}, expected {FORMAT_VERSION}")
    if list(card.get("classes", [])) != list(C.NAMES):
        raise SegmentationError(f"{source}: classes {card.get('classes')} differ from {list(C.NAMES)}")
    try:
        spec = ModelSpec.from_dict(card["model"])
        model = RangeNet(spec)
    except Exception as e:  # wrong types or sizes in the card
        raise SegmentationError(f"{source}: model card does not describe a valid network: {e}") from None
    expected = model.state_dict()
    missing = sorted(set(expected) - set(state))
    extra = sorted(set(state) - set(expected))
    if missing or extra:
        raise SegmentationError(f"{source}: state dict does not fit the network: missing {missing[:5]}, "
                                f"unexpected {extra[:5]}")
    for k, v in expected.items():
        got = state[k]
        if not isinstance(got, torch.Tensor) or got.shape != v.shape or got.dtype != v.dtype:
            desc = f"{tuple(got.shape)} {got.dtype}" if isinstance(got, torch.Tensor) else type(got).__name__
            raise SegmentationError(f"{source}: tensor {k!r} is {desc}, the network needs {tuple(v.shape)} {v.dtype}")
        if v.is_floating_point() and not torch.isfinite(got).all():
            raise SegmentationError(f"{source}: tensor {k!r} has non-finite values")
    model.load_state_dict(state)
    return model.eval().set_circular(True)


class Labeller(nn.Module):
    """The network plus its read-out: (B, 6, H, W) range images -> (labels (B, H, W) uint8, confidence
    (B, H, W) float32 softmax probability of the label). One module, so every backend computes the same."""

    def __init__(self, net: RangeNet):
        super().__init__()
        self.net = net

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        y = self.net.folded_logits(x)  # (b, k, f, h, w / f): reduce over classes before unfolding azimuth
        top, labels = y.max(1)
        conf = 1.0 / torch.exp(y - top.unsqueeze(1)).sum(1)  # = max softmax; cheaper than softmax in ONNX Runtime
        b, f, h, wf = labels.shape
        unfold = lambda t: t.permute(0, 2, 3, 1).reshape(b, h, wf * f)  # noqa: E731
        return unfold(labels.to(torch.uint8)), unfold(conf)


class _OnnxRunner:
    """A Labeller exported to ONNX in memory and run by ONNX Runtime on the CPU with ``threads`` threads."""

    def __init__(self, labeller: Labeller, height: int, width: int, threads: int):
        import onnxruntime as ort  # ImportError -> the caller falls back to eager

        x = _probe_input(height, width)
        buf = io.BytesIO()
        with warnings.catch_warnings():  # the TorchScript-based exporter warns that it is deprecated
            warnings.simplefilter("ignore")
            torch.onnx.export(labeller, (x,), buf, dynamo=False, input_names=["image"],
                              output_names=["labels", "confidence"], opset_version=17,
                              dynamic_axes={"image": {0: "batch"}, "labels": {0: "batch"}, "confidence": {0: "batch"}})
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        opts.log_severity_level = 3
        self.session = ort.InferenceSession(buf.getvalue(), opts, providers=["CPUExecutionProvider"])
        self._check(labeller, x)

    def _check(self, labeller: Labeller, x: torch.Tensor) -> None:
        """The export must give PyTorch's logits on a fixed input (to EXPORT_TOLERANCE)."""
        with torch.no_grad():
            want_labels, want_conf = labeller(x)
        labels, conf = self(x.numpy())
        diff = float(np.abs(conf - want_conf.numpy()).max())
        agree = float((labels == want_labels.numpy()).mean())
        if diff > EXPORT_TOLERANCE or agree < 0.999:
            raise RuntimeError(f"ONNX export differs from PyTorch: confidence {diff:.2e}, labels agree {agree:.4%}")

    def __call__(self, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        labels, conf = self.session.run(None, {"image": np.ascontiguousarray(images, np.float32)})
        return labels, conf


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
    """Per-point semantic labels of LiDAR scans with the range-image network.

    Use :meth:`from_config`; :meth:`predict` one scan, :meth:`predict_batch` several (same result as one
    at a time). CPU inference uses ``threads`` threads (1 by default) and ``backend`` onnxruntime (default;
    eager PyTorch when onnxruntime is missing or its export fails the check) or eager. ``self.backend``
    says which one runs.
    """

    def __init__(self, model: RangeNet, card: dict, device: str = "cpu", threads: int = 1,
                 backend: str = "onnxruntime"):
        if device not in ("cpu", "cuda") and not device.startswith("cuda:"):
            raise SegmentationError(f"unknown device {device!r}; use cpu or cuda")
        if device.startswith("cuda") and not torch.cuda.is_available():
            raise SegmentationError("device cuda requested but torch sees no CUDA GPU")
        if backend not in BACKENDS:
            raise SegmentationError(f"unknown segmentation backend {backend!r}; use {' or '.join(BACKENDS)}")
        self.device = torch.device(device)
        self.threads = threads
        self.card = card
        self.height = int(card.get("input", {}).get("height", HEIGHT))
        self.width = int(card.get("input", {}).get("width", WIDTH))
        self.model = fold_batchnorm(model).to(self.device)  # same outputs, no BatchNorm passes
        self.labeller = Labeller(self.model).eval()
        if self.device.type == "cpu":
            torch.set_num_threads(threads)  # process-wide: torch has one CPU thread pool
        self.backend, self._onnx = "eager", None
        if backend == "onnxruntime" and self.device.type == "cpu":
            try:
                self._onnx = _OnnxRunner(self.labeller, self.height, self.width, threads)
                self.backend = "onnxruntime"
            except Exception as e:  # no onnxruntime, an export the runtime rejects, or a failed check
                log.warning("segmentation: onnxruntime backend unavailable (%s: %s); using eager PyTorch",
                            type(e).__name__, str(e).splitlines()[0] if str(e) else "")

    @classmethod
    def from_config(cls, cfg: SegmentationConfig) -> "Segmenter":
        """The network of ``cfg.weights`` ("" = the shipped weights) on ``cfg.device`` with ``cfg.threads``."""
        path = Path(cfg.weights) if cfg.weights else SHIPPED
        card, state = load_weights(path)
        return cls(build_model(card, state, str(path)), card, cfg.device, cfg.threads, cfg.backend)

    def predict(self, points: np.ndarray, ring: np.ndarray | None = None,
                intensity: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(labels (N,) uint8 class ids, confidence (N,) float32 softmax probability of that label) of one
        scan: points (N, 3) float32 in the sensor frame, optional ring (N,) and intensity (N,)."""
        return self.predict_batch([(points, ring, intensity)])[0]

    def predict_batch(self, scans: Sequence[Scan]) -> list[tuple[np.ndarray, np.ndarray]]:
        """:meth:`predict` for each (points, ring, intensity) of ``scans``, run as one batch."""
        if not scans:
            return []
        images, projections = [], []
        for points, ring, intensity in scans:
            image, proj = project(points, ring, intensity, self.height, self.width)
            images.append(image)
            projections.append(proj)
        labels, conf = self._run(images[0][None] if len(images) == 1 else np.stack(images))  # no copy for one scan
        return [(proj.unproject(lab), proj.unproject(cf)) for proj, lab, cf in zip(projections, labels, conf)]

    def predict_image(self, image: np.ndarray, proj: Projection) -> tuple[np.ndarray, np.ndarray]:
        """Per-point (labels, confidence) of an already projected scan."""
        labels, conf = self._run(image[None])
        return proj.unproject(labels[0]), proj.unproject(conf[0])

    def _run(self, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(B, H, W) uint8 labels and float32 confidence of (B, 6, H, W) range images."""
        if self._onnx is not None:
            return self._onnx(images)
        return self._run_eager(images)

    @torch.inference_mode()
    def _run_eager(self, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = torch.from_numpy(images).to(self.device, non_blocking=True)
        labels, conf = self.labeller(x)
        return labels.cpu().numpy(), conf.float().cpu().numpy()


def segment_frame(frame, cfg: SegmentationConfig, segmenter: Segmenter | None = None
                  ) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(labels (N,) uint8, confidence (N,) float32 or None) of a window.Frame as ``cfg.mode`` says.

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
    labels, conf = segmenter.predict(frame.points, frame.ring, frame.intensity)
    if cfg.min_confidence > 0:
        labels = np.where(conf < cfg.min_confidence, np.uint8(C.OTHER), labels)
    return labels, conf
