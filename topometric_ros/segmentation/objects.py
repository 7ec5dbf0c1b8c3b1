"""One label per object: desk and chair points that touch take their object's majority label.

The network labels pixels, and a chair beside a desk, or a desk seen edge-on, often comes out part desk and
part chair. Here the desk- and chair-labelled points are joined into objects: two of them are joined when
their grid cells are neighbours (NEIGHBOURS: the 8 cells around, and the cells two columns or two rows away;
azimuth wraps around; a cell's points all join its last one) and they lie less than ``gap`` m apart in 3D.
An object whose commonest label holds at least SHARE of its points takes that label on all of them.
Floor, wall, pillar, ceiling and other points are left alone and never join objects. Points are in the
SENSOR frame, metres. Chosen on the validation layout (docs/results.md, seventeenth session). One numba pass
(union-find over the grid), single thread, GIL released.
"""
from __future__ import annotations

import numba
import numpy as np

from .. import classes as C
from ..grid import ScanGrid

#: The classes whose points form objects.
OBJECT_CLASSES = (C.DESK, C.CHAIR)
#: Least fraction of an object's points its commonest label must hold for the whole object to take it.
SHARE = 0.6
#: (rows, columns) steps from a grid cell to the cells whose points may join its own (each pair of cells once:
#: the steps back are the same pairs seen from the other cell).
NEIGHBOURS = np.array([(0, 1), (1, -1), (1, 0), (1, 1), (0, 2), (2, 0)], np.int64)


def unify_objects(points: np.ndarray, grid: ScanGrid, labels: np.ndarray, confidence: np.ndarray, gap: float,
                  share: float = SHARE) -> tuple[np.ndarray, np.ndarray]:
    """(labels (N,) uint8, confidence (N,) float32) with every object of desk and chair points (joined within
    ``gap`` m; module docstring) whose commonest label holds at least ``share`` of it labelled all that; a point
    whose label changes takes the mean confidence of the object's points that had the new label. Points (N, 3)
    in the sensor frame on their grid; points with a NaN coordinate join nothing. ``gap`` <= 0: the input
    unchanged."""
    labels = np.asarray(labels, np.uint8)
    confidence = np.asarray(confidence, np.float32)
    if not gap > 0 or len(points) == 0:
        return labels, confidence
    is_object = np.zeros(C.NUM_CLASSES, np.bool_)
    is_object[list(OBJECT_CLASSES)] = True
    out_labels, out_conf = labels.copy(), confidence.copy()
    _unify(np.ascontiguousarray(points, np.float32), np.asarray(grid.row), np.asarray(grid.col), grid.height,
           grid.width, labels, confidence, is_object, float(gap) ** 2, float(share), NEIGHBOURS, out_labels, out_conf)
    return out_labels, out_conf


@numba.njit(cache=True, nogil=True)
def _unify(points, row, col, height, width, labels, conf, is_object, gap2, share, neighbours, out_labels, out_conf):
    """Set out_labels / out_conf of the objects' points to their object's majority (unify_objects)."""
    members = np.empty(len(points), np.int64)  # the object points, by their index among them
    m = 0
    for i in range(len(points)):
        if is_object[labels[i]] and np.isfinite(points[i, 0] + points[i, 1] + points[i, 2]):
            members[m] = i
            m += 1
    members = members[:m]
    occupant = np.full(height * width, -1, np.int64)  # the last object point of each cell (index among members)
    for k in range(m):
        i = members[k]
        occupant[row[i] * width + col[i]] = k
    parent = np.arange(m)
    for k in range(m):
        i = members[k]
        _join(points, members, parent, k, occupant[row[i] * width + col[i]], gap2)
        for s in range(len(neighbours)):
            r = row[i] + neighbours[s, 0]
            if r < height:
                _join(points, members, parent, k, occupant[r * width + (col[i] + neighbours[s, 1]) % width], gap2)
    classes = len(is_object)
    count = np.zeros((m, classes), np.int64)
    conf_sum = np.zeros((m, classes))
    for k in range(m):
        parent[k] = _root(parent, k)  # now every point's own root
        count[parent[k], labels[members[k]]] += 1
        conf_sum[parent[k], labels[members[k]]] += conf[members[k]]
    winner = np.full(m, -1, np.int64)  # per root: the label its whole object takes, −1 none
    for k in range(m):
        if parent[k] == k:
            best = np.argmax(count[k])
            if count[k, best] >= share * count[k].sum():
                winner[k] = best
    for k in range(m):
        best = winner[parent[k]]
        if best >= 0 and best != labels[members[k]]:
            out_labels[members[k]] = best
            out_conf[members[k]] = conf_sum[parent[k], best] / count[parent[k], best]


@numba.njit(cache=True, nogil=True)
def _join(points, members, parent, a, b, gap2):
    """Join object points a and b (indices among members; b < 0: none) when nearer than sqrt(gap2) m."""
    if b < 0 or b == a:
        return
    i, j = members[a], members[b]
    dx, dy, dz = points[i, 0] - points[j, 0], points[i, 1] - points[j, 1], points[i, 2] - points[j, 2]
    if dx * dx + dy * dy + dz * dz < gap2:
        ra, rb = _root(parent, a), _root(parent, b)
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)


@numba.njit(cache=True, nogil=True)
def _root(parent, k):
    """The root of k's tree (halving the path on the way)."""
    while parent[k] != k:
        parent[k] = parent[parent[k]]
        k = parent[k]
    return k
