"""Any LiDAR: every sensors.py model simulated in its driver's layout, read back by cloud.read_scan, put on
its grid by grid.scan_grid with and without the model named, and bad beams dropped per point."""
from __future__ import annotations

import numpy as np
import pytest

from topometric_ros import bag
from topometric_ros.cloud import make_layout_cloud, read_scan, rosbags_types
from topometric_ros.grid import scan_grid
from topometric_ros.sensors import LAYOUTS, SENSORS, sensor
from topometric_ros.sim.lidar import Lidar, firings_per_sweep
from topometric_ros.sim.scenes import make_scene
from topometric_ros.sim.writer import driver_cloud

STAMP = 1_700_000_000.25


@pytest.fixture(scope="module")
def office():
    return make_scene("office1")


def _cloud(office, name, pose_step=None):
    """One sweep of ``name`` in office1 (instantaneous, or moving by pose_step per firing) as its driver's
    PointCloud2, with the sweep (every firing) it came from."""
    model = sensor(name)
    lidar = Lidar(office, model)
    pose = np.eye(4)
    pose[:3, 3] = [4.0, 3.0, 1.0]
    sweep = lidar.sweep(pose[None], np.random.default_rng(0), returns_only=False)
    n = firings_per_sweep(model)
    t0 = STAMP - (n - 1) * model.period_s / n if model.layout.stamp == "last" else STAMP
    return driver_cloud(sweep, model, STAMP, t0, rosbags_types(bag.typestore())), sweep, t0


@pytest.mark.parametrize("name", list(SENSORS))
def test_every_sensor_reads_back_with_its_rows_times_and_returns(office, name):
    model = sensor(name)
    msg, sweep, t0 = _cloud(office, name)
    scan = read_scan(msg)
    hit = np.isfinite(sweep.points[:, 0])
    assert scan.layout == model.driver
    assert len(scan.points) == hit.sum()  # every return, no no-return point (NaN or zero) kept
    assert sum(scan.dropped.values()) == (~hit).sum()
    lay = LAYOUTS[model.driver]
    assert msg.point_step >= lay.point_step and [f.name for f in msg.fields][:len(lay.fields)] == [f[0] for f in lay.fields]
    if lay.organised:
        assert msg.height > 1 and scan.columns == model.columns
    # per-point time: each return's own firing time relative to the header stamp (HDL-64E: velodyne has none)
    if name == "HDL-64E":
        assert scan.time is None and "constant" in scan.notes[0]
    else:
        fired = np.sort(t0 + sweep.time[hit] - STAMP)
        step = 8 * model.period_s / model.columns if model.driver == "hesai" else 1e-6  # hesai: packet times
        np.testing.assert_allclose(np.sort(scan.time), fired, atol=step)
    # rows: the grid gives every return its true beam, from the ring field, the model, or the scan itself
    if model.pattern == "spinning":
        truth = np.sort(sweep.ring[hit])
        for grid in (scan_grid(scan.points, scan.beam, scan.columns), scan_grid(scan.points, model=model),
                     scan_grid(scan.points)):
            assert grid.height == model.beams
            assert np.array_equal(np.sort(grid.row), truth), grid.source
        assert scan_grid(scan.points).width == model.columns or abs(scan_grid(scan.points).width - model.columns) <= 8
    else:
        for grid in (scan_grid(scan.points, scan.beam, scan.columns),
                     scan_grid(scan.points, scan.beam, scan.columns, layout=scan.layout)):
            assert grid.source.startswith("elevation bins") and grid.height == 32
        assert scan_grid(scan.points, model=model).width == model.columns


def _beams(elevations_deg, per_beam=180, range_m=10.0):
    """(N, 3) float32 points of a spinning scan: each beam's ring of ``per_beam`` azimuths at ``range_m``."""
    e, a = np.meshgrid(np.radians(elevations_deg), np.linspace(0, 2 * np.pi, per_beam, endpoint=False), indexing="ij")
    return (range_m * np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1)).reshape(-1, 3).astype(np.float32)


def test_a_cloud_in_a_non_repetitive_sensors_driver_layout_is_never_read_as_beams():
    """No sensor named: the livox_ros_driver2 layout says non-repetitive, even for a scan whose elevations
    happen to fall into beam-like clusters (about 1 % of simulated Mid-360 scans); a named model wins."""
    pts = _beams(np.linspace(-7, 52, 16))
    assert scan_grid(pts).source == "elevation clusters" and scan_grid(pts).height == 16
    livox = scan_grid(pts, layout="livox")
    assert livox.source == "elevation bins (non-repetitive)" and livox.height == 32 and livox.azimuth is not None
    assert scan_grid(pts, layout="velodyne").source == "elevation clusters"
    assert scan_grid(pts, model=sensor("VLP-16"), layout="livox").source == "VLP-16 beam table"
    from topometric_ros.config import load_config
    from topometric_ros.pipeline import segment_scan
    from topometric_ros.window import Frame

    cfg = load_config(overrides={"segmentation.mode": "none"})  # the Monitor's stage 1 reads the frame's layout
    assert segment_scan(Frame(pts, np.eye(4), 0.0, layout="livox"), cfg).grid.source.startswith("elevation bins")


def test_more_elevation_clusters_than_any_lidar_has_beams_are_no_beams():
    """Elevations in narrow runs 0.15 deg apart: 200 runs are beams, 300 (> grid.MAX_BEAMS) are a
    non-repetitive pattern's chance clustering."""
    from topometric_ros.grid import MAX_BEAMS, beam_centres

    for runs in (200, 300):
        centres = beam_centres(_beams(-20 + 0.15 * np.arange(runs), per_beam=20))
        assert (centres is not None and len(centres) == runs) == (runs <= MAX_BEAMS)


def test_a_grid_is_never_narrower_than_the_network_can_read():
    from topometric_ros.grid import MIN_COLUMNS

    pts = _beams(np.linspace(-15, 15, 16), per_beam=16)
    assert MIN_COLUMNS == 64 and scan_grid(pts, columns=16).width == 64 and scan_grid(pts).width == 64
    assert scan_grid(_beams(np.linspace(-15, 15, 16), per_beam=1800)).width == 1800


def test_an_organised_clouds_width_wins_over_the_named_sensors_firings():
    """An Ouster in 2048x10 mode named as its model (1024 firings in sensors.py): the cloud's 2048 columns are
    the grid's, so no two firings of a beam share a cell; an unorganised cloud takes the model's."""
    model = sensor("OS1-64")
    pts = _beams(model.elevation_deg, per_beam=2048)
    beam = np.repeat(np.arange(model.beams), 2048)
    grid = scan_grid(pts, beam, columns=2048, model=model)
    assert grid.width == 2048 and len(np.unique(grid.row * grid.width + grid.col)) == len(pts)
    assert scan_grid(pts, beam, model=model).width == model.columns == 1024


def test_a_dual_return_scans_second_returns_do_not_count_as_firings():
    """Unorganised, no sensor named, every firing twice (strongest and last return, same azimuth, other
    range): the width is the firings per revolution, not the MAX_COLUMNS cap."""
    single = _beams(np.linspace(-15, 15, 16), per_beam=1800)
    dual = np.concatenate([single, single * 1.5])
    assert scan_grid(single).width == scan_grid(dual).width == 1800


def test_a_bad_beam_id_drops_that_point_not_the_scan():
    types = rosbags_types(bag.typestore())
    lay = LAYOUTS["velodyne"]
    n = 400
    rng = np.random.default_rng(0)
    arrays = {"x": rng.uniform(1, 5, n).astype(np.float32), "y": rng.uniform(1, 5, n).astype(np.float32),
              "z": rng.uniform(-1, 1, n).astype(np.float32), "ring": np.arange(n) % 16, "time": np.zeros(n)}
    arrays["ring"][[3, 77]] = [127, 300]
    scan = read_scan(make_layout_cloud(arrays, lay.fields, lay.point_step, STAMP, "velodyne", types))
    assert len(scan.points) == n - 1 and scan.dropped["bad_beam"] == 1  # 300 >= MAX_BEAMS; 127 is a valid id
    scan16 = read_scan(make_layout_cloud(arrays, lay.fields, lay.point_step, STAMP, "velodyne", types), max_beams=16)
    assert len(scan16.points) == n - 2 and scan16.dropped["bad_beam"] == 2  # a named 16-beam sensor


@pytest.mark.parametrize("stamp", [STAMP, 1.0, 1.95])
@pytest.mark.parametrize("unit, absolute", [("s", False), ("ns", False), ("s", True), ("ns", True), ("us", True)])
def test_a_time_field_in_any_unit_and_reference_becomes_seconds_after_the_stamp(unit, absolute, stamp):
    """Also with a header stamp near 0 (a simulator's clock), where several units land within a sweep or two of
    the stamp: relative ns must not read as absolute ns (-1 s), absolute s not as relative s (+1.5 s), absolute
    us not as relative ns (a 0.1 ms sweep)."""
    types = rosbags_types(bag.typestore())
    t = np.linspace(0.0, 0.0999, 500)
    value = (stamp if absolute else 0.0) + t
    value = {"s": value, "ns": value * 1e9, "us": value * 1e6}[unit]
    kind = 8 if absolute or unit == "s" else 6  # float64 or uint32
    fields = (("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("timestamp", 12, kind))
    arrays = {"x": np.ones(500, np.float32), "y": np.linspace(-1, 1, 500), "z": np.zeros(500), "timestamp": value}
    msg = make_layout_cloud(arrays, fields, 20, stamp, "lidar", types)
    scan = read_scan(msg)
    np.testing.assert_allclose(scan.time, t, atol=1e-6)  # float64 ns since the epoch hold 256 ns steps


@pytest.mark.parametrize("ids_fall", [False, True])
def test_a_beam_too_sparse_for_the_elevation_sample_still_orders_the_rows(ids_fall):
    """Rows come from beam ids ordered by each id's median elevation, found on every grid.SAMPLE-th point; a
    beam with 2 points that the sample misses makes the grid use every point: the order is still right (ids
    falling with elevation, as Ouster's, are reversed), and that row's elevation is NaN (no sampled point)."""
    from topometric_ros.grid import SAMPLE

    beams, per_beam = 8, 50
    el = np.radians(np.linspace(-15, 15, beams))
    az = np.radians(np.arange(per_beam) * 7.0)
    e, a = np.meshgrid(el, az, indexing="ij")
    pts = (10 * np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1)).reshape(-1, 3)
    row = np.repeat(np.arange(beams), per_beam)
    rest, sparse = np.flatnonzero(row != 5), np.flatnonzero(row == 5)[:2]
    order = np.concatenate([rest[:1], sparse, rest[1:]])  # beam 5 at positions 1 and 2: off the sample
    pts, row = pts[order].astype(np.float32), row[order]
    assert np.count_nonzero(row == 5) == 2 and not np.any(row[::SAMPLE] == 5)
    grid = scan_grid(pts, beams - 1 - row if ids_fall else row)
    assert np.array_equal(grid.row, row), grid.source
    assert grid.source == ("ring field (top-down, reversed)" if ids_fall else "ring field")
    expected = np.degrees(el)
    expected[5] = np.nan
    np.testing.assert_allclose(grid.elevation_deg, expected, atol=1e-4)


@pytest.mark.parametrize("ids", ["rising", "falling", "scrambled"])
def test_rows_and_their_elevations_follow_elevation_whatever_order_the_beam_ids_come_in(ids):
    """Every beam in the elevation sample: rows bottom-up, and each row's median elevation is its beam's."""
    beams, per_beam = 8, 90
    el = np.radians(np.linspace(-15, 15, beams))
    e, a = np.meshgrid(el, np.radians(np.arange(per_beam) * 4.0), indexing="ij")
    pts = (10 * np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1)).reshape(-1, 3)
    row = np.repeat(np.arange(beams), per_beam)
    beam_id = {"rising": np.arange(beams), "falling": np.arange(beams)[::-1],
               "scrambled": np.array([3, 7, 0, 5, 1, 6, 2, 4])}[ids]
    grid = scan_grid(pts.astype(np.float32), beam_id[row])
    assert np.array_equal(grid.row, row), grid.source
    np.testing.assert_allclose(grid.elevation_deg, np.degrees(el), atol=1e-4)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_an_azimuth_goes_to_the_cell_centred_nearest_to_it(dtype):
    from topometric_ros.grid import azimuth_cells

    width = 1800
    centres = np.arange(-width // 2, width // 2) * (2 * np.pi / width)
    cells = np.arange(-width // 2, width // 2) % width  # column 0 at +x, counter-clockwise, wrapping at ±π
    np.testing.assert_array_equal(azimuth_cells(centres.astype(dtype), width), cells)
    off = 0.4 * 2 * np.pi / width  # under half a cell either side: the same cell
    np.testing.assert_array_equal(azimuth_cells((centres + off).astype(dtype), width), cells)
    np.testing.assert_array_equal(azimuth_cells((centres - off).astype(dtype), width), cells)
    assert azimuth_cells(np.array([-1e-9, np.pi - 1e-6], dtype), width).tolist() == [0, width // 2]


def test_a_non_repetitive_scans_elevation_bins_split_its_field_of_view_evenly():
    """Non-repetitive rows are NON_REPETITIVE_ROWS equal elevation bins from the lowest elevation to the highest:
    elevations spread evenly put as many points in every row, rows rising with elevation."""
    from topometric_ros.grid import NON_REPETITIVE_ROWS

    el = np.linspace(-7, 52, NON_REPETITIVE_ROWS * 50 + 1)
    grid = scan_grid(_beams(el, per_beam=3), layout="livox")
    counts = np.bincount(grid.row, minlength=grid.height)
    assert grid.height == NON_REPETITIVE_ROWS and counts.min() >= 3 * 49 and counts.max() <= 3 * 52, counts
    assert np.all(np.diff(grid.row.reshape(len(el), 3)[:, 0]) >= 0)


def test_an_unorganised_scans_width_comes_from_its_fullest_rows_not_its_sparsest():
    """No sensor named, no organised width: the firings per revolution are estimated from the azimuth steps of
    the fullest rows; three beams that returned only a few points (sky, a window) do not shrink the grid."""
    full = _beams(np.linspace(-15, 15, 16), per_beam=1800)
    beam = np.repeat(np.arange(16), 1800)
    keep = (beam < 13) | (np.arange(len(beam)) % 45 == 0)  # beams 13-15: 40 returns each, 16° apart
    assert scan_grid(full[keep], beam[keep]).width == 1800


def test_near_points_blurred_by_beam_origin_offsets_do_not_hide_the_beams():
    """Points nearer than grid.CLUSTER_MIN_RANGE do not place beams: a beam origin 5 cm above the sensor's
    shifts the elevation of its near returns by up to ~10° (the more, the nearer), filling the gaps between
    the beams; the far points' clusters are the beams, and the near blur adds none."""
    el = np.linspace(-15, 15, 16)
    rng = np.random.default_rng(0)
    e, a, r = np.radians(rng.choice(el, 600)), rng.uniform(0, 2 * np.pi, 600), rng.uniform(0.3, 1.9, 600)
    near = r[:, None] * np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], 1) + [0.0, 0.0, 0.05]
    grid = scan_grid(np.concatenate([_beams(el, per_beam=1800), near.astype(np.float32)]))
    assert grid.source == "elevation clusters" and grid.height == 16
    np.testing.assert_allclose(grid.elevation_deg, el, atol=0.01)


def test_elevations_in_runs_wider_than_a_beam_are_no_beams():
    """No sensor named, no driver layout: elevations filling 10 bands 2° wide make enough clusters for beams,
    but each is wider than one beam can be (grid.MAX_BEAM_WIDTH_DEG): a non-repetitive pattern, binned."""
    from topometric_ros.grid import beam_centres

    pts = _beams(np.concatenate([lo + np.linspace(0.0, 2.0, 200) for lo in np.arange(10) * 3.0 - 15]), per_beam=10)
    assert beam_centres(pts) is None and scan_grid(pts).source == "elevation bins (non-repetitive)"


def test_each_sensors_beams_firings_and_rate_are_its_datasheets():
    """Facts from the makers' datasheets and manuals, independent of the tables' digits: the field of view, how the
    beams are spaced (uniform, or dense near the horizon), the firings per revolution and 10 Hz. The simulator and
    the grid read the same tables, so a wrong table (a beam off, a uniform table for a gradient one) is otherwise
    simulated and read back as consistently wrong."""
    def spacing(name):
        return np.diff(sensor(name).elevation_deg)

    for name, beams, lo, hi in (("VLP-16", 16, -15.0, 15.0), ("VLP-32C", 32, -25.0, 15.0),
                                ("HDL-32E", 32, -30.67, 10.67), ("HDL-64E", 64, -24.711, 2.0208),
                                ("XT32", 32, -16.0, 15.0)):
        m = sensor(name)
        assert (m.beams, m.elevation_deg[0], m.elevation_deg[-1]) == (beams, lo, hi), name
    np.testing.assert_allclose(spacing("VLP-16"), 2.0)
    np.testing.assert_allclose(spacing("XT32"), 1.0)
    np.testing.assert_allclose(spacing("HDL-32E"), 1.33, atol=0.011)
    # gradient tables: VLP-32C 0.333 deg apart around the horizon, 9.4 deg at the bottom; OS1-32G dense near it too
    assert spacing("VLP-32C").min() == pytest.approx(0.333, abs=1e-3) and spacing("VLP-32C")[0] > 9
    g = spacing("OS1-32G")
    assert g.min() < 0.4 and g.max() > 2.5 and sensor("OS1-32G").beams == 32
    for family in "012":  # the uniform Ouster variants: every 2nd / 4th beam of the 128's optics
        full = spacing(f"OS{family}-128").mean()
        for beams, k in ((64, 2), (32, 4)):
            m = sensor(f"OS{family}-{beams}")
            assert m.beams == beams and spacing(m.name).mean() == pytest.approx(k * full, rel=0.03), m.name
    assert {m.columns for m in SENSORS.values() if m.driver == "ouster"} == {1024}  # 1024x10 mode
    assert sensor("VLP-16").columns == sensor("VLP-32C").columns == 1800  # 0.2 deg at 10 Hz
    assert abs(sensor("HDL-32E").columns - 1 / (10 * 46.08e-6)) < 0.01 * 2170  # one firing cycle each 46.08 us
    assert {m.rate_hz for m in SENSORS.values()} == {10.0}
    mid = sensor("Mid-360")
    assert (mid.fov_deg, mid.points_per_scan, mid.pattern) == ((-7.0, 52.0), 20000, "non_repetitive")


def test_each_driver_layout_is_its_drivers_point_struct():
    """The bytes each driver writes (docs/design.md's table, from the drivers' sources): a real bag is read by
    these offsets and types, while the simulator writes by them too, so a wrong one round-trips unnoticed."""
    from topometric_ros.sensors import FLOAT32, FLOAT64, UINT8, UINT16, UINT32

    want = {
        "velodyne": ((("x", 0, FLOAT32), ("y", 4, FLOAT32), ("z", 8, FLOAT32), ("intensity", 12, FLOAT32),
                      ("ring", 16, UINT16), ("time", 18, FLOAT32)), 22, ("time", "s", False, "last", False)),
        "ouster": ((("x", 0, FLOAT32), ("y", 4, FLOAT32), ("z", 8, FLOAT32), ("intensity", 16, FLOAT32),
                    ("t", 20, UINT32), ("reflectivity", 24, UINT16), ("ring", 26, UINT16), ("ambient", 28, UINT16),
                    ("range", 32, UINT32)),
                   48, ("t", "ns", False, "first", True)),
        "hesai": ((("x", 0, FLOAT32), ("y", 4, FLOAT32), ("z", 8, FLOAT32), ("intensity", 12, FLOAT32),
                   ("ring", 16, UINT16), ("timestamp", 18, FLOAT64)), 26, ("timestamp", "s", True, "first", True)),
        "livox": ((("x", 0, FLOAT32), ("y", 4, FLOAT32), ("z", 8, FLOAT32), ("intensity", 12, FLOAT32),
                   ("tag", 16, UINT8), ("line", 17, UINT8), ("timestamp", 18, FLOAT64)), 26,
                  ("timestamp", "ns", True, "first", False)),
    }
    assert set(LAYOUTS) == set(want)
    for name, (fields, step, (time_field, unit, absolute, stamp, top_first)) in want.items():
        lay = LAYOUTS[name]
        assert (lay.fields, lay.point_step) == (fields, step), name
        assert (lay.time_field, lay.time_unit, lay.time_absolute, lay.stamp, lay.ring_top_first) == \
            (time_field, unit, absolute, stamp, top_first), name
    assert [(n, LAYOUTS[n].organised, LAYOUTS[n].no_return) for n in want] == [
        ("velodyne", "firings x beams", "nan"), ("ouster", "beams x columns", "nan"), ("hesai", "", "zero"),
        ("livox", "", "zero")]


def test_a_sensor_is_found_by_its_name_in_any_case():
    assert sensor("vlp-16") is sensor("VLP-16") is SENSORS["VLP-16"] and sensor("os1-32g").name == "OS1-32G"
    with pytest.raises(ValueError, match="unknown sensor 'VLP-17'; known: VLP-16, VLP-32C"):
        sensor("VLP-17")
