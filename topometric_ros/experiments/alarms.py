"""Drift-alarm detection table on simulated bags never used for tuning (issue 5's acceptance measure).

Two disjoint bag sets (SPLITS) on trajectory seeds that no training or test split uses:
- ``calibration``: thresholds are chosen here (``calibrate``: the smallest health.warn_sigma whose false
  WARN rate on the calibration drift-free data stays within a margin of the target). Several floor plans:
  metric statistics differ between floor plans, so one plan is not enough to calibrate on;
- ``evaluation``: the held-out set the detection table is reported on, with the calibrated config; its
  bags cycle through four floor plans that neither the calibration nor the network's training data uses.
Each group of a set: one bag per drift episode mode and scale (r, t, rt × 1, 1.5, 2) and ``free_bags``
drift-free bags.
Scoring:
- an episode is DETECTED when one of the first ``within`` windows that end after its start is WARN/ERROR;
- a FALSE WARN is a WARN/ERROR window of a drift-free bag; reported per 10 minutes of drift-free data.
Replays are kept under out/replays; a replay whose bag and non-health config are unchanged is reused and
only the health assessment (health.py, a pure function of the window sequence) is run again.
"""
from __future__ import annotations

import csv
import json
import shutil
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from ..config import Config, HealthConfig, flatten
from ..health import RATES, Health, assessment_fields
from ..replay import RECORD_FORMAT, ReplayOptions, load_windows, replay
from ..reports import write_json
from ..sim.drift import DriftSpec
from ..audit import network_digest
from ..bag import load_truth
from ..sim.writer import SIM_VERSION, SimConfig, bag_identity, simulate
from .odometry import VOXEL_SIZE

#: split -> groups of (floor-plan seeds the bags cycle through, first trajectory seed). Disjoint from each
#: other and from the segmentation splits (layout 0 train/test seeds 0../1000.., unseen layout 7 seeds 0..).
#: "calibration" holds every bag thresholds were ever looked at on (layout 7: the first detection table;
#: layout 9: the first held-out table, which showed one floor plan does not calibrate another; layouts 11-14:
#: the held-out table whose sigma false alarms, two parallel pillar faces joined in one co-plane group, were
#: looked at; layouts 15-18: the evaluation split until 2026-11-29, looked at by fixes and defaults and, like
#: every layout above, among the floor plans the shipped network trained on); "evaluation" is fresh floor plans
#: and seeds, outside SEGMENTATION_LAYOUTS, used only to report.
SPLITS = {"calibration": [((7,), 5000), ((9,), 9000), ((11, 12, 13, 14), 11000), ((15, 16, 17, 18), 15000)],
          "evaluation": [((41, 42, 43, 44), 41000)]}
#: Floor plans (layout seeds) the segmentation network's data may come from: layouts 0-39 were simulated for
#: its trainings (data/gpu_train/0-19 trained the shipped weights, model_card.json), 31 is eval-seg's unseen
#: plan, 32 its validation. The evaluation split's plans lie outside, so they are new to the network too.
SEGMENTATION_LAYOUTS = frozenset(range(40))
MODES = ("r", "t", "rt")
SCALES = (1.0, 1.5, 2.0)
ALARM = ("WARN", "ERROR")
GOAL_FALSE_PER_10MIN = 1.0
SIGMA_GRID = tuple(float(x) for x in np.round(np.arange(2.0, 10.01, 0.25), 2))
RATE_MARGIN = 2.0  # a drift-rate WARN limit should sit at least this factor above the drift-free maximum
RATE_EPISODE_FRACTION = 1 / 3  # ... and at most this fraction of the weakest episode's rate
CLEAN_AFTER_S = 10.0  # s after a drift episode's end before a drift bag's windows count as drift-free


#: Speeds of the transfer table (m/s: a slow AMR, walking / handheld, a legged robot or fast AMR, a car) and
#: the scenes each is driven in (a car at 10 m/s only fits the garage).
SPEEDS = (0.3, 1.5, 4.0, 10.0)
SPEED_SCENES = {0.3: ("office1", "office2", "floor2"), 1.5: ("floor2", "office1", "garage", "office2"),
                4.0: ("garage", "floor2"), 10.0: ("garage",)}
#: Sensors each split's bags cycle through: the evaluation's are held out from calibration.
SPLIT_SENSORS = {"calibration": ("VLP-32C", "OS1-64"), "evaluation": ("VLP-16", "OS1-128", "XT32", "HDL-32E")}
#: What plays the SLAM beside the monitor: the bag's own odometry (the simulator's error model, SimConfig.odometry)
#: or KISS-ICP run on the bag's clouds; drift episodes go on top of either.
ESTIMATES = ("sim", "kiss")


@dataclass(frozen=True)
class Run:
    """One replay of the plan: a simulated bag and whose poses the monitor judges (ESTIMATES)."""

    sim: SimConfig
    estimate: str = "sim"
    kiss_voxel: float = VOXEL_SIZE  # m, KISS-ICP's voxel size (estimate kiss; 0: its own rule, max range / 100)

    @property
    def name(self) -> str:
        return _name(self.sim) + self.estimate_tag

    @property
    def estimate_tag(self) -> str:
        """'' (the bag's odometry), '_kiss', or '_kiss<voxel m>' for a voxel size other than VOXEL_SIZE."""
        return "" if self.estimate == "sim" else f"_{self.estimate}{self.voxel_tag}"

    @property
    def voxel_tag(self) -> str:
        """'' for KISS-ICP's default voxel size (VOXEL_SIZE), else the size in m ('0.1'; '0': its own rule)."""
        return "" if self.kiss_voxel == VOXEL_SIZE else f"{self.kiss_voxel:g}"


def plan_bags(scenes: list[str], frames: int, free_bags: int, free_frames: int, rate: float = 5.0,
              split: str = "evaluation", speeds=(1.2,), estimates=("sim",), odometry: str = "ideal",
              scales=SCALES, sensors=None, groups: int | None = None, kiss_voxel: float = VOXEL_SIZE) -> list[Run]:
    """The runs of ``split``: per group of the split (its first ``groups``, or all), speed and estimate, one bag
    per (mode, scale), then ``free_bags`` drift-free bags; scenes cycle (those of SPEED_SCENES a speed fits in,
    among ``scenes``), and so do the split's sensors (SPLIT_SENSORS, or ``sensors``). The estimates of one bag
    share it. kiss_voxel: KISS-ICP's voxel size, m (0: its own rule)."""
    if split not in SPLITS:
        raise ValueError(f"split must be one of {', '.join(SPLITS)}, got {split!r}")
    bad = [e for e in estimates if e not in ESTIMATES]
    if bad or not estimates:
        raise ValueError(f"estimates must be among {', '.join(ESTIMATES)}, got {', '.join(bad) or 'none'}")
    if not (np.isfinite(kiss_voxel) and kiss_voxel >= 0):
        raise ValueError(f"kiss_voxel must be >= 0 (0: KISS-ICP's own rule), got {kiss_voxel}")
    for name, values in (("speeds", speeds), ("scales", scales), ("rate", (rate,))):
        if not len(values) or not all(np.isfinite(v) and v > 0 for v in values):
            raise ValueError(f"{name} must be > 0, got {', '.join(map(str, values)) or 'none'}")
    sensors = tuple(sensors or SPLIT_SENSORS[split])
    runs = []
    for layouts, seed0 in SPLITS[split][:groups]:
        for i, speed in enumerate(speeds):
            fits = [s for s in scenes if s in SPEED_SCENES.get(speed, scenes)] or list(scenes)
            drifts = [DriftSpec(m, k) for m in MODES for k in scales] + [DriftSpec()] * free_bags
            for k, drift in enumerate(drifts):
                sim = SimConfig(scene=fits[k % len(fits)], layout_seed=layouts[k % len(layouts)],
                                seed=seed0 + 100 * i + k, frames=free_frames if drift.mode == "none" else frames,
                                rate=rate, speed=speed, drift=drift, odometry=odometry, sensor=sensors[k % len(sensors)])
                runs += [Run(sim, e, kiss_voxel) for e in estimates]
    return runs


def split_description(split: str, groups: int | None = None) -> str:
    """'layouts 11, 12, 13, 14, seeds 11000+' for reports (the split's first ``groups``, or all)."""
    return "; ".join(f"layout{'s' * (len(l) > 1)} {', '.join(map(str, l))}, seeds {s}+"
                     for l, s in SPLITS[split][:groups])


def _name(sim: SimConfig) -> str:
    d = sim.drift
    tag = "free" if d.mode == "none" else f"{d.mode}{d.scale:g}"
    extra = "" if (sim.speed, sim.sensor, sim.odometry) == (1.2, "VLP-32C", "ideal") else \
        f"_v{sim.speed:g}_{sim.sensor}_{sim.odometry}"
    return f"{sim.scene}_{tag}_L{sim.layout_seed}_s{sim.seed}{extra}"


def _bag(sim: SimConfig, bags: Path, progress: bool) -> Path:
    """Simulate the bag unless an identical one is already there (truth.json carries the config)."""
    path = bags / _name(sim)
    want = bag_identity(json.loads(json.dumps({"config": {**asdict(sim), "drift": asdict(sim.drift)},
                                               "simulator": SIM_VERSION})))  # as truth.json has it
    if bag_identity(load_truth(path)) == want:
        return path
    if path.exists():
        shutil.rmtree(path)
    simulate(sim, path, progress=progress)
    return path


def episode_hits(records: list[dict], episodes: list[dict], within: int = 2) -> list[dict]:
    """Per episode: detected (bool), latency in windows (0 = the first window ending after its start), and
    ``truly_over``: the estimate's TRUE drift (ground truth, :func:`real_drift`) passed a WARN limit in one of
    those first ``within`` windows (an episode on top of a SLAM's own error can stay under the limits)."""
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
                    "truly_over": any(real_drift(r) for r in records[first:first + within]),
                    "covered": first < len(records)})
    return out


def reassess(records: list[dict], health: HealthConfig) -> list[dict]:
    """The window records assessed again with ``health`` (a fresh Health over the same window sequence):
    copies with level, message, z and limits (health.assessment_fields) replaced. Exactly what a replay with
    that health config gives."""
    h, out = Health(health), []
    for r in records:
        res = _Window(r["pne"], r["cpv"], r["n_planes"], r.get("rot_rate", np.nan), r.get("trans_rate", np.nan),
                      r.get("speed", np.nan), r.get("turn_rate", np.nan), r.get("agreement", np.nan),
                      r.get("agreement_scan", -1), r.get("n_scans", 0), r.get("agreement_stamp", np.nan),
                      r.get("rot_rate_se", np.nan), r.get("trans_rate_se", np.nan))
        a = h.assess(res)
        out.append({**r, "level": res.level, "message": res.message, **assessment_fields(a)})
    return out


class _Window:
    """The fields of a WindowResult health.py reads."""

    def __init__(self, pne: float, cpv: float, n_planes: int, rot_rate: float, trans_rate: float,
                 speed: float = np.nan, turn_rate: float = np.nan, agreement: float = np.nan,
                 agreement_scan: int = -1, n_scans: int = 0, agreement_stamp: float = np.nan,
                 rot_rate_se: float = np.nan, trans_rate_se: float = np.nan):
        self.pne, self.cpv, self.n_planes = float(pne), float(cpv), int(n_planes)
        self.rot_rate, self.trans_rate = float(rot_rate), float(trans_rate)
        self.speed, self.turn_rate, self.agreement = float(speed), float(turn_rate), float(agreement)
        self.agreement_scan, self.n_scans = int(agreement_scan), int(n_scans)
        self.agreement_stamp = float(agreement_stamp)
        self.rot_rate_se, self.trans_rate_se = float(rot_rate_se), float(trans_rate_se)
        self.level, self.message = "OK", ""


def _same_run(saved: dict, config: Config) -> bool:
    """A saved replay summary was made with ``config`` apart from its health section, by a replay that writes
    today's window records."""
    now = {k: v for k, v in flatten(config).items() if not k.startswith("health.")}
    was = {k: v for k, v in saved.get("config", {}).items() if not k.startswith("health.")}
    return now == was and not saved.get("error") and saved.get("record_format") == RECORD_FORMAT


def replay_windows(run: Run, out: Path, config: Config, progress: bool) -> tuple[list[dict], dict]:
    """(window records assessed with config.health, replay summary) of one run of the plan, replayed once:
    the bag's own odometry, or KISS-ICP's poses of its clouds with the bag's drift episodes injected on top
    (a sidecar bag replayed beside it)."""
    path = _bag(run.sim, out / "bags", progress)
    target = out / "replays" / run.name
    saved = target / "windows.json"
    if saved.exists():
        doc = load_windows(saved)
        if (_same_run(doc["summary"], config) and doc["summary"].get("bag_truth") == bag_identity(load_truth(path))
                and doc["summary"].get("weights") == network_digest(config)
                and doc["summary"].get("estimate", "sim") == run.estimate):
            return reassess(doc["windows"], config.health), doc["summary"]
    options = ReplayOptions(progress=progress, plot=True)
    if run.estimate == "kiss":
        options = replace(options, odom_topic=KISS_TOPIC, beside=(_kiss_sidecar(path, out / "kiss", run, progress),))
    res = replay(path, target, config, options)
    if res.summary["error"]:
        raise RuntimeError(f"replay of {path} failed: {res.summary['error']}")
    extra = {"bag_truth": bag_identity(load_truth(path)), "weights": network_digest(config), "estimate": run.estimate}
    res.summary.update(extra)
    doc = load_windows(saved)
    doc["summary"].update(extra)
    write_json(saved, doc)
    return res.windows, res.summary


KISS_TOPIC = "/odom_kiss"


def _kiss_sidecar(path: Path, folder: Path, run: Run, progress: bool) -> Path:
    """A bag beside ``path`` with KISS-ICP's poses of its clouds (voxel size run.kiss_voxel) as odometry
    (experiments/odometry.py, cached in ``folder`` as <bag>, or <bag>_voxel<m> for another size), the bag's
    drift episodes (truth.json) injected on top exactly as the simulator injects them."""
    from ..sim.drift import Episode, estimated_poses
    from .odometry import cached_kiss, write_odometry_bag

    name = path.name + (f"_voxel{run.voxel_tag}" if run.voxel_tag else "")
    truth = load_truth(path)
    stamps, poses, frame, _ = cached_kiss(path, folder / f"{name}.npz", voxel_size=run.kiss_voxel, progress=progress)
    episodes = [Episode(**e) for e in truth["episodes"]]
    drift = DriftSpec(**truth["config"]["drift"])
    est = estimated_poses(stamps, poses, drift, episodes, np.random.default_rng(0)) if episodes else poses
    side = folder / f"{name}_odom"
    if side.exists():
        shutil.rmtree(side)
    return write_odometry_bag(side, stamps, est, frame, KISS_TOPIC)


def clean_windows(records: list[dict], episodes: list[dict], settle_s: float = CLEAN_AFTER_S) -> list[dict]:
    """Windows of a drift bag that are drift-free: they end before the next episode starts and start at
    least ``settle_s`` after the previous one ended."""
    return [r for r in records if not any(r["end"] > ep["start"] and r["start"] < ep["end"] + settle_s
                                          for ep in episodes)]


def false_warns(records: list[dict]) -> int:
    """Windows that alarmed while the SLAM's true drift stayed under the limits (real_drift)."""
    return sum(r["level"] in ALARM and not real_drift(r) for r in records)


def real_drift(record: dict) -> bool:
    """A window in which the SLAM itself truly drifted past the monitor's WARN limits (the bag's ground truth,
    replay's true_*_rate): an alarm there is right, not false, injected episode or not."""
    return any(record.get(f"true_{r}", np.nan) >= record.get(f"{r}_warn_at", np.inf) for r in RATES)


def score(runs: list[tuple[Run, list[dict], dict, dict | None]], within: int) -> dict:
    """The detection table of replayed runs: (run, window records, summary, truth) per run. False WARNs are
    counted on the drift-free bags (the goal's measure) and, apart, on the clean stretches of drift bags: an
    alarm in a window whose true drift (ground truth) exceeds the WARN limits is the SLAM's own drift caught
    (``confirmed``), not a false alarm; ``strict`` counts every alarm there. ``cells`` splits it all by (speed,
    estimate) and gives the drift rates' and rpe_estimate's accuracy there."""
    rows, free = [], {"windows": 0, "false_warn_windows": 0, "strict_warn_windows": 0, "minutes": 0.0, "bags": []}
    clean = {"windows": 0, "false_warn_windows": 0, "strict_warn_windows": 0, "minutes": 0.0,
             "after_windows": 0, "after_false_warn_windows": 0, "after_minutes": 0.0}  # after: >= CLEAN_AFTER_S past
    for run, windows, summary, truth in runs:
        sim, window_s = run.sim, _window_s(windows)
        if sim.drift.mode == "none":
            alarms = [r for r in windows if r["level"] in ALARM]
            false = [r for r in alarms if not real_drift(r)]
            minutes = len(windows) * window_s / 60  # the windows' time (the bag runs on past the last)
            free["windows"] += len(windows)
            free["false_warn_windows"] += len(false)
            free["strict_warn_windows"] += len(alarms)
            free["minutes"] += minutes
            free["bags"].append({"bag": run.name, "speed": sim.speed, "estimate": run.estimate, "sensor": sim.sensor,
                                 "windows": len(windows), "false_warns": len(false), "strict_warns": len(alarms),
                                 "real_drift_windows": sum(real_drift(r) for r in windows),
                                 "minutes": minutes, "reasons": sorted({r["message"] for r in false})})
        else:
            hits = [h for h in episode_hits(windows, truth["episodes"], within) if h["covered"]]
            calm = clean_windows(windows, truth["episodes"])
            calm_false, calm_strict = false_warns(calm), sum(r["level"] in ALARM for r in calm)
            clean["windows"] += len(calm)
            clean["false_warn_windows"] += calm_false
            clean["strict_warn_windows"] += calm_strict
            clean["minutes"] += len(calm) * window_s / 60
            after = [r for r in calm if any(r["start"] >= ep["end"] + CLEAN_AFTER_S for ep in truth["episodes"])]
            clean["after_windows"] += len(after)
            clean["after_false_warn_windows"] += false_warns(after)
            clean["after_minutes"] += len(after) * window_s / 60
            rows.append({"bag": run.name, "mode": sim.drift.mode, "scale": sim.drift.scale, "speed": sim.speed,
                         "estimate": run.estimate, "sensor": sim.sensor,
                         "episodes": len(hits), "detected": sum(h["detected"] for h in hits),
                         "truly_over": sum(h["truly_over"] for h in hits),
                         "detected_truly_over": sum(h["detected"] and h["truly_over"] for h in hits),
                         "latencies": [h["latency_windows"] for h in hits],
                         "accuracy": rate_accuracy(windows, truth["episodes"]),
                         "clean_windows": len(calm),
                         "clean_false_warns": calm_false, "clean_strict_warns": calm_strict,
                         "clean_real_drift": sum(real_drift(r) for r in calm),
                         "clean_minutes": len(calm) * window_s / 60, "scans_per_s": summary.get("scans_per_s")})
    n_ep = sum(r["episodes"] for r in rows)
    n_hit = sum(r["detected"] for r in rows)
    per_10min = 10 * free["false_warn_windows"] / free["minutes"] if free["minutes"] else float("nan")
    return {"within_windows": within, "rows": rows, "episodes": n_ep, "detected": n_hit,
            "truly_over": sum(r["truly_over"] for r in rows),
            "detected_truly_over": sum(r["detected_truly_over"] for r in rows),
            "detection_rate": n_hit / n_ep if n_ep else float("nan"), "drift_free": free,
            "false_warns_per_10min": per_10min, "clean_stretches": clean,
            "clean_false_warns_per_10min": 10 * clean["false_warn_windows"] / clean["minutes"]
            if clean["minutes"] else float("nan"), "cells": _cells(rows, free["bags"])}


def rate_accuracy(windows: list[dict], episodes: list[dict]) -> list[dict]:
    """Per episode: the median over the windows lying wholly inside it of each injected rate's reading divided
    by the injected rate (rotation °/s, translation m/s); of rpe_estimate divided by the RPE the injected drift
    alone gives over the window's scans (``rpe_estimate``), by the window's true RPE, which also holds the
    SLAM's own error, drift and scan-to-scan jitter alike (``rpe_estimate_vs_true``), and by the RPE the
    window's true drift trend gives (``rpe_estimate_vs_trend``: the same quantity from ground truth)."""
    from ..metrics.drift_rate import rpe_estimate

    out = []
    for ep in episodes:
        inside = [w for w in windows if w["start"] >= ep["start"] and w["end"] <= ep["end"]]
        if not inside:
            continue
        row = {}
        injected_rates = {"rot_rate": np.degrees(ep["rot_rate"]), "trans_rate": ep["trans_rate"]}  # °/s, m/s
        for rate, injected in injected_rates.items():
            if injected > 0:
                row[rate] = float(np.nanmedian([w.get(rate, np.nan) for w in inside])) / injected
        ratio, trend = [], []
        for w in inside:
            times = np.linspace(w["start"], w["end"], max(int(w.get("n_scans", 2)), 2))
            injected = rpe_estimate(np.degrees(ep["rot_rate"]), ep["trans_rate"], times)
            ratio.append(w.get("rpe_estimate", np.nan) / injected if injected > 0 else np.nan)
            true = rpe_estimate(w.get("true_rot_rate", np.nan), w.get("true_trans_rate", np.nan), times)
            if true > 0:
                trend.append(w.get("rpe_estimate", np.nan) / true)
        row["rpe_estimate"] = float(np.nanmedian(ratio)) if np.isfinite(ratio).any() else float("nan")
        rpe = [w.get("rpe_estimate", np.nan) / w["rpe"] for w in inside if w.get("rpe", 0) > 0]
        row["rpe_estimate_vs_true"] = float(np.nanmedian(rpe)) if rpe else float("nan")
        row["rpe_estimate_vs_trend"] = float(np.nanmedian(trend)) if trend else float("nan")
        for rate in RATES:  # against the window's true drift (the injected one plus the SLAM's own), for the
            # rates the episode injects: in a t-only episode the true rotation is the SLAM's own small error
            true = [w.get(rate, np.nan) / w[f"true_{rate}"] for w in inside if w.get(f"true_{rate}", 0) > 0]
            row[f"{rate}_vs_true"] = float(np.nanmedian(true)) if true and injected_rates[rate] > 0 else float("nan")
        out.append(row)
    return out


def _cells(rows: list[dict], free_bags: list[dict]) -> list[dict]:
    """The table by (speed, estimate): episodes detected, false WARN per 10 min (drift-free bags and clean
    stretches together), and the median accuracy ratios of the rates and rpe_estimate."""
    keys = sorted({(r["speed"], r["estimate"]) for r in rows} | {(b["speed"], b["estimate"]) for b in free_bags})
    cells = []
    for speed, est in keys:
        mine = [r for r in rows if (r["speed"], r["estimate"]) == (speed, est)]
        bags = [b for b in free_bags if (b["speed"], b["estimate"]) == (speed, est)]
        minutes = sum(b["minutes"] for b in bags) + sum(r["clean_minutes"] for r in mine)
        false = sum(b["false_warns"] for b in bags) + sum(r["clean_false_warns"] for r in mine)
        strict = sum(b["strict_warns"] for b in bags) + sum(r["clean_strict_warns"] for r in mine)
        real = sum(b["real_drift_windows"] for b in bags) + sum(r["clean_real_drift"] for r in mine)
        acc = [a for r in mine for a in r["accuracy"]]
        cells.append({"speed": speed, "estimate": est, "sensors": sorted({r["sensor"] for r in mine + bags}),
                      "episodes": sum(r["episodes"] for r in mine), "detected": sum(r["detected"] for r in mine),
                      "truly_over": sum(r["truly_over"] for r in mine),
                      "detected_truly_over": sum(r["detected_truly_over"] for r in mine),
                      "false_warns": false, "strict_warns": strict, "real_drift_windows": real, "minutes": minutes,
                      "false_warns_per_10min": 10 * false / minutes if minutes else float("nan"),
                      "strict_warns_per_10min": 10 * strict / minutes if minutes else float("nan"),
                      **{k: float(np.nanmedian([a[k] for a in acc if k in a])) if any(k in a for a in acc)
                         else float("nan") for k in ("rot_rate", "trans_rate", "rpe_estimate", "rpe_estimate_vs_true",
                                                     "rpe_estimate_vs_trend", "rot_rate_vs_true",
                                                     "trans_rate_vs_true")}})
    return cells


def _window_s(records: list[dict]) -> float:
    """Seconds between window starts (median), the time one window stands for."""
    starts = np.array([r["start"] for r in records])
    return float(np.median(np.diff(starts))) if len(starts) > 1 else 0.0


def _replay_split(out: Path, config: Config, split: str, scenes, frames, free_bags, free_frames, progress,
                  engine: str = "local", workers: int = 2, address: str | None = None,
                  **plan) -> list[tuple[Run, list[dict], dict, dict | None]]:
    """Simulate (or reuse) the split's bags, then replay each run (replay_windows): both as tasks of
    engine.run_tasks (``engine``, ``workers``, ``address``); the runs in plan order."""
    from ..engine import run_tasks

    runs = plan_bags(scenes, frames, free_bags, free_frames, split=split, **plan)
    kw = dict(engine=engine, workers=workers, address=address, progress=progress)
    sims = list({_name(r.sim): r.sim for r in runs}.values())  # a bag shared by two estimates: simulated once
    for sim, _, error in run_tasks(_bag_task, [(sim, out / "bags") for sim in sims], desc="bags", **kw):
        if error is not None:
            raise RuntimeError(f"simulating {_name(sim[0])} failed: {error}")
    done = {}
    for (run, *_), result, error in run_tasks(_replay_task, [(run, out, config) for run in runs], desc="replays",
                                              **kw):
        if error is not None:
            raise RuntimeError(f"replay of {run.name} failed: {error}")
        done[id(run)] = result
    return [(run, *done[id(run)], load_truth(out / "bags" / _name(run.sim))) for run in runs]


def _bag_task(job: tuple) -> Path:
    sim, bags = job
    return _bag(sim, bags, progress=False)


def _replay_task(job: tuple) -> tuple[list[dict], dict]:
    run, out, config = job
    return replay_windows(run, out, config, progress=False)


def run_detection(out: str | Path, config: Config, scenes: list[str], frames: int = 400, free_bags: int = 5,
                  free_frames: int = 750, within: int = 2, progress: bool = True, split: str = "evaluation",
                  **plan) -> dict:
    """Simulate (or reuse) the bags of ``split`` under out/bags, replay each to out/replays (or reuse the
    replay and re-assess health), score, and write out/detection.json, .csv and .png. Returns the table.
    ``plan``: plan_bags' transfer dimensions (rate, speeds, estimates, odometry, scales, sensors)."""
    out = Path(out)
    runs = _replay_split(out, config, split, scenes, frames, free_bags, free_frames, progress, **plan)
    table = score(runs, within)
    table.update(split=split, bags_from=split_description(split, plan.get("groups")),
                 window_size=config.window.setting(),
                 health=asdict(config.health), segmentation=config.segmentation.mode,
                 plan={k: list(v) if isinstance(v, tuple) else v for k, v in plan.items()
                       if k not in ("engine", "workers", "address")})
    _write(out, table)
    return table


def rate_margins(runs: list[tuple[Run, list[dict], dict, dict | None]], within: int) -> dict:
    """How far the drift rates keep drift-free windows from drifting ones (what the rate limits sit between):
    per rate, the largest value of a drift-free window (drift-free bags and clean stretches) and, per episode,
    the largest of its first ``within`` windows, of which the smallest over episodes is reported."""
    free, first = {r: [] for r in RATES}, {r: [] for r in RATES}
    for run, windows, _, truth in runs:
        sim = run.sim
        calm = windows if sim.drift.mode == "none" else clean_windows(windows, truth["episodes"])
        ends = np.array([w["end"] for w in windows])
        for rate in RATES:
            free[rate] += [w.get(rate, np.nan) for w in calm]
            if not (sim.drift.rotation if rate == "rot_rate" else sim.drift.translation):
                continue  # only the drift an episode injects counts for its rate (none for drift-free bags)
            for ep in truth["episodes"]:
                k = int(np.searchsorted(ends, ep["start"], side="right"))
                shown = [w.get(rate, np.nan) for w in windows[k:k + within]]
                if np.any(np.isfinite(shown)):  # (an episode whose windows have no co-plane group shows no rate)
                    first[rate].append(float(np.nanmax(shown)))
    return {rate: {"drift_free_max": float(np.nanmax(free[rate])) if np.any(np.isfinite(free[rate])) else None,
                   "drift_free_windows": int(np.isfinite(free[rate]).sum()),
                   "episode_min": min(first[rate]) if first[rate] else None, "episodes": len(first[rate])}
            for rate in RATES}


def _group(run: Run) -> int:
    """Index of the calibration group (SPLITS) a run of the calibration split belongs to."""
    return next(i for i, (layouts, _) in enumerate(SPLITS["calibration"]) if run.sim.layout_seed in layouts)


def _false_rate(table: dict) -> float:
    """False WARN per 10 min of a scored table, drift-free bags and clean stretches together."""
    fa = table["drift_free"]["false_warn_windows"] + table["clean_stretches"]["false_warn_windows"]
    minutes = table["drift_free"]["minutes"] + table["clean_stretches"]["minutes"]
    return 10 * fa / minutes if minutes else float("nan")


def choose_sigma(sweep: list[dict], target_per_10min: float, margin_sigma: float = 0.25,
                 key: str = "false_warns_per_10min") -> dict | None:
    """The sweep row of the smallest warn_sigma whose false WARN rate (``key``) meets the target, and so does
    every sigma from ``margin_sigma`` below it up (false alarms rise steeply below a cliff; a threshold right
    on the calibration bags' cliff would not hold on new bags). None when no sigma qualifies."""
    rows = sorted(sweep, key=lambda r: r["warn_sigma"])
    for row in rows:
        low = row["warn_sigma"] - margin_sigma - 1e-9
        if rows[0]["warn_sigma"] > low:
            continue  # the grid does not reach margin_sigma below: the margin cannot be checked
        if all(r[key] <= target_per_10min for r in rows if r["warn_sigma"] >= low):
            return row
    return None


def calibrate(out: str | Path, config: Config, scenes: list[str], frames: int = 400, free_bags: int = 5,
              free_frames: int = 750, within: int = 2, target_per_10min: float = 0.5, margin_sigma: float = 0.25,
              progress: bool = True, sigmas=SIGMA_GRID, **plan) -> dict:
    """Choose health.warn_sigma on the CALIBRATION split (``plan``: plan_bags' transfer dimensions): the smallest sigma of the grid whose false WARN rate
    on the calibration drift-free data (drift-free bags and the clean stretches of the drift bags) is <=
    ``target_per_10min`` (a margin under the goal of 1 per 10 min; the smallest such sigma detects the most)
    in EVERY calibration group (floor plans differ: a pooled rate let one plan's false alarms hide behind
    another's quiet minutes, and did not hold on new plans).
    The other health settings (persistence, baseline) are the config's. Writes out/calibration.json/.csv/.png; returns the sweep
    and the choice. The evaluation split is not touched."""
    out = Path(out)
    runs = _replay_split(out, config, "calibration", scenes, frames, free_bags, free_frames, progress, **plan)
    sweep = []
    for sigma in sigmas:
        health = replace(config.health, warn_sigma=float(sigma), error_sigma=max(config.health.error_sigma,
                                                                                 float(sigma)))
        assessed = [(run, reassess(w, health), s, t) for run, w, s, t in runs]
        table = score(assessed, within)
        fa = table["drift_free"]["false_warn_windows"] + table["clean_stretches"]["false_warn_windows"]
        minutes = table["drift_free"]["minutes"] + table["clean_stretches"]["minutes"]
        per_group = [_false_rate(score([r for r in assessed if _group(r[0]) == g], within))
                     for g in range(len(SPLITS["calibration"]))]
        sweep.append({"warn_sigma": float(sigma), "detection_rate": table["detection_rate"],
                      "detected": table["detected"], "episodes": table["episodes"],
                      "false_warn_windows": fa, "minutes": minutes,
                      "false_warns_per_10min": _false_rate(table),
                      "group_false_warns_per_10min": per_group,
                      "worst_group_false_warns_per_10min": max((x for x in per_group if np.isfinite(x)), default=np.nan),
                      "free_bag_false_warns": table["drift_free"]["false_warn_windows"],
                      "free_bag_minutes": table["drift_free"]["minutes"]})
    chosen = choose_sigma(sweep, target_per_10min, margin_sigma, key="worst_group_false_warns_per_10min")
    doc = {"split": "calibration", "bags_from": split_description("calibration", plan.get("groups")),
           "rates": rate_margins(runs, within),
           "target_false_warns_per_10min": target_per_10min, "margin_sigma": margin_sigma, "within_windows": within,
           "health": asdict(config.health), "sweep": sweep, "chosen": chosen}
    _write_calibration(out, doc)
    return doc


#: The relative rate limits' settings swept by calibrate_rates: the learned floor's margin, quantile and cap, the
#: motion shares (rotation per metre and per degree turned, translation per metre) and the rates' persistence.
RATE_GRID = {"noise_margin": (2.0, 3.0, 4.0), "noise_quantile": (0.75, 0.9), "noise_max_factor": (3.0, 5.0, 8.0),
             "rot_per_m": (0.05, 0.1), "rot_per_deg": (0.01, 0.02, 0.04), "trans_per_m": (0.01, 0.02),
             "rate_persist": (1, 2)}


def calibrate_rates(out: str | Path, config: Config, scenes: list[str], frames: int = 400, free_bags: int = 5,
                    free_frames: int = 750, within: int = 2, target_per_10min: float = 0.5, progress: bool = True,
                    grid: dict = RATE_GRID, **plan) -> dict:
    """Choose the relative rate limits on the CALIBRATION split (``plan``: plan_bags' transfer dimensions): every
    combination of ``grid`` is assessed again on the same replays (health only); the chosen one alarms every
    episode on the simulator's own odometry, has no more than ``target_per_10min`` false WARN per 10 min
    (ground-truth aware: see score) in EVERY (speed, estimate) cell and detects the most episodes; ties go to
    the most sensitive (smallest margin, cap and shares). Writes out/rate_calibration.json and returns it.
    The evaluation split is not touched."""
    out = Path(out)
    runs = _replay_split(out, config, "calibration", scenes, frames, free_bags, free_frames, progress, **plan)
    sweep, chosen = sweep_rates(runs, config.health, within, target_per_10min, grid)
    doc = {"split": "calibration", "bags_from": split_description("calibration", plan.get("groups")),
           "target_false_per_10min":
           target_per_10min, "within_windows": within, "grid": {k: list(v) for k, v in grid.items()},
           "health": asdict(config.health), "chosen": chosen, "closest": None if chosen else closest_rates(sweep, grid),
           "sweep": sweep,
           "plan": {k: list(v) if isinstance(v, tuple) else v for k, v in plan.items()}}
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "rate_calibration.json", doc)
    return doc


def sweep_rates(runs, health: HealthConfig, within: int, target_per_10min: float, grid: dict = RATE_GRID
                ) -> tuple[list[dict], dict | None]:
    """Every combination of ``grid`` applied to ``health`` and assessed again on the runs' window records:
    the sweep rows and the chosen one (see calibrate_rates), None when none meets the target."""
    import itertools

    sweep = []
    for values in itertools.product(*grid.values()):
        table = score([(run, reassess(w, replace(health, **dict(zip(grid, values)))), s, t)
                       for run, w, s, t in runs], within)
        worst = max((c["false_warns_per_10min"] for c in table["cells"] if np.isfinite(c["false_warns_per_10min"])),
                    default=np.nan)
        sweep.append({**dict(zip(grid, values)), "detected": table["detected"], "episodes": table["episodes"],
                      "detection_rate": table["detection_rate"], "worst_cell_false_per_10min": worst,
                      "alarms_every_sim_episode": _alarms_every_sim_episode(table["cells"]),
                      "cells": table["cells"]})
    fits = [r for r in sweep if r["worst_cell_false_per_10min"] <= target_per_10min and r["alarms_every_sim_episode"]]
    return sweep, (max(fits, key=lambda r: (r["detected"], *(-r[k] for k in grid))) if fits else None)


def _alarms_every_sim_episode(cells: list[dict]) -> bool:
    """Whether every episode on the simulator's own odometry (estimate 'sim': its error is known and small)
    was alarmed within the windows allowed: plain drift on good odometry must never go unseen, so a setting
    that misses one is not a candidate, however few false WARNs it gives (the unit tests ask the same)."""
    return all(c["detected"] == c["episodes"] for c in cells if c["estimate"] == "sim")


def closest_rates(sweep: list[dict], grid: dict = RATE_GRID) -> dict | None:
    """When no setting meets the target: among those that alarm every episode on the simulator's own
    odometry (all, when none does), the one of fewest false WARNs in its worst cell, then most detections,
    then the most sensitive."""
    finite = [r for r in sweep if np.isfinite(r["worst_cell_false_per_10min"])]
    finite = [r for r in finite if r.get("alarms_every_sim_episode", True)] or finite
    return min(finite, key=lambda r: (r["worst_cell_false_per_10min"], -r["detected"], *(r[k] for k in grid)),
               default=None)


def format_rate_calibration(doc: dict) -> str:
    """The chosen rate-limit settings and their table, for people."""
    c, head = doc["chosen"], "chosen"
    if c is None:
        c, head = doc.get("closest"), (f"no setting of the grid alarms every episode on the simulated odometry and "
                                       f"keeps every (speed, estimate) cell at <= {doc['target_false_per_10min']:g} "
                                       f"false WARN per 10 min; closest")
        if c is None:
            return head.replace("; closest", "") + " (no cell had drift-free data)"
    knobs = ", ".join(f"health.{k}={c[k]:g}" for k in doc["grid"])
    return (f"{head} on the calibration split ({doc['bags_from']}): {knobs}; detected {c['detected']}/{c['episodes']}, "
            f"worst cell {c['worst_cell_false_per_10min']:.2f} false WARN per 10 min\n" + format_cells(c["cells"],
                                                                                                   doc["within_windows"]))


def _write_calibration(out: Path, doc: dict) -> None:
    from ..reports import pyplot, write_csv

    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "calibration.json", doc)
    write_csv(out / "calibration.csv", doc["sweep"])
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 3.2))
    x = [r["warn_sigma"] for r in doc["sweep"]]
    ax.plot(x, [r["false_warns_per_10min"] for r in doc["sweep"]], "o-", color="#d03020", ms=3,
            label="false WARN / 10 min (drift-free, pooled)")
    ax.plot(x, [r.get("worst_group_false_warns_per_10min", np.nan) for r in doc["sweep"]], "^--", color="#802010",
            ms=3, label="worst calibration group (chooses)")
    ax.set_yscale("symlog", linthresh=1.0)
    ax.axhline(doc["target_false_warns_per_10min"], color="#d03020", ls=":", lw=1, label="calibration target")
    ax2 = ax.twinx()
    ax2.plot(x, [r["detection_rate"] for r in doc["sweep"]], "s-", color="#4a7ab0", ms=3, label="detected")
    ax2.set_ylim(0, 1.05)
    ax2.set_ylabel(f"episodes detected within {doc['within_windows']} windows")
    if doc["chosen"]:
        ax.axvline(doc["chosen"]["warn_sigma"], color="grey", ls="--", lw=1, label="chosen")
    ax.set_xlabel("health.warn_sigma")
    ax.set_ylabel("false WARN per 10 min")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title("calibration split: false alarms vs detection")
    fig.tight_layout()
    fig.savefig(out / "calibration.png", dpi=110)
    plt.close(fig)


def format_calibration(doc: dict) -> str:
    """The calibration sweep for people."""
    lines = [f"{'warn_sigma':>10} {'detected':>9} {'false WARN':>10} {'per 10 min':>10}  per 10 min by group"]
    for r in doc["sweep"]:
        groups = " ".join(f"{x:5.2f}" for x in r.get("group_false_warns_per_10min", []))
        lines.append(f"{r['warn_sigma']:>10g} {r['detected']:>4}/{r['episodes']:<4} {r['false_warn_windows']:>10} "
                     f"{r['false_warns_per_10min']:>10.2f}  {groups}")
    c = doc["chosen"]
    minutes = doc["sweep"][0]["minutes"] if doc["sweep"] else 0.0
    lines.append("")
    for rate, (meaning, unit) in RATES.items():
        m, lim = doc.get("rates", {}).get(rate), doc["health"].get(f"{rate}_warn")
        if m and m["drift_free_max"] is not None:
            low = RATE_MARGIN * m["drift_free_max"]
            weakest = (f"episodes of that drift at least {m['episode_min']:.3g} {unit} in their first "
                       f"{doc['within_windows']} windows ({m['episodes']} episodes)" if m["episodes"]
                       else "no episode of that drift")
            span = (f"[{low:.3g}, {RATE_EPISODE_FRACTION * m['episode_min']:.3g}]" if m["episodes"] else f">= {low:.3g}")
            lines.append(f"{meaning} rate: drift-free windows max {m['drift_free_max']:.3g} {unit} "
                         f"({m['drift_free_windows']} windows), {weakest}; WARN limit {lim:g} {unit} "
                         f"(keep it in {span}: {RATE_MARGIN:g} x the drift-free max to "
                         f"{RATE_EPISODE_FRACTION:.2g} x the weakest episode)")
    lines.append("")
    lines.append(f"calibration split ({doc['bags_from']}; {minutes:.1f} min "
                 f"drift-free incl. clean stretches of drift bags): " + (f"warn_sigma {c['warn_sigma']:g} is the smallest with <= "
                                     f"{doc['target_false_warns_per_10min']:g} false WARN per 10 min in every group from "
                                     f"{c['warn_sigma'] - doc['margin_sigma']:g} up"
                                     if c else "no sigma of the grid meets the target"))
    return "\n".join(lines)


def _write(out: Path, table: dict) -> None:
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "detection.json", table)
    with open(out / "detection.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["bag", "mode", "scale", "episodes", "detected", "latencies"])
        for r in table["rows"]:
            w.writerow([r["bag"], r["mode"], r["scale"], r["episodes"], r["detected"],
                        " ".join("-" if x is None else str(x) for x in r["latencies"])])
        fr = table["drift_free"]
        w.writerow(["drift-free", "none", 0, 0, 0, f"{fr['false_warn_windows']} false WARN in {fr['minutes']:.1f} min"])
    from ..reports import pyplot

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
    lines = [f"split {table.get('split', '?')} ({table.get('bags_from', '?')}), health.warn_sigma "
             f"{table.get('health', {}).get('warn_sigma', '?')}, warn_persist {table.get('health', {}).get('warn_persist', '?')}",
             f"{'mode':>5} {'scale':>5} {'episodes':>8} {'detected':>8}  latency (windows)   bag"]
    for r in table["rows"]:
        lat = " ".join("-" if x is None else str(x) for x in r["latencies"])
        lines.append(f"{r['mode']:>5} {r['scale']:>5g} {r['episodes']:>8} {r['detected']:>8}  {lat:<18}  {r['bag']}")
    f = table["drift_free"]
    lines += ["", f"detected within {table['within_windows']} windows: {table['detected']}/{table['episodes']} "
              f"= {100 * table['detection_rate']:.1f} %  (goal >= 95 %); of the episodes whose estimate truly "
              f"passed a limit in those windows: {table.get('detected_truly_over', '?')}/{table.get('truly_over', '?')}",
              f"false WARN: {f['false_warn_windows']} of {f['windows']} drift-free windows in {f['minutes']:.1f} min "
              f"= {table['false_warns_per_10min']:.2f} per 10 min  (goal <= 1)"]
    c = table.get("clean_stretches")
    if c and c["minutes"]:
        after = (f"; of them >= {CLEAN_AFTER_S:g} s after an episode: {c['after_false_warn_windows']} in "
                 f"{c['after_minutes']:.1f} min" if "after_minutes" in c else "")
        lines.append(f"(clean stretches of the drift bags, before the episode (the baseline's windows among them) or "
                     f">= {CLEAN_AFTER_S:g} s after it: {c['false_warn_windows']} false WARN in {c['minutes']:.1f} min"
                     f"{after})")
    for b in f["bags"]:
        if b["false_warns"]:
            lines.append(f"  {b['bag']}: {b['false_warns']} false WARN: {'; '.join(b['reasons'][:3])}")
    if len(table.get("cells", [])) > 1 or any(c["estimate"] != "sim" for c in table.get("cells", [])):
        lines += ["", format_cells(table["cells"], table["within_windows"])]
    return "\n".join(lines)


def format_cells(cells: list[dict], within: int) -> str:
    """The table by speed and estimate: detection (all episodes; those whose estimate truly passed a limit in
    time), false WARN per 10 min, accuracy (median measured / injected, / true)."""
    lines = [f"{'speed':>6} {'estimate':>8} {'detected':>9} {'truly':>6} {'false WARN':>16} {'strict':>7} "
             f"{'rot':>6} {'trans':>6} {'rpe_est':>7} {'rpe_est':>7} {'rpe_est':>7} {'rot':>6} {'trans':>6}  sensors",
             f"{'m/s':>6} {'':>8} {f'<= {within} win':>9} {'over':>6} {'per 10 min':>16} {'/10min':>7} "
             f"{'/inj.':>6} {'/inj.':>6} {'/inj.':>7} {'/true':>7} {'/trend':>7} {'/true':>6} {'/true':>6}"]
    for c in cells:
        lines.append(f"{c['speed']:>6g} {c['estimate']:>8} {c['detected']:>4}/{c['episodes']:<4} "
                     f"{c.get('detected_truly_over', 0):>3}/{c.get('truly_over', 0):<2} "
                     f"{c['false_warns']:>3} in {c['minutes']:4.1f} = {c['false_warns_per_10min']:4.2f} "
                     f"{c['strict_warns_per_10min']:>7.2f} {c['rot_rate']:>6.2f} {c['trans_rate']:>6.2f} "
                     f"{c['rpe_estimate']:>7.2f} {c.get('rpe_estimate_vs_true', float('nan')):>7.2f} "
                     f"{c.get('rpe_estimate_vs_trend', float('nan')):>7.2f} "
                     f"{c['rot_rate_vs_true']:>6.2f} {c['trans_rate_vs_true']:>6.2f}  {', '.join(c['sensors'])}")
    return "\n".join(lines)

