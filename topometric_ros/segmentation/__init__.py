"""Semantic segmentation of LiDAR scans with a small range-image network (plain PyTorch).

projection.py (points <-> range image), model.py (the net), infer.py (Segmenter: shipped weights ->
per-point labels and confidence), checkpoint.py (the weights file: load, check, save), train.py / data.py (training from labelled bags), metrics.py (IoU),
evaluate.py (``topometric eval-seg``). Names resolve lazily so importing the package does not load torch.
"""
from __future__ import annotations

import importlib

_EXPORTS = {"Segmenter": "infer", "SegmentationError": "checkpoint", "SHIPPED": "checkpoint", "segment_frame": "infer"}


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{module}"), name)


__all__ = list(_EXPORTS)
