"""Fleet audit scaling (issue 17): 40 short simulated bags through ``topometric audit``.

Acceptance: 2 workers >= 1.7x faster than 1 (wall) on this machine; every result identical to a single replay
of that bag; Ray's overhead per bag against ``--engine local``.

The bags (4 scenes x 10 trajectory seeds, 20 scans = 4 s at 5 Hz, VLP-32C, every 4th with per-pose drift
noise) are simulated once under OUT/audit/bags and kept. Each variant audits all 40 with ``force`` (nothing
cached) into its own folder, in this process:

- ``local``: --engine local (one bag after another, in-process, one torch / Open3D thread);
- ``ray_1``: a local Ray with 1 worker; ``ray_2``: with 2 workers.

Ray is started (and timed: ``ray_start_s``) before each Ray variant, so the variant's wall time is the audit
alone (task submission, worker processes starting and importing the package, results coming back, reports
written). ``overhead_ms_per_bag`` = (ray_1 wall - local wall) / bags. Medians over ``repeats``. The windows of
every bag (metrics, levels, reasons; not the ms_* timings) are compared with a single ``replay`` of it.
The load of the machine (os.getloadavg) is recorded before and after: it is shared.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import time
from pathlib import Path

from benchmarks.common import OUT, record

SCENES = ("office1", "garage", "floor2", "office2")


def simulate_bags(root: Path, bags: int, frames: int) -> list[Path]:
    from topometric_ros.sim.drift import DriftSpec
    from topometric_ros.sim.writer import SimConfig, simulate

    paths = []
    for i in range(bags):
        path = root / f"night_{i:02d}"
        if not (path / "metadata.yaml").is_file():
            cfg = SimConfig(scene=SCENES[i % len(SCENES)], frames=frames, rate=5.0, speed=1.0, seed=300 + i,
                            drift=DriftSpec.parse("rt:2.0" if i % 4 == 3 else "none", "noise"))
            simulate(cfg, path, progress=False)
        paths.append(path)
    return paths


def _windows(path: Path) -> list[dict]:
    doc = json.loads(Path(path).read_text())
    return [{k: v for k, v in r.items() if not k.startswith("ms_")} for r in doc["windows"]]


def main(bags: int = 40, frames: int = 20, repeats: int = 1, segmentation: str = "labels") -> dict:
    from topometric_ros import engine
    from topometric_ros.audit import audit
    from topometric_ros.config import load_config
    from topometric_ros.replay import ReplayOptions, replay

    root = OUT / "audit"
    load_before = os.getloadavg()
    t = time.perf_counter()
    paths = simulate_bags(root / "bags", bags, frames)
    sim_s = time.perf_counter() - t
    config = load_config(overrides={"segmentation.mode": segmentation})
    walls: dict[str, list[float]] = {"local": [], "ray_1": [], "ray_2": []}
    starts: dict[str, list[float]] = {"ray_1": [], "ray_2": []}
    for _ in range(repeats):
        for variant in walls:
            if variant == "local":
                res = audit(paths, root / variant, config, engine="local", force=True, progress=False)
            else:
                workers = int(variant[-1])
                engine.shutdown()
                t = time.perf_counter()
                engine.ensure_ray(workers=workers)
                starts[variant].append(time.perf_counter() - t)
                res = audit(paths, root / variant, config, engine="ray", workers=workers, force=True, progress=False)
            assert res.summary["failed"] == 0, [r for r in res.rows if r["status"] == "failed"]
            walls[variant].append(res.summary["wall_s"])
            print(f"  {variant:6s} {res.summary['wall_s']:7.1f} s  (load {os.getloadavg()[0]:.1f})", flush=True)
    engine.shutdown()
    # every result identical to a single replay of that bag, made now with this config (never a stale one)
    same = 0
    shutil.rmtree(root / "single", ignore_errors=True)
    for p in paths:
        single = root / "single" / p.name
        replay(p, single, config, ReplayOptions(progress=False, plot=False))
        ref = _windows(single / "windows.json")
        if all(_windows(root / v / "bags" / p.name / "windows.json") == ref for v in walls):
            same += 1
    med = {k: statistics.median(v) for k, v in walls.items()}
    results = {
        "bags": bags, "scans_per_bag": frames, "segmentation": segmentation, "repeats": repeats,
        "cpus": os.cpu_count(), "simulate_s": round(sim_s, 1),
        "wall_s": {k: round(v, 2) for k, v in med.items()}, "wall_s_all": walls,
        "ray_start_s": {k: round(statistics.median(v), 2) for k, v in starts.items()},
        "speedup_2_vs_1": round(med["ray_1"] / med["ray_2"], 2),
        "speedup_2_vs_local": round(med["local"] / med["ray_2"], 2),
        "overhead_ms_per_bag": round(1000 * (med["ray_1"] - med["local"]) / bags, 1),
        "identical_to_single_replay": f"{same}/{bags}",
        "load_before": [round(x, 2) for x in load_before], "load_after": [round(x, 2) for x in os.getloadavg()],
    }
    record("audit", results)
    return results


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bags", type=int, default=40)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--segmentation", default="labels", choices=("labels", "network", "none"))
    a = ap.parse_args()
    main(a.bags, a.frames, a.repeats, a.segmentation)
