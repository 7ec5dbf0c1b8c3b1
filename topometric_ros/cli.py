"""The ``topometric`` command: simulate, replay, alarms, demo (and later train, evaluate, bench)."""
from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import signal
import sys
import threading
from pathlib import Path

from .sensors import DEFAULT_SENSOR, SENSORS


def _scenes(text: str) -> list[str]:
    from .sim.scenes import SCENES

    names = [s.strip() for s in text.split(",") if s.strip()]
    bad = [s for s in names if s not in SCENES]
    if bad or not names:
        raise argparse.ArgumentTypeError(f"unknown scene(s) {', '.join(bad)}; choose from {', '.join(SCENES)}" if bad
                                         else f"give at least one scene: {', '.join(SCENES)}")
    return names


def _sensors(text: str) -> list[str]:
    """'VLP-16' | 'VLP-16,OS1-128' | 'all' -> sensor model names."""
    from .sensors import sensor

    if text.strip().lower() == "all":
        return list(SENSORS)
    try:
        return [sensor(t.strip()).name for t in text.split(",") if t.strip()]
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _sim_config(args: argparse.Namespace, scene: str):
    from .sim.drift import DriftSpec
    from .sim.writer import SimConfig

    return SimConfig(scene=scene, layout_seed=args.layout_seed, seed=args.seed, frames=args.frames, rate=args.rate,
                     odom_rate=args.odom_rate, speed=args.speed, drift=DriftSpec.parse(args.drift, args.drift_kind),
                     storage=args.storage, sensor=args.sensor[0], distortion=not args.no_distortion,
                     odometry=args.odometry, clock_jump=args.clock_jump)


def cmd_simulate(args: argparse.Namespace) -> int:
    """One bag, or with --split train/test bags per scene; with several --sensor models, one set per sensor
    under OUT/<sensor>/."""
    from dataclasses import replace

    from .sim.writer import format_summary, simulate, simulate_split

    out = Path(args.out)
    if not args.split and len(args.scene) != 1:
        print("error: give one --scene without --split", file=sys.stderr)
        return 2
    if args.split and args.train + args.test == 0:
        print("error: --split with --train 0 and --test 0 writes no bag", file=sys.stderr)
        return 2
    from . import storage

    short = _no_episode_fits(args)
    if short:
        print(f"error: {short}", file=sys.stderr)
        return 2
    holder = next((p for p in out.resolve().parents if storage.has_metadata(p)), None)
    if holder is not None:  # the new bag would hide there: readers and the audit take the outer folder as one bag
        print(f"error: --out {args.out} is inside the bag folder {holder}; give a folder outside it", file=sys.stderr)
        return 2
    for name in args.sensor:
        target = out / name if len(args.sensor) > 1 else out
        cfg = replace(_sim_config(args, args.scene[0]), sensor=name)
        if not args.split:
            print(format_summary(simulate(cfg, target, progress=not args.quiet)))
            continue
        summaries = simulate_split(args.scene, target, cfg, args.train, args.test, progress=not args.quiet)
        for s in summaries:
            print(f"[{s['split']}] {s['bag']}: {s['frames']} scans, {s['path_length_m']:.0f} m, {s['elapsed_s']:.1f} s")
        (target / "split.json").write_text(json.dumps(summaries, indent=2))
        print(f"wrote {len(summaries)} bags under {target} (index: {target / 'split.json'})")
    return 0


def _no_episode_fits(args: argparse.Namespace) -> str:
    """Why --drift asks for episodes the bag is too short to hold ("" when one can fit)."""
    from .sim.drift import EPISODE_LENGTH_S

    if args.drift.split(":")[0] in ("none", "") or args.drift_kind != "episodes":
        return ""
    short = _too_short_for_episodes(args.frames, args.rate, f"{EPISODE_LENGTH_S[0]:g}-{EPISODE_LENGTH_S[1]:g} s")
    return short and f"{short}, or --drift-kind noise (drift from the first scan)"


def _too_short_for_episodes(frames: int, rate: float, lasting: str) -> str:
    """Why ``frames`` scans at ``rate`` Hz hold no drift episode ("" when the shortest fits): episodes start after
    EPISODE_WARMUP_S and last ``lasting`` (EPISODE_LENGTH_S, as the caller says it)."""
    from .sim.drift import EPISODE_LENGTH_S, EPISODE_WARMUP_S

    seconds, needed = frames / rate, EPISODE_WARMUP_S + EPISODE_LENGTH_S[0]
    if seconds >= needed:
        return ""
    return (f"--frames {frames} at --rate {rate:g} Hz is {seconds:g} s: drift episodes start after "
            f"{EPISODE_WARMUP_S:g} s and last {lasting}; give --frames {math.ceil(needed * rate)} or more")


def _setting(key: str, kind: type = float):
    """An argparse type for a flag that sets config leaf ``key``: the value as ``kind``, checked against the
    leaf's range like --set and --config check it (parameters.check)."""
    def parse(text: str):
        from .parameters import check

        value = kind(text)
        try:
            check(key, value)
        except ValueError as e:
            raise argparse.ArgumentTypeError(str(e)) from None
        return value

    parse.__name__ = kind.__name__  # argparse names the type in "invalid float value"
    return parse


def _topics(args: argparse.Namespace) -> dict[str, str]:
    """points_topic / odom_topic / tf_static_topic for a bag replay: a --*-topic flag, else what the --config
    file names when it is not the node's default (a robot's own topics), else "" (the bag's, see
    bag.pick_topic)."""
    from .config import read_parameters
    from .parameters import NODE_SPEC

    params = read_parameters(args.config) if getattr(args, "config", None) else {}
    out = {}
    for name in ("points_topic", "odom_topic", "tf_static_topic"):
        given = getattr(args, name, "") or ""
        named = str(params.get(name, "") or "")
        out[name] = given or (named if named != NODE_SPEC[name][0] else "")
    return out


def _set_pairs(args: argparse.Namespace) -> dict:
    """The --set KEY=VALUE pairs, values read as YAML."""
    import yaml

    over = {}
    for item in getattr(args, "set", None) or []:
        key, eq, value = item.partition("=")
        if not eq:
            raise ValueError(f"--set expects KEY=VALUE, got {item!r}")
        over[key.strip()] = yaml.safe_load(value)
    return over


def _monitor_config(args: argparse.Namespace):
    """Config from --config, then --set KEY=VALUE pairs, then the dedicated flags."""
    from .config import load_config

    over = _set_pairs(args)
    if getattr(args, "window_size", None) is not None:
        over["window.size"] = args.window_size
    if getattr(args, "segmentation", None):
        over["segmentation.mode"] = args.segmentation
    elif (getattr(args, "segmentation_fallback", None) and "segmentation.mode" not in over
          and not getattr(args, "config", None)):  # the subcommand's own default yields to --config and --set
        over["segmentation.mode"] = args.segmentation_fallback
    return load_config(getattr(args, "config", None), over)


def _planes_config(args: argparse.Namespace):
    """plane-quality's planes section: the config's (or the defaults'), its detector replaced by --detector."""
    from .config import load_config

    return load_config(args.config, {"planes.detector": args.detector} if args.detector else {}).planes


def _add_topic_args(p: argparse.ArgumentParser, whose: str) -> None:
    """The topics of a bag replay (``whose``: "the bag's" or "each bag's") and --quiet."""
    p.add_argument("--points-topic", default="", help=f"PointCloud2 topic (\"\": /points when it is one, else {whose} only one; "
                                                      "a topic named here is never swapped for another)")
    p.add_argument("--odom-topic", default="", help=f"nav_msgs/Odometry topic of the SLAM estimate (\"\": /odom when it is one, "
                                                    f"else {whose} only one besides --gt-topic)")
    p.add_argument("--gt-topic", default="/odom_gt", help="ground-truth odometry for RPE, when the bag has it "
                                                          "(\"\": none)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _add_monitor_args(p: argparse.ArgumentParser, segmentation_default: str | None = None,
                      windows: bool = True) -> None:
    """--config, --set, --segmentation, and --window-size where the command makes windows (not inspect)."""
    from .config import Config

    defaults = Config()
    p.add_argument("--config", help="YAML config (plain or ROS 2 parameter file, e.g. config/topometric.yaml; "
                                    "without it: the built-in defaults)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a config leaf, e.g. window.size=10")
    if windows:
        p.add_argument("--window-size", type=int, help=f"scans per window; 0 = automatic, the scans of "
                                                       f"window.duration_s ({defaults.window.duration_s:g} s) at the "
                                                       f"bag's own scan rate (paper: 5, 10, 15; default: the config's "
                                                       f"window.size, {defaults.window.size})")
    p.add_argument("--segmentation", choices=("network", "labels", "none"), default=None,
                   help="where labels come from: network (the shipped segmentation), labels (the cloud's own label "
                        "field: simulated bags), none (every point static)"
                        + (f" (default: {segmentation_default}, unless --config or --set segmentation.mode says "
                           f"otherwise)" if segmentation_default else
                           f" (default: the config's segmentation.mode, {defaults.segmentation.mode})"))
    p.set_defaults(segmentation_fallback=segmentation_default)


def _add_engine_args(p: argparse.ArgumentParser) -> None:
    """--engine, --workers, --address: where the jobs run (engine.run_tasks)."""
    p.add_argument("--engine", default="ray", choices=("ray", "local"),
                   help="ray: jobs as Ray tasks (a local Ray started on demand, or --address); local: in this process")
    p.add_argument("--workers", type=int, default=2, help="CPUs of the local Ray started on demand")
    p.add_argument("--address", default="", help="an existing Ray cluster, HOST:PORT (\"\": a local Ray)")


def cmd_replay(args: argparse.Namespace) -> int:
    from .replay import ReplayOptions, format_table, replay

    topics = _topics(args)
    opt = ReplayOptions(points_topic=topics["points_topic"], odom_topic=topics["odom_topic"], gt_topic=args.gt_topic,
                        tf_static_topic=topics["tf_static_topic"] or ReplayOptions.tf_static_topic,
                        rate=args.rate, plot=not args.no_plot, progress=not args.quiet)
    res = replay(args.bag, args.out, _monitor_config(args), opt)
    print(format_table(res.windows, res.summary))
    print(f"wrote {Path(args.out) / 'diagnostics.mcap'}, windows.csv, windows.json"
          + ("" if args.no_plot else ", metrics.png"))
    return _replay_status(res)


def _replay_status(res) -> int:
    """Exit status of a replay: 1 when it failed, processed no scan or gave no window (the console says why),
    else 0."""
    return 1 if res.summary["error"] or res.summary["no_scans"] or not res.windows else 0


AUDIT_EXIT = "exit status: 0 every bag replayed, 1 one or more bags failed (named in the report), 2 bad arguments, " \
             "130 interrupted (Ctrl-C)"


def cmd_audit(args: argparse.Namespace) -> int:
    from .audit import audit, find_bags, format_summary

    bags = find_bags(args.bags)
    if not bags:
        print("error: no bag found", file=sys.stderr)
        return 2
    from .replay import ReplayOptions

    options = {k: v for k, v in _topics(args).items() if v and v != getattr(ReplayOptions, k)}
    if args.gt_topic != ReplayOptions.gt_topic:  # "" = none
        options["gt_topic"] = args.gt_topic  # defaults are left out of the cache key
    try:
        res = audit(bags, args.out, _monitor_config(args), engine=args.engine, workers=args.workers,
                    address=args.address or None, options=options, force=args.force, progress=not args.quiet)
    except KeyboardInterrupt:
        print("audit interrupted: the bags finished so far are written (a rerun does only the rest)", file=sys.stderr)
        return 130
    print(format_summary(res))
    return 1 if res.summary["failed"] else 0


def cmd_inspect(args: argparse.Namespace) -> int:
    from .cloud import bad_beam_note
    from .inspect import format_rows, inspect_bag
    from .pipeline import sensor_model
    from .replay import load_segmenter, network_options
    from .storage import ReadLog

    config = _monitor_config(args)
    unused = _unused_by_inspect(args)
    if unused:
        print(f"note: inspect runs the per-scan stages only (no odometry, no windows): {', '.join(unused)} "
              "has no effect here", file=sys.stderr)
    segmenter = load_segmenter(config) if config.segmentation.mode == "network" else None
    log = ReadLog()
    rows = inspect_bag(args.bag, args.out, config, _topics(args)["points_topic"], args.every, args.limit, segmenter,
                       plot=not args.no_plot, progress=not args.quiet, log=log)
    print(f"segmentation {config.segmentation.mode}{network_options(config, getattr(segmenter, 'precision', ''))}; "
          f"sensor {config.sensor.model or 'read off each cloud'}")
    print(format_rows(rows))
    notes = log.lines() + [bad_beam_note(sum(r.get("bad_beam", 0) for r in rows), sensor_model(config))]
    for note in filter(None, notes):
        print(f"note: {note}")
    if args.limit and len(rows) == args.limit:
        print(f"the first {len(rows)} clouds (every {args.every}); --limit 0 inspects them all")
    print(f"wrote {Path(args.out) / 'scans.csv'}" + ("" if args.no_plot else " and one scan_NNNN.png per scan"))
    return 1 if not rows or all("error" in r for r in rows) else 0


#: Settings inspect's per-scan stages read (cloud, grid, segmentation, planes): a section, or one leaf.
INSPECT_SETTINGS = ("sensor.", "segmentation.", "planes.", "window.voxel_size")


def _unused_by_inspect(args: argparse.Namespace) -> list[str]:
    """The --set keys inspect does not use (window, health, metrics settings, deskew: no odometry)."""
    return [k for k in _set_pairs(args) if k == "sensor.deskew" or not k.startswith(INSPECT_SETTINGS)]


def _alarms_mode_options(args: argparse.Namespace) -> str:
    """Why the alarms options do not go together ("" when they do): options of one mode given to another
    would be dropped silently."""
    calibrating = args.calibrate or args.calibrate_rates
    problems = []
    if args.grid and not args.calibrate_rates:
        problems.append("--grid sweeps settings for --calibrate-rates only")
    if args.margin is not None and not args.calibrate:
        problems.append("--margin is --calibrate's")
    if args.kiss_voxel is not None and "kiss" not in args.estimates:
        problems.append("--kiss-voxel is KISS-ICP's (--estimates kiss)")
    if calibrating and args.split == "evaluation":
        problems.append("calibration runs on the calibration split only (the evaluation split is never tuned on)")
    return "; ".join(problems)


def _too_short_for_an_episode(args: argparse.Namespace) -> str:
    """Why the detection table's drift bags (``--frames`` scans at ``--rate`` Hz) can hold no drift episode ("" when
    they can, and for the calibrations, which choose from drift-free windows)."""
    from .sim.drift import EPISODE_LENGTH_S

    if args.calibrate or args.calibrate_rates:
        return ""
    return _too_short_for_episodes(args.frames, args.rate, f"{EPISODE_LENGTH_S[0]:g} s or more")


def cmd_alarms(args: argparse.Namespace) -> int:
    from .experiments.alarms import SCALES, calibrate, format_calibration, format_detection, run_detection

    mismatch = _alarms_mode_options(args) or _too_short_for_an_episode(args)
    if mismatch:
        print(f"error: {mismatch}", file=sys.stderr)
        return 2

    plan = {"rate": args.rate, "speeds": args.speeds, "estimates": args.estimates, "odometry": args.odometry,
            "scales": args.scales or SCALES, "engine": args.engine, "workers": args.workers,
            "address": args.address or None}
    if args.kiss_voxel is not None:
        plan["kiss_voxel"] = args.kiss_voxel
    if args.sensors:
        plan["sensors"] = args.sensors
    if args.groups:
        plan["groups"] = args.groups
    if args.calibrate_rates:
        from .experiments.alarms import calibrate_rates, format_rate_calibration

        grid = {"grid": dict(args.grid)} if args.grid else {}
        doc = calibrate_rates(args.out, _monitor_config(args), args.scene, frames=args.frames,
                              free_bags=args.free_bags or 5, free_frames=args.free_frames, within=args.within,
                              target_per_10min=args.target, progress=not args.quiet, **grid, **plan)
        print(format_rate_calibration(doc))
        print(f"wrote {Path(args.out) / 'rate_calibration.json'}")
        return 0
    if args.calibrate:
        doc = calibrate(args.out, _monitor_config(args), args.scene, frames=args.frames,
                        free_bags=args.free_bags or 5, free_frames=args.free_frames, within=args.within,
                        target_per_10min=args.target, margin_sigma=0.25 if args.margin is None else args.margin,
                        progress=not args.quiet, **plan)
        print(format_calibration(doc))
        print(f"wrote {Path(args.out) / 'calibration.json'}, calibration.csv, calibration.png")
        return 0
    table = run_detection(args.out, _monitor_config(args), args.scene, frames=args.frames,
                          free_bags=args.free_bags or 5, free_frames=args.free_frames, within=args.within,
                          progress=not args.quiet, split=args.split or "evaluation", **plan)
    print(format_detection(table))
    print(f"wrote {Path(args.out) / 'detection.json'}, detection.csv, detection.png")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from .replay import ReplayOptions, format_table, replay
    from .sim.drift import DriftSpec
    from .sim.writer import SimConfig, format_summary, simulate

    out = Path(args.out)
    bag_dir = out / "garage_demo"
    if bag_dir.exists():
        import shutil

        shutil.rmtree(bag_dir)
    cfg = SimConfig(scene="garage", frames=args.frames, rate=5.0, drift=DriftSpec.parse("rt:1.5"))
    print(format_summary(simulate(cfg, bag_dir)))
    res = replay(bag_dir, out / "replay", _monitor_config(args), ReplayOptions())
    print()
    print(format_table(res.windows, res.summary))
    print(f"plot: {out / 'replay' / 'metrics.png'}; diagnostics: {out / 'replay' / 'diagnostics.mcap'}")
    return _replay_status(res)


def _floats(text: str) -> tuple:
    return tuple(float(x) for x in text.split(",") if x.strip())


def _clock_jump(text: str) -> tuple[float, float, float]:
    """AT,OFFSET,DURATION (s): three finite numbers, DURATION > 0 (argparse type)."""
    try:
        values = _floats(text)
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values) or values[2] <= 0:
        raise argparse.ArgumentTypeError(f"expected AT,OFFSET,DURATION in s (three numbers, DURATION > 0), "
                                         f"got {text!r}")
    return values


def _positive_floats(text: str) -> tuple:
    """A comma list of numbers > 0 (argparse type)."""
    values = _floats(text)
    if not values or min(values) <= 0 or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"expected numbers > 0, got {text!r}")
    return values


def _window_sizes(text: str) -> tuple:
    """A comma list of window sizes, whole numbers >= 2 (argparse type; a window needs two scans)."""
    values = _ints(text)
    if not values or min(values) < 2:
        raise argparse.ArgumentTypeError(f"expected whole numbers >= 2, got {text!r}")
    return values


def _grid_axis(text: str) -> tuple[str, tuple]:
    """KEY=V1,V2 of --grid: a numeric health setting and the values to sweep, each read and checked as --set
    reads it (YAML, config.apply)."""
    import yaml

    from .config import HealthConfig, apply

    key, eq, values = text.partition("=")
    key, items = key.strip().removeprefix("health."), [v for v in values.split(",") if v.strip()]
    default = getattr(HealthConfig(), key, None)
    if not eq or not items or default is None:
        raise argparse.ArgumentTypeError(f"expected KEY=V1,V2 with KEY a health setting, got {text!r}")
    if isinstance(default, str):
        raise argparse.ArgumentTypeError(f"health.{key} is not numeric: it cannot be swept")
    try:
        return key, tuple(getattr(apply(HealthConfig(), {key: yaml.safe_load(v)}, "health."), key) for v in items)
    except ValueError as e:
        raise argparse.ArgumentTypeError(f"{text!r}: {e}") from None


def _ints(text: str) -> tuple:
    return tuple(int(x) for x in text.split(",") if x.strip())


def _number(kind: type, low: float, strictly: bool = False, high: float = math.inf):
    """argparse type: a finite ``kind`` (int: "whole number"; float) >= ``low`` (> ``low`` when ``strictly``)
    and <= ``high``."""
    word = "whole number" if kind is int else "number"

    def parse(text: str):
        try:
            x = kind(text)
        except ValueError:
            x = float("nan")
        if not math.isfinite(x) or not (x > low if strictly else x >= low) or x > high:
            bound = (f"within {'(' if strictly else '['}{low:g}, {high:g}]" if math.isfinite(high)
                     else f"{'>' if strictly else '>='} {low:g}")
            raise argparse.ArgumentTypeError(f"expected a {word} {bound}, got {text!r}")
        return x
    return parse


_count, _positive = _number(int, 0), _number(int, 1)
_positive_number, _non_negative = _number(float, 0.0, strictly=True), _number(float, 0.0)
_fraction = _number(float, 0.0, high=1.0)


def _model_share(text: str) -> tuple:
    """argparse type: MODEL=FRACTION (a sensor model of sensors.SENSORS, a share in [0, 1])."""
    from .sensors import SENSORS

    model, sep, share = text.partition("=")
    if not sep or model not in SENSORS:
        raise argparse.ArgumentTypeError(f"expected MODEL=FRACTION with a sensor model of {', '.join(SENSORS)}, "
                                         f"got {text!r}")
    return model, _fraction(share)


def _words(text: str) -> tuple:
    """A comma list of one word or more (argparse type)."""
    words = tuple(x.strip() for x in text.split(",") if x.strip())
    if not words:
        raise argparse.ArgumentTypeError(f"give at least one value, got {text!r}")
    return words


def _whole_numbers(count: int):
    """An argparse type: a comma list of exactly ``count`` whole numbers > 0."""
    def parse(text: str) -> tuple:
        try:
            values = tuple(int(x) for x in text.split(","))
        except ValueError:
            values = ()
        if len(values) != count or min(values) < 1:
            raise argparse.ArgumentTypeError(f"expected {count} whole numbers > 0 separated by commas, got {text!r}")
        return values
    return parse


def cmd_evaluate(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from .experiments.evaluate import ExperimentSpec, default_out, run

    spec = ExperimentSpec.quick() if args.quick else ExperimentSpec()
    given = {"scenes": args.scenes and tuple(args.scenes), "windows": args.win, "noises": args.noise,
             "scales": args.scales, "labels": args.labels, "trajectories": args.trajectories, "frames": args.frames,
             "baseline_windows": args.baseline_windows}
    spec = replace(spec, **{k: v for k, v in given.items() if v is not None})
    if spec.correlation_window not in spec.windows:
        spec = replace(spec, correlation_window=spec.windows[0])
    out = args.out or default_out(spec, args.quick)
    paths = run(spec, out, workers=args.workers, engine=args.engine, address=args.address or None)
    print(Path(paths["report"]).read_text())
    print(f"wrote {out}/ (report: {paths['report']}) in {paths['elapsed_s']:.0f} s; {paths['reused']} of "
          f"{paths['settings']} settings reused from {out}/runs")
    return 0


def _seeds(text: str) -> list[int]:
    """'3' | '0,3,5' | '0-6' -> seeds."""
    try:
        out = []
        for part in text.split(","):
            lo, _, hi = part.partition("-")
            if hi and int(hi) < int(lo):
                raise argparse.ArgumentTypeError(f"no seed in {part!r} of {text!r} (a range runs low-high)")
            out += list(range(int(lo), int(hi) + 1)) if hi else [int(lo)]
    except ValueError:
        raise argparse.ArgumentTypeError(f"seeds must look like 0 or 0,3,5 or 0-6, got {text!r}") from None
    return list(dict.fromkeys(out))  # each seed once: a repeated one would count its planes twice


def cmd_plane_quality(args: argparse.Namespace) -> int:
    import csv

    from .experiments.plane_quality import evaluate_detector, plot_plane_quality
    from .reports import write_json

    cfg = _planes_config(args)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cols = ("recall", "worst_recall", "truth", "recalled", "surface_recall", "surface_truth", "median_purity",
            "min_purity", "surface_purity", "planes_per_scan", "ms_per_scan")
    rows = []
    print(f"detector {cfg.detector}, {args.frames} scans per scene and trajectory seed "
          f"{', '.join(map(str, args.seed))}, ground-truth "
          "planes: instances (and surfaces: touching coplanar instances as one) with >= 200 points; "
          "recall pooled over the seeds")
    print(f"{'sensor':8s} {'scene':10s} {'recall':>8s} {'worst':>6s} {'planes':>11s} {'surface':>8s} {'med.purity':>11s} "
          f"{'planes/scan':>12s} {'ms/scan':>8s}")
    for name in args.sensor:
        res = evaluate_detector(args.scenes, args.frames, cfg, args.seed, sensor=name)
        stem = out / f"plane_quality_{cfg.detector}" if len(args.sensor) == 1 else out / f"plane_quality_{cfg.detector}_{name}"
        write_json(stem.with_suffix(".json"), res, indent=2)
        for scene, r in res["scenes"].items():
            rows.append((name, scene) + tuple(r[c] for c in cols))
            print(f"{name:8s} {scene:10s} {r['recall']:8.3f} {r['worst_recall']:6.3f} {r['recalled']:5d}/{r['truth']:<5d} "
                  f"{r['surface_recall']:8.3f} {r['median_purity']:11.4f} {r['planes_per_scan']:12.1f} {r['ms_per_scan']:8.1f}")
        plot_plane_quality(res, stem.with_suffix(".png"))
    with open(out / f"plane_quality_{cfg.detector}.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(("sensor", "scene") + cols)
        w.writerows(rows)
    print(f"wrote {out}/plane_quality_{cfg.detector}*.json, .csv, .png")
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    from .audit import find_bags
    from .segmentation.model import ModelSpec
    from .segmentation.train import TrainConfig, train

    cfg = TrainConfig(epochs=args.epochs, crops_per_epoch=args.crops, batch=args.batch, crop_width=args.crop_width,
                      lr=args.lr, every=args.every, seed=args.seed, threads=args.threads, max_minutes=args.max_minutes,
                      device=args.device, workers=args.workers, shares=dict(args.share))
    spec = ModelSpec(widths=args.widths, context=args.context)
    bags = find_bags(args.bags)
    val = find_bags(args.val) if args.val else []
    _refuse_writing_into_bags("--cache", args.cache, bags + val)
    print(f"training on {len(bags)} bag(s), validating on {len(val)}; output {args.out}")
    both = {Path(b).resolve() for b in bags} & {Path(b).resolve() for b in val}
    if both:
        print(f"note: {len(both)} validation bag(s) are training bags too ({', '.join(sorted(p.name for p in both))}): "
              "the epoch kept is chosen on data it trained on")
    card = train(bags, args.out, cfg, spec, val, args.cache, args.command_line, init=args.init or None)
    val_m = card["metrics"].get("val", {})
    if "val_miou" in val_m:
        print(f"val mIoU {100 * val_m['val_miou']:.2f} (paper classes, mean over sensor models); weights in {args.out}")
    _quantize_hint(f"{args.out}/rangenet.pt")
    return 0


def cmd_blend(args: argparse.Namespace) -> int:
    from .segmentation.checkpoint import blend_weights

    path = blend_weights(args.parent, args.tuned, args.alpha, args.out, args.command_line)
    print(f"wrote {path}: {1 - args.alpha:g} x {args.parent} + {args.alpha:g} x {args.tuned}")
    _quantize_hint(path)
    return 0


def _quantize_hint(weights) -> None:
    """New weights have no int8 activation ranges and no non-repetitive statistics yet: say how to make them."""
    print(f"for the int8 network (segmentation.precision auto/int8): topometric quantize <validation bags> "
          f"--weights {weights}")
    print(f"for non-repetitive (Livox-like) scans: topometric norm-stats <their training bags> --weights {weights}")


FEW_CALIBRATION_IMAGES = 8  # range images under which quantize and norm-stats say their estimate rests on few


def cmd_quantize(args: argparse.Namespace) -> int:
    from .segmentation.checkpoint import SHIPPED
    from .audit import find_bags
    from .segmentation.quantize import make_ranges

    bags = find_bags(args.bags)
    path, images = make_ranges(bags, args.weights or SHIPPED, args.every, args.command_line)
    print(f"wrote {path}{'' if args.weights else ' (the shipped weights: their ranges replaced)'} (activation ranges "
          f"of {images} range images from {len(bags)} bag(s); segmentation.precision int8 or auto uses them)")
    if images < FEW_CALIBRATION_IMAGES:
        print(f"note: {images} range image(s) are few for activation ranges; give more scans (--every lower, more "
              "bags)")
    return 0


def cmd_norm_stats(args: argparse.Namespace) -> int:
    from .segmentation.checkpoint import SHIPPED
    from .audit import find_bags
    from .segmentation.norm_stats import make_stats

    bags = find_bags(args.bags)
    path, images, used = make_stats(bags, args.weights or SHIPPED, args.every, args.command_line)
    print(f"wrote {path}{'' if args.weights else ' (the shipped weights: their statistics replaced)'}: BatchNorm "
          f"statistics of {images} non-repetitive range images from {used} of {len(bags)} bag(s); the segmenter "
          f"uses them for non-repetitive scans")
    if images < FEW_CALIBRATION_IMAGES:
        print(f"note: {images} range image(s) are few for BatchNorm statistics; give more scans (--every lower, "
              "more bags)")
    return 0


def cmd_eval_seg(args: argparse.Namespace) -> int:
    from .config import SegmentationConfig
    from .audit import find_bags
    from .segmentation.evaluate import evaluate_bags, format_table, write_report

    bags = find_bags(args.bags)
    segmenter = None
    if args.mode == "network":
        from .segmentation.infer import Segmenter

        segmenter = Segmenter.from_config(SegmentationConfig(weights=args.weights, device=args.device,
                                                             threads=args.threads, passes=args.passes,
                                                             max_beams=args.max_beams, knn=args.knn,
                                                             precision=args.precision, floor_band=args.floor_band,
                                                             object_gap=args.object_gap, floor_snap=args.floor_snap))
    result = evaluate_bags(bags, segmenter, every=args.every, limit=args.limit)
    metrics = write_report(result, args.out, args.title)
    print(format_table(metrics["rows"]))
    sp = metrics["speed"]
    if sp.get("scans"):
        print(f"speed: {sp['scans_per_s']} scans/s (median {sp['median_ms']} ms/scan over {sp['scans']} scans, "
              "each sensor's first left out as warm-up, "
              f"{args.device}, {args.threads} thread(s), {args.passes} pass(es), "
              f"{'every beam' if not args.max_beams else f'at most {args.max_beams} beams'}, "
              f"{f'{args.knn}-nearest-neighbour vote' if args.knn else 'no neighbour vote'}, "
              f"{f'floor band {args.floor_band} m' if args.floor_band else 'no floor check'}, "
              f"{f'objects within {args.object_gap} m' if args.object_gap else 'no object labels'}, "
              f"{f'non-repetitive floor snap {args.floor_snap} m' if args.floor_snap else 'no floor snap'}, "
              f"{segmenter.precision if segmenter else 'no'} network, projection + network + back-projection)")
    elif segmenter is not None:
        print("speed: not measured (each sensor's first scan is left out as warm-up, and no other was scored)")
    if segmenter is not None and result["non_repetitive"]:
        print(f"non-repetitive scans: {result['non_repetitive']}, with "
              + ("their own BatchNorm statistics (rangenet.norm.json)" if segmenter.has_pattern_stats else
                 "the shared BatchNorm statistics: these weights have no rangenet.norm.json (topometric norm-stats)"))
    print(f"wrote {args.out}/per_class_iou.csv, confusion.csv, confusion.png, metrics.json")
    return 0


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """--help shows every option's default, "(default: ...)", lists comma-joined; options whose default is
    nothing to show (None, False, "", an empty list) explain themselves in their help text."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text, d = action.help or "", action.default
        nothing = d is None or d is False or d is argparse.SUPPRESS or (isinstance(d, (str, list)) and not d)
        if "%(default)" in text or nothing or not action.option_strings:
            return text
        shown = ",".join(map(str, d)) if isinstance(d, (list, tuple)) else "%(default)s"
        return f"{text} (default: {shown})"


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose help shows defaults (HelpFormatter); subcommands get the same class."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)

    def parse_args(self, args=None, namespace=None):
        """As argparse's, but an unknown option is refused by its subcommand (its usage, not the top level's),
        naming the closest known options."""
        import difflib

        parsed, extra = self.parse_known_args(args, namespace)
        if extra:
            sub = next(a for a in self._actions if isinstance(a, argparse._SubParsersAction))
            command = sub.choices[parsed.command]
            known = [o for a in command._actions for o in a.option_strings]
            close = [m for e in extra if e.startswith("-")
                     for m in difflib.get_close_matches(e.split("=", 1)[0], known, n=3, cutoff=0.6)]
            command.error(f"unrecognized arguments: {' '.join(extra)}"
                          + (f" (did you mean {' or '.join(dict.fromkeys(close))}?)" if close else ""))
        return parsed


def _add_simulate(sub) -> None:
    """The `simulate` subcommand's options."""
    s = sub.add_parser("simulate", help="simulate a LiDAR robot run in an indoor scene and write a rosbag2 bag")
    s.add_argument("--scene", type=_scenes, default=["garage"], help="floor2, garage, office1, office2 (comma list with --split)")
    s.add_argument("--frames", type=_positive, default=600, help="scans per bag")
    s.add_argument("--rate", type=_positive_number, default=5.0,
                   help="scans per second, at most the sensor's sweep rate (10 = every sweep of a 10 Hz sensor)")
    s.add_argument("--odom-rate", type=_positive_number, default=20.0, help="odometry messages per second")
    s.add_argument("--speed", type=_non_negative, default=1.2, help="robot speed m/s")
    s.add_argument("--drift", default="none", help="MODE[:SCALE], MODE in none, r, t, rt (e.g. rt:1.5)")
    s.add_argument("--drift-kind", default="episodes", choices=("episodes", "noise"),
                   help="drift episodes with known start/end, or per-pose noise")
    s.add_argument("--seed", type=int, default=0, help="trajectory/noise seed")
    s.add_argument("--layout-seed", type=int, default=0, help="floor-plan seed (a new seed is an unseen layout)")
    s.add_argument("--storage", default="mcap", choices=("mcap", "sqlite3"), help="rosbag2 storage")
    s.add_argument("--sensor", default=[DEFAULT_SENSOR], type=_sensors,
                   help=f"LiDAR model(s) and their driver's cloud layout: a name, a comma list (one set of bags per "
                        f"sensor under OUT/<sensor>/) or 'all'; known: {', '.join(SENSORS)}")
    s.add_argument("--odometry", default="ideal", choices=("ideal", "lo"),
                   help="the SLAM's everyday error under the drift: none, or LiDAR-odometry-like (drift rates per "
                        "metre that wander, a share of each turn, jitter, corridor slide)")
    s.add_argument("--clock-jump", type=_clock_jump, default=(), metavar="AT,OFFSET,DURATION",
                   help="cloud stamps jump by OFFSET s from AT s after the start for DURATION s (a clock fault)")
    s.add_argument("--no-distortion", action="store_true",
                   help="instantaneous sweeps (without it: every firing at its own time along the trajectory)")
    s.add_argument("--split", action="store_true", help="write OUT/train and OUT/test bags for each --scene")
    s.add_argument("--train", type=_count, default=2, help="train trajectories per scene with --split")
    s.add_argument("--test", type=_count, default=1, help="test trajectories per scene with --split")
    s.add_argument("--out", required=True, help="output bag directory (with --split: a parent directory)")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=cmd_simulate)


def _add_train(sub) -> None:
    """The `train` subcommand's options."""
    t = sub.add_parser("train", help="train the segmentation network on labelled bags (simulated train split)")
    t.add_argument("bags", nargs="+", help="bags, or folders with bags anywhere below (e.g. data/sim/train)")
    t.add_argument("--val", nargs="*", default=[], help="validation bags (scored every epoch; the epoch of best mIoU on "
                                                        "them is saved); give it after the training bags")
    t.add_argument("--out", default="out/train", help="output folder for rangenet.pt and model_card.json")
    t.add_argument("--epochs", type=_positive, default=12, help="passes over the crops")
    t.add_argument("--crops", type=_positive, default=768, help="random azimuth crops per epoch")
    t.add_argument("--batch", type=_positive, default=12, help="crops per optimiser step")
    t.add_argument("--crop-width", type=_positive, default=480, help="azimuth columns per crop")
    t.add_argument("--lr", type=_non_negative, default=4e-3, help="learning rate")
    t.add_argument("--every", type=_positive, default=3, help="use every n-th scan of each bag")
    t.add_argument("--widths", type=_whole_numbers(3), default="32,48,64", help="channel widths of the three levels")
    t.add_argument("--context", type=_whole_numbers(2), default="2,4",
                   help="azimuth dilations of the two coarsest residual blocks")
    t.add_argument("--max-minutes", type=_non_negative, default=0.0,
                   help="stop training after this many minutes (0 = run all epochs); keeps the best-val epoch")
    t.add_argument("--seed", type=int, default=0, help="crop and initialisation seed")
    t.add_argument("--init", default="", help="start from these weights (fine-tuning; their network replaces "
                                              "--widths/--context; recorded in the model card)")
    t.add_argument("--threads", type=_positive, default=1, help="torch CPU threads")
    t.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or auto (cuda when there is one)")
    t.add_argument("--workers", type=_count, default=1, help="processes that build the projected-scan cache")
    t.add_argument("--cache", default="data/cache", help="folder for the projected-scan cache")
    t.add_argument("--share", type=_model_share, action="append", default=[], metavar="MODEL=FRACTION",
                   help="this sensor model's share of the batches, e.g. Mid-360=0.25 (repeatable; the other models "
                        "split the rest equally; default: every model an equal share)")
    t.set_defaults(func=cmd_train)


def _add_blend(sub) -> None:
    """The `blend` subcommand's options."""
    b = sub.add_parser("blend", help="blend a fine-tuned network with the weights it started from (WiSE-FT)")
    b.add_argument("parent", help="the weights the fine-tune started from")
    b.add_argument("tuned", help="the fine-tuned weights (same network)")
    b.add_argument("--alpha", type=_fraction, default=0.5, help="share of the tuned weights, 0..1")
    b.add_argument("--out", required=True, help="output folder for rangenet.pt and model_card.json")
    b.set_defaults(func=cmd_blend)


def _add_eval_seg(sub) -> None:
    """The `eval-seg` subcommand's options."""
    from .config import CHOICES, SegmentationConfig

    e = sub.add_parser("eval-seg", help="segmentation mIoU, per-class IoU, confusion matrix and speed on labelled bags")
    e.add_argument("bags", nargs="+", help="bags, or folders with bags anywhere below (e.g. data/sim/test)")
    e.add_argument("--weights", default="", help="weights file (\"\": the shipped ones)")
    e.add_argument("--mode", default="network", choices=("network", "labels"),
                   help="network, or labels (score the cloud's own label field: a sanity check)")
    e.add_argument("--device", default="cpu", help="cpu or cuda")
    e.add_argument("--threads", type=_positive, default=1, help="torch CPU threads")
    e.add_argument("--passes", type=int, default=1, choices=(1, 2, 3),
                   help="network passes per scan, averaged (segmentation.passes: 2 adds the mirror image, 3 also a shifted one)")
    e.add_argument("--max-beams", type=_setting("segmentation.max_beams", int), default=0,
                   help="most beams the network sees, the rest take their neighbours' labels (segmentation.max_beams; 0 = all)")
    e.add_argument("--knn", type=_setting("segmentation.knn", int), default=SegmentationConfig().knn,
                   help="k-nearest-neighbour vote after the network (segmentation.knn; 0 = off)")
    e.add_argument("--floor-band", type=_setting("segmentation.floor_band"), default=SegmentationConfig().floor_band,
                   help="m, floor labels standing this far above the floor go to their neighbours' label "
                        "(segmentation.floor_band; 0 = off)")
    e.add_argument("--object-gap", type=_setting("segmentation.object_gap"), default=SegmentationConfig().object_gap,
                   help="m, desk and chair points this close in neighbouring cells form one object, which takes its "
                        "commonest label (segmentation.object_gap; 0 = off)")
    e.add_argument("--floor-snap", type=_setting("segmentation.floor_snap"), default=SegmentationConfig().floor_snap,
                   help="m, in non-repetitive scans, other, wall, desk and chair points this close to the floor plane "
                        "become floor (segmentation.floor_snap; 0 = off)")
    e.add_argument("--precision", default=SegmentationConfig().precision, choices=CHOICES["segmentation.precision"],
                   help="network precision (segmentation.precision: auto = int8 on an x86 CPU with VNNI or AVX2)")
    e.add_argument("--every", type=_positive, default=1, help="use every n-th scan")
    e.add_argument("--limit", type=_count, default=0, help="at most this many scans per bag (0 = all)")
    e.add_argument("--title", default="", help="title of the confusion-matrix plot")
    e.add_argument("--out", default="out/eval_seg", help="output folder")
    e.set_defaults(func=cmd_eval_seg)


def _add_quantize(sub) -> None:
    """The `quantize` subcommand's options."""
    q = sub.add_parser("quantize", help="calibrate the int8 network: activation ranges saved beside the weights")
    q.add_argument("bags", nargs="+", help="labelled or unlabelled bags of any sensors, or folders of bags "
                                           "(e.g. data/any_val/*/test; never the evaluation bags)")
    q.add_argument("--weights", default="", help="weights file (\"\": the shipped ones)")
    q.add_argument("--every", type=_positive, default=2, help="use every n-th scan of each bag")
    q.set_defaults(func=cmd_quantize)


def _add_norm_stats(sub) -> None:
    """The `norm-stats` subcommand's options."""
    n = sub.add_parser("norm-stats", help="BatchNorm statistics for non-repetitive (Livox-like) scans, saved beside "
                                          "the weights")
    n.add_argument("bags", nargs="+", help="bags of a non-repetitive sensor, or folders of bags (the training split, "
                                           "e.g. data/gpu_train/*/Mid-360/train; never the evaluation bags); other "
                                           "sensors' scans are skipped")
    n.add_argument("--weights", default="", help="weights file (\"\": the shipped ones)")
    n.add_argument("--every", type=_positive, default=1, help="use every n-th scan of each bag")
    n.set_defaults(func=cmd_norm_stats)


def _add_replay(sub) -> None:
    """The `replay` subcommand's options."""
    r = sub.add_parser("replay",
                       help="replay a bag through the monitor: diagnostics.mcap, windows.csv/json, metrics.png")
    r.add_argument("bag", help="rosbag2 folder (MCAP or sqlite3) or a .mcap file")
    r.add_argument("--out", required=True, help="output folder")
    r.add_argument("--rate", default="max", help="max (every window processed), realtime, or a speed factor")
    _add_topic_args(r, "the bag's")
    r.add_argument("--no-plot", action="store_true", help="no metrics.png")
    _add_monitor_args(r)
    r.set_defaults(func=cmd_replay)


def _add_audit(sub) -> None:
    """The `audit` subcommand's options."""
    au = sub.add_parser("audit", help="many bags (a fleet's logs) through the monitor on Ray or in-process: "
                                      "per-bag reports and OUT/fleet.csv, fleet.json, index.html",
                        epilog=AUDIT_EXIT)
    au.add_argument("bags", nargs="+", metavar="BAG",
                    help="rosbag2 folders or .mcap files, folders of bags, or globs (quoted: 'logs/*/night_*')")
    au.add_argument("--out", required=True, help="output folder: bags/<bag>/ reports, fleet.csv, fleet.json, index.html")
    au.add_argument("--engine", default="ray", choices=("ray", "local"),
                    help="ray: one Ray task per bag; local: one bag after another in this process, no Ray")
    au.add_argument("--workers", type=int, default=2,
                    help="CPUs of the local Ray started on demand (one bag per CPU); unused with --address")
    au.add_argument("--address", default="", help="join an existing Ray cluster at HOST:PORT (started with `ray "
                                                  "start --head`; or 'auto') instead of starting a local Ray")
    au.add_argument("--force", action="store_true", help="replay every bag again (without it: cached results "
                                                         "whose bag, config and weights digests are unchanged are kept)")
    _add_topic_args(au, "each bag's")
    _add_monitor_args(au)
    au.set_defaults(func=cmd_audit)


def _add_inspect(sub) -> None:
    """The `inspect` subcommand's options."""
    i = sub.add_parser("inspect", help="per-scan stages on a bag's clouds (no odometry needed): layout, grid, "
                                       "segmentation, planes; a PNG per scan and scans.csv")
    i.add_argument("bag", help="rosbag2 folder (MCAP or sqlite3)")
    i.add_argument("--out", default="out/inspect", help="output folder")
    i.add_argument("--points-topic", default="", help="PointCloud2 topic (\"\": /points, else the bag's only one)")
    i.add_argument("--every", type=_positive, default=1, help="every n-th cloud")
    i.add_argument("--limit", type=_count, default=10, help="at most this many clouds (0 = all)")
    i.add_argument("--no-plot", action="store_true", help="no scan_NNNN.png")
    i.add_argument("--quiet", action="store_true", help="no progress bar")
    _add_monitor_args(i, windows=False)  # no odometry, no windows
    i.set_defaults(func=cmd_inspect)


def _add_alarms(sub) -> None:
    """The `alarms` subcommand's options."""
    a = sub.add_parser("alarms", help="drift-alarm detection table on held-out simulated bags (r/t/rt x 1/1.5/2)")
    a.add_argument("--out", default="out/alarms", help="bags, replays and detection.json/csv/png go here")
    a.add_argument("--scene", type=_scenes, default=["garage", "office1", "floor2", "office2"],
                   help="scenes (comma list)")
    a.add_argument("--frames", type=_positive, default=400, help="scans per drift bag (400 = 80 s)")
    a.add_argument("--free-bags", type=_count, default=0, help="drift-free bags per group of the split (0 = 5)")
    a.add_argument("--split", choices=("evaluation", "calibration"), default=None,
                   help="bag set of the table (default evaluation; thresholds are calibrated on 'calibration' only)")
    mode = a.add_mutually_exclusive_group()
    mode.add_argument("--calibrate", action="store_true",
                      help="sweep health.warn_sigma on the calibration split and print the smallest within --target")
    mode.add_argument("--calibrate-rates", action="store_true",
                      help="sweep the relative rate limits (learned floor, motion shares) on the calibration split")
    a.add_argument("--grid", type=_grid_axis, action="append", default=None, metavar="KEY=V1,V2",
                   help="--calibrate-rates: sweep these health settings instead of the default grid (repeatable, "
                        "e.g. --grid rate_sigma=0,1,2; the others stay at their configured values)")
    a.add_argument("--target", type=_non_negative, default=0.5, help="calibration: false WARN per 10 min allowed")
    a.add_argument("--margin", type=_non_negative, default=None,
                   help="--calibrate: the target must also hold this many sigma below the chosen one (default 0.25)")
    a.add_argument("--free-frames", type=_positive, default=750, help="scans per drift-free bag (750 = 150 s)")
    a.add_argument("--within", type=_positive, default=2, help="an episode counts when alarmed within this many windows")
    a.add_argument("--speeds", type=_floats, default=(1.2,), help="robot speeds, m/s (e.g. 0.3,1.5,4,10)")
    a.add_argument("--estimates", type=_words, default=("sim",),
                   help="whose poses the monitor judges: sim (the bag's odometry, --odometry's error) and/or kiss "
                        "(KISS-ICP on the bag's clouds); drift episodes go on top")
    a.add_argument("--kiss-voxel", type=_non_negative, default=None, metavar="M",
                   help="KISS-ICP's voxel size, m (default 0.25; 0 = its own rule, max range / 100: about 0.07 m "
                        "in an office, 5-20x slower there)")
    a.add_argument("--odometry", default="ideal", choices=("ideal", "lo"),
                   help="the simulated odometry's everyday error under the episodes")
    a.add_argument("--rate", type=_positive_number, default=5.0, help="scans per second of the bags (10 = every sweep)")
    a.add_argument("--scales", type=_positive_floats, default=None, help="drift scales of the episode bags (default 1, 1.5, 2)")
    a.add_argument("--sensors", type=_sensors, default=None,
                   help="sensors the bags cycle through (default: the split's own, held out between splits)")
    a.add_argument("--groups", type=_count, default=0,
                   help="only the split's first N groups of floor plans (0 = all; a shorter calibration)")
    a.add_argument("--quiet", action="store_true", help="no progress bars")
    _add_engine_args(a)
    _add_monitor_args(a, "labels")
    a.set_defaults(func=cmd_alarms)


def _add_demo(sub) -> None:
    """The `demo` subcommand's options."""
    d = sub.add_parser("demo", help="simulate a garage bag with a drift episode, replay it, print the alarms")
    d.add_argument("--out", default="out/demo", help="output folder: the bag and the replay's reports")
    d.add_argument("--frames", type=_positive, default=150, help="scans in the demo bag (5 per second)")
    _add_monitor_args(d, "labels")
    d.set_defaults(func=cmd_demo)


def _add_evaluate(sub) -> None:
    """The `evaluate` subcommand's options."""
    e = sub.add_parser("evaluate", help="the paper's noise experiment: every metric against RPE, correlations, timing")
    e.add_argument("--scenes", type=_scenes, default=None, help="scenes (default: floor2,garage)")
    e.add_argument("--win", type=_window_sizes, default=None, help="window sizes (default: 5,10,15)")
    e.add_argument("--noise", type=_words, default=None, help="noise modes among r,t,rt (default: all)")
    e.add_argument("--scales", type=_positive_floats, default=None, help="noise scales (default: 1,1.5,2)")
    e.add_argument("--labels", type=_words, default=None,
                   help="label sources: network (shipped segmentation) and/or gt (default: network,gt)")
    e.add_argument("--trajectories", type=_positive, default=None, help="trajectories per scene (default: 2)")
    e.add_argument("--frames", type=_positive, default=None, help="scans per trajectory (default: 300)")
    e.add_argument("--baseline-windows", type=_positive, default=None,
                   help="windows per trajectory and setting that also get MME/MPV/MOM (default: 8)")
    _add_engine_args(e)
    e.add_argument("--quick", action="store_true", help="a tiny run (office1, one trajectory, window 5, gt labels)")
    e.add_argument("--out", default="", help="output directory; finished settings are reused (\"\": results, the "
                                             "shipped report, for the full experiment; out/evaluate for any other, "
                                             "out/evaluate_quick with --quick)")
    e.set_defaults(func=cmd_evaluate)


def _add_plane_quality(sub) -> None:
    """The `plane-quality` subcommand's options."""
    q = sub.add_parser("plane-quality", help="plane detection recall/purity against simulated plane instances")
    q.add_argument("--scenes", type=_scenes, default=["floor2", "garage", "office1", "office2"],
                   help="scenes (comma list)")
    q.add_argument("--frames", type=_positive, default=20, help="scans per scene")
    q.add_argument("--detector", default=None, choices=("ring", "open3d"),
                   help="plane detector (default: the config's planes.detector, ring)")
    q.add_argument("--seed", type=_seeds, default=[0],
                   help="trajectory/noise seeds: 0 | 0,3,5 | 0-6; recall is pooled over them")
    q.add_argument("--config", default=None, help="YAML config (planes section is used)")
    q.add_argument("--sensor", type=_sensors, default=[DEFAULT_SENSOR], help="sensor model(s): a name, a comma list or 'all'")
    q.add_argument("--out", default="out/planes", help="output folder")
    q.set_defaults(func=cmd_plane_quality)


def build_parser() -> argparse.ArgumentParser:
    from . import __version__

    p = Parser(prog="topometric", description="Map-consistency drift monitor for LiDAR SLAM.")
    p.add_argument("--version", action="version", version=f"topometric {__version__}")
    sub = p.add_subparsers(dest="command", required=True)
    for add in (_add_simulate, _add_train, _add_blend, _add_eval_seg, _add_quantize, _add_norm_stats, _add_replay,
                _add_audit, _add_inspect, _add_alarms, _add_demo, _add_evaluate, _add_plane_quality):
        add(sub)
    return p


def _terminated(signum, frame) -> None:
    """SIGTERM (a timeout, a job scheduler) takes Ctrl-C's path: exit 130, what finished written, files being
    written left out (reports.written_whole). While Ray runs, Ray's own SIGTERM handler replaces this one."""
    raise KeyboardInterrupt(f"signal {signum}")


def _refuse_writing_into_bags(flag: str, folder: str, bags) -> None:
    """ValueError when ``folder`` is one of ``bags``' folders or lies inside one, or is the folder of a bag given
    as its .mcap / .db3 file (links resolved): what is written there would sit among the bag's files, which the
    next read takes as part of the bag."""
    from . import bag

    real = Path(folder).resolve()
    for given in filter(None, bags):
        source = Path(given).resolve()
        if source.is_file() and real == source.parent:
            raise ValueError(f"{flag} {folder} is the folder of the bag file {given}: what the command writes would "
                             "sit beside it, and the next read takes it as part of the bag; give another folder")
        if source.is_dir() and not bag.not_a_bag(source) and (real == source or source in real.parents):
            raise ValueError(f"{flag} {folder} is {'the' if real == source else 'inside the'} bag folder {given}: "
                             "what the command writes would be written into the bag; give a folder outside it")


def _check_out(args: argparse.Namespace) -> None:
    """--out must be a folder, or one that can be made where it is named: ValueError otherwise, before any work
    starts (nothing is made here)."""
    out = getattr(args, "out", None)
    if not out:
        return
    path = Path(out).absolute()
    if path.exists() and not path.is_dir():
        raise ValueError(f"--out {out} is a file; give a folder")
    inputs = [getattr(args, "bag", None), *(getattr(args, "bags", None) or []), *(getattr(args, "val", None) or [])]
    _refuse_writing_into_bags("--out", out, inputs)
    above = next(p for p in path.parents if p.exists())
    if not path.exists() and not (above.is_dir() and os.access(above, os.W_OK | os.X_OK)):
        raise ValueError(f"--out {out}: cannot make a folder in {above}"
                         + (" (a file)" if not above.is_dir() else " (not writable)"))


def _under_out(args: argparse.Namespace, filename) -> bool:
    """Whether ``filename`` (an OSError's) is --out or lies inside it: the folder named cannot be made or written."""
    out = getattr(args, "out", None)
    if not out or not isinstance(filename, (str, os.PathLike)):
        return False
    folder, path = Path(out).absolute(), Path(filename).absolute()
    return path == folder or folder in path.parents


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    args.command_line = "topometric " + shlex.join(sys.argv[1:] if argv is None else argv)  # for model cards
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _terminated) if main_thread else None
    try:
        _check_out(args)
        return args.func(args)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except OSError as e:  # --out's own (it cannot be made or written): exit 2; else the machine's (a full disk): 1
        if _under_out(args, e.filename):
            print(f"error: --out {args.out}: {e.strerror or e} ({e.filename}); give a folder that can be written",
                  file=sys.stderr)
            return 2
        print(f"error: {e}", file=sys.stderr)
        return 2 if isinstance(e, FileNotFoundError) else 1
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except Exception as e:  # noqa: BLE001 - a clear one-line message beats a traceback for users
        from .bag import BagError
        from .segmentation.checkpoint import SegmentationError

        if isinstance(e, (BagError, SegmentationError)):
            print(f"error: {e}", file=sys.stderr)
            return 2
        raise
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())
