"""Semantic segmentation of LiDAR scans with a small range-image network (plain PyTorch).

projection.py (points <-> range image), model.py (the net), infer.py (Segmenter: shipped weights ->
per-point labels and confidence), checkpoint.py (the weights file: load, check, save), train.py / data.py (training from labelled bags), metrics.py (IoU),
evaluate.py (``topometric eval-seg``). Names resolve lazily so importing the package does not load torch.
"""
from __future__ import annotations

from .._lazy import lazy_exports

_EXPORTS = {"Segmenter": "infer", "SegmentationError": "checkpoint", "SHIPPED": "checkpoint", "segment_frame": "infer"}


__getattr__, __all__ = lazy_exports(__name__, _EXPORTS)
