"""The one place the order of work lives: scan -> segment -> planes (once per scan); window -> metrics.

Frames of data: a scan's points and planes stay in its SENSOR frame; a window scores them in the window
frame, the sensor frame of its first scan (T_rel,i = T_1⁻¹ T_i), as map-metrics does.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from .config import Config
from .planes import Plane
from .window import Frame


@dataclass
class ProcessedScan:
    """The cached per-scan result: computed once when the scan arrives, reused by every window.

    points: (N, 3) float32 sensor frame (kept for the MME/MPV/MOM baselines; may be None when they are off).
    labels: (N,) uint8 labels used (predicted or given). pose: (4, 4) sensor-to-map. timings: ms per step.
    """

    stamp: float
    pose: np.ndarray
    planes: list[Plane]
    points: np.ndarray | None = None
    labels: np.ndarray | None = None
    index: int = -1
    timings: dict[str, float] = field(default_factory=dict)


@dataclass
class WindowResult:
    """Scores of one window. pne (nats), cpv (m²); mme, mpv, mom when baselines are on (else None).

    level / message are filled by health.py (OK, WARN, ERROR, STALE)."""

    stamps: list[float]
    pne: float
    cpv: float
    n_planes: int
    n_groups: int
    mme: float | None = None
    mpv: float | None = None
    mom: float | None = None
    timings: dict[str, float] = field(default_factory=dict)
    level: str = "OK"
    message: str = ""


def process_scan(frame: Frame, config: Config, segmenter=None, index: int = -1) -> ProcessedScan:
    """Segment one scan (network, given labels, or none per config.segmentation.mode) and detect its planes."""
    raise NotImplementedError


def score_window(scans: Sequence[ProcessedScan], config: Config) -> WindowResult:
    """PNE and CPV (and baselines when enabled) of already processed scans, in the first scan's frame."""
    raise NotImplementedError


def evaluate_window(frames: Sequence[Frame], config: Config | None = None, cache: dict | None = None,
                    segmenter=None) -> WindowResult:
    """The public one-call API: process each frame (once, via ``cache`` keyed by stamp) and score the window."""
    raise NotImplementedError
