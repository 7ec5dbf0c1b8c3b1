"""Procedural indoor scenes as triangle meshes with per-triangle class and plane-instance ids.

Every surface is planar: a box has six faces, each its own plane instance, so every triangle belongs to
one instance whose plane (n · x + d = 0, map frame, metres) is known exactly. Scenes (all seeded):
``floor2`` an office floor (rooms off a corridor, doors, desks, chairs, pillars, clutter), ``office1`` and
``office2`` single office rooms, ``garage`` an underground car park of ~14,000 m² (pillar grid, cars,
ramps, a lift core, semi-dynamic tables and chairs).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .. import classes as C

SCENES = ("floor2", "garage", "office1", "office2")
#: Obstacles that touch this height band (m above floor) block the robot.
ROBOT_BAND = (0.05, 1.6)


@dataclass
class Scene:
    """A static world. All coordinates in the map frame, metres."""

    name: str
    vertices: np.ndarray  # (V, 3) float32
    triangles: np.ndarray  # (T, 3) int32
    tri_class: np.ndarray  # (T,) uint8, classes.* ids
    tri_instance: np.ndarray  # (T,) int32 plane instance id
    planes: np.ndarray  # (I, 4) float64: unit normal and offset d of each instance
    instance_class: np.ndarray  # (I,) uint8
    bounds: tuple[float, float, float, float]  # xmin, ymin, xmax, ymax
    footprints: list = field(repr=False, default_factory=list)  # (4, 2) rectangles blocking the robot

    @property
    def area(self) -> float:
        xmin, ymin, xmax, ymax = self.bounds
        return (xmax - xmin) * (ymax - ymin)


class SceneBuilder:
    """Collects planar quads and boxes, then builds a :class:`Scene`."""

    def __init__(self, name: str, bounds: tuple[float, float, float, float]):
        self.name, self.bounds = name, bounds
        self._verts: list[np.ndarray] = []
        self._tris: list[np.ndarray] = []
        self._tri_cls: list[int] = []
        self._tri_inst: list[int] = []
        self._planes: list[np.ndarray] = []
        self._inst_cls: list[int] = []
        self._nverts = 0
        self.footprints: list[np.ndarray] = []

    def polygon(self, corners: np.ndarray, cls: int) -> int:
        """A planar convex polygon (K, 3), fan-triangulated, as one plane instance; returns its id."""
        corners = np.asarray(corners, float)
        n = np.cross(corners[1] - corners[0], corners[2] - corners[0])
        n /= np.linalg.norm(n)
        inst = len(self._planes)
        self._planes.append(np.append(n, -n @ corners[0]))
        self._inst_cls.append(cls)
        k = len(corners)
        fan = np.stack([np.zeros(k - 2, int), np.arange(1, k - 1), np.arange(2, k)], axis=1) + self._nverts
        self._verts.append(corners)
        self._tris.append(fan)
        self._tri_cls += [cls] * (k - 2)
        self._tri_inst += [inst] * (k - 2)
        self._nverts += k
        return inst

    def box(self, lo, hi, cls: int, yaw: float = 0.0, blocks: bool = True) -> None:
        """An axis-aligned box from corner lo to hi (m), turned by yaw (rad) about its vertical axis."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        c = (lo + hi) / 2
        x0, y0, z0 = lo - c
        x1, y1, z1 = hi - c
        v = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
                      [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]])
        cy, sy = np.cos(yaw), np.sin(yaw)
        v = v @ np.array([[cy, sy, 0], [-sy, cy, 0], [0, 0, 1]]) + c
        for f in ((0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)):
            self.polygon(v[list(f)], cls)
        if blocks and lo[2] < ROBOT_BAND[1] and hi[2] > ROBOT_BAND[0]:
            self.footprints.append(v[:4, :2])

    def prism(self, center, radius: float, z0: float, z1: float, cls: int, sides: int = 8) -> None:
        """A vertical regular prism (round things: people, bins, round pillars)."""
        a = np.linspace(0, 2 * np.pi, sides, endpoint=False)
        ring = np.stack([center[0] + radius * np.cos(a), center[1] + radius * np.sin(a)], 1)
        bottom, top = np.c_[ring, np.full(sides, z0)], np.c_[ring, np.full(sides, z1)]
        self.polygon(top, cls)
        self.polygon(bottom[::-1], cls)
        for i in range(sides):
            j = (i + 1) % sides
            self.polygon(np.array([bottom[i], bottom[j], top[j], top[i]]), cls)
        if z0 < ROBOT_BAND[1] and z1 > ROBOT_BAND[0]:
            r = radius
            self.footprints.append(np.array(center[:2]) + np.array([[-r, -r], [r, -r], [r, r], [-r, r]]))

    def floor_and_ceiling(self, height: float) -> None:
        xmin, ymin, xmax, ymax = self.bounds
        self.polygon(np.array([[xmin, ymin, 0], [xmax, ymin, 0], [xmax, ymax, 0], [xmin, ymax, 0]]), C.FLOOR)
        self.polygon(np.array([[xmin, ymin, height], [xmin, ymax, height], [xmax, ymax, height],
                               [xmax, ymin, height]]), C.CEILING)

    def wall(self, p0, p1, height: float, doors=(), thickness: float = 0.15, door_height: float = 2.1) -> None:
        """A straight wall from p0 to p1 (x, y), axis-aligned, with door gaps [(s0, s1)] along it (m)."""
        p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
        length = np.linalg.norm(p1 - p0)
        u = (p1 - p0) / length
        nrm = np.array([-u[1], u[0]]) * thickness / 2
        cuts = [0.0] + [s for d in sorted(doors) for s in d] + [length]
        for s0, s1 in zip(cuts[0::2], cuts[1::2]):
            if s1 - s0 > 1e-3:
                self._wall_piece(p0 + u * s0, p0 + u * s1, nrm, 0.0, height)
        for s0, s1 in sorted(doors):  # lintel above each door
            self._wall_piece(p0 + u * s0, p0 + u * s1, nrm, door_height, height, blocks=False)

    def _wall_piece(self, a, b, nrm, z0, z1, blocks=True):
        corners = np.array([a - nrm, b - nrm, b + nrm, a + nrm])
        self.box(np.r_[corners.min(0), z0], np.r_[corners.max(0), z1], C.WALL, blocks=blocks)

    def build(self) -> Scene:
        return Scene(self.name, np.concatenate(self._verts).astype(np.float32),
                     np.concatenate(self._tris).astype(np.int32), np.asarray(self._tri_cls, np.uint8),
                     np.asarray(self._tri_inst, np.int32), np.asarray(self._planes),
                     np.asarray(self._inst_cls, np.uint8), self.bounds, self.footprints)


def _desk_set(b: SceneBuilder, x: float, y: float, yaw: float, rng: np.random.Generator) -> None:
    """A desk (top and four legs) with a chair in front of it; (x, y) is the desk centre."""
    w, dpt, h = rng.uniform(1.2, 1.6), rng.uniform(0.6, 0.8), rng.uniform(0.72, 0.76)
    cy, sy = np.cos(yaw), np.sin(yaw)
    rot = np.array([[cy, -sy], [sy, cy]])
    b.box([x - w / 2, y - dpt / 2, h - 0.04], [x + w / 2, y + dpt / 2, h], C.DESK, yaw)
    for lx, ly in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
        px, py = np.array([x, y]) + rot @ [lx * (w / 2 - 0.05), ly * (dpt / 2 - 0.05)]
        b.box([px - 0.025, py - 0.025, 0], [px + 0.025, py + 0.025, h - 0.04], C.DESK, yaw)
    if rng.random() < 0.9:
        cx, cyy = np.array([x, y]) + rot @ [rng.uniform(-0.3, 0.3), -(dpt / 2 + rng.uniform(0.25, 0.5))]
        _chair(b, cx, cyy, yaw + rng.uniform(-0.6, 0.6))


def _chair(b: SceneBuilder, x: float, y: float, yaw: float) -> None:
    cy, sy = np.cos(yaw), np.sin(yaw)
    b.box([x - 0.23, y - 0.23, 0.42], [x + 0.23, y + 0.23, 0.48], C.CHAIR, yaw)
    bx, by = x - 0.22 * sy, y - 0.22 * cy  # back rest behind the seat
    b.box([bx - 0.22, by - 0.03, 0.5], [bx + 0.22, by + 0.03, 0.95], C.CHAIR, yaw)
    b.box([x - 0.03, y - 0.03, 0.0], [x + 0.03, y + 0.03, 0.42], C.CHAIR, yaw)
    b.box([x - 0.3, y - 0.3, 0.0], [x + 0.3, y + 0.3, 0.05], C.CHAIR, yaw)


def _clutter(b: SceneBuilder, x: float, y: float, rng: np.random.Generator) -> None:
    """Something of class other: a person, a bin, a cabinet or a plant pot."""
    kind = rng.integers(4)
    if kind == 0:
        b.prism((x, y), 0.22, 0.0, rng.uniform(1.6, 1.9), C.OTHER, sides=10)
    elif kind == 1:
        b.prism((x, y), 0.18, 0.0, 0.6, C.OTHER)
    elif kind == 2:
        b.box([x - 0.25, y - 0.45, 0], [x + 0.25, y + 0.45, rng.uniform(1.2, 1.9)], C.OTHER, rng.uniform(0, np.pi))
    else:
        b.prism((x, y), 0.25, 0.0, 0.45, C.OTHER, sides=6)
        b.prism((x, y), 0.35, 0.45, 1.2, C.OTHER, sides=6)


def _pillar(b: SceneBuilder, x: float, y: float, height: float, half: float = 0.3) -> None:
    b.box([x - half, y - half, 0], [x + half, y + half, height], C.PILLAR)


def _furnish(b: SceneBuilder, rng: np.random.Generator, x0, y0, x1, y1, keep_free_y=None, n_other=3) -> None:
    """Rows of desks with chairs, clutter and sometimes a free-standing pillar in a room [x0, x1]×[y0, y1].

    keep_free_y: a y interval kept clear (the side of the room where its door is).
    """
    ylo, yhi = y0 + 1.2, y1 - 1.2
    if keep_free_y is not None:
        ylo, yhi = (max(ylo, keep_free_y[1]), yhi) if keep_free_y[0] <= y0 + 0.1 else (ylo, min(yhi, keep_free_y[0]))
    rows = np.arange(ylo, yhi, 2.6)
    for ry in rows:
        for rx in np.arange(x0 + 1.4, x1 - 1.4, rng.uniform(1.7, 2.4)):
            if rng.random() < 0.75:
                _desk_set(b, rx, ry, rng.choice([0.0, np.pi]) + rng.normal(0, 0.05), rng)
    for _ in range(n_other):
        side = rng.integers(2)
        x = rng.uniform(x0 + 0.5, x1 - 0.5)
        y = y0 + 0.45 if side == 0 else y1 - 0.45
        if keep_free_y is None or not (keep_free_y[0] - 0.5 <= y <= keep_free_y[1] + 0.5):
            _clutter(b, x, y, rng)
    if (x1 - x0) * (y1 - y0) > 60:
        _pillar(b, rng.uniform(x0 + 2, x1 - 2), (y0 + y1) / 2 + rng.uniform(-0.5, 0.5), 3.0, 0.25)


def office_floor(seed: int = 0, height: float = 3.0) -> Scene:
    """floor2: rooms on both sides of a 3 m corridor, a door into every room, ~48 × 20 m."""
    rng = np.random.default_rng(seed)
    length, width = float(rng.uniform(40, 56)), 20.0
    b = SceneBuilder("floor2", (0.0, 0.0, length, width))
    b.floor_and_ceiling(height)
    yc0, yc1 = width / 2 - 1.5, width / 2 + 1.5
    for p0, p1 in (((0, 0), (length, 0)), ((length, 0), (length, width)), ((length, width), (0, width)),
                   ((0, width), (0, 0))):
        b.wall(p0, p1, height)
    for side, (ya, yb, ywall) in enumerate(((0.0, yc0, yc0), (yc1, width, yc1))):
        splits = [0.0]
        while splits[-1] < length - 6:
            splits.append(min(splits[-1] + rng.uniform(6, 10), length))
        splits[-1] = length
        doors = []
        for xa, xb in zip(splits[:-1], splits[1:]):
            if xa > 0:
                b.wall((xa, ya), (xa, yb), height)
                _pillar(b, xa, ywall, height, 0.35)  # structural pillar at the corridor wall line
            s = rng.uniform(xa + 0.6, xb - 1.8)
            doors.append((s, s + 1.2))
            door_side = (yb - 1.5, yb) if side == 0 else (ya, ya + 1.5)
            _furnish(b, rng, xa + 0.1, ya + 0.1, xb - 0.1, yb - 0.1, keep_free_y=door_side)
        b.wall((0, ywall), (length, ywall), height, doors=doors)
    for _ in range(int(length / 8)):  # people and bins in the corridor, near its walls
        _clutter(b, rng.uniform(2, length - 2), rng.choice([yc0 + 0.4, yc1 - 0.4]), rng)
    return b.build()


def office_room(name: str = "office1", seed: int = 0, height: float = 2.9) -> Scene:
    """office1 / office2: one room with desks, chairs, pillars and clutter (office2 is larger)."""
    rng = np.random.default_rng(seed + (0 if name == "office1" else 1000))
    lx, ly = (rng.uniform(11, 13), rng.uniform(8, 10)) if name == "office1" else (rng.uniform(15, 18), rng.uniform(10, 12))
    b = SceneBuilder(name, (0.0, 0.0, lx, ly))
    b.floor_and_ceiling(height)
    b.wall((0, 0), (lx, 0), height)
    b.wall((lx, 0), (lx, ly), height)
    b.wall((lx, ly), (0, ly), height)
    b.wall((0, ly), (0, 0), height, doors=[(ly / 2 - 0.5, ly / 2 + 0.5)])
    _furnish(b, rng, 0.1, 0.1, lx - 0.1, ly - 0.1, n_other=5)
    _pillar(b, lx * rng.uniform(0.3, 0.4), ly / 2, height)
    _pillar(b, lx * rng.uniform(0.6, 0.7), ly / 2, height)
    return b.build()


def garage(seed: int = 0, height: float = 3.2) -> Scene:
    """An underground car park, 120 × 116 m: pillar grid every 8 m, parking bays with cars, driving lanes,
    two ramps along the walls, a lift core, and a few groups of tables and chairs."""
    rng = np.random.default_rng(seed + 2000)
    lx, ly = 120.0, 116.0
    b = SceneBuilder("garage", (0.0, 0.0, lx, ly))
    b.floor_and_ceiling(height)
    for p0, p1 in (((0, 0), (lx, 0)), ((lx, 0), (lx, ly)), ((lx, ly), (0, ly)), ((0, ly), (0, 0))):
        b.wall(p0, p1, height)
    # Period of 16 m in y: lane 6 m, bays 5 m, pillar line, bays 5 m.
    for y_line in np.arange(14.0, ly - 8, 16.0):
        for x in np.arange(8.0, lx - 4, 8.0):
            _pillar(b, x, y_line, height, 0.3)
            for k in range(3):  # three bays between pillars, both sides of the pillar line
                cx = x + 0.3 + 1.25 + k * 2.47
                if cx > lx - 4:
                    continue
                for side in (-1, 1):
                    if rng.random() < 0.65:
                        _car(b, cx, y_line + side * 2.6, rng)
    for x0 in (4.0, lx - 20.0):  # ramps along the north wall, with side walls
        _ramp(b, x0, ly - 5.5, 16.0, 4.0, 1.6)
    core = (lx / 2 - 3, ly / 2 + 3.5)  # lift and stair core in a lane
    b.box([core[0], core[1], 0], [core[0] + 6, core[1] + 4, height], C.WALL)
    for y_lane in np.arange(6.0, ly - 8, 16.0):  # semi-dynamic furniture: tables with chairs at lane ends
        x, y = rng.choice([2.5, lx - 6.5]), y_lane + rng.uniform(-1.0, 1.0)
        _desk_set(b, x, y, rng.uniform(-0.2, 0.2), rng)
        _desk_set(b, x + 2.2, y, rng.uniform(-0.2, 0.2), rng)
        _chair(b, x + 1.1, y + 1.2, rng.uniform(0, 6.28))
    for _ in range(25):
        _clutter(b, rng.uniform(2, lx - 2), rng.uniform(2, ly - 2), rng)
    return b.build()


def _car(b: SceneBuilder, x: float, y: float, rng: np.random.Generator) -> None:
    """A car parked nose-in (class other): body and cabin boxes, length along y."""
    w, length = rng.uniform(1.7, 1.9), rng.uniform(4.2, 4.8)
    yaw = rng.normal(0, 0.03)
    b.box([x - w / 2, y - length / 2, 0.3], [x + w / 2, y + length / 2, 1.0], C.OTHER, yaw)
    b.box([x - w / 2 + 0.1, y - length / 4, 1.0], [x + w / 2 - 0.1, y + length / 4, rng.uniform(1.4, 1.6)],
          C.OTHER, yaw)
    for sx in (-1, 1):
        for sy in (-1, 1):
            wx, wy = x + sx * (w / 2 - 0.15), y + sy * (length / 2 - 0.8)
            b.box([wx - 0.1, wy - 0.3, 0.0], [wx + 0.1, wy + 0.3, 0.3], C.OTHER, yaw, blocks=False)


def _ramp(b: SceneBuilder, x0: float, y0: float, length: float, width: float, rise: float) -> None:
    """A straight ramp (floor class) rising along +x, with a wall on each side."""
    b.polygon(np.array([[x0, y0, 0], [x0 + length, y0, rise], [x0 + length, y0 + width, rise],
                        [x0, y0 + width, 0]]), C.FLOOR)
    b.box([x0, y0 - 0.2, 0], [x0 + length, y0, 1.0 + rise], C.WALL)
    b.box([x0, y0 + width, 0], [x0 + length, y0 + width + 0.2, 1.0 + rise], C.WALL)
    b.box([x0 + length, y0 - 0.2, 0], [x0 + length + 0.2, y0 + width + 0.2, 3.0], C.WALL)
    b.footprints.append(np.array([[x0, y0], [x0 + length, y0], [x0 + length, y0 + width], [x0, y0 + width]]))


def make_scene(name: str, seed: int = 0) -> Scene:
    """Scene by name (see SCENES); ``seed`` selects the layout, so a new seed is a new floor plan."""
    if name == "floor2":
        return office_floor(seed)
    if name in ("office1", "office2"):
        return office_room(name, seed)
    if name == "garage":
        return garage(seed)
    raise ValueError(f"unknown scene {name!r}; choose from {', '.join(SCENES)}")
