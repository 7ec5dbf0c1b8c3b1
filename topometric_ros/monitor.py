"""Monitor: scans and odometry in, scored and assessed windows out. Used by the ROS node AND by replay.

Clouds and poses arrive separately and out of step. A scan waits (``pending``) until odometry newer than
its stamp + ``window.pose_wait_s`` has arrived, then gets the odometry pose interpolated at its stamp,
times the extrinsic (odometry child frame -> sensor frame); a scan with no odometry within
``window.max_pose_gap_s`` (or still waiting after ``window.pose_timeout_s`` of scan time) is dropped and
counted. Each resolved scan is processed ONCE (voxel downsample, segmentation, planes) and pushed to the
sliding window; a window is scored (``window_fn``) and assessed (health.py) when its last scan is processed.

The per-scan work is a chain of STAGES (default pipeline.SCAN_STAGES: segment_scan | plane_scan, or one
``scan_fn``). ``live=True`` runs each stage in its own worker thread, in scan order, so on two cores the
network (torch releases the GIL) segments scan k+1 while planes are found in scan k and the window is
scored. The input queue is bounded: when the workers fall behind, the OLDEST queued scan is dropped and
counted, so memory stays flat and the feeder never blocks; with ``block=True`` the feeder waits instead, so
every scan is processed (replay as fast as possible). Between stages a short queue (STAGE_QUEUE) makes the
upstream stage wait, never drop. ``live=False`` runs the same stages in the caller's thread, in order. Every
stage is a pure function of its input, so serial, pipelined and blocking-live runs give the same windows.
Bad input (malformed clouds, non-finite points, empty scans, bad quaternions, duplicate or backwards
stamps) is counted in ``counters`` and skipped; nothing raises.
"""
from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from . import geometry
from .cloud import CloudError, bad_beam_note, read_scan
from .config import Config
from .health import Health
from .window import Frame, PoseBuffer, SlidingWindow

#: Every counter the monitor keeps, in report order.
COUNTERS = ("scans_in", "poses_in", "scans_processed", "windows", "dropped_queue_full", "dropped_no_pose",
            "dropped_duplicate", "dropped_bad_scan", "nonfinite_points", "no_return_points", "bad_beam_points",
            "scans_deskewed", "not_deskewed", "dropped_clock", "clock_fault_poses", "bad_poses", "duplicate_poses", "time_resets", "scan_errors",
            "window_errors", "windows_discarded", "scans_missing")
#: Counters that are scans lost before processing.
DROP_COUNTERS = ("dropped_queue_full", "dropped_no_pose", "dropped_duplicate", "dropped_bad_scan", "dropped_clock",
                 "scan_errors")
MAX_CLOUD_NOTES = 8  # distinct cloud notes kept for the reports
OTHER_CLOUD_NOTES = "other notes (more distinct ones than the reports list; the last cloud's is on the console)"
MAX_PENDING = 256  # scans waiting for odometry, hard cap (the timeout normally bounds it far lower)
PERIOD_GAPS = 25  # stamp steps between accepted scans the stream's scan period is the median of
MISSING_GAP = 1.6  # a step this many periods long or more held scans that never came (a missed scan: 2; jitter: < 1.5)
STAGE_QUEUE = 2  # live: items between two per-scan stages (the upstream stage waits when full)


@dataclass
class _Scan:
    """A scan before its pose is known: sensor-frame arrays, header stamp (s), receive wall time, and the
    span (s, relative to the stamp) of the sweep to deskew, None when it is not deskewed."""

    stamp: float
    points: np.ndarray
    labels: np.ndarray | None
    ring: np.ndarray | None
    intensity: np.ndarray | None
    arrived: float
    time: np.ndarray | None = None
    columns: int = 0
    sweep: tuple | None = None  # (t_min, t_max, period_s, stamp_at)
    received: float | None = None  # caller's clock (node or bag time), for the failure check
    layout: str = ""  # driver layout name (sensors.LAYOUTS), '' unknown


def extrinsic_from_list(values: Sequence[float]) -> np.ndarray:
    """[x, y, z, qx, qy, qz, qw] (m, quaternion normalised) -> 4×4 pose. ValueError when malformed."""
    v = np.asarray(values, np.float64)
    if v.shape != (7,) or not np.all(np.isfinite(v)):
        raise ValueError(f"extrinsic must be 7 finite numbers [x y z qx qy qz qw], got {list(values)!r}")
    return geometry.pose_from_quat(v[3:], v[:3])


class ClockWatch:
    """Do clouds and odometry keep one clock? Each stream's offset (header stamp minus receive time, s) is
    steady while they do: network and driver delays move it by milliseconds, a clock fault (a driver or PTP
    resync, a wrong time source) by seconds. A cloud whose offset, taken against the odometry's recent median,
    leaves its own baseline (the median of the last accepted clouds) by ``jump_s`` or more is a clock fault,
    and so is an odometry message whose offset leaves the odometry's median. Without receive times there is
    nothing to compare and nothing is flagged.

    A clock that stays stepped (a PTP or NTP step of the robot's clock, a SLAM restarted on another time base)
    is the odometry's clock from then on: RELEARN odometry messages in a row on one new offset (within
    ``jump_s`` of each other) replace its median. Clouds are then judged against the new clock: when they
    stepped with it they fit again, when they did not they stay clock faults (they cannot be paired)."""

    HISTORY = 25  # messages per stream in the medians
    RELEARN = 20  # odometry messages in a row on one new clock before it is the stream's clock (0.2-1 s)

    def __init__(self, jump_s: float):
        self.jump_s = float(jump_s)
        self._odom: deque = deque(maxlen=self.HISTORY)
        self._cloud: deque = deque(maxlen=self.HISTORY)
        self._stepped: deque = deque(maxlen=self.RELEARN)  # offsets of the odometry faults in a row

    def odometry(self, stamp: float, received: float | None) -> str:
        """'' when the odometry message fits its stream's clock (or RELEARN faults in a row made a new one),
        else the fault."""
        if received is None or self.jump_s <= 0:
            return ""
        offset = stamp - received
        if len(self._odom) >= 3 and abs(offset - np.median(self._odom)) >= self.jump_s:
            self._stepped.append(offset)
            if len(self._stepped) < self.RELEARN or np.ptp(self._stepped) >= self.jump_s:
                return (f"clock fault: odometry stamps jumped {offset - np.median(self._odom):+.2f} s against their "
                        "receive times")
            self._odom.clear()  # the step stayed: the stream's clock from now on
            self._odom.extend(self._stepped)
        else:
            self._odom.append(offset)
        self._stepped.clear()
        return ""

    def lead(self) -> float:
        """s the cloud stamps run ahead of the odometry's against their receive times (the median of the last
        accepted clouds; NaN before three): about 0 when both stamp at the measurement and arrive soon after."""
        return float(np.median(self._cloud)) if len(self._cloud) >= 3 else float("nan")

    def cloud(self, stamp: float, received: float | None) -> str:
        """'' when the cloud fits the clock the odometry keeps, else the fault (the cloud is not to be used)."""
        if received is None or self.jump_s <= 0 or len(self._odom) < 3:
            return ""
        lead = (stamp - received) - float(np.median(self._odom))  # s the cloud clock runs ahead of the odometry's
        if len(self._cloud) >= 3 and abs(lead - np.median(self._cloud)) >= self.jump_s:
            return f"clock fault: cloud stamps jumped {lead - np.median(self._cloud):+.2f} s against the odometry"
        self._cloud.append(lead)
        return ""


def _clock(stamp: Any, received: float | None) -> float | None:
    """The caller's receive time, else the stamp (s) when it is a finite number, else None."""
    if received is not None:
        return float(received)
    try:
        value = float(stamp)
    except (TypeError, ValueError):
        return None
    return value if np.isfinite(value) else None


def valid_pose(pose: np.ndarray) -> bool:
    """A 4×4 finite rigid transform (orthonormal rotation, det > 0, within 1e-6)."""
    pose = np.asarray(pose, np.float64)
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        return False
    r = pose[:3, :3]
    return bool(np.abs(r.T @ r - np.eye(3)).max() < 1e-6 and np.linalg.det(r) > 0)


class StaticTransforms:
    """/tf_static transforms (child -> parent) and chains between frames; no TF library needed."""

    def __init__(self) -> None:
        self._parent: dict[str, tuple[str, np.ndarray]] = {}

    def add_message(self, msg: Any) -> int:
        """Store every transform of a tf2_msgs/TFMessage; returns how many were valid."""
        n = 0
        for tf in msg.transforms:
            r, t = tf.transform.rotation, tf.transform.translation
            try:
                pose = geometry.pose_from_quat([r.x, r.y, r.z, r.w], [t.x, t.y, t.z])
            except ValueError:
                continue
            if np.all(np.isfinite(pose)):
                self._parent[tf.child_frame_id.lstrip("/")] = (tf.header.frame_id.lstrip("/"), pose)
                n += 1
        return n

    def links(self) -> list[str]:
        """Every stored transform as "parent -> child"."""
        return [f"{parent} -> {child}" for child, (parent, _) in list(self._parent.items())]  # a snapshot: the
        # node reads it from worker threads while its executor adds transforms

    def lookup(self, parent: str, child: str) -> np.ndarray | None:
        """4×4 child-to-parent pose along stored transforms, None when the frames are not connected upward."""
        parent, child = parent.lstrip("/"), child.lstrip("/")
        pose, frame = np.eye(4), child
        for _ in range(64):
            if frame == parent:
                return pose
            if frame not in self._parent:
                return None
            frame, step = self._parent[frame]
            pose = step @ pose
        return None

    def between(self, frame: str, other: str) -> np.ndarray | None:
        """4×4 pose of ``other`` in ``frame`` through their nearest common ancestor (siblings too), None when
        the two frames share no ancestor."""
        ancestor, seen = other.lstrip("/"), set()
        for _ in range(64):
            up = self.lookup(ancestor, frame)
            if up is not None:
                return geometry.inverse(up) @ self.lookup(ancestor, other)
            if ancestor in seen or ancestor not in self._parent:
                return None
            seen.add(ancestor)
            ancestor = self._parent[ancestor][0]
        return None


class Monitor:
    """The drift monitor. Feed ``add_cloud``/``add_scan`` and ``add_odometry``/``add_pose`` in any order.

    scan_fn(frame, config, segmenter, index) -> ProcessedScan and window_fn(scans, config) -> WindowResult
    default to pipeline's stages and pipeline.score_window. ``stages`` splits scan_fn: the first is called
    as scan_fn is, each later one as stage(previous output, config), the last returns the ProcessedScan.
    ``on_window(result, scans)`` is called for every completed window (in the last stage's thread when
    live); ``results`` keeps the last ``keep_results`` WindowResults (about 16 KB each) for callers without it.
    Use as a context manager, or call ``close``.
    """

    def __init__(self, config: Config | None = None, scan_fn: Callable | None = None,
                 window_fn: Callable | None = None, segmenter: Any = None, live: bool = False,
                 on_window: Callable | None = None, keep_results: int = 1000, block: bool = False,
                 stages: Sequence[Callable] | None = None):
        from . import pipeline

        self.config = config or Config()
        w = self.config.window
        if scan_fn is not None and stages is not None:
            raise ValueError("give scan_fn (one per-scan function) or stages (a split of it), not both")
        if stages is None:  # the default work is split in two stages unless window.pipelined is off
            stages = (scan_fn,) if scan_fn else pipeline.SCAN_STAGES if w.pipelined else (pipeline.process_scan,)
        if not stages:
            raise ValueError("stages must hold at least one per-scan function")
        self.stages = tuple(stages)
        self.window_fn = window_fn or pipeline.score_window
        self.segmenter = segmenter
        self.live = live
        self.block = block  # live: a full queue makes the feeder wait instead of dropping (replay)
        self.on_window = on_window
        self.health = Health(self.config.health)
        self.poses = PoseBuffer(w.pose_horizon_s)
        self.window = SlidingWindow(w.size, w.step, w.duration_s)
        self.model = pipeline.sensor_model(self.config)  # sensors.SensorModel or None (layout read off each cloud)
        self.layout = ""  # driver layout of the last cloud (sensors.LAYOUTS name, "" unknown)
        self.last_note = ""  # why the last cloud's fields or points were not all used (an unusable time field, bad beams)
        self.cloud_notes: dict[str, int] = {}  # clouds per such note (the first MAX_CLOUD_NOTES distinct ones, then
        # OTHER_CLOUD_NOTES)
        self.clock = ClockWatch(self.config.health.clock_jump_s)
        self.clock_fault: tuple[float | None, str] | None = None  # the last clock fault: (receive time, reason)
        self.clock_events: deque = deque(maxlen=1000)  # every clock fault, for the reports
        self.extrinsic = extrinsic_from_list(w.extrinsic)
        self.extrinsic_source = "config"
        self.extrinsic_note = ""  # the extrinsic changed after scans had taken the previous one (a late /tf_static)
        self._posed = 0  # scans given a pose (odometry × extrinsic) so far
        self.static_tf = StaticTransforms()
        self.results: deque = deque(maxlen=keep_results)
        self.last_error = ""
        self.last_error_of: dict[str, str] = {}  # counter -> the last reason counted under it
        self.last_scan_received: float | None = None  # clock/bag time of the last scan (for STALE)
        self.last_pose_received: float | None = None
        # failure check (caller's clock): receive time of the newest scan processed end to end, and of the first
        # scan that failed after it (None while the newest outcome is a success)
        self.last_processed: float | None = None
        self.failing_since: float | None = None
        self._received_of: dict[int, float | None] = {}  # scan index -> receive time, while in the stages
        self._counts = dict.fromkeys(COUNTERS, 0)
        self._lock = threading.Lock()
        self._pending: deque[_Scan] = deque()
        self._last_scan_stamp: float | None = None
        self._steps: deque = deque(maxlen=PERIOD_GAPS)  # s between consecutive clouds accepted in a row
        self._accepted_at = -1  # scans_in when the last scan was accepted
        self._reset_to: tuple[str, float] | None = None  # the last time reset: (stream, stamp it went back to)
        self._odom_child = ""
        self.sensor_frame = ""  # frame_id of the clouds (the sensor frame)
        self.map_frame = ""  # frame_id of the odometry (the frame poses and planes live in)
        self._index = 0
        # live: queue i feeds stage i's thread; queue 0 is the bounded input queue (drop-oldest or block), the
        # queues between stages hold STAGE_QUEUE items and make the upstream stage wait (nothing lost there)
        self._queues: list[deque] = [deque() for _ in self.stages]
        self._queue = self._queues[0]
        self._cond = threading.Condition(self._lock)
        self._busy = [False] * len(self.stages)
        self.stage_cpu_s = [0.0] * len(self.stages)  # CPU time (s) of each stage's thread, window scoring in the last
        self._stop = False
        self._threads: list[threading.Thread] = []
        if live:
            for i in range(len(self.stages)):
                self._threads.append(threading.Thread(target=self._worker, args=(i,), daemon=True,
                                                      name=f"topometric-stage{i}"))
                self._threads[-1].start()

    # ---------------------------------------------------------------- counters
    def count(self, name: str, n: int = 1) -> None:
        with self._lock:
            self._counts[name] = self._counts.get(name, 0) + n

    @property
    def counters(self) -> dict[str, int]:
        """A snapshot of every counter, plus ``dropped_scans`` (all scans lost before processing)."""
        with self._lock:
            out = dict(self._counts)
        out["dropped_scans"] = sum(out[k] for k in DROP_COUNTERS)
        out["dropped_windows"] = out["windows_discarded"] + out["window_errors"]
        return out

    @property
    def queue_length(self) -> int:
        """Scans in the input queue (bounded by window.queue_size)."""
        with self._lock:
            return len(self._queue)

    @property
    def in_flight(self) -> int:
        """Scans queued or being processed in any stage (bounded by queue_size + stages × (STAGE_QUEUE + 1))."""
        with self._lock:
            return sum(map(len, self._queues)) + sum(self._busy)

    @property
    def pending_length(self) -> int:
        """Scans waiting for odometry at (or after) their stamps."""
        return len(self._pending)

    def _error(self, counter: str, message: str, received: float | None = None) -> None:
        """Count a lost scan (or window) and keep its reason; with its receive time it is a failure."""
        self.count(counter)
        self.last_error = self.last_error_of[counter] = message
        if received is not None:
            with self._lock:
                if self.failing_since is None:
                    self.failing_since = received

    def _succeeded(self, received: float | None) -> None:
        if received is not None:
            with self._lock:
                self.last_processed = received if self.last_processed is None else max(self.last_processed, received)
                self.failing_since = None

    # ---------------------------------------------------------------- inputs: messages
    def add_cloud(self, msg: Any, received: float | None = None) -> bool:
        """A sensor_msgs/PointCloud2 of any driver layout (rosbags or rclpy). Malformed clouds are counted,
        never raised; points without a return or with a bad beam id are dropped and counted."""
        model = self.model
        try:
            scan = read_scan(msg, model.beams if model is not None else 0)
        except (CloudError, AttributeError, TypeError, ValueError) as e:
            self.count("scans_in")
            if received is not None:  # a scan did arrive: input has not stopped, it fails (see failing)
                self.last_scan_received = float(received)
            self._error("dropped_bad_scan", f"malformed cloud: {e}", received)
            return False
        if scan.frame_id and scan.frame_id != self.sensor_frame:
            self.sensor_frame = scan.frame_id
            self._resolve_extrinsic()
        self.count("nonfinite_points", scan.dropped.get("nonfinite", 0))
        self.count("no_return_points", scan.dropped.get("no_return", 0))
        self.count("bad_beam_points", scan.dropped.get("bad_beam", 0))
        self.last_note = "; ".join(filter(None, [*scan.notes, bad_beam_note(scan.dropped.get("bad_beam", 0), model)]))
        for note in scan.notes:  # past MAX_CLOUD_NOTES distinct notes, the clouds are still counted
            key = note if note in self.cloud_notes or len(self.cloud_notes) < MAX_CLOUD_NOTES else OTHER_CLOUD_NOTES
            self.cloud_notes[key] = self.cloud_notes.get(key, 0) + 1
        self.layout = scan.layout or self.layout
        extra = {"labels": scan.labels, "ring": scan.beam, "intensity": scan.intensity, "time": scan.time}
        return self._accept(scan.stamp, scan.points, extra, received, finite=True, columns=scan.columns,
                            layout=scan.layout)

    def _sweep(self, time: np.ndarray | None, layout: str) -> tuple | None:
        """(t_min, t_max, period_s, stamp_at) of the sweep to deskew, or None (deskew.sweep_to_deskew)."""
        from .deskew import sweep_to_deskew

        return sweep_to_deskew(time, layout, self.model, self.config.sensor.deskew, self.config.sensor.rate_hz)

    def add_odometry(self, msg: Any, received: float | None = None) -> bool:
        """A nav_msgs/Odometry (pose of its child frame in its parent frame). Bad quaternions are counted."""
        from .bag import odometry_pose

        try:
            stamp, pose = odometry_pose(msg)
        except (ValueError, AttributeError, TypeError) as e:
            self.count("poses_in")
            self._error("bad_poses", f"bad odometry: {e}")
            return False
        self.map_frame = str(getattr(msg.header, "frame_id", "")) or self.map_frame
        child = str(getattr(msg, "child_frame_id", ""))
        if child and child != self._odom_child:
            self._odom_child = child
            self._resolve_extrinsic()
        return self.add_pose(stamp, pose, received)

    def add_tf_static(self, msg: Any) -> None:
        """A tf2_msgs/TFMessage from /tf_static: the extrinsic comes from it when it links the frames."""
        self.static_tf.add_message(msg)
        self._resolve_extrinsic()

    @property
    def extrinsic_gap(self) -> str:
        """Why window.extrinsic stands although the odometry's child frame is not the cloud frame: no /tf_static
        chain links them ('' when one does, when the two frames are one, or before both are known)."""
        child, sensor = self._odom_child.lstrip("/"), self.sensor_frame.lstrip("/")
        if self.extrinsic_source != "config" or not child or not sensor or child == sensor:
            return ""
        held = self.static_tf.links()
        tf = (f"/tf_static holds {', '.join(held[:6])}{', ...' if len(held) > 6 else ''}" if held
              else "no /tf_static came")
        if np.allclose(self.extrinsic, np.eye(4)):
            return (f"no /tf_static chain links the odometry's child frame {child} to the cloud frame {sensor} "
                    f"({tf}): the identity is used (window.extrinsic); if {sensor} is not at {child}, every "
                    "window is judged with that error: set window.extrinsic or record the transform")
        return f"no /tf_static chain links {child} to {sensor} ({tf}): window.extrinsic is used"

    def _resolve_extrinsic(self) -> None:
        """The sensor's pose in the odometry's child frame from /tf_static, whichever of the two hangs below the
        other or both below a common frame (odometry of an IMU beside the LiDAR under base_link)."""
        if self._odom_child and self.sensor_frame:
            pose = self.static_tf.between(self._odom_child, self.sensor_frame)
            if pose is None:
                return
            if self._posed and not np.allclose(pose, self.extrinsic, atol=1e-9):
                self.extrinsic_note = (f"extrinsic changed after {self._posed} scans ({self.extrinsic_source} -> "
                                       f"/tf_static): a window spanning the change mixes the two")
            self.extrinsic, self.extrinsic_source = pose, "tf_static"

    # ---------------------------------------------------------------- inputs: arrays
    def add_pose(self, stamp: float, pose: np.ndarray, received: float | None = None) -> bool:
        """Odometry pose (4×4, odometry child frame -> map) at ``stamp`` s."""
        self.count("poses_in")
        if not np.isfinite(stamp) or not valid_pose(pose):
            self._error("bad_poses", f"pose at {stamp} is not a finite rigid transform")
            return False
        fault = self.clock.odometry(float(stamp), received)
        if fault:
            self._clock_fault("clock_fault_poses", fault, received)
            return False
        self.last_pose_received = float(stamp if received is None else received)
        status = self.poses.add(stamp, pose)
        if status == "duplicate":
            self.count("duplicate_poses")
            return False
        if status == "backwards":
            self._time_reset(f"odometry stamp went backwards to {stamp:.3f}", self.last_pose_received, "odometry",
                             float(stamp))
        self._resolve_pending()
        return True

    def add_scan(self, stamp: float, points: np.ndarray, labels: np.ndarray | None = None,
                 ring: np.ndarray | None = None, intensity: np.ndarray | None = None,
                 received: float | None = None, time: np.ndarray | None = None) -> bool:
        """One scan: (N, 3) sensor-frame points (m) and optional per-point arrays (``time``: s relative to the
        stamp, for deskewing), header stamp (s).

        Non-finite points are removed (counted); an empty, malformed, duplicate scan is dropped (counted).
        Returns True when the scan was accepted (it may still wait for odometry)."""
        extra = {"labels": labels, "ring": ring, "intensity": intensity, "time": time}
        return self._accept(stamp, points, extra, received, finite=False)

    def _accept(self, stamp, points, extra: dict, received, finite: bool, columns: int = 0,
                layout: str = "") -> bool:
        self.count("scans_in")
        clock = _clock(stamp, received)
        if clock is not None:  # a scan arrived, even if it fails below (failing, not STALE)
            self.last_scan_received = clock
        scan = self._checked_scan(stamp, points, extra, finite, clock)
        if scan is None:
            return False
        fault = self.clock.cloud(scan.stamp, received)
        if fault:  # a cloud on another clock would get another moment's pose: drift that is not there
            self._clock_fault("dropped_clock", fault, received)
            return False
        scan.columns, scan.sweep, scan.layout = columns, self._sweep(scan.time, layout), layout
        if self._last_scan_stamp is not None and scan.stamp <= self._last_scan_stamp:
            if scan.stamp == self._last_scan_stamp:
                self._error("dropped_duplicate", f"duplicate scan stamp {stamp:.3f}", clock)
                return False
            self._time_reset(f"scan stamp went backwards to {stamp:.3f}", clock, "scans", scan.stamp)
            self._steps.clear()
        elif self._last_scan_stamp is not None and self._accepted_at == self._counts["scans_in"] - 1:
            self._count_missing(scan.stamp - self._last_scan_stamp)
        self._last_scan_stamp, self._accepted_at = scan.stamp, self._counts["scans_in"]
        self._pending.append(scan)
        while len(self._pending) > MAX_PENDING:
            lost = self._pending.popleft()
            self._error("dropped_no_pose", "too many scans waiting for odometry", lost.received)
        self._resolve_pending()
        return True

    def _count_missing(self, step: float) -> None:
        """Scans that never arrived, by the stamps: a step of k scan periods (k >= MISSING_GAP; the period the
        median of the last PERIOD_GAPS steps between clouds accepted one after the other) held k − 1 of them.
        Steps over a cloud left out for any reason are not judged (that cloud is counted where it failed)."""
        if len(self._steps) >= 3:
            period = float(np.median(self._steps))
            if period > 0 and step >= MISSING_GAP * period:
                self.count("scans_missing", int(round(step / period)) - 1)
                return
        self._steps.append(step)

    def _clock_fault(self, counter: str, message: str, received: float | None) -> None:
        """A message on another clock: counted and dropped; ``clock_fault`` keeps (receive time, reason) for
        the periodic check and the reports, which say it apart from drift."""
        self.count(counter)
        self.last_error = message
        self.clock_fault = (received, message)
        self.clock_events.append(self.clock_fault)

    def _checked_scan(self, stamp, points, extra: dict, finite: bool, received: float | None) -> _Scan | None:
        """The scan with non-finite points removed (skipped when ``finite``: already filtered), or None."""
        try:
            stamp = float(stamp)
            pts = np.asarray(points)
            if pts.ndim != 2 or pts.shape[1] != 3 or not np.issubdtype(pts.dtype, np.number):
                raise ValueError(f"points must be (N, 3) numbers, got shape {pts.shape} {pts.dtype}")
            if not np.isfinite(stamp):
                raise ValueError(f"scan stamp {stamp} is not finite")
            for name, a in extra.items():
                if a is not None and len(a) != len(pts):
                    raise ValueError(f"{name} has {len(a)} entries for {len(pts)} points")
        except (ValueError, TypeError) as e:
            self._error("dropped_bad_scan", f"malformed scan: {e}", received)
            return None
        keep = None if finite else np.isfinite(pts).all(axis=1)
        if keep is not None and not keep.all():
            self.count("nonfinite_points", int((~keep).sum()))
            pts = pts[keep]
            extra = {k: None if a is None else np.asarray(a)[keep] for k, a in extra.items()}
        if len(pts) == 0:
            self._error("dropped_bad_scan", f"empty scan at {stamp:.3f}", received)
            return None
        if extra["time"] is not None:
            t = np.asarray(extra["time"])
            extra["time"] = t if t.dtype.kind == "f" else t.astype(np.float64)
            if not np.isfinite(extra["time"]).all():  # as cloud.read_scan: the field is not used
                extra["time"], self.last_note = None, "per-point times hold non-finite values; not used"
        return _Scan(stamp, pts.astype(np.float32, copy=False), extra["labels"], extra["ring"], extra["intensity"],
                     time.perf_counter(), extra["time"], received=received)

    def _time_reset(self, why: str, now: float | None, stream: str, stamp: float) -> None:
        """Time jumped back (bag loop, sim time reset): forget waiting scans; the window restarts itself.
        Failure-check times later than ``now`` (the receive clock went back too) are forgotten. One reset is
        counted when both streams go back to about the same time (within pose_timeout_s): one loop."""
        last, self._reset_to = self._reset_to, (stream, stamp)
        if last is not None and last[0] != stream and abs(stamp - last[1]) <= self.config.window.pose_timeout_s:
            self._reset_to = None  # the other stream of the same loop
        else:
            self.count("time_resets")
        self.last_error = why
        with self._lock:
            if now is not None and self.last_processed is not None and self.last_processed > now:
                self.last_processed = None
            if now is not None and self.failing_since is not None and self.failing_since > now:
                self.failing_since = None
        if self._pending:
            self.count("dropped_no_pose", len(self._pending))
            self._pending.clear()
        self.health.reset_clock()

    def _resolve_pending(self, final: bool = False) -> None:
        w = self.config.window
        newest = self.poses.newest
        while self._pending:
            scan = self._pending[0]
            after = max(scan.sweep[1], 0.0) if scan.sweep else 0.0  # odometry must cover the sweep's end
            ready = final or (newest is not None and newest >= scan.stamp + after + w.pose_wait_s)
            expired = self._last_scan_stamp - scan.stamp > w.pose_timeout_s
            if not (ready or expired):
                return
            self._pending.popleft()
            pose = self.poses.lookup(scan.stamp, w.max_pose_gap_s)
            if pose is None:
                self._error("dropped_no_pose", f"no odometry within {w.max_pose_gap_s} s of scan {scan.stamp:.3f}",
                            scan.received)
                continue
            self._posed += 1
            frame = Frame(scan.points, pose @ self.extrinsic, scan.stamp, scan.labels, scan.ring, scan.intensity,
                          scan.time, scan.columns, self._motion(scan), scan.layout)
            self._submit(frame, scan.arrived, scan.received)

    def _motion(self, scan: _Scan):
        """The sensor's motion over the scan's sweep from the odometry (deskew.sweep_motion; past the newest
        pose, at most one sweep, the last motion continues), None when the scan is not deskewed or the
        odometry does not cover the sweep (counted)."""
        from .deskew import sweep_motion

        if scan.sweep is None:
            return None
        gap = self.config.window.max_pose_gap_s
        period = scan.sweep[2]

        def poses_at(t: np.ndarray):  # odometry that ends inside the sweep is continued to its end
            poses = self.poses.lookup_many(t, gap, extrapolate_s=period)
            return None if poses is None else poses @ self.extrinsic

        motion = sweep_motion(poses_at, scan.stamp, *scan.sweep)
        self.count("scans_deskewed" if motion is not None else "not_deskewed")
        return motion

    # ---------------------------------------------------------------- work
    def _submit(self, frame: Frame, arrived: float, received: float | None = None) -> None:
        index = self._index
        self._index += 1
        with self._lock:
            self._received_of[index] = received
        if not self.live:
            item = (frame, index, arrived, 0.0)
            for stage in range(len(self.stages)):
                item = self._run_stage(stage, item)
                if item is None:
                    return
            return
        with self._cond:
            size = max(1, self.config.window.queue_size)
            if self.block:
                self._cond.wait_for(lambda: len(self._queue) < size)
            elif len(self._queue) >= size:
                self._received_of.pop(self._queue.popleft()[1], None)  # lost to load, not to a failure
                self._counts["dropped_queue_full"] += 1
            self._queue.append((frame, index, arrived, 0.0))
            self._cond.notify_all()

    def _worker(self, stage: int) -> None:
        """Thread of one stage: take from its queue in order, run, hand on (waiting while the next is full)."""
        queue, last = self._queues[stage], stage == len(self.stages) - 1
        upstream = self._threads[stage - 1] if stage else None

        def finished() -> bool:  # stopping and nothing more can arrive
            return self._stop and (upstream is None or not upstream.is_alive())

        while True:
            with self._cond:
                while not queue and not finished():
                    self._cond.wait(0.1)  # timed: an upstream thread's exit does not notify
                if not queue:
                    self._cond.notify_all()
                    return
                item = queue.popleft()
                self._busy[stage] = True
                self._cond.notify_all()
            try:
                out = self._run_stage(stage, item)
                if out is not None and not last:
                    with self._cond:
                        nxt = self._queues[stage + 1]
                        self._cond.wait_for(lambda: len(nxt) < STAGE_QUEUE)
                        nxt.append(out)
            except Exception as e:  # noqa: BLE001 - a dead stage thread would stall the feeder and every later scan
                self._error("scan_errors", f"scan {item[1]}: internal error: {type(e).__name__}: {e}")
            finally:
                with self._cond:
                    self._busy[stage] = False
                    self._cond.notify_all()

    def _run_stage(self, stage: int, item: tuple) -> tuple | None:
        """One stage of one scan: (data, index, arrived, ms so far) -> the next stage's item, None on error.
        The last stage pushes the ProcessedScan into the window and scores completed windows."""
        data, index, arrived, ms = item
        t0, cpu0 = time.perf_counter(), time.thread_time()
        try:
            return self._stage_step(stage, data, index, arrived, ms, t0)
        finally:
            self.stage_cpu_s[stage] += time.thread_time() - cpu0

    def _stage_step(self, stage: int, data: Any, index: int, arrived: float, ms: float, t0: float) -> tuple | None:
        try:
            if stage == 0:
                out = self.stages[0](data, self.config, self.segmenter, index)
            else:
                out = self.stages[stage](data, self.config)
        except Exception as e:  # noqa: BLE001 - a bad scan must not stop the monitor
            stamp = getattr(data, "stamp", getattr(getattr(data, "frame", None), "stamp", float("nan")))
            self._error("scan_errors", f"scan {stamp:.3f}: {type(e).__name__}: {e}", self._pop_received(index))
            return None
        ms += 1000 * (time.perf_counter() - t0)
        if stage < len(self.stages) - 1:
            return out, index, arrived, ms
        self._finish(out, ms, arrived, self._pop_received(index))
        return None

    def _pop_received(self, index: int) -> float | None:
        with self._lock:
            return self._received_of.pop(index, None)

    def _finish(self, scan: Any, ms: float, arrived: float, received: float | None = None) -> None:
        """A processed scan: count it, push it into the window, score the window when it completes; a success
        for the failure check unless its window failed."""
        scan.timings["monitor"] = ms  # ms, the per-scan stages' compute time (queue waits excluded)
        self.count("scans_processed")
        discarded = self.window.discarded
        scans = self.window.push(scan, scan.stamp)
        if self.window.discarded > discarded:
            self.count("windows_discarded", self.window.discarded - discarded)
        if scans is None or self._score(scans, arrived, received):
            self._succeeded(received)

    def _score(self, scans: list, arrived: float, received: float | None = None) -> bool:
        """Score and assess a completed window; False when scoring failed (counted)."""
        t0 = time.perf_counter()
        try:
            result = self.window_fn(scans, self.config)
        except Exception as e:  # noqa: BLE001
            self._error("window_errors", f"window at {scans[-1].stamp:.3f}: {type(e).__name__}: {e}", received)
            return False
        now = time.perf_counter()
        result.timings["window"] = 1000 * (now - t0)  # ms, scoring this window
        for key in sorted({k for s in scans for k in s.timings}):  # ms, per-scan steps summed over the window
            result.timings[f"scans_{key}"] = float(sum(s.timings.get(key, 0.0) for s in scans))
        result.timings["latency"] = 1000 * (now - arrived)  # ms, last scan's arrival -> window result
        self.health.assess(result)
        self.count("windows")
        self.results.append(result)
        if self.on_window is not None:
            try:
                self.on_window(result, scans)
            except Exception as e:  # noqa: BLE001 - a failing consumer must not stop the worker
                self.last_error = f"on_window: {type(e).__name__}: {e}"
        return True

    # ---------------------------------------------------------------- control
    def flush(self, timeout: float | None = None) -> bool:
        """Resolve every waiting scan with the odometry there is, then wait until the worker is idle.
        Returns False if ``timeout`` (s) passed first."""
        self._resolve_pending(final=True)
        if not self.live:
            return True
        with self._cond:
            return self._cond.wait_for(lambda: not any(self._queues) and not any(self._busy), timeout)

    def release_waiting(self, now: float) -> int:
        """Scans still waiting for odometry when none has arrived for health.stale_after_s before ``now`` (the
        receive clock) will not get it: resolve them with the odometry there is, as at the end of a bag
        (processed where it covers them, deskewed with the last motion continued over at most one sweep; else
        dropped and counted). Returns how many were waiting. Call it from the thread that adds the input."""
        waiting = len(self._pending)
        last = self.last_pose_received
        if waiting and last is not None and now - last > self.config.health.stale_after_s:
            self._resolve_pending(final=True)
            return waiting
        return 0

    def stale(self, now: float) -> tuple[str, str] | None:
        """(STALE, reason) when no scan or no odometry arrived for health.stale_after_s before ``now``
        (clock or bag time, the same clock as ``received``), else None."""
        return self.health.stale(now, self.last_scan_received, self.last_pose_received)

    def failing(self, now: float) -> tuple[str, str] | None:
        """(ERROR, reason) when scans arrive but every one since the last success failed for
        health.fail_after_s before ``now`` (the caller's clock, as ``received``), else None."""
        with self._lock:
            since, last = self.failing_since, self.last_processed
        return self.health.failing(now, since, last, self.last_error, self.counters)

    def clock_status(self, now: float) -> tuple[str, str] | None:
        """("ERROR", reason) while a clock fault was seen within health.stale_after_s before ``now`` (the
        receive clock), else None: its own status, apart from the map-consistency one."""
        if self.clock_fault is None or self.clock_fault[0] is None:
            return None
        if now - self.clock_fault[0] > self.config.health.stale_after_s:
            return None
        return "ERROR", self.clock_fault[1]

    def check(self, now: float) -> tuple[str, str] | None:
        """What the periodic check reports at ``now``: STALE (input stopped; with the failure reason when scans
        fail too), else ERROR (every scan fails), else None (the windows speak)."""
        stale, failing = self.stale(now), self.failing(now)
        if stale and failing:  # e.g. odometry stopped and the scans cannot find poses: say both
            return stale[0], f"{stale[1]}; {failing[1]}"
        return stale or failing

    def close(self, drain: bool = True) -> None:
        """Stop the worker (after the queued work when ``drain``)."""
        if not self._threads:
            return
        with self._cond:
            if not drain:
                for queue in self._queues:
                    queue.clear()
            self._stop = True
            self._cond.notify_all()
        for thread in self._threads:
            thread.join()
        self._threads = []

    def __enter__(self) -> "Monitor":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def warm_up(config: Config, segmenter: Any = None) -> tuple[float, int]:
    """Run three synthetic scans of a box room through a Monitor of ``config`` (windows of 2 scans), so that
    the compiled kernels (numba compiles them on the first start after an install, then loads them from its
    cache) and the network's export for the image shape of sensor.model (else a VLP-32C) are ready before
    live data arrives. Returns (seconds it took, windows scored)."""
    from dataclasses import replace

    from . import bag, cloud, pipeline, sensors

    start = time.perf_counter()
    model = pipeline.sensor_model(config) or sensors.sensor("VLP-32C")
    types = cloud.rosbags_types(bag.typestore())
    small = replace(config, window=replace(config.window, size=2, step=0))
    monitor = Monitor(small, segmenter=segmenter)
    try:
        for k in range(7):  # odometry every 0.05 s, the sensor creeping along x
            monitor.add_odometry(bag.make_odometry(0.05 * k, geometry.make_pose(np.eye(3), [0.01 * k, 0, 0])))
        for k in range(3):
            monitor.add_cloud(cloud.make_cloud(_box_room(model), 0.1 * k, "warm_up", types))
        monitor.flush()
    finally:
        monitor.close()
    return time.perf_counter() - start, monitor.counters["windows"]


def _box_room(model) -> dict[str, np.ndarray]:
    """Fields (x y z intensity ring time label) of one sweep of ``model`` (sensors.SensorModel) in a 12 x 10 x
    3 m box room, the sensor 1.2 m above its floor (sensor frame, m; labels floor, wall, ceiling for
    segmentation.mode labels); a non-repetitive pattern: 20,000 rays spread over its field of view, no ring."""
    from . import classes as C

    rng = np.random.default_rng(0)
    if model.pattern == "non_repetitive":
        n = model.points_per_scan or 20_000
        el = np.radians(rng.uniform(*model.fov_deg, n))
        az = rng.uniform(-np.pi, np.pi, n)
        ring = None
    else:
        el, az = np.meshgrid(np.radians(model.elevation_deg), np.linspace(-np.pi, np.pi, model.columns, endpoint=False))
        el, az = el.ravel(), az.ravel()
        ring = np.tile(np.arange(len(model.elevation_deg)), model.columns).astype(np.uint16)
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], 1)
    walls = np.array([6.0, 5.0, 1.8]), np.array([-6.0, -5.0, -1.2])  # upper and lower bounds per axis
    with np.errstate(divide="ignore"):
        hits = np.where(d > 0, walls[0] / d, np.where(d < 0, walls[1] / d, np.inf))
    reach, side = hits.min(axis=1), hits.argmin(axis=1)  # side 2: floor or ceiling
    pts = (d * reach[:, None]).astype(np.float32)
    label = np.where(side < 2, C.WALL, np.where(d[:, 2] > 0, C.CEILING, C.FLOOR)).astype(np.uint8)
    fields = {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2], "intensity": np.full(len(pts), 50, np.float32),
              "time": ((az + np.pi) / (2 * np.pi) * model.period_s).astype(np.float32), "label": label}
    if ring is not None:
        fields["ring"] = ring
    return fields
