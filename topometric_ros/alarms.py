"""Drift-alarm detection table on held-out simulated bags (issue 5's acceptance measure).

Bags with drift episodes (modes r, t, rt × scales 1, 1.5, 2) and drift-free bags are simulated on a floor
plan and trajectories no training or test split uses (layout seed HELD_OUT_LAYOUT, seeds from
HELD_OUT_SEED), replayed deterministically, and scored:
- an episode is DETECTED when one of the first ``within`` windows that end after its start is WARN/ERROR;
- a FALSE WARN is a WARN/ERROR window of a drift-free bag; reported per 10 minutes of drift-free data.
"""
from __future__ import annotations

import csv
import json
import shutil
from dataclasses import asdict
from pathlib import Path

import numpy as np

from .config import Config
from .replay import ReplayOptions, replay
from .sim.drift import DriftSpec
from .sim.writer import SimConfig, load_truth, simulate

HELD_OUT_LAYOUT = 7  # floor-plan seed no split uses
HELD_OUT_SEED = 5000  # trajectory seeds from here
MODES = ("r", "t", "rt")
SCALES = (1.0, 1.5, 2.0)
ALARM = ("WARN", "ERROR")


def plan_bags(scenes: list[str], frames: int, free_bags: int, free_frames: int, rate: float = 5.0) -> list[SimConfig]:
    """The held-out bag set: one bag per (mode, scale), then ``free_bags`` drift-free bags; scenes cycle."""
    runs, k = [], 0
    for mode in MODES:
        for scale in SCALES:
            runs.append(SimConfig(scene=scenes[k % len(scenes)], layout_seed=HELD_OUT_LAYOUT,
                                  seed=HELD_OUT_SEED + k, frames=frames, rate=rate,
                                  drift=DriftSpec(mode, scale)))
            k += 1
    for j in range(free_bags):
        runs.append(SimConfig(scene=scenes[(k + j) % len(scenes)], layout_seed=HELD_OUT_LAYOUT,
                              seed=HELD_OUT_SEED + k + j, frames=free_frames, rate=rate))
    return runs


def _name(sim: SimConfig) -> str:
    d = sim.drift
    tag = "free" if d.mode == "none" else f"{d.mode}{d.scale:g}"
    return f"{sim.scene}_{tag}_s{sim.seed}"


def _bag(sim: SimConfig, bags: Path, progress: bool) -> Path:
    """Simulate the bag unless an identical one is already there (truth.json carries the config)."""
    path = bags / _name(sim)
    truth = load_truth(path)
    if truth is not None and truth["config"] == {**asdict(sim), "drift": asdict(sim.drift)}:
        return path
    if path.exists():
        shutil.rmtree(path)
    simulate(sim, path, progress=progress)
    return path


def episode_hits(records: list[dict], episodes: list[dict], within: int = 2) -> list[dict]:
    """Per episode: detected (bool) and latency in windows (0 = the first window ending after its start)."""
    out = []
    ends = np.array([r["end"] for r in records])
    for ep in episodes:
        first = int(np.searchsorted(ends, ep["start"], side="right"))
        latency = None  # first alarm in a window overlapping the episode (or the first ``within`` windows)
        for k in range(first, len(records)):
            if records[k]["start"] > ep["end"] and k >= first + within:
                break
            if records[k]["level"] in ALARM:
                latency = k - first
                break
        out.append({"start": ep["start"], "end": ep["end"], "latency_windows": latency,
                    "detected": latency is not None and latency < within,
                    "covered": first < len(records)})
    return out


def run_detection(out: str | Path, config: Config, scenes: list[str], frames: int = 400, free_bags: int = 4,
                  free_frames: int = 750, within: int = 2, progress: bool = True) -> dict:
    """Simulate (or reuse) the held-out bags under out/bags, replay each to out/replays, score, and write
    out/detection.json, out/detection.csv and out/detection.png. Returns the table."""
    out = Path(out)
    bags, replays = out / "bags", out / "replays"
    rows, free = [], {"windows": 0, "false_warn_windows": 0, "minutes": 0.0, "bags": []}
    for sim in plan_bags(scenes, frames, free_bags, free_frames):
        path = _bag(sim, bags, progress)
        res = replay(path, replays / _name(sim), config, ReplayOptions(progress=progress, plot=True))
        if res.summary["error"]:
            raise RuntimeError(f"replay of {path} failed: {res.summary['error']}")
        truth = load_truth(path)
        if sim.drift.mode == "none":
            alarms = [r for r in res.windows if r["level"] in ALARM]
            free["windows"] += len(res.windows)
            free["false_warn_windows"] += len(alarms)
            free["minutes"] += res.summary["bag_s"] / 60
            free["bags"].append({"bag": path.name, "windows": len(res.windows), "false_warns": len(alarms),
                                 "reasons": sorted({r["message"] for r in alarms})})
        else:
            hits = [h for h in episode_hits(res.windows, truth["episodes"], within) if h["covered"]]
            rows.append({"bag": path.name, "mode": sim.drift.mode, "scale": sim.drift.scale,
                         "episodes": len(hits), "detected": sum(h["detected"] for h in hits),
                         "latencies": [h["latency_windows"] for h in hits],
                         "scans_per_s": res.summary["scans_per_s"]})
    n_ep = sum(r["episodes"] for r in rows)
    n_hit = sum(r["detected"] for r in rows)
    per_10min = 10 * free["false_warn_windows"] / free["minutes"] if free["minutes"] else float("nan")
    table = {"within_windows": within, "window_size": config.window.size, "rows": rows,
             "episodes": n_ep, "detected": n_hit, "detection_rate": n_hit / n_ep if n_ep else float("nan"),
             "drift_free": free, "false_warns_per_10min": per_10min}
    _write(out, table)
    return table


def _write(out: Path, table: dict) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "detection.json").write_text(json.dumps(table, indent=1))
    with open(out / "detection.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["bag", "mode", "scale", "episodes", "detected", "latencies"])
        for r in table["rows"]:
            w.writerow([r["bag"], r["mode"], r["scale"], r["episodes"], r["detected"],
                        " ".join("-" if x is None else str(x) for x in r["latencies"])])
        fr = table["drift_free"]
        w.writerow(["drift-free", "none", 0, 0, 0, f"{fr['false_warn_windows']} false WARN in {fr['minutes']:.1f} min"])
    from .reports import pyplot

    plt = pyplot()

    fig, ax = plt.subplots(figsize=(7, 3.2))
    labels = [f"{r['mode']}×{r['scale']:g}" for r in table["rows"]]
    rate = [r["detected"] / r["episodes"] if r["episodes"] else np.nan for r in table["rows"]]
    ax.bar(labels, rate, color="#4a7ab0")
    ax.axhline(0.95, color="grey", ls="--", lw=1, label="goal 95 %")
    ax.set_ylim(0, 1.05)
    ax.set_ylabel(f"detected within {table['within_windows']} windows")
    ax.set_title(f"drift episodes {table['detected']}/{table['episodes']}; "
                 f"false WARN {table['false_warns_per_10min']:.2f} per 10 min drift-free")
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "detection.png", dpi=110)
    plt.close(fig)


def format_detection(table: dict) -> str:
    """The detection table for people."""
    lines = [f"{'mode':>5} {'scale':>5} {'episodes':>8} {'detected':>8}  latency (windows)   bag"]
    for r in table["rows"]:
        lat = " ".join("-" if x is None else str(x) for x in r["latencies"])
        lines.append(f"{r['mode']:>5} {r['scale']:>5g} {r['episodes']:>8} {r['detected']:>8}  {lat:<18}  {r['bag']}")
    f = table["drift_free"]
    lines += ["", f"detected within {table['within_windows']} windows: {table['detected']}/{table['episodes']} "
              f"= {100 * table['detection_rate']:.1f} %  (goal >= 95 %)",
              f"false WARN: {f['false_warn_windows']} of {f['windows']} drift-free windows in {f['minutes']:.1f} min "
              f"= {table['false_warns_per_10min']:.2f} per 10 min  (goal <= 1)"]
    for b in f["bags"]:
        if b["false_warns"]:
            lines.append(f"  {b['bag']}: {b['false_warns']} false WARN: {'; '.join(b['reasons'][:3])}")
    return "\n".join(lines)

