"""What every report shares: matplotlib without a display, and CSV files written atomically."""
from __future__ import annotations

import csv
from pathlib import Path


def pyplot():
    """matplotlib.pyplot on the Agg backend (no display needed; PNG files only)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def write_csv(path: str | Path, rows: list[dict]) -> Path:
    """rows (dicts with the same keys) -> CSV at path, written to a temporary file first so a reader never
    sees half a table."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    with tmp.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]) if rows else [])
        w.writeheader()
        w.writerows(rows)
    tmp.replace(path)
    return path
