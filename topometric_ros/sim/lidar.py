"""LiDAR ray casting with Open3D's RaycastingScene, for every sensors.SensorModel, with motion distortion.

A spinning sensor fires its columns one after another over a sweep (clockwise seen from above: azimuth
falls with time), all beams of a column at once; a non-repetitive one (Livox Mid-360-like) fires single
points along a pattern that never repeats. With ``column_poses`` each firing leaves from the pose the
sensor had at its own time and its point is reported in the sensor frame OF THAT TIME, exactly as a real
sensor does (motion distortion); with one pose the sweep is instantaneous. Ring 0 is the lowest beam.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import classes as C
from ..sensors import DEFAULT_SENSOR, SensorModel, sensor
from .scenes import Scene

#: Typical reflectivity per class (0..1), for a plausible intensity channel.
_REFLECTIVITY = np.array([0.35, 0.25, 0.55, 0.5, 0.4, 0.3, 0.6], np.float32)
#: Irrational steps of the non-repetitive pattern (azimuth and elevation advance per point, in turns).
_GOLDEN = (np.sqrt(5.0) - 1) / 2
_PATTERN_EL = np.sqrt(2.0) / 17


@dataclass
class Scan:
    """One simulated sweep, returns only. Points in the sensor frame (m); per point ring (beam, 0 = lowest;
    None for a non-repetitive sensor), class label, plane instance, time (s since the sweep's first firing)
    and firing index (column of a spinning sensor, point number of a non-repetitive one)."""

    points: np.ndarray  # (N, 3) float32
    intensity: np.ndarray  # (N,) float32, 0..255
    ring: np.ndarray | None  # (N,) uint16
    label: np.ndarray  # (N,) uint8
    instance: np.ndarray  # (N,) int32
    time: np.ndarray  # (N,) float64 s
    firing: np.ndarray  # (N,) int64


def firings(model: SensorModel, sweep: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(directions (F, 3) float32 sensor frame, beam (F,) int, firing index (F,) int) of one sweep in firing
    order; the firing index times model.period_s / firings_per_sweep is the firing time. Spinning: column c
    (azimuth −2π c / columns from +x), all beams; non-repetitive: points_per_scan points along the pattern,
    continued from sweep ``sweep`` so no two sweeps repeat."""
    if model.pattern == "non_repetitive":
        k = np.arange(model.points_per_scan) + sweep * model.points_per_scan
        az = 2 * np.pi * np.mod(k * _GOLDEN, 1.0)
        lo, hi = np.radians(model.fov_deg)
        el = lo + (hi - lo) * np.abs(2 * np.mod(k * _PATTERN_EL, 1.0) - 1)  # a triangle wave: uniform in elevation
        beam = np.zeros(len(k), np.int64)
        column = np.arange(len(k))
    else:
        el1 = np.radians(np.asarray(model.elevation_deg))
        az1 = np.mod(model.columns - np.arange(model.columns), model.columns) * (2 * np.pi / model.columns)
        column, beam = np.divmod(np.arange(model.columns * model.beams), model.beams)
        az, el = az1[column], el1[beam]
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
    return d.astype(np.float32), beam, column


def firings_per_sweep(model: SensorModel) -> int:
    """Columns of a spinning sensor, points of a non-repetitive one."""
    return model.points_per_scan if model.pattern == "non_repetitive" else model.columns


class Lidar:
    """Casts a SensorModel's rays into a Scene. Build once per scene, then :meth:`scan` (one pose) or
    :meth:`sweep` (a pose per firing: motion distortion)."""

    def __init__(self, scene: Scene, model: SensorModel | str = DEFAULT_SENSOR, threads: int | None = None):
        import open3d as o3d

        if threads:
            o3d.utility.set_max_threads(threads)
        self.scene = scene
        self.model = sensor(model) if isinstance(model, str) else model
        self._rc = o3d.t.geometry.RaycastingScene()
        self._rc.add_triangles(o3d.core.Tensor(scene.vertices), o3d.core.Tensor(scene.triangles.astype(np.uint32)))
        self._o3d = o3d
        self._spinning = firings(self.model) if self.model.pattern == "spinning" else None

    def scan(self, sensor_pose: np.ndarray, rng: np.random.Generator, sweep: int = 0) -> Scan:
        """An instantaneous sweep from a 4×4 sensor-to-map pose; noise and dropouts drawn from rng."""
        return self.sweep(np.asarray(sensor_pose)[None], rng, sweep, returns_only=True)

    def sweep(self, column_poses: np.ndarray, rng: np.random.Generator, sweep: int = 0,
              returns_only: bool = True) -> Scan:
        """One sweep: ``column_poses`` (firings_per_sweep, 4, 4) sensor-to-map pose at each firing time, or
        (1, 4, 4) for an instantaneous sweep. Each point is in the sensor frame of its own firing. With
        ``returns_only=False`` every firing is kept (no return: range NaN in ``points``), in firing order."""
        m = self.model
        dirs, beam, column = self._spinning if self._spinning is not None else firings(m, sweep)
        poses = np.asarray(column_poses, np.float64)
        pose = poses[np.minimum(column, len(poses) - 1)] if len(poses) > 1 else np.broadcast_to(poses[0], (1, 4, 4))
        world = np.einsum("fij,fj->fi", pose[:, :3, :3], dirs) if len(poses) > 1 else dirs @ poses[0, :3, :3].T
        rays = np.empty((len(dirs), 6), np.float32)
        rays[:, :3] = pose[:, :3, 3] if len(poses) > 1 else poses[0, :3, 3]
        rays[:, 3:] = world
        hit = self._rc.cast_rays(self._o3d.core.Tensor.from_numpy(rays))
        t = hit["t_hit"].numpy()
        prim = hit["primitive_ids"].numpy()
        keep = (t >= m.min_range) & (t <= m.max_range)
        if m.dropout > 0:
            keep &= rng.random(len(t), dtype=np.float32) >= m.dropout
        noise = np.clip(rng.standard_normal(len(t), dtype=np.float32), -3.0, 3.0)
        rng_m = np.where(keep, t + m.range_noise * noise, np.nan).astype(np.float32)
        prim = np.where(keep, prim, 0)
        label = np.where(keep, self.scene.tri_class[prim], 0).astype(np.uint8)
        normals = hit["primitive_normals"].numpy()
        cos_inc = np.abs(np.einsum("ij,ij->i", normals, world))
        intensity = ((255 * _REFLECTIVITY[label]) * (0.3 + 0.7 * cos_inc) / (1 + 0.01 * np.nan_to_num(rng_m)))
        out = Scan(points=dirs * rng_m[:, None], intensity=intensity.astype(np.float32),
                   ring=beam.astype(np.uint16) if m.pattern == "spinning" else None, label=label,
                   instance=np.where(keep, self.scene.tri_instance[prim], -1).astype(np.int32),
                   time=column * (m.period_s / firings_per_sweep(m)), firing=column)
        return _subset(out, np.flatnonzero(keep)) if returns_only else out


def _subset(scan: Scan, idx: np.ndarray) -> Scan:
    return Scan(scan.points[idx], scan.intensity[idx], None if scan.ring is None else scan.ring[idx],
                scan.label[idx], scan.instance[idx], scan.time[idx], scan.firing[idx])


def class_counts(labels: np.ndarray) -> dict[str, int]:
    """{class name: number of points} for a label array."""
    counts = np.bincount(labels, minlength=C.NUM_CLASSES)
    return {C.NAMES[i]: int(n) for i, n in enumerate(counts)}
