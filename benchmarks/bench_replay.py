"""Replay throughput and memory: a 600-scan simulated VLP-32C garage bag through ``topometric replay``.

Goal (issue 5): >= 25 scans/s on one pinned core, CPU only, segmentation on (5x real time for 5 Hz data);
peak RSS <= 1.5 GB. Each repeat is a fresh ``topometric replay`` process (so RSS is the replay's alone);
scans/s is the replay loop's own figure (reading, parsing, segmentation, planes, metrics, health,
diagnostics writing), wall_s includes start-up (imports, network load). On a shared machine wall time
depends on the load, so the process's CPU time is recorded too: scans_per_cpu_s (whole process, start-up
included) is what one free core would do at least.
"""
from __future__ import annotations

import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import OUT, record, single_core


def _segmentation_mode() -> str:
    """network when the segmentation package and its weights load, else labels (recorded)."""
    try:
        from topometric_ros.config import Config
        from topometric_ros.pipeline import default_segmenter

        default_segmenter(Config().segmentation)
        return "network"
    except Exception as e:  # noqa: BLE001 - the benchmark still runs, and says so
        print(f"  segmentation network unavailable ({type(e).__name__}: {e}); using the bag's labels")
        return "labels"


def _bag(frames: int) -> Path:
    from topometric_ros.sim.drift import DriftSpec
    from topometric_ros.sim.writer import SimConfig, load_truth, simulate

    path = OUT / "bags" / f"garage_rt15_{frames}"
    truth = load_truth(path)
    if truth is None or truth["frames"] != frames:
        shutil.rmtree(path, ignore_errors=True)
        simulate(SimConfig(scene="garage", frames=frames, drift=DriftSpec.parse("rt:1.5")), path, progress=False)
    return path


def main(frames: int = 600, repeats: int = 3) -> dict:
    single_core()  # the replay subprocesses inherit the pinned core
    bag = _bag(frames)
    mode = _segmentation_mode()
    runs = []
    for _ in range(repeats):
        out = Path(tempfile.mkdtemp())
        env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
        t = time.perf_counter()
        usage0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        before = usage0.ru_maxrss
        proc = subprocess.run([sys.executable, "-m", "topometric_ros.cli", "replay", str(bag), "--out", str(out),
                               "--quiet", "--no-plot", "--segmentation", mode, "--set", "segmentation.threads=1"],
                              capture_output=True, text=True, env=env)
        wall = time.perf_counter() - t
        usage = resource.getrusage(resource.RUSAGE_CHILDREN)
        rss_kb = usage.ru_maxrss
        cpu = (usage.ru_utime + usage.ru_stime) - (usage0.ru_utime + usage0.ru_stime)
        if proc.returncode != 0:
            raise RuntimeError(f"replay failed ({proc.returncode}): {proc.stderr[-2000:]}")
        summary = json.loads((out / "windows.json").read_text())["summary"]
        runs.append({"scans_per_s": summary["scans_per_s"], "x_realtime": summary["x_realtime"], "wall_s": wall,
                     "cpu_s": cpu, "scans_per_cpu_s": summary["scans_processed"] / cpu,
                     "peak_rss_mb": max(rss_kb, before) / 1024, "windows": summary["windows"],
                     "levels": summary["levels"], "dropped": summary["counters"]["dropped_scans"]})
        shutil.rmtree(out)
    med = lambda k: round(statistics.median(r[k] for r in runs), 2)  # noqa: E731
    results = {
        "bag": f"garage, {frames} scans, VLP-32C, rt:1.5 drift", "segmentation": mode,
        "scans_per_s_median": med("scans_per_s"), "x_realtime_median": med("x_realtime"),
        "wall_s_median": med("wall_s"), "cpu_s_median": med("cpu_s"),
        "scans_per_cpu_s_median": med("scans_per_cpu_s"),
        "peak_rss_mb_max": round(max(r["peak_rss_mb"] for r in runs), 1),
        "scans_per_s_all": [r["scans_per_s"] for r in runs], "windows": runs[0]["windows"],
        "levels": runs[0]["levels"], "dropped_scans": runs[0]["dropped"],
        "goal_scans_per_s": 25, "goal_peak_rss_mb": 1536,
    }
    return record("replay", results)


if __name__ == "__main__":
    main()
