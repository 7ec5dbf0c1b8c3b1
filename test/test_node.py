"""The ROS 2 node as it runs on a robot: real processes over real DDS (skipped where rclpy does not import).

The node runs as its own process (``python -m topometric_ros.node``, or through ``ros2 launch``); a
simulated bag goes in through test/ros_player.py (another process: /tf_static latched, clouds with the
sensor-data QoS, odometry reliable, at real rate with /clock) or, for hand-made scans, through publishers
in this process; this process listens on /diagnostics, ~/planes and /diagnostics_agg. Every test uses its
own DDS domain on localhost. Segmentation uses the simulated clouds' label field (``segmentation.mode:
labels``) to keep the CPU low.

Live levels versus ``topometric replay`` of the same bag (one Monitor, one Health): replay processes every
scan in order, the node only the scans that reach it in time, so they may differ where the live node
drops a scan (best-effort transport, a full queue under load: a window then holds other scans) or where a
scan's odometry does not come within window.pose_wait_s (the scan waits until pose_timeout_s or is
dropped); with a different window sequence the rolling baseline differs too. On a quiet machine none of
that happens and the levels agree window for window; the test asks >= 95 %.
"""
from __future__ import annotations

import array
import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

pytest.importorskip("rclpy", reason="rclpy is not importable: source a ROS 2 Jazzy "
                                    "(source /opt/ros/jazzy/setup.bash) to run the node tests")

ROOT = Path(__file__).resolve().parents[1]
PLAYER = Path(__file__).resolve().parent / "ros_player.py"
NODE = "topometric_monitor"
CONSISTENCY = f"{NODE}: map consistency"
LEVEL_NAMES = {0: "OK", 1: "WARN", 2: "ERROR", 3: "STALE"}
BASE = {"segmentation.mode": "labels", "health.stale_after_s": 3.0}  # window.size: the default (automatic, 1 s)
BASE_WINDOWS = 10  # health.baseline_windows (default): windows before the sigma alarms start


# -------------------------------------------------------------------- processes and DDS
@pytest.fixture(scope="module")
def ros_env():
    """A DDS domain of this module's own, on localhost; rclpy up in this process."""
    import rclpy

    keep = {k: os.environ.get(k) for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "PYTHONUNBUFFERED")}
    os.environ["ROS_DOMAIN_ID"] = str(random.Random(os.getpid()).randint(20, 99))
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ["PYTHONUNBUFFERED"] = "1"
    rclpy.init()
    yield
    rclpy.shutdown()
    for k, v in keep.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


class Proc:
    """A child process in its own session (so SIGINT reaches it and its children), output in files."""

    def __init__(self, args: list[str], tmp: Path, name: str, env: dict | None = None):
        self.out, self.name = tmp / f"{name}.log", name
        self.popen = subprocess.Popen(args, stdout=open(self.out, "w"), stderr=subprocess.STDOUT,
                                      start_new_session=True, env={**os.environ, **(env or {})}, cwd=ROOT)

    def log(self) -> str:
        return self.out.read_text()

    def sigint(self, timeout: float = 10.0) -> tuple[int | None, float]:
        """SIGINT to the process group; (exit code or None when it had to be killed, seconds to exit)."""
        t0 = time.monotonic()
        if self.popen.poll() is None:
            os.killpg(self.popen.pid, signal.SIGINT)
        try:
            code = self.popen.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(self.popen.pid, signal.SIGKILL)
            self.popen.wait()
            code = None
        return code, time.monotonic() - t0

    def stop(self) -> None:
        """Make sure nothing of it is left (also after a failed test)."""
        if self.popen.poll() is None:
            self.sigint()
        try:
            os.killpg(self.popen.pid, signal.SIGKILL)  # children that outlived the leader
        except ProcessLookupError:
            pass


def write_params(path: Path, values: dict) -> Path:
    path.write_text(yaml.safe_dump({"/**": {"ros__parameters": values}}))
    return path


def start_node(tmp: Path, params: dict, name: str = "node", extra: list[str] = (),
               env: dict | None = None) -> Proc:
    """The node as a process, with ``params`` in a parameter file (top key /**)."""
    f = write_params(tmp / f"{name}.yaml", params)
    return Proc([sys.executable, "-m", "topometric_ros.node", "--ros-args", "--params-file", str(f), *extra],
                tmp, name, env)


class Listener:
    """An rclpy node in this process, spun in a thread, recording messages with their wall receive time."""

    def __init__(self, topics: dict):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        self.node = rclpy.create_node(f"test_listener_{os.getpid()}")
        self.got: dict[str, list] = {t: [] for t in topics}
        self.lock = threading.Lock()
        for topic, kind in topics.items():
            self.node.create_subscription(kind, topic, self._keep(topic),
                                          QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE))
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _keep(self, topic):
        def cb(msg):
            with self.lock:
                self.got[topic].append((time.time(), msg))
        return cb

    def _spin(self):
        from rclpy.executors import ExternalShutdownException

        try:
            self.executor.spin()
        except ExternalShutdownException:
            pass

    def messages(self, topic: str) -> list:
        with self.lock:
            return list(self.got[topic])

    def wait_for(self, topic: str, pred, timeout: float, proc: Proc | None = None):
        """First (time, msg) on topic with pred(msg), waiting up to timeout s (fails early if proc died)."""
        end = time.monotonic() + timeout
        seen = 0
        while time.monotonic() < end:
            msgs = self.messages(topic)
            for t, m in msgs[seen:]:
                if pred(m):
                    return t, m
            seen = len(msgs)
            if proc is not None and proc.popen.poll() is not None:
                pytest.fail(f"{proc.name} exited with {proc.popen.returncode}:\n{proc.log()[-3000:]}")
            time.sleep(0.05)
        return None

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()


def statuses(listener: Listener, name: str = CONSISTENCY) -> list:
    """(receive time, header stamp s, status) of every status called ``name`` on /diagnostics."""
    out = []
    for t, arr in listener.messages("/diagnostics"):
        stamp = arr.header.stamp.sec + 1e-9 * arr.header.stamp.nanosec
        out += [(t, stamp, s) for s in arr.status if s.name == name]
    return out


def level(status) -> str:
    value = status.level
    return LEVEL_NAMES[value[0] if isinstance(value, (bytes, bytearray)) else int(value)]


def values(status) -> dict:
    return {kv.key: kv.value for kv in status.values}


def windows_of(listener: Listener) -> list[dict]:
    """One record per window (by window_end), as replay's windows.json has them."""
    seen = {}
    for _, _, s in statuses(listener):
        v = values(s)
        if "window_end" in v:
            seen.setdefault(float(v["window_end"]), {"start": float(v["window_start"]), "end": float(v["window_end"]),
                                                     "level": level(s), "message": s.message, "values": v})
    return [seen[k] for k in sorted(seen)]


# -------------------------------------------------------------------- the drift bag, live and replayed
@pytest.fixture(scope="module")
def drift_bag(tmp_path_factory):
    """A 40 s garage bag at 5 Hz with one rotation+translation drift episode (20.0-29.3 s)."""
    from topometric_ros.sim.drift import DriftSpec
    from topometric_ros.sim.writer import SimConfig, simulate

    path = tmp_path_factory.mktemp("nodebag") / "garage_rt"
    summary = simulate(SimConfig(scene="garage", frames=200, rate=5.0, drift=DriftSpec.parse("rt:1.5")), path,
                       progress=False)
    return path, summary


def test_the_player_loops_a_bag_with_its_stamps_and_odometry_continued(drift_bag):
    """ros_player --loops (bench_node's long runs): plays back to back, one cloud period between them, in log-time
    order, the odometry moved on rigidly (no step at a seam beyond the bag's own motion, in position and in
    rotation, over one cloud period), /tf_static once; a bag it cannot loop is refused."""
    from nav_msgs.msg import Odometry
    from rclpy.serialization import deserialize_message

    sys.path.insert(0, str(PLAYER.parent))
    import ros_player

    from topometric_ros.bag import odometry_pose
    from topometric_ros.geometry import inverse, rotation_angle

    def play(loops):  # (topic, log time ns, header stamp ns, odometry pose or None): no cloud bytes kept
        return [(topic, t, None if topic == "/tf_static" else ros_player.stamp_ns(raw),
                 odometry_pose(deserialize_message(raw, Odometry))[1] if topic == "/odom" else None)
                for topic, _, t, raw in ros_player.looped_raw(drift_bag[0], ["/points", "/odom", "/tf_static"], loops)]

    once, looped = play(1), play(3)

    def count(msgs, topic):
        return sum(m[0] == topic for m in msgs)

    assert count(looped, "/points") == 3 * count(once, "/points") and count(looped, "/tf_static") == 1
    assert [m[1] for m in looped] == sorted(m[1] for m in looped)
    clouds = np.array([m[2] for m in looped if m[0] == "/points"])
    assert np.all(np.abs(np.diff(clouds) - np.median(np.diff(clouds))) <= 1000)  # ns; seams included

    def odometry(msgs):  # (stamps ns, poses)
        return (np.array([m[2] for m in msgs if m[0] == "/odom"]), [m[3] for m in msgs if m[0] == "/odom"])

    def moves(poses, lag=1):  # (m, degrees) from each pose to the one lag later
        rel = inverse(np.array(poses[:-lag])) @ np.array(poses[lag:])
        return np.linalg.norm(rel[:, :3, 3], axis=1), np.degrees(rotation_angle(rel[:, :3, :3]))

    stamps, poses = odometry(looped)
    assert np.all(np.diff(stamps) > 0)
    bag_stamps, bag_poses = odometry(once)
    lag = int(round(np.median(np.diff(clouds)) / np.median(np.diff(bag_stamps))))
    metres, degrees = moves(poses)
    bag_metres, bag_degrees = moves(bag_poses, lag)
    assert 0 < metres.max() <= bag_metres.max() and degrees.max() <= bag_degrees.max()
    with pytest.raises(ValueError, match="the bag has 0 clouds"):
        next(ros_player.looped_raw(drift_bag[0], ["/odom", "/tf_static"], 2))


@pytest.fixture(scope="module")
def drift_run(ros_env, drift_bag, tmp_path_factory):
    """`topometric replay` of the bag, then the node on use_sim_time fed by the player at real rate with
    /clock (going on 8 s after the data), then SIGINT. Everything the tests below look at."""
    from diagnostic_msgs.msg import DiagnosticArray
    from visualization_msgs.msg import MarkerArray

    from topometric_ros.config import load_config
    from topometric_ros.replay import ReplayOptions, replay

    bag_path, summary = drift_bag
    tmp = tmp_path_factory.mktemp("drift_run")
    params = {**BASE, "use_sim_time": True, "publish_markers": True}
    cfg = load_config(overrides={k: v for k, v in params.items() if "." in k})
    replayed = replay(bag_path, tmp / "replay", cfg, ReplayOptions(plot=False, progress=False)).windows
    listener = Listener({"/diagnostics": DiagnosticArray, f"/{NODE}/planes": MarkerArray})
    node = start_node(tmp, params)
    player = None
    try:
        # the node answers on /diagnostics once /clock runs; the player waits for its subscriptions first
        player = Proc([sys.executable, str(PLAYER), str(bag_path), "--clock", "--clock-tail", "8",
                       "--wait-subscribers", "60"], tmp, "player")
        t_play = time.time()
        player.popen.wait(120)
        played = json.loads(player.log().strip().splitlines()[-1])
        stale = listener.wait_for("/diagnostics", lambda a: any(
            s.name == CONSISTENCY and level(s) == "STALE" and s.message.startswith("no scans for") for s in a.status),
            10, node)
        code, exit_s = node.sigint()
        live = windows_of(listener)
        brief = lambda ws: [{"end": w["end"], "level": w["level"]} for w in ws]  # noqa: E731
        (tmp / "windows.json").write_text(json.dumps({"live": brief(live), "replay": brief(replayed)}))
        return {"replay": replayed, "live": live, "summary": summary, "listener": listener,
                "played": played, "t_play": t_play, "stale": stale, "exit": (code, exit_s), "log": node.log(),
                "statuses": statuses(listener), "markers": listener.messages(f"/{NODE}/planes")}
    finally:
        node.stop()
        if player is not None:
            player.stop()
        listener.close()


def test_drift_bag_alarms_inside_every_episode_and_ok_elsewhere(drift_run):
    """Every episode alarmed (WARN/ERROR) within 2 windows of its start; after the baseline, every window
    clear of the episodes (2 s either side) is OK."""
    from topometric_ros.experiments.alarms import episode_hits

    live, episodes = drift_run["live"], drift_run["summary"]["episodes"]
    assert len(live) >= 36, f"only {len(live)} of 40 windows reached /diagnostics"
    assert drift_run["played"]["published"]["/points"] == 200
    hits = episode_hits(live, episodes, within=2)
    assert episodes and all(h["detected"] for h in hits), hits
    calm = [w for w in live[BASE_WINDOWS:] if not any(w["end"] > ep["start"] - 2 and w["start"] < ep["end"] + 2
                                                      for ep in episodes)]
    assert len(calm) >= 10 and all(w["level"] == "OK" for w in calm), [(w["end"], w["level"]) for w in calm]



def test_the_default_window_is_a_second_of_scans_set_from_the_streams_stamps(drift_run):
    """No window.size given: the node starts with an automatic window, reads the 5 Hz stream's period off its
    first stamps and holds 5 scans (1 s) a window, as the replay of the same bag does."""
    assert "window automatic: 1 s of scans, set from the first 3 scans' stamps" in drift_run["log"]
    assert "window: 5 scans (automatic: 1 s at 5 Hz)" in drift_run["log"]  # logged with the first window
    assert all(w["values"]["window_scans"] == "5" for w in drift_run["live"])
    spans = [w["end"] - w["start"] for w in drift_run["live"]]
    assert spans and all(abs(span - 0.8) < 1e-6 for span in spans), sorted(set(spans))
    assert len(drift_run["replay"]) == 40 and all(
        abs(w["end"] - w["start"] - 0.8) < 1e-6 for w in drift_run["replay"])


def test_drift_bag_levels_equal_replay_in_95_percent_of_windows(drift_run):
    """Windows matched by window_end (full precision: the same stamp reads back the same double)."""
    replayed = {w["end"]: w["level"] for w in drift_run["replay"]}
    live = {w["end"]: w["level"] for w in drift_run["live"]}
    common = set(replayed) & set(live)
    assert len(common) >= 0.9 * len(replayed), (len(common), len(replayed), sorted(live))
    same = sum(replayed[k] == live[k] for k in common)
    assert same >= 0.95 * len(common), [(k, replayed[k], live[k]) for k in sorted(common) if replayed[k] != live[k]]


def test_use_sim_time_stamps_in_bag_time_and_stale_when_input_stops(drift_run):
    """On use_sim_time every status is stamped in bag time (/clock), not wall time; once the data stops
    and /clock goes on, STALE comes within health.stale_after_s (3 s) + the check period."""
    from topometric_ros.sim.writer import START_TIME

    bag_end = START_TIME + 199 / 5.0  # stamp of the last scan
    stamps = [stamp for _, stamp, _ in drift_run["statuses"] if stamp > 0]  # 0: before the first /clock
    assert len(stamps) >= 40 and all(START_TIME - 1 <= s <= bag_end + 9 for s in stamps), (min(stamps), max(stamps))
    assert drift_run["stale"] is not None, "no STALE after the input stopped"
    arr = drift_run["stale"][1]
    st = next(s for s in arr.status if s.name == CONSISTENCY)
    stamp = arr.header.stamp.sec + 1e-9 * arr.header.stamp.nanosec
    assert "no scans for" in st.message and bag_end + 3.0 <= stamp <= bag_end + 4.5, (st.message, stamp - bag_end)


def test_sigint_exits_0_within_2_s_with_workers_joined(drift_run):
    code, seconds = drift_run["exit"]
    assert code == 0 and seconds < 2.0, (code, seconds, drift_run["log"][-2000:])
    assert "worker threads left: 0" in drift_run["log"]


def test_statuses_follow_diagnostic_updater_conventions(drift_run):
    """'<node>: <task>' names, hardware_id from the cloud frame, a scan-rate FrequencyStatus near 5 Hz, a
    latency status, and window values at full precision."""
    sts = drift_run["statuses"]
    assert {s.hardware_id for _, _, s in sts} >= {"velodyne"}
    names = {s.name for _, arr in drift_run["listener"].messages("/diagnostics") for s in arr.status}
    assert {CONSISTENCY, f"{NODE}: scan rate", f"{NODE}: latency"} <= names
    rate_sts = statuses(drift_run["listener"], f"{NODE}: scan rate")
    rates = [float(values(s)["Actual frequency (Hz)"]) for _, _, s in rate_sts
             if level(s) == "OK" and "Actual frequency (Hz)" in values(s)]
    assert rates and abs(np.median(rates) - 5.0) < 0.5, rates
    lat = [float(values(s)["max_s"]) for _, _, s in statuses(drift_run["listener"], f"{NODE}: latency")
           if values(s).get("windows", "0") != "0"]
    assert lat and np.median(lat) < 1.0, lat  # stamp -> window result in sim time
    w = drift_run["live"][5]
    assert re.fullmatch(r"1700000\d\d\d\.\d+", w["values"]["window_start"]), w["values"]["window_start"]
    # the drift rates come with their standard errors (finite, non-negative)
    assert all(0.0 <= float(w["values"][f"{r}_se"]) < float("inf") for r in ("rot_rate", "trans_rate")), w["values"]


def test_sim_time_played_fast_with_odometry_before_the_first_clock(ros_env, drift_bag, tmp_path):
    """use_sim_time, two odometry messages before any /clock (the node clock reads 0: no receive time, not
    an offset of the stamps' whole epoch), then the bag at 4× with /clock: no clock fault, the scans scored,
    and the scan rate in sim time (5 Hz, not 20); diagnostic_updater.period given as a whole number."""
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from topometric_ros import bag

    bag_path, _ = drift_bag
    stamps, _ = bag.read_odometry(bag_path, "/odom")
    listener = Listener({"/diagnostics": DiagnosticArray})
    odom = listener.node.create_publisher(Odometry, "/odom", QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
    # clock_jump_s 1.5: at 4x an executor that a busy CPU holds back 0.2 s (wall) reads as a 0.8 s jump, while the
    # fault this test guards against (a node clock of 0 against the stamps' epoch) is 1.7e9 s
    node = start_node(tmp_path, {**BASE, "use_sim_time": True, "health.clock_jump_s": 1.5},
                      extra=["-p", "diagnostic_updater.period:=1"])
    player = None
    try:
        end = time.monotonic() + 60
        while listener.node.count_subscribers("/odom") == 0 and time.monotonic() < end:
            assert node.popen.poll() is None, node.log()[-3000:]
            time.sleep(0.1)
        for stamp in stamps[:2]:
            msg = Odometry()
            msg.header.stamp.sec, msg.header.stamp.nanosec = int(stamp), int(round((stamp % 1) * 1e9))
            msg.header.frame_id, msg.child_frame_id, msg.pose.pose.orientation.w = "map", "base_link", 1.0
            odom.publish(msg)
        time.sleep(1.0)
        player = Proc([sys.executable, str(PLAYER), str(bag_path), "--clock", "--rate", "4", "--clock-tail", "4",
                       "--wait-subscribers", "60"], tmp_path, "player")
        player.popen.wait(120)
        time.sleep(1.0)
    finally:
        node.stop()
        if player is not None:
            player.stop()
        listener.close()
    clock = statuses(listener, f"{NODE}: clock")
    assert clock and all(level(s) == "OK" for _, _, s in clock), [s.message for _, _, s in clock if level(s) != "OK"]
    assert all(values(s).get("dropped_clock", "0") == "0" for _, _, s in clock)
    windows = windows_of(listener)  # 40 at most (200 scans, 5 a window)
    assert len(windows) >= 25, (len(windows), node.log()[-2000:])
    rates = [float(values(s)["Actual frequency (Hz)"]) for _, _, s in statuses(listener, f"{NODE}: scan rate")
             if int(values(s).get("Events in window", 0)) > 0]
    assert rates and 3.5 < np.median(rates) < 6.5, rates


def test_markers_are_in_the_map_frame(drift_run):
    arrays = [m for _, m in drift_run["markers"]]
    assert len(arrays) >= 30
    cubes = [m for a in arrays for m in a.markers if m.type == m.CUBE]
    assert cubes and {m.header.frame_id for m in cubes} == {"map"}
    bad = [(m.scale.x, m.scale.y) for m in cubes if not (0 < m.scale.y <= m.scale.x < 250)]  # 120 m range
    assert not bad, bad


# -------------------------------------------------------------------- hand-made scans
def rclpy_cloud(points: np.ndarray, stamp: float, frame: str, labels: np.ndarray | None = None):
    from builtin_interfaces.msg import Time
    from sensor_msgs.msg import PointCloud2, PointField
    from std_msgs.msg import Header
    from types import SimpleNamespace

    from topometric_ros.cloud import make_cloud

    types = SimpleNamespace(PointCloud2=PointCloud2, PointField=PointField, Header=Header, Time=Time)
    fields = {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2]}
    if labels is not None:
        fields["label"] = labels
    return make_cloud({k: np.ascontiguousarray(v) for k, v in fields.items()}, stamp, frame, types,
                      data=lambda d: array.array("B", d.tobytes()), align=4)


def rclpy_odom(stamp: float, pose: np.ndarray, frame="map", child="base_link"):
    from nav_msgs.msg import Odometry

    from topometric_ros import geometry

    q, t = geometry.pose_to_quat(pose)
    o = Odometry()
    o.header.frame_id, o.child_frame_id = frame, child
    ns = int(stamp * 1e9)
    o.header.stamp.sec, o.header.stamp.nanosec = ns // 1_000_000_000, ns % 1_000_000_000
    o.pose.pose.position.x, o.pose.pose.position.y, o.pose.pose.position.z = map(float, t)
    o.pose.pose.orientation.x, o.pose.pose.orientation.y, o.pose.pose.orientation.z, o.pose.pose.orientation.w = \
        map(float, q)
    return o


class Feeder:
    """Publishers of this process on /points (sensor data), /odom (reliable) and /tf_static (latched)."""

    def __init__(self, listener: Listener, sensor_offset=(0.0, 0.0, 0.5), child="base_link"):
        from geometry_msgs.msg import TransformStamped
        from nav_msgs.msg import Odometry
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
        from sensor_msgs.msg import PointCloud2
        from tf2_msgs.msg import TFMessage

        node = listener.node
        self.points = node.create_publisher(PointCloud2, "/points", qos_profile_sensor_data)
        self.odom = node.create_publisher(Odometry, "/odom", 10)
        self.tf = node.create_publisher(TFMessage, "/tf_static", QoSProfile(
            depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        t = TransformStamped()
        t.header.frame_id, t.child_frame_id = "base_link", "lidar"
        t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = map(float, sensor_offset)
        t.transform.rotation.w = 1.0
        self.tf.publish(TFMessage(transforms=[t]))
        self.sensor_offset = np.array(sensor_offset)
        self.child = child  # the odometry's child frame (/tf_static links base_link to the cloud frame lidar)
        self.last_odom = 0.0

    def wait_matched(self, timeout=20.0):
        end = time.monotonic() + timeout
        matched = lambda: self.points.get_subscription_count() and self.odom.get_subscription_count()  # noqa: E731
        while time.monotonic() < end and not matched():
            time.sleep(0.05)
        assert matched(), "the node did not subscribe to /points and /odom"

    def wait_tf_static(self, listener: Listener, node: Proc, points, pose, labels=None, timeout=20.0):
        """Scans (``points`` at ``pose``) until the node says its extrinsic comes from our /tf_static. The node
        links the frames only once a scan has told it the cloud's frame, and a scan sent right after the match
        can still be lost (best effort; the node's reader may not know our writer yet), so one is sent each
        second; /tf_static is latched but may arrive after /points and /odom matched."""
        end = time.monotonic() + timeout
        linked = lambda a: any(s.name == CONSISTENCY and values(s).get("extrinsic") == "tf_static"  # noqa: E731
                               for s in a.status)
        while time.monotonic() < end:
            self.scan(points, pose, labels)
            if listener.wait_for("/diagnostics", linked, 1.0, node):
                return
        raise AssertionError(f"the node never took the extrinsic from /tf_static:\n{node.log()[-2000:]}")

    def scan(self, points, pose, labels=None, now=None):
        """Odometry just before and after ``now`` (s, wall), then the cloud stamped ``now``."""
        now = time.time() if now is None else now
        for t in (now - 0.05, now + 0.15):
            if t > self.last_odom:  # odometry stamps only go forward
                self.odom.publish(rclpy_odom(t, pose, child=self.child))
                self.last_odom = t
        self.points.publish(rclpy_cloud(points, now, "lidar", labels))


def wall_patch(width=4.0, height=2.0, distance=3.0, step=0.025, seed=0):
    """A wall seen from the sensor: the plane x = distance, y in ±width/2, z in ±height/2 (m, sensor
    frame), a grid with 5 mm noise; labels all WALL."""
    from topometric_ros import classes

    y, z = np.meshgrid(np.arange(-width / 2, width / 2 + 1e-9, step), np.arange(-height / 2, height / 2 + 1e-9, step))
    rng = np.random.default_rng(seed)
    pts = np.column_stack([distance + rng.normal(0, 0.005, y.size), y.ravel(), z.ravel()]).astype(np.float32)
    return pts, np.full(len(pts), classes.WALL, np.uint8)


def yaw_pose(yaw_deg: float, t):
    from topometric_ros import geometry

    return geometry.yaw_pose(*t, np.radians(yaw_deg))


def test_markers_have_the_true_plane_extents_in_the_map_frame(ros_env, tmp_path):
    """A 4 m × 2 m wall 3 m ahead of a sensor 0.5 m above base_link, base_link at (10, 5, 0) turned 90°:
    the marker is 4 × 2 (± 5 cm; ±1σ would give 2.3 × 1.2), centred at (10, 8, 0.5) in 'map', its normal
    along the map's y axis."""
    from diagnostic_msgs.msg import DiagnosticArray
    from visualization_msgs.msg import MarkerArray

    listener = Listener({"/diagnostics": DiagnosticArray, f"/{NODE}/planes": MarkerArray})
    node = start_node(tmp_path, {**BASE, "window.size": 3, "publish_markers": True, "health.min_planes": 1})
    try:
        feeder = Feeder(listener)
        feeder.wait_matched()
        pts, labels = wall_patch()
        pose = yaw_pose(90.0, (10.0, 5.0, 0.0))
        feeder.wait_tf_static(listener, node, pts, pose, labels)  # the node learns the frames, links them by /tf_static
        t0 = time.time()
        got = None
        for _ in range(30):  # the markers of a window whose scans all came after that
            feeder.scan(pts, pose, labels)
            time.sleep(0.3)
            ends = [float(values(s)["window_end"]) for _, _, s in statuses(listener)
                    if float(values(s).get("window_start", "0")) > t0]
            got = next((a for _, a in listener.messages(f"/{NODE}/planes")
                        if any(m.type == m.CUBE for m in a.markers) and any(
                            abs(a.markers[0].header.stamp.sec + 1e-9 * a.markers[0].header.stamp.nanosec - e) < 1e-3
                            for e in ends)), None)
            if got:
                break
        assert got, "no MarkerArray"
        cubes = [m for m in got.markers if m.type == m.CUBE]
        assert len(cubes) == 3  # one wall per scan, 3 scans per window
        assert all(values(s)["extrinsic"] == "tf_static" for _, _, s in statuses(listener)
                   if float(values(s).get("window_start", "0")) > t0)  # each window says where its extrinsic came from
        for m in cubes:
            assert m.header.frame_id == "map"
            assert abs(m.scale.x - 4.0) < 0.05 and abs(m.scale.y - 2.0) < 0.05, (m.scale.x, m.scale.y)
            p = m.pose.position
            np.testing.assert_allclose([p.x, p.y, p.z], [10.0, 8.0, 0.5], atol=0.05)
            from topometric_ros import geometry

            q = m.pose.orientation
            r = geometry.pose_from_quat([q.x, q.y, q.z, q.w], [0, 0, 0])[:3, :3]
            assert abs(abs(r[1, 2]) - 1) < 1e-3  # the cube's thin axis (the normal) along map y
    finally:
        node.stop()
        listener.close()


def test_odometry_of_a_frame_tf_static_does_not_link_is_named_in_the_status_and_on_the_console(ros_env, tmp_path):
    """Odometry of imu_link, /tf_static only base_link -> lidar: the status's extrinsic says the identity stands
    in and what /tf_static holds, and the console says it once (before: 'config', nothing else)."""
    from diagnostic_msgs.msg import DiagnosticArray

    listener = Listener({"/diagnostics": DiagnosticArray})
    node = start_node(tmp_path, BASE)
    try:
        feeder = Feeder(listener, child="imu_link")
        feeder.wait_matched()
        pts, labels = wall_patch()
        gap = lambda a: any(s.name == CONSISTENCY and "/tf_static holds base_link -> lidar" in  # noqa: E731
                            values(s).get("extrinsic", "") for s in a.status)
        got, end = None, time.monotonic() + 30
        while got is None and time.monotonic() < end:
            feeder.scan(pts, yaw_pose(0.0, (0.0, 0.0, 0.0)), labels)
            got = listener.wait_for("/diagnostics", gap, 1.0, node)
        assert got, node.log()[-3000:]
        extrinsic = values(next(s for s in got[1].status if s.name == CONSISTENCY))["extrinsic"]
        assert extrinsic.startswith("config (no /tf_static chain links the odometry's child frame imu_link to the "
                                    "cloud frame lidar"), extrinsic
        end = time.monotonic() + 15
        while "no /tf_static chain links" not in node.log() and time.monotonic() < end:
            feeder.scan(pts, yaw_pose(0.0, (0.0, 0.0, 0.0)), labels)
            time.sleep(0.5)
    finally:
        node.stop()
        listener.close()
    assert node.log().count("no /tf_static chain links the odometry's child frame imu_link") == 1, node.log()[-3000:]


def test_use_sim_time_without_a_clock_is_said_on_the_console(ros_env, tmp_path):
    """use_sim_time with no /clock: the node's clock stands at 0 and no status goes out; the console says why
    (steady time), and a latency no queue explains names the stamps' time base."""
    from topometric_ros.node import NO_CLOCK_WARN_S, time_base_hint

    node = start_node(tmp_path, {**BASE, "use_sim_time": True})
    try:
        end = time.monotonic() + 60 + 2 * NO_CLOCK_WARN_S  # warm-up, then the steady timer
        while "no /clock came" not in node.log() and time.monotonic() < end and node.popen.poll() is None:
            time.sleep(0.5)
    finally:
        node.stop()
    assert "use_sim_time is true but no /clock came in 5 s or more" in node.log(), node.log()[-3000:]
    assert "a sensor clock counting from power-on" in time_base_hint(9.6e7) and time_base_hint(4.0) == ""


def test_scans_missing_by_their_stamps_warn_in_the_scan_rate_status(ros_env):
    """44 of 120 clouds arrived at a rate the default limits call fine: 'scan rate' says WARN with how many
    never came; 1 of 20 missing is no WARN."""
    from rclpy.clock import Clock, ClockType

    from topometric_ros.node import ScanRate, missing_scans_text

    assert missing_scans_text(44, 76).startswith("76 of 120 scans missing by their stamps: lost on the way")
    assert missing_scans_text(19, 1) == "" and missing_scans_text(0, 0) == ""
    lost = {"n": 0}
    rate = ScanRate(Clock(clock_type=ClockType.STEADY_TIME), 1.0, 1000.0, missing=lambda: lost["n"])
    for _ in range(10):
        rate.tick()
    lost["n"] = 20
    time.sleep(0.2)
    import diagnostic_updater

    stat = rate.run(diagnostic_updater.DiagnosticStatusWrapper())
    assert stat.level == b"\x01" and stat.message.startswith("20 of 30 scans missing"), (stat.level, stat.message)


def _real_bag_with_poses() -> Path | None:
    """../shared/real-sensors' OS1-128 capture with poses (3 scans, KISS-ICP /odom, /tf_static), if here."""
    for root in (os.environ.get("TOPOMETRIC_REAL_SENSORS", ""), ROOT.parent / "shared" / "real-sensors",
                 "/work/shared/real-sensors"):
        if root and (Path(root) / "os1_128_lowbw_3scans_poses" / "metadata.yaml").is_file():
            return Path(root) / "os1_128_lowbw_3scans_poses"
    return None


BIG_BUFFERS = 64 * 2 ** 20  # bytes: DDS socket buffers for 6 MB clouds (docs/ros.md, "Big clouds")


def _rmem_max() -> int:
    try:
        return int(Path("/proc/sys/net/core/rmem_max").read_text())
    except (OSError, ValueError):
        return 0


@pytest.mark.skipif(_real_bag_with_poses() is None, reason="no ../shared/real-sensors (set TOPOMETRIC_REAL_SENSORS)")
@pytest.mark.skipif(_rmem_max() < BIG_BUFFERS, reason="net.core.rmem_max below 64 MB: 6 MB clouds cannot arrive "
                                                      "over DDS (docs/ros.md: sudo sysctl -w net.core.rmem_max=67108864)")
def test_a_real_ouster_bag_through_the_node_in_the_default_mode(ros_env, tmp_path):
    """A real OS1-128 capture (ouster-ros layout: 128 x 1024 organised, NaN no-returns, per-point t; 6 MB a
    cloud) played over Cyclone DDS with the bigger socket buffers docs/ros.md gives, to the node in the default
    mode (network segmentation, layout read off each cloud, deskew): its 3 scans make one window, scored, with
    none lost and the extrinsic from /tf_static. The clouds go reliable (points_qos reliable): over best effort
    a loaded CI machine once lost one of the three, and the window needs all three."""
    from diagnostic_msgs.msg import DiagnosticArray

    dds = {"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp", "CYCLONEDDS_URI": (
        f'<CycloneDDS><Domain id="any"><Internal><SocketReceiveBufferSize min="{BIG_BUFFERS}B"/></Internal>'
        "</Domain></CycloneDDS>")}
    listener = Listener({"/diagnostics": DiagnosticArray})
    f = write_params(tmp_path / "node.yaml", {"window.size": 3, "points_topic": "/ouster/points", "odom_topic": "/odom",
                                              "points_qos": "reliable"})
    node = Proc([sys.executable, "-m", "topometric_ros.node", "--ros-args", "--params-file", str(f)], tmp_path,
                "node", env=dds)
    player = None
    try:
        listener.wait_for("/diagnostics", lambda a: any(  # the node is up and has subscribed (warmed up)
            s.name == CONSISTENCY and not s.message.startswith("starting") for s in a.status), 120, node)
        player = Proc([sys.executable, str(PLAYER), str(_real_bag_with_poses()), "--rate", "0.5", "--reliable-clouds",
                       "--wait-subscribers", "30", "--topics", "/ouster/points", "/odom", "/tf_static"],
                      tmp_path, "player", env=dds)
        player.popen.wait(60)
        got = listener.wait_for("/diagnostics", lambda a: any(
            s.name == CONSISTENCY and "window_end" in values(s) for s in a.status), 30, node)
        last = statuses(listener)[-1][2] if statuses(listener) else None
        assert got, f"no window scored: {last and (last.message, values(last))}\n{player.log()[-2000:]}"
        status = next(s for s in got[1].status if s.name == CONSISTENCY and "window_end" in values(s))
        v = values(status)
        assert v["extrinsic"] == "tf_static" and v["windows"] == "1", v
        assert v["cloud_note"] == "" and v["bad_beam_points"] == "0", v  # every field of the driver's clouds used
        assert abs(float(v["window_end"]) - float(v["window_start"]) - 0.2) < 0.01, v  # scans 1-3 of a 10 Hz sweep
        assert int(v["scans_processed"]) == 3 and int(v["dropped_scans"]) == 0, v
        assert int(v["n_planes"]) >= 3 * 12, v  # 13-96 planes a scan on these captures (topometric inspect)
        assert level(status) in ("OK", "WARN"), status.message  # 3 scans at 2.45 m/s, KISS-ICP poses: no ERROR
    finally:
        node.stop()
        if player is not None:
            player.stop()
        listener.close()


def test_every_status_says_starting_while_the_node_warms_up_and_the_inputs_wait_for_it(ros_env, tmp_path):
    """A first start after an install (numba's cache empty: the kernels compile, tens of seconds): all four
    statuses go out STALE 'starting' from the start, nothing is subscribed meanwhile, then the node subscribes
    and says what it monitors."""
    from diagnostic_msgs.msg import DiagnosticArray

    ours = {CONSISTENCY, f"{NODE}: scan rate", f"{NODE}: latency", f"{NODE}: clock"}
    starting = lambda a: {s.name for s in a.status if level(s) == "STALE" and s.message.startswith(  # noqa: E731
        "starting: warming up")} == ours
    listener = Listener({"/diagnostics": DiagnosticArray})
    node = start_node(tmp_path, {**BASE, "points_topic": "/warm_points"},
                      env={"NUMBA_CACHE_DIR": str(tmp_path / "numba")})
    try:
        assert listener.wait_for("/diagnostics", starting, 60, node), [s.message for _, _, s in statuses(listener)]
        assert "warm in" not in node.log(), "the warm-up ended before the first status: no cold cache?"
        assert listener.node.count_subscribers("/warm_points") == 0
        got = listener.wait_for("/diagnostics", lambda a: any(
            s.name == CONSISTENCY and s.message.startswith("no scans yet") for s in a.status), 240, node)
        assert got, [s.message for _, _, s in statuses(listener)][-3:]
        assert listener.node.count_subscribers("/warm_points") == 1
    finally:
        node.stop()
        listener.close()
    log = node.log()
    assert log.index("warm in") < log.index("monitoring /warm_points"), log[-3000:]
    messages = [s.message for _, _, s in statuses(listener) if s.message != "Node starting up"]  # the Updater's
    first = next(i for i, m in enumerate(messages) if not m.startswith("starting"))          # own, as a task is added
    assert first >= 3 and all(not m.startswith("starting") for m in messages[first:]), messages


def test_no_clouds_says_whether_the_topic_has_a_publisher(ros_env, tmp_path):
    """STALE without clouds: the status says the cloud topic has no publisher, and once one is there (a
    publisher that sends nothing: as if its clouds were lost on the way) that it has one, and where to look;
    without odometry, the same for the odometry topic and a QoS that cannot match."""
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import PointCloud2

    listener = Listener({"/diagnostics": DiagnosticArray})
    node = start_node(tmp_path, {**BASE, "points_topic": "/quiet_points"})
    try:
        stale = lambda words: lambda a: any(  # noqa: E731
            s.name == CONSISTENCY and level(s) == "STALE" and words in s.message for s in a.status)
        assert listener.wait_for("/diagnostics", stale("/quiet_points has no publisher"), 30, node)
        listener.node.create_publisher(PointCloud2, "/quiet_points", qos_profile_sensor_data)
        got = listener.wait_for("/diagnostics", stale("/quiet_points has 1 publisher"), 30, node)
        assert got, [s.message for _, _, s in statuses(listener)][-3:]
        message = next(s.message for s in got[1].status if s.name == CONSISTENCY)
        assert message.startswith("no scans yet") and "socket buffers, docs/ros.md" in message, message
        # a cloud comes through, then none: the publisher stopped, not a transport that never delivered
        import array
        from types import SimpleNamespace

        from builtin_interfaces.msg import Time
        from sensor_msgs.msg import PointField
        from std_msgs.msg import Header

        from topometric_ros.cloud import make_cloud

        types = SimpleNamespace(PointCloud2=PointCloud2, PointField=PointField, Header=Header, Time=Time)
        pts = np.random.default_rng(0).uniform(-5, 5, (500, 3)).astype(np.float32)
        cloud = make_cloud({"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]}, time.time(), "lidar", types,
                           data=lambda d: array.array("B", d.tobytes()))
        publisher = listener.node.create_publisher(PointCloud2, "/quiet_points", qos_profile_sensor_data)
        end = time.monotonic() + 20  # best effort, and discovery takes a moment: until the node counts one
        while time.monotonic() < end and not listener.wait_for("/diagnostics", lambda a: any(
                s.name == CONSISTENCY and int(values(s).get("scans_in", "0")) > 0 for s in a.status), 0.2, node):
            cloud.header.stamp.sec = int(time.time())
            publisher.publish(cloud)
        got = listener.wait_for("/diagnostics", stale("which sent clouds before: has the driver stopped"), 30, node)
        assert got, [s.message for _, _, s in statuses(listener)][-3:]
        status = next(s for s in got[1].status if s.name == CONSISTENCY)
        message, v = status.message, values(status)
        assert message.startswith("no scans for") and "socket buffers" not in message, message
        # no odometry ever came: the scans wait for it, and the counters say where every scan is
        assert int(v["waiting_for_odometry"]) >= 1 and int(v["scans_in"]) == \
            int(v["scans_processed"]) + int(v["dropped_scans"]) + int(v["waiting_for_odometry"]), v
        # no odometry either: no publisher, then one offering best effort, which odom_qos reliable never hears
        assert "(/odom has no publisher)" in message, message
        from nav_msgs.msg import Odometry

        listener.node.create_publisher(Odometry, "/odom", qos_profile_sensor_data)
        got = listener.wait_for("/diagnostics", stale("its publisher offers best effort, which odom_qos "
                                                      "reliable never receives: set odom_qos sensor_data"), 30, node)
        assert got, [s.message for _, _, s in statuses(listener)][-3:]
    finally:
        node.stop()
        listener.close()
    log = node.log()  # the console says it too (once the node's first health.stale_after_s are over), not
    assert "[topometric_monitor]: map consistency: STALE: no " in log, log[-3000:]  # /diagnostics alone
    assert "(/odom has no publisher)" in log, log[-3000:]


def test_every_scan_failing_gives_an_error_with_the_reason_within_2_s(ros_env, tmp_path):
    """Labels mode on clouds without a label field: every scan fails, scans keep arriving (no STALE). The
    node says ERROR with the reason within 2 s of the first cloud; SIGINT while scans still arrive: exit 0
    within 2 s, workers joined."""
    from diagnostic_msgs.msg import DiagnosticArray

    listener = Listener({"/diagnostics": DiagnosticArray})
    node = start_node(tmp_path, BASE)
    try:
        feeder = Feeder(listener)
        feeder.wait_matched()
        pts, _ = wall_patch()
        pose = yaw_pose(0.0, (0.0, 0.0, 0.0))
        t_first = time.time()
        found = None
        while time.time() - t_first < 5.0 and found is None:
            feeder.scan(pts, pose)
            found = listener.wait_for("/diagnostics", lambda a: any(
                s.name == CONSISTENCY and level(s) in ("WARN", "ERROR") for s in a.status), 0.1, node)
        assert found is not None, "the node stayed silent while every scan failed"
        st = next(s for s in found[1].status if s.name == CONSISTENCY)
        assert found[0] - t_first < 2.0, found[0] - t_first
        assert "no label field" in st.message and "scan_errors" in st.message, st.message
        assert int(values(st)["scan_errors"]) >= 1 and values(st)["scans_processed"] == "0"
        for _ in range(5):
            feeder.scan(pts, pose)
            time.sleep(0.1)
        code, seconds = node.sigint()
        assert code == 0 and seconds < 2.0 and "worker threads left: 0" in node.log(), (code, seconds)
    finally:
        node.stop()
        listener.close()


# -------------------------------------------------------------------- parameters
@pytest.mark.parametrize("bad, words", [
    ({"health.stale_after_s": 0}, ["health.stale_after_s", "out of range"]),  # int for a float leaf
    ({"window.size": 500.0}, ["window.size", "out of range"]),  # float for an int leaf
    ({"window.size": 1}, ["parameter 'window.size' = 1: a window needs 2 scans or more; 0 = automatic"]),
    ({"window.sise": 10}, ["unknown parameter", "window.sise"]),
    ({"segmentation.mode": "magic"}, ["segmentation.mode", "one of"]),
    ({"latency_warn_s": "-5"}, ["latency_warn_s", "out of range"]),  # a quoted number: checked once it is one
    ({"points_topic": "velodyne points"}, ["parameter 'points_topic' = 'velodyne points' is not a topic name",
                                           "must not contain characters"]),  # before the warm-up, not in spin
])
def test_bad_parameters_stop_the_node_with_a_message_naming_them(ros_env, tmp_path, bad, words):
    node = start_node(tmp_path, {**BASE, **bad})
    try:
        code = node.popen.wait(60)
    finally:
        node.stop()
    log = node.log()
    assert code == 2 and all(w in log for w in words) and "Traceback" not in log, (code, log[-2000:])


def test_a_command_line_parameter_out_of_range_is_refused_too(ros_env, tmp_path):
    node = start_node(tmp_path, BASE, extra=["-p", "health.warn_sigma:=-1"])
    try:
        code = node.popen.wait(60)
    finally:
        node.stop()
    assert code == 2 and "health.warn_sigma" in node.log()


def test_a_plain_yaml_given_as_a_parameter_file_is_refused_with_how_one_looks(ros_env, tmp_path):
    """replay's --config takes a plain YAML; the node's --params-file needs the ROS 2 form: exit 2 and a line
    saying so (rcl's parser fails inside rclpy.init), not a traceback."""
    plain = tmp_path / "plain.yaml"
    plain.write_text("window:\n  size: 3\n")
    node = Proc([sys.executable, "-m", "topometric_ros.node", "--ros-args", "--params-file", str(plain)], tmp_path,
                "plain")
    try:
        code = node.popen.wait(60)
    finally:
        node.stop()
    log = node.log()
    assert code == 2 and "Traceback" not in log, (code, log[-2000:])
    assert "cannot start: " in log and "Couldn't parse params file" in log and "ros__parameters:" in log, log


# -------------------------------------------------------------------- ros2 launch and the aggregator
@pytest.fixture(scope="module")
def ament_prefix(tmp_path_factory):
    """An install prefix laid out as colcon lays out this package (setup.py's data_files and the
    console script in lib/topometric_ros), so `ros2 launch topometric_ros ...` finds it."""
    if shutil.which("ros2") is None:
        pytest.skip("ros2 (ros2cli) not on PATH: source a ROS 2 Jazzy with ros2launch")
    prefix = tmp_path_factory.mktemp("install")
    share = prefix / "share" / "topometric_ros"
    (prefix / "share" / "ament_index" / "resource_index" / "packages").mkdir(parents=True)
    (prefix / "share" / "ament_index" / "resource_index" / "packages" / "topometric_ros").write_text("")
    for sub in ("launch", "config"):
        shutil.copytree(ROOT / sub, share / sub)
    shutil.copy(ROOT / "package.xml", share / "package.xml")
    exe = prefix / "lib" / "topometric_ros" / "topometric_monitor"
    exe.parent.mkdir(parents=True)
    exe.write_text(f"#!/bin/sh\nexec {sys.executable} -m topometric_ros.node \"$@\"\n")
    exe.chmod(0o755)
    return prefix


def test_launch_topics_win_over_the_yaml_under_a_namespace_and_the_aggregator_groups_us(
        ros_env, tmp_path, ament_prefix):
    """ros2 launch with namespace:=robot1, a parameter file that sets other topics, window.size 7 and
    use_sim_time, and points_topic:=/launch_points: the node subscribes to /launch_points (not the file's), keeps
    the file's odom topic, window.size 7 and use_sim_time (no use_sim_time argument given) under the namespace
    ('/**'), and the real diagnostic_aggregator (config/analyzers.yaml) shows our status under its SLAM/Map
    consistency path on /diagnostics_agg (this test publishes /clock)."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from rcl_interfaces.srv import GetParameters, SetParameters
    from rclpy.parameter import Parameter
    from rosgraph_msgs.msg import Clock

    STALE_LEVEL = DiagnosticStatus.STALE

    yaml_file = write_params(tmp_path / "mine.yaml", {**BASE, "points_topic": "/yaml_points",
                                                      "odom_topic": "/yaml_odom", "window.size": 7,
                                                      "use_sim_time": True})
    env = {"AMENT_PREFIX_PATH": f"{ament_prefix}:{os.environ.get('AMENT_PREFIX_PATH', '')}"}
    listener = Listener({"/diagnostics_agg": DiagnosticArray})
    clock = listener.node.create_publisher(Clock, "/clock", 10)
    listener.node.create_timer(0.02, lambda: clock.publish(Clock(clock=listener.node.get_clock().now().to_msg())))
    launch = Proc(["ros2", "launch", "topometric_ros", "monitor.launch.py", f"config:={yaml_file}",
                   "points_topic:=/launch_points", "namespace:=robot1", "aggregator:=true"], tmp_path, "launch", env)
    try:
        agg = listener.wait_for("/diagnostics_agg", lambda a: any(
            s.name.startswith("/Aggregation/SLAM/Map consistency/") and "map consistency" in s.name
            for s in a.status), 60, launch)
        assert agg is not None, launch.log()[-3000:]
        names = sorted(s.name for s in agg[1].status)
        assert any(n.endswith(CONSISTENCY) or n.endswith("map consistency") for n in names), names
        # the group counts our four statuses (num_items): not "Expected 3, found 4" (ERROR) once they are in
        group = listener.wait_for("/diagnostics_agg", lambda a: any(
            s.name == "/Aggregation/SLAM/Map consistency" and "xpected" not in s.message and s.level != STALE_LEVEL
            for s in a.status), 20, launch)
        assert group is not None, [(s.name, s.message) for s in agg[1].status]
        end = time.monotonic() + 10  # the aggregator's status can arrive before discovery shows our endpoints
        while not listener.node.get_subscriptions_info_by_topic("/launch_points") and time.monotonic() < end:
            time.sleep(0.1)
        subs = listener.node.get_subscriptions_info_by_topic("/launch_points")
        assert [(s.node_name, s.node_namespace) for s in subs] == [(NODE, "/robot1")], subs
        assert listener.node.get_subscriptions_info_by_topic("/yaml_points") == []
        assert [s.node_name for s in listener.node.get_subscriptions_info_by_topic("/yaml_odom")] == [NODE]
        client = listener.node.create_client(GetParameters, f"/robot1/{NODE}/get_parameters")
        assert client.wait_for_service(20)
        future = client.call_async(GetParameters.Request(names=["window.size", "points_topic", "use_sim_time"]))
        end = time.monotonic() + 10
        while not future.done() and time.monotonic() < end:
            time.sleep(0.05)
        size, topic, sim_time = future.result().values
        assert size.integer_value == 7 and topic.string_value == "/launch_points" and sim_time.bool_value
        # every parameter is read once at start: the Updater's too (a change would be accepted and ignored)
        setter = listener.node.create_client(SetParameters, f"/robot1/{NODE}/set_parameters")
        assert setter.wait_for_service(20)
        future = setter.call_async(SetParameters.Request(parameters=[
            Parameter("diagnostic_updater.period", Parameter.Type.DOUBLE, 5.0).to_parameter_msg(),
            Parameter("use_sim_time", Parameter.Type.BOOL, False).to_parameter_msg()]))
        end = time.monotonic() + 10
        while not future.done() and time.monotonic() < end:
            time.sleep(0.05)
        for refused in future.result().results:  # use_sim_time: a change would stop the node's clock
            assert not refused.successful and "read-only" in refused.reason, refused
    finally:
        code, seconds = launch.sigint(15)
        launch.stop()
        listener.close()
    log = launch.log()
    assert code == 0 and "[topometric_monitor-1]: process has finished cleanly" in log, log[-3000:]
    assert "[topometric_monitor-1] Traceback" not in log, log[-3000:]


def test_a_launch_argument_that_is_not_true_or_false_starts_no_node(ros_env, tmp_path, ament_prefix):
    """aggregator:=yes: launch stops with the reason before any node starts (before: the monitor started, then
    launch failed on the aggregator's condition and left it running with no parent)."""
    env = {"AMENT_PREFIX_PATH": f"{ament_prefix}:{os.environ.get('AMENT_PREFIX_PATH', '')}"}
    launch = Proc(["ros2", "launch", "topometric_ros", "monitor.launch.py", "aggregator:=yes",
                   "namespace:=no_orphan_here"], tmp_path, "launch", env)
    try:
        code = launch.popen.wait(60)
    finally:
        launch.stop()
    assert code != 0 and "aggregator must be true or false, got 'yes'" in launch.log(), launch.log()[-3000:]
    time.sleep(1.0)
    left = subprocess.run(["pgrep", "-f", "__ns:=/no_orphan_here"], capture_output=True, text=True).stdout.split()
    for pid in left:
        os.kill(int(pid), signal.SIGKILL)
    assert not left, "a node outlived its launch"
