"""Damaged bags keep every intact scan: a small simulated bag (MCAP and sqlite3) written to disk, damaged on disk
(a zeroed chunk, random bytes over a chunk, a zeroed record header, a truncated file, a zeroed database page, no
metadata.yaml) and replayed. Which scans are intact is worked out independently of the reader under test:

- MCAP: each cloud's message record is located in the ORIGINAL file (its serialized bytes, from the mcap
  library's reader, found verbatim in the uncompressed chunks); a cloud is intact when no damaged byte touches
  its record and the file still holds all of it.
- sqlite3: each row's pages (its b-tree leaf, its overflow chain and the interior pages above them) come from
  SQLite's dbstat table on the ORIGINAL file; a row is intact when every one of its pages is still there, whole.

The per-scan and per-window functions are a cheap real score (floor spread, as test_replay's) so the test
measures reading, not plane detection.
"""
from __future__ import annotations

import shutil
import sqlite3
from pathlib import Path

import numpy as np
import pytest

from topometric_ros import classes, geometry
from topometric_ros.config import load_config
from topometric_ros.pipeline import ProcessedScan, WindowResult
from topometric_ros.replay import ReplayOptions, replay
from topometric_ros.sim.writer import SimConfig, simulate

FRAMES = 12
PAGE = 4096


def floor_scan(frame, config, segmenter=None, index=-1):
    floor = frame.points[frame.labels == classes.FLOOR].astype(np.float64)
    return ProcessedScan(frame.stamp, frame.pose, [], points=geometry.transform_points(frame.pose, floor), index=index)


def floor_window(scans, config):
    heights = np.array([s.points[:, 2].mean() for s in scans])
    return WindowResult([s.stamp for s in scans], pne=float(np.ptp(heights)), cpv=float(heights.var()),
                        n_planes=len(scans), n_groups=1)


def run(bag_path, out):
    config = load_config(overrides={"window.size": 3, "health.baseline_windows": 1})
    return replay(bag_path, out, config, ReplayOptions(progress=False, plot=False), floor_scan, floor_window)


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    root = tmp_path_factory.mktemp("damaged")
    out = {}
    for storage in ("mcap", "sqlite3"):
        simulate(SimConfig(scene="office1", frames=FRAMES, rate=5.0, storage=storage, compress=False), root / storage,
                 progress=False)  # uncompressed chunks: the damage is placed by finding the clouds' bytes
        out[storage] = root / storage
    return out


# ------------------------------------------------------------------ ground truth, independent of the reader
def mcap_cloud_spans(file: Path) -> list[tuple[int, int]]:
    """[start, end) file bytes of each /points message record (9 record + 22 message header bytes + data)."""
    from mcap.reader import make_reader

    blob = file.read_bytes()
    spans = []
    with open(file, "rb") as f:
        for _, _, message in make_reader(f).iter_messages(topics=["/points"]):
            at = blob.find(message.data)
            assert at > 0 and blob.find(message.data, at + 1) < 0  # verbatim and unique: uncompressed chunks
            spans.append((at - 31, at + len(message.data)))
    return spans


def mcap_intact(spans, damaged: list[tuple[int, int]], size: int) -> int:
    return sum(end <= size and all(end <= a or start >= b for a, b in damaged) for start, end in spans)


def mcap_chunks(file: Path) -> list:
    from mcap.reader import make_reader

    with open(file, "rb") as f:
        return sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)


def sqlite_cloud_rows(db: Path) -> list[tuple[int, set[int]]]:
    """(leaf page, every page) of each /points row, from dbstat: leaf cells in b-tree (path) order are the rows
    in id order; a cell's overflow pages are named '<leaf path><cell>+<n>'; the interior pages above a leaf
    are the prefixes of its path."""
    con = sqlite3.connect(db)
    pages = con.execute("SELECT path, pageno, pagetype, ncell FROM dbstat WHERE name = 'messages' "
                        "ORDER BY path").fetchall()
    topics = [t for (t,) in con.execute("SELECT t.name FROM messages m JOIN topics t ON m.topic_id = t.id "
                                        "ORDER BY m.id")]
    con.close()
    by_path = {path: pageno for path, pageno, _, _ in pages}
    overflow: dict[str, set[int]] = {}
    for path, pageno, kind, _ in pages:
        if kind == "overflow":
            overflow.setdefault(path.split("+")[0], set()).add(pageno)
    rows = []
    for path, pageno, kind, ncell in pages:
        if kind == "leaf":
            parts = path.strip("/").split("/")
            above = {by_path["/"]} | {by_path["/" + "/".join(parts[:k]) + "/"] for k in range(1, len(parts))}
            rows += [(pageno, above | {pageno} | overflow.get(f"{path}{cell:03x}", set())) for cell in range(ncell)]
    assert len(rows) == len(topics)
    return [row for row, topic in zip(rows, topics) if topic == "/points"]


def sqlite_intact(rows: list[tuple[int, set[int]]], lost_pages: set[int], whole_pages: int) -> int:
    return sum(max(p) <= whole_pages and not (p & lost_pages) for _, p in rows)


# ------------------------------------------------------------------ damage
def copy_bag(src: Path, dst: Path, metadata: bool | str = True) -> Path:
    """A copy of the bag; metadata False: without metadata.yaml, "cut": its first 200 bytes, "empty": 0 bytes."""
    shutil.copytree(src, dst)
    meta = dst / "metadata.yaml"
    if not metadata:
        meta.unlink()
    elif metadata in ("cut", "empty"):
        meta.write_bytes(meta.read_bytes()[:200] if metadata == "cut" else b"")
    return next(dst.glob("*.mcap")) if any(dst.glob("*.mcap")) else next(dst.glob("*.db3"))


def overwrite(file: Path, start: int, end: int, random: bool = False) -> None:
    data = bytearray(file.read_bytes())
    rng = np.random.default_rng(7)
    fill = rng.integers(0, 256, end - start, dtype=np.uint8).tobytes() if random else bytes(end - start)
    data[start:end] = fill
    file.write_bytes(bytes(data))


def truncate(file: Path, size: int) -> None:
    file.write_bytes(file.read_bytes()[:size])


def mcap_variants(src: Path, root: Path):
    """name -> (bag path, intact clouds): each damage applied to a fresh copy of the MCAP bag."""
    (orig,) = src.glob("*.mcap")
    spans, chunks, size = mcap_cloud_spans(orig), mcap_chunks(orig), orig.stat().st_size
    third, fifth = chunks[3], chunks[5]
    whole = (third.chunk_start_offset, third.chunk_start_offset + third.chunk_length)
    out = {}

    def variant(name, damage=(), cut=None, random=False, metadata=True):
        f = copy_bag(src, root / name, metadata)
        for a, b in damage:
            overwrite(f, a, b, random)
        if cut:
            truncate(f, cut)
        out[name] = (root / name, mcap_intact(spans, list(damage), cut or size))

    variant("mcap_zeroed_chunk", [whole])
    variant("mcap_random_bytes_over_a_chunk", [whole], random=True)
    cloud = next(s for s in spans if fifth.chunk_start_offset < s[0] < fifth.chunk_start_offset + fifth.chunk_length)
    variant("mcap_zeroed_cloud_record_header", [(cloud[0], cloud[0] + 40)])
    variant("mcap_truncated", cut=int(size * 0.6))
    variant("mcap_zeroed_chunk_and_truncated", [whole], cut=int(size * 0.8))
    variant("mcap_no_metadata_yaml", metadata=False)
    variant("mcap_no_metadata_yaml_but_a_cut_one", metadata="cut")
    variant("mcap_no_metadata_yaml_but_an_empty_one", metadata="empty")
    return out


def zstd_copy(src: Path, dst: Path) -> Path:
    """The bag rewritten with zstd-compressed chunks (as `ros2 bag record` can write them)."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

    from topometric_ros.bag import typestore

    writer = Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with AnyReader([src], default_typestore=typestore()) as reader, writer:
        conns = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=typestore()) for c in reader.connections}
        for c, t, raw in reader.messages():
            writer.write(conns[c.id], t, raw)
    return dst


def zstd_variant(src: Path, root: Path):
    """A zstd bag with its middle chunk zeroed and the file cut 100 bytes into a later chunk (no summary):
    intact = clouds of the chunks wholly before the cut, but the zeroed one (clouds mapped to chunks by log
    time: rosbags writes chunks one after another)."""
    from mcap.reader import make_reader

    bag_dir = zstd_copy(src, root / "zstd_source")
    (orig,) = bag_dir.glob("*.mcap")
    chunks = mcap_chunks(orig)
    assert {c.compression for c in chunks} == {"zstd"}
    with open(orig, "rb") as f:
        times = [m.log_time for _, _, m in make_reader(f).iter_messages(topics=["/points"])]
    zeroed, cut = chunks[len(chunks) // 2], chunks[-3].chunk_start_offset + 100
    whole = [c for c in chunks if c is not zeroed and c.chunk_start_offset + c.chunk_length <= cut]
    intact = sum(any(c.message_start_time <= t <= c.message_end_time for c in whole) for t in times)
    f = copy_bag(bag_dir, root / "mcap_zstd_zeroed_chunk_and_truncated")
    overwrite(f, zeroed.chunk_start_offset, zeroed.chunk_start_offset + zeroed.chunk_length)
    truncate(f, cut)
    return {"mcap_zstd_zeroed_chunk_and_truncated": (root / "mcap_zstd_zeroed_chunk_and_truncated", intact)}


def sqlite_variants(src: Path, root: Path):
    (orig,) = src.glob("*.db3")
    rows, pages = sqlite_cloud_rows(orig), orig.stat().st_size // PAGE
    leaf = rows[len(rows) // 2][0]  # the leaf page of a cloud in the middle of the table
    out = {}

    def variant(name, cut_pages=None, zero_page=None, metadata=True):
        f = copy_bag(src, root / name, metadata)
        if zero_page:
            overwrite(f, (zero_page - 1) * PAGE, zero_page * PAGE)
        if cut_pages:
            truncate(f, cut_pages * PAGE + 1000)  # a page cut in two
        out[name] = (root / name, sqlite_intact(rows, {zero_page} if zero_page else set(), cut_pages or pages))

    variant("sqlite3_truncated", cut_pages=int(pages * 0.6))
    variant("sqlite3_no_metadata_yaml", metadata=False)
    variant("sqlite3_truncated_no_metadata_yaml", cut_pages=int(pages * 0.6), metadata=False)
    variant("sqlite3_zeroed_leaf_page", zero_page=leaf)
    return out


# ------------------------------------------------------------------ tests
def test_every_damaged_variant_keeps_every_intact_scan(bags, tmp_path):
    variants = {**mcap_variants(bags["mcap"], tmp_path), **zstd_variant(bags["mcap"], tmp_path),
                **sqlite_variants(bags["sqlite3"], tmp_path)}
    rows = []
    for name, (path, intact) in variants.items():
        s = run(path, tmp_path / f"out_{name}").summary
        rows.append((name, intact, s["scans_read"], s["scans_processed"], s["bag_read"], s["notes"], s["error"]))
    print(f"\n{'variant':36s} {'intact':>6s} {'read':>5s} {'processed':>9s}  bag_read")
    for name, intact, read, processed, counts, notes, _ in rows:
        print(f"{name:36s} {intact:6d} {read:5d} {processed:9d}  {({k: v for k, v in counts.items() if v})}")
        print("    " + "\n    ".join(notes))
    for name, intact, read, processed, counts, notes, error in rows:
        assert 0 < intact <= FRAMES and error == "", name
        assert read == intact and processed == intact, (name, intact, read, processed, notes)
        assert notes, name  # every variant says what it met
        damaged = any(n.startswith("damaged bag:") for n in notes)
        assert damaged == ("no_metadata" not in name or "truncated" in name), (name, notes)
        assert ("no_metadata" in name) == any("metadata.yaml" in n for n in notes), (name, notes)
        if damaged and "truncated" not in name or "and_truncated" in name:  # damage in the middle: read past it
            assert counts["recovered"] > 0 and counts["chunks_damaged"] + counts["rows_skipped"] > 0, (name, counts)


def test_a_flipped_byte_in_an_uncompressed_chunk_is_noted_by_its_crc(tmp_path):
    """An uncompressed MCAP whose writer stored chunk CRCs (the mcap library's, as rosbag2's MCAP plugin does;
    rosbags writes 0: nothing to check) with one payload byte flipped: every message is still read (the records
    are intact), and the chunk's CRC says the chunk is damaged, as for a compressed chunk."""
    from mcap.writer import CompressionType, Writer

    from topometric_ros import storage

    file = tmp_path / "flipped.mcap"
    with open(file, "wb") as f:
        writer = Writer(f, compression=CompressionType.NONE, chunk_size=200)
        writer.start("ros2", "test")
        schema = writer.register_schema("std_msgs/msg/String", "ros2msg", b"string data")
        channel = writer.register_channel("/words", "cdr", schema)
        for k in range(10):
            writer.add_message(channel, log_time=k, publish_time=k, data=b"HELLOWORLD%d" % k)
        writer.finish()
    data = bytearray(file.read_bytes())
    at = data.find(b"HELLOWORLD4")
    data[at] ^= 0xFF
    file.write_bytes(bytes(data))
    log = storage.ReadLog()
    got = [raw for _, _, _, raw in storage.read_raw(file, ["/words"], log)]
    assert len(got) == 10 and bytes(got[4]).endswith(b"ELLOWORLD4") and bytes(got[4]) != b"HELLOWORLD4"
    assert log.chunks_damaged == 1 and log.chunks_lost == 0
    assert any("CRC mismatch" in line for line in log.lines()), log.lines()


def test_a_truncated_database_of_64_kib_pages_is_noted(tmp_path):
    """SQLite stores a 65536-byte page size as 1 in its header: a database of such pages cut in half is still
    seen as truncated."""
    from topometric_ros.storage import _truncation

    file = tmp_path / "big_pages.db3"
    con = sqlite3.connect(file)
    con.execute("PRAGMA page_size=65536")
    con.execute("CREATE TABLE t (b BLOB)")
    con.executemany("INSERT INTO t VALUES (?)", [(bytes(50_000),) for _ in range(20)])
    con.commit()
    con.close()
    assert int.from_bytes(file.read_bytes()[16:18], "big") == 1
    pages = file.stat().st_size // 65536
    truncate(file, file.stat().st_size // 2)
    assert _truncation(file) == f", file truncated: {pages // 2} of {pages} pages"


def test_an_undamaged_bag_reads_as_rosbags_reads_it(bags):
    """The tolerant reader gives exactly rosbags' messages, order and bytes on an intact bag of each storage."""
    from rosbags.highlevel import AnyReader

    from topometric_ros import bag, storage

    for path in bags.values():
        log = storage.ReadLog()
        mine = list(storage.read_raw(path, None, log))
        with AnyReader([path], default_typestore=bag.typestore()) as reader:
            ref = [(c.topic, c.msgtype, t, bytes(raw)) for c, t, raw in reader.messages()]
        assert mine == ref and log.lines() == [] and len(mine) > FRAMES
        assert storage.topic_table(path) == {c: v for c, v in bag.topics(path).items()}


def test_what_is_no_bag_at_all_is_a_bag_error(tmp_path):
    """A folder without storage files and a file that is no .mcap or .db3: each a BagError that says which."""
    from topometric_ros import bag

    (tmp_path / "empty").mkdir()
    (tmp_path / "x.bag").write_bytes(b"not a bag at all")
    for path, why in ((tmp_path / "empty", "no rosbag2 bag at .*empty \\(a bag folder has metadata.yaml"),
                      (tmp_path / "x.bag", "x.bag is not a rosbag2 bag: give a bag folder or its .mcap or .db3 file")):
        with pytest.raises(bag.BagError, match=why):
            bag.topics(path)
        with pytest.raises(bag.BagError, match=why):
            list(bag.read_messages(path))


def test_the_topic_counts_of_a_bag_of_two_files_add_up(bags, tmp_path):
    """A bag folder of two storage files (a split recording): every topic's count over both files, not the last
    file's."""
    from topometric_ros import storage

    (one,) = bags["mcap"].glob("*.mcap")
    split = tmp_path / "split"
    split.mkdir()
    shutil.copy(one, split / "split_0.mcap")
    shutil.copy(one, split / "split_1.mcap")
    single = storage.topic_table(one)
    assert single["/points"][1] == FRAMES
    assert storage.topic_table(split) == {t: (kind, 2 * n) for t, (kind, n) in single.items()}


def test_a_read_log_describes_at_most_max_notes_damages_and_counts_the_rest():
    """Twelve damages: the first MAX_NOTES described, the other four counted in one line, then the summary."""
    from topometric_ros import storage

    log = storage.ReadLog()
    for i in range(12):
        log.damage(f"damage {i}")
    log.message()
    assert log.notes == [f"damage {i}" for i in range(storage.MAX_NOTES)] and log.more_notes == 12 - storage.MAX_NOTES
    assert log.lines() == log.notes + ["4 more damages not described",
                                       "damaged bag: 1 messages read, 1 of them past damage"]
