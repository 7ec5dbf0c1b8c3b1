"""A small rosbag2 player over rclpy, for the node tests and benchmarks/bench_node.py (not product code).

    python test/ros_player.py BAG [--rate 1] [--clock] [--clock-tail 8] [--topics /points /odom /tf_static]
                              [--remap /points:=/velodyne_points] [--wait-subscribers 10] [--log scans.jsonl]
                              [--reliable-clouds] [--loops 1]

Messages go out as the bag stores them (CDR bytes, no decoding) at the bag's pace times ``--rate``, with
the QoS a robot uses: /tf_static latched (reliable, transient local), clouds with the sensor-data profile
(best effort; reliable, keep last 10, with ``--reliable-clouds``), everything else reliable. ``--clock`` publishes /clock (rosgraph_msgs/Clock) in bag time at
100 Hz while playing, and for ``--clock-tail`` s of bag time after the last message, so a node on
``use_sim_time`` sees time go on after its input stops. ``--loops N`` plays the bag N times back to back
(a long live run from a short bag): each play starts one cloud period after the last ended, its stamps shifted
so, its odometry moved rigidly to start where the last play's ended, /tf_static sent once. ``--log`` writes one JSON line per published cloud:
its header stamp (s) and the wall time (s, time.time()) it was published. Prints a JSON summary on exit.
"""
from __future__ import annotations

import argparse
import importlib
import json
import struct
import sys
import time
from pathlib import Path

import numpy as np
import rclpy
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

from topometric_ros.geometry import inverse, pose_from_quat, pose_to_quat

CLOCK_HZ = 100.0


def message_class(msgtype: str):
    """'sensor_msgs/msg/PointCloud2' -> the rclpy message class."""
    package, _, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{package}.msg"), name)


def qos_for(topic: str, msgtype: str, reliable_clouds: bool = False) -> QoSProfile:
    if topic == "/tf_static":
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)
    if msgtype == "sensor_msgs/msg/PointCloud2":
        if reliable_clouds:
            return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE)
        return qos_profile_sensor_data
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE)


def header_stamp(raw: bytes) -> float:
    """Stamp (s) of a CDR message that starts with std_msgs/Header (after the 4-byte encapsulation)."""
    sec, nanosec = struct.unpack_from("<iI", raw, 4)
    return sec + 1e-9 * nanosec


def read_raw(bag: Path, topics: list[str]):
    """(topic, msgtype, log time ns, CDR bytes) of the wanted topics, in log-time order."""
    from rosbags.rosbag2 import Reader

    with Reader(bag) as reader:
        conns = [c for c in reader.connections if c.topic in topics]
        for conn, t_ns, raw in reader.messages(connections=conns):
            yield conn.topic, conn.msgtype, t_ns, bytes(raw)


def _odometry_pose(msg) -> np.ndarray:
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    return pose_from_quat(np.array([q.x, q.y, q.z, q.w]), np.array([p.x, p.y, p.z]))


def _shift_stamp(raw: bytes, shift_ns: int) -> bytes:
    """CDR bytes of a message starting with std_msgs/Header, its stamp moved by shift_ns."""
    out = bytearray(raw)
    ns = int(round(header_stamp(raw) * 1e9)) + shift_ns
    struct.pack_into("<iI", out, 4, ns // 1_000_000_000, ns % 1_000_000_000)
    return bytes(out)


def looped_raw(bag: Path, topics: list[str], loops: int, odom_topic: str = "/odom"):
    """read_raw over ``loops`` plays of the bag (see --loops): (topic, msgtype, log time ns, CDR bytes)."""
    if loops == 1:
        yield from read_raw(bag, topics)
        return
    from nav_msgs.msg import Odometry
    from rclpy.serialization import deserialize_message, serialize_message

    odometry = [(t_ns, raw) for _, _, t_ns, raw in read_raw(bag, [odom_topic])]
    clouds = [t_ns for _, msgtype, t_ns, _ in read_raw(bag, topics) if msgtype == "sensor_msgs/msg/PointCloud2"]
    period_ns = (clouds[-1] - clouds[0]) // max(1, len(clouds) - 1)
    shift_ns = clouds[-1] - clouds[0] + period_ns
    seam = (clouds[0] - period_ns // 2, clouds[-1] + period_ns // 2)  # other plays' odometry between them

    def pose_at(t_ns: int) -> np.ndarray:
        nearest = min(odometry, key=lambda m: abs(m[0] - t_ns))[1]
        return _odometry_pose(deserialize_message(nearest, Odometry))

    step = pose_at(clouds[-1]) @ inverse(pose_at(clouds[0]))  # a play's start moved onto the last play's end
    anchor = np.eye(4)
    for k in range(loops):
        for topic, msgtype, t_ns, raw in read_raw(bag, topics):
            if k and topic == "/tf_static":  # latched: sent once
                continue
            if topic == odom_topic and ((k and t_ns < seam[0]) or (k < loops - 1 and t_ns > seam[1])):
                continue
            t_ns += k * shift_ns
            if k and topic == odom_topic:
                msg = deserialize_message(raw, Odometry)
                q, t = pose_to_quat(anchor @ _odometry_pose(msg))
                pose = msg.pose.pose
                (pose.position.x, pose.position.y, pose.position.z) = t
                (pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w) = q
                raw = serialize_message(msg)
            yield topic, msgtype, t_ns, _shift_stamp(raw, k * shift_ns) if k else raw
        anchor = anchor @ step


def play(args) -> dict:
    remap = dict(r.split(":=", 1) for r in args.remap)
    node = rclpy.create_node("topometric_player")
    pubs, counts = {}, {}
    from rosbags.rosbag2 import Reader

    with Reader(args.bag) as reader:
        for conn in reader.connections:
            if conn.topic in args.topics and conn.topic not in pubs:
                out = remap.get(conn.topic, conn.topic)
                pubs[conn.topic] = node.create_publisher(message_class(conn.msgtype), out,
                                                         qos_for(conn.topic, conn.msgtype, args.reliable_clouds))
                counts[conn.topic] = 0
    clock_pub = None
    if args.clock:
        from rosgraph_msgs.msg import Clock

        clock_pub = node.create_publisher(Clock, "/clock", 10)
    _wait_for_subscribers(node, [p for t, p in pubs.items() if t != "/tf_static"], args.wait_subscribers)
    log = open(args.log, "w") if args.log else None
    wall0 = t0 = None
    next_clock = 0.0
    last_bag = None
    for topic, msgtype, t_ns, raw in looped_raw(args.bag, list(pubs), args.loops):
        t = t_ns * 1e-9
        if t0 is None:
            wall0, t0 = time.monotonic(), t
        while True:  # wait for this message's time, publishing /clock meanwhile
            bag_now = t0 + (time.monotonic() - wall0) * args.rate
            if clock_pub is not None and time.monotonic() >= next_clock:
                clock_pub.publish(_clock(min(bag_now, t)))
                next_clock = time.monotonic() + 1.0 / CLOCK_HZ
            if bag_now >= t:
                break
            time.sleep(min(t - bag_now, 1.0 / CLOCK_HZ) / args.rate)
        pubs[topic].publish(raw)
        counts[topic] += 1
        last_bag = t
        if log is not None and msgtype == "sensor_msgs/msg/PointCloud2":
            log.write(json.dumps({"stamp": header_stamp(raw), "wall": time.time()}) + "\n")
    if log is not None:
        log.close()
    if clock_pub is not None and last_bag is not None:
        end = time.monotonic() + args.clock_tail / args.rate
        while time.monotonic() < end:
            clock_pub.publish(_clock(t0 + (time.monotonic() - wall0) * args.rate))
            time.sleep(1.0 / CLOCK_HZ)
    node.destroy_node()
    return {"published": counts, "bag_s": None if last_bag is None else last_bag - t0}


def _clock(seconds: float):
    from builtin_interfaces.msg import Time
    from rosgraph_msgs.msg import Clock

    ns = int(seconds * 1e9)
    return Clock(clock=Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000))


def _wait_for_subscribers(node, pubs, timeout: float) -> None:
    """Wait until every publisher has a subscriber (discovery), at most ``timeout`` s."""
    end = time.monotonic() + timeout
    while time.monotonic() < end and not all(p.get_subscription_count() > 0 for p in pubs):
        time.sleep(0.05)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bag", type=Path)
    ap.add_argument("--rate", type=float, default=1.0, help="speed factor (1 = real time)")
    ap.add_argument("--clock", action="store_true", help="publish /clock in bag time")
    ap.add_argument("--clock-tail", type=float, default=0.0, help="s of bag time /clock goes on after the end")
    ap.add_argument("--topics", nargs="+", default=["/points", "/odom", "/tf_static"])
    ap.add_argument("--remap", nargs="*", default=[], help="FROM:=TO topic names")
    ap.add_argument("--wait-subscribers", type=float, default=10.0, help="s to wait for subscribers first")
    ap.add_argument("--log", help="JSON lines: stamp and publish wall time of each cloud")
    ap.add_argument("--reliable-clouds", action="store_true", help="publish clouds reliable (keep last 10), not "
                                                                   "best effort: a test that must lose none")
    ap.add_argument("--loops", type=int, default=1, help="plays of the bag back to back (odometry continued)")
    args = ap.parse_args(argv)
    rclpy.init()
    try:
        print(json.dumps(play(args)), flush=True)
    except KeyboardInterrupt:
        return 130
    finally:
        if rclpy.ok():
            rclpy.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
