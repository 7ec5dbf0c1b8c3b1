"""Frames, the odometry buffer and the sliding window of scans.

A Frame is one scan with the pose SLAM gave it. PoseBuffer gives a scan the odometry pose interpolated at
its stamp; SlidingWindow groups processed scans into windows of ``size`` every ``step`` scans (or of about a
second of scans, the size set from the stream's own stamps).
"""
from __future__ import annotations

import bisect
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from . import geometry


@dataclass
class Frame:
    """One LiDAR scan and its pose.

    points: (N, 3) float32, sensor frame, metres, all finite.
    pose: (4, 4) float64, sensor-to-map.
    stamp: seconds (header stamp of the cloud).
    labels: optional (N,) uint8 class ids (classes.py), e.g. the simulator's ground truth.
    ring: optional (N,) beam id as the cloud gives it (ring field, else the organised row; grid.py orders
    them by elevation), intensity: optional (N,) float32.
    time: optional (N,) float32 s of each point relative to ``stamp``; columns: firings per revolution of an
    organised cloud (0 = unknown); motion: deskew.SweepMotion when the points are to be deskewed; layout: the
    cloud's driver layout name (sensors.LAYOUTS, '' unknown).
    """

    points: np.ndarray
    pose: np.ndarray
    stamp: float
    labels: np.ndarray | None = None
    ring: np.ndarray | None = None
    intensity: np.ndarray | None = None
    time: np.ndarray | None = None
    columns: int = 0
    motion: Any = None
    layout: str = ""

    def __len__(self) -> int:
        return len(self.points)


class PoseBuffer:
    """Odometry poses by stamp, for looking up the pose of a scan at its own stamp (TF-free).

    Poses are 4×4 child-to-parent (e.g. base_link-to-map); stamps in seconds and strictly increasing.
    Only the last ``horizon_s`` seconds are kept, so memory stays bounded.
    """

    def __init__(self, horizon_s: float = 30.0):
        self.horizon_s = float(horizon_s)
        self._stamps: list[float] = []
        self._poses: list[np.ndarray] = []

    def __len__(self) -> int:
        return len(self._stamps)

    @property
    def newest(self) -> float | None:
        """Stamp (s) of the newest pose, None when empty."""
        return self._stamps[-1] if self._stamps else None

    @property
    def oldest(self) -> float | None:
        return self._stamps[0] if self._stamps else None

    def clear(self) -> None:
        self._stamps.clear()
        self._poses.clear()

    def add(self, stamp: float, pose: np.ndarray) -> str:
        """Append a pose. Returns 'ok', 'duplicate' (same stamp as the newest: ignored) or 'backwards'
        (older than the newest: the buffer restarts from this pose, a time jump)."""
        stamp = float(stamp)
        status = "ok"
        if self._stamps and stamp == self._stamps[-1]:
            return "duplicate"
        if self._stamps and stamp < self._stamps[-1]:
            self.clear()
            status = "backwards"
        self._stamps.append(stamp)
        self._poses.append(np.asarray(pose, np.float64))
        cut = 0
        while cut < len(self._stamps) - 2 and self._stamps[cut + 1] < stamp - self.horizon_s:
            cut += 1
        if cut:
            del self._stamps[:cut], self._poses[:cut]
        return status

    def lookup(self, stamp: float, max_gap_s: float, extrapolate_s: float = 0.0) -> np.ndarray | None:
        """Pose at ``stamp`` interpolated between the poses around it (slerp + linear), or None when the
        stamp is outside the buffer or either neighbour is more than ``max_gap_s`` away. Up to
        ``extrapolate_s`` past the newest pose, the last two poses' motion is continued (constant velocity)."""
        poses = self.lookup_many(np.array([stamp]), max_gap_s, extrapolate_s)
        return None if poses is None else poses[0]

    def lookup_many(self, stamps: np.ndarray, max_gap_s: float, extrapolate_s: float = 0.0) -> np.ndarray | None:
        """(K, 4, 4) poses at ``stamps`` (s), each as :meth:`lookup` says, in one vectorised pass (a sweep's knots:
        many small lookups are slow under the GIL of a busy node); None when any of them is missing."""
        t = np.asarray(stamps, np.float64).reshape(-1)
        if not self._stamps or len(t) == 0:
            return None
        newest = self._stamps[-1]
        ahead = (t > newest) & (t <= newest + extrapolate_s) if extrapolate_s > 0 else np.zeros(len(t), bool)
        out = np.empty((len(t), 4, 4))
        if ahead.any():
            moved = self._extrapolate(t[ahead], max_gap_s)
            if moved is None:
                return None
            out[ahead] = moved
        inside = t[~ahead]
        if len(inside) == 0:
            return out
        if inside.min() < self._stamps[0] or inside.max() > newest:
            return None
        lo = bisect.bisect_right(self._stamps, float(inside.min())) - 1
        hi = min(bisect.bisect_right(self._stamps, float(inside.max())) + 1, len(self._stamps))
        st, poses = np.array(self._stamps[lo:hi]), np.stack(self._poses[lo:hi])
        i = np.searchsorted(st, inside, side="right") - 1
        exact = st[i] == inside
        j = np.minimum(i + 1, len(st) - 1)
        if np.any(~exact & ((inside - st[i] > max_gap_s) | (st[j] - inside > max_gap_s))):
            return None
        found = poses[i].copy()  # an exact hit needs no neighbour
        if not exact.all():
            found[~exact] = geometry.interpolate_poses(st, poses, inside[~exact])[0]
        out[~ahead] = found
        return out

    def _extrapolate(self, stamps: np.ndarray, max_gap_s: float) -> np.ndarray | None:
        """(K, 4, 4): the newest pose moved on by the last step's motion, scaled to each of ``stamps`` (K,) s;
        None without two poses within max_gap_s."""
        if len(self._stamps) < 2 or self._stamps[-1] - self._stamps[-2] > max_gap_s:
            return None
        a, b = self._poses[-2], self._poses[-1]
        step = geometry.inverse(a) @ b
        u = (stamps - self._stamps[-1]) / (self._stamps[-1] - self._stamps[-2])
        rot = geometry.rotvec_to_matrix(u[:, None] * geometry.matrix_to_rotvec(step[:3, :3]))
        return b @ geometry.make_pose(rot, u[:, None] * step[:3, 3])


#: Stamps that give an automatic window size the stream's scan period (AUTO_PROBE when their intervals are
#: even, up to AUTO_PROBE_MAX when not), and the fewest and most scans such a window holds (config.RANGES: 200).
AUTO_PROBE, AUTO_PROBE_MAX, AUTO_MIN, AUTO_MAX = 3, 6, 3, 200
#: Intervals longer than this × the median are taken for dropped scans when the period is read.
DROPPED = 1.5


class SlidingWindow:
    """Consecutive items (processed scans) grouped into windows of ``size`` that start every ``step`` items.

    ``size`` 0: automatic, the scans of ``duration_s`` seconds at the stream's scan rate, set once from the
    first AUTO_PROBE stamps (round(duration_s / period), AUTO_MIN to AUTO_MAX scans; the period: the median of
    their intervals within DROPPED × their median, so neither a dropped scan nor stamp jitter moves it much).
    Three stamps cannot tell a dropped scan from jitter, so uneven ones (one interval over DROPPED × another)
    wait for more, up to AUTO_PROBE_MAX; a window smaller than the scans held then starts at the newest ones.
    Until then ``size`` is None. ``push`` returns the completed window (a list) when the pushed item is a
    window's last, else None. An item whose stamp is not newer than the previous one (bag loop, sim time reset,
    duplicate) restarts the window: the partial window is discarded and counted in ``discarded``.
    """

    def __init__(self, size: int, step: int = 0, duration_s: float = 1.0):
        if size < 0:
            raise ValueError(f"window size must be 0 (automatic) or >= 1, got {size}")
        if step < 0:
            raise ValueError(f"window step must be >= 0 (0 = size), got {step}")
        if size == 0 and not duration_s > 0:
            raise ValueError(f"an automatic window needs a duration > 0 s, got {duration_s}")
        self.duration_s, self._step = float(duration_s), int(step)
        self.size: int | None = int(size) or None
        self.step: int | None = int(step or size) or None
        self.scan_period_s: float | None = None  # automatic size: the stream's scan period (s) it was set from
        self._probe: list[float] = []  # automatic size: the stamps so far, until it is set
        self._items: deque = deque()
        self._skip = 0  # items still to skip before the next window starts (step > size)
        self._last_stamp: float | None = None
        self.discarded = 0  # partial windows thrown away by resets
        self.resets = 0

    def __len__(self) -> int:
        return len(self._items)

    def reset(self) -> None:
        if self._items:
            self.discarded += 1
        self._items.clear()
        self._probe.clear()
        self._skip = 0
        self._last_stamp = None

    def push(self, item, stamp: float) -> list | None:
        stamp = float(stamp)
        if self._last_stamp is not None and stamp <= self._last_stamp:
            self.resets += 1
            self.reset()
        self._last_stamp = stamp
        if self._skip:
            self._skip -= 1
            return None
        self._items.append(item)
        if self.size is None:
            self._set_size(stamp)
        if self.size is None or len(self._items) < self.size:
            return None
        window = list(self._items)
        drop = min(self.step, self.size)
        for _ in range(drop):
            self._items.popleft()
        self._skip = self.step - drop
        return window

    def describe(self) -> str:
        """The window in words: "10 scans (automatic: 1 s at 10 Hz)", "5 scans", or, automatic and not set yet,
        "automatic: 1 s of scans, set from the first 3 scans' stamps (up to 6 when uneven)"."""
        if self.size is None:
            return (f"automatic: {self.duration_s:g} s of scans, set from the first {AUTO_PROBE} scans' stamps "
                    f"(up to {AUTO_PROBE_MAX} when uneven)")
        auto = ""
        if self.scan_period_s:
            natural = round(self.duration_s / self.scan_period_s)  # before the clip to AUTO_MIN .. AUTO_MAX
            bound = (f", at least {AUTO_MIN}" if natural < AUTO_MIN else f", at most {AUTO_MAX}" if natural > AUTO_MAX
                     else "")
            auto = f" (automatic: {self.duration_s:g} s at {1 / self.scan_period_s:.3g} Hz{bound})"
        every = f", one every {self.step} scans" if self.step != self.size else ""
        return f"{self.size} scans{auto}{every}"

    def _set_size(self, stamp: float) -> None:
        """Automatic size: collect the stamp; at AUTO_PROBE even stamps (or AUTO_PROBE_MAX uneven ones), set the
        scan period, size and step (when 0)."""
        self._probe.append(stamp)
        gaps = np.diff(self._probe)
        if len(self._probe) < AUTO_PROBE or (len(self._probe) < AUTO_PROBE_MAX and gaps.max() > DROPPED * gaps.min()):
            return  # too few stamps, or uneven ones: a dropped scan or stamp jitter, which more stamps tell apart
        self.scan_period_s = float(np.median(gaps[gaps <= DROPPED * np.median(gaps)]))
        size = int(np.clip(round(self.duration_s / self.scan_period_s), AUTO_MIN, AUTO_MAX))
        while len(self._items) > size:  # the probe held more scans than the window: it starts at the newest
            self._items.popleft()
        self.step = self._step or size  # before size: another thread's describe() reads step once size is set
        self.size = size
        self._probe.clear()
