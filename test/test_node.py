"""The ROS 2 node, in-process with real rclpy publishers and subscribers (skips where rclpy is missing;
runs under ``colcon test`` in a ROS 2 Jazzy workspace).

A simulated bag is published message by message on /points, /odom and /tf_static; the node must publish
DiagnosticArray windows on /diagnostics with the conventional name and hardware_id, and reject
out-of-range parameters. Segmentation uses the bag's labels and the per-window work is the real pipeline."""
import array
import time

import pytest

rclpy = pytest.importorskip("rclpy")

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.exceptions import InvalidParameterValueException  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data  # noqa: E402
from sensor_msgs.msg import PointCloud2, PointField  # noqa: E402
from std_msgs.msg import Header  # noqa: E402
from builtin_interfaces.msg import Time  # noqa: E402
from tf2_msgs.msg import TFMessage  # noqa: E402
from types import SimpleNamespace  # noqa: E402

from topometric_ros import bag, geometry  # noqa: E402
from topometric_ros.cloud import make_cloud, read_cloud  # noqa: E402
from topometric_ros.node import MonitorNode  # noqa: E402

RCL_TYPES = SimpleNamespace(PointCloud2=PointCloud2, PointField=PointField, Header=Header, Time=Time)


@pytest.fixture
def ros():
    rclpy.init()
    yield
    rclpy.shutdown()


def _to_rclpy_cloud(msg):
    fields = read_cloud(msg)
    return make_cloud(fields, msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec, msg.header.frame_id,
                      RCL_TYPES, data=lambda d: array.array("B", d.tobytes()), align=4)


def _to_rclpy_odom(msg):
    stamp, pose = bag.odometry_pose(msg)
    q, t = geometry.pose_to_quat(pose)
    o = Odometry()
    o.header.frame_id, o.child_frame_id = msg.header.frame_id, msg.child_frame_id
    o.header.stamp = Time(sec=msg.header.stamp.sec, nanosec=msg.header.stamp.nanosec)
    o.pose.pose.position.x, o.pose.pose.position.y, o.pose.pose.position.z = map(float, t)
    o.pose.pose.orientation.x, o.pose.pose.orientation.y, o.pose.pose.orientation.z, o.pose.pose.orientation.w = \
        map(float, q)
    return o


def _to_rclpy_tf(msg):
    from geometry_msgs.msg import TransformStamped

    out = TFMessage()
    for tf in msg.transforms:
        t = TransformStamped()
        t.header.frame_id, t.child_frame_id = tf.header.frame_id, tf.child_frame_id
        for a in "xyz":
            setattr(t.transform.translation, a, float(getattr(tf.transform.translation, a)))
        for a in "xyzw":
            setattr(t.transform.rotation, a, float(getattr(tf.transform.rotation, a)))
        out.transforms.append(t)
    return out


def test_node_publishes_window_diagnostics(ros, office_bag):
    bag_path, _ = office_bag
    node = MonitorNode(parameter_overrides=[Parameter("segmentation.mode", value="labels"),
                                            Parameter("window.size", value=5),
                                            Parameter("health.baseline_windows", value=2)])
    peer = rclpy.create_node("topometric_test_peer")
    got = []
    peer.create_subscription(DiagnosticArray, "/diagnostics", got.append, 10)
    latched = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    pubs = {"/points": peer.create_publisher(PointCloud2, "/points", qos_profile_sensor_data),
            "/odom": peer.create_publisher(Odometry, "/odom", 10),
            "/tf_static": peer.create_publisher(TFMessage, "/tf_static", latched)}
    convert = {"/points": _to_rclpy_cloud, "/odom": _to_rclpy_odom, "/tf_static": _to_rclpy_tf}
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    executor.add_node(peer)
    for _ in range(20):  # let discovery settle
        executor.spin_once(timeout_sec=0.05)
    for topic, _, msg in bag.read_messages(bag_path, ["/points", "/odom", "/tf_static"]):
        pubs[topic].publish(convert[topic](msg))
        executor.spin_once(timeout_sec=0.01)
        time.sleep(0.02 if topic == "/points" else 0.0)  # a little slower than the worker
    deadline = time.time() + 60
    while time.time() < deadline and not [a for a in got if a.status and a.status[0].values]:
        executor.spin_once(timeout_sec=0.1)
    windows = [a.status[0] for a in got if a.status and any(kv.key == "pne" for kv in a.status[0].values)]
    assert windows, "no window diagnostics published"
    st = windows[0]
    assert st.name == "topometric: map consistency" and st.hardware_id == "velodyne"
    values = {kv.key: kv.value for kv in st.values}
    assert float(values["n_planes"]) > 0 and "dropped_windows" in values
    assert node.monitor.extrinsic_source == "tf_static"
    node.destroy_node()
    peer.destroy_node()


def test_out_of_range_and_bad_choice_parameters_are_rejected(ros):
    with pytest.raises(InvalidParameterValueException):
        MonitorNode(parameter_overrides=[Parameter("window.size", value=0)])
    with pytest.raises(ValueError):
        MonitorNode(parameter_overrides=[Parameter("segmentation.mode", value="magic")])
