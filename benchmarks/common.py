"""Helpers shared by the benchmarks: pin to one core, time medians, write a JSON record."""
from __future__ import annotations

import json
import os
import platform
import statistics
import time
from pathlib import Path
from typing import Callable

OUT = Path(os.environ.get("TOPOMETRIC_BENCH_OUT", "out/bench"))


def single_core() -> None:
    """Pin this process to one CPU and every thread pool we use to one thread."""
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    import open3d as o3d

    o3d.utility.set_max_threads(1)
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:
        pass


def median_ms(fn: Callable[[], object], repeats: int = 20, warmup: int = 2) -> tuple[float, list[float]]:
    """Median wall time of fn() in ms over repeats (after warmup calls), and all samples."""
    for _ in range(warmup):
        fn()
    samples = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        samples.append(1000 * (time.perf_counter() - t))
    return statistics.median(samples), samples


def record(name: str, results: dict) -> Path:
    """Write OUT/<name>.json with the machine description and print it."""
    OUT.mkdir(parents=True, exist_ok=True)
    doc = {"benchmark": name, "machine": platform.platform(), "cpus": os.cpu_count(), "results": results}
    path = OUT / f"{name}.json"
    path.write_text(json.dumps(doc, indent=2))
    for key, value in results.items():
        print(f"  {key:40s} {value}")
    print(f"  -> {path}")
    return path
