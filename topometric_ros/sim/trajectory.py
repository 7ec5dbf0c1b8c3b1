"""Robot trajectories through a scene's free space.

A 2-D occupancy grid is rasterised from the scene's obstacle footprints; routes join random far-apart
goals by shortest paths that keep clear of obstacles (Dijkstra on the grid, cost rising near walls),
then are smoothed and driven at constant speed. Poses are base_link-to-map 4×4 matrices (base on the floor).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import csgraph

from .. import geometry
from .scenes import Scene


@dataclass
class FreeSpace:
    """Cells (row = y, col = x) where the robot fits, and each cell's clearance to obstacles (m)."""

    free: np.ndarray  # (H, W) bool
    clearance: np.ndarray  # (H, W) float, m
    origin: np.ndarray  # (2,) map x, y of cell (0, 0) centre
    resolution: float  # m per cell

    def cell_xy(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        return self.origin + np.stack([cols, rows], -1) * self.resolution


def free_space(scene: Scene, resolution: float = 0.2, robot_radius: float = 0.45) -> FreeSpace:
    """Rasterise obstacle footprints (every cell a footprint overlaps, however thin the footprint: testing cell
    centres alone let a 0.15 m wall fall between them and routes through it); keep the largest connected region
    with clearance > robot_radius."""
    xmin, ymin, xmax, ymax = scene.bounds
    origin = np.array([xmin, ymin]) + resolution / 2
    w, h = int(np.ceil((xmax - xmin) / resolution)), int(np.ceil((ymax - ymin) / resolution))
    occ = np.zeros((h, w), bool)
    occ[0, :] = occ[-1, :] = occ[:, 0] = occ[:, -1] = True
    for fp in scene.footprints:
        c0 = np.clip(np.floor((fp.min(0) - origin) / resolution).astype(int), 0, [w - 1, h - 1])
        c1 = np.clip(np.ceil((fp.max(0) - origin) / resolution).astype(int), 0, [w - 1, h - 1])
        cols, rows = np.meshgrid(np.arange(c0[0], c1[0] + 1), np.arange(c0[1], c1[1] + 1))
        pts = origin + np.stack([cols, rows], -1) * resolution
        hit = _overlaps(fp, pts, resolution / 2)
        occ[rows[hit], cols[hit]] = True
    clearance = ndimage.distance_transform_edt(~occ) * resolution
    free = clearance > robot_radius
    lab, n = ndimage.label(free)
    if n == 0:
        raise ValueError(f"scene {scene.name} has no free space for a robot of radius {robot_radius} m")
    sizes = ndimage.sum(free, lab, index=np.arange(1, n + 1))
    return FreeSpace(lab == 1 + int(np.argmax(sizes)), clearance, origin, resolution)


def _overlaps(quad: np.ndarray, centres: np.ndarray, half: float) -> np.ndarray:
    """Whether each axis-aligned square cell (centres (..., 2), half side ``half``) overlaps a convex quad (4, 2):
    no separating axis among the cell's axes and the quad's edge normals."""
    quad = np.asarray(quad, float)
    edges = np.roll(quad, -1, axis=0) - quad
    axes = np.vstack([np.eye(2), np.stack([-edges[:, 1], edges[:, 0]], 1)])
    hit = np.ones(centres.shape[:-1], bool)
    for axis in axes:
        norm = np.linalg.norm(axis)
        if norm < 1e-12:
            continue
        axis = axis / norm
        q = quad @ axis
        c = centres @ axis
        r = half * (abs(axis[0]) + abs(axis[1]))
        hit &= (c + r >= q.min()) & (c - r <= q.max())
    return hit


def plan_route(space: FreeSpace, length: float, rng: np.random.Generator, min_leg: float = 8.0) -> np.ndarray:
    """A route (K, 2) of map x, y through free space at least ``length`` m long, via random goals."""
    rows, cols = np.nonzero(space.free)
    index = -np.ones(space.free.shape, int)
    index[rows, cols] = np.arange(len(rows))
    graph = _grid_graph(space, rows, cols, index)
    xy = space.cell_xy(rows, cols)
    current = int(rng.integers(len(rows)))
    route, total = [xy[current]], 0.0
    while total < length:
        dist, pred = csgraph.dijkstra(graph, indices=current, return_predecessors=True)
        far = np.flatnonzero(np.isfinite(dist) & (np.linalg.norm(xy - xy[current], axis=1) > min_leg))
        if len(far) == 0:
            far = np.flatnonzero(np.isfinite(dist) & (dist > 0))
        goal = int(rng.choice(far))
        path = [goal]
        while path[-1] != current:
            path.append(int(pred[path[-1]]))
        leg = xy[path[::-1]][1:]
        total += np.linalg.norm(np.diff(np.vstack([route[-1], leg]), axis=0), axis=1).sum()
        route.extend(leg)
        current = goal
    return np.asarray(route)


def _grid_graph(space: FreeSpace, rows, cols, index) -> sparse.csr_matrix:
    """8-connected graph over free cells; edge cost = length × (1 + 1 / clearance) keeps routes central."""
    src, dst, cost = [], [], []
    h, w = space.free.shape
    penalty = 1.0 + 1.0 / np.maximum(space.clearance, 1e-3)
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        r2, c2 = rows + dr, cols + dc
        ok = (r2 >= 0) & (r2 < h) & (c2 >= 0) & (c2 < w)
        ok[ok] &= space.free[r2[ok], c2[ok]]
        a, b = index[rows[ok], cols[ok]], index[r2[ok], c2[ok]]
        step = np.hypot(dr, dc) * space.resolution
        c = step * 0.5 * (penalty[rows[ok], cols[ok]] + penalty[r2[ok], c2[ok]])
        src += [a, b]
        dst += [b, a]
        cost += [c, c]
    n = len(rows)
    return sparse.csr_matrix((np.concatenate(cost), (np.concatenate(src), np.concatenate(dst))), shape=(n, n))


@dataclass
class Trajectory:
    """A smooth base_link trajectory, sampled densely in time; :meth:`poses_at` interpolates."""

    stamps: np.ndarray  # (M,) s
    poses: np.ndarray  # (M, 4, 4) base_link to map

    def poses_at(self, t: np.ndarray) -> np.ndarray:
        return geometry.interpolate_poses(self.stamps, self.poses, t)[0]


#: Largest heading rate of the simulated robot (deg/s) and the time (s, Gaussian σ) over which it speeds up
#: or slows its turn. Without them a route that doubles back flipped the heading by up to 180° between two
#: 100 Hz samples; odometry at 20 Hz then gave scans poses tens of degrees off, and drift alarms on
#: drift-free bags followed.
MAX_YAW_RATE_DEG = 90.0
YAW_SMOOTH_S = 0.2


def follow_heading(yaw: np.ndarray, dt: float, max_rate_deg: float = MAX_YAW_RATE_DEG,
                   smooth_s: float = YAW_SMOOTH_S) -> np.ndarray:
    """The heading (rad, unwrapped) a robot turning at most ``max_rate_deg`` deg/s gets when it follows the
    wanted heading ``yaw`` sampled every ``dt`` s, with its turn rate smoothed over ``smooth_s`` s."""
    step = float(np.radians(max_rate_deg) * dt)
    out, heading = np.empty_like(yaw), float(yaw[0])
    for i, wanted in enumerate(yaw.tolist()):  # a rate limit is sequential; plain floats keep it fast
        heading += min(max(wanted - heading, -step), step)
        out[i] = heading
    return ndimage.gaussian_filter1d(out, smooth_s / dt, mode="nearest") if smooth_s > 0 else out


def drive(route: np.ndarray, duration: float, speed: float, start_time: float, rng: np.random.Generator,
          rate: float = 100.0, smooth_m: float = 0.5) -> Trajectory:
    """Drive a route at ``speed`` (m/s) for ``duration`` s from ``start_time``: smoothed path, heading along
    the path turning at most MAX_YAW_RATE_DEG (where the route doubles back the robot moves on while it
    turns), a 1 s speed ramp at the start, and small floor-induced roll/pitch (±0.3°) and bounce (2 mm)."""
    seg = np.linalg.norm(np.diff(route, axis=0), axis=1)
    s = np.r_[0, np.cumsum(seg)]
    keep = np.r_[True, seg > 1e-9]
    s, route = s[keep], route[keep]
    dense_s = np.arange(0, s[-1], 0.05)
    path = np.stack([np.interp(dense_s, s, route[:, 0]), np.interp(dense_s, s, route[:, 1])], 1)
    path = ndimage.gaussian_filter1d(path, smooth_m / 0.05, axis=0, mode="nearest")
    ps = np.r_[0, np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))]
    t = np.arange(0, duration, 1.0 / rate)
    dist = speed * np.where(t < 1.0, 0.5 * t * t, t - 0.5)  # accelerate over the first second
    if dist[-1] > ps[-1]:
        raise ValueError(f"route of {ps[-1]:.1f} m is too short for {duration:.1f} s at {speed} m/s")
    x, y = np.interp(dist, ps, path[:, 0]), np.interp(dist, ps, path[:, 1])
    ahead = np.minimum(dist + 0.3, ps[-1])
    yaw = np.arctan2(np.interp(ahead, ps, path[:, 1]) - y, np.interp(ahead, ps, path[:, 0]) - x)
    yaw = follow_heading(np.unwrap(yaw), 1.0 / rate)
    phase = rng.uniform(0, 2 * np.pi, 3)
    roll = np.radians(0.3) * np.sin(2 * np.pi * 0.7 * t + phase[0])
    pitch = np.radians(0.3) * np.sin(2 * np.pi * 0.5 * t + phase[1])
    z = 0.002 * np.sin(2 * np.pi * 1.3 * t + phase[2])
    poses = geometry.yaw_pose(x, y, z, yaw, roll, pitch)
    return Trajectory(start_time + t, poses)


def random_trajectory(scene: Scene, duration: float, speed: float, start_time: float,
                      rng: np.random.Generator) -> Trajectory:
    """Plan a route long enough for ``duration`` s at ``speed`` m/s through the scene and drive it."""
    space = free_space(scene, resolution=0.4 if scene.area > 2000 else 0.2)
    route = plan_route(space, 1.3 * speed * duration + 10.0, rng)
    return drive(route, duration, speed, start_time, rng)
