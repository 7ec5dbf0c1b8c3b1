"""rosbag2 I/O, no ROS install needed.

Reading streams message by message (MCAP or sqlite3, detected from the bag's files) through storage.py, which
keeps every message a damaged bag still holds and reads a bag folder without metadata.yaml; bags it does not
read (compressed bag files, ROS 1) go through rosbags. Messages deserialise with the ROS 2 Jazzy typestore.
Writing uses rosbags and Jazzy message definitions, MCAP by default. Odometry converts to (stamp s, 4×4 pose
child-to-parent).
"""
from __future__ import annotations

import json
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Iterable, Iterator, Sequence

import numpy as np

from . import geometry
from .cloud import make_header, stamp_seconds

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
ODOMETRY = "nav_msgs/msg/Odometry"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
STORAGES = ("mcap", "sqlite3")


class BagError(RuntimeError):
    """A bag that cannot be opened, or a topic that is missing from it."""


@lru_cache(maxsize=1)
def typestore() -> Any:
    """The ROS 2 Jazzy typestore (message definitions as Jazzy ships them)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def msg_types() -> SimpleNamespace:
    """Message classes of the Jazzy typestore, by short name (PointCloud2, Odometry, ...)."""
    t = typestore().types
    return SimpleNamespace(**{name.rsplit("/", 1)[-1]: cls for name, cls in t.items()})


def topics(path: str | Path | Sequence[str | Path]) -> dict[str, tuple[str, int]]:
    """{topic: (msgtype, message count)} of a bag (also of a damaged one, or one without metadata.yaml), or of
    several bags read as one (a list of paths)."""
    from . import storage

    if isinstance(path, (list, tuple)):
        table: dict[str, tuple[str, int]] = {}
        for p in path:
            for topic, (kind, n) in topics(p).items():
                table[topic] = (kind, table.get(topic, (kind, 0))[1] + n)
        return table
    check_bag(path)
    try:
        return storage.topic_table(path)
    except storage.Unsupported:
        pass
    with _opened(path) as reader:
        return {c.topic: (c.msgtype, c.msgcount) for c in reader.connections}


def unreadable(path: str | Path, topic: str) -> str:
    """Why ``topic`` cannot be read from a damaged bag whose metadata.yaml lists it ("" when the bag is whole or
    does not list it): the damage found and the listing."""
    from . import storage

    listed = storage.listed_topics(path)
    if topic not in listed:
        return ""
    log = storage.ReadLog()
    try:
        storage.topic_table(path, log)
    except storage.Unsupported:
        return ""
    if not log.summary():  # whole, only without this topic: not a damage
        return ""
    damage = list(dict.fromkeys(log.lines()))  # each note once
    return (f"{topic} cannot be read from {path}: its storage is damaged ({'; '.join(damage)}); "
            f"metadata.yaml lists {describe_topics(listed)}")


def unreadable_clouds(path: str | Path) -> str:
    """:func:`unreadable` for the first PointCloud2 topic the bag's metadata.yaml lists ("" when it lists none)."""
    from . import storage

    listed = [t for t, (kind, _) in sorted(storage.listed_topics(path).items()) if kind == POINTCLOUD2]
    return unreadable(path, listed[0]) if listed else ""


def not_a_bag(path: str | Path) -> str:
    """Why ``path`` is no rosbag2 bag (a bag folder, or a .mcap / .db3 file); "" when it is one."""
    from . import storage

    path = Path(path)
    if not path.exists():
        return f"bag not found: {path}"
    if path.is_dir() and not storage.is_bag_folder(path):
        return f"no rosbag2 bag at {path} (a bag folder has metadata.yaml and .mcap or .db3 files)"
    if path.is_file() and path.suffix not in (".mcap", ".db3"):
        return f"{path} is not a rosbag2 bag: give a bag folder or its .mcap or .db3 file"
    return ""


def check_bag(path: str | Path) -> None:
    """BagError unless ``path`` is a rosbag2 bag (not_a_bag says why)."""
    why = not_a_bag(path)
    if why:
        raise BagError(why)


def pick_topic(topics: dict[str, tuple[str, int]], msgtype: str, given: str = "", default: str = "",
               exclude: Iterable[str] = ()) -> tuple[str, str]:
    """(topic, note): ``given`` whenever one is given (a topic the user named is never swapped for another: the
    caller reports it missing); else ``default`` when the bag has it as a ``msgtype`` (a note names the other
    topics of that type); else the bag's only topic of ``msgtype`` (not in ``exclude``), with a note saying so;
    else ``default`` (the caller reports it missing)."""
    if given:
        return given, ""
    of_type = [t for t, (kind, _) in sorted(topics.items()) if kind == msgtype and t not in set(exclude)]
    if default in of_type:
        others = [t for t in of_type if t != default]
        return default, (f"using {default}; the bag has other {msgtype} topics too: {', '.join(others)} (name one "
                         f"to use it)" if others else "")
    if len(of_type) == 1:
        if default in set(exclude):
            return of_type[0], (f"{default} is named for another role: using the bag's only other {msgtype} topic "
                                f"{of_type[0]}")
        what = f"{default} is a {topics[default][0]}" if default in topics else f"no {default or 'topic'} in the bag"
        return of_type[0], f"{what}: using its only {msgtype} topic {of_type[0]}"
    return default, ""


def describe_topics(topics: dict[str, tuple[str, int]]) -> str:
    """'/a (type, n messages), ...' for a topic listing."""
    return ", ".join(f"{t} ({kind}, {n})" for t, (kind, n) in sorted(topics.items())) or "no topics"


@contextmanager
def _opened(path: str | Path) -> Iterator[Any]:
    """An open rosbags AnyReader; BagError when the bag cannot be opened."""
    from rosbags.highlevel import AnyReader

    path = Path(path)
    if not path.exists():
        raise BagError(f"bag not found: {path}")
    try:
        reader = AnyReader([path], default_typestore=typestore())
        reader.open()
    except Exception as e:  # rosbags raises several types for unreadable bags
        raise BagError(f"cannot open bag {path}: {e}") from e
    try:
        yield reader
    finally:
        reader.close()


def read_messages(path: str | Path | Sequence[str | Path], topic_names: Iterable[str] | None = None, log: Any = None,
                  strict: bool = True) -> Iterator[tuple[str, int, Any]]:
    """Yield (topic, receive time ns, deserialised message) in time order (per storage file), one at a time;
    of several bags read as one (a list of paths, e.g. a sidecar odometry bag beside the recording), merged in
    header-stamp order (each bag's receive times may be another clock).

    ``topic_names`` limits the topics; a named topic missing from the bag raises BagError (``strict``) or is
    left out. A damaged bag gives every message it still holds; ``log`` (a storage.ReadLog) says what was
    skipped, and counts messages that do not deserialise (skipped too).
    """
    from . import storage

    if isinstance(path, (list, tuple)):
        yield from _merged(path, topic_names, log, strict)
        return
    path = Path(path)
    check_bag(path)
    log = log if log is not None else storage.ReadLog()
    try:
        for file in storage.bag_files(path):
            storage.storage_of(file)
    except storage.Unsupported:
        yield from _rosbags_messages(path, topic_names, strict, log)
        return
    if topic_names is not None and strict:
        _check_topics(path, set(topic_names), set(topics(path)))
    store = typestore()
    for topic, msgtype, t_ns, raw in storage.read_raw(path, topic_names, log):
        try:
            msg = store.deserialize_cdr(raw, msgtype)
        except Exception:  # noqa: BLE001 - a damaged or unknown message is counted and skipped
            log.undecodable += 1
            continue
        yield topic, t_ns, msg


def _merged(paths: Sequence[str | Path], topic_names: Iterable[str] | None, log: Any, strict: bool
            ) -> Iterator[tuple[str, int, Any]]:
    """read_messages of several bags merged by the messages' header stamps (message_stamp_ns), the clock the
    Monitor pairs scans and poses on: each bag's receive times may be another clock (a recording's system
    time, a sidecar written at its stamps); ``strict`` checks the topics of all of them."""
    import heapq

    wanted = None if topic_names is None else set(topic_names)
    if wanted is not None and strict:
        _check_topics(", ".join(str(p) for p in paths), wanted, set(topics(paths)))
    streams = [read_messages(p, None if wanted is None else sorted(wanted & set(topics(p))), log, strict=False)
               for p in paths]
    yield from heapq.merge(*streams, key=message_stamp_ns)


def message_stamp_ns(message: tuple[str, int, Any]) -> int:
    """The header stamp (ns) of a (topic, receive time ns, message) from read_messages; a tf2_msgs/TFMessage's
    earliest transform stamp; the receive time for a message with neither."""
    _, t_ns, msg = message
    headers = [msg.header] if hasattr(msg, "header") else [tf.header for tf in getattr(msg, "transforms", ())]
    if not headers:
        return t_ns
    return min(int(h.stamp.sec) * 1_000_000_000 + int(h.stamp.nanosec) for h in headers)


def _check_topics(path: Path | str, wanted: set[str], have: set[str]) -> None:
    missing = wanted - have
    if missing:
        raise BagError(f"topic(s) {', '.join(sorted(missing))} not in {path} (has: {', '.join(sorted(have))})")


def _rosbags_messages(path: Path, topic_names: Iterable[str] | None, strict: bool, log: Any
                      ) -> Iterator[tuple[str, int, Any]]:
    """read_messages through rosbags' AnyReader (bags storage.py does not read): no topic named, no message
    (rosbags reads every topic for an empty connection list); a message that does not deserialise is counted
    in ``log`` and skipped."""
    with _opened(path) as reader:
        conns = reader.connections
        if topic_names is not None:
            wanted = set(topic_names)
            if strict:
                _check_topics(path, wanted, {c.topic for c in conns})
            conns = [c for c in conns if c.topic in wanted]
            if not conns:
                return
        for conn, t_ns, raw in reader.messages(connections=conns):
            log.message()
            try:
                msg = reader.deserialize(raw, conn.msgtype)
            except Exception:  # noqa: BLE001 - as read_messages: a damaged message is counted and skipped
                log.undecodable += 1
                continue
            yield conn.topic, t_ns, msg


def odometry_pose(msg: Any) -> tuple[float, np.ndarray]:
    """nav_msgs/Odometry -> (header stamp s, 4×4 child-to-parent pose). Quaternion is normalised."""
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    return stamp_seconds(msg.header), geometry.pose_from_quat([q.x, q.y, q.z, q.w], [p.x, p.y, p.z])


def read_odometry(path: str | Path, topic: str = "/odom") -> tuple[np.ndarray, np.ndarray]:
    """All odometry of a topic -> ((N,) stamps s, (N, 4, 4) poses), in bag order."""
    stamps, poses = [], []
    for _, _, msg in read_messages(path, [topic]):
        s, t = odometry_pose(msg)
        stamps.append(s)
        poses.append(t)
    return np.asarray(stamps), np.asarray(poses).reshape(-1, 4, 4)


def make_odometry(stamp: float, pose: np.ndarray, frame_id: str = "map", child_frame_id: str = "base_link") -> Any:
    """nav_msgs/Odometry (Jazzy, rosbags) from a 4×4 child-to-parent pose; zero twist and covariance."""
    m = msg_types()
    q, t = geometry.pose_to_quat(pose)
    cov = np.zeros(36)
    pose_msg = m.PoseWithCovariance(
        pose=m.Pose(position=m.Point(x=t[0], y=t[1], z=t[2]), orientation=m.Quaternion(x=q[0], y=q[1], z=q[2], w=q[3])),
        covariance=cov)
    twist = m.TwistWithCovariance(twist=m.Twist(linear=m.Vector3(x=0.0, y=0.0, z=0.0),
                                                angular=m.Vector3(x=0.0, y=0.0, z=0.0)), covariance=cov.copy())
    return m.Odometry(header=make_header(stamp, frame_id, m), child_frame_id=child_frame_id, pose=pose_msg, twist=twist)


def make_tf(stamp: float, pose: np.ndarray, frame_id: str, child_frame_id: str) -> Any:
    """tf2_msgs/TFMessage holding one transform (child-to-parent pose)."""
    m = msg_types()
    q, t = geometry.pose_to_quat(pose)
    tf = m.TransformStamped(header=make_header(stamp, frame_id, m), child_frame_id=child_frame_id,
                            transform=m.Transform(translation=m.Vector3(x=t[0], y=t[1], z=t[2]),
                                                  rotation=m.Quaternion(x=q[0], y=q[1], z=q[2], w=q[3])))
    return m.TFMessage(transforms=[tf])


def _latched_qos() -> Any:
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    zero = QosTime(0, 0)
    return Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL,
               zero, zero, QosLiveliness.AUTOMATIC, zero, False)


class BagWriter:
    """Streaming rosbag2 writer (Jazzy types): ``with BagWriter(path) as w: w.write('/odom', t, msg)``.

    Topics are registered on first write from the message's type; ``latched`` topics (e.g. /tf_static)
    are offered with transient-local QoS. The output directory must not exist yet. ``compress`` (MCAP only):
    the file's chunks are zstd-compressed when the bag is closed (as ros2 bag record --compression-format zstd
    --storage-preset-profile does for MCAP chunks; every MCAP reader reads them).
    """

    def __init__(self, path: str | Path, storage: str = "mcap", latched: Iterable[str] = ("/tf_static",),
                 compress: bool = False):
        from rosbags.rosbag2 import StoragePlugin, Writer

        if storage not in STORAGES:
            raise ValueError(f"storage must be one of {STORAGES}, got {storage!r}")
        self.path = Path(path)
        if self.path.is_dir() and not self.path.is_symlink() and not any(self.path.iterdir()):
            try:
                self.path.rmdir()  # an empty folder made for it: the writer makes the bag folder itself
            except OSError:
                pass  # a mount point: "exists already" below
        if self.path.exists():
            raise BagError(f"{self.path} exists already; choose a new output path or remove it")
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        self._writer = Writer(self.path, version=9, storage_plugin=plugin)
        self._latched = set(latched)
        self._conns: dict[str, Any] = {}
        self._compress = compress and storage == "mcap"

    def __enter__(self) -> "BagWriter":
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._writer.open()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._writer.close()
        if exc[0] is not None:  # interrupted or failed: no metadata.yaml, so nothing takes it for a whole bag
            (self.path / "metadata.yaml").unlink(missing_ok=True)
            return
        if self._compress:
            for file in self.path.glob("*.mcap"):
                zstd_chunks(file)

    def write(self, topic: str, stamp: float, msg: Any) -> None:
        """Serialise and write one message with receive time ``stamp`` (s)."""
        conn = self._conns.get(topic)
        if conn is None:
            qos = [_latched_qos()] if topic in self._latched else []
            conn = self._writer.add_connection(topic, msg.__msgtype__, typestore=typestore(), offered_qos_profiles=qos)
            self._conns[topic] = conn
        raw = typestore().serialize_cdr(msg, msg.__msgtype__)
        self._writer.write(conn, int(round(stamp * 1e9)), raw)


def zstd_chunks(file: Path) -> None:
    """Rewrite an MCAP file with zstd-compressed chunks (schemas, channels, messages and metadata records
    copied as they are), replacing it only once the new file is complete."""
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    tmp = file.with_suffix(".mcap.tmp")
    with open(file, "rb") as f, open(tmp, "wb") as g:
        reader = make_reader(f)
        writer = Writer(g, compression=CompressionType.ZSTD)
        writer.start(profile=reader.get_header().profile, library=reader.get_header().library)
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if schema is not None and schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(channel.topic, channel.message_encoding,
                                                               schemas.get(channel.schema_id, 0), channel.metadata)
            writer.add_message(channels[channel.id], message.log_time, message.data, message.publish_time,
                               message.sequence)
        for meta in reader.iter_metadata():
            writer.add_metadata(meta.name, meta.metadata)
        writer.finish()
    tmp.replace(file)


def bag_name(bag_path: str | Path) -> str:
    """A bag's name: its folder's ("." names the folder it is), or its file's without the extension."""
    p = Path(bag_path)
    return p.stem if p.is_file() else p.resolve().name


def truth_path(bag_path: str | Path) -> Path:
    """Where a simulated bag keeps its truth.json: in the bag folder (the folder of a bag given as its .mcap or
    .db3 file)."""
    p = Path(bag_path).resolve()  # a linked .mcap: the bag it belongs to
    return (p.parent if p.is_file() else p) / "truth.json"


def load_truth(bag_path: str | Path) -> dict | None:
    """The truth.json a simulated bag carries (settings, drift episodes), or None for other bags."""
    p = truth_path(bag_path)
    return json.loads(p.read_text()) if p.exists() else None
