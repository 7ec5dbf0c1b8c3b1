"""bag.py: write -> read back identical; simulated bags are standard Jazzy MCAP bags."""
import json
from pathlib import Path

import numpy as np
import pytest

from topometric_ros import bag, geometry
from topometric_ros.cloud import make_cloud, read_cloud, rosbags_types


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_write_read_round_trip_identical(tmp_path, rng, storage):
    types = rosbags_types(bag.typestore())
    clouds, poses, stamps = [], geometry.noise_transforms(7, 1.0, 10.0, rng), 1.7e9 + np.arange(7) * 0.1
    with bag.BagWriter(tmp_path / "b", storage=storage) as w:
        for i, t in enumerate(stamps):
            arrays = {"x": rng.normal(size=300).astype(np.float32), "y": rng.normal(size=300).astype(np.float32),
                      "z": rng.normal(size=300).astype(np.float64), "ring": rng.integers(0, 32, 300).astype(np.uint16)}
            clouds.append(arrays)
            w.write("/points", t, make_cloud(arrays, t, "velodyne", types))
            w.write("/odom", t, bag.make_odometry(t, poses[i]))
    assert bag.topics(tmp_path / "b") == {"/points": (bag.POINTCLOUD2, 7), "/odom": (bag.ODOMETRY, 7)}
    got = [(topic, t, m) for topic, t, m in bag.read_messages(tmp_path / "b", ["/points"])]
    assert [t for _, t, _ in got] == [int(round(s * 1e9)) for s in stamps]
    for (_, _, msg), ref in zip(got, clouds):
        out = read_cloud(msg)
        for k, v in ref.items():
            np.testing.assert_array_equal(out[k], v)
            assert out[k].dtype == v.dtype
    s, p = bag.read_odometry(tmp_path / "b", "/odom")
    np.testing.assert_allclose(s, stamps, atol=1e-6)
    np.testing.assert_allclose(p, poses, atol=1e-12)


def test_missing_bag_and_topic_give_bag_error(tmp_path, office_bag):
    with pytest.raises(bag.BagError, match="not found"):
        list(bag.read_messages(tmp_path / "nope"))
    with pytest.raises(bag.BagError, match="/lidar"):
        list(bag.read_messages(office_bag[0], ["/lidar"]))
    with pytest.raises(bag.BagError, match="exists"):
        bag.BagWriter(office_bag[0])


def test_simulated_bag_decodes_with_independent_mcap_reader(office_bag):
    """The mcap + mcap-ros2-support decoders (not rosbags) read our bag: a standard ROS 2 MCAP file."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path, summary = office_bag
    (mcap_file,) = path.glob("*.mcap")
    seen = {}
    with open(mcap_file, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            seen[channel.topic] = seen.get(channel.topic, 0) + 1
            if channel.topic == "/points" and seen["/points"] == 1:
                assert schema.name == "sensor_msgs/msg/PointCloud2"
                # velodyne_pointcloud's organised XYZIRT (packed, 22 bytes) + the simulator's label byte
                assert [f.name for f in decoded.fields] == ["x", "y", "z", "intensity", "ring", "time", "label"]
                assert decoded.point_step == 23 and decoded.header.frame_id == "velodyne"
                assert (decoded.height, decoded.width) == (1800, 32)  # one row per firing, one column per ring
                assert len(decoded.data) == decoded.height * decoded.width * decoded.point_step
            if channel.topic == "/tf_static":
                assert decoded.transforms[0].child_frame_id == "velodyne"
                assert decoded.transforms[0].transform.translation.z == pytest.approx(1.0)
    assert seen["/points"] == summary["frames"] == 30
    assert seen["/odom"] == seen["/odom_gt"] > seen["/points"]
    assert seen["/tf_static"] == 1


def test_an_interrupted_write_leaves_nothing_that_passes_for_whole(tmp_path):
    """A bag whose writing raised (Ctrl-C, SIGTERM) keeps no metadata.yaml, so nothing takes it for a whole bag
    (training's bag search needs one); a file written through reports.written_whole is there whole or not at
    all, with no partial file left."""
    from topometric_ros.reports import written_whole

    path = tmp_path / "cut"
    with pytest.raises(KeyboardInterrupt):
        with bag.BagWriter(path) as w:
            w.write("/odom", 1.0, bag.make_odometry(1.0, np.eye(4)))
            raise KeyboardInterrupt
    assert path.is_dir() and not (path / "metadata.yaml").exists()
    whole = tmp_path / "cache.npz"
    with pytest.raises(KeyboardInterrupt):
        with written_whole(whole) as tmp:
            np.savez(tmp, a=np.arange(3))
            raise KeyboardInterrupt
    assert list(tmp_path.glob("cache*")) == []
    with written_whole(whole) as tmp:
        np.savez(tmp, a=np.arange(3))
    assert list(tmp_path.glob("cache*")) == [whole] and np.load(whole)["a"].tolist() == [0, 1, 2]


def test_a_file_compressed_bag_reads_through_rosbags_with_the_same_rules(tmp_path):
    """A bag whose files are zstd-compressed whole (storage.py leaves it to rosbags): no topic named gives no
    message (not every topic), a message that does not deserialise is counted and skipped, and a topic missing
    from several bags read as one names them all."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

    from topometric_ros.storage import ReadLog

    store = bag.typestore()
    writer = Writer(tmp_path / "z", version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.FILE, CompressionFormat.ZSTD)
    with writer:
        odom = writer.add_connection("/odom", bag.ODOMETRY, typestore=store)
        for k in range(4):
            raw = store.serialize_cdr(bag.make_odometry(1.0 + k, np.eye(4)), bag.ODOMETRY)
            writer.write(odom, int((1.0 + k) * 1e9), bytes(raw[:20]) if k == 2 else raw)  # one cut message
    assert list(bag.read_messages(tmp_path / "z", [])) == []
    log = ReadLog()
    got = list(bag.read_messages(tmp_path / "z", ["/odom"], log))
    assert [t for _, t, _ in got] == [1_000_000_000, 2_000_000_000, 4_000_000_000] and log.undecodable == 1
    assert log.messages == 4  # read, the cut one among them (as storage.py counts)
    with bag.BagWriter(tmp_path / "side") as w:
        w.write("/odom2", 1.0, bag.make_odometry(1.0, np.eye(4)))
    with pytest.raises(bag.BagError, match="not in .*z, .*side"):
        list(bag.read_messages([tmp_path / "z", tmp_path / "side"], ["/points"]))
    merged = list(bag.read_messages([tmp_path / "z", tmp_path / "side"], ["/odom2"], ReadLog()))
    assert [topic for topic, _, _ in merged] == ["/odom2"]  # the compressed bag has no /odom2: nothing from it


def test_a_default_topic_is_taken_only_when_it_has_the_type_and_others_are_named():
    """/odom that is no Odometry is not the estimate: the bag's only Odometry topic is (ground truth aside); an
    Odometry /odom is, and a note names the other Odometry topics; a topic the user named is never swapped."""
    pose = "geometry_msgs/msg/PoseStamped"
    topics = {"/odom": (pose, 5), "/slam/odometry": (bag.ODOMETRY, 5), "/odom_gt": (bag.ODOMETRY, 5)}
    assert bag.pick_topic(topics, bag.ODOMETRY, "", "/odom", exclude=["/odom_gt"]) == (
        "/slam/odometry", f"/odom is a {pose}: using its only {bag.ODOMETRY} topic /slam/odometry")
    topics["/odom"] = (bag.ODOMETRY, 5)
    assert bag.pick_topic(topics, bag.ODOMETRY, "", "/odom", exclude=["/odom_gt"]) == (
        "/odom", f"using /odom; the bag has other {bag.ODOMETRY} topics too: /slam/odometry (name one to use it)")
    assert bag.pick_topic(topics, bag.ODOMETRY, "/nowhere", "/odom") == ("/nowhere", "")
    assert bag.pick_topic({"/odom": (bag.ODOMETRY, 1), "/odom_gt": (bag.ODOMETRY, 1)}, bag.ODOMETRY, "", "/odom",
                          exclude=["/odom_gt"]) == ("/odom", "")


def test_a_simulated_bag_given_as_its_mcap_file_has_its_truth(office_bag, tmp_path):
    """A bag given as its .mcap file is the same bag (README): its truth.json, scene and sensor are found (eval-seg
    grouped such a bag as 'scene:office1_rt.mcap', and train's --share found no sensor in it), also through a
    link to the file."""
    from topometric_ros.segmentation.data import scene_of, sensor_of

    folder, truth = office_bag
    (mcap,) = folder.glob("*.mcap")
    link = tmp_path / "linked.mcap"
    link.symlink_to(mcap)
    assert bag.load_truth(mcap) == bag.load_truth(link) == bag.load_truth(folder) == json.loads(json.dumps(truth))
    assert scene_of(mcap) == scene_of(folder) == "office1" and sensor_of(mcap) == sensor_of(folder) == "VLP-32C"


def _rss_file_mb() -> float:
    """Resident pages of mapped files (MB) of this process (Linux)."""
    line = next(x for x in Path("/proc/self/status").read_text().splitlines() if x.startswith("RssFile:"))
    return int(line.split()[1]) / 1024


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="RssFile is Linux's")
@pytest.mark.parametrize("compress", [False, True])
def test_a_bag_read_holds_about_a_chunk_of_its_file_in_memory_not_the_file(tmp_path, rng, compress):
    """The MCAP reader maps the file and gives each chunk's pages back once read: the resident memory of a
    reader does not grow with the bag (a replay of a 5.4 GB bag grew to 5 GB before). The messages are the
    ones written."""
    types = rosbags_types(bag.typestore())
    n = 250_000  # 4 MB a cloud
    with bag.BagWriter(tmp_path / "b", compress=compress) as w:
        w.write("/tf_static", 0.0, bag.make_tf(0.0, np.eye(4), "base_link", "lidar"))
        for i in range(20):  # random floats: zstd cannot shrink them much
            xyz = {k: rng.normal(size=n).astype(np.float32) for k in "xyzw"}
            xyz["z"][-1] = i + 1
            w.write("/points", 0.1 * (i + 1), make_cloud(xyz, 0.1 * (i + 1), "lidar", types))
    size_mb = sum(f.stat().st_size for f in (tmp_path / "b").glob("*.mcap")) / 2**20
    before, most = _rss_file_mb(), 0.0
    for i, (_, _, msg) in enumerate(bag.read_messages(tmp_path / "b", ["/points"])):
        assert read_cloud(msg)["z"][-1] == i + 1.0
        most = max(most, _rss_file_mb() - before)
    assert i == 19 and size_mb > 60 and most < 0.25 * size_mb, (most, size_mb)


def test_a_read_of_one_topic_leaves_out_the_chunks_the_index_shows_without_it(tmp_path, rng):
    """Reading /tf_static alone (replay's read of it before the scans) opens only the chunks that hold it: the
    index's per-chunk channels say which; every topic read together gives the same messages in the same order."""
    from topometric_ros import storage

    types = rosbags_types(bag.typestore())
    with bag.BagWriter(tmp_path / "b") as w:
        w.write("/tf_static", 0.0, bag.make_tf(0.0, np.eye(4), "base_link", "lidar"))
        for i in range(30):
            t = 0.1 * (i + 1)
            w.write("/points", t, make_cloud({k: rng.normal(size=100_000).astype(np.float32) for k in "xyz"},
                                             t, "lidar", types))
            w.write("/odom", t, bag.make_odometry(t, np.eye(4)))
    log = storage.ReadLog()
    assert [topic for topic, *_ in storage.read_raw(tmp_path / "b", {"/tf_static"}, log)] == ["/tf_static"]
    assert log.chunks_skipped >= 20, log.chunks_skipped
    every = [(topic, t, bytes(raw)) for topic, _, t, raw in storage.read_raw(tmp_path / "b", None, storage.ReadLog())]
    some = [(topic, t, bytes(raw)) for topic, _, t, raw in storage.read_raw(tmp_path / "b", {"/odom", "/tf_static"},
                                                                             storage.ReadLog())]
    assert len(every) == 61 and some == [m for m in every if m[0] != "/points"]


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="mlockall is Linux's")
def test_a_process_with_locked_memory_reads_a_bag_whole(tmp_path, rng):
    """A real-time process locks its memory (mlockall), where giving mapped pages back fails (EINVAL): the read
    goes on and keeps them (in a child process: the lock would hold for this one)."""
    import subprocess
    import sys

    types = rosbags_types(bag.typestore())
    with bag.BagWriter(tmp_path / "b") as w:
        for i in range(5):
            w.write("/points", 0.1 * (i + 1), make_cloud({k: rng.normal(size=50_000).astype(np.float32) for k in "xyz"},
                                                         0.1 * (i + 1), "lidar", types))
    script = ("import ctypes, sys\n"
              "if ctypes.CDLL(None).mlockall(3): sys.exit(3)\n"  # MCL_CURRENT | MCL_FUTURE
              "from topometric_ros import storage\n"
              f"print(len(list(storage.read_raw({str(tmp_path / 'b')!r}, None, storage.ReadLog()))))\n")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=Path(__file__).parents[1])
    if out.returncode == 3:
        pytest.skip("mlockall refused here (RLIMIT_MEMLOCK)")
    assert out.returncode == 0 and out.stdout.strip() == "5", out.stderr[-2000:]


def test_odometry_pose_reads_the_quaternion_as_x_y_z_w_and_normalises_it():
    """A nav_msgs/Odometry written field by field (not by make_odometry): orientation (x, y, z, w) =
    (0, 0, 2 sin 45°, 2 cos 45°), a quarter turn about z at twice unit length, position (1, 2, 3), stamp
    12 s + 500 ms: the pose is that turn and translation, the stamp 12.5 s."""
    m = bag.msg_types()
    odom = bag.make_odometry(0.0, np.eye(4))
    odom.header.stamp.sec, odom.header.stamp.nanosec = 12, 500_000_000
    s = 2 * np.sin(np.pi / 4)
    odom.pose.pose.orientation = m.Quaternion(x=0.0, y=0.0, z=s, w=s)
    odom.pose.pose.position = m.Point(x=1.0, y=2.0, z=3.0)
    stamp, pose = bag.odometry_pose(odom)
    assert stamp == pytest.approx(12.5)
    np.testing.assert_allclose(pose, [[0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]], atol=1e-12)


def test_the_topics_of_several_bags_read_as_one_add_up_their_message_counts(tmp_path):
    with bag.BagWriter(tmp_path / "a") as w:
        for k in range(3):
            w.write("/odom", 1.0 + k, bag.make_odometry(1.0 + k, np.eye(4)))
    with bag.BagWriter(tmp_path / "b") as w:
        for k in range(2):
            w.write("/odom", 10.0 + k, bag.make_odometry(10.0 + k, np.eye(4)))
        w.write("/odom2", 10.0, bag.make_odometry(10.0, np.eye(4)))
    assert bag.topics([tmp_path / "a", tmp_path / "b"]) == {"/odom": (bag.ODOMETRY, 5), "/odom2": (bag.ODOMETRY, 1)}


def test_a_message_that_does_not_deserialise_is_counted_and_skipped_in_an_mcap_bag(tmp_path):
    """An uncompressed MCAP bag (read by storage.py, not rosbags) holding 4 odometry messages, the third cut
    short: 3 come back, and the read log counts 4 messages read, 1 undecodable."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from topometric_ros.storage import ReadLog

    store = bag.typestore()
    with Writer(tmp_path / "cut", version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        odom = writer.add_connection("/odom", bag.ODOMETRY, typestore=store)
        for k in range(4):
            raw = store.serialize_cdr(bag.make_odometry(1.0 + k, np.eye(4)), bag.ODOMETRY)
            writer.write(odom, int((1.0 + k) * 1e9), bytes(raw[:20]) if k == 2 else raw)
    log = ReadLog()
    got = list(bag.read_messages(tmp_path / "cut", ["/odom"], log))
    assert [t for _, t, _ in got] == [1_000_000_000, 2_000_000_000, 4_000_000_000]
    assert log.undecodable == 1 and log.messages == 4
    assert "1 messages undecodable" in log.summary()


def test_the_stamp_of_a_tf_message_is_its_earliest_transform_stamp():
    tf = bag.make_tf(2.0, np.eye(4), "odom", "base_link")
    tf.transforms.append(bag.make_tf(1.5, np.eye(4), "base_link", "lidar").transforms[0])
    assert bag.message_stamp_ns(("/tf", 7, tf)) == 1_500_000_000
    assert bag.message_stamp_ns(("/x", 7, object())) == 7  # neither header nor transforms: the receive time
