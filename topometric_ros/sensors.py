"""LiDAR models and their ROS 2 drivers' PointCloud2 layouts: the one truth the product and the simulator share.

A SensorModel is the geometry (beam elevations, firings per revolution, rate, range limits, noise) and a
DriverLayout how its driver writes a cloud (fields and offsets, organised or not, what a missing return
looks like, the per-point time field and what header.stamp is the time of). Facts are from the drivers'
sources (ros-drivers/velodyne ros2 @04a7ca7, ouster-lidar/ouster-ros jazzy-devel @eaaf35d, ouster-sdk test
metadata @46b7bce, HesaiLidar_ROS_2.0 @e7e112f + SDK 2.0, Livox-SDK/livox_ros_driver2 @13eb05e); see
docs/design.md for what each choice rests on. Elevations are in degrees, ascending (index = ring in the
velodyne convention, 0 = lowest beam); all spinning models rotate clockwise seen from above (azimuth
atan2(y, x) falls with time).
"""
from __future__ import annotations

from dataclasses import dataclass


# PointField datatypes (sensor_msgs/PointField)
INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = range(1, 9)


@dataclass(frozen=True)
class DriverLayout:
    """How a ROS 2 driver writes a PointCloud2.

    fields: ((name, byte offset, datatype), ...); point_step in bytes. organised: 'beams x columns' (Ouster:
    height = beams), 'firings x beams' (velodyne: width = rings) or '' (height 1). no_return: 'nan' (kept
    with NaN x/y/z), 'dropped' or 'zero' (kept at 0, 0, 0). time_field, time_unit ('s' or 'ns') and
    time_absolute: the per-point time; stamp: 'first' or 'last' - the point time header.stamp is.
    ring_top_first: ring 0 is the highest beam. padding: {offset: float32 value} bytes the driver fills.
    pattern: 'spinning' (beams) or 'non_repetitive' (a driver only such sensors use: their scans have no rows).
    """

    name: str
    fields: tuple
    point_step: int
    organised: str
    no_return: str
    time_field: str
    time_unit: str
    time_absolute: bool
    stamp: str
    ring_field: str | None
    ring_top_first: bool
    frame_id: str
    padding: tuple = ()
    pattern: str = "spinning"


LAYOUTS = {
    # velodyne_pointcloud PointcloudXYZIRT / OrganizedCloudXYZIRT (addPointField packs: point_step 22); time
    # relative to header.stamp = the LAST packet of the scan (timestamp_first_packet false), so mostly < 0
    "velodyne": DriverLayout("velodyne", (("x", 0, FLOAT32), ("y", 4, FLOAT32), ("z", 8, FLOAT32),
                                          ("intensity", 12, FLOAT32), ("ring", 16, UINT16), ("time", 18, FLOAT32)),
                             22, "firings x beams", "nan", "time", "s", False, "last", "ring", False, "velodyne"),
    # ouster-ros point type 'original' (os_point.h): organised beams x columns, destaggered, NaN for no return,
    # t = ns since the scan's column-0 time = header.stamp; ring 0 = top beam
    "ouster": DriverLayout("ouster", (("x", 0, FLOAT32), ("y", 4, FLOAT32), ("z", 8, FLOAT32),
                                      ("intensity", 16, FLOAT32), ("t", 20, UINT32), ("reflectivity", 24, UINT16),
                                      ("ring", 26, UINT16), ("ambient", 28, UINT16), ("range", 32, UINT32)),
                           48, "beams x columns", "nan", "t", "ns", False, "first", "ring", True, "os_lidar",
                           padding=((12, 1.0),)),
    # HesaiLidar_ROS_2.0 LidarPointXYZIRT: unorganised, no return published as (0, 0, 0), timestamp = the
    # packet's absolute time (s); header.stamp = the frame's first packet; ring 0 = top channel
    "hesai": DriverLayout("hesai", (("x", 0, FLOAT32), ("y", 4, FLOAT32), ("z", 8, FLOAT32),
                                    ("intensity", 12, FLOAT32), ("ring", 16, UINT16), ("timestamp", 18, FLOAT64)),
                          26, "", "zero", "timestamp", "s", True, "first", "ring", True, "hesai_lidar"),
    # livox_ros_driver2 xfer_format 0 (PointXYZRTLT, packed): timestamp = absolute ns as float64,
    # header.stamp = the frame's first point; line = point index % 4 (no beams)
    "livox": DriverLayout("livox", (("x", 0, FLOAT32), ("y", 4, FLOAT32), ("z", 8, FLOAT32),
                                    ("intensity", 12, FLOAT32), ("tag", 16, UINT8), ("line", 17, UINT8),
                                    ("timestamp", 18, FLOAT64)),
                          26, "", "zero", "timestamp", "ns", True, "first", None, False, "livox_frame",
                          pattern="non_repetitive"),
}


@dataclass(frozen=True)
class SensorModel:
    """A LiDAR: beam elevations (deg, ascending; empty for a non-repetitive pattern), firings per revolution
    (``columns``; the grid columns of a non-repetitive one), scans per second, range limits and Gaussian range
    noise sigma (m), random dropout fraction, driver layout name, and for a non-repetitive pattern its
    elevation field of view (deg), grid rows and points per scan."""

    name: str
    elevation_deg: tuple
    columns: int
    rate_hz: float
    min_range: float
    max_range: float
    range_noise: float
    driver: str
    dropout: float = 0.01
    pattern: str = "spinning"
    fov_deg: tuple = ()
    grid_rows: int = 0
    points_per_scan: int = 0

    @property
    def beams(self) -> int:
        """Rows of the sensor's grid: its beams, or the elevation bins of a non-repetitive pattern."""
        return self.grid_rows if self.pattern == "non_repetitive" else len(self.elevation_deg)

    @property
    def layout(self) -> DriverLayout:
        return LAYOUTS[self.driver]

    @property
    def period_s(self) -> float:
        """Duration of one sweep (s)."""
        return 1.0 / self.rate_hz


def _asc(values) -> tuple:
    return tuple(float(v) for v in sorted(values))


VLP16 = _asc(range(-15, 16, 2))
VLP32C = _asc([-25.0, -15.639, -11.31, -8.843, -7.254, -6.148, -5.333, -4.667, -4.0, -3.667, -3.333, -3.0, -2.667,
               -2.333, -2.0, -1.667, -1.333, -1.0, -0.667, -0.333, 0.0, 0.333, 0.667, 1.0, 1.333, 1.667, 2.333,
               3.333, 4.667, 7.0, 10.333, 15.0])
HDL32E = _asc([-30.67, -29.33, -28.0, -26.67, -25.33, -24.0, -22.67, -21.33, -20.0, -18.67, -17.33, -16.0, -14.67,
               -13.33, -12.0, -10.67, -9.33, -8.0, -6.67, -5.33, -4.0, -2.67, -1.33, 0.0, 1.33, 2.67, 4.0, 5.33, 6.67,
               8.0, 9.33, 10.67])
HDL64E = _asc([-24.711, -24.2763, -23.763, -23.2502, -22.7379, -22.2261, -21.7147, -21.2037, -20.693, -20.1827,
               -19.6726, -19.1627, -18.5578, -18.1435, -17.6341, -17.1247, -16.6153, -16.1059, -15.5965, -15.087,
               -14.5773, -14.0674, -13.5573, -13.047, -12.5363, -12.0253, -11.5139, -11.0021, -10.4898, -9.977,
               -9.4637, -8.9497, -8.5208, -8.1799, -7.8391, -7.4986, -7.1581, -6.8178, -6.4777, -6.1376, -5.7976,
               -5.4578, -5.118, -4.7783, -4.4386, -4.099, -3.7594, -3.4198, -3.0802, -2.7406, -2.401, -2.0614,
               -1.7217, -1.382, -1.0422, -0.7024, -0.3624, -0.0223, 0.3178, 0.6581, 0.9986, 1.3391, 1.6799, 2.0208])
# Ouster beam altitudes from ouster-sdk's test metadata (tests/pcaps/*.json, 1024x10): 128-beam optics per
# family; the 64- and 32-beam uniform variants take every 2nd / 4th beam of the same optics; OS1-32G is the
# shipped gradient table of OS-1-32-G (dense near the horizon).
OS0_128 = _asc([45.75, 44.7, 43.93, 43.47, 42.72, 41.68, 40.94, 40.46, 39.7, 38.69, 37.95, 37.47, 36.71, 35.72, 35,
                34.51, 33.74, 32.78, 32.06, 31.56, 30.8, 29.85, 29.13, 28.62, 27.86, 26.93, 26.23, 25.7, 24.93, 24.03,
                23.33, 22.79, 22.03, 21.16, 20.46, 19.91, 19.13, 18.3, 17.6, 17.04, 16.27, 15.45, 14.76, 14.19, 13.41,
                12.62, 11.94, 11.34, 10.55, 9.81, 9.13, 8.51, 7.71, 6.99, 6.31, 5.68, 4.87, 4.17, 3.5, 2.86, 2.06,
                1.37, 0.71, 0.04, -0.77, -1.43, -2.09, -2.77, -3.6, -4.23, -4.9, -5.6, -6.43, -7.05, -7.71, -8.43,
                -9.24, -9.85, -10.51, -11.28, -12.07, -12.65, -13.34, -14.1, -14.91, -15.48, -16.16, -16.95, -17.77,
                -18.32, -18.99, -19.8, -20.62, -21.17, -21.84, -22.68, -23.5, -24.02, -24.7, -25.56, -26.39, -26.9,
                -27.57, -28.46, -29.29, -29.78, -30.47, -31.36, -32.21, -32.68, -33.37, -34.29, -35.14, -35.6,
                -36.29, -37.24, -38.11, -38.55, -39.24, -40.21, -41.08, -41.51, -42.23, -43.22, -44.09, -44.52,
                -45.24, -46.26])
OS1_128 = _asc([20.95, 20.67, 20.36, 20.03, 19.73, 19.41, 19.11, 18.76, 18.47, 18.14, 17.82, 17.5, 17.19, 16.86, 16.53,
                16.2, 15.89, 15.56, 15.23, 14.9, 14.57, 14.23, 13.9, 13.57, 13.25, 12.91, 12.57, 12.22, 11.9, 11.55,
                11.2, 10.87, 10.54, 10.18, 9.84, 9.51, 9.15, 8.81, 8.47, 8.11, 7.78, 7.43, 7.08, 6.74, 6.39, 6.04, 5.7,
                5.34, 4.98, 4.64, 4.29, 3.93, 3.58, 3.24, 2.88, 2.53, 2.17, 1.82, 1.47, 1.12, 0.78, 0.41, 0.07, -0.28,
                -0.64, -0.99, -1.35, -1.7, -2.07, -2.4, -2.75, -3.11, -3.46, -3.81, -4.15, -4.5, -4.86, -5.22, -5.57,
                -5.9, -6.27, -6.61, -6.97, -7.3, -7.67, -8.01, -8.35, -8.69, -9.05, -9.38, -9.71, -10.07, -10.42,
                -10.76, -11.09, -11.43, -11.78, -12.12, -12.46, -12.78, -13.15, -13.46, -13.8, -14.12, -14.48, -14.79,
                -15.11, -15.46, -15.79, -16.12, -16.45, -16.76, -17.11, -17.44, -17.74, -18.06, -18.39, -18.72,
                -19.02, -19.32, -19.67, -19.99, -20.27, -20.57, -20.92, -21.22, -21.54, -21.82])
OS2_128 = _asc([10.76, 10.58, 10.42, 10.24, 10.1, 9.93, 9.76, 9.57, 9.41, 9.24, 9.09, 8.91, 8.75, 8.57, 8.41, 8.23,
                8.08, 7.9, 7.74, 7.55, 7.39, 7.21, 7.03, 6.86, 6.7, 6.53, 6.35, 6.18, 6.02, 5.83, 5.67, 5.5, 5.32, 5.14,
                4.97, 4.81, 4.63, 4.46, 4.28, 4.11, 3.95, 3.76, 3.58, 3.43, 3.24, 3.07, 2.9, 2.72, 2.55, 2.37, 2.21,
                2.03, 1.87, 1.69, 1.51, 1.32, 1.16, 0.98, 0.81, 0.63, 0.46, 0.29, 0.11, -0.05, -0.25, -0.42, -0.58,
                -0.76, -0.93, -1.11, -1.28, -1.45, -1.63, -1.81, -1.97, -2.16, -2.32, -2.5, -2.68, -2.85, -3.02, -3.19,
                -3.37, -3.55, -3.73, -3.9, -4.07, -4.25, -4.4, -4.58, -4.75, -4.94, -5.11, -5.28, -5.46, -5.64, -5.8,
                -5.96, -6.15, -6.32, -6.49, -6.66, -6.84, -7, -7.17, -7.35, -7.51, -7.69, -7.86, -8.04, -8.22, -8.38,
                -8.55, -8.72, -8.89, -9.06, -9.23, -9.4, -9.57, -9.74, -9.91, -10.07, -10.24, -10.41, -10.58, -10.75,
                -10.92, -11.09])
OS1_32G = _asc([12.75, 10.03, 7.27, 4.47, 3.41, 2.35, 2.02, 1.65, 1.29, 0.93, 0.6, 0.23, -0.13, -0.49, -0.83, -1.17,
                -1.54, -1.88, -2.24, -2.6, -2.96, -3.65, -4.36, -5.06, -5.76, -7.17, -8.57, -9.95, -11.31, -12.66,
                -14.01, -15.32])
XT32 = _asc(range(-16, 16))


def _ouster(family: str, table: tuple, beams: int, max_range: float, noise: float, suffix: str = "") -> SensorModel:
    step = len(table) // beams
    return SensorModel(f"OS{family}-{beams}{suffix}", table if suffix else table[step // 2::step], 1024, 10.0,
                       0.3, max_range, noise, "ouster")


def _models() -> dict[str, SensorModel]:
    models = [
        SensorModel("VLP-16", VLP16, 1800, 10.0, 0.9, 100.0, 0.015, "velodyne"),
        SensorModel("VLP-32C", VLP32C, 1800, 10.0, 0.9, 200.0, 0.015, "velodyne"),
        SensorModel("HDL-32E", HDL32E, 2176, 10.0, 1.0, 100.0, 0.01, "velodyne"),
        SensorModel("HDL-64E", HDL64E, 2088, 10.0, 1.0, 120.0, 0.01, "velodyne"),
        SensorModel("XT32", XT32, 2000, 10.0, 0.05, 120.0, 0.01, "hesai"),
        SensorModel("Mid-360", (), 200, 10.0, 0.1, 70.0, 0.02, "livox", pattern="non_repetitive",
                    fov_deg=(-7.0, 52.0), grid_rows=32, points_per_scan=20000),
        _ouster("1", OS1_32G, 32, 120.0, 0.015, "G"),
    ]
    for family, table, max_range, noise in (("0", OS0_128, 55.0, 0.015), ("1", OS1_128, 120.0, 0.015),
                                            ("2", OS2_128, 240.0, 0.02)):
        models += [_ouster(family, table, beams, max_range, noise) for beams in (32, 64, 128)]
    return {m.name: m for m in models}


SENSORS = _models()
DEFAULT_SENSOR = "VLP-32C"


def sensor(name: str) -> SensorModel:
    """The model called ``name`` (case-insensitive), or a ValueError listing the known ones."""
    for key, model in SENSORS.items():
        if key.lower() == str(name).lower():
            return model
    raise ValueError(f"unknown sensor {name!r}; known: {', '.join(SENSORS)}")


def layout_of(field_names) -> DriverLayout | None:
    """The driver layout whose fields a cloud has (its time field decides), or None."""
    names = set(field_names)
    for layout in LAYOUTS.values():
        if {f[0] for f in layout.fields} <= names:
            return layout
    return None


def layout_pattern(name: str) -> str:
    """The scan pattern ('spinning', 'non_repetitive') of the sensors that driver layout ``name`` serves, '' when
    the layout is unknown."""
    layout = LAYOUTS.get(name)
    return layout.pattern if layout is not None else ""
