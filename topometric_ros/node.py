"""The ROS 2 node ``topometric_monitor``: the ONLY module that imports rclpy.

A thin adapter: PointCloud2 / Odometry / tf_static messages go to a live Monitor (monitor.py, the same
code replay runs), whose worker threads do the per-scan work. Clouds are taken serialized and read with
rosbags, as replay reads bags: a 6 MB cloud (128 × 1024) is deserialized and read in 13 ms that way, in 19 ms
through rclpy's message (time the callback holds the GIL the workers need). Diagnostics follow diagnostic_updater's
conventions (its Updater publishes on /diagnostics every ``diagnostic_updater.period`` s, names
"<node name>: <task>", one hardware_id):

- ``map consistency``: each completed window's level, reason and values, published as the window
  completes (so every window reaches /diagnostics) and repeated by the Updater; STALE when input stops;
  ERROR with the reason when scans arrive but every one fails (Monitor.check, checked every CHECK_PERIOD_S
  and published at once when the state changes);
- ``scan rate``: the clouds received per second of the node's clock (sim time on use_sim_time), with
  diagnostic_updater.FrequencyStatus's levels and keys (ScanRate);
- ``clock``: ERROR while clouds or odometry arrive on another clock (a clock fault, not drift);
- ``latency``: node clock minus the stamp of a window's last scan when its result is out (s).

While the node warms up (monitor.warm_up, in a thread; it subscribes to its inputs after it) all four say STALE
"starting".

Optionally each window's planes go out as a MarkerArray on ~/planes (map frame, the inliers' rectangles).
Parameters: parameters.py (the node's own, the Updater's, one read-only parameter per config leaf); a
value out of range whatever its YAML type, a bad choice or an unknown key stops the node with exit code 2
and a message naming the parameter.
"""
from __future__ import annotations

import signal
import sys
import threading
from collections import deque

import diagnostic_updater
import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import Point
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.exceptions import InvalidParameterValueException, ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import ColorRGBA, Header
from tf2_msgs.msg import TFMessage
from visualization_msgs.msg import Marker, MarkerArray

from . import config as config_module
from . import bag, geometry, parameters
from .health import NODE_NAME, TASK, window_values
from .monitor import Monitor, warm_up

CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"

CHECK_PERIOD_S = 0.25  # s (node clock), how often STALE / every-scan-failing is checked
NO_CLOCK_WARN_S = 5.0  # s (steady), how often a use_sim_time without /clock is said on the console
OTHER_TIME_BASE_S = 60.0  # s, a latency this large is the stamps' time base, not processing
MISSING_SHARE = 0.1  # more of the scans missing by their stamps than this: WARN in 'scan rate'
LEVELS = {"OK": DiagnosticStatus.OK, "WARN": DiagnosticStatus.WARN, "ERROR": DiagnosticStatus.ERROR,
          "STALE": DiagnosticStatus.STALE}
GROUP_COLOURS = np.array([[0.89, 0.10, 0.11], [0.22, 0.49, 0.72], [0.30, 0.69, 0.29], [0.60, 0.31, 0.64],
                          [1.00, 0.50, 0.00], [0.65, 0.34, 0.16], [0.97, 0.51, 0.75], [0.40, 0.40, 0.40]])


def _descriptor(name: str, value, description: str) -> ParameterDescriptor:
    """Read-only; dynamic typing (YAML 5 for a float leaf must not kill the node: parameters.check and
    load_config check and convert); the range is shown, and checked by parameters.check whatever the type."""
    d = ParameterDescriptor(name=name, description=description, read_only=True, dynamic_typing=True)
    if name in parameters.RANGES:
        lo, hi = parameters.RANGES[name]
        if isinstance(value, float):
            d.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
        elif isinstance(value, int) and not isinstance(value, bool):
            d.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]
    if name in parameters.ALL_CHOICES:
        d.additional_constraints = "one of: " + ", ".join(parameters.ALL_CHOICES[name])
    return d


class ScanRate(diagnostic_updater.DiagnosticTask):
    """diagnostic_updater.FrequencyStatus's rule (ERROR no events, WARN below low_hz × (1 − tolerance) or above
    high_hz × (1 + tolerance), over the last ``window`` runs of the Updater, same keys) on the node's clock:
    Jazzy's Python FrequencyStatus builds a clock of its own, which reads system time, so a bag played at 5×
    on use_sim_time read 5× the sensor's rate (the C++ one takes the node's clock, ros/diagnostics#217)."""

    def __init__(self, clock, low_hz: float, high_hz: float, tolerance: float = 0.1, window: int = 5,
                 missing=lambda: 0):
        super().__init__("scan rate")
        self._clock, self.low_hz, self.high_hz, self.tolerance = clock, low_hz, high_hz, tolerance
        self._missing = missing  # () -> scans missing by the stamps so far (Monitor's scans_missing)
        self._lock = threading.Lock()
        self._count = 0
        self._runs: deque = deque(maxlen=window)  # (clock s, count, missing) of the last runs
        self._start = self._seconds() or None  # clock s counting starts at (None: a sim clock not going yet)

    def _seconds(self) -> float:
        return self._clock.now().nanoseconds * 1e-9

    def tick(self) -> None:
        with self._lock:
            self._count += 1
            if self._start is None:
                self._start = self._seconds() or None

    def run(self, stat):
        with self._lock:
            now, count, missing = self._seconds(), self._count, self._missing()
            if not self._runs:  # the first run: from the start (on use_sim_time, the first tick on /clock)
                self._runs.extend([(self._start or now, 0, 0)] * self._runs.maxlen)
            then, before, missing_before = self._runs[0]
            self._runs.append((now, count, missing))
        events, span, lost = count - before, now - then, missing - missing_before
        hz = events / span if span > 0 else float("nan")
        if events == 0:
            stat.summary(DiagnosticStatus.ERROR, "No events recorded.")
        elif hz < self.low_hz * (1 - self.tolerance):
            stat.summary(DiagnosticStatus.WARN, "Frequency too low.")
        elif hz > self.high_hz * (1 + self.tolerance):
            stat.summary(DiagnosticStatus.WARN, "Frequency too high.")
        elif why := missing_scans_text(events, lost):
            stat.summary(DiagnosticStatus.WARN, why)
        else:
            stat.summary(DiagnosticStatus.OK, "Desired frequency met")
        stat.add("Events in window", str(events))
        stat.add("Scans missing in window", str(lost))
        stat.add("Events since startup", str(count))
        stat.add("Duration of window (s)", f"{span:f}")
        stat.add("Actual frequency (Hz)", f"{hz:f}")
        return stat


def missing_scans_text(received: int, missing: int) -> str:
    """A WARN's text when more than MISSING_SHARE of the scans the cloud stamps say were sent never arrived
    ("" otherwise): the rate limits alone miss it (44 of 120 big clouds arrived, and 4 Hz met 1 Hz)."""
    if missing <= MISSING_SHARE * (received + missing):
        return ""
    return (f"{missing} of {received + missing} scans missing by their stamps: lost on the way (a big cloud over "
            "best-effort DDS needs bigger socket buffers, docs/ros.md) or dropped by the driver")


def time_base_hint(latency_s: float) -> str:
    """For a latency no queue explains (a minute or more): the stamps and the node clock count from different
    origins."""
    if not latency_s >= OTHER_TIME_BASE_S:
        return ""
    return (f" (the scan stamps are {latency_s:.3g} s behind the node's clock: a sensor clock counting from "
            "power-on, or a bag played without --clock / use_sim_time?)")


def _read_only_at_runtime(changes) -> SetParametersResult:
    """Refuse runtime changes of the Updater's parameters and of use_sim_time, read once at start like all of
    ours (use_sim_time turned on later would stop the node's clock, and with it every status, until a /clock)."""
    names = [p.name for p in changes if p.name in parameters.UPDATER_SPEC or p.name == "use_sim_time"]
    if names:
        return SetParametersResult(successful=False, reason=f"{', '.join(names)}: read-only (set at start)")
    return SetParametersResult(successful=True)


def _qos(name: str) -> QoSProfile:
    if name == "sensor_data":
        return qos_profile_sensor_data
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE)


def _stamp_msg(seconds: float):
    from builtin_interfaces.msg import Time

    ns = int(round(seconds * 1e9))
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def plane_markers(scans, result, frame_id: str, stamp) -> MarkerArray:
    """One thin CUBE per plane of the window (map frame): the rectangle holding all its inliers
    (Plane.box), coloured by co-plane group when the result carries ``groups``, else by class. Old markers
    are deleted first."""
    group_of = {}
    for g, members in enumerate(getattr(result, "groups", None) or []):
        for key in members:
            group_of[tuple(key)] = g
    header = Header(frame_id=frame_id, stamp=stamp)
    markers = [Marker(header=header, ns="topometric_planes", id=0, action=Marker.DELETEALL)]
    for i, scan in enumerate(scans):
        for j, plane in enumerate(scan.planes):
            centre, axes, size = plane.box(scan.pose)
            q, _ = geometry.pose_to_quat(geometry.make_pose(axes, centre))
            colour = GROUP_COLOURS[group_of.get((i, j), plane.cls) % len(GROUP_COLOURS)]
            m = Marker(header=header, ns="topometric_planes", id=len(markers), type=Marker.CUBE,
                       action=Marker.ADD,
                       color=ColorRGBA(r=float(colour[0]), g=float(colour[1]), b=float(colour[2]), a=0.6))
            m.pose.position = Point(x=float(centre[0]), y=float(centre[1]), z=float(centre[2]))
            m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z, m.pose.orientation.w = map(float, q)
            m.scale.x, m.scale.y, m.scale.z = float(size[0]), float(size[1]), 0.02
            markers.append(m)
    return MarkerArray(markers=markers)


class MonitorNode(Node):
    """Subscribes to points, odometry and tf_static; publishes /diagnostics (and plane markers)."""

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        self._updater_period_as_float()
        self.updater = diagnostic_updater.Updater(self)  # declares diagnostic_updater.period / use_fqn
        p = self._declare_parameters()
        self._check_topic_names(p)
        self.add_on_set_parameters_callback(_read_only_at_runtime)
        from .replay import load_segmenter

        segmenter = load_segmenter(self.config) if self.config.segmentation.mode == "network" else None
        self.p = p
        self._lock = threading.Lock()
        self._last_window = None  # (level, message, values) of the newest window
        self._latency = {"last": float("nan"), "max": float("nan"), "windows": 0}
        self._window_told = False  # the window's size logged (with the first window: an automatic size is set then)
        self._checked = (None, None)  # the last Monitor.check and clock_status outcomes published
        self.monitor = Monitor(self.config, segmenter=segmenter, live=True, on_window=self._on_window,
                               keep_results=0)  # every window goes out through _on_window
        self.rate: ScanRate | None = None  # made as the node subscribes
        self.updater.setHardwareID(p["hardware_id"] or "none")
        for name, task in ((TASK, self._consistency_task), ("scan rate", self._scan_rate_task),
                           ("latency", self._latency_task), ("clock", self._clock_task)):
            self.updater.add(name, self._until_subscribed(task))
        self.marker_pub = self.create_publisher(MarkerArray, "~/planes", 1) if p["publish_markers"] else None
        self._typestore = bag.typestore()
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)  # runs without /clock, unlike the node's
        self._started: float | None = None  # steady s the node subscribed at (None while it warms up)
        self._told = [None, None]  # the levels of Monitor.check and clock_status last said on the console
        self._gap_since = None  # steady time (s) the extrinsic gap was first seen, None = no gap; told once
        self._gap_told = False
        self.create_timer(CHECK_PERIOD_S, self._on_check)
        self.create_timer(NO_CLOCK_WARN_S, self._on_steady, clock=self._steady)
        self._warm_began = self._steady_s()
        self._warm = self.create_guard_condition(self._subscribe)  # triggered by the warm-up thread as it ends
        self.get_logger().info("warming up: the pipeline's compiled kernels (the first start after an install "
                               "compiles them: a minute or two on a small CPU; later starts load them); the "
                               "statuses say 'starting' until the node subscribes")
        threading.Thread(target=self._warm_up, args=(segmenter,), daemon=True, name="warm-up").start()

    def _warm_up(self, segmenter) -> None:
        """The warm-up thread: monitor.warm_up, then the executor subscribes (the guard condition's callback)."""
        try:
            seconds, _ = warm_up(self.config, segmenter)
            self.get_logger().info(f"warm in {seconds:.1f} s")
        except Exception as e:  # noqa: BLE001 - live data will compile what it needs; the node still runs
            self.get_logger().warning(f"warm-up failed ({type(e).__name__}: {e}); the first scans compile instead")
        finally:
            self._warm.trigger()

    def _subscribe(self) -> None:
        """Once warm (in the executor's thread): the scan rate's count and the subscriptions start; the console
        says what is monitored."""
        if self._started is not None:
            return
        p = self.p
        self.rate = ScanRate(self.get_clock(), p["scan_rate_min_hz"], p["scan_rate_max_hz"],
                             missing=lambda: self.monitor.counters["scans_missing"])
        self.create_subscription(PointCloud2, p["points_topic"], self._on_cloud, _qos(p["points_qos"]), raw=True)
        self.create_subscription(Odometry, p["odom_topic"], self._on_odom, _qos(p["odom_qos"]))
        latched = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.create_subscription(TFMessage, p["tf_static_topic"], self.monitor.add_tf_static, latched)
        self._started = self._steady_s()
        from .replay import network_options

        self.get_logger().info(
            f"monitoring {self.resolve_topic_name(p['points_topic'])} + {self.resolve_topic_name(p['odom_topic'])}: "
            f"window {self.monitor.window.describe()}, sensor {self.config.sensor.model or 'read off each cloud'}, "
            f"segmentation {self.config.segmentation.mode}"
            f"{network_options(self.config, getattr(self.monitor.segmenter, 'precision', ''))}, "
            f"diagnostics on /diagnostics as '{self.updater.node_name}: {TASK}'")

    def _until_subscribed(self, task):
        """An Updater task that says STALE 'starting' while the node warms up, then is ``task``."""
        def run(stat):
            if self._started is not None:
                return task(stat)
            stat.summary(DiagnosticStatus.STALE,
                         f"starting: warming up the pipeline for {self._steady_s() - self._warm_began:.0f} s (the "
                         "first start after an install compiles its kernels: a minute or two on a small CPU; later "
                         "starts take seconds); the inputs are subscribed after it")
            return stat
        return run

    def _scan_rate_task(self, stat):
        return self.rate.run(stat)

    # ------------------------------------------------------------ parameters
    def _check_topic_names(self, p: dict) -> None:
        """A topic parameter that is no ROS topic name stops the node at start (ValueError: exit 2), not when it
        subscribes after the warm-up."""
        for name in ("points_topic", "odom_topic", "tf_static_topic"):
            try:
                self.resolve_topic_name(p[name])
            except _rclpy.RCLError as e:
                why = str(e).split(", at /")[0].removeprefix("failed to resolve name: ")
                raise ValueError(f"parameter '{name}' = {p[name]!r} is not a topic name: {why}") from None

    def _updater_period_as_float(self) -> None:
        """A whole number given for diagnostic_updater.period (``:=2``, YAML ``2``) as the float the Updater
        declares it as: a float parameter of ours takes one too (the Updater's own declaration would stop the
        node)."""
        name = "diagnostic_updater.period"
        given = getattr(self, "_parameter_overrides", {}).get(name)
        if given is not None and given.type_ == Parameter.Type.INTEGER:
            self._parameter_overrides[name] = Parameter(name, Parameter.Type.DOUBLE, float(given.value))

    def _declare_parameters(self) -> dict:
        """Declare every parameter (node, config leaves), check each value whatever its type, refuse keys
        the node does not know; sets self.config and returns the node's own parameter values."""
        texts = {**{k: t for k, (_, t) in parameters.NODE_SPEC.items()}, **parameters.config_descriptions()}
        values = {}
        for name, default in parameters.defaults().items():
            if name in parameters.UPDATER_SPEC:
                values[name] = self.get_parameter(name).value
                continue
            try:
                values[name] = self.declare_parameter(name, default, _descriptor(name, default, texts[name])).value
            except InvalidParameterValueException:  # rclpy's range check came first: say it as ours does
                parameters.check(name, self._parameter_overrides[name].value)
                raise
        given = set(getattr(self, "_parameter_overrides", {}))  # from params files and -p (rclpy keeps them)
        parameters.check_known(given, {n for n in given if self.has_parameter(n)})
        for name, value in values.items():
            parameters.check(name, value)
        self.config = parameters.config_from({k: v for k, v in values.items() if k not in parameters.NODE_SPEC
                                              and k not in parameters.UPDATER_SPEC})
        node = {k: values[k] for k in parameters.NODE_SPEC}
        for name, (default, _) in parameters.NODE_SPEC.items():  # node parameters: the default's type
            node[name] = config_module._coerce(name, default, node[name])
            parameters.check(name, node[name])  # again as a number: a quoted '-5' reads as one only now
        return node

    # ------------------------------------------------------------ callbacks
    def _now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _received(self) -> float | None:
        """The node clock (s) as a message's receive time; None while it reads 0 (use_sim_time before the first
        /clock): a 0 would teach the clock watch an offset of the stamps' whole epoch."""
        return self._now() or None

    def _on_cloud(self, raw: bytes) -> None:
        """A serialized sensor_msgs/PointCloud2 (CDR), read with rosbags (numpy views, no per-field copies)."""
        msg = self._typestore.deserialize_cdr(raw, CLOUD_TYPE)
        self.rate.tick()
        if not self.p["hardware_id"] and msg.header.frame_id and self.updater.hwid != msg.header.frame_id:
            self.updater.setHardwareID(msg.header.frame_id)
        self.monitor.add_cloud(msg, received=self._received())

    def _on_odom(self, msg: Odometry) -> None:
        self.monitor.add_odometry(msg, received=self._received())

    def _on_window(self, result, scans) -> None:
        """Worker thread: keep the window's status, publish it now (every window reaches /diagnostics)."""
        latency = self._now() - result.stamps[-1]
        values = window_values(result, self.monitor.counters, self._sources())
        if not self._window_told:
            self._window_told = True
            self.get_logger().info(f"window: {self.monitor.window.describe()}")  # an automatic size is known now
        with self._lock:
            self._last_window = (result.level, result.message, values)
            lat = self._latency
            lat["last"], lat["windows"] = latency, lat["windows"] + 1
            lat["max"] = latency if np.isnan(lat["max"]) else max(lat["max"], latency)
        self.updater.publish(self._status(TASK, result.level, result.message, values))
        if result.level != "OK":
            self.get_logger().warning(f"{result.level}: {result.message}", throttle_duration_sec=5.0)
        if self.marker_pub is not None:
            frame = self.monitor.map_frame or "map"
            self.marker_pub.publish(plane_markers(scans, result, frame, _stamp_msg(result.stamps[-1])))

    def _status(self, name: str, level: str, message: str, values: dict) -> diagnostic_updater.DiagnosticStatusWrapper:
        stat = diagnostic_updater.DiagnosticStatusWrapper(name=name, hardware_id=self.updater.hwid)
        stat.summary(LEVELS[level], message)
        for key, value in values.items():
            stat.add(str(key), str(value))
        return stat

    def _consistency_task(self, stat):
        """The Updater's 'map consistency': STALE / every scan failing, else the newest window."""
        checked = self.monitor.check(self._now())
        with self._lock:
            last = self._last_window
        if checked is not None:
            stat.summary(LEVELS[checked[0]], checked[1] + self._lost_clouds_hint(checked) +
                         self._lost_odometry_hint(checked))
            values = {**self._monitor_values(), "last_error": self.monitor.last_error}
        elif last is not None:
            stat.summary(LEVELS[last[0]], last[1])
            values = last[2]
        else:
            stat.summary(DiagnosticStatus.OK, f"waiting for the first window ({self.monitor.window.describe()})")
            values = self._monitor_values()
        for key, value in values.items():
            stat.add(key, value)
        return stat

    def _lost_clouds_hint(self, checked: tuple[str, str]) -> str:
        """For a STALE without clouds: whether the cloud topic has publishers, and where clouds that never
        arrived may be lost (after clouds did arrive, that the publisher stopped)."""
        if checked[0] != "STALE" or "no scans" not in checked[1]:
            return ""
        topic = self.resolve_topic_name(self.p["points_topic"])
        publishers = self.count_publishers(topic)
        if not publishers:
            return f" ({topic} has no publisher)"
        some = f"{topic} has {publishers} publisher{'s' * (publishers > 1)}"
        if self.monitor.last_scan_received is not None:  # clouds came through before: not a transport problem
            return f" ({some}, which sent clouds before: has the driver stopped publishing?)"
        qos = "; points_qos reliable does not match a best-effort driver" if self.p["points_qos"] == "reliable" else ""
        return (f" ({some}: if it publishes, its clouds are lost "
                f"on the way; a big cloud over best-effort DDS needs bigger socket buffers, docs/ros.md{qos})")

    def _lost_odometry_hint(self, checked: tuple[str, str]) -> str:
        """For a STALE without odometry: whether the odometry topic has publishers, and a QoS that cannot match
        (odom_qos reliable against a best-effort publisher: nothing is ever delivered)."""
        if checked[0] != "STALE" or "no odometry" not in checked[1]:
            return ""
        topic = self.resolve_topic_name(self.p["odom_topic"])
        infos = self.get_publishers_info_by_topic(topic)
        if not infos:
            return f" ({topic} has no publisher)"
        best_effort = sum(i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for i in infos)
        if best_effort and self.p["odom_qos"] == "reliable":
            who = ("its publisher offers" if len(infos) == 1 else
                   f"{best_effort} of its {len(infos)} publishers offer{'s' * (best_effort == 1)}")
            return f" ({topic}: {who} best effort, which odom_qos reliable never receives: set odom_qos sensor_data)"
        return ""

    def _monitor_values(self) -> dict:
        """The monitor's counters, where its extrinsic comes from and its cloud note, as status values (no
        window yet)."""
        return {**{k: str(v) for k, v in self.monitor.counters.items()}, **self._sources()}

    def _sources(self) -> dict[str, str]:
        """Where the extrinsic comes from, why the last cloud's field was not used ("" none), and the window's
        size in scans ("" while an automatic size is not set)."""
        size = self.monitor.window.size
        extrinsic = self.monitor.extrinsic_source
        why = "; ".join(filter(None, (self.monitor.extrinsic_note, self.monitor.extrinsic_gap)))
        if why:
            extrinsic = f"{extrinsic} ({why})"
        return {"extrinsic": extrinsic, "cloud_note": self.monitor.last_note,
                "window_scans": "" if size is None else str(size),
                "waiting_for_odometry": str(self.monitor.pending_length)}  # scans_in = processed + dropped + these
                                                                             # + in flight

    def _latency_task(self, stat):
        """The Updater's 'latency': scan stamp -> window result (node clock), worst since the last report."""
        with self._lock:
            lat, self._latency = self._latency, {"last": self._latency["last"], "max": float("nan"), "windows": 0}
        p = self.p
        if lat["windows"] == 0:
            stat.summary(DiagnosticStatus.OK, "no window since the last report")
        elif lat["max"] > p["latency_error_s"]:
            stat.summary(DiagnosticStatus.ERROR, f"latency {lat['max']:.2f} s above {p['latency_error_s']:g} s"
                         + time_base_hint(lat["max"]))
        elif lat["max"] > p["latency_warn_s"]:
            stat.summary(DiagnosticStatus.WARN, f"latency {lat['max']:.2f} s above {p['latency_warn_s']:g} s")
        else:
            stat.summary(DiagnosticStatus.OK, f"latency {lat['max']:.2f} s")
        stat.add("last_s", repr(lat["last"]))
        stat.add("max_s", repr(lat["max"]))
        stat.add("windows", str(lat["windows"]))
        stat.add("queue", str(self.monitor.in_flight))
        return stat

    def _clock_task(self, stat):
        """The Updater's 'clock': ERROR while clouds or odometry arrive on another clock (monitor.ClockWatch),
        reported here and not as drift (such messages are dropped, not scored)."""
        fault = self.monitor.clock_status(self._now())
        if fault is None:
            stat.summary(DiagnosticStatus.OK, "clouds and odometry keep one clock")
        else:
            stat.summary(DiagnosticStatus.ERROR, fault[1])
        counters = self.monitor.counters
        stat.add("dropped_clock", str(counters["dropped_clock"]))
        stat.add("clock_fault_poses", str(counters["clock_fault_poses"]))
        return stat

    def _on_check(self) -> None:
        """Publish at once when STALE / every-scan-failing / a clock fault starts or ends (the Updater repeats it);
        scans still waiting for odometry that stopped are released (Monitor.release_waiting)."""
        if self._started is None:  # warming up: nothing subscribed yet
            return
        now = self._now()
        self.monitor.release_waiting(now)  # the odometry stopped: scans waiting for it are scored with what came
        checked = self.monitor.check(now), self.monitor.clock_status(now)
        changed = [c and c[0] for c in checked] != [c and c[0] for c in self._checked]
        self._checked = checked
        if changed:
            self.updater.force_update()
        self._tell(checked)

    def _tell(self, checked: tuple) -> None:
        """The console too, not /diagnostics alone: a STALE, an every-scan-failing ERROR or a clock fault that
        starts (after the node's first stale_after_s, when inputs not there yet are no news), and that it ended."""
        levels = [c and c[0] for c in checked]
        if levels == self._told or self._steady_s() - self._started < self.config.health.stale_after_s:
            return
        log = self.get_logger()
        for task, now, before in zip((TASK, "clock"), checked, self._told):
            if now is not None and now[0] != before:
                hints = self._lost_clouds_hint(now) + self._lost_odometry_hint(now) if task == TASK else ""
                log.warning(f"{task}: {now[0]}: {now[1]}{hints}")
            elif now is None and before is not None:
                log.info(f"{task}: {before} over")
        self._told = levels

    def _steady_s(self) -> float:
        return self._steady.now().nanoseconds * 1e-9

    def _on_steady(self) -> None:
        """Every NO_CLOCK_WARN_S of steady time: say so while use_sim_time waits for a /clock that never came (the
        node's clock stands at 0: no status, no STALE), and tell an extrinsic gap that lasted (a /tf_static
        arriving just after the first scan closes one at once)."""
        if self.get_parameter("use_sim_time").value and not self._now():
            self.get_logger().warning(
                f"use_sim_time is true but no /clock came in {NO_CLOCK_WARN_S:g} s or more: the node's clock stands "
                "at 0, so no status goes out (play the bag with --clock, or use_sim_time:=false on a robot)")
        gap = self.monitor.extrinsic_gap if np.allclose(self.monitor.extrinsic, np.eye(4)) else ""  # a set
        now = self._steady_s()                                             # window.extrinsic is the user's choice
        self._gap_since = (self._gap_since or now) if gap else None
        if gap and not self._gap_told and now - self._gap_since >= NO_CLOCK_WARN_S / 2:
            self._gap_told = True
            self.get_logger().warning(gap)

    def destroy_node(self) -> None:
        self.monitor.close(drain=False)
        super().destroy_node()


def main(args=None) -> int:
    try:
        rclpy.init(args=args)
    except _rclpy.RCLError as e:  # e.g. a params file that is no ROS 2 parameter file
        print(f"{NODE_NAME}: cannot start: {str(e).split(', at /')[0]} (a ROS 2 parameter file has `/**:` or the "
              "node name, then `ros__parameters:`, as config/topometric.yaml; docs/ros.md)", file=sys.stderr)
        return 2
    node = None
    code = 0
    try:
        node = MonitorNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except _rclpy.RCLError:  # SIGINT while spin sets up its wait set: the context is already shut down
        if rclpy.ok():
            raise
    except (ValueError, ParameterException) as e:  # a bad parameter: a clear message, not a traceback
        print(f"{NODE_NAME}: {e}", file=sys.stderr)
        code = 2
    finally:
        # Ctrl-C in a terminal reaches ros2 launch and its nodes, then launch sends its own SIGINT: a second
        # one must not interrupt the teardown (the workers are joined next, in well under a second)
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        if node is not None:
            node.destroy_node()
            left = [t.name for t in threading.enumerate() if t.name.startswith("topometric-")]
            print(f"{NODE_NAME}: stopped; worker threads left: {len(left)}", file=sys.stderr, flush=True)
        if rclpy.ok():
            rclpy.shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
