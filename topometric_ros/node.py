"""The ROS 2 node ``topometric_monitor``: the ONLY module that imports rclpy.

A thin adapter: PointCloud2 / Odometry / tf_static messages go to a live Monitor (monitor.py, the same
code replay runs), whose worker thread does the per-scan work; each completed window is published on
/diagnostics (diagnostic_msgs/DiagnosticArray, built by health.diagnostic_status) and, optionally, as a
MarkerArray of the window's planes. A timer publishes STALE when input stops (node clock, so
``use_sim_time`` works).

Parameters: the node's own (topics, QoS, hardware_id, markers) plus one read-only parameter per config
leaf, named ``section.field`` (e.g. ``window.size``), with its description and range; values come from
config/topometric.yaml via the launch file.
"""
from __future__ import annotations

import dataclasses
import inspect
import re
import sys
from types import SimpleNamespace

import numpy as np
import rclpy
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import ColorRGBA, Header
from tf2_msgs.msg import TFMessage
from visualization_msgs.msg import Marker, MarkerArray

from . import config as config_module
from .config import CHOICES
from .health import diagnostic_array, diagnostic_status, window_values
from .monitor import Monitor

NODE_NAME = "topometric_monitor"
DIAG_TYPES = SimpleNamespace(DiagnosticArray=DiagnosticArray, DiagnosticStatus=DiagnosticStatus, KeyValue=KeyValue,
                             Header=Header, Time=Time)

#: Ranges of numeric config leaves: name -> (min, max). Others are unbounded.
RANGES = {
    "window.size": (1, 200), "window.step": (0, 200), "window.pose_wait_s": (0.0, 10.0),
    "window.max_pose_gap_s": (0.001, 10.0), "window.queue_size": (1, 1000), "window.voxel_size": (0.0, 5.0),
    "window.pose_timeout_s": (0.0, 60.0), "window.pose_horizon_s": (1.0, 3600.0),
    "segmentation.threads": (1, 64), "planes.min_points": (3, 1_000_000), "planes.max_sample_points": (3, 1_000_000),
    "metrics.radius": (0.01, 10.0), "metrics.min_neighbours": (0, 10_000),
    "health.stale_after_s": (0.1, 3600.0), "health.baseline_windows": (1, 100_000),
    "health.baseline_history": (1, 1_000_000), "health.warn_sigma": (0.0, 1000.0), "health.error_sigma": (0.0, 1000.0),
    "health.warn_persist": (1, 1000), "health.persist_windows": (1, 1000),
    "health.pne_min_sigma": (0.0, 100.0), "health.cpv_min_sigma": (0.0, 100.0),
    "health.pne_warn": (-1e3, 1e3), "health.pne_error": (-1e3, 1e3),
    "health.cpv_warn": (0.0, 1e6), "health.cpv_error": (0.0, 1e6),
    "health.rot_rate_warn": (0.0, 360.0), "health.rot_rate_error": (0.0, 360.0),
    "health.trans_rate_warn": (0.0, 100.0), "health.trans_rate_error": (0.0, 100.0), "health.min_planes": (0, 1_000_000),
}
QOS_CHOICES = ("sensor_data", "reliable")


def config_descriptions() -> dict[str, str]:
    """'section.field' -> the unit comment written next to the field in config.py (one source of truth)."""
    out = {}
    for f in dataclasses.fields(config_module.Config):
        source = inspect.getsource(type(getattr(config_module.Config(), f.name)))
        for m in re.finditer(r"^\s+(\w+): [^=]+=.*?#\s*(.+)$", source, re.M):
            out[f"{f.name}.{m.group(1)}"] = m.group(2).strip()
    return out


def _descriptor(name: str, value, description: str) -> ParameterDescriptor:
    # dynamic typing: YAML "5" for a float leaf must not kill the node; load_config converts and checks types
    d = ParameterDescriptor(name=name, description=description, read_only=True, dynamic_typing=True)
    if name in RANGES and isinstance(value, (int, float)) and not isinstance(value, bool):
        lo, hi = RANGES[name]
        if isinstance(value, float):
            d.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
        else:
            d.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]
    if name in CHOICES:
        d.additional_constraints = "one of: " + ", ".join(CHOICES[name])
    return d


def _qos(name: str) -> QoSProfile:
    if name == "sensor_data":
        return qos_profile_sensor_data
    if name == "reliable":
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE)
    raise ValueError(f"QoS must be one of {QOS_CHOICES}, got {name!r}")


def _stamp_msg(seconds: float) -> Time:
    ns = int(round(seconds * 1e9))
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


GROUP_COLOURS = np.array([[0.89, 0.10, 0.11], [0.22, 0.49, 0.72], [0.30, 0.69, 0.29], [0.60, 0.31, 0.64],
                          [1.00, 0.50, 0.00], [0.65, 0.34, 0.16], [0.97, 0.51, 0.75], [0.40, 0.40, 0.40]])


def plane_markers(scans, result, frame_id: str, stamp: Time) -> MarkerArray:
    """One thin CUBE per plane of the window (map frame), coloured by co-plane group when the result carries
    ``groups`` (list of lists of (scan index in window, plane index)), else by class. Old markers deleted."""
    from . import geometry

    group_of = {}
    for g, members in enumerate(getattr(result, "groups", None) or []):
        for key in members:
            group_of[tuple(key)] = g
    markers = [Marker(header=Header(frame_id=frame_id, stamp=stamp), ns="topometric_planes", id=0,
                      action=Marker.DELETEALL)]
    k = 1
    for i, scan in enumerate(scans):
        for j, plane in enumerate(scan.planes):
            normal, mean, scatter = plane.transformed_stats(scan.pose)
            vals, vecs = np.linalg.eigh(scatter / max(plane.count, 1))
            axes = vecs[:, ::-1]  # largest spread first; the last axis is the normal
            if np.linalg.det(axes) < 0:
                axes[:, 2] *= -1
            q, _ = geometry.pose_to_quat(geometry.make_pose(axes, mean))
            size = 2 * np.sqrt(np.maximum(vals[::-1], 1e-6))
            colour = GROUP_COLOURS[group_of.get((i, j), plane.cls) % len(GROUP_COLOURS)]
            m = Marker(header=Header(frame_id=frame_id, stamp=stamp), ns="topometric_planes", id=k,
                       type=Marker.CUBE, action=Marker.ADD,
                       color=ColorRGBA(r=float(colour[0]), g=float(colour[1]), b=float(colour[2]), a=0.6))
            m.pose.position = Point(x=float(mean[0]), y=float(mean[1]), z=float(mean[2]))
            m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z, m.pose.orientation.w = map(float, q)
            m.scale.x, m.scale.y, m.scale.z = float(size[0]), float(size[1]), 0.02
            markers.append(m)
            k += 1
    return MarkerArray(markers=markers)


class MonitorNode(Node):
    """Subscribes to points, odometry and tf_static; publishes /diagnostics (and plane markers)."""

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        p = self._declare_node_parameters()
        config = self._declare_config_parameters()
        segmenter = None
        if config.segmentation.mode == "network":
            from .replay import load_segmenter

            segmenter = load_segmenter(config)
        self.monitor = Monitor(config, segmenter=segmenter, live=True, on_window=self._on_window)
        self.hardware_id = p["hardware_id"]
        self.diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.marker_pub = self.create_publisher(MarkerArray, "~/planes", 1) if p["publish_markers"] else None
        self.create_subscription(PointCloud2, p["points_topic"], self._on_cloud, _qos(p["points_qos"]))
        self.create_subscription(Odometry, p["odom_topic"], self._on_odom, _qos(p["odom_qos"]))
        latched = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.create_subscription(TFMessage, p["tf_static_topic"], self.monitor.add_tf_static, latched)
        self.create_timer(p["diagnostics_period_s"], self._on_timer)
        self.get_logger().info(
            f"monitoring {p['points_topic']} + {p['odom_topic']}: window {config.window.size} scans, "
            f"segmentation {config.segmentation.mode}, diagnostics on /diagnostics")

    # ------------------------------------------------------------ parameters
    def _declare_node_parameters(self) -> dict:
        spec = {
            "points_topic": ("/points", "PointCloud2 topic (sensor frame)"),
            "odom_topic": ("/odom", "nav_msgs/Odometry topic of the SLAM pose (child frame -> map)"),
            "tf_static_topic": ("/tf_static", "static transforms; give the odom child -> cloud frame extrinsic"),
            "points_qos": ("sensor_data", "QoS of the points subscription: sensor_data | reliable"),
            "odom_qos": ("reliable", "QoS of the odometry subscription: sensor_data | reliable"),
            "hardware_id": ("", "DiagnosticStatus hardware_id; empty = the cloud's frame_id"),
            "publish_markers": (False, "publish the window's planes as a MarkerArray on ~/planes"),
            "diagnostics_period_s": (1.0, "s, how often STALE is checked and published"),
        }
        out = {}
        for name, (default, text) in spec.items():
            d = ParameterDescriptor(name=name, description=text, read_only=True)
            if name == "diagnostics_period_s":
                d.floating_point_range = [FloatingPointRange(from_value=0.05, to_value=60.0, step=0.0)]
            if name.endswith("_qos"):
                d.additional_constraints = "one of: " + ", ".join(QOS_CHOICES)
            out[name] = self.declare_parameter(name, default, d).value
            if name.endswith("_qos") and out[name] not in QOS_CHOICES:
                raise ValueError(f"parameter {name} must be one of {QOS_CHOICES}, got {out[name]!r}")
        return out

    def _declare_config_parameters(self) -> config_module.Config:
        texts = config_descriptions()
        values = {}
        for name, default in config_module.flatten(config_module.Config()).items():
            value = self.declare_parameter(name, default, _descriptor(name, default, texts.get(name, name))).value
            if name in CHOICES and value not in CHOICES[name]:
                raise ValueError(f"parameter {name} must be one of {CHOICES[name]}, got {value!r}")
            values[name] = list(value) if isinstance(default, list) else value
        return config_module.load_config(overrides=values)

    # ------------------------------------------------------------ callbacks
    def _now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _on_cloud(self, msg: PointCloud2) -> None:
        self.monitor.add_cloud(msg, received=self._now())

    def _on_odom(self, msg: Odometry) -> None:
        self.monitor.add_odometry(msg, received=self._now())

    def _on_window(self, result, scans) -> None:
        """Worker thread: publish the window's status (and planes)."""
        values = window_values(result, self.monitor.counters)
        hw = self.hardware_id or self.monitor.sensor_frame
        status = diagnostic_status(DIAG_TYPES, result.level, result.message, values, hardware_id=hw)
        self.diag_pub.publish(diagnostic_array(DIAG_TYPES, self._now(), [status]))
        if result.level != "OK":
            self.get_logger().warning(f"{result.level}: {result.message}", throttle_duration_sec=5.0)
        if self.marker_pub is not None:
            frame = self.monitor.map_frame or "map"
            self.marker_pub.publish(plane_markers(scans, result, frame, _stamp_msg(result.stamps[-1])))

    def _on_timer(self) -> None:
        stale = self.monitor.stale(self._now())
        if stale is None:
            return
        level, reason = stale
        counters = {k: str(v) for k, v in self.monitor.counters.items()}
        hw = self.hardware_id or self.monitor.sensor_frame
        status = diagnostic_status(DIAG_TYPES, level, reason, counters, hardware_id=hw)
        self.diag_pub.publish(diagnostic_array(DIAG_TYPES, self._now(), [status]))

    def destroy_node(self) -> None:
        self.monitor.close(drain=False)
        super().destroy_node()


def main(args=None) -> int:
    rclpy.init(args=args)
    node = None
    try:
        node = MonitorNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ValueError, ParameterException) as e:  # a bad parameter: a clear message, not a traceback
        print(f"{NODE_NAME}: {e}", file=sys.stderr)
        return 2
    finally:
        if node is not None:
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
