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
so, its odometry moved rigidly to go on where the last play's was a period after its last cloud, /tf_static sent
once (clouds, odometry and /tf_static only: other topics are refused). ``--log`` writes one JSON line per
published cloud: its header stamp (s) and the wall time (s, time.time()) it was published. Prints a JSON summary
on exit.
"""
from __future__ import annotations

import argparse
import importlib
import json
import math
import struct
import sys
import time
from pathlib import Path

import numpy as np
import rclpy
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

from topometric_ros.bag import odometry_pose
from topometric_ros.geometry import inverse, pose_to_quat

CLOCK_HZ = 100.0
CLOUD, ODOMETRY = "sensor_msgs/msg/PointCloud2", "nav_msgs/msg/Odometry"


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


def stamp_ns(raw: bytes) -> int:
    """Header stamp (integer ns) of a CDR message that starts with std_msgs/Header."""
    sec, nanosec = struct.unpack_from("<iI", raw, 4)
    return sec * 1_000_000_000 + nanosec


def _shift_stamp(raw: bytes, shift_ns: int) -> bytes:
    """CDR bytes of a message starting with std_msgs/Header, its stamp moved by shift_ns."""
    out = bytearray(raw)
    ns = stamp_ns(raw) + shift_ns
    struct.pack_into("<iI", out, 4, ns // 1_000_000_000, ns % 1_000_000_000)
    return bytes(out)


def _loop_plan(bag: Path, topics: list[str]) -> tuple[int, tuple[int, int], dict]:
    """(shift ns between plays, (from, to) header stamps ns of a middle play's odometry, {odometry topic: the 4x4
    motion from the first cloud's stamp to one cloud period past the last}) for looped_raw."""
    from nav_msgs.msg import Odometry
    from rclpy.serialization import deserialize_message

    from topometric_ros.window import PoseBuffer

    clouds, odometry, other = [], {}, set()
    for topic, msgtype, _, raw in read_raw(bag, topics):
        if msgtype == CLOUD:
            clouds.append(stamp_ns(raw))
        elif msgtype == ODOMETRY:
            odometry.setdefault(topic, PoseBuffer(horizon_s=math.inf)).add(
                *odometry_pose(deserialize_message(raw, Odometry)))
        elif topic != "/tf_static":
            other.add(topic)
    if other or len(clouds) < 2:
        raise ValueError(f"--loops moves clouds (2 or more) and odometry on; the bag has {len(clouds)} clouds"
                         + (f" and {', '.join(sorted(other))} (leave out with --topics)" if other else ""))
    period = (clouds[-1] - clouds[0]) // (len(clouds) - 1)
    steps = {}
    for topic, poses in odometry.items():
        first, after_last = (poses.lookup(ns * 1e-9, 1.0, 1.0) for ns in (clouds[0], clouds[-1] + period))
        steps[topic] = np.eye(4) if first is None or after_last is None else after_last @ inverse(first)
    return clouds[-1] - clouds[0] + period, (clouds[0] - period // 2, clouds[-1] + period // 2), steps


def looped_raw(bag: Path, topics: list[str], loops: int):
    """read_raw over ``loops`` plays of the bag (see --loops): (topic, msgtype, log time ns, CDR bytes). Play k's
    stamps and log times are shifted by k x (the clouds' span + one period); its odometry (every Odometry topic)
    is moved rigidly so it goes on from where play k - 1's was one period after its last cloud, and the plays'
    odometry is cut half a period outside their clouds so it meets without overlap; /tf_static goes out once."""
    if loops < 1:
        raise ValueError(f"--loops must be 1 or more, got {loops}")
    if loops == 1:
        yield from read_raw(bag, topics)
        return
    from nav_msgs.msg import Odometry
    from rclpy.serialization import deserialize_message, serialize_message

    shift, (cut_from, cut_to), steps = _loop_plan(bag, topics)
    anchors = {topic: np.eye(4) for topic in steps}
    for k in range(loops):
        keep_from, keep_to = cut_from if k else -math.inf, cut_to if k < loops - 1 else math.inf  # odometry stamps
        for topic, msgtype, t_ns, raw in read_raw(bag, topics):
            if k and topic == "/tf_static":  # latched: sent once
                continue
            if msgtype == ODOMETRY and not keep_from <= stamp_ns(raw) < keep_to:
                continue
            if k and msgtype == ODOMETRY:
                msg = deserialize_message(raw, Odometry)
                q, t = pose_to_quat(anchors[topic] @ odometry_pose(msg)[1])
                pose = msg.pose.pose
                (pose.position.x, pose.position.y, pose.position.z) = t
                (pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w) = q
                raw = serialize_message(msg)
            yield topic, msgtype, t_ns + k * shift, _shift_stamp(raw, k * shift) if k else raw
        anchors = {topic: anchor @ steps[topic] for topic, anchor in anchors.items()}


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
    if args.loops < 1:
        ap.error(f"--loops must be 1 or more, got {args.loops}")
    rclpy.init()
    try:
        print(json.dumps(play(args)), flush=True)
    except KeyboardInterrupt:
        return 130
    except ValueError as e:  # a bag --loops cannot loop
        print(f"ros_player: {e}", file=sys.stderr)
        return 2
    finally:
        if rclpy.ok():
            rclpy.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
