"""sensor_msgs/PointCloud2 <-> numpy for any field layout.

Duck-typed: works on rosbags messages and rclpy messages alike (anything with the PointCloud2 attributes
and a ``data`` buffer). Parsing is one structured-dtype view of the buffer, never a Python loop over
points. Every malformed cloud raises :class:`CloudError` and nothing else.
"""
from __future__ import annotations

from types import SimpleNamespace
from typing import Any, Callable, Mapping

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
    """(N, 3) float32 points (sensor frame) and the (M,) bool mask of finite points they were taken by."""
    pts = np.stack([fields["x"], fields["y"], fields["z"]], axis=1)
    pts = pts.reshape(len(pts), 3) if pts.ndim == 2 else pts[:, :, 0]  # a count>1 x field uses element 0
    finite = np.isfinite(pts).all(axis=1)
    return pts[finite].astype(np.float32, copy=False), finite


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


def make_header(stamp: float, frame_id: str, types: Any) -> Any:
    """std_msgs/Header from float seconds."""
    ns = int(round(stamp * 1e9))
    return types.Header(stamp=types.Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000), frame_id=frame_id)


def rosbags_types(typestore: Any) -> SimpleNamespace:
    """The message classes make_cloud needs, from a rosbags typestore."""
    t = typestore.types
    return SimpleNamespace(PointCloud2=t["sensor_msgs/msg/PointCloud2"], PointField=t["sensor_msgs/msg/PointField"],
                           Header=t["std_msgs/msg/Header"], Time=t["builtin_interfaces/msg/Time"])
