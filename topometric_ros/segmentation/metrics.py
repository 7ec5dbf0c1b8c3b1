"""Confusion matrices and IoU: the segmentation scores (training logs, eval-seg, tests)."""
from __future__ import annotations

from typing import Iterable

import numpy as np

from .. import classes as C


def confusion(truth: np.ndarray, pred: np.ndarray, num_classes: int = C.NUM_CLASSES) -> np.ndarray:
    """(K, K) int64 counts, rows = ground truth, columns = prediction; labels >= K are ignored."""
    truth = np.asarray(truth).ravel().astype(np.int64)
    pred = np.asarray(pred).ravel().astype(np.int64)
    keep = (truth < num_classes) & (pred < num_classes)
    idx = truth[keep] * num_classes + pred[keep]
    return np.bincount(idx, minlength=num_classes * num_classes).reshape(num_classes, num_classes)


def iou_per_class(conf: np.ndarray) -> np.ndarray:
    """(K,) IoU = TP / (TP + FP + FN) per class; NaN for a class absent from truth and prediction."""
    tp = np.diag(conf).astype(np.float64)
    denom = conf.sum(0) + conf.sum(1) - tp
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(denom > 0, tp / denom, np.nan)


def miou(conf: np.ndarray, over: Iterable[int] = C.PAPER_CLASSES) -> float:
    """Mean IoU over the classes ``over`` (default: the paper's five) that occur; NaN if none does."""
    iou = iou_per_class(conf)[list(over)]
    return float(np.nanmean(iou)) if np.isfinite(iou).any() else float("nan")


def accuracy(conf: np.ndarray) -> float:
    """Overall point accuracy."""
    total = conf.sum()
    return float(np.trace(conf) / total) if total else float("nan")
