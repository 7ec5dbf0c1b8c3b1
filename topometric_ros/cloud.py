"""sensor_msgs/PointCloud2 <-> numpy for any field layout.

Duck-typed: works on rosbags messages and rclpy messages alike (anything with the PointCloud2 attributes
and a ``data`` buffer). Parsing is one structured-dtype view of the buffer, never a Python loop over
points. Every malformed cloud raises :class:`CloudError` and nothing else.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any, Callable, Mapping, Sequence

import numba
import numpy as np

#: sensor_msgs/PointField datatype constants -> numpy type codes.
DATATYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
_CODES = {np.dtype(code): dt for dt, code in DATATYPES.items()}


class CloudError(ValueError):
    """A PointCloud2 that cannot be parsed (layout, length, missing x/y/z, no points)."""


def stamp_seconds(header: Any) -> float:
    """Header stamp (sec, nanosec) -> float seconds."""
    return float(header.stamp.sec) + 1e-9 * float(header.stamp.nanosec)


def _check_int(name: str, value: Any) -> int:
    try:
        v = int(value)
    except (TypeError, ValueError):
        raise CloudError(f"{name} is not an integer: {value!r}") from None
    if v < 0:
        raise CloudError(f"{name} is negative: {v}")
    return v


def _field_dtype(msg: Any) -> np.dtype:
    """Structured numpy dtype (itemsize = point_step) that describes one point of the cloud."""
    point_step = _check_int("point_step", msg.point_step)
    order = ">" if bool(msg.is_bigendian) else "<"
    names, formats, offsets = [], [], []
    for f in msg.fields:
        code = DATATYPES.get(int(f.datatype))
        if code is None:
            raise CloudError(f"field {f.name!r}: unknown datatype {f.datatype}")
        count = _check_int(f"field {f.name!r} count", f.count)
        offset = _check_int(f"field {f.name!r} offset", f.offset)
        if count < 1:
            raise CloudError(f"field {f.name!r}: count {count} < 1")
        if f.name in names:
            raise CloudError(f"duplicate field {f.name!r}")
        size = np.dtype(code).itemsize * count
        if offset + size > point_step:
            raise CloudError(f"field {f.name!r} ends at byte {offset + size}, beyond point_step {point_step}")
        names.append(str(f.name))
        formats.append((order + code, (count,)) if count > 1 else order + code)
        offsets.append(offset)
    if point_step == 0:
        raise CloudError("point_step is 0")
    try:
        return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step})
    except (ValueError, TypeError) as e:  # overlapping fields with object-like layouts
        raise CloudError(f"invalid field layout: {e}") from None


def read_cloud(msg: Any) -> dict[str, np.ndarray]:
    """All fields of a PointCloud2 as native-endian arrays of length height × width (row-major).

    Raises CloudError on any malformed cloud, including one with zero points or without x, y, z.
    """
    try:
        return _read_cloud(msg)
    except CloudError:
        raise
    except (TypeError, AttributeError, ValueError, OverflowError) as e:  # attributes of the wrong kind
        raise CloudError(f"malformed PointCloud2: {type(e).__name__}: {e}") from None


def _read_cloud(msg: Any) -> dict[str, np.ndarray]:
    dtype = _field_dtype(msg)
    missing = [n for n in "xyz" if n not in dtype.names]
    if missing:
        raise CloudError(f"cloud has no {'/'.join(missing)} field (fields: {list(dtype.names)})")
    height, width = _check_int("height", msg.height), _check_int("width", msg.width)
    row_step = _check_int("row_step", msg.row_step)
    if height * width == 0:
        raise CloudError("cloud has zero points")
    if row_step < width * dtype.itemsize:
        raise CloudError(f"row_step {row_step} < width {width} × point_step {dtype.itemsize}")
    data = np.frombuffer(msg.data, dtype=np.uint8) if not isinstance(msg.data, np.ndarray) else msg.data.view(np.uint8)
    if data.size != height * row_step:
        raise CloudError(f"data has {data.size} bytes, expected height {height} × row_step {row_step}")
    if row_step == width * dtype.itemsize:
        points = np.frombuffer(data, dtype=dtype, count=height * width)
    else:  # rows carry padding after their points
        rows = data.reshape(height, row_step)[:, : width * dtype.itemsize]
        points = np.frombuffer(np.ascontiguousarray(rows), dtype=dtype, count=height * width)
    return {name: points[name].astype(points[name].dtype.newbyteorder("="), copy=False) for name in dtype.names}


def xyz(fields: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) float32 points (sensor frame) and the (M,) bool mask of finite points they were taken by (finite
    as float32: a float64 beyond its range counts as not finite). CloudError when x, y or z is not one number
    per point."""
    pts, finite, _ = _returns(*_xyz_float32(fields), False)
    return pts, finite


def _xyz_float32(fields: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The x, y, z fields as float32 (M,) arrays (float32 fields as they are: strided views of the cloud's
    buffer); CloudError when one is not one number per point."""
    bad = [n for n in "xyz" if fields[n].ndim != 1]
    if bad:
        raise CloudError(f"field(s) {'/'.join(bad)} must have count 1, got shape(s) {[fields[n].shape for n in bad]}")
    with np.errstate(over="ignore", invalid="ignore"):
        return tuple(fields[n] if fields[n].dtype == np.float32 else fields[n].astype(np.float32) for n in "xyz")


@numba.njit(cache=True, nogil=True)
def _returns(x, y, z, drop_zero):
    """(points (K, 3) float32 in order, the (M,) bool mask of them, how many finite points were (0, 0, 0)) of
    per-point float32 x, y, z: the finite points, and with ``drop_zero`` not (0, 0, 0) either. One pass."""
    keep = np.empty(len(x), np.bool_)
    pts = np.empty((len(x), 3), np.float32)
    k = zero = 0
    for i in range(len(x)):
        a, b, c = x[i], y[i], z[i]
        keep[i] = np.isfinite(a) and np.isfinite(b) and np.isfinite(c)
        if keep[i] and a == 0 and b == 0 and c == 0:
            zero += 1
            keep[i] = not drop_zero
        if keep[i]:
            pts[k, 0], pts[k, 1], pts[k, 2] = a, b, c
            k += 1
    return pts[:k], keep, zero


@dataclass
class CloudScan:
    """What a PointCloud2 gives the monitor, for any driver layout (sensors.LAYOUTS or unknown).

    points: (N, 3) float32 sensor frame, the returns only (NaN and all-zero no-return points and points with a
    bad beam id removed). beam: (N,) int beam id as the cloud gives it (ring field, else the beam axis of an
    organised cloud), None when it gives none. columns: firings per revolution of an organised cloud, else 0.
    time: (N,) float32 s relative to the header stamp, None without a usable per-point time field.
    intensity (N,) float32, labels (N,) uint8 or None. dropped: points removed, by reason (nonfinite,
    no_return, bad_beam). notes: why a field
    was not used. layout: the detected driver layout name ('' unknown).
    """

    stamp: float
    frame_id: str
    points: np.ndarray
    beam: np.ndarray | None
    columns: int
    time: np.ndarray | None
    intensity: np.ndarray | None
    labels: np.ndarray | None
    dropped: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)
    layout: str = ""


#: Names a per-point time field goes by (ouster t, velodyne time, hesai/livox timestamp, others).
TIME_FIELDS = ("t", "time", "timestamp", "time_stamp", "offset_time", "time_offset")
MAX_SWEEP_S = 1.0  # s, per-point times spanning more than this are not one sweep: not used
MIN_SWEEP_S = 0.005  # s, a sweep shorter than this is no real sensor's: a unit that gives one is a misreading
#: (scale to s, reference) of a time field: relative s, absolute s/ns/us (reference: the header stamp), relative ns
TIME_UNITS = ((1.0, 0.0), (1.0, None), (1e-9, None), (1e-6, None), (1e-9, 0.0))


def read_scan(msg: Any, max_beams: int = 0) -> CloudScan:
    """A PointCloud2 of any layout -> CloudScan (possibly with no points left). ``max_beams`` > 0: beam ids at
    or above it (or below 0) are bad (a named sensor's beam count; else grid.MAX_BEAMS). CloudError for a
    malformed cloud (its layout, data or header), and no other exception."""
    try:
        with np.errstate(all="ignore"):  # signalling NaNs and out-of-range casts in garbage data: handled below
            return _read_scan(msg, max_beams)
    except CloudError:
        raise
    except Exception as e:  # noqa: BLE001 - whatever a malformed message does, it is a CloudError
        raise CloudError(f"malformed PointCloud2: {type(e).__name__}: {e}") from None


def bad_beam_note(points: int, model: Any = None) -> str:
    """Console / report line for ``points`` dropped for a beam id out of range: of the named sensor model (a
    sensors.SensorModel; None: grid.MAX_BEAMS); "" for none."""
    if not points:
        return ""
    from .grid import MAX_BEAMS

    if model is None:
        return f"{points} points dropped: beam id outside 0..{MAX_BEAMS - 1}"
    return (f"{points} points dropped: beam id outside 0..{model.beams - 1}, the {model.beams} beams of "
            f"sensor.model {model.name}; is sensor.model right?")


def _header(msg: Any) -> tuple[float, str]:
    """(stamp s, frame_id) of the header; CloudError for a stamp that is not a finite number."""
    try:
        stamp = stamp_seconds(msg.header)
    except (AttributeError, TypeError, ValueError, OverflowError) as e:
        raise CloudError(f"bad header stamp: {type(e).__name__}: {e}") from None
    if not np.isfinite(stamp):
        raise CloudError(f"header stamp {stamp} is not finite")
    frame_id = getattr(msg.header, "frame_id", "")
    return stamp, frame_id if isinstance(frame_id, str) else ""


def _read_scan(msg: Any, max_beams: int) -> CloudScan:
    from .grid import MAX_BEAMS
    from .sensors import layout_of

    fields = read_cloud(msg)
    stamp, frame_id = _header(msg)
    pts, keep, zero = _returns(*_xyz_float32(fields), True)
    dropped = {"nonfinite": int(len(keep) - len(pts) - zero)}  # NaN: ouster-ros' and velodyne's "no return"
    if zero:  # (0, 0, 0): hesai's and livox's "no return"
        dropped["no_return"] = int(zero)
    height, width = int(msg.height), int(msg.width)
    beam, notes = _beams(fields, height, width), []
    columns = max(height, width) if height > 1 and width > 1 else 0  # an organised cloud: firings x beams or v.v.
    if beam is not None:
        beam = beam[keep]
        bad = (beam < 0) | (beam >= (max_beams or MAX_BEAMS))
        if bad.any():
            dropped["bad_beam"] = int(bad.sum())
            keep[np.flatnonzero(keep)[bad]] = False
            pts, beam = pts.compress(~bad, axis=0), beam[~bad]
    time, note = _times(fields, stamp, keep)
    if note:
        notes.append(note)
    value = fields.get("intensity")
    intensity = value[keep].astype(np.float32) if value is not None and value.ndim == 1 else None
    labels, note = _labels(fields, keep)
    if note:
        notes.append(note)
    layout = layout_of(fields)
    return CloudScan(stamp, frame_id, pts, beam, columns, time, intensity, labels, dropped, notes,
                     layout.name if layout else "")


def _labels(fields: Mapping[str, np.ndarray], keep: np.ndarray) -> tuple[np.ndarray | None, str]:
    """(N,) uint8 class per kept point from an integer ``label`` field of count 1 with values in 0..255, and
    a note when a label field is there but not usable."""
    label = fields.get("label")
    if label is None:
        return None, ""
    if label.ndim != 1 or label.dtype.kind not in "iu":
        return None, f"label field of type {label.dtype} x {label.shape[1:] or 1}: not used"
    kept = label[keep]
    if len(kept) and (kept.min() < 0 or kept.max() > 255):
        return None, "label field holds values outside 0..255: not used"
    return kept.astype(np.uint8), ""


def _beams(fields: Mapping[str, np.ndarray], height: int, width: int) -> np.ndarray | None:
    """(M,) beam id of every point: the ring field, else the beam axis of an organised cloud (the shorter side:
    ouster-ros writes beams x columns, velodyne_pointcloud firings x beams), else None."""
    ring = fields.get("ring")
    if ring is not None and ring.ndim == 1 and ring.dtype.kind in "iu":
        return ring.astype(np.int64)
    if height > 1 and width > 1:
        index = np.arange(height * width)
        return index // width if height <= width else index % width
    return None


def _times(fields: Mapping[str, np.ndarray], stamp: float, keep: np.ndarray) -> tuple[np.ndarray | None, str]:
    """Per-point time (s, relative to the header stamp) from the first time field there is, whatever its unit
    and reference (relative s or ns, absolute s or ns), and a note when the field is there but unusable."""
    name = next((n for n in TIME_FIELDS if n in fields and fields[n].ndim == 1), None)
    if name is None:
        return None, ""
    raw = fields[name]
    if not keep.any():
        return None, ""
    ends = np.array(_kept_range(raw, keep))  # v * scale - ref is monotone in v: its extremes are at the ends
    unit = _time_unit(ends, stamp)
    if unit is None:
        return None, f"time field {name!r} is neither a time relative to the header stamp nor near it; not used"
    t = _kept_times(raw, keep, *unit)
    first, last = (float(v) for v in ends * unit[0] - unit[1])
    span = last - first
    if span == 0.0:
        return None, f"time field {name!r} is constant; times from the azimuth instead"
    if span > MAX_SWEEP_S or max(abs(first), abs(last)) > 2 * MAX_SWEEP_S:
        return None, f"time field {name!r} spans {span:.3g} s, not one sweep; not used"
    return t, ""


def _time_unit(ends: np.ndarray, stamp: float) -> tuple[float, float] | None:
    """(scale, reference) that maps a time field's (lowest, highest) raw value to seconds after ``stamp`` (s),
    or None. Of the units that land within 2 sweeps of the stamp, the one whose times lie closest to it among
    those giving a sweep of MIN_SWEEP_S or more: a stamp near 0 (simulated time) lets several units land."""
    fits = []
    for scale, ref in TIME_UNITS:
        ref = stamp if ref is None else ref
        t = ends * scale - ref
        far = float(np.abs(t).max())
        if far <= 2 * MAX_SWEEP_S:
            fits.append((t[1] - t[0] < MIN_SWEEP_S, far, scale, ref))
    return min(fits)[2:] if fits else None


@numba.njit(cache=True, nogil=True)
def _kept_range(raw, keep):
    """(lowest, highest) of raw[keep] as float64 (NaN, NaN when one is NaN); keep holds at least one True."""
    lo, hi = np.inf, -np.inf
    for i in range(len(raw)):
        if keep[i]:
            v = np.float64(raw[i])
            if v != v:
                return np.nan, np.nan
            lo, hi = min(lo, v), max(hi, v)
    return lo, hi


@numba.njit(cache=True, nogil=True)
def _kept_times(raw, keep, scale, ref):
    """float32 (raw[keep] as float64 * scale - ref), in one pass."""
    out = np.empty(np.count_nonzero(keep), np.float32)
    k = 0
    for i in range(len(raw)):
        if keep[i]:
            out[k] = np.float64(raw[i]) * scale - ref
            k += 1
    return out


def pack_cloud(arrays: Mapping[str, np.ndarray], align: int = 1) -> tuple[list[tuple[str, int, int, int]], int, np.ndarray]:
    """Pack per-point arrays (all length N) into (fields [(name, offset, datatype, count)], point_step, data).

    Fields are laid out in the given order, each at its natural alignment capped at ``align`` bytes (as a C
    struct would), point_step rounded up to ``align``;
    data is a little-endian (N × point_step,) uint8 array.
    """
    arrays = {k: np.asarray(v) for k, v in arrays.items()}
    n = {len(v) for v in arrays.values()}
    if len(n) != 1:
        raise CloudError(f"arrays differ in length: {sorted(n)}")
    fields, offset = [], 0
    for name, a in arrays.items():
        base = a.dtype.newbyteorder("<")
        if base.newbyteorder("=") not in _CODES:
            raise CloudError(f"field {name!r}: dtype {a.dtype} has no PointField datatype")
        natural = min(align, base.itemsize)  # natural alignment, capped at align
        offset = -(-offset // natural) * natural
        count = int(np.prod(a.shape[1:])) if a.ndim > 1 else 1
        fields.append((name, offset, _CODES[base.newbyteorder("=")], count))
        offset += base.itemsize * count
    point_step = -(-offset // align) * align
    dtype = np.dtype({"names": list(arrays), "offsets": [f[1] for f in fields], "itemsize": point_step,
                      "formats": [(a.dtype.newbyteorder("<").str, a.shape[1:]) if a.ndim > 1
                                  else a.dtype.newbyteorder("<").str for a in arrays.values()]})
    out = np.zeros(n.pop(), dtype=dtype)
    for name, a in arrays.items():
        out[name] = a
    return fields, point_step, out.view(np.uint8).reshape(-1)


def make_cloud(arrays: Mapping[str, np.ndarray], stamp: float, frame_id: str, types: Any,
               data: Callable[[np.ndarray], Any] = lambda d: d, align: int = 1) -> Any:
    """Build a PointCloud2 (height 1, dense) from per-point arrays.

    ``types`` has attributes PointCloud2, PointField, Header and Time (see :func:`rosbags_types`; rclpy's
    message classes fit too, with ``data=lambda d: array.array('B', d.tobytes())``).
    """
    fields, point_step, buf = pack_cloud(arrays, align)
    n = len(buf) // point_step
    return types.PointCloud2(
        header=make_header(stamp, frame_id, types),
        height=1, width=n,
        fields=[types.PointField(name=nm, offset=o, datatype=dt, count=c) for nm, o, dt, c in fields],
        is_bigendian=False, point_step=point_step, row_step=point_step * n, data=data(buf), is_dense=True)


def make_layout_cloud(arrays: Mapping[str, np.ndarray], fields: Sequence[tuple[str, int, int]], point_step: int,
                      stamp: float, frame_id: str, types: Any, height: int = 1, padding: Sequence[tuple] = (),
                      is_dense: bool = False) -> Any:
    """A PointCloud2 with exactly the given layout: ``fields`` ((name, byte offset, datatype), ...) of
    ``point_step`` bytes, filled from ``arrays`` (name -> (N,) array; a field without an array stays 0),
    ``padding`` ((offset, float32 value), ...) bytes a driver fills, ``height`` rows of N / height points."""
    n = len(next(iter(arrays.values())))
    dtype = np.dtype({"names": [f[0] for f in fields], "offsets": [f[1] for f in fields], "itemsize": point_step,
                      "formats": ["<" + DATATYPES[f[2]] for f in fields]})
    out = np.zeros(n, dtype)
    for name, _, _ in fields:
        if name in arrays:
            out[name] = arrays[name]
    buf = out.view(np.uint8).reshape(n, point_step)
    for offset, value in padding:
        buf[:, offset:offset + 4] = np.frombuffer(np.float32(value).tobytes(), np.uint8)
    width = n // height
    return types.PointCloud2(
        header=make_header(stamp, frame_id, types), height=height, width=width,
        fields=[types.PointField(name=nm, offset=o, datatype=dt, count=1) for nm, o, dt in fields],
        is_bigendian=False, point_step=point_step, row_step=point_step * width, data=buf.reshape(-1),
        is_dense=is_dense)


def make_header(stamp: float, frame_id: str, types: Any) -> Any:
    """std_msgs/Header from float seconds."""
    ns = int(round(stamp * 1e9))
    return types.Header(stamp=types.Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000), frame_id=frame_id)


def rosbags_types(typestore: Any) -> SimpleNamespace:
    """The message classes make_cloud needs, from a rosbags typestore."""
    t = typestore.types
    return SimpleNamespace(PointCloud2=t["sensor_msgs/msg/PointCloud2"], PointField=t["sensor_msgs/msg/PointField"],
                           Header=t["std_msgs/msg/Header"], Time=t["builtin_interfaces/msg/Time"])
