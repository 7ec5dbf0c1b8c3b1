"""Labels cleaned by their neighbours in space: the k-nearest-neighbour vote of RangeNet++ (Milioto et al.,
IROS 2019, Algorithm 1) on the scan's grid (grid.ScanGrid).

The network labels pixels of a range image, and at the edge of an object a pixel can take the label of the
surface beside it in the image although the point lies metres behind it (a wall point seen past a chair's
edge labelled chair). Here every point takes the majority label of the ``k`` points nearest to it in 3D among
the cells of a ``window`` (rows, columns) of the grid around its own (azimuth wraps around), counting only
those within ``distance`` metres; its own label wins ties. Points are in the SENSOR frame, metres. One pass
over the points in a compiled numba kernel (single thread, GIL released).
"""
from __future__ import annotations

import numba
import numpy as np

from .. import classes as C
from ..grid import ScanGrid, cell_points

#: Rows x columns of grid cells around a point whose points may vote (chosen with k = 3 and 0.5 m on the
#: validation layout: docs/results.md).
WINDOW = (3, 5)
assert C.NUM_CLASSES <= 8, "_classes_across keeps a window's classes as the bits of a uint8"


def knn_vote(points: np.ndarray, grid: ScanGrid, labels: np.ndarray, confidence: np.ndarray, k: int,
             distance: float, window: tuple[int, int] = WINDOW) -> tuple[np.ndarray, np.ndarray]:
    """(labels (N,) uint8, confidence (N,) float32) after the vote: points (N, 3) sensor frame, their grid,
    the network's labels and confidence; ``distance`` m; ``window`` (rows, columns) of grid cells. A point
    whose label changes takes the mean confidence of the neighbours that voted for its new label. k <= 0: the
    input unchanged. A cell of several points (a non-repetitive grid's) offers the last of them to its
    neighbours."""
    if k <= 0 or len(points) == 0:
        return labels, confidence
    labels = np.asarray(labels, np.uint8)
    confidence = np.asarray(confidence, np.float32)
    out_labels, out_conf = labels.copy(), confidence.copy()
    _vote(np.ascontiguousarray(points, np.float32), np.asarray(grid.row), np.asarray(grid.col), grid.height,
          grid.width, labels, confidence, int(k), int(window[0]), int(window[1]), float(distance) ** 2,
          C.NUM_CLASSES, out_labels, out_conf)
    return out_labels, out_conf


@numba.njit(cache=True, nogil=True)
def _vote(points, row, col, height, width, labels, conf, k, rows, columns, distance2, classes, out_labels, out_conf):
    """Fill out_labels / out_conf (copies of labels / conf) with each point's vote; see knn_vote."""
    occupant = cell_points(row, col, height, width)
    across = _classes_across(occupant, labels, height, width, columns)
    best_d = np.empty(k)
    best_j = np.empty(k, np.int64)
    votes = np.empty(classes)
    window = np.empty(rows * columns, np.int64)
    for i in range(len(points)):
        present = np.uint8(0)  # the classes in the point's window: its own alone, and nothing can change
        for dr in range(-(rows // 2), rows - rows // 2):
            r = row[i] + dr
            if 0 <= r < height:
                present |= across[r * width + col[i]]
        if present == np.uint8(1) << labels[i]:
            continue
        n = 0  # the window's points
        for dr in range(-(rows // 2), rows - rows // 2):
            r = row[i] + dr
            if r < 0 or r >= height:
                continue
            for dc in range(-(columns // 2), columns - columns // 2):
                c = col[i] + dc
                c = c + width if c < 0 else (c - width if c >= width else c)
                j = occupant[r * width + c]
                if j >= 0:
                    window[n] = j
                    n += 1
        found = 0
        for t in range(n):
            j = window[t]
            dx = points[j, 0] - points[i, 0]
            dy = points[j, 1] - points[i, 1]
            dz = points[j, 2] - points[i, 2]
            d = dx * dx + dy * dy + dz * dz
            if d < distance2:
                found = keep_nearest(best_d, best_j, found, d, j)
        votes[:] = 0.0
        votes[labels[i]] = 0.5  # ties: the network's own label
        for t in range(found):
            votes[labels[best_j[t]]] += 1.0
        win = np.argmax(votes)
        if win != labels[i]:
            total, agree = 0.0, 0
            for t in range(found):
                if labels[best_j[t]] == win:
                    total += conf[best_j[t]]
                    agree += 1
            out_labels[i] = win
            out_conf[i] = total / agree


@numba.njit(cache=True, nogil=True)
def _classes_across(occupant, labels, height, width, columns):
    """Per grid cell, the classes (bit c for class c) of the cells' occupants in the ``columns`` cells of its
    row centred on it (azimuth wraps); with the rows above and below, a point's window holds only its own
    class when the union is that class's bit."""
    bits = np.zeros(height * width, np.uint8)
    for cell in range(height * width):
        if occupant[cell] >= 0:
            bits[cell] = np.uint8(1) << labels[occupant[cell]]
    across = np.zeros(height * width, np.uint8)
    half = columns // 2
    for r in range(height):
        base = r * width
        for c in range(width):
            m = np.uint8(0)
            for dc in range(-half, columns - half):
                cc = c + dc
                cc = cc + width if cc < 0 else (cc - width if cc >= width else cc)
                m |= bits[base + cc]
            across[base + c] = m
    return across


@numba.njit(cache=True, nogil=True, inline="always")
def keep_nearest(best_d, best_j, found, d, j):
    """Insert point j at squared distance d into the ascending best_d / best_j (capacity len(best_d)), dropping
    the farthest when full; returns how many they hold. Inlined into floor._relabel too: numba's cache does not
    see a change here from there, so clear __pycache__/*.nbi after editing it."""
    k = len(best_d)
    if found == k and d >= best_d[k - 1]:
        return found
    s = min(found, k - 1)
    while s > 0 and best_d[s - 1] > d:
        best_d[s] = best_d[s - 1]
        best_j[s] = best_j[s - 1]
        s -= 1
    best_d[s] = d
    best_j[s] = j
    return min(found + 1, k)
