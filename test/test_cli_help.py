"""`topometric <command> --help` shows every option's default (a real process for replay; every subcommand's
formatted help for the rest)."""
from __future__ import annotations

import argparse
import os
import subprocess
import sys

import pytest


def test_replay_help_in_a_real_process_shows_defaults():
    out = subprocess.run([sys.executable, "-m", "topometric_ros.cli", "replay", "--help"], capture_output=True,
                         text=True, check=True, env={"COLUMNS": "200", "PATH": ""}).stdout
    out = " ".join(out.split())
    for shown in ("(default: max)", "(default: /odom_gt)", "default: the config's window.size, 0)",
                  "(default: the config's segmentation.mode, network)"):
        assert shown in out, (shown, out)


def test_every_option_of_every_subcommand_shows_its_default(monkeypatch):
    from topometric_ros.cli import build_parser

    monkeypatch.setenv("COLUMNS", "300")  # no wrapping inside a default such as VLP-32C
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    checked = 0
    for name, parser in sub.choices.items():
        text = " ".join(parser.format_help().split())
        for action in parser._actions:
            d = action.default
            if not action.option_strings or d is None or d is False or d == argparse.SUPPRESS or d in ("", []):
                continue
            shown = ",".join(map(str, d)) if isinstance(d, (list, tuple)) else str(d)
            assert f"(default: {shown})" in text, (name, action.option_strings, shown)
            checked += 1
    assert len(sub.choices) >= 9 and checked > 50
    demo = " ".join(sub.choices["demo"].format_help().split())
    assert "--frames FRAMES scans in the demo bag (5 per second) (default: 150)" in demo
    assert "(default: labels, unless --config or --set segmentation.mode says otherwise)" in demo  # the demo's


def test_alarms_kiss_voxel_help_states_the_harness_default(monkeypatch):
    """--kiss-voxel's default is None (the parser does not load KISS-ICP's module); its help names the size
    that None means, odometry.VOXEL_SIZE, and must follow it."""
    from topometric_ros.cli import build_parser
    from topometric_ros.experiments.odometry import VOXEL_SIZE

    monkeypatch.setenv("COLUMNS", "300")
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    assert f"(default {VOXEL_SIZE:g}; 0 = its own rule" in " ".join(sub.choices["alarms"].format_help().split())


def test_alarms_groups_refuses_a_negative_count_with_a_clear_error():
    from topometric_ros.cli import build_parser

    parser = build_parser()
    assert parser.parse_args(["alarms", "--groups", "1"]).groups == 1
    res = subprocess.run([sys.executable, "-m", "topometric_ros.cli", "alarms", "--groups", "-1"],
                         capture_output=True, text=True)
    assert res.returncode == 2 and "expected a whole number >= 0, got '-1'" in res.stderr


def test_counts_that_must_be_positive_are_refused_before_anything_runs():
    """--frames 0 used to end in an IndexError traceback, --every 0 and --rate 0 in a division by zero,
    --window-size 0 in the default window size (0 is automatic now), alarms --speeds 0 or --estimates orb in a run of simulations:
    each is a one-line error now (exit 2), before anything runs."""
    from topometric_ros.cli import build_parser

    parser = build_parser()
    assert parser.parse_args(["simulate", "--frames", "1", "--out", "x"]).frames == 1
    assert parser.parse_args(["train", "x", "--share", "Mid-360=0.25", "--share", "VLP-16=0.1"]).share == [
        ("Mid-360", 0.25), ("VLP-16", 0.1)]
    for argv, words in ((["simulate", "--frames", "0", "--out", "x"], "argument --frames: expected a whole number >= 1"),
                        (["demo", "--frames", "-3"], "argument --frames: expected a whole number >= 1"),
                        (["inspect", "bag", "--every", "0"], "argument --every: expected a whole number >= 1"),
                        (["eval-seg", "bag", "--every", "x"], "argument --every: expected a whole number >= 1"),
                        (["replay", "bag", "--out", "o", "--window-size", "-1"], "'window.size' = -1 is out of range"),
                        (["replay", "bag", "--out", "o", "--window-size", "1"],
                         "'window.size' = 1: a window needs 2 scans or more; 0 = automatic"),
                        (["evaluate", "--win", "5,1"], "argument --win: expected whole numbers >= 2, got '5,1'"),
                        (["simulate", "--split", "--train", "0", "--test", "0", "--out", "x"], "writes no bag"),
                        (["evaluate", "--scales", "0"], "argument --scales: expected numbers > 0, got '0'"),
                        (["simulate", "--rate", "0", "--out", "x"], "argument --rate: expected a number > 0"),
                        (["simulate", "--rate", "1000", "--out", "x"],
                         "rate 1000 is more scans a second than the VLP-32C makes (it sweeps 10 times a second)"),
                        (["simulate", "--speed", "-1", "--out", "x"], "argument --speed: expected a number >= 0"),
                        (["simulate", "--drift", "rt:1.5", "--frames", "60", "--out", "x"],  # was a drift-free bag
                         "--frames 60 at --rate 5 Hz is 12 s: drift episodes start after 20 s and last 6-10 s; give "
                         "--frames 130 or more, or --drift-kind noise"),
                        (["alarms", "--speeds", "1.5,0", "--out", "x"], "speeds must be > 0, got 1.5, 0.0"),
                        (["alarms", "--estimates", "sim,orb", "--out", "x"], "estimates must be among sim, kiss, got orb"),
                        (["train", "x", "--share", "Mid-360"], "argument --share: expected MODEL=FRACTION"),
                        (["train", "x", "--share", "Mid360=0.3"], "got 'Mid360=0.3'"),
                        (["train", "x", "--share", "Mid-360=2"], "argument --share: expected a number within [0, 1]"),
                        (["simulate", "--clock-jump", "10,1", "--out", "x"],
                         "argument --clock-jump: expected AT,OFFSET,DURATION in s (three numbers, DURATION > 0)")):
        res = subprocess.run([sys.executable, "-m", "topometric_ros.cli", *argv], capture_output=True, text=True)
        assert res.returncode == 2 and words in res.stderr and "Traceback" not in res.stderr, (argv, res.stderr)


def test_alarms_grid_takes_health_settings_in_their_own_type_and_refuses_others():
    from topometric_ros.cli import build_parser

    args = build_parser().parse_args(["alarms", "--grid", "rate_sigma=0,1.5", "--grid", "health.rate_persist=1,2"])
    assert dict(args.grid) == {"rate_sigma": (0.0, 1.5), "rate_persist": (1, 2)}
    assert isinstance(dict(args.grid)["rate_persist"][1], int)
    for bad, why in (("window_size=5", "KEY a health setting"), ("rate_limits=a,b", "not numeric"),
                     ("rate_persist=1.5", "config key 'health.rate_persist' must be int, got 1.5"),
                     ("rate_sigma=0,50", "'health.rate_sigma' = 50 is out of range")):
        res = subprocess.run([sys.executable, "-m", "topometric_ros.cli", "alarms", "--grid", bad],
                             capture_output=True, text=True)
        assert res.returncode == 2 and why in res.stderr, (bad, res.stderr)


def test_an_output_that_is_a_file_or_a_bag_that_is_none_is_a_one_line_error(tmp_path):
    """--out naming a file (or a folder under one), a text file or an empty folder given as the bag: exit 2 and
    one line that says which, before any output folder is made. --version answers."""
    afile, empty = tmp_path / "notes.txt", tmp_path / "empty"
    afile.write_text("not a bag")
    empty.mkdir()
    cases = ((["replay", str(empty), "--out", str(afile)], f"--out {afile} is a file; give a folder"),
             (["inspect", str(empty), "--out", str(afile / "sub")],
              f"--out {afile / 'sub'}: cannot make a folder in {afile} (a file)"),
             (["replay", str(afile), "--out", str(tmp_path / "o1")],
              f"{afile} is not a rosbag2 bag: give a bag folder or its .mcap or .db3 file"),
             (["inspect", str(empty), "--out", str(tmp_path / "o2")],
              f"no rosbag2 bag at {empty} (a bag folder has metadata.yaml and .mcap or .db3 files)"))
    for argv, words in cases:
        res = subprocess.run([sys.executable, "-m", "topometric_ros.cli", *argv], capture_output=True, text=True)
        assert res.returncode == 2 and words in res.stderr and "Traceback" not in res.stderr, (argv, res.stderr)
    assert not (tmp_path / "o1").exists() and not (tmp_path / "o2").exists()
    from topometric_ros import __version__

    res = subprocess.run([sys.executable, "-m", "topometric_ros.cli", "--version"], capture_output=True, text=True)
    assert res.returncode == 0 and res.stdout.strip() == f"topometric {__version__}"


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux's /proc")
def test_an_output_folder_the_os_will_not_make_is_named_as_the_flag(office_bag):
    """/proc looks writable to root, yet no folder can be made in it: exit 2, the error names --out (not a bare
    OS message), before the bag is read."""
    res = subprocess.run([sys.executable, "-m", "topometric_ros.cli", "replay", str(office_bag[0]), "--out", "/proc/x",
                          "--segmentation", "labels", "--quiet"], capture_output=True, text=True)
    assert res.returncode == 2 and res.stderr.strip().startswith("error: --out /proc/x: "), res.stderr
    assert "Traceback" not in res.stderr


@pytest.mark.parametrize("argv, words", [
    (["alarms", "--frames", "129"], "--frames 129 at --rate 5 Hz is 25.8 s: drift episodes start after 20 s and "
                                    "last 6 s or more; give --frames 130 or more"),
    (["plane-quality", "--seed", "3-1"], "no seed in '3-1' of '3-1' (a range runs low-high)"),
    (["plane-quality", "--seed", "3-1,5"], "no seed in '3-1' of '3-1,5'"),
    (["plane-quality", "--scenes", ""], "give at least one scene"),
    (["alarms", "--estimates", ""], "give at least one value"),
])
def test_a_research_run_that_could_hold_nothing_is_refused(tmp_path, argv, words):
    """An alarms run whose bags are too short for any drift episode ended with '0/0 = nan %' and exit 0; an empty
    seed range or scene list with an error from numpy, or (plane-quality) an empty table and exit 0."""
    res = subprocess.run([sys.executable, "-m", "topometric_ros.cli", *argv, "--out", str(tmp_path / "x")],
                         capture_output=True, text=True)
    assert res.returncode == 2 and words in res.stderr and "Traceback" not in res.stderr, res.stderr
    assert not (tmp_path / "x").exists()


def test_repeated_seeds_count_once():
    """plane-quality --seed 0,0 counted every plane twice (26/26 for 13/13)."""
    from topometric_ros.cli import build_parser

    args = build_parser().parse_args(["plane-quality", "--seed", "0,0,2-3,3"])
    assert args.seed == [0, 2, 3]


def test_simulate_writes_into_an_empty_folder_but_not_into_another_bag(office_bag, tmp_path):
    """An empty folder made for the bag is used (it was 'exists already'); a bag written inside another bag's
    folder is refused (the reader then takes its files as the outer bag's)."""
    empty = tmp_path / "empty"
    empty.mkdir()
    base = [sys.executable, "-m", "topometric_ros.cli", "simulate", "--scene", "office1", "--frames", "2"]
    res = subprocess.run([*base, "--out", str(empty)], capture_output=True, text=True)
    assert res.returncode == 0 and (empty / "metadata.yaml").is_file(), res.stderr
    res = subprocess.run([*base, "--out", str(office_bag[0] / "inner")], capture_output=True, text=True)
    assert res.returncode == 2 and "is inside the bag folder" in res.stderr, res.stderr
    assert not (office_bag[0] / "inner").exists()
    project = tmp_path / "project"  # a metadata.yaml that is no rosbag2 bag's does not make a bag folder
    project.mkdir()
    (project / "metadata.yaml").write_text("title: my dataset\n")
    res = subprocess.run([*base, "--rate", "10", "--out", str(project / "out" / "sim")], capture_output=True, text=True)
    assert res.returncode == 0 and (project / "out" / "sim" / "metadata.yaml").is_file(), res.stderr


def test_an_unknown_option_is_refused_by_its_subcommand_with_the_closest_known_ones():
    """A misspelt option of a subcommand: exit 2 with that subcommand's usage (not the top level's) and the
    options it may have meant."""
    res = subprocess.run([sys.executable, "-m", "topometric_ros.cli", "replay", "bag", "--out", "o", "--windowsize",
                          "3"], capture_output=True, text=True)
    assert res.returncode == 2 and res.stderr.startswith("usage: topometric replay"), res.stderr
    assert "error: unrecognized arguments: --windowsize 3 (did you mean --window-size?)" in res.stderr
    res = subprocess.run([sys.executable, "-m", "topometric_ros.cli", "inspect", "bag", "--topic", "/x"],
                         capture_output=True, text=True)
    assert res.returncode == 2 and "usage: topometric inspect" in res.stderr
    assert "(did you mean --points-topic?)" in res.stderr


def test_benchmarks_help_lists_every_benchmark_and_refuses_an_unknown_one():
    """`python -m benchmarks --help`: every bench_<name>.py with what it measures (the ones a bare run leaves
    out marked); an unknown name: exit 2 and the list, not a ModuleNotFoundError traceback."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    names = sorted(p.stem.removeprefix("bench_") for p in (root / "benchmarks").glob("bench_*.py"))
    res = subprocess.run([sys.executable, "-m", "benchmarks", "--help"], capture_output=True, text=True, cwd=root)
    listed = [line.split()[0] for line in res.stdout.splitlines() if line.startswith("  ")]
    assert res.returncode == 0 and listed == names and "sensors" in names, res.stdout
    assert "The whole per-scan pipeline per sensor" in res.stdout and "(not in the default set)" in res.stdout
    res = subprocess.run([sys.executable, "-m", "benchmarks", "nope"], capture_output=True, text=True, cwd=root)
    assert res.returncode == 2 and "no benchmark named nope" in res.stderr and "Traceback" not in res.stderr


def test_a_subcommands_own_segmentation_default_yields_to_config_and_set(tmp_path):
    """demo and alarms default to the bags' own labels, but a --config or --set segmentation.mode wins over that
    default (only --segmentation itself wins over them); replay has no default of its own: the config's."""
    from topometric_ros.cli import _monitor_config, build_parser

    parser = build_parser()
    net = tmp_path / "net.yaml"
    net.write_text("segmentation:\n  mode: network\n")
    for argv, mode in ((["demo"], "labels"), (["demo", "--set", "segmentation.mode=network"], "network"),
                       (["alarms", "--config", str(net)], "network"),
                       (["alarms", "--config", str(net), "--segmentation", "none"], "none"),
                       (["replay", "bag", "--out", "o"], "network"), (["replay", "bag", "--out", "o", "--config", str(net),
                                                                   "--segmentation", "labels"], "labels")):
        assert _monitor_config(parser.parse_args(argv)).segmentation.mode == mode, argv


def test_plane_quality_takes_the_detector_of_its_config_unless_named(tmp_path):
    from topometric_ros.cli import _planes_config, build_parser

    cfg = tmp_path / "p.yaml"
    cfg.write_text("planes:\n  detector: open3d\n")
    parser = build_parser()
    for argv, detector in ((["plane-quality", "--config", str(cfg)], "open3d"),
                           (["plane-quality", "--config", str(cfg), "--detector", "ring"], "ring"),
                           (["plane-quality"], "ring")):
        assert _planes_config(parser.parse_args(argv)).detector == detector, argv


def test_alarms_options_of_another_mode_are_refused_not_dropped(tmp_path):
    """--grid without --calibrate-rates, --margin without --calibrate, --kiss-voxel without KISS-ICP, a calibration
    on the evaluation split, or both calibrations at once: exit 2 saying why (each was accepted and silently dropped)."""
    cases = ((["--grid", "rate_sigma=0,1"], "--grid sweeps settings for --calibrate-rates only"),
             (["--calibrate-rates", "--margin", "1"], "--margin is --calibrate's"),
             (["--calibrate", "--split", "evaluation"], "calibration runs on the calibration split only"),
             (["--kiss-voxel", "0.1"], "--kiss-voxel is KISS-ICP's"),
             (["--calibrate", "--calibrate-rates"], "not allowed with argument"))
    for extra, words in cases:
        res = subprocess.run([sys.executable, "-m", "topometric_ros.cli", "alarms", "--out", str(tmp_path / "x"), *extra],
                             capture_output=True, text=True)
        assert res.returncode == 2 and words in res.stderr and "Traceback" not in res.stderr, (extra, res.stderr)
        assert not (tmp_path / "x").exists()  # refused before any work


def test_eval_seg_flags_that_set_config_leaves_take_their_ranges(tmp_path):
    """--floor-band 5 (segmentation.floor_band: 0 to 0.2 m) and --knn 99 are refused as --set would refuse
    them: exit 2 naming the leaf and its range, before any data is read."""
    for extra, words in ((["--floor-band", "5"], "'segmentation.floor_band' = 5.0 is out of range [0, 0.2]"),
                         (["--knn", "99"], "'segmentation.knn' = 99 is out of range [0, 15]")):
        res = subprocess.run([sys.executable, "-m", "topometric_ros.cli", "eval-seg", str(tmp_path / "nothing"),
                              *extra], capture_output=True, text=True)
        assert res.returncode == 2 and words in res.stderr and "Traceback" not in res.stderr, (extra, res.stderr)


def test_outputs_beside_a_loose_bag_file_are_fine_only_its_own_folder_is_not(office_bag, tmp_path):
    """A bag given as its .mcap file: its own folder is refused for output (the next read would take the files as
    part of the bag), a folder below it is not (train's default data/cache beside data/run.mcap); for a bag
    folder, the folder and anything inside it are refused."""
    import shutil

    from topometric_ros.cli import _refuse_writing_into_bags

    data = tmp_path / "data"
    data.mkdir()
    loose = data / "run.mcap"
    shutil.copy(next(office_bag[0].glob("*.mcap")), loose)
    _refuse_writing_into_bags("--cache", str(data / "cache"), [loose])
    with pytest.raises(ValueError, match="is the folder of the bag file"):
        _refuse_writing_into_bags("--cache", str(data), [loose])
    with pytest.raises(ValueError, match="is inside the bag folder"):
        _refuse_writing_into_bags("--cache", str(office_bag[0] / "cache"), [office_bag[0]])
