"""cloud.py: any valid layout round-trips; any corruption raises CloudError and nothing else; an organised cloud's
beams come from its shorter side."""
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from topometric_ros import bag
from topometric_ros.cloud import DATATYPES, CloudError, make_cloud, read_cloud, read_scan, rosbags_types, xyz


def duck_cloud(fields, point_step, height, width, row_step, data, bigendian=False):
    """A PointCloud2 look-alike: what read_cloud must accept from rclpy, rosbags or anything else."""
    return SimpleNamespace(fields=[SimpleNamespace(name=n, offset=o, datatype=d, count=c) for n, o, d, c in fields],
                           point_step=point_step, height=height, width=width, row_step=row_step, data=data,
                           is_bigendian=bigendian, is_dense=False)


@st.composite
def layouts(draw):
    """Random valid layout: fields x, y, z plus extras in any order, gaps, endianness, row padding."""
    extra = draw(st.lists(st.sampled_from(["intensity", "ring", "t", "label", "range", "pad2"]), unique=True, max_size=4))
    names = draw(st.permutations(["x", "y", "z"] + extra))
    fields, offset = [], 0
    for name in names:
        dt = draw(st.sampled_from([7, 8])) if name in "xyz" else draw(st.sampled_from(sorted(DATATYPES)))
        count = 1 if name in "xyz" else draw(st.integers(1, 3))
        offset += draw(st.integers(0, 5))
        fields.append((name, offset, dt, count))
        offset += np.dtype(DATATYPES[dt]).itemsize * count
    point_step = offset + draw(st.integers(0, 9))
    height, width = draw(st.integers(1, 4)), draw(st.integers(1, 40))
    row_step = width * point_step + draw(st.sampled_from([0, 0, 3, 16]))
    return fields, point_step, height, width, row_step, draw(st.booleans()), draw(st.integers(0, 2**31))


def fill(fields, point_step, height, width, row_step, bigendian, seed):
    """Random values per field and the exact bytes a driver would send for them."""
    rng = np.random.default_rng(seed)
    order = ">" if bigendian else "<"
    values, buf = {}, np.zeros(height * row_step, np.uint8)
    n = height * width
    for name, offset, dt, count in fields:
        code = np.dtype(DATATYPES[dt])
        if code.kind == "f":
            v = rng.normal(0, 50, size=(n, count)).astype(code)
            v[rng.random(v.shape) < 0.05] = np.nan
        else:
            info = np.iinfo(code)
            v = rng.integers(info.min, info.max, size=(n, count), endpoint=True, dtype=code)
        values[name] = v if count > 1 else v[:, 0]
        raw = v.astype(code.newbyteorder(order)).view(np.uint8).reshape(n, -1)
        for i in range(n):  # reference encoder: deliberately the slow, obvious way
            r, c = divmod(i, width)
            start = r * row_step + c * point_step + offset
            buf[start:start + raw.shape[1]] = raw[i]
    return values, buf.tobytes()


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(layouts())
def test_any_valid_layout_round_trips(layout):
    fields, point_step, height, width, row_step, big, seed = layout
    values, data = fill(fields, point_step, height, width, row_step, big, seed)
    out = read_cloud(duck_cloud(fields, point_step, height, width, row_step, data, big))
    assert set(out) == set(values)
    for name, v in values.items():
        np.testing.assert_array_equal(out[name], v)
        assert out[name].dtype.isnative
    pts, finite = xyz(out)
    ref = np.stack([values["x"], values["y"], values["z"]], 1)
    np.testing.assert_array_equal(finite, np.isfinite(ref).all(1))
    np.testing.assert_array_equal(pts, ref[finite].astype(np.float32))


CORRUPTIONS = ["truncate", "extend", "point_step", "width", "height", "row_step", "drop_x", "datatype",
               "offset", "count", "duplicate", "negative", "not_int", "zero_points", "fields_none", "data_none"]


def corrupt(msg, how, rng):
    m = SimpleNamespace(**vars(msg))
    m.fields = [SimpleNamespace(**vars(f)) for f in msg.fields]
    if how == "truncate":
        m.data = m.data[: int(rng.integers(0, len(m.data)))]
    elif how == "extend":
        m.data = m.data + bytes(int(rng.integers(1, 50)))
    elif how == "point_step":
        m.point_step = int(rng.integers(0, 3 * m.point_step + 2))
    elif how == "width":
        # more points than a row holds (a bigger width can still fit in padded rows: that is valid)
        m.width = m.row_step // m.point_step + int(rng.integers(1, 5))
    elif how == "height":
        m.height = m.height + int(rng.integers(1, 5))
    elif how == "row_step":
        m.row_step = int(rng.integers(0, m.row_step))
    elif how == "drop_x":
        m.fields = [f for f in m.fields if f.name != "x"]
    elif how == "datatype":
        m.fields[int(rng.integers(len(m.fields)))].datatype = int(rng.choice([0, 9, 42, 255, -1]))
    elif how == "offset":
        m.fields[int(rng.integers(len(m.fields)))].offset = m.point_step + int(rng.integers(0, 100))
    elif how == "count":
        m.fields[int(rng.integers(len(m.fields)))].count = 0
    elif how == "duplicate":
        m.fields.append(m.fields[0])
    elif how == "negative":
        setattr(m, str(rng.choice(["width", "height", "point_step", "row_step"])), -int(rng.integers(1, 10)))
    elif how == "not_int":
        setattr(m, str(rng.choice(["width", "height", "point_step", "row_step"])), rng.choice([None, "abc", 1.5e300]))
    elif how == "zero_points":
        m.width, m.row_step, m.data = 0, 0, b""
    elif how == "fields_none":
        m.fields = None
    elif how == "data_none":
        m.data = None
    return m


ALWAYS_INVALID = {"truncate", "extend", "drop_x", "datatype", "offset", "count", "duplicate", "negative",
                  "zero_points", "fields_none", "data_none", "width", "height"}


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(layouts(), st.sampled_from(CORRUPTIONS), st.integers(0, 2**31))
def test_corruptions_raise_cloud_error_only(layout, how, seed):
    fields, point_step, height, width, row_step, big, vseed = layout
    _, data = fill(fields, point_step, height, width, row_step, big, vseed)
    msg = corrupt(duck_cloud(fields, point_step, height, width, row_step, data, big), how, np.random.default_rng(seed))
    if how in ALWAYS_INVALID:
        with pytest.raises(CloudError):
            read_cloud(msg)
    else:  # may happen to stay valid (e.g. a smaller point_step that still fits every field)
        try:
            read_cloud(msg)
        except CloudError:
            pass


def velodyne_layout():
    # velodyne_pointcloud: x y z intensity float32, ring uint16, time float32 -> point_step 22
    return [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("intensity", 12, 7, 1), ("ring", 16, 4, 1),
            ("time", 18, 7, 1)], 22


def ouster_layout():
    # ouster-ros: x y z (+pad) intensity float32, t uint32, reflectivity/ring/ambient uint16, range uint32
    return [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("intensity", 16, 7, 1), ("t", 20, 6, 1),
            ("reflectivity", 24, 4, 1), ("ring", 26, 4, 1), ("ambient", 28, 4, 1), ("range", 32, 6, 1)], 48


@pytest.mark.parametrize("layout", [velodyne_layout, ouster_layout])
def test_real_driver_layouts_parse(layout):
    fields, step = layout()
    height, width = (1, 1000) if step == 22 else (64, 16)
    values, data = fill(fields, step, height, width, width * step, False, 7)
    out = read_cloud(duck_cloud(fields, step, height, width, width * step, data))
    np.testing.assert_array_equal(out["ring"], values["ring"])
    assert out["ring"].dtype == np.uint16
    np.testing.assert_array_equal(out["x"], values["x"])


def test_rosbags_message_round_trip_through_cdr():
    rng = np.random.default_rng(0)
    arrays = {"x": rng.normal(size=500).astype(np.float32), "y": rng.normal(size=500).astype(np.float32),
              "z": rng.normal(size=500).astype(np.float32), "intensity": rng.random(500).astype(np.float32),
              "ring": rng.integers(0, 32, 500).astype(np.uint16), "label": rng.integers(0, 7, 500).astype(np.uint8)}
    store = bag.typestore()
    msg = make_cloud(arrays, 1.7e9 + 0.123456789, "velodyne", rosbags_types(store), align=4)
    assert msg.point_step == 20
    back = store.deserialize_cdr(store.serialize_cdr(msg, msg.__msgtype__), msg.__msgtype__)
    out = read_cloud(back)
    for k, v in arrays.items():
        np.testing.assert_array_equal(out[k], v)
    assert back.header.stamp.sec == 1_700_000_000
    assert abs(back.header.stamp.nanosec - 123456789) < 1000  # float64 seconds resolve ~0.24 µs at 1.7e9 s


@pytest.mark.parametrize("beams_first", [True, False])
def test_an_organised_cloud_without_a_ring_field_takes_its_beams_from_the_shorter_side(beams_first):
    """ouster-ros writes beams x columns (height = beams), velodyne_pointcloud firings x beams (width = beams)."""
    from topometric_ros.cloud import make_layout_cloud

    beams, columns = 4, 100
    n = beams * columns
    idx = np.arange(n)
    beam = idx // columns if beams_first else idx % beams  # each point's beam in row-major order
    arrays = {"x": np.full(n, 5.0, np.float32), "y": (idx % 97).astype(np.float32) * 0.1, "z": beam.astype(np.float32)}
    fields = (("x", 0, 7), ("y", 4, 7), ("z", 8, 7))
    msg = make_layout_cloud(arrays, fields, 12, 1.7e9, "lidar", rosbags_types(bag.typestore()),
                            height=beams if beams_first else columns)
    scan = read_scan(msg)
    assert scan.columns == columns
    np.testing.assert_array_equal(scan.beam, beam)
