"""Fuzzed PointCloud2 messages through cloud.read_scan and Monitor.add_cloud: ``python -m benchmarks fuzz``.

Each case is a PointCloud2-like message drawn by hypothesis (:func:`clouds`): a driver-like layout (x, y, z and
extras among intensity, ring, per-point time in any unit, label; any datatype, count, offset, padding,
endianness, organisation) filled with values that range from plausible to garbage (NaN, inf, zeros, huge,
random bytes), then up to three corruptions (odd point_step, offsets, counts, row_step, endianness flag,
huge width/height with little data, unknown datatypes, negative or non-integer numbers, duplicated or
non-string field names, data of another type or length, header and stamp faults, missing attributes),
wrapped as a rosbags message class (topometric_ros.bag.msg_types()) or a SimpleNamespace duck type.

What must hold (:func:`check_case`): read_scan raises CloudError and nothing else; Monitor.add_cloud never
raises, and either accepts the cloud or counts it (dropped_bad_scan / dropped_duplicate); accepted clouds get
odometry around their stamp, so the monitor (live=False, segmentation none) processes them through the real
per-scan pipeline (grid, deskew, planes) and scores windows. A per-case alarm (CASE_LIMIT_S) turns a hang into
a reported "Timeout".

The run reports cases, outcomes, exceptions by type, the slowest case and the time per case; goal (issue 16):
10,000 cases, no exception but CloudError, no case near the limit.
"""
from __future__ import annotations

import array
import re
import signal
import time
from collections import Counter
from types import SimpleNamespace
from typing import Any

import numpy as np
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

CASE_LIMIT_S = 10.0  # s, a case that takes longer counts as a hang
DATATYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
EXTRA_FIELDS = ["intensity", "ring", "t", "time", "timestamp", "label", "reflectivity", "pad"]
WEIRD_INTS = [0, -1, -(2**31), 2**31, 2**32 + 1, 2**63, 2**64 + 5, None, "12", 3.5, float("nan"), float("inf"),
              True, np.int64(7), b"\x01", [1], object()]
CORRUPTIONS = ["x_count_2", "count", "datatype", "offset", "point_step", "row_step", "width_huge", "height_huge",
               "width", "height", "bigendian", "duplicate", "field_name", "data_type", "data_length", "fields",
               "header", "stamp", "frame_id", "time_garbage", "ring_odd", "label_odd", "missing_attribute",
               "field_entry", "is_dense"]


# ------------------------------------------------------------------ the strategy
@st.composite
def layouts(draw) -> dict:
    """A driver-like layout: fields [(name, offset, datatype, count)], point_step, height, width, row_step."""
    extra = draw(st.lists(st.sampled_from(EXTRA_FIELDS), unique=True, max_size=4))
    names = draw(st.permutations(["x", "y", "z"] + extra))
    fields, offset = [], 0
    for name in names:
        float_xyz = name in "xyz" and draw(st.integers(0, 9)) > 0
        dt = draw(st.sampled_from([7, 8])) if float_xyz else draw(st.sampled_from(sorted(DATATYPES)))
        count = 1 if name in "xyz" or draw(st.integers(0, 5)) else draw(st.integers(2, 3))
        offset += draw(st.sampled_from([0, 0, 0, 1, 2, 4]))
        fields.append([name, offset, dt, count])
        offset += np.dtype(DATATYPES[dt]).itemsize * count
    point_step = offset + draw(st.sampled_from([0, 0, 1, 4, 8]))
    organised = draw(st.booleans())
    height = draw(st.integers(2, 16)) if organised else 1
    width = draw(st.integers(1, 64 if organised else 600))
    row_step = width * point_step + draw(st.sampled_from([0, 0, 0, 3, 16]))
    return {"fields": fields, "point_step": point_step, "height": height, "width": width, "row_step": row_step,
            "bigendian": draw(st.integers(0, 9)) == 0}


def _values(rng: np.random.Generator, name: str, code: np.dtype, n: int, style: str, stamp: float) -> np.ndarray:
    """n values of one field: plausible for its name (coordinates in m, beams, per-point times in several
    units) or garbage, as ``style`` says."""
    if style == "bytes":
        return rng.integers(0, 256, n * code.itemsize, dtype=np.uint8).view(code)
    if name in ("x", "y", "z"):
        v = rng.normal(0, 8, n)
        if style == "nasty":
            v[rng.random(n) < 0.3] = rng.choice([np.nan, np.inf, -np.inf, 0.0, 1e30, -1e-30])
    elif name == "ring":
        v = rng.integers(0, 128, n)
    elif name in ("t", "time", "timestamp"):
        unit = rng.choice([1.0, 1e9, 1e6])
        base = rng.choice([0.0, stamp])
        v = (base + np.sort(rng.random(n)) * 0.1) * unit
    else:
        v = rng.random(n) * 100
    if code.kind in "iu":
        info = np.iinfo(code)
        return np.clip(np.nan_to_num(v), info.min, info.max).astype(code)
    return v.astype(code)


def _data(layout: dict, style: str, seed: int, stamp: float) -> bytes:
    """The buffer a driver would send for the layout (padding bytes random)."""
    rng = np.random.default_rng(seed)
    order = ">" if layout["bigendian"] else "<"
    n, width, height = layout["width"] * layout["height"], layout["width"], layout["height"]
    buf = rng.integers(0, 256, height * layout["row_step"], dtype=np.uint8)
    rows = buf.reshape(height, layout["row_step"])[:, : width * layout["point_step"]].reshape(n, layout["point_step"])
    for name, offset, dt, count in layout["fields"]:
        code = np.dtype(DATATYPES[dt])
        v = _values(rng, name, code, n * count, style, stamp).astype(code.newbyteorder(order))
        rows[:, offset:offset + code.itemsize * count] = v.view(np.uint8).reshape(n, -1)
    buf.reshape(height, layout["row_step"])[:, : width * layout["point_step"]] = rows.reshape(height, -1)
    return buf.tobytes()


@st.composite
def clouds(draw) -> tuple[Any, list[str]]:
    """(message, corruptions applied): a PointCloud2-like message as described in the module docstring."""
    layout = draw(layouts())
    stamp = 1.7e9 + draw(st.floats(0, 1000, allow_nan=False))
    data = _data(layout, draw(st.sampled_from(["plausible", "plausible", "nasty", "bytes"])),
                 draw(st.integers(0, 2**32 - 1)), stamp)
    sec = int(stamp)
    msg = {"header": {"sec": sec, "nanosec": int((stamp - sec) * 1e9), "frame_id": "lidar"},
           "height": layout["height"], "width": layout["width"], "point_step": layout["point_step"],
           "row_step": layout["row_step"], "is_bigendian": layout["bigendian"], "is_dense": False,
           "fields": [list(f) for f in layout["fields"]], "data": data}
    applied = draw(st.lists(st.sampled_from(CORRUPTIONS), max_size=3))
    for how in applied:
        _corrupt(draw, msg, how)
    return _build(msg, draw(st.sampled_from(["rosbags", "namespace"]))), applied


def _pick_field(draw, msg: dict) -> list | None:
    fields = msg["fields"] if isinstance(msg["fields"], list) else []
    fields = [f for f in fields if isinstance(f, list) and len(f) == 4]
    return draw(st.sampled_from(fields)) if fields else None


def _corrupt(draw, msg: dict, how: str) -> None:
    """Apply one corruption to the message's plain description (in place)."""
    f = _pick_field(draw, msg)
    weird = st.sampled_from(WEIRD_INTS)
    if how == "x_count_2":
        for g in msg["fields"] if isinstance(msg["fields"], list) else []:
            if isinstance(g, list) and g[0] == "x":
                g[3] = 2
    elif how in ("count", "datatype", "offset") and f is not None:
        f[{"count": 3, "datatype": 2, "offset": 1}[how]] = draw(st.one_of(weird, st.integers(-5, 300)))
    elif how in ("point_step", "row_step", "width", "height"):
        msg[how] = draw(st.one_of(weird, st.integers(-3, 4096)))
    elif how in ("width_huge", "height_huge"):
        msg[how.split("_")[0]] = draw(st.sampled_from([2**20, 2**31 - 1, 2**32, 2**40, 2**62]))
    elif how == "bigendian":
        msg["is_bigendian"] = draw(st.sampled_from([True, None, "yes", 2, np.array([1, 0]), float("nan")]))
    elif how == "duplicate" and f is not None:
        msg["fields"].append(list(f))
    elif how == "field_name" and f is not None:
        f[0] = draw(st.sampled_from([None, 5, b"x", "", "y", "x", "ring", "t", "\x00", "label"]))
    elif how == "data_type":
        msg["data"] = _retype(draw, msg["data"])
    elif how == "data_length" and isinstance(msg["data"], bytes):
        cut = draw(st.integers(-64, 64))
        msg["data"] = msg["data"][:cut] if cut < 0 else msg["data"] + bytes(cut)
    elif how == "fields":
        msg["fields"] = draw(st.sampled_from([None, [], "xyz", {"x": 1}, 7, [None]]))
    elif how == "field_entry" and isinstance(msg["fields"], list):
        msg["fields"].append(draw(st.sampled_from([None, 3, "x", ("q",), SimpleNamespace(name="q")])))
    elif how in ("header", "stamp", "frame_id"):
        _corrupt_header(draw, msg, how)
    elif how in ("time_garbage", "ring_odd", "label_odd"):
        _odd_field(draw, msg, how)
    elif how == "missing_attribute":
        msg.setdefault("missing", []).append(draw(st.sampled_from(
            ["header", "fields", "data", "height", "width", "point_step", "row_step", "is_bigendian"])))
    elif how == "is_dense":
        msg["is_dense"] = draw(st.sampled_from([None, "no", 3]))


def _retype(draw, data: Any) -> Any:
    data = data if isinstance(data, bytes) else bytes(64)  # retyped once already: start again from bytes
    kind = draw(st.sampled_from(["bytearray", "memoryview", "array", "uint8", "float32", "list", "str", "none",
                                 "int", "uint8_2d"]))
    return {"bytearray": lambda: bytearray(data), "memoryview": lambda: memoryview(data),
            "array": lambda: array.array("B", data), "uint8": lambda: np.frombuffer(data, np.uint8),
            "float32": lambda: np.frombuffer(data[: len(data) // 4 * 4], np.float32),
            "list": lambda: list(data[:64]), "str": lambda: data[:64].decode("latin-1"), "none": lambda: None,
            "int": lambda: 5, "uint8_2d": lambda: np.frombuffer(data[: len(data) // 2 * 2], np.uint8).reshape(2, -1)
            }[kind]()


def _corrupt_header(draw, msg: dict, how: str) -> None:
    h = msg["header"]
    if how == "header":
        msg["header"] = draw(st.sampled_from([None, 5, "header", {}]))
    elif how == "stamp" and isinstance(h, dict):
        h[draw(st.sampled_from(["sec", "nanosec"]))] = draw(st.one_of(
            st.sampled_from([None, "1", float("nan"), float("inf"), -5, 2**70, 10**9 + 7, 0]), st.integers()))
    elif how == "frame_id" and isinstance(h, dict):
        h["frame_id"] = draw(st.sampled_from([None, 5, "", "/lidar", "\x00", b"lidar"]))


def _odd_field(draw, msg: dict, how: str) -> None:
    """A time, ring or label field of an odd type or count, or garbage values (the data are overwritten)."""
    if not isinstance(msg["fields"], list) or not isinstance(msg["point_step"], int) or msg["point_step"] < 8:
        return
    name = {"time_garbage": draw(st.sampled_from(["t", "time", "timestamp"])), "ring_odd": "ring",
            "label_odd": "label"}[how]
    dt = draw(st.sampled_from(sorted(DATATYPES)))
    count = draw(st.sampled_from([1, 1, 2]))
    size = np.dtype(DATATYPES[dt]).itemsize * count
    offset = draw(st.integers(0, max(0, msg["point_step"] - size)))
    others = [f for f in msg["fields"] if not (isinstance(f, list) and f[0] == name)]
    msg["fields"] = others + [[name, offset, dt, count]]


def _build(msg: dict, kind: str) -> Any:
    """The message as a rosbags message class or a SimpleNamespace (fields and header alike)."""
    from topometric_ros.bag import msg_types

    m = msg_types()
    make = (lambda cls, **kw: cls(**kw)) if kind == "rosbags" else (lambda cls, **kw: SimpleNamespace(**kw))
    h = msg["header"]
    header = (make(m.Header, stamp=make(m.Time, sec=h["sec"], nanosec=h["nanosec"]), frame_id=h["frame_id"])
              if isinstance(h, dict) and {"sec", "nanosec", "frame_id"} <= set(h) else h)
    fields = msg["fields"]
    if isinstance(fields, list):
        fields = [make(m.PointField, name=f[0], offset=f[1], datatype=f[2], count=f[3])
                  if isinstance(f, list) and len(f) == 4 else f
                  for f in fields]
    out = make(m.PointCloud2, header=header, height=msg["height"], width=msg["width"], fields=fields,
               is_bigendian=msg["is_bigendian"], point_step=msg["point_step"], row_step=msg["row_step"],
               data=msg["data"], is_dense=msg["is_dense"])
    for name in msg.get("missing", []):
        if kind == "namespace":
            vars(out).pop(name, None)
        else:
            setattr(out, name, None)  # a dataclass keeps its attributes: the closest is None
    return out


# ------------------------------------------------------------------ the checks
def new_monitor():
    """A monitor that processes in the caller's thread with the real per-scan pipeline, no network."""
    from topometric_ros.config import load_config
    from topometric_ros.monitor import Monitor

    config = load_config(overrides={"segmentation.mode": "none", "window.size": 3, "health.baseline_windows": 2})
    return Monitor(config, live=False)


def check_case(msg: Any, monitor: Any) -> dict:
    """Run one message through read_scan and Monitor.add_cloud; the outcome, never an exception:
    {'read_scan': 'ok' | 'CloudError' | other exception type, 'add_cloud': 'accepted' | 'counted' |
    'uncounted' (rejected without a counter) | exception type, 'ms': time of both}."""
    from topometric_ros.cloud import CloudError, read_scan

    t0 = time.perf_counter()
    out = {}
    try:
        scan = read_scan(msg)
        out["read_scan"] = "ok"
        _odometry_around(monitor, scan.stamp)
    except CloudError:
        out["read_scan"] = "CloudError"
    except Exception as e:  # noqa: BLE001 - the outcome under test
        out["read_scan"] = type(e).__name__
    before = monitor.counters
    try:
        accepted = monitor.add_cloud(msg, received=0.0)
        after = monitor.counters
        counted = sum(after[k] - before[k] for k in ("dropped_bad_scan", "dropped_duplicate"))
        ok = after["scans_in"] - before["scans_in"] == 1
        outcome = "accepted" if accepted else "counted" if counted == 1 else "uncounted"
        out["add_cloud"] = outcome if ok else "scans_in"  # scans_in must count every call once
        if after["scan_errors"] + after["window_errors"] > before["scan_errors"] + before["window_errors"]:
            out["processing_error"] = monitor.last_error.split(": ", 1)[-1][:90]  # caught and counted by the monitor
    except Exception as e:  # noqa: BLE001 - the outcome under test
        out["add_cloud"] = type(e).__name__
    out["ms"] = 1000 * (time.perf_counter() - t0)
    return out


def _odometry_around(monitor: Any, stamp: float) -> None:
    """Poses at 20 Hz from just before a parsed stamp to past its sweep, so the monitor processes the scan."""
    if np.isfinite(stamp) and abs(stamp) < 1e12:
        for dt in np.arange(-0.1, 0.35, 0.05):
            monitor.add_pose(stamp + dt, np.eye(4))


def restamp(msg: Any, k: int) -> None:
    """Give the k-th case a 5 Hz stamp (when its header is whole), so the monitor's windows fill."""
    stamp = getattr(getattr(msg, "header", None), "stamp", None)
    if isinstance(getattr(stamp, "sec", None), int) and isinstance(getattr(stamp, "nanosec", None), int):
        stamp.sec, stamp.nanosec = 1_700_000_000 + k // 5, (k % 5) * 200_000_000


class _Timeout(BaseException):  # not an Exception: no handler under test may swallow it
    pass


def _alarm(signum, frame):
    raise _Timeout()


def warm_up() -> None:
    """Process a few valid clouds first, so imports and first-call costs are not timed as a case."""
    from topometric_ros.bag import msg_types
    from topometric_ros.cloud import make_cloud

    monitor, rng = new_monitor(), np.random.default_rng(0)
    for k in range(4):
        pts = rng.normal(0, 5, (2000, 3)).astype(np.float32)
        check_case(make_cloud({"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]}, 1e9 + 0.2 * k, "lidar",
                              msg_types()), monitor)


def run(cases: int, seed: int = 0) -> dict:
    """``cases`` hypothesis-drawn messages (derandomised by ``seed``) through check_case; a summary."""
    warm_up()
    tally: dict = {"read_scan": Counter(), "add_cloud": Counter(), "corruptions": Counter(), "ms": [],
                   "examples": {}, "why": Counter(), "processed": 0, "processing": Counter()}
    monitor = [new_monitor()]

    @settings(max_examples=cases, deadline=None, database=None, derandomize=True, phases=[Phase.generate],
              suppress_health_check=list(HealthCheck))
    @given(clouds(), st.just(seed))
    def one(case, _seed):
        msg, applied = case
        if "stamp" not in applied:
            restamp(msg, len(tally["ms"]))
        if len(tally["ms"]) % 200 == 0:
            tally["processed"] += monitor[0].counters["scans_processed"]
            monitor[0] = new_monitor()  # a fresh monitor now and then: windows start again
        signal.signal(signal.SIGALRM, _alarm)
        signal.setitimer(signal.ITIMER_REAL, CASE_LIMIT_S)
        try:
            out = check_case(msg, monitor[0])
        except _Timeout:
            out = {"read_scan": "Timeout", "add_cloud": "Timeout", "ms": 1000 * CASE_LIMIT_S}
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
        if "processing_error" in out:
            tally["processing"][out["processing_error"]] += 1
        if out["add_cloud"] == "counted":
            tally["why"][re.sub(r"-?\d[\d.e+-]*", "N", monitor[0].last_error.split(":")[0])[:40]] += 1
        for key in ("read_scan", "add_cloud"):
            tally[key][out[key]] += 1
            if out[key] not in ("ok", "CloudError", "accepted", "counted"):
                tally["examples"].setdefault(out[key], applied)
        tally["corruptions"].update(applied or ["none"])
        tally["ms"].append(out["ms"])

    one()
    ms = np.array(tally["ms"])
    return {"cases": len(ms), "read_scan": dict(tally["read_scan"]), "add_cloud": dict(tally["add_cloud"]),
            "failures_by_type": {k: v for key in ("read_scan", "add_cloud") for k, v in tally[key].items()
                                 if k not in ("ok", "CloudError", "accepted", "counted")},
            "failure_examples": tally["examples"], "case_ms_median": round(float(np.median(ms)), 3),
            "case_ms_p99": round(float(np.percentile(ms, 99)), 2), "case_ms_max": round(float(ms.max()), 2),
            "case_limit_s": CASE_LIMIT_S,
            "scans_processed": tally["processed"] + monitor[0].counters["scans_processed"],
            "dropped_because": dict(tally["why"]), "processing_errors": dict(tally["processing"].most_common(10)),
            "corruptions": dict(tally["corruptions"])}


def main(cases: int = 10_000) -> dict:
    from benchmarks.common import record

    t = time.perf_counter()
    results = run(cases)
    results["wall_s"] = round(time.perf_counter() - t, 1)
    return record("fuzz", results)


if __name__ == "__main__":
    main()
