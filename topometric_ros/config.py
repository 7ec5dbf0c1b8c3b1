"""Configuration: the one place every tunable lives, with its default and unit.

Sections are dataclasses; ``load_config`` reads a YAML file that is either a plain nested mapping or a
ROS 2 parameter file (``<node>: ros__parameters: {...}``), so config/topometric.yaml serves the node and
the replay alike. Unknown keys are errors (a typo must not silently fall back to a default). The node
declares one ROS parameter per leaf, named ``section.field``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, is_dataclass, replace
from pathlib import Path
from typing import Any, Mapping

from .sensors import SENSORS


@dataclass
class WindowConfig:
    """Sliding window of scans and the pose lookup (window.py, monitor.py)."""

    size: int = 0  # scans per window, 2 or more; 0 = automatic: the scans of duration_s at the stream's own scan rate (10 at 10 Hz; the alarms are calibrated on 1 s windows); the paper: 5, 10, 15
    duration_s: float = 1.0  # s of scans an automatic window (size 0) holds (1 s: 10 scans at 10 Hz), its size set once from the first 3 scans' stamps (up to 6 when uneven)
    step: int = 0  # scans between window starts; 0 = size (the paper's choice)
    pose_wait_s: float = 0.1  # a scan waits until odometry newer than its stamp + this arrives
    max_pose_gap_s: float = 0.5  # a scan with an odometry pose before or after it farther than this (s) is dropped (never interpolated across an odometry gap)
    queue_size: int = 8  # scans waiting for the worker; when full the oldest is dropped
    pipelined: bool = True  # live: per-scan work in two worker threads (segmentation | planes + window), overlapping on 2 cores
    voxel_size: float = 0.0  # m, voxel downsample per scan before segmentation (0 = off)
    pose_timeout_s: float = 2.0  # s of scan time a scan may wait for odometry before it is dropped
    pose_horizon_s: float = 30.0  # s of odometry kept for the lookup
    extrinsic: list = field(default_factory=lambda: [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])  # odom child -> sensor: x y z (m) qx qy qz qw; /tf_static wins when it has it

    def setting(self) -> int | str:
        """The window size as configured, for reports: scans, or "automatic (1 s)"."""
        return self.size or f"automatic ({self.duration_s:g} s)"


@dataclass
class SensorConfig:
    """The LiDAR (sensors.py, grid.py) and motion compensation (deskew.py)."""

    model: str = ""  # a sensors.SENSORS name (VLP-16, OS1-128, XT32, Mid-360, ...); "" = read the layout off each cloud
    deskew: str = "auto"  # auto: per-point times, else azimuth times for a known spinning driver | on: also unknown sensors | off
    rate_hz: float = 0.0  # Hz, sweeps per second for azimuth-derived times; 0 = the model's, else 10


@dataclass
class SegmentationConfig:
    """Which labels reach plane detection (segmentation/)."""

    mode: str = "network"  # network | labels (the cloud's label field) | none (every point static)
    weights: str = ""  # path to weights; "" = the shipped ones
    device: str = "cpu"  # cpu | cuda
    threads: int = 1  # CPU threads for inference (torch and ONNX Runtime)
    backend: str = "onnxruntime"  # CPU runtime: onnxruntime (exported in memory from the checked weights) | eager (PyTorch; also the fallback without onnxruntime)
    precision: str = "auto"  # onnxruntime network: auto (int8 on an x86 CPU with VNNI or AVX2, else float32) | int8 | float32; int8 runs the net's body in 8-bit integers, calibrated on simulated scans (segmentation time −15 to −30 %, mIoU within −0.4 to +0.4 of float32)
    min_confidence: float = 0.0  # network points below this softmax probability (with passes > 1: the mean over the passes) become "other" (0 = keep all)
    passes: int = 1  # network passes per scan, probabilities averaged: 1 | 2 (+ the mirror image) | 3 (+ mirror and a half-fold azimuth shift; about +0.7 mIoU at 3x the network time: offline replays, audits)
    max_beams: int = 0  # most beams the network sees (0 = all): a sensor with more has every k-th beam segmented (k = ceil(beams / max_beams)), the beams between take their nearest segmented neighbour's label (about 1/k of the network's time)
    knn: int = 3  # k-nearest-neighbour vote after the network (RangeNet++): each point takes the majority label of the k points nearest to it in 3D, itself included, in a 3 x 5 cell window of the scan grid (0 = off; 3: +0.35-0.72 mIoU)
    knn_distance: float = 0.5  # m, neighbours this far or farther do not vote
    floor_band: float = 0.04  # m; after the kNN vote, a floor-labelled point more than this above the scan's floor plane (at most 0.3 m) and above the floor within 1 m of it takes the label of its nearest non-floor neighbours (chair and desk feet; 0 = off; unseen layout: +0.08-0.33 mIoU and floor IoU +0.04-0.5 on spinning sensors, Mid-360 +0.8 and +3.7)
    object_gap: float = 0.2  # m; desk and chair points in neighbouring grid cells less than this apart form one object, which takes its commonest label when that holds >= 60 % of its points (0 = off; desk and chair labels only, so planes and alarms are unchanged; unseen layout: +0.14-0.88 mIoU on spinning sensors, Mid-360 -0.5)
    floor_snap: float = 0.02  # m; last, non-repetitive scans (Mid-360) only: other, wall, desk and chair points within this of the scan's floor plane become floor (0 = off; validation layout: Mid-360 floor IoU 88.5 -> 93.4, mIoU +1.0; spinning sensors lose floor IoU with it, so they never get it)


@dataclass
class PlaneConfig:
    """Per-scan plane detection per static class (planes.py)."""

    detector: str = "ring"  # ring (fast, uses the scan structure) | open3d (detect_planar_patches)
    min_points: int = 50  # smallest plane kept
    min_width: float = 0.02  # m, RMS spread of a plane's inliers across its long axis; narrower = a line, dropped
    max_sample_points: int = 256  # inlier points kept per plane for display (stats use all inliers)
    inlier_distance: float = 0.05  # m, largest point-to-plane distance of an inlier
    normal_angle_deg: float = 10.0  # deg, largest angle between normals of parts of one plane
    merge_distance: float = 0.06  # m, largest offset between parts of one plane (each centroid to the other plane)
    merge_gap: float = 0.3  # m, coplanar wall/pillar parts farther apart than this stay separate planes
    merge_floor_ceiling: bool = True  # coplanar floor (ceiling) parts are one plane whatever the gap
    merge_across_gaps: bool = True  # coplanar wall/pillar parts too (gaps behind occluders); openings split again
    opening_width: float = 0.5  # m, a wider see-through gap (door) near a wall's foot splits it; 0 = never
    opening_band: float = 1.0  # m, height above a wall's lowest inlier searched for openings
    opening_min_points: int = 5  # rays through the gap needed to call it an opening
    opening_through: float = 0.2  # ... and at least this fraction of the gap's rays (others hit an occluder)
    # ring detector: tiles of the scan grid (grid.py), sized for a 32-beam, 1800-column grid and scaled to others
    tile_rings: int = 4  # grid rows per tile per 32 beams
    tile_columns: int = 6  # azimuth cells per tile per 1800 columns
    tile_levels: int = 4  # quadtree levels: tiles of 1×1 up to 2^(levels-1) × 2^(levels-1) base tiles
    tile_min_points: int = 8  # fewer points of a class in a tile: the tile gives no plane seed
    tile_max_rms: float = 0.02  # m, RMS point-to-plane distance of a planar tile
    tile_min_flatness: float = 1.5  # a tile's smaller in-plane spread over its RMS off-plane (lines are no seeds)
    tile_angle_deg: float = 20.0  # deg, largest normal angle between neighbouring tiles grown into one segment
    # open3d detector: PointCloud.detect_planar_patches (Araújo & Oliveira 2020)
    o3d_knn: int = 30  # neighbours for normal estimation and the detector's search
    o3d_normal_variance_deg: float = 60.0  # detector's normal_variance_threshold_deg
    o3d_coplanarity_deg: float = 75.0  # detector's coplanarity_deg
    o3d_outlier_ratio: float = 0.75  # detector's outlier_ratio


@dataclass
class MetricsConfig:
    """PNE, CPV and the MME/MPV/MOM baselines (metrics/)."""

    baselines: bool = False  # also compute MME, MPV, MOM (slower)
    pne_cluster_deg: float = 15.0  # deg, half-angle of a PNE normal cluster around its heaviest normal
    pne_floor_deg: float = 0.1  # deg, floor on the PNE tangent spread (a perfect cluster stays finite)
    cpv_angle_deg: float = 10.0  # deg, largest angle between normals of co-planar planes
    cpv_epsilon: float = 0.3  # m, largest |D2 - D1| of co-planar planes (paper Eq. 10)
    rate_gate_per_m: float = 0.0  # m per m the window travelled, added to cpv_epsilon for the drift-rate fit's own co-plane groups (0 = it uses CPV's)
    radius: float = 1.0  # m, neighbourhood radius of MME/MPV/MOM
    min_neighbours: int = 5  # a point counts when it has more than this many neighbours
    exact_baselines: bool = False  # exact MME/MPV (every point) instead of the fast approximation


@dataclass
class HealthConfig:
    """Drift alarms (health.py)."""

    stale_after_s: float = 5.0  # no input for this long (bag/sim time aware) -> STALE
    clock_jump_s: float = 0.5  # s, a cloud or odometry stamp this far off its stream's clock is a clock fault (reported apart, not as drift; 0 = off)
    fail_after_s: float = 1.0  # s, scans arrive but every one fails (bad layout, no pose, ...) for this long -> ERROR with the reason
    baseline_windows: int = 10  # windows that form the robust baseline (median/MAD) before sigma alarms start
    baseline_history: int = 50  # most recent OK windows the rolling baseline keeps
    warn_sigma: float = 6.0  # robust z above the baseline median -> WARN (`topometric alarms --calibrate` when the calibration split was floor plans 7, 9, 11-14)
    error_sigma: float = 8.0  # robust z above the baseline median -> ERROR
    warn_persist: int = 2  # WARN needs z >= warn_sigma in this many of the last persist_windows windows (1 = at once)
    persist_windows: int = 2  # windows the persistence rule looks back over (this one included)
    pne_min_sigma: float = 0.3  # nats, floor of the PNE baseline spread (quiet sites; dev bags: 0.23-0.39 drift-free)
    cpv_min_sigma: float = 0.5  # floor of the ln(CPV) baseline spread (CPV is a variance: compared on a log scale)
    pne_warn: float = 0.0  # nats, absolute PNE limit -> WARN (0 = off; PNE is usually negative)
    pne_error: float = 0.0  # nats, absolute PNE limit -> ERROR (0 = off)
    cpv_warn: float = 0.0  # m², absolute CPV limit -> WARN (0 = off)
    cpv_error: float = 0.0  # m², absolute CPV limit -> ERROR (0 = off)
    rate_limits: str = "relative"  # relative: floor + a share of the motion (KITTI-like), floor learned per run | absolute: the *_rate_warn/_error below
    rot_floor: float = 0.5  # deg/s, rotation drift allowed standing still (relative limits; raised per run by the learned noise floor)
    rot_per_m: float = 0.05  # deg per m travelled, added to the rotation limit (relative limits)
    rot_per_deg: float = 0.01  # deg per deg turned, added to the rotation limit (relative limits)
    trans_floor: float = 0.04  # m/s, translation drift allowed standing still (relative limits; raised per run by the learned noise floor)
    trans_per_m: float = 0.0125  # m per m travelled (a fraction of the distance), added to the translation limit (relative limits)
    trans_per_deg: float = 0.0005  # m per deg turned, added to the translation limit (relative limits; chosen by `topometric alarms --calibrate-rates --grid trans_per_deg=...` on the calibration split)
    error_factor: float = 2.0  # ERROR at this multiple of a rate's WARN limit (relative limits)
    rate_persist: int = 2  # a drift rate between its WARN and ERROR limits alarms once it was above WARN in this many of the last persist_windows windows (1 = at once; relative limits only); at ERROR at once
    rate_sigma: float = 1.75  # a drift rate is judged by its lower bound rate − rate_sigma × its standard error (metrics/drift_rate.py: each scan's planes one sample), so that one scan's pose noise does not read as drift (0 = the rate itself)
    noise_warn: float = 1.5  # a drift rate's standard error (the poses' scan-to-scan scatter) at least this x its WARN limit -> WARN "pose noise" at once (0 = off)
    noise_windows: int = 15  # windows that learn the run's noise floor of the rates; meanwhile the floors are noise_max_factor x theirs
    noise_quantile: float = 0.75  # quantile of the learning windows' rates (above the motion share) the floor is learned from
    noise_margin: float = 1.0  # learned floor = this x that quantile
    noise_max_factor: float = 2.0  # a learned floor is at most this x the configured one (keeps drift detectable)
    rot_rate_warn: float = 0.6  # deg/s, absolute rotation drift limit -> WARN at once (rate_limits absolute; 0 = off)
    rot_rate_error: float = 1.2  # deg/s -> ERROR (rate_limits absolute; 0 = off)
    trans_rate_warn: float = 0.05  # m/s, absolute translation drift limit -> WARN at once (rate_limits absolute; 0 = off)
    trans_rate_error: float = 0.1  # m/s -> ERROR (rate_limits absolute; 0 = off)
    min_planes: int = 3  # fewer planes than this in a window -> WARN (metrics unreliable)
    agreement_warn: float = 0.4  # a scan whose plane inliers another scan sees in the same place fall below this share -> WARN at once (a pose jump, lost track; 0 = off)


@dataclass
class Config:
    window: WindowConfig = field(default_factory=WindowConfig)
    sensor: SensorConfig = field(default_factory=SensorConfig)
    segmentation: SegmentationConfig = field(default_factory=SegmentationConfig)
    planes: PlaneConfig = field(default_factory=PlaneConfig)
    metrics: MetricsConfig = field(default_factory=MetricsConfig)
    health: HealthConfig = field(default_factory=HealthConfig)


#: Keys of config/topometric.yaml that belong to the ROS node (topics, QoS, ...), not to Config: skipped here.
NODE_PARAMETERS = ("points_topic", "odom_topic", "tf_static_topic", "points_qos", "odom_qos", "hardware_id",
                   "publish_markers", "scan_rate_min_hz", "scan_rate_max_hz", "latency_warn_s", "latency_error_s",
                   "diagnostic_updater.period", "diagnostic_updater.use_fqn", "use_sim_time")
#: Leaves that take one of a few strings.
CHOICES = {"segmentation.mode": ("network", "labels", "none"), "segmentation.device": ("cpu", "cuda"),
           "sensor.deskew": ("auto", "on", "off"), "sensor.model": ("", *SENSORS),
           "health.rate_limits": ("relative", "absolute"),
           "segmentation.backend": ("onnxruntime", "eager"), "segmentation.precision": ("auto", "int8", "float32"),
           "planes.detector": ("ring", "open3d")}

#: Ranges of numeric config leaves: name -> (min, max), both included (checked by apply, so by load_config
#: and the node alike). Others are unbounded.
RANGES: dict[str, tuple[float, float]] = {
    # window
    "window.size": (0, 200), "window.duration_s": (0.05, 60.0), "window.step": (0, 200),
    "window.pose_wait_s": (0.0, 10.0),
    "window.max_pose_gap_s": (0.001, 10.0), "window.queue_size": (1, 1000), "window.voxel_size": (0.0, 5.0),
    "window.pose_timeout_s": (0.0, 60.0), "window.pose_horizon_s": (1.0, 3600.0),
    # sensor
    "sensor.rate_hz": (0.0, 100.0),
    # segmentation
    "segmentation.threads": (1, 64), "segmentation.min_confidence": (0.0, 1.0), "segmentation.passes": (1, 3),
    "segmentation.max_beams": (0, 256), "segmentation.knn": (0, 15), "segmentation.knn_distance": (0.0, 100.0),
    "segmentation.floor_band": (0.0, 0.2), "segmentation.object_gap": (0.0, 1.0),
    "segmentation.floor_snap": (0.0, 0.2),
    # planes
    "planes.min_points": (3, 1_000_000), "planes.max_sample_points": (3, 1_000_000),
    "planes.min_width": (0.0, 10.0), "planes.inlier_distance": (0.001, 1.0), "planes.normal_angle_deg": (0.1, 90.0),
    "planes.merge_distance": (0.0, 1.0), "planes.merge_gap": (0.0, 100.0), "planes.opening_width": (0.0, 100.0),
    "planes.opening_band": (0.0, 100.0), "planes.opening_through": (0.0, 1.0), "planes.tile_max_rms": (0.0001, 1.0),
    "planes.tile_min_flatness": (0.0, 1000.0), "planes.tile_angle_deg": (0.1, 90.0),
    "planes.o3d_normal_variance_deg": (0.1, 90.0), "planes.o3d_coplanarity_deg": (0.1, 90.0),
    "planes.o3d_outlier_ratio": (0.0, 1.0), "planes.opening_min_points": (1, 100_000), "planes.tile_rings": (1, 64),
    "planes.tile_columns": (1, 512), "planes.tile_levels": (1, 8), "planes.tile_min_points": (3, 100_000),
    "planes.o3d_knn": (3, 1000),
    # metrics
    "metrics.pne_cluster_deg": (0.1, 90.0), "metrics.pne_floor_deg": (0.001, 10.0), "metrics.cpv_angle_deg": (0.1, 90.0),
    "metrics.cpv_epsilon": (0.001, 10.0),
    "metrics.radius": (0.01, 10.0), "metrics.min_neighbours": (0, 10_000), "metrics.rate_gate_per_m": (0.0, 1.0),
    # health
    "health.stale_after_s": (0.1, 3600.0), "health.fail_after_s": (0.0, 3600.0),
    "health.clock_jump_s": (0.0, 3600.0), "health.baseline_windows": (1, 100_000),
    "health.baseline_history": (1, 1_000_000), "health.warn_sigma": (0.0, 1000.0),
    "health.error_sigma": (0.0, 1000.0), "health.warn_persist": (1, 1000), "health.persist_windows": (1, 1000),
    "health.pne_min_sigma": (0.0, 100.0), "health.cpv_min_sigma": (0.0, 100.0), "health.pne_warn": (-1e3, 1e3),
    "health.pne_error": (-1e3, 1e3), "health.cpv_warn": (0.0, 1e6), "health.cpv_error": (0.0, 1e6),
    "health.rot_rate_warn": (0.0, 360.0), "health.rot_rate_error": (0.0, 360.0),
    "health.trans_rate_warn": (0.0, 100.0), "health.trans_rate_error": (0.0, 100.0),
    "health.rot_floor": (0.0, 360.0), "health.rot_per_m": (0.0, 100.0), "health.rot_per_deg": (0.0, 10.0),
    "health.trans_floor": (0.0, 100.0), "health.trans_per_m": (0.0, 10.0), "health.trans_per_deg": (0.0, 1.0), "health.error_factor": (1.0, 100.0),
    "health.rate_persist": (1, 1000), "health.rate_sigma": (0.0, 10.0), "health.noise_warn": (0.0, 1000.0),
    "health.noise_windows": (0, 100_000), "health.noise_quantile": (0.0, 1.0), "health.noise_margin": (0.0, 100.0),
    "health.noise_max_factor": (1.0, 1000.0), "health.min_planes": (0, 1_000_000),
    "health.agreement_warn": (0.0, 1.0),
}

#: Values inside a leaf's range that it still refuses, with why (checked by apply and the node alike).
REFUSED: dict[str, dict[Any, str]] = {
    "window.size": {1: "a window needs 2 scans or more; 0 = automatic (window.duration_s of scans)"},
}


def _unwrap_ros(doc: Mapping[str, Any]) -> Mapping[str, Any]:
    """A ROS 2 parameter file {node: {ros__parameters: {...}}} -> its parameters; the one top key may be any
    node name or pattern ('topometric_monitor', '/robot1/topometric_monitor', '/**')."""
    if len(doc) == 1:
        (inner,) = doc.values()
        if isinstance(inner, Mapping) and "ros__parameters" in inner:
            return inner["ros__parameters"]
    return doc


def _nest(flat: Mapping[str, Any]) -> dict:
    """{'window.size': 5} -> {'window': {'size': 5}}; nested mappings pass through."""
    out: dict = {}
    for key, value in flat.items():
        head, dot, rest = str(key).partition(".")
        if dot:
            out.setdefault(head, {})[rest] = value
        elif isinstance(value, Mapping):
            out.setdefault(head, {}).update(value)
        else:
            out[head] = value
    return out


def apply(obj: Any, values: Mapping[str, Any], where: str = "") -> Any:
    """A copy of dataclass ``obj`` with ``values`` (nested or dotted keys) applied; ValueError on unknown keys
    or values of the wrong type."""
    known = {f.name: f for f in fields(obj)}
    changes = {}
    for key, value in _nest(values).items():
        name = f"{where}{key}"
        if key not in known:
            raise ValueError(f"unknown config key {name!r}; known: {', '.join(where + k for k in known)}")
        current = getattr(obj, key)
        if is_dataclass(current):
            if not isinstance(value, Mapping):
                raise ValueError(f"config key {name!r} is a section; give a mapping")
            changes[key] = apply(current, value, f"{name}.")
        else:
            changes[key] = _coerce(name, current, value)
            if name in CHOICES and changes[key] not in CHOICES[name]:
                choices = ", ".join(c or repr(c) for c in CHOICES[name])  # '' shows as ''
                raise ValueError(f"config key {name!r} must be one of {choices}, got {value!r}")
            if name in RANGES and not RANGES[name][0] <= changes[key] <= RANGES[name][1]:
                raise ValueError(f"config key {name!r} = {value!r} is out of range "
                                 f"[{RANGES[name][0]:g}, {RANGES[name][1]:g}]")
            if name == "window.extrinsic":
                changes[key] = _extrinsic(name, changes[key])
            if name in REFUSED and changes[key] in REFUSED[name]:
                raise ValueError(f"config key {name!r} = {value!r}: {REFUSED[name][changes[key]]}")
    return replace(obj, **changes)


def _extrinsic(name: str, value: list) -> list[float]:
    """``value`` as the 7 floats [x y z qx qy qz qw] (m; a quaternion of non-zero norm); ValueError naming the
    key otherwise."""
    numbers = [float(v) for v in value if isinstance(v, (int, float)) and not isinstance(v, bool)]
    if len(numbers) != 7 or len(value) != 7 or not all(math.isfinite(v) for v in numbers):
        raise ValueError(f"config key {name!r} must be 7 finite numbers [x, y, z, qx, qy, qz, qw] (m; a quaternion), "
                         f"got {value!r}")
    if math.hypot(*numbers[3:]) < 1e-9:
        raise ValueError(f"config key {name!r}: the quaternion {numbers[3:]} has zero norm (identity: 0, 0, 0, 1)")
    return numbers


def _number(value: Any) -> float | None:
    """``value`` as a float when it is a number, or a string that reads as one (YAML 1.1 leaves 1e-3 a string),
    else None."""
    try:
        if isinstance(value, (int, float)):
            return float(value)
        return float(value) if isinstance(value, str) else None
    except (ValueError, OverflowError):  # not a number; an int past the float range
        return None


def _coerce(name: str, current: Any, value: Any) -> Any:
    kind = type(current)
    if kind is str and isinstance(value, bool) and {"on", "off"} <= set(CHOICES.get(name, ())):
        return "on" if value else "off"  # YAML 1.1 reads a bare on / off as a boolean
    if kind is bool:
        if isinstance(value, bool):
            return value
    elif kind is float and not isinstance(value, bool) and (number := _number(value)) is not None:
        if not math.isfinite(number):
            raise ValueError(f"config key {name!r} must be a finite number, got {value!r}")
        return number
    elif isinstance(value, kind) and not isinstance(value, bool):
        return value
    raise ValueError(f"config key {name!r} must be {kind.__name__}, got {value!r}")


def flatten(obj: Any, prefix: str = "") -> dict[str, Any]:
    """{'window.size': 5, ...}: every leaf of a config, named as the node declares it."""
    out = {}
    for f in fields(obj):
        value = getattr(obj, f.name)
        if is_dataclass(value):
            out.update(flatten(value, f"{prefix}{f.name}."))
        else:
            out[f"{prefix}{f.name}"] = value
    return out


def load_config(path: str | Path | None = None, overrides: Mapping[str, Any] | None = None) -> Config:
    """Defaults, then the YAML file at ``path`` (plain or ROS 2 parameter file; the node-only keys of
    NODE_PARAMETERS are skipped), then ``overrides`` (nested or dotted keys, e.g. {'window.size': 10})."""
    cfg = Config()
    if path is not None:
        params = read_parameters(path)
        try:
            cfg = apply(cfg, {k: v for k, v in params.items() if k not in NODE_PARAMETERS})
        except ValueError as e:
            raise ValueError(f"{path}: {e}") from None
    if overrides:
        cfg = apply(cfg, overrides)
    return cfg


def read_parameters(path: str | Path) -> Mapping[str, Any]:
    """The keys of a YAML config file (plain, or a ROS 2 parameter file's ros__parameters), unchecked."""
    import yaml

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"config file not found: {p}")
    try:
        doc = yaml.safe_load(p.read_text()) or {}
    except yaml.YAMLError as e:
        raise ValueError(f"{p}: not valid YAML: {' '.join(str(e).split())}") from None
    if not isinstance(doc, Mapping):
        raise ValueError(f"{p}: expected a mapping at the top level")
    return _unwrap_ros(doc)
