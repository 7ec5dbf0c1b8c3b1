"""BatchNorm statistics of the network for non-repetitive scans (Livox-like patterns), kept beside the weights.

The network's BatchNorm layers normalise with running means and variances learned over all sensors. A
non-repetitive pattern's image (about one point per pixel, a sparse, speckled image reaching 52 deg up) has
activations far from a spinning sensor's, so those shared statistics misread it. ``topometric norm-stats``
re-estimates the statistics on such scans alone (the weights unchanged) and writes them beside the weights
(``rangenet.norm.json``, tied to the weights' tensor digest as the int8 ranges are). The Segmenter then runs a
non-repetitive scan (its grid has per-point azimuths) through the network with these statistics and every
other scan with the weights' own: spinning sensors are untouched.
"""
from __future__ import annotations

from pathlib import Path
from typing import Iterable

import numpy as np
import torch
from torch import nn

from .model import RangeNet

NORM_NAME = "rangenet.norm.json"
FORMAT_VERSION = 1
PATTERN = "non_repetitive"  # the scans these statistics are for: grids with per-point azimuths
STAT_KEYS = ("running_mean", "running_var")


def estimate(model: RangeNet, images: Iterable[np.ndarray]) -> tuple[dict[str, list], int]:
    """({BatchNorm buffer name: values}, images seen): the running mean and variance of every BatchNorm layer of
    ``model`` over scans given as their (k, 6, rows, cols) range images (projection.project's, the network's raw
    input): each scan's batch statistics, averaged with the same weight per scan (not a moving average).
    ``model`` is left as it was."""
    net = _copy(model)
    layers = [m for m in net.modules() if isinstance(m, nn.BatchNorm2d)]
    if not layers:
        raise ValueError("the network has no BatchNorm layer (folded?): estimate on the weights as loaded")
    for m in layers:
        m.reset_running_stats()
        m.momentum = None  # cumulative average
    net.train().set_circular(True)
    n = 0
    with torch.no_grad():
        for image in images:
            net(torch.from_numpy(np.ascontiguousarray(image, np.float32)))
            n += len(image)
    if n == 0:
        raise ValueError("no non-repetitive scan to estimate the statistics on (a Livox-like pattern: its grid has "
                         "per-point azimuths)")
    stats = {k: v.tolist() for k, v in net.state_dict().items() if k.rsplit(".", 1)[-1] in STAT_KEYS}
    return stats, n


def with_stats(model: RangeNet, stats: dict[str, list]) -> RangeNet:
    """A copy of ``model`` (with its BatchNorm layers, not folded) whose BatchNorm running statistics are ``stats``."""
    net = _copy(model)
    state = net.state_dict()
    for k, v in stats.items():
        state[k] = torch.tensor(v, dtype=state[k].dtype).reshape(state[k].shape)
    net.load_state_dict(state)
    return net.eval()


def write_stats(stats: dict[str, list], weights: str | Path, state_sha256: str, command: str, images: int) -> Path:
    """Save ``stats`` beside ``weights`` (NORM_NAME), tied to their tensors' digest; returns the path."""
    from .checkpoint import write_beside

    doc = {"format_version": FORMAT_VERSION, "pattern": PATTERN, "state_sha256": state_sha256, "images": images,
           "command": command, "statistics": stats}
    return write_beside(weights, NORM_NAME, doc)


def load_stats(weights: str | Path, state_sha256: str, keys: Iterable[str]) -> tuple[dict | None, str]:
    """(statistics, "") for the weights whose tensors hash to ``state_sha256`` and whose BatchNorm buffers are
    among ``keys`` (a state dict's names), or (None, why not)."""
    from .checkpoint import beside, read_beside

    doc, why = read_beside(weights, NORM_NAME, FORMAT_VERSION, "statistics", state_sha256, "non-repetitive statistics",
                           "topometric norm-stats")
    if doc is None:
        return None, why
    if set(doc["statistics"]) != {k for k in keys if k.rsplit(".", 1)[-1] in STAT_KEYS}:
        return None, f"{beside(weights, NORM_NAME)}: its layers do not match the network's BatchNorm layers"
    return doc["statistics"], ""


def make_stats(bags, weights: str | Path, every: int = 1, command: str = "") -> tuple[Path, int, int]:
    """Estimate the non-repetitive statistics of ``weights`` on every ``every``-th scan of ``bags`` (their
    non-repetitive scans; others are skipped) and save them beside the weights: (path, images, bags used)."""
    from tqdm import tqdm

    from .checkpoint import build_model, load_weights, state_digest
    from .data import read_scans
    from .projection import checked, project

    card, state = load_weights(weights)
    model = build_model(card, state, str(weights))
    used: set[str] = set()

    def images():
        for bag in tqdm(bags, desc="scans", unit="bag"):
            for s in read_scans(bag, every=every):
                if s.grid.azimuth is not None:
                    used.add(str(bag))
                    yield project(*checked(s.points, s.grid, s.intensity), s.intensity)[0]

    stats, n = estimate(model, images())
    return write_stats(stats, weights, state_digest(state), command, n), n, len(used)


def _copy(model: RangeNet) -> RangeNet:
    net = RangeNet(model.spec)
    net.load_state_dict(model.state_dict())
    return net
