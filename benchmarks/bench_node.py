"""The ROS 2 node live: a simulated garage bag (VLP-32C by default) at 10 Hz for 2 minutes over real DDS.

    source /opt/ros/jazzy/setup.bash && python -m benchmarks node    # the defaults
    python -m benchmarks.bench_node [seconds] [mode] [sensor] [KEY=VALUE ...]

e.g. ``python -m benchmarks.bench_node 60 network OS1-128 segmentation.max_beams=64``: another sensors.py model, and
node parameters set on top of config/topometric.yaml (recorded as ``node_<mode>_<sensor>[_<key>-<value>].json``).

test/ros_player.py plays the bag at real rate with /clock (clouds best effort, odometry reliable, /tf_static
latched; a run longer than LOOP_S plays a LOOP_S bag again and again, its odometry continued: ``--loops``, so a
long run needs no long bag; its 1200 scans are whole 1 s windows) into ``python -m topometric_ros.node``
(use_sim_time, config/topometric.yaml, the given segmentation mode: network by default, the product's default);
this process listens on /diagnostics. Recorded:

- scans published, received by the node, processed, dropped (transport = published - received; the
  node's own counters for the rest), windows;
- latency from a scan's publication to the window status that ends with it on /diagnostics (wall time,
  both ends on this machine; p50, p99, max): transport + pose wait + per-scan work + window scoring;
- windows by level (OK / WARN / ERROR: the bag's drift episodes alarm);
- the node process's CPU (user + system over the run, in % of one core) and RSS (mean over the run, its first,
  middle and last minute, the growth per hour from the first and from the middle minute to the last, and the
  peak, VmHWM; RssAnon, the heap without the mapped files, the same way); the player's CPU beside it (it shares
  the cores).

A benchmark, not a test: needs rclpy (a sourced Jazzy); the figures go to OUT/node.json.
"""
from __future__ import annotations

import json
import math
import os
import shutil
import signal
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import yaml

from benchmarks.common import OUT, record
from topometric_ros.health import LEVELS

ROOT = Path(__file__).resolve().parents[1]
PLAYER = ROOT / "test" / "ros_player.py"
RATE_HZ = 10.0
TICK = os.sysconf("SC_CLK_TCK")


RSS_SPAN_S = 60  # s of RSS samples averaged at a run's start and end
LOOP_S = 120.0  # s of the longest bag simulated; longer runs loop it


def _bag(seconds: float, sensor: str = "VLP-32C") -> Path:
    from topometric_ros.bag import load_truth
    from topometric_ros.sim.drift import DriftSpec
    from topometric_ros.sim.writer import SIM_VERSION, SimConfig, simulate

    frames = int(seconds * RATE_HZ)
    path = OUT / "bags" / (f"garage_rt15_{frames}_10hz" + ("" if sensor == "VLP-32C" else f"_{sensor}"))
    truth = load_truth(path)
    if truth is None or truth["frames"] != frames or truth.get("simulator") != SIM_VERSION:
        shutil.rmtree(path, ignore_errors=True)
        print(f"  simulating {frames} scans at {RATE_HZ:g} Hz ...", flush=True)
        simulate(SimConfig(scene="garage", frames=frames, rate=RATE_HZ, drift=DriftSpec.parse("rt:1.5"),
                           sensor=sensor), path, progress=False)
    return path


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICK  # utime + stime


def _status_kb(pid: int, key: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    return 0


class _Diagnostics:
    """Window statuses on /diagnostics: window_end -> (wall receive time, values, level name)."""

    def __init__(self):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        self.node = rclpy.create_node("bench_node_listener")
        self.windows: dict[float, tuple[float, dict, str]] = {}
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on,
                                      QoSProfile(depth=500, reliability=ReliabilityPolicy.RELIABLE))
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        threading.Thread(target=self._spin, daemon=True).start()

    def _spin(self):
        try:
            self.executor.spin()
        except Exception:  # noqa: BLE001 - shutdown
            pass

    def _on(self, arr):
        now = time.time()
        for s in arr.status:
            values = {kv.key: kv.value for kv in s.values}
            if s.name.endswith(": map consistency") and "window_end" in values:
                level = LEVELS[s.level[0] if isinstance(s.level, bytes) else s.level]
                self.windows.setdefault(float(values["window_end"]), (now, values, level))

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()


def _rss_trend(rss: list[float], key: str = "node_rss_mb") -> dict:
    """The node's RSS (MB, one sample a second) in the run's first, middle and last RSS_SPAN_S, and the growth per
    hour from the first and from the middle to the last: a long run (``python -m benchmarks.bench_node 2400``)
    shows whether memory stays bounded (the second half's growth near 0) or grows on."""
    if len(rss) < 3 * RSS_SPAN_S:
        return {}
    mid = (len(rss) - RSS_SPAN_S) // 2
    first, middle, last = (statistics.mean(rss[i:i + RSS_SPAN_S]) for i in (0, mid, len(rss) - RSS_SPAN_S))
    return {f"{key}_first_minute": round(first, 1), f"{key}_middle_minute": round(middle, 1),
            f"{key}_last_minute": round(last, 1),
            f"{key}_growth_per_hour": round((last - first) / ((len(rss) - RSS_SPAN_S) / 3600), 1),
            f"{key}_growth_per_hour_second_half": round((last - middle) / ((len(rss) - RSS_SPAN_S - mid) / 3600), 1)}


def _percentile(xs: list[float], q: float) -> float:
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(round(q / 100 * (len(xs) - 1))))]


def main(seconds: float = 120.0, mode: str = "network", sensor: str = "VLP-32C", settings: dict | None = None) -> dict:
    import rclpy

    settings = settings or {}
    loops = max(1, math.ceil(seconds / LOOP_S - 1e-9))
    bag = _bag(LOOP_S if loops > 1 else seconds, sensor)
    work = OUT / "node_run"
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    params = yaml.safe_load((ROOT / "config" / "topometric.yaml").read_text())
    params["/**"]["ros__parameters"].update({"use_sim_time": True, "segmentation.mode": mode, **settings})
    (work / "params.yaml").write_text(yaml.safe_dump(params))
    env = {**os.environ, "ROS_DOMAIN_ID": os.environ.get("ROS_DOMAIN_ID", "42"),
           "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "OMP_NUM_THREADS": "1"}
    os.environ.update({k: env[k] for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")})
    rclpy.init()
    diag = _Diagnostics()
    node = subprocess.Popen([sys.executable, "-m", "topometric_ros.node", "--ros-args", "--params-file",
                             str(work / "params.yaml")], env=env, start_new_session=True,
                            stdout=open(work / "node.log", "w"), stderr=subprocess.STDOUT)
    player = None
    try:
        player = subprocess.Popen([sys.executable, str(PLAYER), str(bag), "--clock", "--clock-tail", "2",
                                   "--wait-subscribers", "120", "--loops", str(loops),
                                   "--log", str(work / "scans.jsonl")], env=env,
                                  start_new_session=True, stdout=subprocess.PIPE, stderr=open(work / "player.log", "w"))
        while not (work / "scans.jsonl").exists() or not (work / "scans.jsonl").stat().st_size:
            if player.poll() is not None:
                raise RuntimeError(f"player exited early: {(work / 'player.log').read_text()[-2000:]}")
            time.sleep(0.05)
        cpu0, cpu0_player, t0 = _cpu_s(node.pid), _cpu_s(player.pid), time.monotonic()
        rss, anon = [], []
        while player.poll() is None:
            rss.append(_status_kb(node.pid, "VmRSS") / 1024)
            anon.append(_status_kb(node.pid, "RssAnon") / 1024)
            cpu_player = _cpu_s(player.pid)
            time.sleep(1.0)
        time.sleep(3.0)  # the last windows
        wall = time.monotonic() - t0
        cpu = _cpu_s(node.pid) - cpu0
        peak = _status_kb(node.pid, "VmHWM") / 1024
        played = json.loads(player.stdout.read().decode().strip().splitlines()[-1])
    finally:
        for proc in (p for p in (player, node) if p is not None):
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGINT)
                proc.wait(20)
        diag.close()
        rclpy.shutdown()
    published = {json.loads(line)["stamp"]: json.loads(line)["wall"] for line in open(work / "scans.jsonl")}
    latencies = [1000 * (t - published[end]) for end, (t, *_) in diag.windows.items() if end in published]
    last = diag.windows[max(diag.windows)][1] if diag.windows else {}
    counters = {k: int(last.get(k, 0)) for k in ("scans_in", "scans_processed", "dropped_scans", "dropped_queue_full",
                                                   "dropped_no_pose", "scan_errors", "windows")}
    results = {
        "bag": f"garage, {sensor}, {RATE_HZ:g} Hz, {played['published'].get('/points', 0)} scans "
               f"({played['bag_s']:.0f} s{f', {loops} plays of a {LOOP_S:.0f} s bag' if loops > 1 else ''}), "
               f"rt:1.5 drift", "segmentation": mode, "settings": settings,
        "scans_published": played["published"].get("/points", 0),
        "scans_received": counters["scans_in"], "scans_processed": counters["scans_processed"],
        "dropped_transport": played["published"].get("/points", 0) - counters["scans_in"],
        "dropped_in_node": counters["dropped_scans"], "dropped_queue_full": counters["dropped_queue_full"],
        "windows": len(diag.windows),
        "latency_ms_p50": round(statistics.median(latencies), 1) if latencies else None,
        "latency_ms_p99": round(_percentile(latencies, 99), 1) if latencies else None,
        "latency_ms_max": round(max(latencies), 1) if latencies else None,
        "node_cpu_percent_of_one_core": round(100 * cpu / wall, 1),
        "node_cpu_ms_per_scan": round(1000 * cpu / max(1, counters["scans_processed"]), 1),
        "player_cpu_percent_of_one_core": round(100 * (cpu_player - cpu0_player) / wall, 1),
        "node_rss_mb_mean": round(statistics.mean(rss), 1) if rss else None, "node_rss_mb_peak": round(peak, 1),
        **_rss_trend(rss), **_rss_trend(anon, "node_rss_anon_mb"),
        "windows_by_level": {lv: sum(v[2] == lv for v in diag.windows.values()) for lv in ("OK", "WARN", "ERROR")},
        "load_average_1min_at_end": round(os.getloadavg()[0], 2),
    }
    name = "_".join([f"node_{mode}"] + ([sensor] if sensor != "VLP-32C" else [])
                    + [f"{k}-{v}" for k, v in settings.items()])
    return record(name, results)


def _setting(text: str) -> tuple[str, object]:
    """KEY=VALUE -> (key, value read as YAML: 64 -> int, on -> True)."""
    key, _, value = text.partition("=")
    return key, yaml.safe_load(value)


if __name__ == "__main__":
    args = sys.argv[1:]
    main(float(args[0]) if args else 120.0, args[1] if len(args) > 1 else "network",
         args[2] if len(args) > 2 else "VLP-32C", dict(_setting(a) for a in args[3:]))
