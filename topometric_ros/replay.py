"""Replay a rosbag2 bag through the Monitor (the same code the node runs) and write reports.

Outputs in the output folder: ``diagnostics.mcap`` (diagnostic_msgs/DiagnosticArray on /diagnostics,
stamped in bag time; opens in Foxglove and ``ros2 bag``), ``windows.csv`` and ``windows.json`` (every
window's metrics, timings, level, reason, floats at full precision; the JSON is strict, null where a metric is
NaN, and also holds the summary and counters; :func:`load_windows` reads it back with NaN) and
``metrics.png`` (PNE, CPV, drift rates and the RPE estimate over time with alarm bands; the true RPE
when the bag has ground truth).

Rate ``max`` (default) is deterministic: every scan and every window is processed in order (the worker
thread processes while the reader reads on; the reader waits, never drops). ``realtime``
(or a factor such as 2.0) feeds the monitor at bag speed through its live worker thread, as on a robot.
A bag that breaks mid-file (truncated) is reported in the summary; what was processed is still written.
"""
from __future__ import annotations

import json
import shutil
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from . import bag, geometry, storage
from .cloud import bad_beam_note
from .config import Config, flatten
from .health import assessment_fields, diagnostic_array, diagnostic_status, status_name, window_values
from .monitor import MISSING_GAP, Monitor, valid_pose
from .reports import csv_value, remove_reports, write_csv, write_json
from .window import AUTO_PROBE, SlidingWindow

DIAGNOSTICS_TOPIC = "/diagnostics"
DRAIN_POLL_S = 0.2  # s, how often the progress bar moves while the monitor finishes the last scans
#: fields of a window record (windows.json): 2 added the drift rates and rpe_estimate, 3 the joint rate fit, 4 speed,
#: turn rate and per-window rate limits, 5 the true rates as trends over all scans, 6 the scan agreement
RECORD_FORMAT = 6


@dataclass
class ReplayOptions:
    """Topics, speed and reporting of one replay."""

    points_topic: str = ""  # "" = the bag's only PointCloud2 topic, else /points
    odom_topic: str = ""  # "" = the bag's only Odometry topic (besides gt_topic), else /odom
    gt_topic: str = "/odom_gt"  # ground truth for RPE when the bag has it
    tf_static_topic: str = "/tf_static"
    rate: str = "max"  # max | realtime | a speed factor (e.g. "2")
    hardware_id: str = ""  # "" = the cloud's frame_id
    plot: bool = True
    progress: bool = True
    beside: tuple = ()  # more bags read with it, merged in time order (e.g. a sidecar odometry bag)


@dataclass
class ReplayResult:
    out: Path
    windows: list[dict] = field(default_factory=list)
    summary: dict = field(default_factory=dict)


def _speed(rate: str) -> float | None:
    """None for as fast as possible, else the speed factor (1 = real time)."""
    if rate in ("max", "", None):
        return None
    if rate == "realtime":
        return 1.0
    try:
        value = float(rate)
    except ValueError:
        raise ValueError(f"rate must be 'max', 'realtime' or a speed factor, got {rate!r}") from None
    if not value > 0:
        raise ValueError(f"rate factor must be > 0, got {value}")
    return value


# ------------------------------------------------------------------ reading (damaged bags too)
def _one_clock(messages: Iterator[tuple[str, int, Any]]) -> Iterator[tuple[str, int, Any]]:
    """Messages of several recordings merged by header stamp (a sidecar odometry bag): their receive times are
    different clocks, so each topic's are moved by the offset its first message had to its stamp. STALE, the
    odometry's coverage and the clock watch then read one clock, and a topic whose stamps jump later still
    shows the jump."""
    offsets: dict[str, int] = {}
    for topic, t_ns, msg in messages:
        offset = offsets.setdefault(topic, t_ns - bag.message_stamp_ns((topic, t_ns, msg)))
        yield topic, t_ns - offset, msg


def read_bag(path: str | Path, wanted: set[str], log: storage.ReadLog) -> Iterator[tuple[str, int, Any]]:
    """(topic, receive ns, message) of the wanted topics the bag has (others are left out), in time order.
    A damaged bag (a zeroed chunk, a truncated file, no metadata.yaml) gives every message it still holds;
    ``log`` says what was skipped."""
    yield from bag.read_messages(path, sorted(wanted), log=log, strict=False)


# ------------------------------------------------------------------ replay
#: The first columns of every window record (windows.csv's header even when a replay gives no window).
CORE_COLUMNS = ("index", "start", "end", "n_scans", "pne", "cpv", "rot_rate", "trans_rate", "rot_rate_se",
                "trans_rate_se", "rpe_estimate")


class _Recorder:
    """Collects window records and writes the diagnostics bag as windows complete (thread safe)."""

    def __init__(self, out: Path, monitor_ref: list, hardware_id: str):
        self.types = bag.msg_types()
        self.tmp = out / ".diagnostics_bag"
        if self.tmp.exists():
            shutil.rmtree(self.tmp)
        self.writer = bag.BagWriter(self.tmp).__enter__()
        self.lock = threading.Lock()
        self.records: list[dict] = []
        self.poses: list[list] = []  # per window: the scans' (stamp, sensor pose)
        self.clock_faults: list[dict] = []
        self.stales: list[tuple[float, str]] = []  # (bag time s, reason) of each STALE status written
        self.monitor_ref = monitor_ref
        self.hardware_id = hardware_id

    def window(self, result, scans) -> None:
        """Keep a window's record (its first keys are CORE_COLUMNS) and write its /diagnostics status."""
        m = self.monitor_ref[0]
        a = m.health.last
        rec = {"index": len(self.records), "start": result.stamps[0], "end": result.stamps[-1],
               "n_scans": len(scans), "pne": result.pne, "cpv": result.cpv, "rot_rate": result.rot_rate,
               "trans_rate": result.trans_rate, "rot_rate_se": result.rot_rate_se,
               "trans_rate_se": result.trans_rate_se, "rpe_estimate": result.rpe_estimate}
        for name in ("mme", "mpv", "mom"):
            if getattr(result, name) is not None:
                rec[name] = getattr(result, name)
        rec.update(n_planes=result.n_planes, n_groups=result.n_groups, level=result.level, message=result.message)
        rec.update(speed=result.speed, turn_rate=result.turn_rate, agreement=result.agreement,
                   agreement_scan=result.agreement_scan, agreement_stamp=result.agreement_stamp)
        rec.update(assessment_fields(a))
        rec.update({f"ms_{k}": round(float(v), 3) for k, v in result.timings.items()})
        counters = m.counters
        status = diagnostic_status(self.types, result.level, result.message, window_values(result, counters),
                                   hardware_id=self.hardware_id or m.sensor_frame)
        with self.lock:
            self.records.append(rec)
            self.poses.append([(s.stamp, s.pose) for s in scans])
            self.writer.write(DIAGNOSTICS_TOPIC, result.stamps[-1],
                              diagnostic_array(self.types, result.stamps[-1], [status]))

    def stale(self, stamp: float, reason: str, hardware_id: str) -> None:
        status = diagnostic_status(self.types, "STALE", reason, {}, hardware_id=hardware_id)
        with self.lock:
            self.stales.append((stamp, reason))
            self.writer.write(DIAGNOSTICS_TOPIC, stamp, diagnostic_array(self.types, stamp, [status]))

    def stale_notes(self, start: float | None) -> list[str]:
        """One note for the STALE statuses written (how many, the first's time into the bag and reason)."""
        if not self.stales:
            return []
        t, reason = self.stales[0]
        n = len(self.stales)
        return [f"STALE {n} time{'s' * (n > 1)} in diagnostics.mcap, first at {t - (start or t):.1f} s: {reason}"]

    def clock_fault(self, stamp: float, reason: str, hardware_id: str) -> None:
        """A clock fault as its own ERROR status ("<node>: clock"), apart from the map-consistency windows."""
        self.clock_faults.append({"received": stamp, "message": reason})
        status = diagnostic_status(self.types, "ERROR", reason, {}, name=status_name(task="clock"),
                                   hardware_id=hardware_id)
        with self.lock:
            self.writer.write(DIAGNOSTICS_TOPIC, stamp, diagnostic_array(self.types, stamp, [status]))

    def close(self, target: Path) -> None:
        self.writer.__exit__(None, None, None)
        files = list(self.tmp.glob("*.mcap"))
        if target.exists():
            target.unlink()
        if files:
            files[0].replace(target)
        shutil.rmtree(self.tmp, ignore_errors=True)


def replay(bag_path: str | Path, out: str | Path, config: Config | None = None,
           options: ReplayOptions | None = None, scan_fn: Callable | None = None,
           window_fn: Callable | None = None, segmenter: Any = None) -> ReplayResult:
    """Stream the bag through a Monitor and write the reports to ``out``. Never raises for a broken bag:
    a damaged bag gives every scan it still holds (``summary['notes']`` and ``summary['bag_read']`` say what
    was skipped), an error is in ``summary['error']`` and everything processed before it is written; when no
    scan was processed ``summary['no_scans']`` says why."""
    config = config or Config()
    opt = options or ReplayOptions()
    speed = _speed(opt.rate)
    bag.check_bag(bag_path)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    remove_reports(out)  # an earlier replay's: none may pass for this one's (an interrupted run)
    if segmenter is None and scan_fn is None and config.segmentation.mode == "network":
        segmenter = load_segmenter(config)
    ref: list = []
    rec = _Recorder(out, ref, opt.hardware_id)
    # as fast as possible: the worker thread processes every scan in order (the reader waits when it is
    # ahead), so reading and parsing overlap the per-scan work; real time: a live monitor that drops
    monitor = Monitor(config, scan_fn, window_fn, segmenter, live=True, block=speed is None, on_window=rec.window,
                      keep_results=0)  # the recorder keeps every window
    ref.append(monitor)
    notes: list[str] = []
    source = [bag_path, *opt.beside] if opt.beside else bag_path
    opt, topics = _resolve_topics(source, opt, notes)
    feed = _Feed(monitor, rec, opt, speed)
    log, wall0 = storage.ReadLog(), time.perf_counter()
    wanted = {opt.points_topic, opt.odom_topic, opt.gt_topic, opt.tf_static_topic}
    _static_transforms_first(monitor, source, opt.tf_static_topic, topics)
    messages = (_one_clock(bag.read_messages(source, sorted(wanted & set(topics)), log)) if opt.beside
                else read_bag(bag_path, wanted, log))
    try:
        feed.run(messages, topics.get(opt.points_topic, (None, None))[1])
    finally:
        monitor.flush()
        monitor.close()
        rec.close(out / "diagnostics.mcap")
    feed.wall_s = time.perf_counter() - wall0  # reading and processing, up to the last window
    records = rec.records
    if feed.gt_stamps:
        to_sensor = monitor.static_tf.between(feed.gt_frame, monitor.sensor_frame) if feed.gt_frame else None
        if to_sensor is None:
            notes.append(f"ground truth frame {feed.gt_frame or '(none)'} not linked to the sensor frame "
                         f"{monitor.sensor_frame or '(none)'} in /tf_static: compared through the odometry extrinsic")
        _add_rpe(records, rec.poses, np.asarray(feed.gt_stamps), np.stack(feed.gt_poses),
                 monitor.extrinsic if to_sensor is None else to_sensor)
    c = monitor.counters
    notes += [f"{n} cloud{'s' * (n > 1)}: {note}" for note, n in monitor.cloud_notes.items()]
    if c["bad_beam_points"]:
        notes.append(bad_beam_note(c["bad_beam_points"], monitor.model))
    if feed.bad_gt:
        notes.append(f"{feed.bad_gt} ground-truth message{'s' * (feed.bad_gt > 1)} of {opt.gt_topic} left out: "
                     f"no finite rigid transform (RPE uses the others)")
    notes += _loss_notes({**c, "dropped_no_pose": 0} if not c["poses_in"] else c, monitor.last_error_of, opt)
    if c["scans_missing"]:
        n = c["scans_missing"]
        notes.append(f"the cloud stamps show {n} scan{'s' * (n > 1)} missing (steps of {MISSING_GAP:g} scan periods "
                     f"or more between clouds that came one after the other): lost before or by the recording")
    notes += [n for n in (monitor.extrinsic_note, monitor.extrinsic_gap, _clock_lead_note(monitor)) if n]
    notes += feed.coverage_notes(config) + rec.stale_notes(feed.first)
    if c["scans_processed"] and not records:
        notes.append(_why_no_window(c, monitor.window, monitor.last_error))
    notes += _baseline_notes(records, config)
    summary = _summary(bag_path, monitor, records, feed, notes + log.lines(), speed)
    summary.update(topics={t: list(v) for t, v in topics.items()}, bag_read=log.counts(),
                   segmentation=config.segmentation.mode,
                   segmentation_options=network_options(config, getattr(segmenter, "precision", "")),
                   sensor=config.sensor.model or "read off each cloud",
                   layout=monitor.layout, points_topic=opt.points_topic, odom_topic=opt.odom_topic)
    summary["odometry_interval_s"] = feed.odometry_interval()
    summary["odometry_messages"] = len(feed.odometry_times)
    summary["no_scans"] = "" if summary["scans_processed"] else why_no_scans(summary, topics, config)
    summary["notes"] = [n for n in summary["notes"] if n != summary["no_scans"]]  # said once, as the reason
    summary["clock_faults"] = rec.clock_faults
    write_reports(out, records, summary, truth=bag.load_truth(bag_path), plot=opt.plot)
    return ReplayResult(out, records, summary)


class _Feed:
    """The reading loop of a replay: messages to the monitor (paced at ``speed``, None = as fast as the
    monitor takes them), STALE statuses in bag time, ground truth kept for RPE, reading CPU time."""

    def __init__(self, monitor: Monitor, rec: "_Recorder", opt: ReplayOptions, speed: float | None):
        self.monitor, self.rec, self.opt, self.speed = monitor, rec, opt, speed
        self.gt_stamps: list[float] = []
        self.gt_poses: list[np.ndarray] = []
        self.gt_frame = ""  # the ground truth's child frame (its poses are of that frame)
        self.bad_gt = 0  # ground-truth messages left out: no finite rigid transform
        self.n_scans, self.first, self.last = 0, None, None
        self.clouds: list[float | None] = [None, None]  # receive time (s) of the first and last cloud
        self.odometry_times: list[float] = []  # receive time (s) of every odometry message
        self.error, self.wall_s, self.reader_cpu_s = "", 0.0, 0.0  # wall_s: set by replay, flush included
        self._stale = False
        self._levels: Counter = Counter()  # the levels of rec.records[:self._counted], for the progress bar
        self._counted = 0

    def run(self, messages: Iterator[tuple[str, int, Any]], total: int | None) -> None:
        """Feed every message, then wait for the monitor to finish every scan; an exception of the reader ends
        the loop and is kept in ``error``. The bar counts scans done (processed or dropped), not scans read:
        the monitor works behind the reader."""
        from tqdm import tqdm

        wall0, cpu0 = time.perf_counter(), time.thread_time()
        bar = tqdm(total=total, desc="replay", unit="scan", disable=not self.opt.progress, leave=False)
        try:
            for topic, t_ns, msg in messages:
                self._message(topic, t_ns * 1e-9, msg, wall0)
                if topic == self.opt.points_topic:
                    self._show(bar)
        except Exception as e:  # noqa: BLE001 - a broken bag is reported, the work done so far is kept
            self.error = f"{type(e).__name__}: {e}"
        finally:
            self.reader_cpu_s = time.thread_time() - cpu0
            try:
                while not self.monitor.flush(timeout=DRAIN_POLL_S):
                    self._show(bar)
                self._show(bar)
                bar.refresh()
            finally:
                bar.close()

    def _show(self, bar) -> None:
        """The bar at the scans the monitor is done with, the windows and alarms so far beside it."""
        c = self.monitor.counters
        bar.update(c["scans_processed"] + c["dropped_scans"] - bar.n)
        if not bar.disable:
            with self.rec.lock:  # only the windows recorded since the last call: a long bag's bar stays cheap
                new = self.rec.records[self._counted:]
            self._levels.update(r["level"] for r in new)
            self._counted += len(new)
            bar.set_postfix_str(f"windows {self._counted}, WARN {self._levels['WARN']}, "
                                f"ERROR {self._levels['ERROR']}", refresh=False)

    def _message(self, topic: str, t: float, msg: Any, wall0: float) -> None:
        opt, monitor = self.opt, self.monitor
        self.first = t if self.first is None else self.first
        self.last = t
        if self.speed is not None:
            time.sleep(max(0.0, wall0 + (t - self.first) / self.speed - time.perf_counter()))
        if monitor.last_scan_received is not None:
            # the bag's first stale_after_s: a stream not started yet (odometry after the first cloud) is no STALE
            stale = monitor.stale(t) if t - self.first >= monitor.config.health.stale_after_s else None
            if stale and not self._stale:
                self.rec.stale(t, stale[1], opt.hardware_id or monitor.sensor_frame)
            self._stale = bool(stale)
        faults = len(monitor.clock_events)
        self._dispatch(topic, t, msg)
        if len(monitor.clock_events) > faults:
            self.rec.clock_fault(t, monitor.clock_events[-1][1], opt.hardware_id or monitor.sensor_frame)

    def odometry_interval(self) -> float | None:
        """s between odometry messages (the median of the receive times' steps: a dropout does not count as the
        rate), None with fewer than two."""
        times = self.odometry_times
        return float(np.median(np.diff(times))) if len(times) >= 2 else None

    def coverage_notes(self, config: Config) -> list[str]:
        """Where the odometry leaves clouds without poses: it starts or ends more than health.stale_after_s
        from the clouds (receive times), or comes farther apart than window.max_pose_gap_s."""
        (c0, c1), times = self.clouds, self.odometry_times
        if c0 is None or not times:
            return []
        o0, o1 = times[0], times[-1]
        notes, limit = [], config.health.stale_after_s
        if o0 - c0 > limit:
            notes.append(f"the odometry starts {o0 - c0:.1f} s after the clouds: the scans before it are not judged")
        if c1 - o1 > limit:
            notes.append(f"the odometry ends {c1 - o1:.1f} s before the clouds (at {o1 - self.first:.1f} s of "
                         f"{c1 - self.first:.1f} s): the scans after it are not judged")
        gap, every = config.window.max_pose_gap_s, self.odometry_interval()
        if every is not None and every > gap:
            notes.append(_slow_odometry(every, len(times), gap))
        return notes

    def _ground_truth(self, msg: Any) -> None:
        """Keep a ground-truth pose for RPE; one that is no finite rigid transform is counted and left out."""
        try:
            s, pose = bag.odometry_pose(msg)
        except (ValueError, AttributeError, TypeError):
            s, pose = float("nan"), None
        if pose is None or not np.isfinite(s) or not valid_pose(pose):
            self.bad_gt += 1
            return
        self.gt_stamps.append(s)
        self.gt_poses.append(pose)
        self.gt_frame = str(getattr(msg, "child_frame_id", "")) or self.gt_frame

    def _dispatch(self, topic: str, t: float, msg: Any) -> None:
        opt, monitor = self.opt, self.monitor
        if topic == opt.points_topic:
            monitor.add_cloud(msg, received=t)
            self.n_scans += 1
            self.clouds = [self.clouds[0] if self.clouds[0] is not None else t, t]
        elif topic == opt.odom_topic:
            monitor.add_odometry(msg, received=t)
            self.odometry_times.append(t)
        elif topic == opt.gt_topic:
            self._ground_truth(msg)
        elif topic == opt.tf_static_topic:
            monitor.add_tf_static(msg)


def _static_transforms_first(monitor: Monitor, source: Any, topic: str, topics: dict) -> None:
    """The bag's /tf_static before any scan, wherever it was recorded (a recorder started before
    robot_state_publisher, a sidecar bag): a scan's pose must not take one extrinsic and a later scan's another.
    What cannot be read here is read (and counted) with the other messages."""
    if topic not in topics:
        return
    try:
        for _, _, msg in bag.read_messages(source, [topic], storage.ReadLog(), strict=False):
            monitor.add_tf_static(msg)
    except Exception:  # noqa: BLE001 - the main read meets the same damage and reports it
        pass


def _why_no_window(counters: dict, window: SlidingWindow, last_error: str) -> str:
    """Why scans were processed but no window came out: too few for the window (window.size, or an automatic
    window's), or windows lost (counted)."""
    n = counters["scans_processed"]
    if window.size is None and n >= AUTO_PROBE and window.resets:
        return (f"no window from {n} scans: the stream restarted {window.resets} times (stamps not newer than the "
                f"last) before {AUTO_PROBE} scans in a row could set the automatic window's size")
    if window.size is None or n < window.size:
        fix = f"replay with --window-size {n} (or a longer bag)" if n >= 2 else "a window needs at least 2 scans"
        what = f"of {window.describe()}" if window.size else f"({window.describe()})"
        return f"no window: {n} scan{'s' * (n > 1)} processed, fewer than a window {what}; {fix}"
    return (f"no window from {n} scans: {counters['windows_discarded']} discarded, {counters['window_errors']} "
            f"failed; last error: {last_error or 'none'}")


def why_no_scans(summary: dict, topics: dict[str, tuple[str, int]], config: Config) -> str:
    """Why a replay processed no scan, from the bag's topics, the reading and the monitor's counters."""
    c, points, odom = summary["counters"], summary["points_topic"], summary["odom_topic"]
    clouds = _of_type(topics, bag.POINTCLOUD2)
    damaged = bag.unreadable(summary["bag"], points) if points not in topics else ""
    if not clouds:
        return damaged or bag.unreadable_clouds(summary["bag"]) or "the bag has no sensor_msgs/msg/PointCloud2 topic"
    if points not in topics:
        return damaged or (f"PointCloud2 topic {points} is not in the bag (its PointCloud2 topics: "
                           f"{', '.join(clouds)}); name one with --points-topic")
    if topics[points][0] != bag.POINTCLOUD2:
        return f"topic {points} holds {topics[points][0]}, not sensor_msgs/msg/PointCloud2"
    if odom in topics and topics[odom][0] != bag.ODOMETRY:
        return (f"topic {odom} holds {topics[odom][0]}, not {bag.ODOMETRY} (its Odometry topics: "
                f"{', '.join(_of_type(topics, bag.ODOMETRY)) or 'none'}); name one with --odom-topic")
    if summary["scans_read"] == 0:
        return f"no message of {points} could be read" + (f" ({summary['error']})" if summary["error"] else "")
    if c["dropped_bad_scan"] >= summary["scans_read"]:
        return (f"every cloud of {points} ({summary['scans_read']}) was malformed or empty; "
                f"last: {_last(summary, 'dropped_bad_scan')}")
    if c["poses_in"] == 0:
        odoms = _of_type(topics, bag.ODOMETRY)
        where = (f"{odom} is not in the bag" if odom not in topics else f"no message of {odom} could be read")
        tf = [t for t in _of_type(topics, bag.TF_MESSAGE) if not t.endswith("tf_static")]
        if not odoms:
            return (f"no odometry: the bag has no {bag.ODOMETRY} topic"
                    + (f" (its transforms on {', '.join(tf)} are not read as poses)" if tf else "")
                    + f"; the monitor judges the SLAM's poses as {bag.ODOMETRY}: record the SLAM's odometry topic "
                      "with the clouds; `topometric inspect` looks at the clouds alone")
        return (f"no odometry: {where} (its Odometry topics: {', '.join(odoms)}"
                + (f"; its transforms on {', '.join(tf)} are not read as poses" if tf else "")
                + "); the monitor needs the SLAM poses as nav_msgs/msg/Odometry, name the topic with --odom-topic")
    if c["bad_poses"] >= c["poses_in"]:
        return f"every odometry message of {odom} was invalid; last: {_last(summary, 'bad_poses')}"
    if c["scan_errors"]:
        hint = ("; mode 'labels' reads the cloud's own label field (simulated bags): use --segmentation network "
                "(or none) for a real sensor's bag") if config.segmentation.mode == "labels" else ""
        return f"every scan failed in processing; last: {_last(summary, 'scan_errors')}{hint}"
    every = summary.get("odometry_interval_s")
    if c["dropped_no_pose"] and every is not None and every > config.window.max_pose_gap_s:
        return _slow_odometry(every, summary["odometry_messages"], config.window.max_pose_gap_s)
    if c["dropped_no_pose"]:
        return (f"no cloud had odometry within window.max_pose_gap_s = {config.window.max_pose_gap_s} s of its "
                f"stamp (clouds and odometry on different clocks?); last: {_last(summary, 'dropped_no_pose')}")
    return f"no scan was processed; last monitor error: {summary['last_monitor_error'] or 'none'}"


def _last(summary: dict, counter: str) -> str:
    """The last reason the monitor counted under ``counter`` (its last error of any kind when none)."""
    return summary["last_error_of"].get(counter) or summary["last_monitor_error"]


def _slow_odometry(every: float, n: int, gap: float) -> str:
    """The note for odometry that comes farther apart than window.max_pose_gap_s."""
    from .config import RANGES

    top = RANGES["window.max_pose_gap_s"][1]
    fix = (f"`--set window.max_pose_gap_s={1.5 * every:.2g}` interpolates over the gaps" if 1.5 * every <= top else
           f"too sparse to interpolate over (window.max_pose_gap_s goes to {top:g} s)")
    return (f"the odometry comes every {every:.2f} s ({n} messages), farther apart than window.max_pose_gap_s = "
            f"{gap:g} s: scans between two messages get no pose; {fix}")


#: s, odometry this much later than the clouds (against their stamps) is noted: a SLAM's latency is less.
LATE_ODOMETRY_S = 2.0


def _clock_lead_note(monitor: Monitor) -> str:
    """A note when the odometry's stamps sit off the clouds' against their receive times from the start (a
    constant offset is no clock jump, but poses are looked up at the wrong time: drift alarms may be the clock).
    Odometry stamped later than the clouds by health.clock_jump_s is noted (it cannot arrive before its stamp
    unless a clock is off); odometry that arrives later is noted from LATE_ODOMETRY_S (a SLAM's latency)."""
    lead, limit = monitor.clock.lead(), monitor.config.health.clock_jump_s
    if not np.isfinite(lead) or limit <= 0:
        return ""
    if lead <= -limit:
        return (f"the odometry's stamps run {-lead:.2f} s ahead of the clouds' against their receive times: "
                "stamped on another clock, its poses are looked up at the wrong time and the drift alarms may be "
                "that offset")
    if lead >= max(limit, LATE_ODOMETRY_S):
        return (f"the odometry arrives {lead:.2f} s later than the clouds against their stamps: a SLAM that slow, "
                "or odometry stamped on another clock (its poses then looked up at the wrong time, and the drift "
                "alarms that offset)")
    return ""


def _baseline_notes(records: list[dict], config: Config) -> list[str]:
    """When the PNE/CPV baselines never finished learning, or were learned mostly on windows that alarmed."""
    learning = [r for r in records if "learning baseline" in str(r.get("message", ""))]
    if not learning:
        return []
    judged = [r for r in records if np.isfinite(_num(r.get("z_pne"))) or np.isfinite(_num(r.get("z_cpv")))]
    if not judged:
        n = len(learning)
        return [f"the PNE/CPV baselines were still being learned at the bag's end ({n} of the "
                f"{config.health.baseline_windows} windows of health.baseline_windows): PNE and CPV judged by their "
                "absolute limits only, the drift rates as everywhere"]
    alarmed = sum(r["level"] != "OK" for r in learning)
    if 2 * alarmed > len(learning):
        return [f"the PNE/CPV baselines were learned on {len(learning)} windows, {alarmed} of them WARN or ERROR: "
                "their sigma limits are relative to a start that may already have been inconsistent"]
    return []


def _of_type(topics: dict[str, tuple[str, int]], msgtype: str) -> list[str]:
    return sorted(t for t, (kind, _) in topics.items() if kind == msgtype)


def load_segmenter(config: Config):
    """The network (pipeline.default_segmenter, loaded once), or a clear ValueError when it cannot load."""
    from .pipeline import default_segmenter

    try:
        return default_segmenter(config.segmentation)
    except (RuntimeError, ImportError, FileNotFoundError) as e:
        raise ValueError(f"{e}") from None


#: The prefix of a note on input the monitor left out (audit's console repeats them).
LEFT_OUT = "left out: "


def _loss_notes(counters: dict, last_error_of: dict[str, str], opt: ReplayOptions) -> list[str]:
    """A note per kind of bad input the monitor counted and left out (malformed clouds, invalid odometry, scans
    that failed in processing): how many, and the last reason."""
    kinds = (("dropped_bad_scan", f"malformed or empty cloud of {opt.points_topic}",
              f"malformed or empty clouds of {opt.points_topic}"),
             ("bad_poses", f"invalid odometry message of {opt.odom_topic}",
              f"invalid odometry messages of {opt.odom_topic}"),
             ("dropped_no_pose", "scan with no odometry at its stamp", "scans with no odometry at their stamps"),
             ("scan_errors", "scan that failed in processing", "scans that failed in processing"))
    return [f"{LEFT_OUT}{n} {one if n == 1 else many}; last: {last_error_of.get(counter, '')}"
            for counter, one, many in kinds if (n := counters.get(counter, 0))]


def _resolve_topics(path, opt: ReplayOptions, notes: list[str]) -> tuple[ReplayOptions, dict]:
    """The options with the points and odometry topics found in the bag (bag.pick_topic; notes say when a
    topic was picked) and the bag's topics {topic: (type, count)} ({} when they cannot be listed)."""
    from dataclasses import replace as with_

    try:
        topics = bag.topics(path)
    except Exception as e:  # noqa: BLE001 - unlistable: stream with the given (or default) names
        notes.append(f"topics unreadable ({type(e).__name__}: {e})")
        return with_(opt, points_topic=opt.points_topic or "/points", odom_topic=opt.odom_topic or "/odom"), {}
    points, note_p = bag.pick_topic(topics, bag.POINTCLOUD2, opt.points_topic, "/points")
    odom, note_o = bag.pick_topic(topics, bag.ODOMETRY, opt.odom_topic, "/odom", exclude=[opt.gt_topic])
    notes += [n for n in (note_p, note_o) if n]
    if opt.gt_topic and opt.gt_topic == odom:
        notes.append(f"the ground-truth topic {opt.gt_topic} is the odometry topic: it is read as odometry, "
                     "so no RPE")
    elif opt.gt_topic in topics and topics[opt.gt_topic][0] != bag.ODOMETRY:
        notes.append(f"ground-truth topic {opt.gt_topic} holds {topics[opt.gt_topic][0]}, not {bag.ODOMETRY}: no RPE")
    elif opt.gt_topic and opt.gt_topic != ReplayOptions.gt_topic and opt.gt_topic not in topics:
        notes.append(f"ground-truth topic {opt.gt_topic} is not in the bag: no RPE (its Odometry topics: "
                     f"{', '.join(_of_type(topics, bag.ODOMETRY)) or 'none'})")
    return with_(opt, points_topic=points, odom_topic=odom), topics


def _add_rpe(records, window_poses, gt_stamps, gt_poses, extrinsic) -> None:
    """``extrinsic``: ground-truth child frame -> sensor frame (the estimate's window poses are sensor poses).
    Ground-truth columns of each window record (bags with ground truth): ``rpe`` (Eq. 4 over its consecutive
    scans) and the TRUE drift rates over the window, ``true_rot_rate`` (°/s) and ``true_trans_rate`` (m/s):
    the trend of the estimate's error against ground truth over its scans (drift_rate.true_drift_rates)."""
    from .metrics.drift_rate import true_drift_rates
    from .metrics.rpe import rpe

    order = np.argsort(gt_stamps, kind="stable")
    gt_stamps, gt_poses = gt_stamps[order], gt_poses[order]
    for rec, poses in zip(records, window_poses):
        stamps = np.array([s for s, _ in poses])
        gt, valid = geometry.interpolate_poses(gt_stamps, gt_poses, stamps)
        ok = bool(valid.all()) and len(stamps) > 1
        est, gt_sensor = np.stack([p for _, p in poses]), gt @ extrinsic
        rec["rpe"] = rpe(gt_sensor, est) if ok else float("nan")
        rates = true_drift_rates(gt_sensor, est, stamps) if ok else (float("nan"), float("nan"))
        rec["true_rot_rate"], rec["true_trans_rate"] = rates


def _summary(bag_path, monitor: Monitor, records: list[dict], feed: _Feed, notes: list[str], speed) -> dict:
    levels = [r["level"] for r in records]
    bag_s = (feed.last - feed.first) if feed.first is not None else 0.0
    c, wall = monitor.counters, feed.wall_s
    per_scan = 1000 / max(1, c["scans_processed"])
    return {
        "bag": str(bag_path), "record_format": RECORD_FORMAT,
        "mode": "deterministic" if speed is None else f"live x{speed:g}",
        "windows": len(records), "levels": {k: levels.count(k) for k in ("OK", "WARN", "ERROR")},
        "scans_read": feed.n_scans, "scans_processed": c["scans_processed"], "wall_s": round(wall, 3),
        "bag_s": round(bag_s, 3), "scans_per_s": round(c["scans_processed"] / wall, 2) if wall > 0 else None,
        "x_realtime": round(bag_s / wall, 2) if wall > 0 else None,
        "extrinsic_source": monitor.extrinsic_source, "counters": c, "error": feed.error, "notes": notes,
        "last_monitor_error": monitor.last_error, "last_error_of": dict(monitor.last_error_of),
        "cpu_ms_per_scan": {"reader": round(feed.reader_cpu_s * per_scan, 2),  # reading + decoding (this thread)
                            **{f"stage{i}": round(t * per_scan, 2) for i, t in enumerate(monitor.stage_cpu_s)}},
        "window": monitor.window.describe(), "window_scans": monitor.window.size,
        "config": flatten(monitor.config),
    }


# ------------------------------------------------------------------ reports
def write_reports(out: Path, records: list[dict], summary: dict, truth: dict | None = None,
                  plot: bool = True) -> None:
    """windows.csv, windows.json and (plot) metrics.png in ``out``."""
    keys: list[str] = []
    for r in records:
        keys += [k for k in r if k not in keys]
    rows = [{k: csv_value(r.get(k, "")) for k in keys} for r in records]
    write_csv(out / "windows.csv", rows, CORE_COLUMNS)  # no window: the header still, for scripts reading many
    write_json(out / "windows.json", {"summary": summary, "windows": records})
    if plot:
        plot_metrics(records, out / "metrics.png", truth, summary)


def load_windows(path: str | Path) -> dict:
    """A windows.json as written ({'summary', 'windows'}), with the window records' nulls back as NaN (strict
    JSON has no NaN: a metric that could not be computed is written as null)."""
    doc = json.loads(Path(path).read_text())
    doc["windows"] = [{k: float("nan") if v is None else v for k, v in r.items()} for r in doc.get("windows", [])]
    return doc


LEVEL_COLOURS = {"WARN": "#f0a030", "ERROR": "#d03020"}
BASELINE_COLOUR = "#7fa7d0"
SE_COLOUR = "#7a7a7a"  # the drift rates' ± standard error band
#: (record key, axis label with its unit) of each row of metrics.png
PLOT_ROWS = [("pne", "PNE (nats)"), ("cpv", "CPV (m², log scale)"), ("rot_rate", "rotation drift (°/s)"),
             ("trans_rate", "translation drift (m/s)"),
             ("rpe_estimate", "RPE estimate\nmean ‖E−I‖_F per scan pair\n(Eq. 4: rad and m mixed)"),
             ("agreement", "scan agreement\n(worst scan's share\nof planes in place)")]


def plot_metrics(records: list[dict], path: Path, truth: dict | None = None, summary: dict | None = None) -> None:
    """metrics.png: PNE, CPV, the drift rates, the RPE estimate (with the true RPE when the bag has ground
    truth) and the scan agreement per window over bag time; WARN/ERROR windows shaded, their limits dashed,
    simulated drift episodes (truth.json) hatched, the baseline-learning windows (health.baseline_windows, from the summary's config)
    shaded and labelled; bag, segmentation mode and sensor in the title; one legend, outside the plots."""
    from .reports import pyplot

    fig = metrics_figure(records, truth, summary)
    fig.savefig(path, dpi=110)
    pyplot().close(fig)


def metrics_figure(records: list[dict], truth: dict | None = None, summary: dict | None = None):
    """The matplotlib figure of :func:`plot_metrics` (the caller closes it)."""
    from .reports import pyplot

    plt = pyplot()
    fig, axes = plt.subplots(len(PLOT_ROWS), 1, figsize=(13, 2.6 * len(PLOT_ROWS)), sharex=True, squeeze=False,
                             layout="constrained")
    t0 = records[0]["start"] if records else 0.0
    learning = _baseline_span(records, summary, t0)
    for ax, (key, label) in zip(axes[:, 0], PLOT_ROWS):
        _plot_row(ax, records, key, label, t0, truth, learning)
    if learning is not None:
        axes[0, 0].annotate(f"learning baseline\n(first {learning[2]} windows:\nno PNE/CPV limits yet)",
                            xy=(0.5 * (learning[0] + learning[1]), 0.97), xycoords=("data", "axes fraction"),
                            ha="center", va="top", fontsize=8, color="#2a4a70")
    axes[-1, 0].set_xlabel("bag time since the first window's start (s); each point at its window's end")
    fig.legend(handles=_legend_handles(records, truth, learning), loc="outside right center", fontsize=8,
               title="per window", title_fontsize=8)
    fig.suptitle(_plot_title(summary))
    if not records:
        fig.text(0.45, 0.5, _no_window_text(summary), ha="center", va="center", fontsize=12, wrap=True,
                 bbox={"facecolor": "white", "edgecolor": LEVEL_COLOURS["ERROR"]})
    return fig


def _no_window_text(summary: dict | None) -> str:
    """Why the plot is empty, from the summary (no scan processed, or too few for a window)."""
    s = summary or {}
    why = s.get("no_scans") or next((n for n in s.get("notes", []) if n.startswith("no window")), "")
    return "NO WINDOW" + (f"\n{why}" if why else "")


def _plot_row(ax, records: list[dict], key: str, label: str, t0: float, truth: dict | None, learning) -> None:
    """One metric over time with every band: level shading, baseline span, episodes, limits."""
    t = np.array([r["end"] - t0 for r in records])
    for r, nxt in zip(records, records[1:] + [None]):
        if r["level"] in LEVEL_COLOURS:  # the window's span, up to the next window's start (no gaps)
            right = nxt["start"] if nxt is not None and nxt["start"] > r["end"] else r["end"]
            ax.axvspan(r["start"] - t0, right - t0, color=LEVEL_COLOURS[r["level"]], alpha=0.35, lw=0)
    if learning is not None:
        ax.axvspan(learning[0], learning[1], color=BASELINE_COLOUR, alpha=0.18, lw=0)
    for ep in (truth or {}).get("episodes", []):
        ax.axvspan(ep["start"] - t0, ep["end"] - t0, facecolor="none", edgecolor="grey", hatch="//", lw=0.5)
    values = np.array([_num(r.get(key)) for r in records])
    if any(f"{key}_se" in r for r in records):  # the rate's standard error (jackknife over scans)
        se = np.array([_num(r.get(f"{key}_se")) for r in records])
        ax.fill_between(t, values - se, values + se, color=SE_COLOUR, alpha=0.3, lw=0)
    ax.plot(t, values, "k.-", lw=1, ms=3)
    if key == "rpe_estimate":
        ax.plot(t, [_num(r.get("rpe")) for r in records], ".-", color="#4a7ab0", lw=1, ms=3)
    for level in ("warn", "error"):  # a tick at each window too: one window draws no line
        ax.plot(t, [_num(r.get(f"{key}_{level}_at")) for r in records], "--", marker="_", ms=10,
                color=LEVEL_COLOURS[level.upper()], lw=1)
    if key == "cpv" and any(_num(r.get("cpv")) > 0 for r in records):
        ax.set_yscale("log")  # a variance: drift multiplies it
    ax.set_ylabel(label, fontsize=9)
    ax.grid(alpha=0.3)


def _num(v) -> float:
    """A record value as a float (None, from strict JSON, and missing values as NaN)."""
    return float("nan") if v is None else float(v)


def _baseline_span(records: list[dict], summary: dict | None, t0: float) -> tuple[float, float, int] | None:
    """(start, end s from t0, windows) of the baseline-learning windows at the start of the run."""
    n = int(((summary or {}).get("config") or {}).get("health.baseline_windows", 0) or 0)
    if not records or n <= 0:
        return None
    last = records[min(n, len(records)) - 1]
    return records[0]["start"] - t0, last["end"] - t0, min(n, len(records))


def _legend_handles(records: list[dict], truth: dict | None, learning) -> list:
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    handles = [Line2D([], [], color="k", marker=".", lw=1, label="metric (monitor)")]
    if any(np.isfinite(_num(r.get("rpe"))) for r in records):
        handles.append(Line2D([], [], color="#4a7ab0", marker=".", lw=1, label="RPE from ground truth"))
    handles += [Line2D([], [], color=LEVEL_COLOURS["WARN"], ls="--", lw=1, label="WARN limit"),
                Line2D([], [], color=LEVEL_COLOURS["ERROR"], ls="--", lw=1, label="ERROR limit"),
                Patch(color=LEVEL_COLOURS["WARN"], alpha=0.35, label="WARN window"),
                Patch(color=LEVEL_COLOURS["ERROR"], alpha=0.35, label="ERROR window")]
    if any("rot_rate_se" in r for r in records):
        handles.append(Patch(color=SE_COLOUR, alpha=0.3, label="drift rate ± standard error"))
    if learning is not None:
        handles.append(Patch(color=BASELINE_COLOUR, alpha=0.18, label=f"learning baseline ({learning[2]} windows)"))
    if truth and truth.get("episodes"):
        handles.append(Patch(facecolor="none", edgecolor="grey", hatch="//", label="drift episode (truth)"))
    return handles


def _plot_title(summary: dict | None) -> str:
    """'topometric: map consistency per window — <bag>' and a line with segmentation, sensor and window."""
    s = summary or {}
    bag_name = Path(s.get("bag", "")).name or "?"
    window = s.get("window") or f"{(s.get('config') or {}).get('window.size', '?')} scans"
    return (f"topometric: map consistency per window — bag {bag_name}\n"
            f"segmentation {s.get('segmentation', '?')}, sensor {s.get('sensor', '?')}"
            f"{', ' + s['layout'] + ' layout' if s.get('layout') else ''}, window {window}")


def format_table(records: list[dict], summary: dict, max_rows: int = 60) -> str:
    """The window table (alarms always shown; OK rows thinned beyond max_rows) and the summary lines."""
    t0 = records[0]["start"] if records else 0.0
    has_rpe = any("rpe" in r for r in records)
    head = (f"{'win':>4} {'t_end s':>8} {'PNE':>8} {'CPV':>10} {'°/s':>6} {'m/s':>6} {'planes':>6}"
            + (f" {'RPE gt':>7}" if has_rpe else ""))  # the true RPE (ground truth), not rpe_estimate
    lines = [head + "  level  reason"]
    step = max(1, len(records) // max_rows)
    for i, r in enumerate(records):
        if r["level"] == "OK" and i % step:
            continue
        row = (f"{r['index']:>4} {r['end'] - t0:>8.1f} {r['pne']:>8.4f} {r['cpv']:>10.3g} "
               f"{r.get('rot_rate', float('nan')):>6.2f} {r.get('trans_rate', float('nan')):>6.3f} {r['n_planes']:>6}")
        if has_rpe:
            row += f" {r.get('rpe', float('nan')):>7.4f}"
        lines.append(f"{row}  {r['level']:<5}  {r['message']}")
    s, c = summary, summary["counters"]
    lines += ["", f"windows        {s['windows']}  (OK {s['levels']['OK']}, WARN {s['levels']['WARN']}, "
              f"ERROR {s['levels']['ERROR']})",
              f"scans          {s['scans_read']} read, {s['scans_processed']} processed, {c['dropped_scans']} dropped "
              f"(no pose {c['dropped_no_pose']}, queue {c['dropped_queue_full']}, bad {c['dropped_bad_scan']}, "
              f"duplicate {c['dropped_duplicate']}, clock {c.get('dropped_clock', 0)}, errors {c['scan_errors']})",
              f"speed          {s['scans_per_s']} scans/s, {s['x_realtime']}x real time ({s['mode']}, "
              f"{s['wall_s']:.1f} s wall for {s['bag_s']:.1f} s of bag)",
              f"extrinsic      from {s['extrinsic_source']}"]
    lines += _run_lines(s)
    return "\n".join(lines)


SEGMENTATION_TEXT = {"network": "network (the shipped weights unless segmentation.weights names others)",
                     "labels": "labels (the clouds' own label field)", "none": "none (every point counts as static)"}


def network_options(config: Config, precision: str = "") -> str:
    """How the network runs, in words: its precision (the Segmenter's: int8 or float32), passes beyond one,
    a beam limit, the neighbour vote ("" for none of them, or when the network does not run)."""
    seg = config.segmentation
    if seg.mode != "network":
        return ""
    return "".join([f", {precision} inference" if precision else "",
                    f", {seg.passes} passes" if seg.passes > 1 else "",
                    f", at most {seg.max_beams} beams through the network" if seg.max_beams else "",
                    f", a {seg.knn}-nearest-neighbour vote" if seg.knn else ""])


def _run_lines(s: dict) -> list[str]:
    """What ran and what went wrong: segmentation mode, sensor, topics, notes, error, why no scan."""
    if "segmentation" not in s:  # a summary of an older record format
        return [f"notes          {n}" for n in s.get("notes", [])]
    layout = f", {s['layout']} driver layout" if s.get("layout") else ""
    lines = [f"segmentation   {SEGMENTATION_TEXT.get(s['segmentation'], s['segmentation'])}"
             f"{s.get('segmentation_options', '')}",
             f"sensor         {s['sensor']}{layout}",
             f"topics         clouds {s['points_topic']}, odometry {s['odom_topic']}"]
    if s.get("window"):
        lines.append(f"window         {s['window']}")
    lines += [f"note           {n}" for n in s["notes"]]
    if s.get("clock_faults"):
        first = s["clock_faults"][0]
        lines.append(f"clock faults   {len(s['clock_faults'])} message(s) on another clock, first at bag time "
                     f"{first['received']!r} s: {first['message']} (reported as 'clock', not as drift)")
    if s["error"]:
        lines.append(f"ERROR          {s['error']} (reports hold what was processed before it)")
    if s.get("no_scans"):
        lines.append(f"NO SCAN PROCESSED: {s['no_scans']}")
        lines.append("the bag's topics (type, messages):")
        lines += [f"  {t}  {kind}  {n}" for t, (kind, n) in sorted(s["topics"].items())] or ["  none could be listed"]
    return lines
