"""`topometric audit`: many bags on a real local Ray (2 workers) and in-process, against single replays; a corrupt
bag, a killed worker, the cache, the fleet report in a real headless Chromium, a two-node Ray cluster."""
from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest

from topometric_ros.audit import COLUMNS, MANIFEST, SCRATCH, audit, find_bags
from topometric_ros.cli import main
from topometric_ros.config import load_config
from topometric_ros.engine import ensure_ray
from topometric_ros.replay import ReplayOptions, replay
from topometric_ros.sim.drift import DriftSpec
from topometric_ros.sim.writer import SimConfig, simulate

LABELS = ["--segmentation", "labels"]


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """Four short office bags (15 scans, 3 windows of 5; one with per-pose drift noise: WARN windows) and a corrupt one (an MCAP file of
    garbage behind a real metadata.yaml)."""
    root = tmp_path_factory.mktemp("fleet")
    for i in range(4):
        cfg = SimConfig(scene="office1", frames=15, rate=5.0, speed=0.8, seed=100 + i,
                        drift=DriftSpec.parse("rt:2.0" if i == 1 else "none", "noise"))
        simulate(cfg, root / "good" / f"night_{i}", progress=False)
    bad = root / "good" / "night_corrupt"
    bad.mkdir()
    shutil.copy(root / "good" / "night_0" / "metadata.yaml", bad)
    (bad / "night_0.mcap").write_bytes(os.urandom(50_000))
    return root / "good"


def _windows(path: Path) -> list[dict]:
    """A windows.json's window records without the timings (ms_*: wall-clock, differ between any two runs)."""
    doc = json.loads(Path(path).read_text())
    return [{k: v for k, v in r.items() if not k.startswith("ms_")} for r in doc["windows"]]


def _good(fleet: Path) -> list[Path]:
    return sorted(p for p in fleet.iterdir() if p.name != "night_corrupt")


def test_ray_audit_equals_single_replays_and_names_the_corrupt_bag(fleet, tmp_path, capsys):
    out = tmp_path / "audit"
    assert main(["audit", str(fleet / "night_*"), "--out", str(out), "--workers", "2", "--quiet", *LABELS]) == 1
    printed = capsys.readouterr().out
    assert "audit: 5 bags: 4 done, 0 cached, 1 failed" in printed and "engine ray, 2 workers" in printed
    assert "FAILED night_corrupt: " in printed and f"report: {out / 'index.html'}" in printed
    config = load_config(overrides={"segmentation.mode": "labels"})
    for bag in _good(fleet):
        single = replay(bag, tmp_path / "single" / bag.name, config, ReplayOptions(progress=False, plot=False))
        assert single.windows and not single.summary["error"]
        assert _windows(out / "bags" / bag.name / "windows.json") == _windows(tmp_path / "single" / bag.name / "windows.json")
        for name in ("windows.csv", "metrics.png", "diagnostics.mcap", MANIFEST):
            assert (out / "bags" / bag.name / name).stat().st_size > 0
    doc = json.loads((out / "fleet.json").read_text())
    assert doc["failed"] == [{"bag": "night_corrupt", "path": str(fleet / "night_corrupt"),
                              "reason": doc["failed"][0]["reason"]}]
    assert doc["failed"][0]["reason"].startswith(f"/points cannot be read from {fleet / 'night_corrupt'}: its storage "
                                                 "is damaged (")  # not "no PointCloud2 topic": metadata.yaml lists it
    assert "damaged bag" in doc["failed"][0]["reason"] and "(sensor_msgs/msg/PointCloud2, 15)" in doc["failed"][0]["reason"]
    rows = {r["bag"]: r for r in doc["bags"]}
    drift = rows["night_1"]
    assert drift["status"] == "ok" and drift["scans"] == 15 and drift["windows"] == 3
    assert drift["worst_level"] in ("WARN", "ERROR") and drift["episodes_alarmed"] >= 1 and drift["worst_reason"]
    assert drift["rot_rate_p99"] >= drift["rot_rate_p50"] > 0
    assert {r["worker"].split(" node ")[0] for r in doc["bags"] if r["status"] == "ok"} != {f"{socket.gethostname()}:{os.getpid()}"}
    csv_lines = (out / "fleet.csv").read_text().splitlines()
    assert csv_lines[0].split(",") == list(COLUMNS) and len(csv_lines) == 6


def test_a_bag_with_no_window_fails_and_a_damaged_one_that_gives_windows_is_noted(fleet, tmp_path, capsys):
    """As replay's exit status: a bag too short for one window is a failed bag with replay's reason; a bag cut
    short that still gives windows is ok, and its damage is on the console, in fleet.csv and index.html."""
    bags = tmp_path / "bags"
    simulate(SimConfig(scene="office1", frames=3, rate=5.0, seed=7), bags / "short", progress=False)
    shutil.copytree(fleet / "night_2", bags / "cut")
    (mcap,) = (bags / "cut").glob("*.mcap")
    mcap.write_bytes(mcap.read_bytes()[:int(mcap.stat().st_size * 0.75)])
    out = tmp_path / "audit"
    assert main(["audit", str(bags), "--out", str(out), "--engine", "local", "--quiet", *LABELS]) == 1
    printed = capsys.readouterr().out
    assert "audit: 2 bags: 1 done, 0 cached, 1 failed" in printed
    assert ("FAILED short: no window: 3 scans processed, fewer than a window of 5 scans (automatic: 1 s at 5 Hz); "
            "replay with --window-size 3") in printed
    assert "  note cut: damaged bag: " in printed
    rows = {r["bag"]: r for r in json.loads((out / "fleet.json").read_text())["bags"]}
    assert rows["cut"]["status"] == "ok" and rows["cut"]["windows"] >= 1
    with open(out / "fleet.csv") as f:
        cut = next(r for r in csv.DictReader(f) if r["bag"] == "cut")
    assert "damaged bag: " in cut["notes"] and "damaged bag: " in (out / "index.html").read_text()


def test_a_bag_that_comes_to_share_its_name_keeps_its_cached_audit(fleet, tmp_path):
    """night_0 audited alone (folder night_0), then with another bag called night_0 (both get hashed folder
    names): the first is cached and its folder moved to its new name, only the newcomer runs; alone again,
    it moves back, still cached."""
    config = load_config(overrides={"segmentation.mode": "labels"})
    mine, twin = fleet / "night_0", tmp_path / "robot2" / "night_0"
    shutil.copytree(mine, twin)
    out = tmp_path / "audit"
    assert audit([mine], out, config, engine="local", progress=False).summary["ran"] == 1
    both = audit([mine, twin], out, config, engine="local", progress=False)
    assert (both.summary["ran"], both.summary["cached"]) == (1, 1) and [r["cached"] for r in both.rows] == [True, False]
    names = sorted(p.name for p in (out / "bags").iterdir())
    assert len(names) == 2 and all(n.startswith("night_0-") for n in names), names  # no stale night_0 left
    assert both.rows[0]["bag"] != both.rows[1]["bag"] and both.rows[0]["metrics_png"] == \
        f"bags/{both.rows[0]['bag']}/metrics.png"
    alone = audit([mine], out, config, engine="local", progress=False)
    assert (alone.summary["ran"], alone.summary["cached"]) == (0, 1) and alone.rows[0]["bag"] == "night_0"
    assert (out / "bags" / "night_0" / "windows.json").is_file()


def test_rerun_recomputes_nothing_and_a_config_change_recomputes_all(fleet, tmp_path):
    bags = find_bags([str(fleet)])
    assert [b.name for b in bags] == ["night_0", "night_1", "night_2", "night_3", "night_corrupt"]
    config = load_config(overrides={"segmentation.mode": "labels"})
    first = audit(bags, tmp_path, config, engine="local", progress=False)
    with pytest.raises(FileNotFoundError, match="no rosbag2 bag under"):
        find_bags([str(tmp_path)])  # the audit's own output (bags/*/diagnostics.mcap) is not a fleet
    with pytest.raises(FileNotFoundError, match="no rosbag2 bag at"):
        find_bags([str(fleet / "night_0" / "truth.json")])
    replayed = tmp_path / "replayed"  # a replay's reports (diagnostics.mcap beside windows.json) are no bag either
    replay(bags[0], replayed, config, ReplayOptions(progress=False, plot=False))
    with pytest.raises(FileNotFoundError, match="holds a replay's or an audit's reports \\(windows.json beside"):
        find_bags([str(replayed)])
    shutil.copytree(bags[2], replayed / "inner")  # a bag in a folder that holds reports is a bag all the same
    assert find_bags([str(replayed / "inner")]) == [replayed / "inner"]
    linked = tmp_path / "linked"  # bags linked into a folder are found; links back up are walked once (two of
    linked.mkdir()                 # them, unchecked, would give 2^40 paths before the kernel's link limit)
    (linked / "a").symlink_to(bags[1], target_is_directory=True)
    for loop in ("loop1", "loop2"):
        (linked / loop).symlink_to(linked, target_is_directory=True)
    assert find_bags([str(linked)]) == [linked / "a"]
    assert (first.summary["ran"], first.summary["done"], first.summary["failed"]) == (5, 4, 1)
    stamps = {p: p.stat().st_mtime_ns for p in (tmp_path / "bags").rglob("*")}
    again = audit(bags, tmp_path, config, engine="local", progress=False)
    assert (again.summary["ran"], again.summary["cached"], again.summary["failed"]) == (0, 4, 1)  # they add up
    assert {p: p.stat().st_mtime_ns for p in (tmp_path / "bags").rglob("*")} == stamps  # nothing rewritten
    assert [r["cached"] for r in again.rows] == [True] * 5
    assert [r["status"] for r in again.rows] == [r["status"] for r in first.rows]
    changed = load_config(overrides={"segmentation.mode": "labels", "health.warn_sigma": 5.5})
    third = audit(bags, tmp_path, changed, engine="local", progress=False)
    assert (third.summary["ran"], third.summary["cached"]) == (5, 0)
    # a changed byte of one bag: only that bag again
    truth = fleet / "night_2" / "truth.json"
    keep = truth.read_bytes()
    try:
        truth.write_bytes(keep.replace(b"{", b"{ ", 1))
        fourth = audit(bags, tmp_path, changed, engine="local", progress=False)
        assert fourth.summary["ran"] == 1 and [r["bag"] for r in fourth.rows if not r["cached"]] == ["night_2"]
    finally:
        truth.write_bytes(keep)
    # a cached bag whose metrics.png was lost (index.html links it): replayed again, the picture back
    (tmp_path / "bags" / "night_1" / "metrics.png").unlink()
    fifth = audit(bags, tmp_path, changed, engine="local", progress=False)
    assert [r["bag"] for r in fifth.rows if not r["cached"]] == ["night_1", "night_2"]  # night_2: truth restored
    assert (tmp_path / "bags" / "night_1" / "metrics.png").is_file()
    (tmp_path / "bags" / "night_3" / "audit.json").write_text('{"key": 1}')  # a manifest without its row
    sixth = audit(bags, tmp_path, changed, engine="local", progress=False)
    assert [r["bag"] for r in sixth.rows if not r["cached"]] == ["night_3"]


def _descends_from_us(pid: int) -> bool:
    """``pid`` is a descendant of this test process (our Ray's workers, not another Ray on the machine)."""
    while pid > 1:
        try:
            pid = int((Path("/proc") / str(pid) / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            return False
        if pid == os.getpid():
            return True
    return False


def _task_pids() -> list[int]:
    """Our Ray's worker processes running an engine task right now (Ray titles them ray::<function>)."""
    pids = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                if (d / "cmdline").read_bytes().startswith(b"ray::_call_remote") and _descends_from_us(int(d.name)):
                    pids.append(int(d.name))
            except OSError:
                pass
    return pids


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="finds the Ray worker's pid in /proc (Linux)")
def test_a_worker_killed_mid_run_fails_its_bag_only_and_a_rerun_completes_it(fleet, tmp_path):
    bags = _good(fleet)
    config = load_config(overrides={"segmentation.mode": "labels"})
    # Ray started from this (main) thread: Ray's own processes die with the thread that started them
    ensure_ray(workers=2)
    result = {}
    t = threading.Thread(target=lambda: result.update(
        res=audit(bags, tmp_path, config, engine="ray", workers=2, progress=False)))
    t.start()
    killed, deadline = None, time.monotonic() + 120
    while killed is None and time.monotonic() < deadline and t.is_alive():
        pids = _task_pids()
        if pids:
            time.sleep(0.1)  # mid-task: it has started reading the bag ...
            if pids[0] in _task_pids():  # ... and not yet finished it (a bag takes about a second)
                killed = pids[0]
                os.kill(killed, signal.SIGKILL)
        time.sleep(0.02)
    t.join(timeout=300)
    assert killed is not None, "no Ray task process seen"
    rows = result["res"].rows
    failed = [r for r in rows if r["status"] == "failed"]
    assert len(failed) == 1 and "Worker" in failed[0]["reason"] and "died" in failed[0]["reason"].lower(), failed
    assert all((tmp_path / "bags" / r["bag"] / "windows.json").is_file() for r in rows if r["status"] == "ok")
    assert len([r for r in rows if r["status"] == "ok"]) == len(bags) - 1
    report = json.loads((tmp_path / "fleet.json").read_text())
    assert [f["bag"] for f in report["failed"]] == [failed[0]["bag"]]
    assert failed[0]["bag"] in (tmp_path / "index.html").read_text()
    rerun = audit(bags, tmp_path, config, engine="ray", workers=2, progress=False)
    assert (rerun.summary["ran"], rerun.summary["cached"], rerun.summary["failed"]) == (1, len(bags) - 1, 0)
    assert [r["bag"] for r in rerun.rows if not r["cached"]] == [failed[0]["bag"]]
    scratch = Path(tempfile.gettempdir()) / SCRATCH  # the killed worker's replay folder: removed by the rerun
    assert not list(scratch.glob(f"{killed}-*")), list(scratch.iterdir())


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
SNAP = CHROMIUM is not None and os.path.realpath(CHROMIUM).startswith("/snap/")


def _chromium(profile: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
                           f"--user-data-dir={profile}", *args], capture_output=True, text=True, timeout=120)


@pytest.mark.skipif(CHROMIUM is None, reason="chromium not installed (Debian package chromium; make install adds "
                                              "it on Debian where apt-get can)")
@pytest.mark.skipif(SNAP, reason="chromium is a snap here (Ubuntu): confined, it cannot read pytest's temporary files")
def test_index_html_in_headless_chromium_shows_every_bag_and_sorts(fleet, tmp_path):
    config = load_config(overrides={"segmentation.mode": "labels"})
    res = audit(find_bags([str(fleet)]), tmp_path, config, engine="local", progress=False)
    page = tmp_path / "index.html"
    shot = tmp_path / "fleet.png"
    profile = tmp_path / ".chromium"
    r = _chromium(profile, f"--screenshot={shot}", "--window-size=1600,700", "--hide-scrollbars", f"file://{page}")
    assert shot.is_file() and shot.stat().st_size > 20_000, r.stderr[-2000:]
    assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    dom = _chromium(profile, "--dump-dom", f"file://{page}").stdout
    for row in res.rows:
        assert f'data-v="{row["bag"]}"' in dom
        if row["status"] == "ok":
            assert f'href="bags/{row["bag"]}/metrics.png"' in dom and (tmp_path / row["metrics_png"]).is_file()
    assert "night_corrupt" in dom.split('id="failed"')[1]
    order = lambda html: sorted(("night_0", "night_1", "night_2", "night_3"), key=html.index)  # noqa: E731
    ok = [r for r in res.rows if r["status"] == "ok"]
    worst_first = [r["bag"] for r in sorted(ok, key=lambda r: -r["rot_rate_p99"])]
    sorted_dom = _chromium(profile, "--dump-dom", f"file://{page}#sort=-rot_rate_p99").stdout
    tbody = sorted_dom.split("<tbody>")[1]
    assert order(tbody) == worst_first  # the page's own script sorted the table (numbers as numbers)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ray_cli() -> str | None:
    return shutil.which("ray", path=str(Path(sys.executable).parent))


def _cluster_pids(port: int) -> list[int]:
    """The processes of the Ray cluster whose GCS listens on ``port``: an argument of their command line
    names it (--gcs-address=HOST:PORT, --address=HOST:PORT, --gcs_server_port=PORT, --port=PORT)."""
    pids = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit() and int(d.name) != os.getpid():
            try:
                args = (d / "cmdline").read_bytes().decode(errors="replace").split("\0")
            except OSError:
                continue
            if any(a.endswith(f":{port}") or a in (f"--gcs_server_port={port}", f"--port={port}") for a in args):
                pids.append(int(d.name))
    return pids + [c for p in pids for c in _descendants(p)]  # the raylets' agents (ray::DashboardAgent, ...)


def _descendants(pid: int) -> list[int]:
    children: dict[int, list[int]] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(d.name))
    out, todo = [], [pid]
    while todo:
        for c in children.get(todo.pop(), []):
            out.append(c)
            todo.append(c)
    return out


@pytest.fixture
def two_node_cluster(tmp_path):
    """A head and a worker node started with `ray start` on this machine (1 CPU each), token auth on the
    loopback interface; torn down by ending this cluster's own processes (found by its port), not `ray stop`,
    which would end every Ray on the machine."""
    ray = _ray_cli()
    if ray is None:
        pytest.skip("the ray command is not installed beside this Python")
    port = _free_port()
    env = {**os.environ, "RAY_AUTH_MODE": "token", "RAY_USAGE_STATS_ENABLED": "0"}
    head = subprocess.run([ray, "start", "--head", f"--port={port}", "--num-cpus=1", "--include-dashboard=false",
                           "--node-ip-address=127.0.0.1", "--disable-usage-stats"],
                          capture_output=True, text=True, env=env, timeout=120)
    try:
        if head.returncode != 0:
            pytest.skip(f"`ray start --head` failed here: {head.stderr.strip().splitlines()[-1:]}")
        worker = subprocess.run([ray, "start", f"--address=127.0.0.1:{port}", "--num-cpus=1",
                                 "--node-ip-address=127.0.0.1", "--disable-usage-stats"],
                                capture_output=True, text=True, env=env, timeout=120)
        if worker.returncode != 0:
            pytest.skip(f"`ray start --address` (second node) failed here: {worker.stderr.strip().splitlines()[-1:]}")
        yield f"127.0.0.1:{port}", env
    finally:
        for sig in (signal.SIGTERM, signal.SIGKILL):
            for pid in _cluster_pids(port):
                try:
                    os.kill(pid, sig)
                except ProcessLookupError:
                    pass
            time.sleep(1.0)


def test_audit_on_a_two_node_cluster_through_address(fleet, tmp_path, two_node_cluster):
    address, env = two_node_cluster
    out = tmp_path / "audit"
    r = subprocess.run([sys.executable, "-m", "topometric_ros.cli", "audit", *map(str, _good(fleet)), "--out", str(out),
                        "--address", address, "--quiet", *LABELS], capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr[-3000:]
    assert "audit: 4 bags: 4 done, 0 cached, 0 failed" in r.stdout and f"cluster {address}" in r.stdout
    rows = json.loads((out / "fleet.json").read_text())["bags"]
    nodes = {row["worker"].split(" node ")[1] for row in rows}
    assert len(nodes) == 2, rows  # both nodes ran bags (1 CPU each, 4 tasks)


def test_the_cache_key_holds_the_code_and_a_failed_bag_keeps_no_earlier_reports(fleet, tmp_path, monkeypatch):
    """Another version of the package's sources is another key (results of other code are not reused); a bag
    given as "." is named after its folder; a task that fails leaves none of an earlier audit's reports."""
    from topometric_ros import audit as audit_mod

    src = tmp_path / "src"
    shutil.copytree(Path(audit_mod.__file__).parent, src, ignore=shutil.ignore_patterns("__pycache__", "*.pt"))
    before = audit_mod.code_digest(src)
    assert before == audit_mod.code_digest(src) and before == audit_mod.code_digest()
    (src / "health.py").write_text((src / "health.py").read_text() + "\n# one more line\n")
    assert audit_mod.code_digest(src) != before
    config = load_config(overrides={"segmentation.mode": "labels"})
    tasks, _ = audit_mod.plan([fleet / "night_0"], tmp_path / "out", config)
    assert tasks[0].key["code"] == before
    monkeypatch.chdir(fleet / "night_1")
    assert audit_mod.bag_names([Path("."), fleet / "night_0"]) == ["night_1", "night_0"]
    folder = tmp_path / "out" / "bags" / "night_0"
    folder.mkdir(parents=True)
    (folder / "windows.json").write_text("{}")  # an earlier audit's
    row = audit_mod._store(tmp_path / "out", tasks[0], None, "worker died")
    assert row["status"] == "failed" and not (folder / "windows.json").exists()
    assert json.loads((folder / MANIFEST).read_text())["key"] is None


def _record(i: int, level: str, rot: float, warn_at: float = 1.0) -> dict:
    """A window record of windows.json as fleet_row reads it: 1 s windows from 100 s on."""
    return {"index": i, "start": 100.0 + i, "end": 101.0 + i, "level": level, "message": f"window {i} {level}",
            "rot_rate": rot, "trans_rate": 0.01, "rot_rate_warn_at": warn_at, "trans_rate_warn_at": 1.0}


def test_a_fleet_row_counts_each_level_and_names_the_worst_window():
    """Known windows: OK, WARN 5x its limit, ERROR 2x, OK, WARN, WARN: each level counted in its own column, two
    alarm episodes, the worst window the ERROR one (a higher level beats a larger excess) at its end since the first
    window's start; rate quantiles over the finite rates only (a window with no rate is no NaN quantile)."""
    from topometric_ros.audit import BagTask, fleet_row

    levels = ["OK", "WARN", "ERROR", "OK", "WARN", "WARN"]
    rots = [0.1, 5.0, 2.0, float("nan"), 1.5, 1.2]
    records = [_record(i, lv, r) for i, (lv, r) in enumerate(zip(levels, rots))]
    task = BagTask("/bags/b", "b", load_config(), {})
    row = fleet_row(task, records, {"bag_s": 6.0, "scans_processed": 30, "notes": []})
    assert (row["status"], row["windows"], row["ok"], row["warn"], row["error"]) == ("ok", 6, 2, 3, 1)
    assert row["episodes_alarmed"] == 2
    assert (row["worst_level"], row["worst_reason"], row["worst_time_s"]) == ("ERROR", "window 2 ERROR", 3.0)
    assert row["rot_rate_p50"] == pytest.approx(1.5) and row["rot_rate_p99"] == pytest.approx(4.88)
    # among windows of one level, the one furthest above its drift-rate WARN limit
    warns = [_record(0, "WARN", 3.0, warn_at=2.0), _record(1, "WARN", 2.0, warn_at=0.5), _record(2, "OK", 9.0)]
    assert fleet_row(task, warns, {"notes": []})["worst_reason"] == "window 1 WARN"


def test_the_cache_key_changes_with_the_replay_options_and_the_network_weights(office_bag, tmp_path):
    """Another topic for the replay, or other bytes of the network's weights, is another key: an audit never
    reuses a bag's results of other topics or another network."""
    from topometric_ros.audit import plan

    bag_path, _ = office_bag
    labels = load_config(overrides={"segmentation.mode": "labels"})
    key = plan([bag_path], tmp_path, labels)[0][0].key
    assert key == plan([bag_path], tmp_path, labels, {})[0][0].key
    assert key != plan([bag_path], tmp_path, labels, {"points_topic": "/front/points"})[0][0].key
    weights = tmp_path / "mine.pt"
    keys = []
    for data in (b"one network", b"another network"):
        weights.write_bytes(data)
        network = load_config(overrides={"segmentation.mode": "network", "segmentation.weights": str(weights)})
        keys.append(plan([bag_path], tmp_path, network)[0][0].key)
    assert keys[0]["config"] == keys[1]["config"] and keys[0] != keys[1]
