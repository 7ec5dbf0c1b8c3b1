"""``topometric eval-seg``: segmentation quality and speed on labelled bags.

Per bag, per scene and over all bags: IoU of every class, mIoU over the paper's five classes (its
Table 2) and over all seven, the confusion matrix (the paper's Fig. 6) as CSV and PNG, and scans/s
of segmentation including projection and back-projection (median over scans).
"""
from __future__ import annotations

import statistics
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from .. import classes as C
from ..bag import bag_name
from ..reports import write_csv, write_json
from .data import read_scans, scene_of, sensor_of
from .metrics import accuracy, confusion, iou_per_class, miou


def evaluate_bags(bags: Sequence[str | Path], segmenter=None, every: int = 1, limit: int = 0,
                  topic: str = "", progress: bool = True) -> dict:
    """Score ``segmenter`` (None = the clouds' own label field, a sanity check) on labelled bags.

    Returns {'bags': {bag: conf}, 'scenes': {scene: conf}, 'sensors': {sensor: conf}, 'all': conf,
    'scan_ms': [...], 'sensor_ms': {sensor: [...]}, 'non_repetitive': scans whose grid has per-point azimuths}
    with (K, K) confusion matrices (rows truth, columns prediction); the times leave out each sensor's first
    scan (warm-up: the network's export for its shape).
    """
    from tqdm import tqdm

    per_bag, per_scene, per_sensor, times, sensor_ms, warm, non_repetitive = {}, {}, {}, [], {}, set(), 0
    total = np.zeros((C.NUM_CLASSES, C.NUM_CLASSES), np.int64)
    for b in tqdm(list(bags), desc="eval-seg", unit="bag", disable=not progress):
        conf = np.zeros_like(total)
        sensor = sensor_of(b)
        for scan in read_scans(b, topic, every, limit):
            if scan.label is None:
                raise ValueError(f"{b}: the cloud has no label field; eval-seg needs ground truth")
            non_repetitive += scan.grid.azimuth is not None
            if segmenter is None:
                pred = scan.label
            else:
                t = time.perf_counter()
                pred, _ = segmenter.predict(scan.points, scan.grid, scan.intensity)
                ms = 1000 * (time.perf_counter() - t)
                if sensor in warm:  # a sensor's first scan exports the network for its image shape: not timed
                    times.append(ms)
                    sensor_ms.setdefault(sensor, []).append(ms)
                warm.add(sensor)
            conf += confusion(scan.label, pred)
        per_bag[str(b)] = conf
        scene = scene_of(b)
        per_scene[scene] = per_scene.get(scene, 0) + conf
        per_sensor[sensor] = per_sensor.get(sensor, 0) + conf
        total += conf
    return {"bags": per_bag, "scenes": per_scene, "sensors": per_sensor, "all": total, "scan_ms": times,
            "non_repetitive": non_repetitive,
            "sensor_ms": sensor_ms}


def summary_row(name: str, conf: np.ndarray) -> dict:
    """{'group', 'points', 'accuracy', 'miou_paper', 'miou_all', <class>: IoU %} for one confusion matrix."""
    iou = iou_per_class(conf)
    row = {"group": name, "points": int(conf.sum()), "accuracy": round(100 * accuracy(conf), 2),
           "miou_paper": round(100 * miou(conf), 2), "miou_all": round(100 * miou(conf, range(C.NUM_CLASSES)), 2)}
    row.update({C.NAMES[c]: (round(100 * float(v), 2) if np.isfinite(v) else None) for c, v in enumerate(iou)})
    return row


def _bag_label(path: Path, names: list[str]) -> str:
    """A bag's name; with the two folders above it when ``names`` (every bag's name) holds it twice (simulate
    --split names a sensor's bags alike: VLP-16/test/office1_0, OS1-32/test/office1_0)."""
    name = bag_name(path)
    return name if names.count(name) == 1 else "/".join(path.parts[-3:])


def write_report(result: dict, out: str | Path, title: str = "") -> dict:
    """per_class_iou.csv, confusion.csv, confusion.png and metrics.json under ``out``; returns metrics."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    names = [bag_name(b) for b in result["bags"]]
    rows = [summary_row(f"bag:{_bag_label(Path(b), names)}", c) for b, c in result["bags"].items()]
    rows += [summary_row(f"scene:{s}", c) for s, c in result["scenes"].items()]
    if len(result.get("sensors", {})) > 1:
        rows += [summary_row(f"sensor:{s}", c) for s, c in result["sensors"].items()]
    rows.append(summary_row("all", result["all"]))
    write_csv(out / "per_class_iou.csv", rows)
    conf = result["all"]
    write_csv(out / "confusion.csv", [{"truth\\pred": name, **dict(zip(C.NAMES, conf[c].tolist()))}
                                      for c, name in enumerate(C.NAMES)])
    plot_confusion(conf, out / "confusion.png", title)
    ms = result["scan_ms"]
    speed = {"scans": len(ms)}
    if ms:
        med = statistics.median(ms)
        speed.update({"median_ms": round(med, 2), "scans_per_s": round(1000 / med, 1),
                      "p90_ms": round(float(np.percentile(ms, 90)), 2)})
    speed["per_sensor_median_ms"] = {k: round(statistics.median(v), 2) for k, v in result.get("sensor_ms", {}).items()}
    metrics = {"title": title, "rows": rows, "confusion": conf.tolist(), "classes": list(C.NAMES),
               "speed": speed}
    write_json(out / "metrics.json", metrics, indent=2)
    return metrics


def plot_confusion(conf: np.ndarray, path: str | Path, title: str = "") -> None:
    """Row-normalised confusion matrix (% of each true class), like the paper's Fig. 6."""
    from ..reports import pyplot

    plt = pyplot()

    with np.errstate(invalid="ignore", divide="ignore"):
        norm = 100 * conf / conf.sum(1, keepdims=True)
    fig, ax = plt.subplots(figsize=(6.4, 5.4))
    im = ax.imshow(np.nan_to_num(norm), cmap="Blues", vmin=0, vmax=100)
    for i in range(len(conf)):
        for j in range(len(conf)):
            if np.isfinite(norm[i, j]) and (norm[i, j] >= 0.05 or i == j):
                ax.text(j, i, f"{norm[i, j]:.1f}", ha="center", va="center", fontsize=8,
                        color="white" if norm[i, j] > 60 else "black")
    ax.set_xticks(range(len(conf)), C.NAMES, rotation=45, ha="right")
    ax.set_yticks(range(len(conf)), C.NAMES)
    ax.set_xlabel("predicted")
    ax.set_ylabel("ground truth")
    ax.set_title(title or "confusion (% of true class)")
    fig.colorbar(im, ax=ax, fraction=0.046)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def format_table(rows: list[dict]) -> str:
    """A fixed-width text table of summary rows (IoU %)."""
    cols = ["miou_paper", *[C.NAMES[c] for c in C.PAPER_CLASSES], "ceiling", "other", "miou_all"]
    head = f"{'group':24s}" + "".join(f"{c:>11s}" for c in cols)
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(f"{r['group'][:24]:24s}" + "".join(
            f"{r[c]:11.2f}" if r[c] is not None else f"{'-':>11s}" for c in cols))
    return "\n".join(lines)
