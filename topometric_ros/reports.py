"""What every report shares: matplotlib without a display, CSV and strict JSON files written atomically."""
from __future__ import annotations

import csv
import json
import math
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np


#: What a replay writes into its --out folder (an audit keeps the same per bag).
REPORT_FILES = ("windows.csv", "windows.json", "metrics.png", "diagnostics.mcap")


def remove_reports(folder: str | Path) -> None:
    """Remove the REPORT_FILES in ``folder`` (an earlier run's), nothing else."""
    for name in REPORT_FILES:
        (Path(folder) / name).unlink(missing_ok=True)


def pyplot():
    """matplotlib.pyplot on the Agg backend (no display needed; PNG files only)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


@contextmanager
def written_whole(path: str | Path) -> Iterator[Path]:
    """A path beside ``path`` (same suffix, so numpy and torch keep the name) to write to; moved onto ``path``
    when the block ends, removed when it raises (Ctrl-C, SIGTERM): a reader never takes half a file for one."""
    path = Path(path)
    tmp = path.with_name(f"{path.stem}.partial{path.suffix}")
    try:
        yield tmp
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)


def write_csv(path: str | Path, rows: list[dict], columns: Sequence[str] = ()) -> Path:
    """rows (dicts) -> CSV at path, written whole (:func:`written_whole`); the columns are ``columns``, then every
    row's other keys in the order first seen (a row without one leaves it empty: inspect's failed clouds have
    fewer)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    columns = list(dict.fromkeys([*columns, *(key for row in rows for key in row)]))
    with written_whole(path) as tmp, tmp.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=columns)
        w.writeheader()
        w.writerows(rows)
    return path


def strict(obj: Any) -> Any:
    """``obj`` as strict JSON values: non-finite floats as None (null: NaN and inf are not JSON, and jq and
    most parsers reject them), numpy scalars and arrays as Python numbers and lists, tuples as lists."""
    if isinstance(obj, dict):
        return {str(k): strict(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [strict(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return strict(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def write_json(path: str | Path, obj: Any, indent: int = 1) -> Path:
    """``obj`` as strict JSON (see :func:`strict`; floats at full precision) at path, written whole
    (:func:`written_whole`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(strict(obj), indent=indent, allow_nan=False)
    with written_whole(path) as tmp:
        tmp.write_text(text)
    return path


def csv_value(v: Any) -> Any:
    """A CSV cell: floats at full precision (the shortest text that reads back as the same float: stamps such
    as 1700000000.2 stay exact), 'nan'/'inf' for non-finite ones; anything else as it is."""
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    return v.item() if isinstance(v, np.generic) else v
