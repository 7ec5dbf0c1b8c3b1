"""replay.py: a simulated bag through the Monitor -> diagnostics.mcap (decoded with the independent
mcap-ros2-support decoder), windows.csv/.json, metrics.png; truncated bags; real-time mode.

Where the metrics are not the point, the per-scan/per-window functions are a cheap real score (the spread
of the floor height across the window, from the bag's ground-truth labels)."""
import copy
import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from topometric_ros import classes, geometry
from topometric_ros.bag import BagError
from topometric_ros.config import load_config
from topometric_ros.pipeline import ProcessedScan, WindowResult
from topometric_ros.metrics.rpe import rpe as relative_pose_error
from topometric_ros.replay import CORE_COLUMNS, ReplayOptions, metrics_figure, network_options, replay
from topometric_ros.reports import pyplot

mcap_ros2_decoder = pytest.importorskip("mcap_ros2.decoder")


def floor_scan(frame, config, segmenter=None, index=-1):
    floor = frame.points[frame.labels == classes.FLOOR].astype(np.float64)
    world = geometry.transform_points(frame.pose, floor)
    return ProcessedScan(frame.stamp, frame.pose, [], points=world, index=index)


def floor_window(scans, config):
    heights = np.array([s.points[:, 2].mean() for s in scans])
    return WindowResult([s.stamp for s in scans], pne=float(np.ptp(heights)), cpv=float(heights.var()),
                        n_planes=len(scans), n_groups=1)


def cfg(**over):
    return load_config(overrides={"window.size": 5, "health.baseline_windows": 2, **over})


def run(bag_path, out, **opt):
    return replay(bag_path, out, cfg(), ReplayOptions(progress=False, **opt), floor_scan, floor_window)


def read_diagnostics(path):
    from mcap.reader import make_reader

    out = []
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[mcap_ros2_decoder.DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            out.append((channel.topic, schema.name, message.log_time, decoded))
    return out


def test_replay_writes_decodable_diagnostics_and_reports(office_bag, tmp_path):
    bag_path, truth = office_bag
    res = run(bag_path, tmp_path / "out")
    s = res.summary
    assert s["error"] == "" and s["scans_read"] == 30 and s["scans_processed"] == 30
    assert s["windows"] == 6 and s["extrinsic_source"] == "tf_static"
    # floor height agrees within a window before drift starts (ground-truth labels, tf_static extrinsic)
    assert res.windows[0]["cpv"] < 1e-4
    msgs = read_diagnostics(tmp_path / "out" / "diagnostics.mcap")
    assert len(msgs) == 6
    for (topic, schema, log_time, arr), rec in zip(msgs, res.windows):
        assert topic == "/diagnostics" and schema == "diagnostic_msgs/msg/DiagnosticArray"
        stamp = arr.header.stamp.sec + 1e-9 * arr.header.stamp.nanosec
        assert stamp == pytest.approx(rec["end"], abs=1e-6)  # bag time, not wall time
        assert log_time == pytest.approx(rec["end"] * 1e9, abs=1e3)
        st = arr.status[0]
        assert st.name == "topometric_monitor: map consistency" and st.hardware_id == "velodyne"
        values = {kv.key: kv.value for kv in st.values}
        assert float(values["pne"]) == rec["pne"] and float(values["window_end"]) == rec["end"]  # full precision
        assert st.level == {"OK": 0, "WARN": 1, "ERROR": 2}[rec["level"]]
        assert st.message == rec["message"]
    rows = list(csv.DictReader(open(tmp_path / "out" / "windows.csv")))
    assert len(rows) == 6 and float(rows[2]["cpv"]) == pytest.approx(res.windows[2]["cpv"], rel=1e-5)
    assert tuple(rows[0])[:len(CORE_COLUMNS)] == CORE_COLUMNS  # what a replay without windows writes as header
    doc = json.loads((tmp_path / "out" / "windows.json").read_text())
    assert doc["summary"]["windows"] == 6 and len(doc["windows"]) == 6
    assert all(np.isfinite(r["rpe"]) for r in res.windows)  # the bag has /odom_gt
    assert (tmp_path / "out" / "metrics.png").stat().st_size > 10_000


def test_reports_hold_stamps_at_full_precision_and_strict_json(office_bag, tmp_path):
    """windows.csv and windows.json give back every stamp exactly (1700000001.2, not 1.7e+09); windows.json is
    strict JSON (a metric that could not be computed is null, not a bare NaN that jq rejects); load_windows
    turns the nulls back into NaN."""
    import subprocess

    from topometric_ros.replay import load_windows

    bag_path, _ = office_bag
    res = run(bag_path, tmp_path / "out", plot=False)
    path = tmp_path / "out" / "windows.json"

    def refuse(constant):
        raise ValueError(f"non-standard JSON constant {constant}")

    doc = json.loads(path.read_text(), parse_constant=refuse)
    nan_keys = {k for r in res.windows for k, v in r.items() if isinstance(v, float) and not np.isfinite(v)}
    assert nan_keys and all(w[k] is None for w, r in zip(doc["windows"], res.windows) for k in nan_keys
                            if not np.isfinite(r[k]))  # the baseline windows have no z-score yet
    rows = list(csv.DictReader(open(tmp_path / "out" / "windows.csv")))
    for row, w, r in zip(rows, doc["windows"], res.windows):
        assert float(row["start"]) == w["start"] == r["start"] and float(row["end"]) == w["end"] == r["end"]
        assert float(row["pne"]) == r["pne"] and r["end"] % 1 > 0  # sub-second stamps survive
    back = load_windows(path)["windows"]
    assert all(np.isnan(b[k]) for b, r in zip(back, res.windows) for k in nan_keys if not np.isfinite(r[k]))
    if shutil.which("jq"):  # the strict parser the issue names
        out = subprocess.run(["jq", "-e", ".windows | length", str(path)], capture_output=True, text=True)
        assert out.returncode == 0 and out.stdout.strip() == str(len(res.windows)), out.stderr


def test_metrics_png_says_what_it_shows_and_keeps_its_legend_off_the_data(office_bag, tmp_path):
    """Title: bag and segmentation mode; a unit on every axis; one legend outside every plot, with the WARN and
    ERROR limits and the baseline-learning span (health.baseline_windows = 2 here: shaded over windows 0-1)."""
    from topometric_ros.replay import plot_metrics

    bag_path, truth = office_bag
    res = run(bag_path, tmp_path / "out", plot=False)
    fig = metrics_figure(res.windows, truth, res.summary)
    fig.canvas.draw()
    title = fig.get_suptitle()
    assert "bag office1_rt" in title and "segmentation network" in title  # run() keeps the config's mode
    axes = fig.axes
    assert len(axes) == 6 and all("(" in ax.get_ylabel() for ax in axes)  # a unit (or what it is) on each
    assert "‖E−I‖_F" in axes[-2].get_ylabel() and "agreement" in axes[-1].get_ylabel()
    assert "(s)" in axes[-1].get_xlabel()
    # the pose-jump limit (health.agreement_warn) is drawn on the agreement row
    assert any(np.allclose(line.get_ydata(), 0.4) for line in axes[-1].get_lines() if len(line.get_ydata()))
    (legend,) = fig.legends
    labels = [t.get_text() for t in legend.get_texts()]
    for wanted in ("WARN limit", "ERROR limit", "WARN window", "ERROR window", "learning baseline (2 windows)",
                   "RPE from ground truth"):
        assert wanted in labels, labels
    box = legend.get_window_extent()
    assert all(not box.overlaps(ax.get_window_extent()) for ax in axes)  # outside the data
    spans = [p for p in axes[0].patches if abs(p.get_x() - 0.0) < 1e-9]  # the baseline span starts at 0 s
    assert any(abs(p.get_width() - (res.windows[1]["end"] - res.windows[0]["start"])) < 1e-6 for p in spans)
    pyplot().close(fig)
    plot_metrics(res.windows, tmp_path / "m.png", truth, res.summary)
    assert (tmp_path / "m.png").stat().st_size > 10_000


def test_replay_of_a_truncated_bag_keeps_what_it_holds_and_says_so(office_bag, tmp_path):
    """(The damaged-bag variants and their intact-scan counts are in test_damaged_bags.)"""
    bag_path, _ = office_bag
    broken = tmp_path / "broken"
    shutil.copytree(bag_path, broken)
    (mcap_file,) = broken.glob("*.mcap")
    data = mcap_file.read_bytes()
    mcap_file.write_bytes(data[: int(len(data) * 0.6)])
    res = run(broken, tmp_path / "out")
    s = res.summary
    assert s["error"] == "" and "no readable summary" in s["notes"][0] and s["notes"][-1].startswith("damaged bag:")
    assert 0 < s["scans_read"] < 30 and 1 <= s["windows"] < 6 and s["bag_read"]["chunks_damaged"] == 1
    assert len(read_diagnostics(tmp_path / "out" / "diagnostics.mcap")) == s["windows"]
    assert json.loads((tmp_path / "out" / "windows.json").read_text())["summary"]["notes"] == s["notes"]


def test_realtime_mode_runs_through_the_live_worker(office_bag, tmp_path):
    bag_path, _ = office_bag
    res = run(bag_path, tmp_path / "out", rate="20", plot=False)  # 20x real time: 6 s of bag in ~0.3 s
    c = res.summary["counters"]
    assert res.summary["mode"] == "live x20"
    assert c["scans_processed"] + c["dropped_scans"] == 30
    assert res.summary["windows"] == len(read_diagnostics(tmp_path / "out" / "diagnostics.mcap"))


def test_missing_bag_and_bad_rate_are_clear_errors(tmp_path):
    with pytest.raises(BagError):
        run(tmp_path / "nope", tmp_path / "out")
    with pytest.raises(ValueError):
        ReplayOptions  # noqa: B018
        replay(tmp_path, tmp_path / "out", cfg(), ReplayOptions(rate="fast", progress=False))


def test_rpe_is_zero_for_identical_and_grows_with_error():
    gt = geometry.yaw_pose(np.arange(5.0), 0.0, 0.0, 0.1 * np.arange(5))
    assert relative_pose_error(gt, gt) == pytest.approx(0.0, abs=1e-12)
    est = gt @ geometry.make_pose(np.eye(3), [[0, 0, 0.01 * k] for k in range(5)])
    worse = gt @ geometry.make_pose(np.eye(3), [[0, 0, 0.03 * k] for k in range(5)])
    assert 0 < relative_pose_error(gt, est) < relative_pose_error(gt, worse)


def test_replay_survives_a_bag_of_bad_input_and_counts_each_case(office_bag, tmp_path):
    """Copy the office bag, injecting: a malformed cloud, a cloud of NaN/inf, an empty cloud, a duplicate
    scan, odometry with a non-unit (x3) and a zero quaternion, and a backwards jump of all stamps."""
    from topometric_ros import bag
    from topometric_ros.cloud import make_cloud, rosbags_types, stamp_seconds

    bag_path, _ = office_bag
    bad = tmp_path / "bad"
    n_points, injected = 0, False
    with bag.BagWriter(bad) as w:
        for topic, t_ns, msg in bag.read_messages(bag_path):
            t = t_ns * 1e-9
            w.write(topic, t, msg)
            if topic == "/points":
                n_points += 1
                if n_points == 3:
                    w.write(topic, t + 0.001, msg)  # duplicate stamp
                if n_points == 4:
                    broken = copy.copy(msg)
                    broken.point_step = 7  # fields beyond point_step
                    w.write(topic, t + 0.001, broken)
                if n_points == 5:  # every point NaN (x, y, z), same stamp
                    nans = np.full(1000, np.nan, np.float32)
                    nan = make_cloud({"x": nans, "y": nans, "z": nans}, stamp_seconds(msg.header), "velodyne",
                                     rosbags_types(bag.typestore()))
                    w.write(topic, t + 0.001, nan)
                if n_points == 6:
                    empty = copy.copy(msg)
                    empty.width, empty.row_step, empty.data = 0, 0, np.zeros(0, np.uint8)
                    w.write(topic, t + 0.001, empty)
            if topic == "/odom" and n_points == 8 and not injected:
                injected = True
                q = msg.pose.pose.orientation
                odd = copy.deepcopy(msg)
                odd.pose.pose.orientation.x, odd.pose.pose.orientation.w = 3 * q.x, 3 * q.w
                odd.pose.pose.orientation.y, odd.pose.pose.orientation.z = 3 * q.y, 3 * q.z
                odd.header.stamp.nanosec = (odd.header.stamp.nanosec + 1000) % 1_000_000_000
                w.write(topic, t + 0.0001, odd)
                zero = copy.deepcopy(msg)
                zero.pose.pose.orientation.x = zero.pose.pose.orientation.y = 0.0
                zero.pose.pose.orientation.z = zero.pose.pose.orientation.w = 0.0
                w.write(topic, t + 0.0002, zero)
    res = run(bad, tmp_path / "out")
    c = res.summary["counters"]
    assert res.summary["error"] == ""
    assert c["dropped_duplicate"] == 1
    assert c["dropped_bad_scan"] == 3  # malformed, all-NaN, empty
    assert c["nonfinite_points"] > 0
    assert c["bad_poses"] == 1  # the zero quaternion; the x3 one is normalised and used
    notes = res.summary["notes"]  # each kind left out in the notes, with its count and last reason
    assert "left out: 3 malformed or empty clouds of /points; last: malformed cloud: cloud has zero points" in notes, notes
    assert "left out: 1 invalid odometry message of /odom; last: bad odometry: quaternion with zero or non-finite norm" \
        in notes, notes
    assert c["scans_processed"] == 30 and res.summary["windows"] == 6
    assert len(read_diagnostics(tmp_path / "out" / "diagnostics.mcap")) == 6


def test_replay_cli_exit_codes(office_bag, tmp_path, capsys):
    from topometric_ros import cli

    bag_path, _ = office_bag
    assert cli.main(["replay", str(tmp_path / "missing"), "--out", str(tmp_path / "o1"), "--quiet"]) == 2
    assert "bag not found" in capsys.readouterr().err
    broken = tmp_path / "broken"
    shutil.copytree(bag_path, broken)
    (f,) = broken.glob("*.mcap")
    f.write_bytes(f.read_bytes()[:100_000])  # not one whole cloud left
    assert cli.main(["replay", str(broken), "--out", str(tmp_path / "o2"), "--quiet", "--no-plot",
                     "--segmentation", "labels"]) == 1
    out = capsys.readouterr().out
    assert "NO SCAN PROCESSED: no message of /points could be read" in out and "damaged bag:" in out
    assert (tmp_path / "o2" / "windows.json").exists()


def rewrite(src, dst, change, scans=6):
    """The first ``scans`` clouds of a bag (and everything up to them) through change(topic, msg) -> list of
    (topic, msg) to write instead."""
    from topometric_ros import bag

    n = 0
    with bag.BagWriter(dst) as w:
        for topic, t_ns, msg in bag.read_messages(src):
            n += topic == "/points"
            if n > scans:
                break
            for new_topic, new_msg in change(topic, msg):
                w.write(new_topic, t_ns * 1e-9, new_msg)
    return dst


def replay_cli(bag_path, out, capsys, *extra):
    from topometric_ros import cli

    code = cli.main(["replay", str(bag_path), "--out", str(out), "--quiet", "--no-plot", *extra])
    return code, capsys.readouterr().out, json.loads((out / "windows.json").read_text())["summary"]


def test_a_sidecar_odometry_bag_on_another_receive_clock_still_pairs_every_scan(office_bag, tmp_path,
                                                                                 split_off_odometry):
    """The recording's receive times are its system clock (1000 s after the stamps), the sidecar odometry bag
    was written at the stamps: read beside it, every scan finds its poses (merged by header stamp; by receive
    time all odometry came first and a 1 s pose buffer had forgotten it), the same windows as the bag alone."""
    bag_path, _ = office_bag
    recording, sidecar = split_off_odometry(bag_path, tmp_path / "recording", tmp_path / "sidecar")
    config = load_config(overrides={"segmentation.mode": "labels", "window.size": 5, "window.pose_horizon_s": 1.0})
    alone = replay(bag_path, tmp_path / "alone", config, ReplayOptions(progress=False, plot=False)).summary
    both = replay(recording, tmp_path / "both", config, ReplayOptions(beside=(sidecar,), progress=False,
                                                                      plot=False)).summary
    assert alone["counters"]["scans_processed"] == 30 and alone["windows"] == 6
    assert both["counters"]["scans_processed"] == 30 and both["windows"] == 6
    assert both["counters"]["dropped_scans"] == 0
    # the two recordings' receive times are two clocks: read on the stamps, no odometry "ends" 1000 s early,
    assert not any(k in n for n in both["notes"] for k in ("odometry ends", "odometry starts", "STALE", "clock"))


def test_a_late_tf_static_and_bad_ground_truth_lose_nothing_and_say_so(office_bag, tmp_path):
    """/tf_static recorded after every scan: read first, every window as with it in front (no note); ground
    truth with a NaN position and one with a zero quaternion: left out, counted in a note, RPE from the rest."""
    from topometric_ros import bag

    bag_path, _ = office_bag
    moved = tmp_path / "late_tf"
    statics, bad, last = [], 0, 0.0
    with bag.BagWriter(moved) as w:
        for topic, t_ns, msg in bag.read_messages(bag_path):
            last = t_ns * 1e-9
            if topic == "/tf_static":
                statics.append(msg)
                continue
            if topic == "/odom_gt" and bad < 2 and last > 2.0:
                msg = copy.deepcopy(msg)
                if bad == 0:
                    msg.pose.pose.position.x = float("nan")
                else:
                    q = msg.pose.pose.orientation
                    q.x = q.y = q.z = q.w = 0.0
                bad += 1
            w.write(topic, last, msg)
        for msg in statics:
            w.write("/tf_static", last + 1.0, msg)
    config = load_config(overrides={"segmentation.mode": "labels", "window.size": 5})
    front = replay(bag_path, tmp_path / "front", config, ReplayOptions(progress=False, plot=False))
    late = replay(moved, tmp_path / "late", config, ReplayOptions(progress=False, plot=False))
    assert statics and bad == 2 and late.summary["extrinsic_source"] == "tf_static"
    assert [w["pne"] for w in late.windows] == [w["pne"] for w in front.windows] and len(late.windows) == 6
    assert not any("extrinsic changed" in n for n in late.summary["notes"])
    assert "2 ground-truth messages of /odom_gt left out: no finite rigid transform (RPE uses the others)" in \
        late.summary["notes"]
    assert all(np.isfinite(w["rpe"]) for w in late.windows)


def test_topics_a_config_file_names_are_the_replays_unless_a_flag_names_others(office_bag, tmp_path, capsys):
    """A robot's parameter file (odom_topic /slam/odometry) given as --config picks that topic in a bag that
    has /odom too; --odom-topic wins over it; the shipped file (the node's default topics) names none."""
    import yaml

    bag_path, _ = office_bag
    both = rewrite(bag_path, tmp_path / "both", lambda t, m: [(t, m), ("/slam/odometry", m)] if t == "/odom"
                   else [(t, m)], scans=30)
    robot = tmp_path / "robot.yaml"
    robot.write_text(yaml.safe_dump({"/**": {"ros__parameters": {"odom_topic": "/slam/odometry",
                                                                  "segmentation.mode": "labels"}}}))
    code, out, summary = replay_cli(both, tmp_path / "o1", capsys, "--config", str(robot))
    assert code == 0 and summary["odom_topic"] == "/slam/odometry", out
    code, out, summary = replay_cli(both, tmp_path / "o2", capsys, "--config", str(robot), "--odom-topic", "/odom")
    assert code == 0 and summary["odom_topic"] == "/odom", out
    code, out, summary = replay_cli(both, tmp_path / "o3", capsys, "--config",
                                    str(Path(__file__).resolve().parents[1] / "config" / "topometric.yaml"),
                                    "--segmentation", "labels")
    assert code == 0 and summary["odom_topic"] == "/odom" and "other nav_msgs/msg/Odometry topics too" in out, out


def test_inspect_gives_a_cloud_that_cannot_be_segmented_its_row_and_goes_on(office_bag, tmp_path, capsys):
    """labels mode, the third cloud without its label field: that row says why, the other five are inspected."""
    from topometric_ros import cli

    bag_path, _ = office_bag
    seen = []

    def third_unlabelled(topic, msg):
        if topic == "/points":
            seen.append(topic)
            if len(seen) == 3:
                msg = copy.copy(msg)
                msg.fields = [f for f in msg.fields if f.name != "label"]
        return [(topic, msg)]

    path = rewrite(bag_path, tmp_path / "third", third_unlabelled)
    assert cli.main(["inspect", str(path), "--out", str(tmp_path / "out"), "--no-plot", "--quiet",
                     "--segmentation", "labels"]) == 0
    with open(tmp_path / "out" / "scans.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 6 and [bool(r["error"]) for r in rows] == [False, False, True, False, False, False], rows
    assert "label" in rows[2]["error"] and all(int(r["planes"]) > 0 for i, r in enumerate(rows) if i != 2)


def test_inspect_names_the_settings_it_does_not_use(office_bag, tmp_path, capsys):
    """window, health and deskew settings do nothing without odometry and windows: inspect says so; the
    per-scan settings it reads (planes, window.voxel_size) pass without a note."""
    from topometric_ros import cli

    bag_path, _ = office_bag
    args = ["inspect", str(bag_path), "--out", str(tmp_path / "out"), "--no-plot", "--quiet", "--limit", "1",
            "--segmentation", "labels", "--set", "planes.min_points=40", "--set", "window.voxel_size=0.05"]
    assert cli.main(args) == 0
    assert "no effect" not in capsys.readouterr().err
    assert cli.main(args + ["--set", "window.size=10", "--set", "health.warn_sigma=4", "--set",
                            "sensor.deskew=off"]) == 0
    err = capsys.readouterr().err
    assert "window.size, health.warn_sigma, sensor.deskew has no effect here" in err, err
    with pytest.raises(SystemExit) as stop:  # inspect makes no windows: it does not offer --window-size
        cli.main(args + ["--window-size", "5"])
    assert stop.value.code == 2 and "unrecognized arguments: --window-size 5" in capsys.readouterr().err


def test_replay_that_processes_no_scan_fails_and_says_why(office_bag, tmp_path, capsys):
    """Zero scans processed: exit 1, the reason, the bag's topics with types and counts, and the mode that ran."""
    bag_path, _ = office_bag

    def no_label(topic, msg):  # what a real driver's cloud looks like: no label field
        if topic == "/points":
            msg = copy.copy(msg)
            msg.fields = [f for f in msg.fields if f.name != "label"]
        return [(topic, msg)]

    cases = {
        "labels_without_label_field": (rewrite(bag_path, tmp_path / "nolabel", no_label), ["--segmentation", "labels"],
                                       "every scan failed in processing; last: scan",
                                       "use --segmentation network"),
        "no_odometry": (rewrite(bag_path, tmp_path / "noodom", lambda t, m: [] if "odom" in t else [(t, m)]),
                        ["--segmentation", "labels"], "no odometry: the bag has no nav_msgs/msg/Odometry topic; the "
                        "monitor judges the SLAM's poses as nav_msgs/msg/Odometry",
                        "record the SLAM's odometry topic with the clouds; `topometric inspect` looks at the clouds alone"),
        "wrong_topic_named": (rewrite(bag_path, tmp_path / "two", lambda t, m: [(t, m)] + [("/front/points", m)] * (t == "/points")),
                              ["--segmentation", "labels", "--points-topic", "/lidar"],
                              "PointCloud2 topic /lidar is not in the bag (its PointCloud2 topics: /front/points, /points)",
                              "name one with --points-topic"),
        "named_topic_never_swapped": (bag_path, ["--segmentation", "labels", "--points-topic", "/lidar"],
                                      "PointCloud2 topic /lidar is not in the bag (its PointCloud2 topics: /points)",
                                      "name one with --points-topic"),
        "named_odometry_never_swapped": (bag_path, ["--segmentation", "labels", "--odom-topic", "/slam"],
                                         "no odometry: /slam is not in the bag (its Odometry topics: /odom, /odom_gt)",
                                         "name the topic with --odom-topic"),
        "topic_of_another_type": (bag_path, ["--segmentation", "none", "--points-topic", "/odom"],
                                  "topic /odom holds nav_msgs/msg/Odometry, not sensor_msgs/msg/PointCloud2", ""),
        "odometry_of_another_type": (bag_path, ["--segmentation", "none", "--odom-topic", "/points"],
                                     "topic /points holds sensor_msgs/msg/PointCloud2, not nav_msgs/msg/Odometry "
                                     "(its Odometry topics: /odom, /odom_gt)", "name one with --odom-topic"),
    }
    for name, (path, args, reason, hint) in cases.items():
        code, out, summary = replay_cli(path, tmp_path / f"out_{name}", capsys, *args)
        assert code == 1 and summary["scans_processed"] == 0, (name, out)
        assert f"NO SCAN PROCESSED: {reason}" in out and hint in out and summary["no_scans"].startswith(reason), (name, out)
        assert "  /points  sensor_msgs/msg/PointCloud2  " in out, (name, out)
        assert f"segmentation   {args[1]} (" in out and "sensor         read off each cloud" in out, (name, out)
        # said once, as the reason: no note of a window or of scans without odometry besides it
        assert not any(n.startswith("no window") or "with no odometry at" in n for n in summary["notes"]), (name, out)
    assert "  /odom  nav_msgs/msg/Odometry  " in out  # the bag's topics with their types and counts


def test_sigterm_stops_a_replay_like_ctrl_c(office_bag, tmp_path):
    """SIGTERM (a timeout, a scheduler) mid-replay: exit 130 with "interrupted", no traceback, and the
    diagnostics of what was processed written (the 30-scan bag at half real rate takes 12 s; the signal
    comes 2 s after the replay has started)."""
    import signal
    import subprocess
    import sys
    import time

    bag_path, _ = office_bag
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "topometric_ros.cli", "replay", str(bag_path), "--out", str(out),
                             "--segmentation", "labels", "--rate", "0.5", "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while not out.exists() and time.monotonic() < deadline:  # replay() has started (its imports are done)
        time.sleep(0.1)
    time.sleep(2.0)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "interrupted" in err and "Traceback" not in err, err
    assert (out / "diagnostics.mcap").stat().st_size > 0


def test_a_folder_that_is_no_bag_is_refused_before_anything_runs(tmp_path):
    from topometric_ros.bag import BagError
    from topometric_ros.replay import replay

    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "readme.txt").write_text("not a bag")
    with pytest.raises(BagError, match="no rosbag2 bag at .*notes .a bag folder has metadata.yaml"):
        replay(tmp_path / "notes", tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_points_lost_to_a_wrong_sensor_model_and_unused_time_fields_are_reported(office_bag, tmp_path, capsys):
    """A 32-beam bag replayed as a VLP-16 loses its beams 16-31: the console and windows.json give the points
    dropped and ask whether sensor.model is right. Clouds whose time field reads 0 everywhere say, per cloud
    count, why it was not used (the azimuth gives the times)."""
    from topometric_ros.cloud import read_scan

    bag_path, _ = office_bag

    def zero_time(topic, msg):
        if topic != "/points":
            return [(topic, msg)]
        (offset,) = [f.offset for f in msg.fields if f.name == "time"]
        data = np.frombuffer(bytes(msg.data), np.uint8).reshape(-1, msg.point_step).copy()
        data[:, offset:offset + 4] = 0
        msg = copy.copy(msg)
        msg.data = data.reshape(-1)
        return [(topic, msg)]

    short = rewrite(bag_path, tmp_path / "short", zero_time, scans=6)
    from topometric_ros import bag

    lost = sum(int((read_scan(m).beam >= 16).sum()) for t, _, m in bag.read_messages(short) if t == "/points")
    code, out, summary = replay_cli(short, tmp_path / "out", capsys, "--segmentation", "labels", "--window-size",
                                    "3", "--set", "sensor.model=VLP-16")
    assert code == 0 and summary["windows"] == 2 and summary["counters"]["bad_beam_points"] == lost > 0, out
    note = f"{lost} points dropped: beam id outside 0..15, the 16 beams of sensor.model VLP-16; is sensor.model right?"
    assert note in summary["notes"] and f"note           {note}" in out
    assert "6 clouds: time field 'time' is constant; times from the azimuth instead" in summary["notes"], out


def test_a_bag_shorter_than_a_window_says_so_and_how_to_replay_it(office_bag, tmp_path, capsys):
    """Scans processed but no window (3 scans of 5 Hz, automatic windows of 5): not a bare "windows 0" but exit 1,
    the reason and the option that gives a window, also on metrics.png; with that option, one window. Two scans
    do not even set the automatic size, and say so."""
    bag_path, _ = office_bag
    rewrite(bag_path, tmp_path / "two", lambda t, m: [(t, m)], scans=2)
    code, out, summary = replay_cli(tmp_path / "two", tmp_path / "out2", capsys, "--segmentation", "labels")
    assert code == 1 and summary["windows"] == 0 and summary["window_scans"] is None, out
    assert ("no window: 2 scans processed, fewer than a window (automatic: 1 s of scans, set from the first 3 "
            "scans' stamps (up to 6 when uneven)); replay with --window-size 2") in out
    rewrite(bag_path, tmp_path / "three", lambda t, m: [(t, m)], scans=3)
    code, out, summary = replay_cli(tmp_path / "three", tmp_path / "out", capsys, "--segmentation", "labels")
    assert code == 1 and summary["scans_processed"] == 3 and summary["windows"] == 0, out
    assert ("note           no window: 3 scans processed, fewer than a window of 5 scans (automatic: 1 s at 5 Hz); "
            "replay with --window-size 3") in out
    assert "window         5 scans (automatic: 1 s at 5 Hz)" in out and summary["window_scans"] == 5
    with open(tmp_path / "out" / "windows.csv") as f:  # a header all the same, for scripts reading many replays
        assert tuple(csv.DictReader(f).fieldnames) == CORE_COLUMNS
    fig = metrics_figure([], None, summary)  # metrics.png says so too, not six empty panels alone
    assert any(t.get_text().startswith("NO WINDOW\nno window: 3 scans processed") for t in fig.texts)
    pyplot().close(fig)
    code, out, summary = replay_cli(tmp_path / "three", tmp_path / "out3", capsys, "--segmentation", "labels",
                                    "--window-size", "3")
    assert code == 0 and summary["windows"] == 1 and "no window" not in out, out


def test_a_stream_that_keeps_restarting_before_an_automatic_window_is_set_says_so():
    """Stamps that go back every other scan never give three in a row to set the automatic size: the reason is
    the restarts, not a bag too short (whose hint, a smaller --window-size, would not help)."""
    from topometric_ros.replay import _why_no_window
    from topometric_ros.window import SlidingWindow

    window = SlidingWindow(0)
    for stamp in (10.0, 10.1, 5.0, 5.1, 1.0, 1.1):
        assert window.push(stamp, stamp) is None
    assert window.size is None and window.resets == 2
    why = _why_no_window({"scans_processed": 6}, window, "")
    assert why == ("no window from 6 scans: the stream restarted 2 times (stamps not newer than the last) before 3 "
                   "scans in a row could set the automatic window's size"), why


def test_the_progress_bar_ends_at_every_scan_done_with_the_windows_beside_it(office_bag, tmp_path, capsys):
    """The bar counts scans the monitor is done with, not clouds read (the reader runs ahead of the work), and
    its last state is drawn before it is cleared: 3/3 and the window they made, not 0/3."""
    bag_path, _ = office_bag
    rewrite(bag_path, tmp_path / "three", lambda t, m: [(t, m)], scans=3)
    config = load_config(overrides={"window.size": 3, "health.baseline_windows": 2})
    replay(tmp_path / "three", tmp_path / "out", config, ReplayOptions(progress=True, plot=False),
           floor_scan, floor_window)
    states = [s.strip() for s in capsys.readouterr().err.split("\r") if "replay:" in s]
    assert states and states[-1].startswith("replay: 100%") and " 3/3 " in states[-1], states
    assert states[-1].endswith("windows 1, WARN 0, ERROR 0]"), states


def test_a_replay_that_processes_scans_names_its_mode_and_sensor(office_bag, tmp_path, capsys):
    bag_path, _ = office_bag
    rewrite(bag_path, tmp_path / "short", lambda t, m: [(t, m)], scans=6)
    code, out, summary = replay_cli(tmp_path / "short", tmp_path / "out", capsys, "--segmentation", "labels",
                                    "--window-size", "5", "--set", "sensor.model=VLP-32C")
    assert code == 0 and summary["scans_processed"] == 6 and summary["no_scans"] == "", out
    assert "segmentation   labels (the clouds' own label field)" in out and "sensor         VLP-32C, velodyne" in out
    assert "NO SCAN" not in out
    # the network's options are named beside the mode (none here: labels); the default: one pass and the vote
    assert network_options(load_config(None)) == ", a 3-nearest-neighbour vote"
    assert network_options(load_config(None, {"segmentation.passes": 3, "segmentation.max_beams": 64,
                                               "segmentation.knn": 0})) == \
        ", 3 passes, at most 64 beams through the network"
    assert network_options(load_config(None, {"segmentation.knn": 5})) == ", a 5-nearest-neighbour vote"
    assert network_options(load_config(None), "int8") == ", int8 inference, a 3-nearest-neighbour vote"
    assert network_options(load_config(None, {"segmentation.mode": "labels", "segmentation.max_beams": 64})) == ""


def test_replay_with_the_real_pipeline_on_ground_truth_labels(office_bag, tmp_path):
    """The default per-scan/per-window functions (pipeline.process_scan / score_window): finite scores,
    planes in every window, no alarm in a drift-free stretch (the fixture's drift starts after 20 s)."""
    bag_path, truth = office_bag
    # a 3-window baseline (a test-sized bag) is far noisier than the calibrated 10-window one: wider band
    config = load_config(overrides={"segmentation.mode": "labels", "health.baseline_windows": 3,
                                    "health.warn_sigma": 6.0})
    res = replay(bag_path, tmp_path / "out", config, ReplayOptions(progress=False, plot=False))
    assert res.summary["error"] == "" and res.summary["windows"] == 6
    assert all(ep["start"] > res.windows[-1]["end"] for ep in truth["episodes"])
    for r in res.windows:
        assert np.isfinite(r["pne"]) and np.isfinite(r["cpv"]) and r["n_planes"] >= 10
        assert r["level"] == "OK", r["message"]
        assert r["rpe"] == pytest.approx(0.0, abs=1e-6)
        assert r["ms_scans_planes"] > 0  # per-step timings of the pipeline reach the report


def test_an_odometry_gap_is_reported_stale_in_bag_time(office_bag, tmp_path):
    """No /odom for 3 s of bag time: one STALE status (bag-time stamped) and the scans in the gap dropped."""
    from topometric_ros import bag

    bag_path, _ = office_bag
    gap = tmp_path / "gap"
    t_first, odom_times = None, []
    with bag.BagWriter(gap) as w:
        for topic, t_ns, msg in bag.read_messages(bag_path):
            t = t_ns * 1e-9
            t_first = t if topic == "/points" and t_first is None else t_first
            if topic == "/odom" and t_first is not None and 1.0 < t - t_first < 4.0:
                continue
            odom_times += [t] * (topic == "/odom")
            w.write(topic, t, msg)
    config = cfg(**{"health.stale_after_s": 1.5})
    res = replay(gap, tmp_path / "out", config, ReplayOptions(progress=False, plot=False), floor_scan, floor_window)
    msgs = read_diagnostics(tmp_path / "out" / "diagnostics.mcap")
    stale = [(log_time, arr.status[0]) for _, _, log_time, arr in msgs
             if arr.status[0].level == 3]
    assert len(stale) == 1
    log_time, status = stale[0]
    assert "no odometry for" in status.message
    assert 1.0 + 1.5 < log_time * 1e-9 - t_first < 4.0 + 0.5  # in the gap, in bag time
    assert res.summary["counters"]["dropped_no_pose"] >= 10  # 2.6 s of 5 Hz scans had no odometry
    # the odometry's interval is its usual step (the median), not pulled up by the gap
    assert res.summary["odometry_interval_s"] == pytest.approx(np.median(np.diff(odom_times)), abs=1e-6)
    assert res.summary["odometry_interval_s"] < np.mean(np.diff(odom_times)) - 0.01


def test_a_damaged_bag_whose_clouds_cannot_be_read_says_so_not_that_it_has_none(office_bag, tmp_path, capsys):
    """The .mcap cut to its first 100 bytes (metadata.yaml intact): replay (exit 1) and inspect (exit 2) say the
    clouds cannot be read because the storage is damaged, and what metadata.yaml lists."""
    from topometric_ros import cli

    bag_path, _ = office_bag
    cut = tmp_path / "cut"
    shutil.copytree(bag_path, cut)
    (mcap_file,) = cut.glob("*.mcap")
    mcap_file.write_bytes(mcap_file.read_bytes()[:100])
    code, out, summary = replay_cli(cut, tmp_path / "out", capsys, "--segmentation", "labels")
    reason = f"/points cannot be read from {cut}: its storage is damaged ("
    assert code == 1 and summary["no_scans"].startswith(reason), out
    assert "metadata.yaml lists " in summary["no_scans"] and "/points (sensor_msgs/msg/PointCloud2, 30)" in out
    assert cli.main(["inspect", str(cut), "--out", str(tmp_path / "insp"), "--segmentation", "labels"]) == 2
    assert f"error: {reason}" in capsys.readouterr().err


def test_ground_truth_topic_problems_are_noted(office_bag, tmp_path):
    """A ground-truth topic named but absent, or the odometry topic itself: a note each, no RPE."""
    bag_path, _ = office_bag
    absent = run(bag_path, tmp_path / "a", gt_topic="/truth").summary["notes"]
    assert "ground-truth topic /truth is not in the bag: no RPE (its Odometry topics: /odom, /odom_gt)" in absent
    same = run(bag_path, tmp_path / "b", gt_topic="/odom", odom_topic="/odom").summary["notes"]
    assert any(n.startswith("the ground-truth topic /odom is the odometry topic") for n in same), same
    swapped = run(bag_path, tmp_path / "d", gt_topic="/odom").summary["notes"]  # the estimate: the other one
    assert ("/odom is named for another role: using the bag's only other nav_msgs/msg/Odometry topic /odom_gt"
            in swapped), swapped
    assert not any("ground-truth" in n for n in run(bag_path, tmp_path / "c").summary["notes"])  # /odom_gt is there
    clouds = run(bag_path, tmp_path / "e", gt_topic="/points").summary
    assert ("ground-truth topic /points holds sensor_msgs/msg/PointCloud2, not nav_msgs/msg/Odometry: no RPE"
            in clouds["notes"]) and clouds["windows"] == 6


def test_inspect_refuses_a_topic_of_another_type_with_its_type(office_bag, tmp_path, capsys):
    from topometric_ros import cli

    bag_path, _ = office_bag
    assert cli.main(["inspect", str(bag_path), "--out", str(tmp_path / "o"), "--points-topic", "/odom"]) == 2
    err = capsys.readouterr().err
    assert "error: topic /odom holds nav_msgs/msg/Odometry, not sensor_msgs/msg/PointCloud2" in err, err
    assert not (tmp_path / "o").exists()


def test_an_out_folder_inside_the_bag_is_refused_before_anything_runs(office_bag, tmp_path, capsys):
    """replay, inspect and audit: --out the bag folder or a folder in it is refused (exit 2, nothing written)."""
    from topometric_ros import cli

    bag_path, _ = office_bag
    mine = tmp_path / "bag"
    shutil.copytree(bag_path, mine)
    before = sorted(p.name for p in mine.iterdir())
    for argv in (["replay", str(mine), "--out", str(mine)], ["inspect", str(mine), "--out", str(mine / "r")],
                 ["audit", str(mine), "--out", str(mine / "a"), "--engine", "local"],
                 ["replay", str(next(mine.glob("*.mcap"))), "--out", str(mine)]):
        assert cli.main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith("error: --out ") and (" bag folder " in err or "bag file" in err), err
    link = tmp_path / "link"  # the bag through a link is the bag
    link.symlink_to(mine, target_is_directory=True)
    assert cli.main(["inspect", str(mine), "--out", str(link)]) == 2 and "is the bag folder" in capsys.readouterr().err
    assert sorted(p.name for p in mine.iterdir()) == before
    loose = tmp_path / "downloads"  # a loose .mcap: a folder beside it is fine, only its own folder is refused
    loose.mkdir()
    shutil.copy(next(mine.glob("*.mcap")), loose / "run.mcap")
    assert cli.main(["inspect", str(loose / "run.mcap"), "--out", str(loose), "--limit", "1"]) == 2
    assert cli.main(["inspect", str(loose / "run.mcap"), "--out", str(loose / "inspect"), "--limit", "1",
                     "--segmentation", "labels", "--no-plot"]) == 0


# ------------------------------------------------------------------ what the odometry leaves unjudged, said
def _rewritten(bag_path, out, change):
    """A copy of ``bag_path`` at ``out``: change(topic, t, msg, t_first_cloud) -> [(topic, t, msg), ...]."""
    from topometric_ros import bag

    first = None
    with bag.BagWriter(out) as w:
        for topic, t_ns, msg in bag.read_messages(bag_path):
            t = t_ns * 1e-9
            first = t if topic == "/points" and first is None else first
            for item in change(topic, t, msg, first):
                w.write(*item)
    return out


def _notes(bag_path, out, **over):
    config = load_config(overrides={"segmentation.mode": "labels", "window.size": 5, **over})
    return replay(bag_path, out, config, ReplayOptions(progress=False, plot=False)).summary


def test_odometry_that_ends_before_the_clouds_is_said_not_passed_as_green(office_bag, tmp_path):
    """/odom stops 3 s into a 6 s bag: the lost scans are a left-out note, the odometry's end a note, the STALE
    status a note (before: all windows OK and nothing said but a counter)."""
    bag_path, _ = office_bag
    cut = _rewritten(bag_path, tmp_path / "cut", lambda topic, t, msg, first: [] if topic == "/odom" and first
                     is not None and t - first > 3.0 else [(topic, t, msg)])
    s = _notes(cut, tmp_path / "out", **{"health.stale_after_s": 1.0})
    lost = s["counters"]["dropped_no_pose"]
    assert 10 <= lost <= 16 and s["scans_processed"] == 30 - lost
    notes = "\n".join(s["notes"])
    assert f"left out: {lost} scans with no odometry at their stamps; last: no odometry within" in notes
    assert "the odometry ends 2." in notes and "the scans after it are not judged" in notes
    assert "STALE 1 time in diagnostics.mcap" in notes and "no odometry for" in notes
    whole = _notes(bag_path, tmp_path / "whole", **{"health.stale_after_s": 1.0})
    assert not any(k in n for n in whole["notes"] for k in ("left out", "odometry ends", "STALE"))


def test_clouds_missing_from_the_recording_are_said(office_bag, tmp_path):
    """Every third cloud after the fifth left out of the recording (9 of 30): a note counts them from the stamps; the bag
    as recorded has none."""
    bag_path, _ = office_bag
    count = {"n": 0}

    def thin(topic, t, msg, first):
        if topic == "/points":
            count["n"] += 1
            if count["n"] > 5 and count["n"] % 3 == 0:
                return []
        return [(topic, t, msg)]

    s = _notes(_rewritten(bag_path, tmp_path / "thin", thin), tmp_path / "out")
    assert s["counters"]["scans_missing"] == 8 and s["scans_read"] == 21  # the 9th gone is the last: no step after it
    assert "the cloud stamps show 8 scans missing (steps of 1.6 scan periods or more" in "\n".join(s["notes"])
    whole = _notes(bag_path, tmp_path / "whole")
    assert whole["counters"]["scans_missing"] == 0 and not any("missing" in n for n in whole["notes"])


def test_odometry_of_a_frame_tf_static_does_not_link_to_the_clouds_is_said(office_bag, tmp_path):
    """The odometry of base_footprint, /tf_static only base_link -> sensor: the identity extrinsic is used and
    a note says which frames are unlinked and what /tf_static holds."""
    bag_path, _ = office_bag

    def footprint(topic, t, msg, first):
        if topic == "/odom":
            msg = copy.deepcopy(msg)
            msg.child_frame_id = "base_footprint"
        return [(topic, t, msg)]

    s = _notes(_rewritten(bag_path, tmp_path / "fp", footprint), tmp_path / "out")
    assert s["extrinsic_source"] == "config"
    gap = [n for n in s["notes"] if n.startswith("no /tf_static chain links")]
    assert len(gap) == 1 and "odometry's child frame base_footprint" in gap[0]
    assert "/tf_static holds base_link -> " in gap[0] and "the identity is used" in gap[0]
    whole = _notes(bag_path, tmp_path / "whole")
    assert whole["extrinsic_source"] == "tf_static" and not any("/tf_static chain" in n for n in whole["notes"])


def test_odometry_stamped_seconds_off_the_clouds_is_said_to_be_a_clock_offset(office_bag, tmp_path):
    """Odometry headers 2 s late from the start (receive times as recorded): no clock jump, but the clouds'
    lead on the odometry says what the drift alarms may be; the bag as recorded has no such note."""
    bag_path, _ = office_bag

    def late(topic, t, msg, first):
        if topic == "/odom":
            msg = copy.deepcopy(msg)
            msg.header.stamp.sec += 2
        return [(topic, t, msg)]

    s = _notes(_rewritten(bag_path, tmp_path / "late", late), tmp_path / "out")
    lead = [n for n in s["notes"] if n.startswith("the odometry's stamps run")]
    assert len(lead) == 1 and " ahead of the clouds' against their receive times" in lead[0], s["notes"]
    assert 1.9 <= float(lead[0].split()[4]) <= 2.1
    clock = ("the odometry's stamps run", "the odometry arrives")
    assert not any(n.startswith(clock) for n in _notes(bag_path, tmp_path / "whole")["notes"])

    def received_late(seconds):  # a SLAM that publishes its (rightly stamped) odometry late
        return lambda topic, t, msg, first: [(topic, t + seconds * (topic == "/odom"), msg)]

    slam = _notes(_rewritten(bag_path, tmp_path / "slam", received_late(0.6)), tmp_path / "out_slam")
    assert slam["scans_processed"] == 30 and not any(n.startswith(clock) for n in slam["notes"]), slam["notes"]
    slow = _notes(_rewritten(bag_path, tmp_path / "slow", received_late(2.5)), tmp_path / "out_slow")
    assert any(n.startswith("the odometry arrives 2.") for n in slow["notes"]), slow["notes"]


def test_odometry_farther_apart_than_the_pose_gap_names_the_setting(office_bag, tmp_path):
    """Odometry every 1.5 s (one message in 30): no scan finds a pose within window.max_pose_gap_s; the reason
    names the odometry's interval and the setting to raise, and that setting then pairs the scans."""
    bag_path, _ = office_bag
    count = {"n": 0}

    def sparse(topic, t, msg, first):
        if topic == "/odom":
            count["n"] += 1
            return [(topic, t, msg)] if count["n"] % 30 == 1 else []
        return [(topic, t, msg)]

    slow = _rewritten(bag_path, tmp_path / "slow", sparse)
    s = _notes(slow, tmp_path / "out")
    assert s["scans_processed"] == 0
    assert "the odometry comes every 1.5" in s["no_scans"] and "window.max_pose_gap_s = 0.5 s" in s["no_scans"]
    assert s["no_scans"] not in s["notes"]  # said once
    fixed = _notes(slow, tmp_path / "fixed", **{"window.max_pose_gap_s": 2.3})
    assert fixed["scans_processed"] >= 20


def test_a_bag_whose_poses_are_only_on_tf_says_they_are_not_read(office_bag, tmp_path):
    """/odom replaced by /tf transforms: the reason says the bag has no Odometry topic and that /tf is not read
    as poses (before: 'name the topic with --odom-topic', with no topic to name)."""
    from topometric_ros import bag

    bag_path, _ = office_bag

    def tf_only(topic, t, msg, first):
        if topic == "/odom_gt":
            return []
        if topic != "/odom":
            return [(topic, t, msg)]
        stamp, pose = bag.odometry_pose(msg)
        return [("/tf", t, bag.make_tf(stamp, pose, msg.header.frame_id, msg.child_frame_id))]

    s = _notes(_rewritten(bag_path, tmp_path / "tf", tf_only), tmp_path / "out")
    assert s["scans_processed"] == 0
    assert s["no_scans"].startswith("no odometry: the bag has no nav_msgs/msg/Odometry topic (its transforms on /tf "
                                    "are not read as poses)")
    assert "--odom-topic" not in s["no_scans"]


def test_a_bag_too_short_to_learn_the_baselines_says_so(office_bag, tmp_path):
    """6 windows against health.baseline_windows 10: a note that PNE/CPV were judged by absolute limits only;
    with 2 baseline windows, no such note."""
    bag_path, _ = office_bag
    short = _notes(bag_path, tmp_path / "short", **{"health.baseline_windows": 10})
    assert any(n.startswith("the PNE/CPV baselines were still being learned at the bag's end (6 of the 10 windows "
                            "of health.baseline_windows)") for n in short["notes"]), short["notes"]
    armed = _notes(bag_path, tmp_path / "armed", **{"health.baseline_windows": 2})
    assert not any("baselines were" in n for n in armed["notes"])


def test_a_replay_into_a_folder_of_older_reports_leaves_none_of_them(office_bag, tmp_path):
    """An earlier replay's reports in --out are removed first: a replay without a plot (or one interrupted
    before its reports) leaves no metrics.png of another bag beside its own files."""
    bag_path, _ = office_bag
    out = tmp_path / "out"
    out.mkdir()
    for name in ("metrics.png", "windows.csv", "windows.json"):
        (out / name).write_text("an older replay's")
    (out / "mine.txt").write_text("the user's")
    s = _notes(bag_path, out)
    assert s["windows"] == 6 and not (out / "metrics.png").exists()
    assert json.loads((out / "windows.json").read_text())["summary"]["windows"] == 6
    assert (out / "mine.txt").read_text() == "the user's"


def test_odometry_that_starts_after_the_clouds_is_said_and_goes_stale_only_after_stale_after_s(office_bag, tmp_path):
    """/odom only from 3 s after the first cloud: a note says when it starts and that the scans before it are
    not judged; the STALE status for the missing odometry comes stale_after_s into the bag, not at its start."""
    bag_path, _ = office_bag
    late = _rewritten(bag_path, tmp_path / "late", lambda topic, t, msg, first: [] if topic == "/odom" and (
        first is None or t - first < 3.0) else [(topic, t, msg)])
    s = _notes(late, tmp_path / "out", **{"health.stale_after_s": 1.0})
    start = [n for n in s["notes"] if n.startswith("the odometry starts ")]
    assert len(start) == 1 and start[0].endswith(" s after the clouds: the scans before it are not judged"), s["notes"]
    assert 2.9 <= float(start[0].split()[3]) <= 3.1, start
    # no odometry for stale_after_s once the bag has run that long: STALE then, not at the bag's first message
    assert "STALE 1 time in diagnostics.mcap, first at 1.0 s: no odometry yet" in s["notes"], s["notes"]


def test_a_bag_whose_every_cloud_or_every_odometry_message_is_bad_says_so(office_bag, tmp_path):
    """Every cloud malformed (fields beyond point_step), or every odometry message a zero quaternion: the reason
    no scan was processed says so with the count and the last error, not a generic "no scan was processed"."""
    bag_path, _ = office_bag

    def malformed(topic, msg):
        if topic == "/points":
            msg = copy.copy(msg)
            msg.point_step = 7
        return [(topic, msg)]

    def zero_quaternion(topic, msg):
        if topic == "/odom":
            msg = copy.deepcopy(msg)
            q = msg.pose.pose.orientation
            q.x = q.y = q.z = q.w = 0.0
        return [(topic, msg)]

    clouds = run(rewrite(bag_path, tmp_path / "clouds", malformed), tmp_path / "o1", plot=False).summary
    assert clouds["scans_processed"] == 0 and clouds["scans_read"] == 6
    assert clouds["no_scans"].startswith("every cloud of /points (6) was malformed or empty; last: malformed cloud"), \
        clouds["no_scans"]
    poses = run(rewrite(bag_path, tmp_path / "poses", zero_quaternion), tmp_path / "o2", plot=False).summary
    assert poses["scans_processed"] == 0 and poses["counters"]["bad_poses"] == poses["counters"]["poses_in"] > 0
    assert poses["no_scans"].startswith("every odometry message of /odom was invalid; last: bad odometry: "
                                        "quaternion"), poses["no_scans"]  # not a scan's later "no odometry within"


def test_scans_enough_for_a_window_that_gave_none_say_it_was_lost_not_too_few():
    """A window's worth of scans (5 of 5) and no window: the window failed, so the reason counts the lost
    windows and the last error; "fewer than a window, replay with --window-size 5" would be wrong advice."""
    from topometric_ros.replay import _why_no_window
    from topometric_ros.window import SlidingWindow

    why = _why_no_window({"scans_processed": 5, "windows_discarded": 0, "window_errors": 1}, SlidingWindow(5),
                         "ValueError: no planes")
    assert why == "no window from 5 scans: 0 discarded, 1 failed; last error: ValueError: no planes", why
    assert _why_no_window({"scans_processed": 4}, SlidingWindow(5), "").startswith(
        "no window: 4 scans processed, fewer than a window of 5 scans")


def test_one_cloud_missing_from_the_recording_is_said(office_bag, tmp_path):
    """The tenth cloud left out of the recording: one scan missing, noted (in the singular)."""
    bag_path, _ = office_bag
    count = {"n": 0}

    def drop_tenth(topic, t, msg, first):
        count["n"] += topic == "/points"
        return [] if topic == "/points" and count["n"] == 10 else [(topic, t, msg)]

    s = _notes(_rewritten(bag_path, tmp_path / "one", drop_tenth), tmp_path / "out")
    assert s["counters"]["scans_missing"] == 1 and s["scans_read"] == 29
    assert any(n.startswith("the cloud stamps show 1 scan missing (steps of ") for n in s["notes"]), s["notes"]


def test_rpe_is_given_only_for_windows_the_ground_truth_covers(office_bag, tmp_path):
    """Ground truth that stops 3.5 s into the bag: windows inside it have a finite RPE, windows that end after
    its last pose (one of them partly covered) have none, as a pose outside the ground truth cannot be
    interpolated."""
    bag_path, _ = office_bag
    last = []

    def cut_truth(topic, t, msg, first):
        if topic == "/odom_gt" and first is not None and t - first > 3.5:
            return []
        if topic == "/odom_gt":
            last.append(msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec)
        return [(topic, t, msg)]

    res = run(_rewritten(bag_path, tmp_path / "cut", cut_truth), tmp_path / "out", plot=False)
    end = last[-1]
    assert len(res.windows) == 6 and any(w["start"] <= end < w["end"] for w in res.windows)
    assert [bool(np.isfinite(w["rpe"])) for w in res.windows] == [w["end"] <= end for w in res.windows]


def test_inspect_takes_every_nth_cloud_up_to_its_limit(office_bag, tmp_path):
    """every 3, limit 2: clouds 0 and 3 of the bag, two rows, not a third; limit 0: all of every 10th."""
    from topometric_ros.inspect import inspect_bag

    bag_path, _ = office_bag
    config = load_config(overrides={"segmentation.mode": "labels"})
    rows = inspect_bag(bag_path, tmp_path / "a", config, every=3, limit=2, plot=False)
    assert [r["scan"] for r in rows] == [0, 3] and all("error" not in r for r in rows), rows
    assert [r["scan"] for r in inspect_bag(bag_path, tmp_path / "b", config, every=10, limit=0, plot=False)] == [0, 10, 20]


def test_a_report_holds_an_infinite_value_as_null_not_as_a_crash(tmp_path):
    """An infinite metric (a z-score over a zero spread) is written as null as NaN is: strict JSON has neither."""
    from topometric_ros.reports import write_json

    path = write_json(tmp_path / "w.json", {"z_pne": float("inf"), "z_cpv": -np.inf, "pne": float("nan"), "n": 1.5})
    assert json.loads(path.read_text()) == {"z_pne": None, "z_cpv": None, "pne": None, "n": 1.5}


def test_baselines_learned_mostly_on_alarmed_windows_are_noted_warn_and_error_alike():
    """Four learning windows, then judged ones: two alarmed of four is not most (no note); two WARN and one ERROR
    of four is, and the note counts all three."""
    from topometric_ros.replay import _baseline_notes

    def records(levels):
        learning = [{"level": lv, "message": "learning baseline (pne 3/4)", "z_pne": float("nan")} for lv in levels]
        return learning + [{"level": "OK", "message": "ok", "z_pne": 0.5}]

    cfg = load_config()
    assert _baseline_notes(records(["OK", "WARN", "OK", "ERROR"]), cfg) == []
    (note,) = _baseline_notes(records(["WARN", "OK", "ERROR", "WARN"]), cfg)
    assert note.startswith("the PNE/CPV baselines were learned on 4 windows, 3 of them WARN or ERROR"), note
