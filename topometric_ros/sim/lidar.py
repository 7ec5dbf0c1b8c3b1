"""VLP-32C ray casting with Open3D's RaycastingScene.

Rays leave the sensor origin; points come back in the sensor frame (x forward, z up), ordered
azimuth-major like a driver's cloud. Ring 0 is the lowest beam (velodyne_driver convention).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import classes as C
from .scenes import Scene

#: VLP-32C elevation angles (deg) by laser id, from the sensor manual; non-uniform, −25° to +15°.
VLP32C_ELEVATION_DEG = np.array([
    -25.0, -1.0, -1.667, -15.639, -11.31, 0.0, -0.667, -8.843, -7.254, 0.333, -0.333, -6.148, -5.333, 1.333,
    0.667, -4.0, -4.667, 1.667, 1.0, -3.667, -3.333, 3.333, 2.333, -2.667, -3.0, 7.0, 4.667, -2.333, -2.0,
    15.0, 10.333, -1.333])
#: Elevation by ring (ascending), the order ring ids refer to.
RING_ELEVATION_DEG = np.sort(VLP32C_ELEVATION_DEG)
#: Typical reflectivity per class (0..1), for a plausible intensity channel.
_REFLECTIVITY = np.array([0.35, 0.25, 0.55, 0.5, 0.4, 0.3, 0.6], np.float32)


@dataclass(frozen=True)
class LidarSpec:
    """A spinning LiDAR: beams × azimuth steps, range limits (m), Gaussian range noise (m, truncated at
    3σ) and a random dropout fraction."""

    elevation_deg: tuple = tuple(RING_ELEVATION_DEG)
    azimuth_steps: int = 1800
    min_range: float = 0.4
    max_range: float = 100.0
    range_noise: float = 0.008
    dropout: float = 0.01

    @property
    def rings(self) -> int:
        return len(self.elevation_deg)

    def directions(self) -> tuple[np.ndarray, np.ndarray]:
        """Unit ray directions (rings × azimuth_steps, 3) in the sensor frame, azimuth-major, and ring ids."""
        el = np.radians(np.asarray(self.elevation_deg))
        az = np.arange(self.azimuth_steps) * (2 * np.pi / self.azimuth_steps)
        azg, elg = np.meshgrid(az, el, indexing="ij")  # (A, R)
        d = np.stack([np.cos(elg) * np.cos(azg), np.cos(elg) * np.sin(azg), np.sin(elg)], -1).reshape(-1, 3)
        ring = np.tile(np.arange(self.rings, dtype=np.uint16), self.azimuth_steps)
        return d.astype(np.float32), ring


@dataclass
class Scan:
    """One simulated sweep. Points in the sensor frame (m); per-point ring, class label, plane instance."""

    points: np.ndarray  # (N, 3) float32
    intensity: np.ndarray  # (N,) float32, 0..255
    ring: np.ndarray  # (N,) uint16
    label: np.ndarray  # (N,) uint8
    instance: np.ndarray  # (N,) int32


class Lidar:
    """Casts a LidarSpec's rays into a Scene. Build once per scene, then call :meth:`scan` per pose."""

    def __init__(self, scene: Scene, spec: LidarSpec = LidarSpec(), threads: int | None = None):
        import open3d as o3d

        if threads:
            o3d.utility.set_max_threads(threads)
        self.scene, self.spec = scene, spec
        self._rc = o3d.t.geometry.RaycastingScene()
        self._rc.add_triangles(o3d.core.Tensor(scene.vertices), o3d.core.Tensor(scene.triangles.astype(np.uint32)))
        self._dirs, self._ring = spec.directions()
        self._rays = np.empty((len(self._dirs), 6), np.float32)
        self._o3d = o3d

    def scan(self, sensor_pose: np.ndarray, rng: np.random.Generator) -> Scan:
        """Sweep from a 4×4 sensor-to-map pose; noise and dropouts drawn from rng."""
        rot = sensor_pose[:3, :3].astype(np.float32)
        self._rays[:, :3] = sensor_pose[:3, 3]
        np.matmul(self._dirs, rot.T, out=self._rays[:, 3:])
        hit = self._rc.cast_rays(self._o3d.core.Tensor.from_numpy(self._rays))
        t = hit["t_hit"].numpy()
        prim = hit["primitive_ids"].numpy()
        spec = self.spec
        keep = (t >= spec.min_range) & (t <= spec.max_range)
        if spec.dropout > 0:
            keep &= rng.random(len(t), dtype=np.float32) >= spec.dropout
        idx = np.flatnonzero(keep)
        noise = rng.standard_normal(len(idx), dtype=np.float32)
        np.clip(noise, -3.0, 3.0, out=noise)
        rng_m = t[idx] + spec.range_noise * noise
        dirs = self._dirs[idx]
        prim = prim[idx]
        label = self.scene.tri_class[prim]
        normals = hit["primitive_normals"].numpy()[idx]
        cos_inc = np.abs(np.einsum("ij,ij->i", normals, self._rays[idx, 3:]))
        intensity = (255 * _REFLECTIVITY[label]).astype(np.float32) * (0.3 + 0.7 * cos_inc) / (1 + 0.01 * rng_m)
        return Scan(points=dirs * rng_m[:, None], intensity=intensity.astype(np.float32), ring=self._ring[idx],
                    label=label, instance=self.scene.tri_instance[prim])


def class_counts(labels: np.ndarray) -> dict[str, int]:
    """{class name: number of points} for a label array."""
    counts = np.bincount(labels, minlength=C.NUM_CLASSES)
    return {C.NAMES[i]: int(n) for i, n in enumerate(counts)}
