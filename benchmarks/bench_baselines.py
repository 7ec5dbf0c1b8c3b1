"""MME / MPV speed and accuracy on one core.

1. map-metrics' depth reference data (104k points, radius 0.2 m): exact MME and MPV, time and error
   against the reference values (goal: 1e-8, <= 0.3 s each; map-metrics C++ needs 3.3 / 3.8 s).
2. Simulated VLP-32 windows (garage, floor2; 5 / 10 / 15 scans, radius 1.0 m): the fast approximation
   (exact=False), and the exact value where it is feasible, with the relative error (goal: 15 scans
   <= 10 s each, within 0.5 %).

Run: ``python -m benchmarks baselines`` (``TOPOMETRIC_BENCH_FULL=1`` adds exact 15-scan garage, minutes;
``TOPOMETRIC_BENCH_BASE=<git revision>`` times that revision's _neighbours.py on the reference data too,
interleaved with the current one, for before/after numbers from one run under the same load).
"""
from __future__ import annotations

import os
import statistics
import subprocess
import time
import types
from pathlib import Path

import numpy as np

from benchmarks.common import median_ms, record, single_core

#: windows (scene -> scan counts) whose exact value is computed too (exact cost grows with the square of
#: the density: 5 floor2 scans hold ~5e9 neighbour pairs, minutes on one core)
EXACT = {"garage": (5,)}


def _timed(fn):
    t = time.perf_counter()
    value = fn()
    return value, time.perf_counter() - t


def neighbours_at(rev: str):
    """topometric_ros/metrics/_neighbours.py as of git revision ``rev``, as a module (None when git cannot
    show it)."""
    root = Path(__file__).resolve().parents[1]
    shown = subprocess.run(["git", "show", f"{rev}:topometric_ros/metrics/_neighbours.py"], cwd=root,
                           capture_output=True, text=True)
    if shown.returncode != 0:
        return None
    module = types.ModuleType(f"neighbours_{rev}")
    exec(compile(shown.stdout.replace("from .. import geometry", "from topometric_ros import geometry"),
                 f"{rev}:_neighbours.py", "exec"), module.__dict__)
    return module


def reference(results: dict, repeats: int = 5, base: str | None = None) -> None:
    from topometric_ros.metrics import _neighbours, reference_data
    from topometric_ros.metrics.mme import mme_from_covariances
    from topometric_ros.metrics.mpv import mpv_from_covariances

    data = reference_data.load()
    if data is None:
        results["reference"] = f"skipped: no data at {reference_data.folder()}"
        return
    clouds, poses, _ = data
    versions = {"": _neighbours}
    if base:
        old = neighbours_at(base)
        if old is None:
            results["reference_base"] = f"skipped: git cannot show {base}"
        else:
            versions[f"base_{base}_"] = old
            results["reference_base"] = base
    metrics = {"mme": (mme_from_covariances, reference_data.REF_MME),
               "mpv": (mpv_from_covariances, reference_data.REF_MPV)}

    def run(nb, from_covariances):  # as mme() / mpv(): aggregate, neighbourhoods, metric
        return from_covariances(*nb.map_covariances(nb.aggregate_map(clouds, poses), reference_data.RADIUS))

    samples = {(v, m): [] for v in versions for m in metrics}
    cpu = {(v, m): [] for v in versions for m in metrics}
    for k in range(repeats + 1):  # the first round warms up; versions interleaved, same load for both
        for prefix, nb in versions.items():
            for name, (fn, ref) in metrics.items():
                t, c = time.perf_counter(), time.process_time()
                value = run(nb, fn)
                if k:
                    samples[prefix, name].append(time.perf_counter() - t)
                    cpu[prefix, name].append(time.process_time() - c)
                else:
                    results[f"reference_{prefix}{name}_value"] = value
                    results[f"reference_{prefix}{name}_abs_error"] = abs(value - ref)
    for (prefix, name), secs in samples.items():
        results[f"reference_{prefix}{name}_s_median"] = round(statistics.median(secs), 3)
        results[f"reference_{prefix}{name}_s_min"] = round(min(secs), 3)
        # CPU seconds of this process: less sensitive than wall time to other jobs on the shared core
        results[f"reference_{prefix}{name}_cpu_s_median"] = round(statistics.median(cpu[prefix, name]), 3)


def windows(results: dict, sizes=(5, 10, 15), repeats: int = 3, full: bool = False) -> None:
    from topometric_ros.metrics.mme import mme
    from topometric_ros.metrics.mpv import mme_mpv, mpv
    from topometric_ros.sim.frames import simulated_frames

    for scene in ("garage", "floor2"):
        frames, _ = simulated_frames(scene, max(sizes))
        for n in sizes:
            clouds = [f.points for f in frames[:n]]
            poses = np.stack([f.pose for f in frames[:n]])
            key = f"{scene}_{n}"
            results[f"{key}_points"] = int(sum(len(c) for c in clouds))
            fast = {}
            for name, fn in (("mme", mme), ("mpv", mpv)):
                fast[name] = fn(clouds, poses, exact=False)
                med, _ = median_ms(lambda: fn(clouds, poses, exact=False), repeats=repeats, warmup=0)
                results[f"{key}_{name}_fast_value"] = fast[name]
                results[f"{key}_{name}_fast_s_median"] = round(med / 1000, 2)
            if n in EXACT.get(scene, ()) or (full and scene == "garage"):
                (e_mme, e_mpv), secs = _timed(lambda: mme_mpv(clouds, poses, exact=True))
                results[f"{key}_exact_mme_mpv_s"] = round(secs, 1)
                results[f"{key}_mme_exact_value"] = e_mme
                results[f"{key}_mpv_exact_value"] = e_mpv
                results[f"{key}_mme_fast_rel_error"] = abs(fast["mme"] / e_mme - 1)
                results[f"{key}_mpv_fast_rel_error"] = abs(fast["mpv"] / e_mpv - 1)


def mom_window(results: dict, scene: str = "garage", n: int = 5) -> None:
    """MOM with the orthogonal subsets extracted from the first scan (no speed goal; map-metrics' way)."""
    from topometric_ros.metrics.mom import mom
    from topometric_ros.sim.frames import simulated_frames

    frames, _ = simulated_frames(scene, n)
    value, secs = _timed(lambda: mom([f.points for f in frames], np.stack([f.pose for f in frames])))
    results[f"{scene}_{n}_mom_value"] = value
    results[f"{scene}_{n}_mom_s"] = round(secs, 2)


def main() -> dict:
    single_core()
    results: dict = {}
    reference(results, base=os.environ.get("TOPOMETRIC_BENCH_BASE"))
    windows(results, full=os.environ.get("TOPOMETRIC_BENCH_FULL") == "1")
    mom_window(results)
    return record("baselines", results)


if __name__ == "__main__":
    main()
