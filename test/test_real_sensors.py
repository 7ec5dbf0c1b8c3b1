"""Real Ouster captures (../shared/real-sensors, ouster-ros layout: organised, NaN for no return, per-point
``t``) through the default mode (network segmentation, layout read off the cloud): every scan of every bag
reaches segmentation and planes, and the bag with poses gives its window with no scan lost."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from topometric_ros import bag
from topometric_ros.config import load_config


def _real_sensors() -> Path | None:
    for p in (os.environ.get("TOPOMETRIC_REAL_SENSORS", ""), Path(__file__).resolve().parents[2] / "shared" / "real-sensors",
              "/work/shared/real-sensors"):
        if p and Path(p).is_dir():
            return Path(p)
    return None


ROOT = _real_sensors()
BAGS = sorted(p for p in ROOT.iterdir() if (p / "metadata.yaml").is_file()) if ROOT else []
pytestmark = pytest.mark.skipif(ROOT is None, reason="no ../shared/real-sensors (set TOPOMETRIC_REAL_SENSORS)")


@pytest.mark.parametrize("path", BAGS, ids=[p.name for p in BAGS])
def test_every_real_scan_is_segmented_and_gives_planes(path, tmp_path):
    from topometric_ros.inspect import inspect_bag

    rows = inspect_bag(path, tmp_path, load_config(), limit=100)
    assert len(rows) == bag.topics(path)["/ouster/points"][1]
    for r in rows:
        assert "error" not in r, r
        assert r["layout"] == "ouster" and r["time_field"] == "yes"  # t decoded
        assert r["points"] > 10_000 and r["dropped"] > 0  # NaN no-returns removed, not fatal
        beams = int(r["cloud"].split("x")[0])
        assert r["grid"] == f"{beams}x1024" and r["rows_from"] == "ring field (top-down, reversed)"
        assert r["network_image"] == f"{-(-beams // 32)}x32x1024"  # interleaved images of at most 32 beams
        assert r["planes"] >= 5
        assert (tmp_path / f"scan_{r['scan']:04d}.png").stat().st_size > 10_000


def test_the_bag_with_poses_gives_its_window_and_loses_no_scan(tmp_path):
    from topometric_ros.replay import ReplayOptions, replay

    path = ROOT / "os1_128_lowbw_3scans_poses"
    res = replay(path, tmp_path, load_config(overrides={"window.size": 3}), ReplayOptions(progress=False))
    c = res.summary["counters"]
    assert res.summary["error"] == "" and res.summary["windows"] == 1
    assert c["scans_processed"] == 3 and c["dropped_scans"] == 0 and c["scans_deskewed"] == 3
    assert res.windows[0]["n_planes"] > 100
    # KISS-ICP's poses of real scans line up (0.93 of the worst scan's plane inliers): no pose jump
    assert res.windows[0]["agreement"] > 0.8 and "pose jump" not in res.windows[0]["message"]


def test_inspect_says_how_the_network_ran(tmp_path, capsys):
    """The console names the mode and the network's precision (int8 on an x86 CPU with VNNI or AVX2, else float32)."""
    from topometric_ros.cli import main
    from topometric_ros.segmentation.quantize import cpu_runs_int8

    path = ROOT / "os1_32_g_legacy"
    assert main(["inspect", str(path), "--out", str(tmp_path / "auto"), "--no-plot"]) == 0
    want = "int8" if cpu_runs_int8() else "float32"
    assert f"segmentation network, {want} inference, a 3-nearest-neighbour vote; sensor read off each cloud" \
        in capsys.readouterr().out
    assert main(["inspect", str(path), "--out", str(tmp_path / "f32"), "--no-plot",
                 "--set", "segmentation.precision=float32"]) == 0
    assert "segmentation network, float32 inference," in capsys.readouterr().out


def test_inspect_says_what_it_left_out_and_what_a_wrong_sensor_model_cost(tmp_path, capsys):
    """--limit stops early and says so (0 = every cloud); named as a 64-beam model, the 128-beam capture loses
    the points of beams 64-127, and the console counts them and asks whether sensor.model is right. The table's
    columns line up."""
    from topometric_ros.cli import main
    from topometric_ros.cloud import read_scan

    path = ROOT / "os1_128_lowbw_3scans_poses"
    assert main(["inspect", str(path), "--out", str(tmp_path / "two"), "--no-plot", "--limit", "2", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "the first 2 clouds (every 1); --limit 0 inspects them all" in out
    assert main(["inspect", str(path), "--out", str(tmp_path / "all"), "--no-plot", "--limit", "0", "--quiet",
                 "--set", "sensor.model=OS1-64"]) == 0
    out = capsys.readouterr().out
    lost = sum(int((read_scan(m).beam >= 64).sum()) for t, _, m in bag.read_messages(path) if t == "/ouster/points")
    assert lost > 100_000 and "the first" not in out
    assert (f"note: {lost} points dropped: beam id outside 0..63, the 64 beams of sensor.model OS1-64; is "
            "sensor.model right?") in out
    table = out.splitlines()[1:5]  # the header and the 3 clouds
    assert table[0].split()[:2] == ["scan", "layout"] and len({len(line) for line in table}) == 1, table
