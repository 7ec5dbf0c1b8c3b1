"""Simulate a robot run and write it as a rosbag2 bag.

Topics: /points (PointCloud2 in the named sensor's driver layout and frame (sensors.LAYOUTS), plus a uint8
``label`` field with the ground-truth class), /odom (estimated base_link pose, with drift), /odom_gt (ground
truth), /tf_static (base_link -> sensor frame). Each sweep is motion-distorted (every firing at its own time
along the true trajectory) unless ``distortion`` is off; header stamp and per-point time as the driver
writes them. Odometry runs at ``odom_rate`` with stamps offset from the scans', so scans need interpolated
poses. The bag folder also gets ``truth.json``: the settings, the drift episodes and per-class point counts.
"""
from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from .. import bag, classes, geometry
from ..cloud import DATATYPES as DATATYPES_NP, make_layout_cloud, rosbags_types
from ..reports import written_whole
from ..sensors import DEFAULT_SENSOR, SensorModel, sensor
from .drift import (EPISODE_LENGTH_S, EPISODE_WARMUP_S, DriftSpec, OdometryError, estimated_poses, odometry_error,
                    plan_episodes)
from .lidar import Lidar, Scan, firings_per_sweep
from .scenes import make_scene
from .trajectory import random_trajectory

START_TIME = 1_700_000_000.0  # s, bag time of the first scan
#: Version of what the simulator writes for a given SimConfig, kept in truth.json so caches of simulated bags
#: notice a change. 2: the heading turns at a bounded rate (sim/trajectory.py MAX_YAW_RATE_DEG). 3: any
#: sensor in its driver's layout, motion distortion. 4: free space marks every cell a wall overlaps (routes
#: drove through 0.15 m walls that fell between cell centres).
SIM_VERSION = 4
BASE_FRAME, MAP_FRAME = "base_link", "map"


@dataclass
class SimConfig:
    """Everything that determines a simulated bag; the same config gives the same bag."""

    scene: str = "garage"
    layout_seed: int = 0  # floor plan
    seed: int = 0  # trajectory, noise, drift
    frames: int = 600
    rate: float = 5.0  # scans per second
    odom_rate: float = 20.0  # odometry messages per second
    speed: float = 1.2  # m/s
    sensor_height: float = 1.0  # m, base_link -> sensor
    drift: DriftSpec = field(default_factory=DriftSpec)
    storage: str = "mcap"
    sensor: str = DEFAULT_SENSOR  # a sensors.SENSORS name
    distortion: bool = True  # each firing at its own time along the trajectory (False: instantaneous sweeps)
    odometry: str = "ideal"  # the SLAM's everyday error under the drift: ideal (none) | lo (LiDAR-odometry-like)
    clock_jump: tuple = ()  # (at s after the start, offset s, duration s): cloud stamps jump by offset meanwhile
    compress: bool = True  # MCAP chunks zstd-compressed (2-3x smaller bags; every MCAP reader reads them)

    def __post_init__(self) -> None:
        sweeps = sensor(self.sensor).rate_hz
        if self.rate > sweeps:
            raise ValueError(f"rate {self.rate:g} is more scans a second than the {self.sensor} makes (it sweeps "
                             f"{sweeps:g} times a second): one scan per sweep at most")

    @property
    def extrinsic(self) -> np.ndarray:
        """base_link -> sensor, 4×4."""
        return geometry.make_pose(np.eye(3), [0.0, 0.0, self.sensor_height])


def _progress(total: int, desc: str, enabled: bool):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="scan", disable=not enabled, leave=False)


def simulate(cfg: SimConfig, out: str | Path, progress: bool = True) -> dict:
    """Write the bag for ``cfg`` to directory ``out`` (must not exist). Returns the summary (also in truth.json)."""
    t_start = time.perf_counter()
    out = Path(out)
    rng = np.random.default_rng(cfg.seed)
    scene = make_scene(cfg.scene, cfg.layout_seed)
    duration = cfg.frames / cfg.rate + 1.0
    traj = random_trajectory(scene, duration, cfg.speed, START_TIME - 0.5, rng)
    odom_t = START_TIME - 0.4 + 0.013 + np.arange(int((duration - 0.2) * cfg.odom_rate)) / cfg.odom_rate
    gt_odom = traj.poses_at(odom_t)
    episodes = plan_episodes(START_TIME, START_TIME + cfg.frames / cfg.rate, cfg.drift, rng)
    est_odom = estimated_poses(odom_t, _everyday(cfg, scene, odom_t, gt_odom), cfg.drift, episodes, rng)
    scan_t = START_TIME + np.arange(cfg.frames) / cfg.rate
    model = sensor(cfg.sensor)
    lidar = Lidar(scene, model)
    types = rosbags_types(bag.typestore())
    counts = np.zeros(classes.NUM_CLASSES, np.int64)
    n_points, sensor_poses = [], []
    frame_id = model.layout.frame_id
    k = 0  # next odometry message
    with bag.BagWriter(out, storage=cfg.storage, compress=cfg.compress) as w, _progress(cfg.frames, f"simulate {cfg.scene}", progress) as bar:
        w.write("/tf_static", scan_t[0] - 0.5, bag.make_tf(scan_t[0] - 0.5, cfg.extrinsic, BASE_FRAME, frame_id))
        for i, stamp in enumerate(scan_t):
            scan, t0 = _sweep(lidar, traj, cfg, float(stamp), i, rng)
            received = t0 + model.period_s + 0.02  # the driver publishes after the sweep
            while k < len(odom_t) and odom_t[k] <= received:  # odometry up to this scan's receive time
                w.write("/odom", odom_t[k], bag.make_odometry(odom_t[k], est_odom[k], MAP_FRAME, BASE_FRAME))
                w.write("/odom_gt", odom_t[k], bag.make_odometry(odom_t[k], gt_odom[k], MAP_FRAME, BASE_FRAME))
                k += 1
            shift = _clock_shift(cfg, float(stamp))
            w.write("/points", received, driver_cloud(scan, model, float(stamp) + shift, t0 + shift, types))
            hit = np.isfinite(scan.points[:, 0])
            counts += np.bincount(scan.label[hit], minlength=classes.NUM_CLASSES)
            n_points.append(int(hit.sum()))
            sensor_poses.append(traj.poses_at(np.array([stamp]))[0] @ cfg.extrinsic)
            bar.update()
        for j in range(k, len(odom_t)):
            w.write("/odom", odom_t[j], bag.make_odometry(odom_t[j], est_odom[j], MAP_FRAME, BASE_FRAME))
            w.write("/odom_gt", odom_t[j], bag.make_odometry(odom_t[j], gt_odom[j], MAP_FRAME, BASE_FRAME))
    sensor_poses = np.stack(sensor_poses)
    summary = {
        "bag": str(out), "simulator": SIM_VERSION, "config": {**asdict(cfg), "drift": asdict(cfg.drift)},
        "scene_area_m2": round(scene.area, 1), "frames": cfg.frames, "duration_s": cfg.frames / cfg.rate,
        "path_length_m": float(np.linalg.norm(np.diff(sensor_poses[:, :3, 3], axis=0), axis=1).sum()),
        "mean_points_per_scan": float(np.mean(n_points)),
        "class_points": {classes.NAMES[c]: int(n) for c, n in enumerate(counts)},
        "episodes": [e.as_dict() for e in episodes],
        "elapsed_s": round(time.perf_counter() - t_start, 2),
    }
    with written_whole(out / "truth.json") as tmp:
        tmp.write_text(json.dumps(summary, indent=2))
    return summary


def _everyday(cfg: SimConfig, scene, stamps: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Ground truth with the SLAM's everyday error of ``cfg.odometry`` (sim/drift.py odometry_error; its own
    random stream, so the rest of the bag is the same as with ideal odometry)."""
    if cfg.odometry == "ideal":
        return gt
    if cfg.odometry != "lo":
        raise ValueError(f"odometry must be ideal or lo, got {cfg.odometry!r}")
    from .trajectory import free_space

    err = OdometryError()
    space = free_space(scene, resolution=0.4 if scene.area > 2000 else 0.2)
    xy = gt[:-1, :2, 3]
    cell = np.clip(np.rint((xy - space.origin) / space.resolution).astype(int), 0, np.array(space.free.shape[::-1]) - 1)
    narrow = space.clearance[cell[:, 1], cell[:, 0]] < err.corridor_clearance_m
    steps = geometry.inverse(gt[:-1]) @ gt[1:]
    straight = np.degrees(geometry.rotation_angle(steps[:, :3, :3])) / np.diff(stamps) < 5.0
    return odometry_error(stamps, gt, np.random.default_rng([cfg.seed, 7]), err, narrow & straight)


def _clock_shift(cfg: SimConfig, stamp: float) -> float:
    """s added to a cloud's stamps by the simulated clock fault at ``stamp`` (0 outside it)."""
    if not cfg.clock_jump:
        return 0.0
    at, offset, duration = cfg.clock_jump
    return float(offset) if START_TIME + at <= stamp < START_TIME + at + duration else 0.0


def _sweep(lidar: Lidar, traj, cfg: SimConfig, stamp: float, index: int, rng: np.random.Generator
           ) -> tuple[Scan, float]:
    """Sweep ``index`` stamped ``stamp`` (every firing kept, in firing order) and its first firing's time t0:
    the stamp for drivers that stamp the first point, the stamp minus the sweep for those that stamp the last."""
    m = lidar.model
    n = firings_per_sweep(m)
    t_fire = np.arange(n) * (m.period_s / n)
    t0 = stamp - t_fire[-1] if m.layout.stamp == "last" else stamp
    times = t0 + t_fire if cfg.distortion else np.array([stamp])
    poses = traj.poses_at(times) @ cfg.extrinsic
    return lidar.sweep(poses, rng, index, returns_only=False), t0


def driver_cloud(scan: Scan, model: SensorModel, stamp: float, t0: float, types) -> object:
    """The PointCloud2 the model's driver writes for a sweep (every firing, no return = NaN range), plus a
    uint8 ``label`` field (ground truth): layout, organisation, no-return points, ring order, per-point time
    and header stamp as in sensors.LAYOUTS."""
    lay = model.layout
    hit = np.isfinite(scan.points[:, 0])
    t_abs = t0 + scan.time  # s, each firing's time
    pts = scan.points if lay.no_return == "nan" else np.where(hit[:, None], scan.points, 0.0)
    a = {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2], "intensity": scan.intensity,
         "label": np.where(hit, scan.label, 0).astype(np.uint8)}
    if scan.ring is not None:
        a["ring"] = (model.beams - 1 - scan.ring) if lay.ring_top_first else scan.ring
    if lay.name == "velodyne":  # velodyne_pointcloud has no firing-time table for the HDL-64E: time stays 0
        a["time"] = np.zeros(len(t_abs), np.float32) if model.name == "HDL-64E" else (t_abs - stamp).astype(np.float32)
    elif lay.name == "ouster":
        a["t"] = np.rint((t_abs - stamp) * 1e9).astype(np.uint32)
        a["reflectivity"] = np.minimum(scan.intensity, 255).astype(np.uint16)
        a["range"] = np.where(hit, np.rint(np.linalg.norm(np.nan_to_num(scan.points), axis=1) * 1000), 0).astype(np.uint32)
    elif lay.name == "hesai":  # the packet's time (8 columns of 50 us blocks per packet)
        packet = (scan.firing // 8) * 8 * (model.period_s / model.columns)
        a["timestamp"] = t0 + packet
    elif lay.name == "livox":
        a["timestamp"] = t_abs * 1e9
        a["line"] = (scan.firing % 4).astype(np.uint8)
    height = 1
    if lay.organised == "beams x columns":  # row 0 = the top beam, columns in firing order
        order = np.lexsort((scan.firing, model.beams - 1 - scan.ring))
        a, height = {k: v[order] for k, v in a.items()}, model.beams
    elif lay.organised == "firings x beams":  # one row per firing, one column per ring (ascending)
        height = model.columns
    if lay.no_return == "dropped":
        a = {k: v[hit] for k, v in a.items()}
    end = max(off + np.dtype(DATATYPES_NP[dt]).itemsize for _, off, dt in lay.fields)
    fields = (*lay.fields, ("label", end, 2))
    step = max(lay.point_step, end + 1)
    return make_layout_cloud(a, fields, step, stamp, lay.frame_id, types, height, lay.padding, is_dense=False)


#: SimConfig fields that change how a bag is stored, not what it holds.
STORAGE_ONLY = ("compress",)


def bag_identity(truth: dict | None) -> dict | None:
    """What makes a simulated bag what it is (its config and the simulator version), from its truth.json:
    equal identities, equal bags (how it is stored aside)."""
    if truth is None:
        return None
    return {**{k: v for k, v in truth["config"].items() if k not in STORAGE_ONLY}, "simulator": truth.get("simulator", 1)}


def simulate_split(scenes: list[str], out: str | Path, cfg: SimConfig, n_train: int = 2, n_test: int = 1,
                   progress: bool = True) -> list[dict]:
    """Train/test bags per scene (the paper's Table 1): out/train/<scene>_<k> and out/test/<scene>_<k>.

    Trajectories are disjoint: train uses seeds cfg.seed + 0.., test cfg.seed + 1000..; same floor plan.
    """
    out = Path(out)
    summaries = []
    for scene in scenes:
        for split, n, base in (("train", n_train, 0), ("test", n_test, 1000)):
            for k in range(n):
                run = replace(cfg, scene=scene, seed=cfg.seed + base + k)
                summaries.append({"split": split, **simulate(run, out / split / f"{scene}_{k}", progress)})
    return summaries


def format_summary(s: dict) -> str:
    """Human-readable lines for one simulate() summary."""
    total = sum(s["class_points"].values()) or 1
    share = ", ".join(f"{k} {100 * v / total:.1f}%" for k, v in s["class_points"].items())
    lines = [f"bag            {s['bag']}",
             f"scene          {s['config']['scene']} ({s['scene_area_m2']:.0f} m²), {s['frames']} scans "
             f"at {s['config']['rate']} Hz = {s['duration_s']:.1f} s, path {s['path_length_m']:.1f} m",
             f"points/scan    {s['mean_points_per_scan']:.0f}",
             f"classes        {share}",
             f"drift          {s['config']['drift']['mode']} × {s['config']['drift']['scale']} "
             f"({s['config']['drift']['kind']}), {len(s['episodes'])} episode(s)"]
    lines += [f"  episode {i}: {e['start'] - START_TIME:7.1f} s .. {e['end'] - START_TIME:7.1f} s"
              for i, e in enumerate(s["episodes"])]
    drift = s["config"]["drift"]
    if drift["mode"] != "none" and drift["kind"] == "episodes" and not s["episodes"]:
        lines.append(f"  NO EPISODE FITS: episodes start after {EPISODE_WARMUP_S:g} s and last {EPISODE_LENGTH_S[0]:g}-"
                     f"{EPISODE_LENGTH_S[1]:g} s; give more --frames, or --drift-kind noise (drift from the first scan)")
    lines.append(f"elapsed        {s['elapsed_s']:.1f} s")
    return "\n".join(lines)
