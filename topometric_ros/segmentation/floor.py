"""Floor labels checked against the floor around them.

The network's commonest floor error is the foot of a chair or desk (a base or wheels 3-10 cm above the
floor) labelled floor: in the range image it continues the floor. Here a plane is fitted to the scan's
floor-labelled points (trimmed least squares) to say which way is up and roughly where the floor is. A
floor-labelled point more than ``band`` above that plane (and at most REACH above: higher up it is another
level, a ramp or a step) and more than ``band`` above the lowest floor-labelled point within DISTANCE of it
(real floors are not one plane: the step must be local) takes the majority label of the VOTERS nearest
non-floor points within DISTANCE (a tie: the nearest voter's class among the tied); with none there it stays
floor. Neighbours are searched among the grid cells of a WINDOW around the point's own (azimuth wraps around).
Points are in the SENSOR frame, metres. Chosen on the validation layout (docs/results.md, sixteenth session).

The other way round, for non-repetitive scans only (snap_to_floor): there the floor is sparse and seen at
grazing angles, and the network reads a good share of it as wall or other; a point of those classes (or desk,
chair) lying within a band of the floor plane becomes floor. Spinning scans lose floor IoU with it (their
floors are read well, and what lies on the plane there is mostly a wall's foot): twenty-first session.
"""
from __future__ import annotations

import numba
import numpy as np

from .. import classes as C
from ..grid import ScanGrid
# mean_scatter and keep_nearest are compiled into _fit and _relabel: after editing either, clear numba's cache
# (__pycache__/*.nbi)
from ..planes import UPRIGHT, mean_scatter
from .knn import keep_nearest

#: Fewest floor-labelled points the plane is fitted to (fewer: labels unchanged).
MIN_FLOOR_POINTS = 50
#: Most floor-labelled points the fit uses (an even subsample of them beyond).
FIT_POINTS = 1024
#: m, points at most this far from the plane always count in the trimmed fit; beyond, the closest 80 %.
FIT_TOLERANCE = 0.03
#: m, floor-labelled points higher than this above the plane are left alone (another level, not a chair's foot).
REACH = 0.3
#: Non-floor points that vote on a lifted point's label.
VOTERS = 5
#: m, neighbours (floor points for the local step, other points as voters) are at most this far away.
DISTANCE = 1.0
#: Rows x columns of grid cells around a lifted point searched for neighbours.
WINDOW = (7, 15)
#: Classes a non-repetitive scan's point on the floor plane gives up for floor (snap_to_floor).
SNAPPED = (C.OTHER, C.WALL, C.DESK, C.CHAIR)


def floor_plane(points: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, float] | None:
    """(unit normal (3,) pointing from the floor towards the sensor, offset m) of the plane through the finite
    floor-labelled points (sensor frame; height above the floor = points @ normal − offset; the sensor sees the
    floor from above, so an upside-down sensor is judged as an upright one), or None with fewer than
    MIN_FLOOR_POINTS of them or a plane tilted more than 45 deg from the sensor's x-y plane. Four rounds of least
    squares, each on the points within FIT_TOLERANCE of the last plane or its closest 80 %."""
    points = np.asarray(points)
    floor = np.flatnonzero(labels == C.FLOOR)
    floor = floor[np.isfinite(points[floor]).all(1)]
    if len(floor) < MIN_FLOOR_POINTS:
        return None
    normal, centre = _fit(points[floor[::-(-len(floor) // FIT_POINTS)]].astype(np.float64), FIT_TOLERANCE)
    if normal @ centre > 0:  # the sensor (the origin) lies on the normal's side
        normal = -normal
    if not abs(normal[2]) >= UPRIGHT:  # tilted more than 45°: no floor; NaN too (a degenerate fit)
        return None
    return normal, float(normal @ centre)


@numba.njit(cache=True, nogil=True)
def _fit(p, tolerance):
    """(unit normal, centroid) of the points (n, 3): four rounds of least squares, each on the points within
    ``tolerance`` of the last plane or its closest 80 %."""
    n = len(p)
    keep = np.ones(n, np.bool_)
    normal = np.full(3, np.nan)
    centre = np.zeros(3)
    dist = np.empty(n)
    for _ in range(4):
        kept = p[keep]
        if len(kept) < 3:
            return np.full(3, np.nan), centre
        centre, scatter = mean_scatter(kept)
        normal = np.linalg.eigh(scatter)[1][:, 0]  # the direction of least spread
        for i in range(n):
            dist[i] = abs((p[i, 0] - centre[0]) * normal[0] + (p[i, 1] - centre[1]) * normal[1]
                          + (p[i, 2] - centre[2]) * normal[2])
        k = int(0.8 * (n - 1))
        cut = max(tolerance, np.partition(dist, k)[k])
        for i in range(n):
            keep[i] = dist[i] <= cut
    return normal, centre


def lift_off_floor(points: np.ndarray, grid: ScanGrid, labels: np.ndarray, confidence: np.ndarray, band: float,
                   distance: float = DISTANCE, window: tuple[int, int] = WINDOW) -> tuple[np.ndarray, np.ndarray]:
    """(labels (N,) uint8, confidence (N,) float32) with floor-labelled points standing more than ``band`` m
    above the floor (the plane and the floor within ``distance`` m around them; module docstring) relabelled by
    their nearest non-floor neighbours; a relabelled point takes the mean confidence of the neighbours that voted
    for its new label. Points (N, 3) in the sensor frame on their grid. ``band`` <= 0 or no floor plane: the
    input unchanged."""
    labels = np.asarray(labels, np.uint8)
    confidence = np.asarray(confidence, np.float32)
    plane = floor_plane(points, labels) if band > 0 and len(points) else None
    if plane is None:
        return labels, confidence
    out_labels, out_conf = labels.copy(), confidence.copy()
    rows, columns = int(window[0]), min(int(window[1]), grid.width)  # a narrow grid's columns count once
    _relabel(np.ascontiguousarray(points, np.float32), np.asarray(grid.row), np.asarray(grid.col), grid.height,
             grid.width, labels, confidence, plane[0], plane[1], float(band), REACH, rows, columns,
             float(distance) ** 2, VOTERS, C.FLOOR, C.NUM_CLASSES, out_labels, out_conf)
    return out_labels, out_conf


def snap_to_floor(points: np.ndarray, labels: np.ndarray, confidence: np.ndarray, band: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(labels (N,) uint8, confidence (N,) float32) with the SNAPPED-class points within ``band`` m of the scan's
    floor plane (floor_plane, either side) labelled floor, taking the mean confidence of the floor-labelled
    points. Points (N, 3) in the sensor frame. ``band`` <= 0 or no floor plane: the input unchanged. Meant for
    non-repetitive scans only (module docstring)."""
    labels = np.asarray(labels, np.uint8)
    confidence = np.asarray(confidence, np.float32)
    plane = floor_plane(points, labels) if band > 0 and len(points) else None
    if plane is None:
        return labels, confidence
    normal, offset = plane
    with np.errstate(invalid="ignore"):
        on_floor = np.abs(np.asarray(points, np.float64) @ normal - offset) <= band
    snap = on_floor & np.isin(labels, SNAPPED)
    if not snap.any():
        return labels, confidence
    out_labels, out_conf = labels.copy(), confidence.copy()
    out_labels[snap] = C.FLOOR
    out_conf[snap] = confidence[labels == C.FLOOR].mean()
    return out_labels, out_conf


@numba.njit(cache=True, nogil=True)
def _relabel(points, row, col, height, width, labels, conf, normal, offset, band, reach, rows, columns, distance2,
             voters, floor, classes, out_labels, out_conf):
    """Set out_labels / out_conf of the floor points between band and reach above the plane (normal, offset), and
    more than band above the floor points within sqrt(distance2) of them, to the vote of their ``voters`` nearest
    non-floor points (lift_off_floor)."""
    lifted = _lifted(points, labels, normal, offset, band, reach, floor)
    if len(lifted) == 0:
        return
    start, members = _cell_members(row, col, height, width, lifted, rows, columns)
    best_d = np.empty(voters)
    best_j = np.empty(voters, np.int64)
    votes = np.zeros(classes)
    for i in lifted:
        found = 0
        h_i = _along(points, i, normal)
        lowest = h_i  # of the floor-labelled points near it (height above the plane + offset)
        for dr in range(-(rows // 2), rows - rows // 2):
            r = row[i] + dr
            if r < 0 or r >= height:
                continue
            for dc in range(-(columns // 2), columns - columns // 2):
                cell = r * width + (col[i] + dc) % width
                for m in range(start[cell], start[cell + 1]):
                    j = members[m]
                    d = (points[i, 0] - points[j, 0]) ** 2 + (points[i, 1] - points[j, 1]) ** 2 \
                        + (points[i, 2] - points[j, 2]) ** 2
                    if not d <= distance2:  # NaN too
                        continue
                    if labels[j] == floor:
                        lowest = min(lowest, _along(points, j, normal))
                    else:
                        found = keep_nearest(best_d, best_j, found, d, j)
        if found and h_i - lowest > band:
            out_labels[i], out_conf[i] = _vote(labels, conf, best_j[:found], votes)


@numba.njit(cache=True, nogil=True)
def _lifted(points, labels, normal, offset, band, reach, floor):
    """Indices of the floor-labelled points more than band and at most reach above the plane (normal, offset)."""
    lifted = np.empty(len(points), np.int64)
    n = 0
    for i in range(len(points)):
        if labels[i] == floor:
            h = _along(points, i, normal) - offset
            if band < h <= reach:
                lifted[n] = i
                n += 1
    return lifted[:n]


@numba.njit(cache=True, nogil=True)
def _cell_members(row, col, height, width, lifted, rows, columns):
    """(start (cells + 1,), members): the points of each grid cell within a rows x columns window of a lifted
    point are members[start[cell]:start[cell + 1]] (a counting sort by cell; other cells are empty)."""
    cells = height * width
    wanted = np.zeros(cells, np.bool_)
    for i in lifted:
        for dr in range(-(rows // 2), rows - rows // 2):
            r = row[i] + dr
            if 0 <= r < height:
                for dc in range(-(columns // 2), columns - columns // 2):
                    wanted[r * width + (col[i] + dc) % width] = True
    start = np.zeros(cells + 1, np.int64)
    for i in range(len(row)):
        cell = row[i] * width + col[i]
        if wanted[cell]:
            start[cell + 1] += 1
    for c in range(cells):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    members = np.empty(start[cells], np.int64)
    for i in range(len(row)):
        cell = row[i] * width + col[i]
        if wanted[cell]:
            members[fill[cell]] = i
            fill[cell] += 1
    return start, members


@numba.njit(cache=True, nogil=True, inline="always")
def _along(points, i, normal):
    """Point i's coordinate along ``normal`` (m)."""
    return points[i, 0] * normal[0] + points[i, 1] * normal[1] + points[i, 2] * normal[2]


@numba.njit(cache=True, nogil=True)
def _vote(labels, conf, voters, votes):
    """(label, confidence) of the majority of ``voters`` (nearest first; a tie goes to the class of the nearest
    voter among the tied) and the mean confidence of the voters for it; ``votes`` (classes,) is scratch."""
    votes[:] = 0.0
    for j in voters:
        votes[labels[j]] += 1.0
    top = votes.max()
    winner = labels[voters[0]]
    for j in voters:
        if votes[labels[j]] == top:
            winner = labels[j]
            break
    total = 0.0
    for j in voters:
        if labels[j] == winner:
            total += conf[j]
    return np.uint8(winner), np.float32(total / top)
