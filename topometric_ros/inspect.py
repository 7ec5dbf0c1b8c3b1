"""``topometric inspect``: the per-scan stages on a bag's clouds, drawn for a person, no odometry needed.

For every ``every``-th cloud (at most ``limit``): how the cloud was read (driver layout, dropped points, per-
point time), its grid (rows from where, size), the network's image (images x rows x columns), the
segmentation and the planes, as one PNG per scan (the grid coloured by class, a top view by class and a top
view by plane) and one CSV row per scan. It answers "does my sensor work with the monitor?" before any
odometry is involved.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from . import bag, classes as C, storage
from .cloud import CloudError, read_scan
from .config import Config
from .pipeline import segment_scan, sensor_model
from .planes import detect_planes
from .reports import pyplot, write_csv
from .segmentation.projection import image_shape
from .window import Frame

#: Colours of the classes (classes.NAMES order) in every plot.
CLASS_COLOURS = np.array([[0.6, 0.6, 0.6], [0.55, 0.35, 0.15], [0.12, 0.47, 0.71], [0.89, 0.1, 0.11],
                          [1.0, 0.5, 0.0], [0.6, 0.31, 0.64], [0.2, 0.63, 0.17]])


def cloud_topic(path: str | Path, topic: str = "") -> tuple[str, int]:
    """(``topic`` if the bag has it, else the bag's only PointCloud2 topic; its message count); BagError listing
    the topics otherwise."""
    topics = bag.topics(path)
    found, _ = bag.pick_topic(topics, bag.POINTCLOUD2, topic, "/points")
    if found not in topics:
        damaged = bag.unreadable(path, found) or (not topic and bag.unreadable_clouds(path))
        if damaged:
            raise bag.BagError(damaged)
        raise bag.BagError(f"no PointCloud2 topic {found} in {path}; name one with --points-topic. "
                           f"Topics: {bag.describe_topics(topics)}")
    if topics[found][0] != bag.POINTCLOUD2:
        raise bag.BagError(f"topic {found} holds {topics[found][0]}, not {bag.POINTCLOUD2}; name a PointCloud2 "
                           f"topic with --points-topic. Topics: {bag.describe_topics(topics)}")
    return found, topics[found][1]


def inspect_bag(path: str | Path, out: str | Path, config: Config | None = None, topic: str = "",
                every: int = 1, limit: int = 10, segmenter=None, plot: bool = True,
                progress: bool = False, log: storage.ReadLog | None = None) -> list[dict]:
    """Run grid + segmentation + planes on every ``every``-th cloud of ``path``, at most ``limit`` of them (0:
    all), and write OUT/scans.csv and OUT/scan_NNNN.png (``progress``: a progress bar). Returns the CSV rows
    (one per cloud; a cloud that cannot be read gets its error); ``log`` says what of a damaged bag was
    skipped."""
    from tqdm import tqdm

    config = config or Config()
    topic, count = cloud_topic(path, topic)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if segmenter is None and config.segmentation.mode == "network":
        from .pipeline import default_segmenter

        segmenter = default_segmenter(config.segmentation)
    model = sensor_model(config)
    rows = []
    every = max(int(every), 1)
    total = -(-count // every) if not limit else min(limit, -(-count // every))
    with tqdm(total=total, desc="inspect", unit="scan", disable=not progress, leave=False) as bar:
        for k, (_, _, msg) in enumerate(bag.read_messages(path, [topic], log)):
            if k % every:
                continue
            if limit and len(rows) >= limit:
                break
            rows.append(_inspect_one(k, msg, config, model, segmenter, out if plot else None))
            bar.update()
    write_csv(out / "scans.csv", rows)
    return rows


#: The console table's columns (scans.csv has every field).
TABLE_COLUMNS = ("scan", "layout", "cloud", "points", "dropped", "time_field", "grid", "rows_from", "planes", "ms")


def format_rows(rows: list[dict]) -> str:
    """The console table of inspect_bag's rows: a column each of TABLE_COLUMNS, as wide as its widest entry;
    a cloud's error last on its line. ms: grid, segmentation and planes of that cloud (the first includes
    loading the network)."""
    cells = [[str(r.get(c, "")) for c in TABLE_COLUMNS] for r in rows]
    widths = [max([len(c)] + [len(line[i]) for line in cells]) for i, c in enumerate(TABLE_COLUMNS)]
    lines = ["  ".join(c.rjust(w) for c, w in zip(TABLE_COLUMNS, widths))]
    for r, line in zip(rows, cells):
        lines.append("  ".join(v.rjust(w) for v, w in zip(line, widths)) + (f"  ERROR {r['error']}" if "error" in r else ""))
    return "\n".join(lines)


def _inspect_one(k: int, msg, config: Config, model, segmenter, out: Path | None) -> dict:
    row = {"scan": k, "stamp": repr(float(msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec))}
    try:
        scan = read_scan(msg, model.beams if model is not None else 0)
    except CloudError as e:
        return {**row, "error": str(e)}
    row.update(layout=scan.layout or "unknown", cloud=f"{msg.height}x{msg.width}", points=len(scan.points),
               dropped=sum(scan.dropped.values()), bad_beam=scan.dropped.get("bad_beam", 0),
               time_field="yes" if scan.time is not None else "no", notes="; ".join(scan.notes))
    if len(scan.points) == 0:
        return {**row, "error": "no returns"}
    frame = Frame(scan.points, np.eye(4), scan.stamp, scan.labels, scan.beam, scan.intensity, scan.time, scan.columns,
                  layout=scan.layout)
    t0 = time.perf_counter()
    try:
        seg = segment_scan(frame, config, segmenter, k)
        planes, assign = detect_planes(seg.frame.points, seg.labels, seg.grid, config.planes, k, return_inliers=True)
    except (ValueError, RuntimeError) as e:  # this cloud's reason in its row; the others go on
        return {**row, "error": f"{type(e).__name__}: {e}"}
    images, rows, columns = image_shape(seg.grid)  # what the network sees (a non-repetitive grid's is finer)
    row.update(grid=f"{seg.grid.height}x{seg.grid.width}", rows_from=seg.grid.source,
               network_image=f"{images}x{rows}x{columns}", planes=len(planes),
               ms=round(1000 * (time.perf_counter() - t0), 1),
               **{f"share_{C.NAMES[c]}": round(float(np.mean(seg.labels == c)), 3) for c in range(C.NUM_CLASSES)})
    if out is not None:
        plot_scan(seg, assign, out / f"scan_{k:04d}.png", f"scan {k}: {row['layout']} {row['cloud']}, grid "
                  f"{row['grid']} ({row['rows_from']}), {config.segmentation.mode} segmentation, {row['planes']} planes")
    return row


def plot_scan(seg, assign: np.ndarray, path: Path, title: str) -> None:
    """The grid coloured by class (rows bottom-up), and top views (sensor frame, m) by class and by plane
    (``assign``: each point's plane index, −1 none)."""
    plt = pyplot()
    pts, labels, grid = seg.frame.points, seg.labels, seg.grid
    image = np.ones((grid.height, grid.width, 3))
    image[grid.row, grid.col] = CLASS_COLOURS[np.minimum(labels, C.NUM_CLASSES - 1)]
    fig = plt.figure(figsize=(13, 8.5))
    ax = fig.add_subplot(2, 1, 1)
    ax.imshow(image[::-1], aspect="auto", interpolation="nearest")
    ax.set_xlabel("azimuth column (0 = +x, counter-clockwise)")
    ax.set_ylabel("grid row (top = highest beam)")
    ax.set_title(title, fontsize=10)
    reach = float(np.percentile(np.hypot(pts[:, 0], pts[:, 1]), 95)) + 1.0
    for i, (colour, what) in enumerate(((CLASS_COLOURS[np.minimum(labels, C.NUM_CLASSES - 1)], "class"),
                                        (_plane_colours(assign), "plane (grey: none)"))):
        a = fig.add_subplot(2, 2, 3 + i)
        a.scatter(pts[:, 0], pts[:, 1], s=0.3, c=colour, linewidths=0)
        a.set_xlim(-reach, reach)
        a.set_ylim(-reach, reach)
        a.set_aspect("equal")
        a.set_xlabel("x (m, sensor frame)")
        a.set_ylabel("y (m)")
        a.set_title(f"top view by {what}", fontsize=10)
    from matplotlib.patches import Patch

    fig.legend(handles=[Patch(color=CLASS_COLOURS[c], label=C.NAMES[c]) for c in range(C.NUM_CLASSES)],
               loc="lower center", ncol=C.NUM_CLASSES, fontsize=9)
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _plane_colours(assign: np.ndarray) -> np.ndarray:
    rng = np.random.default_rng(0)
    palette = rng.uniform(0.1, 0.9, (int(assign.max()) + 2, 3))
    colours = palette[np.maximum(assign, 0)]
    colours[assign < 0] = 0.85
    return colours
