"""`topometric audit`: many bags through the same Monitor and config, one task per bag, one fleet report.

Each bag is one task (engine.run_tasks: Ray, or ``--engine local`` in this process): the task replays the
bag exactly as ``topometric replay`` does (replay.replay, the same config) into a temporary folder and hands
back its reports (windows.csv, windows.json, metrics.png, diagnostics.mcap) and a summary row; this process
writes them under OUT/bags/<bag>/ with a manifest (audit.json), so a worker killed mid-task leaves nothing
half-written and workers need no write access to OUT.

Cache: a bag's manifest holds its key, (bag digest: sha256 over the bag's files' names and bytes; config
digest: sha256 of the resolved config as canonical JSON, segmentation.weights and window.pipelined left out;
weights digest: sha256 of the weights file and the files beside it (int8 ranges, non-repetitive BatchNorm
statistics) when the network segments; the replay options). A bag whose key
is unchanged is not run again; a bag whose task failed (an exception, a worker that died) has no key and is
run again by the next audit. A bag that replays but processes nothing or breaks off (``summary['error']``
/ ``summary['no_scans']``, exit 1 of ``topometric replay``) is a failed bag with that reason, and is cached
like any other result (the same bytes fail the same way; ``--force`` runs everything again).

Weights: with Ray the bytes of the weights file (and the files beside it) are put in the object store once and
every task checks their sha256 against the digest of the key before using them (a copy in the worker's temp
folder, named by digest).

Report: OUT/fleet.csv, OUT/fleet.json (strict JSON) and OUT/index.html (one self-contained page, a table
sortable by clicking its headers, linking each bag's metrics.png; failed bags listed with their reason).
"""
from __future__ import annotations

import glob
import hashlib
import html
import json
import os
import shutil
import tempfile
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from .config import Config, flatten
from .reports import REPORT_FILES, remove_reports, write_csv, write_json
from .bag import bag_name, not_a_bag

MANIFEST = "audit.json"
AUDIT_FORMAT = 1
LEVELS = ("OK", "WARN", "ERROR")
_RANK = {"OK": 0, "WARN": 1, "ERROR": 2}
#: the columns of fleet.csv / index.html, in order
COLUMNS = ("bag", "status", "reason", "duration_s", "scans", "window_scans", "windows", "ok", "warn", "error",
           "worst_level", "worst_time_s", "worst_reason", "rot_rate_p50", "rot_rate_p99", "trans_rate_p50",
           "trans_rate_p99", "episodes_alarmed", "notes", "wall_s", "cached", "worker", "path", "metrics_png")
#: config leaves that cannot change a window's result (left out of the config digest)
NOT_IN_KEY = ("segmentation.weights", "window.pipelined")


# ------------------------------------------------------------------ finding bags
def _reports_in(folder: Path) -> str:
    """The report file that marks ``folder`` as an audit's or a replay's output ("" none)."""
    return next((name for name in (MANIFEST, "windows.json") if (folder / name).is_file()), "")


def _is_bag(p: Path) -> bool:
    """A bag, and not an audit's or a replay's output (their diagnostics.mcap beside a manifest or windows.json)."""
    if _reports_in(p.parent if p.is_file() else p):
        return False
    return not not_a_bag(p)


def find_bags(args: Iterable[str]) -> list[Path]:
    """Bags from paths and globs: a bag (a rosbag2 folder, a .mcap / .db3 file) as it is; a folder that is not
    a bag: every bag under it. In the order given (each folder's bags sorted), each bag once."""
    out: list[Path] = []
    for arg in args:
        matches = sorted(glob.glob(arg, recursive=True)) if glob.has_magic(arg) else [arg]
        if not matches:
            raise FileNotFoundError(f"no bag matches {arg}")
        for m in map(Path, matches):
            if not m.exists():
                raise FileNotFoundError(f"no bag at {m}")
            if _is_bag(m):
                out.append(m)
                continue
            found, visited = [], set()
            for root, dirs, _ in os.walk(m, followlinks=True):  # bags linked into a folder count; each folder once
                visited.add(os.path.realpath(root))
                if _is_bag(Path(root)):
                    found.append(Path(root))
                    dirs.clear()  # not into a bag's own folders
                dirs[:] = [d for d in dirs if os.path.realpath(os.path.join(root, d)) not in visited]
            if not found:
                reports = _reports_in(m) if m.is_dir() and not not_a_bag(m) else ""
                if reports:
                    raise FileNotFoundError(f"{m} holds a replay's or an audit's reports ({reports} beside a "
                                            "diagnostics.mcap), so it is not read as a bag; if it is a bag, move the "
                                            "reports out of it")
                raise FileNotFoundError(f"no rosbag2 bag {'under' if m.is_dir() else 'at'} {m} (a bag is a folder "
                                        "with metadata.yaml or *.mcap / *.db3, or such a file)")
            out += sorted(found)
    seen, unique = set(), []
    for p in out:
        if p.resolve() not in seen:
            seen.add(p.resolve())
            unique.append(p)
    return unique


def bag_names(bags: list[Path]) -> list[str]:
    """A folder name per bag under OUT/bags: the bag's name, with a short hash of its path where two bags of
    the set share a name."""
    base = [bag_name(p) for p in bags]
    return [b if base.count(b) == 1 else _hashed_name(b, p) for b, p in zip(base, bags)]


def _hashed_name(base: str, path: Path) -> str:
    """``base`` and a short hash of the bag's resolved path (bags of one name told apart)."""
    return f"{base}-{hashlib.sha256(str(path.resolve()).encode()).hexdigest()[:8]}"


# ------------------------------------------------------------------ the cache key
def bag_digest(path: str | Path) -> str:
    """sha256 over a bag's files (relative name, size, bytes), in name order: a changed byte is a new bag."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no bag at {path}")
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    h = hashlib.sha256()
    for f in files:
        h.update(f"{f.relative_to(path) if f != path else f.name}\0{f.stat().st_size}\0".encode())
        with f.open("rb") as fh:
            while chunk := fh.read(1 << 20):
                h.update(chunk)
    return h.hexdigest()


def config_digest(config: Config) -> str:
    """sha256 of the resolved config as canonical JSON (sorted keys), without the leaves that cannot change a
    result (NOT_IN_KEY: the weights count by their digest, not their path)."""
    flat = {k: v for k, v in flatten(config).items() if k not in NOT_IN_KEY}
    return hashlib.sha256(json.dumps(flat, sort_keys=True, default=str).encode()).hexdigest()


def weights_files(config: Config) -> dict[str, Path]:
    """The files of the network a replay with ``config`` loads: {"weights": the weights, "int8": their int8
    activation ranges, "norm": their non-repetitive BatchNorm statistics, each beside them when there} ({}
    without the network)."""
    if config.segmentation.mode != "network":
        return {}
    from .segmentation.checkpoint import SHIPPED, beside

    weights = Path(config.segmentation.weights) if config.segmentation.weights else SHIPPED
    files = {name: beside(weights, file) for name, file in _files_beside_weights().items()}
    return {"weights": weights, **{name: path for name, path in files.items() if path.is_file()}}


def _files_beside_weights() -> dict[str, str]:
    """The network's files beside its weights, by the names weights_files gives them."""
    from .segmentation.norm_stats import NORM_NAME
    from .segmentation.quantize import RANGES_NAME

    return {"int8": RANGES_NAME, "norm": NORM_NAME}


def weights_digest(files: dict[str, bytes]) -> str | None:
    """sha256 over the network's files (weights_files' names and bytes), None for none."""
    if not files:
        return None
    h = hashlib.sha256()
    for name in sorted(files):
        h.update(f"{name}|{len(files[name])}|".encode() + files[name])
    return h.hexdigest()


def _read(files: dict[str, Path]) -> dict[str, bytes]:
    return {name: path.read_bytes() for name, path in files.items()}


# ------------------------------------------------------------------ one bag (the task)
@dataclass(frozen=True)
class BagTask:
    """What a worker needs for one bag: where it is, the config, the replay options and the cache key."""

    path: str
    name: str
    config: Config
    key: dict
    options: dict = field(default_factory=dict)  # replay.ReplayOptions fields (topics)


def audit_bag(task: BagTask, weights: dict[str, bytes] | None = None) -> dict:
    """Replay one bag as ``topometric replay`` does; returns {'row': fleet row, 'files': {name: bytes}}.
    ``weights``: the network's files (weights_files' names, bytes) shipped by the engine (checked against
    the key's digest)."""
    from .replay import ReplayOptions, replay

    config = task.config
    want = task.key.get("weights")
    if want:
        if weights is not None:
            if weights_digest(weights) != want:
                raise ValueError(f"the weights shipped to this worker do not hash to {want[:12]}…")
            config = replace(config, segmentation=replace(config.segmentation, weights=str(_weights_copy(weights, want))))
        elif weights_digest(_read(weights_files(config))) != want:
            raise ValueError(f"{weights_files(config)['weights']} or the files beside it changed since the audit "
                             f"started (sha256 is not {want[:12]}…)")
    # one bag per CPU: the bag's per-scan stages run one after the other (window.pipelined gives the same
    # windows, in two threads; here the parallelism is across bags)
    config = replace(config, window=replace(config.window, pipelined=False))
    with _scratch() as tmp:
        options = ReplayOptions(**task.options, plot=True, progress=False)
        res = replay(task.path, tmp, config, options)
        files = {name: (Path(tmp) / name).read_bytes() for name in REPORT_FILES if (Path(tmp) / name).is_file()}
    return {"row": fleet_row(task, res.windows, res.summary), "files": files}


#: Folder in the machine's temp folder where tasks replay their bags, one sub-folder per replay named
#: ``<pid>-<random>``: a task removes those of processes no longer alive (a worker killed mid-replay).
SCRATCH = "topometric-audit"


def _scratch() -> tempfile.TemporaryDirectory:
    """A temporary folder for one replay under SCRATCH, after removing the folders of dead processes."""
    root = Path(tempfile.gettempdir()) / SCRATCH
    root.mkdir(exist_ok=True)
    for old in root.iterdir():
        pid = old.name.split("-", 1)[0]
        if pid.isdigit() and not _alive(int(pid)):
            shutil.rmtree(old, ignore_errors=True)
    return tempfile.TemporaryDirectory(prefix=f"{os.getpid()}-", dir=root)


def _alive(pid: int) -> bool:
    """Whether a process of that id exists (one of another user's counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _weights_copy(files: dict[str, bytes], digest: str) -> Path:
    """The shipped network's files in this machine's temp folder, in a folder named by their digest (written
    once); returns the weights' path."""
    folder = Path(tempfile.gettempdir()) / "topometric-weights" / digest
    paths = {"weights": folder / "rangenet.pt", **{name: folder / f for name, f in _files_beside_weights().items()}}
    if weights_digest({n: paths[n].read_bytes() for n in files if paths[n].is_file()}) != digest:
        folder.mkdir(parents=True, exist_ok=True)
        for name, data in files.items():
            tmp = paths[name].with_suffix(f".{os.getpid()}.tmp")
            tmp.write_bytes(data)
            tmp.replace(paths[name])
    return paths["weights"]


def _quantile(values: list[float], q: float) -> float | None:
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], float)
    return float(np.quantile(v, q)) if len(v) else None


def alarm_episodes(levels: list[str]) -> int:
    """Runs of consecutive WARN / ERROR windows."""
    return sum(1 for i, lv in enumerate(levels) if lv != "OK" and (i == 0 or levels[i - 1] == "OK"))


def worst_window(records: list[dict]) -> dict | None:
    """The window with the highest level; among those, the one furthest above its drift-rate WARN limit."""
    def excess(r: dict) -> float:
        ratios = [r.get(m, np.nan) / r[f"{m}_warn_at"] for m in ("rot_rate", "trans_rate")
                  if r.get(f"{m}_warn_at") and np.isfinite(r.get(f"{m}_warn_at", np.nan))]
        ratios = [x for x in ratios if np.isfinite(x)]
        return max(ratios, default=-np.inf)

    return max(records, key=lambda r: (_RANK.get(r["level"], 0), excess(r)), default=None)


def fleet_row(task: BagTask, records: list[dict], summary: dict) -> dict:
    """One bag's line of the fleet report (see COLUMNS) from its replay."""
    levels = [r["level"] for r in records]
    no_window = "" if records else next((n for n in summary.get("notes", []) if n.startswith("no window")),
                                        "no window")
    failed = summary.get("error") or summary.get("no_scans") or no_window  # as replay's exit status 1
    damage = [n for n in summary.get("notes", []) if n.startswith("damaged bag")]
    if failed and damage:
        failed += f" ({damage[-1]})"
    worst = worst_window(records)
    t0 = records[0]["start"] if records else 0.0
    row = {"bag": task.name, "status": "failed" if failed else "ok", "reason": failed,
           "duration_s": summary.get("bag_s"), "scans": summary.get("scans_processed"),
           "window_scans": summary.get("window_scans"),
           "windows": len(records), **{lv.lower(): levels.count(lv) for lv in LEVELS},
           "worst_level": worst["level"] if worst else None,
           "worst_time_s": round(worst["end"] - t0, 3) if worst else None,
           "worst_stamp": worst["end"] if worst else None,
           "worst_reason": worst["message"] if worst else None,
           "rot_rate_p50": _quantile([r.get("rot_rate") for r in records], 0.5),
           "rot_rate_p99": _quantile([r.get("rot_rate") for r in records], 0.99),
           "trans_rate_p50": _quantile([r.get("trans_rate") for r in records], 0.5),
           "trans_rate_p99": _quantile([r.get("trans_rate") for r in records], 0.99),
           "episodes_alarmed": alarm_episodes(levels), "wall_s": summary.get("wall_s"),
           "scans_read": summary.get("scans_read"), "notes": summary.get("notes", []),
           "path": task.path, "metrics_png": f"bags/{task.name}/metrics.png" if records else None,
           "worker": _where()}
    return row


def _where() -> str:
    """host:pid of this process, and the Ray node id when it runs as a Ray task."""
    import socket
    import sys

    where = f"{socket.gethostname()}:{os.getpid()}"
    ray = sys.modules.get("ray")  # not imported for it: a local run without Ray stays without it
    try:
        if ray is not None and ray.is_initialized():
            where += f" node {ray.get_runtime_context().get_node_id()[:12]}"
    except Exception:  # noqa: BLE001 - no Ray here: host:pid is enough
        pass
    return where


# ------------------------------------------------------------------ the whole audit
@dataclass
class AuditResult:
    out: Path
    rows: list[dict]
    summary: dict


def code_digest(root: Path = Path(__file__).parent) -> str:
    """sha256 over the package's Python sources (relative name and bytes, in name order): results of other code
    are not reused."""
    h = hashlib.sha256()
    for file in sorted(root.rglob("*.py")):
        h.update(str(file.relative_to(root)).encode() + b"\0" + file.read_bytes() + b"\0")
    return h.hexdigest()


def network_digest(config: Config) -> str | None:
    """weights_digest of the network files a replay with ``config`` loads (None without the network)."""
    return weights_digest(_read(weights_files(config)))


def plan(bags: list[Path], out: Path, config: Config, options: dict | None = None,
         force: bool = False) -> tuple[list[BagTask], list[dict]]:
    """(tasks to run, rows of cached bags): a bag whose manifest holds the same key is cached."""
    common = {"config": config_digest(config), "weights": network_digest(config), "code": code_digest(),
              "options": dict(sorted((options or {}).items())), "format": AUDIT_FORMAT}
    tasks, cached = [], []
    for path, name in zip(bags, bag_names(bags)):
        key = {"bag": bag_digest(path), **common}
        task = BagTask(str(path), name, config, key, dict(options or {}))
        manifest = None if force else _cached_manifest(out / "bags", name, key) or _moved_here(out / "bags", path,
                                                                                              name, key)
        if manifest:
            cached.append({**manifest["row"], "path": str(path), "cached": True})
        else:
            tasks.append(task)
    return tasks, cached


def _cached_manifest(folder: Path, name: str, key: dict) -> dict | None:
    """The manifest of OUT/bags/<name> when it holds ``key`` and the reports its row names are there, else
    None."""
    manifest = _load_manifest(folder / name)
    row = manifest.get("row") if isinstance(manifest, dict) else None
    if not isinstance(row, dict) or manifest.get("key") != key:
        return None
    needed = ["windows.json"] + (["metrics.png"] if row.get("metrics_png") else [])
    return manifest if all((folder / name / f).is_file() for f in needed) else None


def _moved_here(folder: Path, path: Path, name: str, key: dict) -> dict | None:
    """The same bag audited under its other folder name (a bag of the set now shares its name, or no longer
    does: bag_names), moved to ``name`` with its manifest renamed; None when there is none (or ``name`` is
    taken)."""
    base = bag_names([path])[0]
    for other in {base, _hashed_name(base, path)} - {name}:
        manifest = _cached_manifest(folder, other, key)
        if manifest and Path(manifest["row"].get("path", "")).resolve() == path.resolve() \
                and not (folder / name).exists():
            (folder / other).rename(folder / name)
            row = {**manifest["row"], "bag": name}
            if row.get("metrics_png"):
                row["metrics_png"] = f"bags/{name}/metrics.png"
            manifest = {**manifest, "row": row}
            write_json(folder / name / MANIFEST, manifest)
            return manifest
    return None


def _load_manifest(folder: Path) -> dict | None:
    try:
        return json.loads((folder / MANIFEST).read_text())
    except (OSError, ValueError):
        return None


def _store(out: Path, task: BagTask, result: dict | None, error: str | None) -> dict:
    """Write a finished task's reports and manifest under OUT/bags/<name>/; its row (cached: False)."""
    folder = out / "bags" / task.name
    if error is not None:  # the task raised or its worker died: no key, the next audit runs it again
        row = {"bag": task.name, "status": "failed", "reason": error, "path": task.path, "cached": False}
        remove_reports(folder)  # an earlier audit's reports are not this one's
        write_json(folder / MANIFEST, {"key": None, "row": row})
        return row
    remove_reports(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for name, data in result["files"].items():
        tmp = folder / f".{name}.tmp"
        tmp.write_bytes(data)
        tmp.replace(folder / name)
    row = {**result["row"], "cached": False}
    write_json(folder / MANIFEST, {"key": task.key, "row": row})
    return row


def audit(bags: list[str | Path], out: str | Path, config: Config | None = None, engine: str = "ray",
          workers: int = 2, address: str | None = None, options: dict | None = None, force: bool = False,
          progress: bool = True) -> AuditResult:
    """Audit ``bags`` into ``out`` (see the module doc); returns the rows (bag order) and the summary."""
    from . import engine as eng

    config = config or Config()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    paths = [Path(b) for b in bags]
    tasks, cached = plan(paths, out, config, options, force)
    shared = {}
    if engine == "ray" and tasks and tasks[0].key.get("weights"):
        shared["weights"] = _read(weights_files(config))  # to the object store once; checked by digest
    rows = {r["bag"]: r for r in cached}
    for task, result, error in eng.run_tasks(audit_bag, tasks, engine=engine, workers=workers, address=address,
                                             desc="audit", progress=progress, shared=shared):
        rows[task.name] = _store(out, task, result, error)
    ordered = [rows[n] for n in bag_names(paths)]
    summary = {"bags": len(ordered), "ran": len(tasks),  # done + cached + failed = bags
               "done": sum(1 for r in ordered if r["status"] == "ok" and not r.get("cached")),
               "cached": sum(1 for r in ordered if r["status"] == "ok" and r.get("cached")),
               "failed": sum(1 for r in ordered if r["status"] == "failed"),
               "engine": engine, "workers": workers if engine == "ray" and not address else None,
               "address": address or None, "wall_s": round(time.perf_counter() - started, 3),
               "config_digest": config_digest(config), "weights_digest": network_digest(config),
               "segmentation": config.segmentation.mode, "window_size": config.window.setting(),
               "created": time.strftime("%Y-%m-%d %H:%M:%S %Z")}
    write_report(out, ordered, summary, config)
    return AuditResult(out, ordered, summary)


# ------------------------------------------------------------------ the report
def write_report(out: Path, rows: list[dict], summary: dict, config: Config | None = None) -> None:
    """OUT/fleet.csv, OUT/fleet.json and OUT/index.html."""
    from .reports import csv_value

    write_csv(out / "fleet.csv", [{c: csv_value(_text(r.get(c))) if r.get(c) is not None else "" for c in COLUMNS}
                                  for r in rows])
    failed = [{"bag": r["bag"], "path": r.get("path"), "reason": r.get("reason")} for r in rows
              if r["status"] == "failed"]
    write_json(out / "fleet.json", {"summary": summary, "bags": rows, "failed": failed,
                                    "config": flatten(config) if config else None})
    (out / "index.html").write_text(render_html(rows, summary))


LEVEL_CSS = {"OK": "#2e8b57", "WARN": "#f0a030", "ERROR": "#d03020", "failed": "#7a1010"}


def _text(v: Any) -> Any:
    """A report cell: a list (a bag's notes) as one '; '-joined text, anything else as it is."""
    return "; ".join(map(str, v)) if isinstance(v, list) else v


def _cell(row: dict, col: str) -> str:
    v = _text(row.get(col))
    if v is None or v == "":
        return '<td data-v=""></td>'
    if col == "bag":  # its path on hover (bags of one name from two robots are told apart), its plot on click
        title = html.escape(str(row.get("path") or ""))
        if row.get("metrics_png"):
            return (f'<td class="name" data-v="{html.escape(str(v))}" title="{title}"><a href='
                    f'"{html.escape(row["metrics_png"])}">{html.escape(str(v))}</a></td>')
        return f'<td class="name" data-v="{html.escape(str(v))}" title="{title}">{html.escape(str(v))}</td>'
    if isinstance(v, bool):
        text = "yes" if v else "no"
    elif isinstance(v, float):
        text = f"{v:.4g}"
    else:
        text = str(v)
    cls = ' class="txt"' if col in ("reason", "worst_reason", "notes") else ""
    if col in ("worst_level", "status") and v in LEVEL_CSS:
        cls = f' class="lv-{v}"'
    return f'<td data-v="{html.escape(str(v))}"{cls}>{html.escape(text)}</td>'


def _scans(window_size: Any) -> str:
    """A summary's window_size in words: "10 scans", or as written ("automatic (1 s)")."""
    return f"{window_size} scans" if isinstance(window_size, int) else str(window_size)


def render_html(rows: list[dict], summary: dict) -> str:
    """index.html: one self-contained page (inline CSS and JS, no network): the fleet table, sortable by
    clicking a header (numbers as numbers), level colours, each bag linking its metrics.png; failed bags
    with their reason."""
    cols = [c for c in COLUMNS if c not in ("path", "metrics_png", "worker")]
    head = "".join(f'<th onclick="sortBy({i})" title="sort">{html.escape(c)}</th>' for i, c in enumerate(cols))
    body = "\n".join(f'<tr class="st-{html.escape(r["status"])}">' + "".join(_cell(r, c) for c in cols) + "</tr>"
                     for r in rows)
    failed = [r for r in rows if r["status"] == "failed"]
    fail_html = ("<h2>Failed bags</h2>\n<ul id=\"failed\">" + "".join(
        f"<li><b>{html.escape(r['bag'])}</b> ({html.escape(str(r.get('path', '')))}): {html.escape(str(r.get('reason', '')))}</li>"
        for r in failed) + "</ul>") if failed else "<h2>Failed bags</h2>\n<p id=\"failed\">none</p>"
    css = "".join(f"tr td.lv-{k}{{background:{c};color:#fff}}" for k, c in LEVEL_CSS.items())
    s = summary
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>topometric fleet audit</title>
<style>
body{{font-family:sans-serif;margin:1.5em;font-size:13px}} table{{border-collapse:collapse}}
th,td{{border:1px solid #ccc;padding:3px 6px;text-align:right;white-space:nowrap}}
td.txt{{text-align:left;white-space:normal;min-width:16em;max-width:30em}} td.name{{text-align:left}}
th{{background:#eee;cursor:pointer;user-select:none}} th:hover{{background:#ddd}}
tr.st-failed td{{background:#fbe9e7}} {css}
</style></head><body>
<h1>topometric fleet audit</h1>
<p id="summary">{s['bags']} bag{'s' * (s['bags'] != 1)}: {s['done']} done, {s['cached']} cached, {s['failed']} failed; engine {html.escape(str(s['engine']))}{'' if s.get('workers') is None else f", {s['workers']} worker{'s' * (s['workers'] != 1)}"}{'' if not s.get('address') else f", cluster {html.escape(str(s['address']))}"};
segmentation {html.escape(str(s.get('segmentation')))}, window {html.escape(_scans(s.get('window_size')))}; config {str(s.get('config_digest'))[:12]};
{html.escape(str(s.get('created')))}. Rates: rotation °/s, translation m/s; worst_time_s: since the bag's first window's start.
Click a header to sort (or open index.html#sort=COLUMN, #sort=-COLUMN descending); a bag's name opens its metrics.png.</p>
<table id="fleet"><thead><tr>{head}</tr></thead>
<tbody>
{body}
</tbody></table>
{fail_html}
<script>
var dir = {{}};
function sortBy(col) {{
  var tb = document.querySelector('#fleet tbody'), rows = Array.from(tb.rows);
  dir[col] = -(dir[col] || -1);
  var key = function (r) {{ var v = r.cells[col].dataset.v;
    return /^-?[0-9]+([.][0-9]*)?([eE][-+]?[0-9]+)?$/.test(v) ? parseFloat(v) : v; }};
  rows.sort(function (a, b) {{ var x = key(a), y = key(b);
    if (x === '' || x === undefined) return 1; if (y === '' || y === undefined) return -1;
    if (typeof x === typeof y) return (x < y ? -1 : x > y ? 1 : 0) * dir[col];
    return (typeof x === 'number' ? -1 : 1) * dir[col]; }});
  rows.forEach(function (r) {{ tb.appendChild(r); }});
}}
// index.html#sort=COLUMN (ascending) or #sort=-COLUMN (descending): a link that opens the table sorted
(function () {{
  var m = /sort=(-?)([a-z0-9_]+)/.exec(location.hash); if (!m) return;
  var names = Array.from(document.querySelectorAll('#fleet th')).map(function (th) {{ return th.textContent; }});
  var col = names.indexOf(m[2]); if (col < 0) return;
  dir[col] = m[1] ? 1 : -1; sortBy(col);
}})();
</script>
</body></html>
"""


def format_summary(res: AuditResult) -> str:
    """The CLI's closing lines: counts, failed bags with their reasons, damage and input left out, where the
    report is."""
    from .replay import LEFT_OUT

    s = res.summary
    lines = [f"audit: {s['bags']} bag{'s' * (s['bags'] != 1)}: {s['done']} done, {s['cached']} cached, "
             f"{s['failed']} failed "
             f"({s['wall_s']:.1f} s, engine {s['engine']}"
             + (f", {s['workers']} worker{'s' * (s['workers'] != 1)}" if s.get("workers") else "")
             + (f", cluster {s['address']}" if s.get("address") else "") + ")"]
    lines += [f"  FAILED {r['bag']}: {r.get('reason')}" for r in res.rows if r["status"] == "failed"]
    lines += [f"  note {r['bag']}: {n}" for r in res.rows if r["status"] == "ok"
              for n in r.get("notes", []) if n.startswith(("damaged bag", LEFT_OUT))]
    lines.append(f"report: {res.out / 'index.html'}, {res.out / 'fleet.csv'}, {res.out / 'fleet.json'}")
    return "\n".join(lines)
