"""The one place the order of work lives: scan -> grid -> deskew -> segment -> planes (once per scan);
window -> metrics.

Frames of data: a scan's points and planes stay in its SENSOR frame; a window scores them in the window
frame, the sensor frame of its first scan (T_rel,i = T_1⁻¹ T_i), as map-metrics does.
"""
from __future__ import annotations

import time
from dataclasses import astuple, dataclass, field, replace
from typing import Sequence

import numpy as np

from . import classes as C
from . import geometry, planes as planes_mod
from .config import Config
from .deskew import azimuth_times, deskew
from .grid import ScanGrid, scan_grid
from .metrics import cpv as cpv_mod
from .metrics import drift_rate as drift_mod
from .metrics import pne as pne_mod
from .planes import Plane
from .window import Frame

#: The class every point gets in segmentation mode "none": one static class, so plane detection runs once
#: over the whole scan and CPV joins planes regardless of what they really are.
NONE_MODE_CLASS = C.WALL


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
    _stacked: tuple | None = field(default=None, init=False, repr=False, compare=False)

    def plane_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The planes stacked (sensor frame, computed once): classes (P,), normals (P, 3), means (P, 3),
        scatters (P, 3, 3), counts (P,)."""
        if self._stacked is None:
            p = self.planes
            self._stacked = (np.array([q.cls for q in p], int), np.array([q.normal for q in p]).reshape(-1, 3),
                             np.array([q.mean for q in p]).reshape(-1, 3),
                             np.array([q.scatter for q in p]).reshape(-1, 3, 3),
                             np.array([q.count for q in p], np.float64))
        return self._stacked


@dataclass
class WindowResult:
    """Scores of one window. pne (nats), cpv (m²); mme, mpv, mom when baselines are on (else None).

    rot_rate (deg/s) and trans_rate (m/s): the drift rates the co-plane groups show (metrics/drift_rate.py);
    rpe_estimate: the RPE (Eq. 4) those rates give over the window's consecutive scans. speed (m/s) and
    turn_rate (deg/s): the sensor's motion over the window by the SLAM poses (what relative limits scale with).
    n_planes: planes in the window; n_groups: CPV co-plane groups; n_clusters: PNE normal clusters.
    agreement: the lowest share, over the window's scans, of a scan's plane inliers that another scan
    sees in the same place (cpv.window_agreement; 0-1, low for a scan off by a pose jump); agreement_scan:
    that scan's position in the window (−1 none).
    pne / cpv / rates / agreement are NaN when the window has no normal cluster / co-plane group.
    timings: ms per metric.

    level / message are filled by health.py (OK, WARN, ERROR, STALE)."""

    stamps: list[float]
    pne: float
    cpv: float
    n_planes: int
    n_groups: int
    n_clusters: int = 0
    rot_rate: float = float("nan")
    trans_rate: float = float("nan")
    rot_rate_se: float = float("nan")
    trans_rate_se: float = float("nan")
    rpe_estimate: float = float("nan")
    speed: float = float("nan")
    turn_rate: float = float("nan")
    agreement: float = float("nan")
    agreement_scan: int = -1
    mme: float | None = None
    mpv: float | None = None
    mom: float | None = None
    timings: dict[str, float] = field(default_factory=dict)
    level: str = "OK"
    message: str = ""

    @property
    def n_scans(self) -> int:
        return len(self.stamps)

    @property
    def agreement_stamp(self) -> float:
        """Stamp (s) of the scan that gives the window's agreement; NaN when none does."""
        k = self.agreement_scan
        return float(self.stamps[k]) if 0 <= k < len(self.stamps) else float("nan")


class _Timer:
    """Collects wall times in ms into a dict: ``with timer("step"): ...``."""

    def __init__(self, into: dict[str, float]):
        self.into = into

    def __call__(self, name: str):
        self.name = name
        return self

    def __enter__(self):
        self.start = time.perf_counter()

    def __exit__(self, *exc):
        self.into[self.name] = 1000.0 * (time.perf_counter() - self.start)


_SEGMENTERS: dict[tuple, object] = {}


def default_segmenter(seg_config):
    """The shipped network for ``config.segmentation`` (loaded once per distinct setting)."""
    key = astuple(seg_config)
    if key not in _SEGMENTERS:
        from .segmentation.infer import Segmenter

        _SEGMENTERS[key] = Segmenter.from_config(seg_config)
    return _SEGMENTERS[key]


def voxel_indices(points: np.ndarray, size: float) -> np.ndarray:
    """Sorted indices of one point (the first) per occupied voxel of edge ``size`` (m).

    The three integer voxel coordinates are packed into one int64 key (a 1-D unique is ~10x faster than a
    row-wise one); the same points as ``np.unique(keys, axis=0, return_index=True)``."""
    if len(points) == 0:
        return np.zeros(0, np.int64)
    keys = np.floor(points / size).astype(np.int64)
    keys -= keys.min(axis=0)
    extent = keys.max(axis=0) + 1
    if np.prod(extent.astype(np.float64)) >= 2.0 ** 62:  # cannot pack (absurd extent / size): row-wise
        _, first = np.unique(keys, axis=0, return_index=True)
        return np.sort(first)
    packed = (keys[:, 0] * extent[1] + keys[:, 1]) * extent[2] + keys[:, 2]
    _, first = np.unique(packed, return_index=True)
    return np.sort(first)


def sensor_model(config: Config):
    """The sensors.SensorModel config.sensor.model names, or None (layout read off each cloud)."""
    from .sensors import sensor

    return sensor(config.sensor.model) if config.sensor.model else None


def scan_labels(frame: Frame, config: Config, segmenter=None, grid=None) -> np.ndarray:
    """(N,) uint8 class per point by ``config.segmentation.mode`` (segmentation.infer.segment_frame: network,
    the cloud's labels, or none = every point NONE_MODE_CLASS); ``grid``: the scan's grid.ScanGrid."""
    from .segmentation.infer import segment_frame

    seg = config.segmentation
    if seg.mode == "network" and segmenter is None:
        segmenter = default_segmenter(seg)
    labels, _ = segment_frame(frame, seg, segmenter, grid)
    return np.full(len(frame.points), NONE_MODE_CLASS, np.uint8) if labels is None else labels


@dataclass
class SegmentedScan:
    """A scan after the first per-scan stage: ``frame`` (deskewed and voxel downsampled when configured, sensor
    frame at the stamp), its (N,) uint8 ``labels``, its ``grid`` (grid.ScanGrid of the points as fired), the
    scan's position ``index`` and timings in ms so far."""

    frame: Frame
    labels: np.ndarray
    index: int = -1
    timings: dict[str, float] = field(default_factory=dict)
    grid: ScanGrid | None = None


def segment_scan(frame: Frame, config: Config, segmenter=None, index: int = -1) -> SegmentedScan:
    """Per-scan stage 1: the scan grid (grid.py, from the points as fired), deskew when the frame carries its
    sweep motion (deskew.py), optional voxel downsampling (config.window.voxel_size), then segmentation
    (network, given labels, or none per config.segmentation.mode). Timings in ms under 'grid', 'deskew',
    'voxel', 'segment'. Torch releases the GIL while the network runs, so this stage overlaps stage 2 of the
    previous scan."""
    timings: dict[str, float] = {}
    timer = _Timer(timings)
    labels = frame.labels
    if labels is not None and len(labels) != len(frame.points):
        raise ValueError(f"scan at {frame.stamp}: {len(labels)} labels for {len(frame.points)} points")
    with timer("grid"):
        grid = scan_grid(frame.points, frame.ring, frame.columns, sensor_model(config), frame.layout)
    if frame.motion is not None:
        with timer("deskew"):
            m = frame.motion
            times = frame.time if frame.time is not None else azimuth_times(frame.points, m.period_s, m.stamp_at)
            frame = replace(frame, points=deskew(frame.points, times, m), motion=None)
    if config.window.voxel_size > 0:
        with timer("voxel"):
            keep = voxel_indices(frame.points, config.window.voxel_size)
            frame = replace(frame, points=frame.points[keep], **{k: None if getattr(frame, k) is None
                                                                 else getattr(frame, k)[keep]
                                                                 for k in ("labels", "ring", "intensity", "time")})
            grid = grid.subset(keep)
    with timer("segment"):
        labels = scan_labels(frame, config, segmenter, grid)
    return SegmentedScan(frame, labels, index, timings, grid)


def plane_scan(seg: SegmentedScan, config: Config) -> ProcessedScan:
    """Per-scan stage 2: the planes of a segmented scan (sensor frame) -> the cached ProcessedScan. Timings
    in ms under 'planes' and 'total' (the sum of both stages' steps)."""
    frame, timings = seg.frame, dict(seg.timings)
    with _Timer(timings)("planes"):
        found = planes_mod.detect_planes(frame.points, seg.labels, seg.grid, config.planes, frame=seg.index)
    timings["total"] = float(sum(timings.values()))
    return ProcessedScan(stamp=float(frame.stamp), pose=np.asarray(frame.pose, np.float64), planes=found,
                         points=frame.points if config.metrics.baselines else None, labels=seg.labels,
                         index=seg.index, timings=timings)


def process_scan(frame: Frame, config: Config, segmenter=None, index: int = -1) -> ProcessedScan:
    """Grid, deskew, segment one scan and detect its planes: :func:`segment_scan` then :func:`plane_scan`
    (the Monitor may run the two in separate threads). Sensor frame throughout; timings in ms per step and
    'total'. Points are kept only when config.metrics.baselines."""
    return plane_scan(segment_scan(frame, config, segmenter, index), config)


#: The per-scan work as stages (Monitor runs each in its own worker thread when window.pipelined is on).
SCAN_STAGES = (segment_scan, plane_scan)


@dataclass
class WindowPlanes:
    """All planes of a window as arrays in the WINDOW frame (first scan's sensor frame).

    classes (M,), scans (M,) position of the scan in the window, normals (M, 3), means (M, 3) m,
    scatters (M, 3, 3) m², counts (M,) inliers."""

    classes: np.ndarray
    scans: np.ndarray
    normals: np.ndarray
    means: np.ndarray
    scatters: np.ndarray
    counts: np.ndarray


def window_planes(scans: Sequence[ProcessedScan], poses: np.ndarray) -> WindowPlanes:
    """Put each scan's cached planes into the window frame with (K, 4, 4) window-relative poses: exact, the
    same as Plane.transformed_stats (n -> R n, mean -> R mean + t, scatter -> R S Rᵀ), vectorised."""
    arrays = [s.plane_arrays() for s in scans]
    scan = np.repeat(np.arange(len(scans)), [len(a[0]) for a in arrays])
    cls, normals, means, scatters, counts = (np.concatenate(parts) for parts in zip(*arrays))
    r, t = poses[scan, :3, :3], poses[scan, :3, 3]
    return WindowPlanes(cls, scan, np.einsum("mij,mj->mi", r, normals), np.einsum("mij,mj->mi", r, means) + t,
                        r @ scatters @ np.swapaxes(r, 1, 2), counts)


@dataclass
class PlaneScores:
    """What the window's planes give: pne (nats), cpv (m²), drift rates (deg/s, m/s), counts, and the lowest
    scan agreement (0-1, see WindowResult) with that scan's position in the window (−1 none)."""

    pne: float
    cpv: float
    rot_rate: float
    trans_rate: float
    n_clusters: int
    n_groups: int
    agreement: float = float("nan")
    agreement_scan: int = -1
    rot_rate_se: float = float("nan")
    trans_rate_se: float = float("nan")


def plane_metrics(wp: WindowPlanes, times, config: Config, timings: dict[str, float] | None = None,
                  distance: float = 0.0, poses=None) -> PlaneScores:
    """PNE, CPV and the drift rates of window-frame planes (``times``: (K,) s of the window's scans) with the
    thresholds of config.metrics. ``distance`` (m, the path the window travelled) widens the rate fit's own
    offset gate by metrics.rate_gate_per_m per m, so that a drift larger than CPV's ε still forms groups.
    ``poses`` (K, 4, 4): the scans' sensor poses in the window frame (None: standing still), for the rate
    fit's body-frame drift model (drift_rate.drift_rates)."""
    m = config.metrics
    timer = _Timer(timings if timings is not None else {})
    with timer("pne"):
        clusters = pne_mod.pne_clusters(wp.normals, wp.counts, m.pne_cluster_deg, m.pne_floor_deg)
        pne = pne_mod.pne_of_clusters(clusters)
    with timer("cpv"):
        groups = cpv_mod.coplane_groups(wp.classes, wp.scans, wp.normals, wp.means, wp.scatters, wp.counts,
                                        m.cpv_angle_deg, m.cpv_epsilon)
        cpv = cpv_mod.cpv_of_groups(groups)
        agreement, worst = cpv_mod.window_agreement(groups, wp.scans, wp.counts, len(times))
    with timer("rates"):
        widen = m.rate_gate_per_m * distance if np.isfinite(distance) else 0.0
        rate_groups = groups if widen <= 0 else cpv_mod.coplane_groups(
            wp.classes, wp.scans, wp.normals, wp.means, wp.scatters, wp.counts, m.cpv_angle_deg, m.cpv_epsilon + widen)
        rot, trans, rot_se, trans_se = drift_mod.drift_rates(rate_groups, wp.scans, wp.normals, wp.means, wp.counts,
                                                             times, poses)
    return PlaneScores(pne, cpv, rot, trans, len(clusters), len(groups), agreement, worst, rot_se, trans_se)


def score_window(scans: Sequence[ProcessedScan], config: Config) -> WindowResult:
    """PNE and CPV (and baselines when enabled) of already processed scans, in the first scan's frame.

    Timings in ms under 'transform', 'pne', 'cpv', 'rates' (and 'mme', 'mpv', 'mom'), and 'total'."""
    if not scans:
        raise ValueError("a window needs at least one scan")
    timings: dict[str, float] = {}
    timer = _Timer(timings)
    start = time.perf_counter()
    poses = geometry.relative_to_first(np.stack([s.pose for s in scans]))
    with timer("transform"):
        wp = window_planes(scans, poses)
    stamps = [s.stamp for s in scans]
    speed, turn_rate = window_motion(poses, stamps)
    ps = plane_metrics(wp, stamps, config, timings, distance=speed * (stamps[-1] - stamps[0]), poses=poses)
    result = WindowResult(stamps=stamps, pne=ps.pne, cpv=ps.cpv, n_planes=len(wp.counts), n_groups=ps.n_groups,
                          n_clusters=ps.n_clusters, rot_rate=ps.rot_rate, trans_rate=ps.trans_rate,
                          rot_rate_se=ps.rot_rate_se, trans_rate_se=ps.trans_rate_se,
                          rpe_estimate=drift_mod.rpe_estimate(ps.rot_rate, ps.trans_rate, stamps), speed=speed,
                          turn_rate=turn_rate, agreement=ps.agreement, agreement_scan=ps.agreement_scan,
                          timings=timings)
    if config.metrics.baselines:
        _baselines(result, scans, poses, config)
    timings["total"] = 1000.0 * (time.perf_counter() - start)
    return result


def window_motion(poses: np.ndarray, stamps) -> tuple[float, float]:
    """(speed m/s, turn rate deg/s) of a window: the path length and the summed rotation angle between its
    consecutive (K, 4, 4) poses over its duration; NaN for a single scan."""
    span = float(stamps[-1] - stamps[0]) if len(stamps) > 1 else 0.0
    if span <= 0:
        return float("nan"), float("nan")
    steps = geometry.inverse(poses[:-1]) @ poses[1:]
    distance = float(np.linalg.norm(steps[:, :3, 3], axis=1).sum())
    turn = float(np.degrees(geometry.rotation_angle(steps[:, :3, :3])).sum())
    return distance / span, turn / span


def baselines(clouds: Sequence[np.ndarray], poses: np.ndarray, m) -> dict[str, float]:
    """MME, MPV (one shared neighbourhood pass) and MOM (map-metrics definitions; MOM keeps map-metrics' own
    neighbour threshold, > 3) of sensor-frame clouds and window-relative poses, with 'mme', 'mpv', 'mom' times
    in ms under 't_*'. ``m``: MetricsConfig (radius, min_neighbours, exact_baselines)."""
    from .metrics.mom import mom
    from .metrics.mpv import mme_mpv

    start = time.perf_counter()
    out = dict(zip(("mme", "mpv"), map(float, mme_mpv(clouds, poses, m.radius, m.min_neighbours, m.exact_baselines))))
    out["t_mme"] = out["t_mpv"] = 500.0 * (time.perf_counter() - start)  # one pass, half each
    start = time.perf_counter()
    out["mom"] = float(mom(clouds, poses, m.radius))  # NaN when no three orthogonal planes are found
    out["t_mom"] = 1000.0 * (time.perf_counter() - start)
    return out


def _baselines(result: WindowResult, scans: Sequence[ProcessedScan], poses: np.ndarray, config: Config) -> None:
    """Fill result.mme / mpv / mom and their timings from the scans' kept points."""
    clouds = [s.points for s in scans]
    if any(c is None for c in clouds):
        raise ValueError("baselines need the scans' points: process them with config.metrics.baselines on")
    values = baselines(clouds, poses, config.metrics)
    result.mme, result.mpv, result.mom = values["mme"], values["mpv"], values["mom"]
    result.timings.update({k: values[f"t_{k}"] for k in ("mme", "mpv", "mom")})


def evaluate_window(frames: Sequence[Frame], config: Config | None = None, cache: dict | None = None,
                    segmenter=None) -> WindowResult:
    """The public one-call API: process each frame (once, via ``cache`` keyed by stamp) and score the window.

    ``cache`` (a dict the caller keeps across calls) maps stamp -> ProcessedScan; entries older than this
    window's first stamp are dropped, so a caller sliding forward keeps it bounded. Default config:
    ``Config()`` (network segmentation)."""
    config = config if config is not None else Config()
    if not frames:
        raise ValueError("a window needs at least one frame")
    cache = cache if cache is not None else {}
    scans = []
    for frame in frames:
        key = float(frame.stamp)
        if key not in cache:
            cache[key] = process_scan(frame, config, segmenter)
        scans.append(cache[key])
    first = min(float(f.stamp) for f in frames)
    for key in [k for k in cache if k < first]:
        del cache[key]
    return score_window(scans, config)
