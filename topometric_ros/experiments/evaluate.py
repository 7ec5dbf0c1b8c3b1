"""The paper's noise experiment: every metric against RPE over windows of perturbed poses.

For each scene and trajectory (simulated in memory, ground-truth poses), each scan is segmented and its planes
detected ONCE (per label source: the shipped network, and ground-truth labels for comparison). Then for every
setting (label source, window size, noise mode r / t / rt, scale) each window's poses are perturbed, per pose,
by noise whose magnitude is drawn per window, σ = u · scale · base with u ~ U(0, 1) (base: sim/drift.py
BASE_NOISE_ROT_DEG, BASE_NOISE_TRANS_M), so the windows' RPE spans a range. PNE and CPV are scored on every
window; MME, MPV and MOM (which need every point) on a seeded random subset of windows. Correlations of each
metric with RPE (Pearson, Spearman, Kendall) and Multi-relation(PNE, CPV, RPE) are computed per setting.

Work is split into jobs written as CSV files under OUT/runs/: a finished job is never recomputed (resumable),
and jobs run on engine.run_tasks (Ray tasks: a local Ray with ``workers`` CPUs or a cluster at ``address``;
or ``engine="local"``, one after another in this process).
"""
from __future__ import annotations

import hashlib
import json
import pickle
import time
from dataclasses import asdict, dataclass, replace
from functools import lru_cache
from pathlib import Path

import numpy as np

from .. import geometry
from ..reports import pyplot, write_csv, written_whole
from ..sim.drift import BASE_NOISE_ROT_DEG, BASE_NOISE_TRANS_M

METRICS = ("mme", "mpv", "mom", "pne", "cpv")
BASELINES = ("mme", "mpv", "mom")
NOISE_SIGMAS = {"r": (1.0, 0.0), "t": (0.0, 1.0), "rt": (1.0, 1.0)}  # which of (rotation, translation) is on
BASELINE_JOB = "baselines"  # the job kind that computes MME/MPV/MOM (label independent)
TRAJECTORY_SEED0 = 2000  # evaluation trajectories: seeds 2000.. (training bags use 0.. and 1000..)


@dataclass(frozen=True)
class ExperimentSpec:
    """What to run. frames: scans per trajectory (5 Hz). baseline_windows: windows per (trajectory, setting) that
    also get MME/MPV/MOM. labels: label sources, 'network' (shipped segmentation) and/or 'gt'."""

    scenes: tuple = ("floor2", "garage")
    trajectories: int = 2
    frames: int = 300
    windows: tuple = (5, 10, 15)
    noises: tuple = ("r", "t", "rt")
    scales: tuple = (1.0, 1.5, 2.0)
    labels: tuple = ("network", "gt")
    correlation_window: int = 5
    baseline_windows: int = 8
    radius: float = 1.0
    seed: int = 0

    def __post_init__(self) -> None:
        """ValueError for an experiment that cannot run: nothing to run, an unknown noise mode or label source, or
        trajectories too short for one window."""
        empty = [name for name in ("scenes", "windows", "noises", "scales", "labels") if not getattr(self, name)]
        if empty:
            raise ValueError(f"give at least one of each: {', '.join(empty)}")
        bad = [n for n in self.noises if n not in NOISE_SIGMAS] + [x for x in self.labels if x not in ("network", "gt")]
        if bad:
            raise ValueError(f"unknown noise mode or label source: {', '.join(bad)} (noise: r, t, rt; labels: "
                             "network, gt)")
        if self.frames < max(self.windows):
            raise ValueError(f"--frames {self.frames} holds no window of {max(self.windows)} scans (--win); give at "
                             f"least {max(self.windows)}")

    @classmethod
    def quick(cls) -> "ExperimentSpec":
        """A tiny run for CI: one office room, one trajectory, window 5 only, ground-truth labels."""
        return cls(scenes=("office1",), trajectories=1, frames=100, windows=(5,), labels=("gt",), baseline_windows=1)


def default_out(spec: ExperimentSpec, quick: bool = False) -> str:
    """Where an experiment writes without --out: out/evaluate_quick for --quick, results/ (the shipped report) for
    the full experiment only, out/evaluate for any other."""
    return "out/evaluate_quick" if quick else "results" if spec == ExperimentSpec() else "out/evaluate"


# ---------------------------------------------------------------- per-scan work (once per trajectory)

def _frames(scene: str, traj: int, spec: ExperimentSpec):
    from ..sim.frames import simulated_frames

    frames, _ = simulated_frames(scene, spec.frames, rate=5.0, speed=1.0, seed=TRAJECTORY_SEED0 + traj)
    return frames


def _scan_cache(out: Path, scene: str, traj: int, labels: str, spec: ExperimentSpec) -> Path:
    """Pickle of the trajectory's ProcessedScans (planes only, no points); computed once."""
    path = out / "cache" / f"{scene}_{traj}_{_label_tag(labels)}.pkl"
    if path.exists():
        return path
    from ..config import load_config
    from ..pipeline import process_scan

    config = load_config(overrides={"segmentation.mode": "network" if labels == "network" else "labels"})
    segmenter = None
    if labels == "network":
        from ..segmentation.infer import Segmenter

        segmenter = Segmenter.from_config(config.segmentation)
    scans = [replace(process_scan(f, config, segmenter, i), points=None, labels=None)
             for i, f in enumerate(_frames(scene, traj, spec))]
    path.parent.mkdir(parents=True, exist_ok=True)
    with written_whole(path) as tmp:
        tmp.write_bytes(pickle.dumps(scans))
    return path


# ---------------------------------------------------------------- one setting (label source, window, noise, scale)

def _perturb(poses: np.ndarray, noise: str, scale: float, rng: np.random.Generator) -> np.ndarray:
    """Each pose times an independent perturbation; magnitude u·scale·base with u ~ U(0, 1) per window."""
    on_r, on_t = NOISE_SIGMAS[noise]
    u = rng.uniform(0.0, 1.0)
    noise_t = geometry.noise_transforms(len(poses), np.radians(BASE_NOISE_ROT_DEG) * scale * u * on_r,
                                        BASE_NOISE_TRANS_M * scale * u * on_t, rng)
    return poses @ noise_t


def _label_tag(labels: str) -> str:
    """Name of a label source in cached files: 'network' carries the shipped weights' digest, so new weights
    recompute its scans and jobs while ground truth and baselines are kept."""
    if labels != "network":
        return labels
    from ..segmentation.checkpoint import SHIPPED

    return f"network-{_file_digest(str(SHIPPED))}"


@lru_cache(maxsize=None)
def _file_digest(path: str) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:8]


def _job_name(source: str, scene: str, traj: int, win: int, noise: str, scale: float) -> str:
    """source: a label source (PNE/CPV job) or BASELINE_JOB (MME/MPV/MOM, which use every point, not labels)."""
    return f"{_label_tag(source)}_{scene}_{traj}_w{win}_{noise}_{scale:g}"


def _setting_seed(spec: ExperimentSpec, scene: str, traj: int, win: int, noise: str, scale: float) -> list[int]:
    """Seed of one setting (the same for every label source and the baselines)."""
    return [spec.seed, traj, win, ["r", "t", "rt"].index(noise), int(scale * 100), sum(map(ord, scene))]


def _perturbed_windows(gt: np.ndarray, spec: ExperimentSpec, scene: str, traj: int, win: int, noise: str,
                       scale: float) -> list[np.ndarray]:
    """Estimated poses of every window of a trajectory (gt: (N, 4, 4)) under one setting. Seeded by the setting
    only, so every label source and the baselines see the same perturbed windows."""
    rng = np.random.default_rng(_setting_seed(spec, scene, traj, win, noise, scale))
    return [_perturb(gt[w * win:(w + 1) * win], noise, scale, rng) for w in range(len(gt) // win)]


def _baseline_windows(spec: ExperimentSpec, scene: str, traj: int, win: int, noise: str, scale: float,
                      n_windows: int) -> list[int]:
    """The seeded random subset of windows that get MME/MPV/MOM."""
    seed = _setting_seed(spec, scene, traj, win, noise, scale) + [1]
    k = min(spec.baseline_windows, n_windows)
    return sorted(np.random.default_rng(seed).choice(n_windows, k, replace=False).tolist())


def _run_job(out: Path, spec: ExperimentSpec, source: str, scene: str, traj: int, win: int, noise: str,
             scale: float) -> Path:
    """Score every window of one trajectory under one setting; writes OUT/runs/<job>.csv."""
    path = out / "runs" / f"{_job_name(source, scene, traj, win, noise, scale)}.csv"
    if not path.exists():
        rows = (_baseline_rows if source == BASELINE_JOB else _plane_rows)(out, spec, source, scene, traj, win, noise,
                                                                          scale)
        write_csv(path, rows)
    return path


def _plane_rows(out: Path, spec: ExperimentSpec, labels: str, scene: str, traj: int, win: int, noise: str,
                scale: float) -> list[dict]:
    """Per window: RPE (Eq. 4 and its parts), PNE, CPV, plane counts and times, from the cached scans."""
    from ..config import load_config
    from ..metrics.rpe import rpe, rpe_parts
    from ..pipeline import score_window

    scans = pickle.loads(_scan_cache(out, scene, traj, labels, spec).read_bytes())
    config = load_config()
    gt = np.stack([s.pose for s in scans])
    rows = []
    for w, est in enumerate(_perturbed_windows(gt, spec, scene, traj, win, noise, scale)):
        window = scans[w * win:(w + 1) * win]
        result = score_window([replace(s, pose=p) for s, p in zip(window, est)], config)
        gt_w = gt[w * win:(w + 1) * win]
        rot_deg, trans_m = rpe_parts(gt_w, est)
        rows.append({"window": w, "rpe": rpe(gt_w, est), "rpe_rot_deg": rot_deg, "rpe_trans_m": trans_m,
                     "pne": result.pne, "cpv": result.cpv, "n_planes": result.n_planes, "n_groups": result.n_groups,
                     "t_pne_ms": result.timings["pne"], "t_cpv_ms": result.timings["cpv"]})
    return rows


def _baseline_rows(out: Path, spec: ExperimentSpec, _source: str, scene: str, traj: int, win: int, noise: str,
                   scale: float) -> list[dict]:
    """MME, MPV, MOM and their times on the seeded subset of windows (every point of the scans, no labels)."""
    from ..config import load_config
    from ..pipeline import baselines

    config = load_config(overrides={"metrics.radius": spec.radius})  # fast MME/MPV (exact_baselines off)
    frames = _frames(scene, traj, spec)
    gt = np.stack([f.pose for f in frames])
    windows = _perturbed_windows(gt, spec, scene, traj, win, noise, scale)
    rows = []
    for w in _baseline_windows(spec, scene, traj, win, noise, scale, len(windows)):
        values = baselines([f.points for f in frames[w * win:(w + 1) * win]], windows[w], config.metrics)
        rows.append({"window": w, **{k if k in BASELINES else f"{k}_ms": v for k, v in values.items()}})
    return rows


def _read_csv(path: Path) -> dict[str, np.ndarray]:
    data = np.genfromtxt(path, delimiter=",", names=True, dtype=float)
    return {k: np.atleast_1d(data[k]) for k in data.dtype.names}


# ---------------------------------------------------------------- the whole experiment

def jobs(spec: ExperimentSpec) -> list[tuple]:
    """(source, scene, traj, win, noise, scale) of every job: one per label source (PNE, CPV) and one for the
    baselines. Windows other than the correlation window are run for timing (rt noise at the first scale)."""
    out = []
    for source in (*spec.labels, BASELINE_JOB):
        for scene in spec.scenes:
            for traj in range(spec.trajectories):
                for win in spec.windows:
                    settings = ([(n, s) for n in spec.noises for s in spec.scales] if win == spec.correlation_window
                                else [("rt", spec.scales[0])])
                    out += [(source, scene, traj, win, n, s) for n, s in settings]
    return out


def _cache_task(job: tuple) -> Path:
    return _scan_cache(*job)


def _job_task(job: tuple) -> Path:
    return _run_job(*job)


def _all(results, what: str) -> None:
    """Consume engine.run_tasks; the first failed job ends the experiment with its reason."""
    for item, _, error in results:
        if error is not None:
            raise RuntimeError(f"{what} {item[2:] if what == 'job' else item[1:4]} failed: {error}")


def run(spec: ExperimentSpec, out: str | Path, workers: int = 2, progress: bool = True, engine: str = "ray",
        address: str | None = None) -> dict:
    """Run (or resume) the experiment into ``out``; returns the paths of what it wrote. The jobs run on
    engine.run_tasks (``engine``, ``workers``, ``address``)."""
    from ..engine import ensure_ray, run_tasks

    out = Path(out)
    _same_runs(spec, out)
    started = time.perf_counter()
    todo = [j for j in jobs(spec) if not (out / "runs" / f"{_job_name(*j)}.csv").exists()]
    if engine == "ray" and todo:
        ensure_ray(workers, address)  # an unreachable cluster is refused before anything is written
    out.mkdir(parents=True, exist_ok=True)
    (out / "spec.json").write_text(json.dumps(asdict(spec), indent=2))
    caches = sorted({(j[1], j[2], j[0]) for j in todo if j[0] != BASELINE_JOB})
    todo.sort(key=lambda j: j[0] != BASELINE_JOB)  # the long baseline jobs first, so the workers end evenly
    kw = dict(engine=engine, workers=workers, address=address, progress=progress)
    _all(run_tasks(_cache_task, [(out, scene, traj, labels, spec) for scene, traj, labels in caches],
                   desc="scans (segment + planes)", **kw), "scan cache")
    _all(run_tasks(_job_task, [(out, spec, *j) for j in todo], desc="settings", **kw), "job")
    paths = write_tables(spec, out)
    paths["elapsed_s"] = round(time.perf_counter() - started, 1)
    paths["reused"], paths["settings"] = len(jobs(spec)) - len(todo), len(jobs(spec))
    return paths


#: ExperimentSpec fields that shape every stored run but are not in the run files' names.
RUN_SHAPING = ("frames", "seed", "radius", "baseline_windows")


def _same_runs(spec: ExperimentSpec, out: Path) -> None:
    """ValueError when ``out`` holds runs made with other RUN_SHAPING settings: reusing them would report
    the old numbers under the new spec."""
    path = out / "spec.json"
    if not path.is_file():
        return
    old = json.loads(path.read_text())
    if not (out / "runs").is_dir():  # a report without its runs (the shipped results/): only the same experiment
        if (out / "REPORT.md").is_file() and old != json.loads(json.dumps(asdict(spec))):
            raise ValueError(f"{out} holds the report of another experiment ({path}) without its runs: give another "
                             "--out, or remove it to replace that report")
        return
    differ = [f"{k} {old.get(k)!r} (now {getattr(spec, k)!r})" for k in RUN_SHAPING if old.get(k) != getattr(spec, k)]
    if differ:
        raise ValueError(f"{out} holds runs made with {', '.join(differ)}: give another --out, or remove {out} to "
                         "compute them again")


def load_runs(spec: ExperimentSpec, out: Path) -> list[tuple[tuple, dict[str, np.ndarray]]]:
    """(job, per-window columns) of every label-source job, with the baselines of the same perturbed windows
    joined in (NaN on windows without baselines)."""
    runs = []
    for job in jobs(spec):
        if job[0] == BASELINE_JOB:
            continue
        data = _read_csv(out / "runs" / f"{_job_name(*job)}.csv")
        base_path = out / "runs" / f"{_job_name(BASELINE_JOB, *job[1:])}.csv"
        base = _read_csv(base_path) if base_path.read_text().count("\n") > 1 else None  # header only: no windows
        for column in (*BASELINES, *(f"t_{m}_ms" for m in BASELINES)):
            data[column] = np.full(len(data["window"]), np.nan)
            if base is not None:
                data[column][np.searchsorted(data["window"], base["window"])] = base[column]
        runs.append((job, data))
    return runs


def _select(runs, labels: str, win: int, noise: str, scale: float) -> list[dict[str, np.ndarray]]:
    """The per-window tables of every trajectory run under one setting."""
    return [d for (lab, _, _, w, n, s), d in runs if lab == labels and w == win and n == noise and s == scale]


POOLS = ("all", "common", "per-trajectory")  # how windows are pooled in the tables (see correlation_table)
PLANE_METRICS = ("pne", "cpv")


def _pools(sel: list[dict[str, np.ndarray]]) -> dict[str, list[dict[str, np.ndarray]]]:
    """The windows of one setting three ways: 'all' (every trajectory's windows together), 'common' (only the
    windows that have every metric, the fair comparison with the baselines) and 'per-trajectory' (one group
    per trajectory: scene content sets each trajectory's metric level, which pooling mixes into the ranks)."""
    cat = {k: np.concatenate([d[k] for d in sel]) for k in sel[0]}
    common = np.all([np.isfinite(cat[m]) for m in METRICS], axis=0)
    return {"all": [cat], "common": [{k: v[common] for k, v in cat.items()}], "per-trajectory": sel}


def _median_of(groups: list[dict[str, np.ndarray]], fn, metrics: tuple) -> tuple[float, int]:
    """Median over groups of fn(*columns) on each group's windows where all ``metrics`` are finite, and the
    median number of windows used."""
    values, sizes = [], []
    for g in groups:
        ok = np.all([np.isfinite(g[m]) for m in metrics], axis=0)
        sizes.append(int(ok.sum()))
        values.append(fn(*(g[m][ok] for m in metrics)) if ok.sum() >= 3 else np.nan)
    return float(np.nanmedian(values)) if np.isfinite(values).any() else float("nan"), int(np.median(sizes))


def _rank_multi_relation(*variables) -> float:
    from ..correlation import multi_relation

    return multi_relation(*variables, ranks=True)


def main_pool(spec: ExperimentSpec) -> str:
    """The pooling the claims are checked on: 'common' (all five metrics on the same windows) when the
    baselines cover at least 20 windows per setting, else 'all'."""
    return "common" if spec.baseline_windows * spec.trajectories * len(spec.scenes) >= 20 else "all"


def correlation_table(spec: ExperimentSpec, runs) -> list[dict]:
    """Rows (labels, noise, scale, windows, metric, n, pearson, spearman, kendall) at the correlation window size,
    for each way of pooling windows (POOLS; per-trajectory rows are medians over trajectories and only for PNE
    and CPV, the baselines having too few windows per trajectory). n: windows (per trajectory for medians)."""
    from ..correlation import kendall, pearson, spearman

    rows = []
    for labels in spec.labels:
        for noise in spec.noises:
            for scale in spec.scales:
                for pool, groups in _pools(_select(runs, labels, spec.correlation_window, noise, scale)).items():
                    for metric in PLANE_METRICS if pool == "per-trajectory" else METRICS:
                        row = {"labels": labels, "noise": noise, "scale": scale, "windows": pool, "metric": metric}
                        for name, fn in (("pearson", pearson), ("spearman", spearman), ("kendall", kendall)):
                            row[name], row["n"] = _median_of(groups, fn, (metric, "rpe"))
                        rows.append(row)
    return rows


def multirelation_table(spec: ExperimentSpec, runs) -> list[dict]:
    """Multi-relation(PNE, CPV, RPE), (PNE, RPE), (CPV, RPE) per label source, noise, scale and window pooling
    ('all' and 'per-trajectory' median; see _pools); also MR(PNE, CPV, RPE) of ranks, which separates monotone
    but non-linear dependence (PNE is logarithmic in the normal spread, CPV quadratic in offsets) from none."""
    from ..correlation import multi_relation

    rows = []
    for labels in spec.labels:
        for noise in spec.noises:
            for scale in spec.scales:
                pools = _pools(_select(runs, labels, spec.correlation_window, noise, scale))
                for pool in ("all", "per-trajectory"):
                    row = {"labels": labels, "noise": noise, "scale": scale, "windows": pool}
                    for name, metrics in (("mr_pne_cpv_rpe", ("pne", "cpv", "rpe")), ("mr_pne_rpe", ("pne", "rpe")),
                                          ("mr_cpv_rpe", ("cpv", "rpe"))):
                        row[name], row["n"] = _median_of(pools[pool], multi_relation, metrics)
                    row["mr_pne_cpv_rpe_ranks"], _ = _median_of(pools[pool], _rank_multi_relation,
                                                                ("pne", "cpv", "rpe"))
                    rows.append(row)
    return rows


def timing_table(spec: ExperimentSpec, runs) -> list[dict]:
    """Per metric and window size: median / p90 / max ms per window, single thread (PNE, CPV: planes cached)."""
    rows = []
    for win in spec.windows:
        sel = [d for (lab, _, _, w, _, _), d in runs if w == win and lab == spec.labels[0]]
        for metric in METRICS + ("pne+cpv",):
            if metric == "pne+cpv":
                t = np.concatenate([d["t_pne_ms"] + d["t_cpv_ms"] for d in sel])
            else:
                t = np.concatenate([d[f"t_{metric}_ms"] for d in sel])
            t = t[np.isfinite(t)]
            if len(t):
                rows.append({"window": win, "metric": metric, "n": len(t), "median_ms": float(np.median(t)),
                             "p90_ms": float(np.quantile(t, 0.9)), "max_ms": float(t.max())})
    return rows


def write_tables(spec: ExperimentSpec, out: Path) -> dict:
    """correlations.csv, multirelation.csv, timing.csv, the figures and REPORT.md from the finished runs."""
    runs = load_runs(spec, out)
    tables = {"correlations": correlation_table(spec, runs), "multirelation": multirelation_table(spec, runs),
              "timing": timing_table(spec, runs)}
    paths = {}
    for name, rows in tables.items():
        write_csv(out / f"{name}.csv", rows)
        paths[name] = str(out / f"{name}.csv")
    paths.update(figures(spec, tables, runs, out))
    paths["report"] = str(report(spec, tables, paths, out))
    return paths


# ---------------------------------------------------------------- figures and report

def figures(spec: ExperimentSpec, tables: dict, runs, out: Path) -> dict:
    """PNGs in the paper's style: grouped correlation bars (Figs. 8-10), Multi-relation (Fig. 11), time per
    window size (Fig. 12), and PNE/CPV-vs-RPE scatter plots."""
    plt = pyplot()
    paths = {}
    corr = tables["correlations"]
    pool = main_pool(spec)
    for labels in spec.labels:
        fig, axes = plt.subplots(len(spec.noises), 3, figsize=(12, 3 * len(spec.noises)), squeeze=False)
        for i, noise in enumerate(spec.noises):
            for j, kind in enumerate(("pearson", "spearman", "kendall")):
                ax = axes[i, j]
                width = 0.8 / len(spec.scales)
                for k, scale in enumerate(spec.scales):
                    vals = [next((r[kind] for r in corr if r["labels"] == labels and r["noise"] == noise
                                  and r["scale"] == scale and r["metric"] == m and r["windows"] == pool), np.nan)
                            for m in METRICS]
                    ax.bar(np.arange(len(METRICS)) + (k - (len(spec.scales) - 1) / 2) * width, vals, width,
                           label=f"scale {scale:g}")
                ax.set_xticks(range(len(METRICS)), [m.upper() for m in METRICS])
                ax.axhline(0, color="k", lw=0.5)
                ax.set_ylim(-1, 1)
                ax.set_title(f"{kind.capitalize()} with RPE, noise {noise}")
        axes[0, 0].legend(fontsize=8)
        fig.suptitle(f"Correlation of each metric with RPE (window {spec.correlation_window}, labels: {labels}, "
                     f"windows: {pool})")
        fig.tight_layout()
        paths[f"fig_correlations_{labels}"] = _save(fig, out / f"correlations_{labels}.png")

    fig, ax = plt.subplots(figsize=(8, 3.8))
    mr = tables["multirelation"]
    groups = [(n, s) for n in spec.noises for s in spec.scales]
    bars = [(labels, pool) for labels in spec.labels for pool in ("all", "per-trajectory")]
    width = 0.8 / len(bars)
    for k, (labels, pool) in enumerate(bars):
        vals = [next(r["mr_pne_cpv_rpe"] for r in mr if r["labels"] == labels and r["noise"] == n and r["scale"] == s
                     and r["windows"] == pool) for n, s in groups]
        ax.bar(np.arange(len(groups)) + (k - (len(bars) - 1) / 2) * width, vals, width,
               label=f"labels: {labels}, windows: {pool}")
    ax.set_xticks(range(len(groups)), [f"{n} ×{s:g}" for n, s in groups])
    ax.axhline(0.9, color="gray", ls="--", lw=0.8)
    ax.set_ylim(0, 1)
    ax.set_ylabel("Multi-relation(PNE, CPV, RPE)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    paths["fig_multirelation"] = _save(fig, out / "multirelation.png")

    fig, axes = plt.subplots(1, len(METRICS), figsize=(3 * len(METRICS), 3.5), squeeze=False)
    for ax, metric in zip(axes[0], METRICS):
        data = []
        for win in spec.windows:
            t = np.concatenate([d[f"t_{metric}_ms"] for (lab, _, _, w, _, _), d in runs
                                if w == win and lab == spec.labels[0]])
            data.append(t[np.isfinite(t)])
        ax.boxplot(data, tick_labels=[str(w) for w in spec.windows])
        ax.set_yscale("log")
        ax.set_title(metric.upper())
        ax.set_xlabel("window (scans)")
    axes[0, 0].set_ylabel("time per window (ms, one thread)")
    fig.tight_layout()
    paths["fig_timing"] = _save(fig, out / "timing.png")

    fig, axes = plt.subplots(2, len(spec.noises), figsize=(4 * len(spec.noises), 6.5), squeeze=False)
    for j, noise in enumerate(spec.noises):
        sel = [(scale, d) for (lab, _, _, w, n, scale), d in runs
               if lab == spec.labels[0] and w == spec.correlation_window and n == noise]
        for i, (metric, unit) in enumerate((("pne", "PNE (nats)"), ("cpv", "CPV (m²)"))):
            colours = {}
            for scale, d in sel:  # one colour per noise scale, each trajectory's windows in it
                first = scale not in colours
                colours.setdefault(scale, f"C{len(colours)}")
                axes[i, j].scatter(d["rpe"], d[metric], s=4, alpha=0.4, color=colours[scale],
                                   label=f"noise ×{scale:g}" if first else None)
            axes[i, j].set_title(f"{metric.upper()} vs RPE, noise {noise}")
            axes[i, j].set_xlabel("RPE (Eq. 4)")
            axes[i, j].set_ylabel(unit)
            axes[i, j].legend(fontsize=7, markerscale=3)
    fig.tight_layout()
    paths["fig_scatter"] = _save(fig, out / "scatter.png")
    return paths


def _save(fig, path: Path) -> str:
    fig.savefig(path, dpi=110)
    pyplot().close(fig)
    return str(path)


def _fmt(x) -> str:
    return "—" if x is None or not np.isfinite(x) else f"{x:.3f}"


def claims(spec: ExperimentSpec, tables: dict, labels: str) -> list[str]:
    """The paper's claims checked on these tables, one line each (holds / does not hold, with the numbers):
    best metric among all five on the main pooling, PNE vs CPV per trajectory, Multi-relation both ways."""
    corr = [r for r in tables["correlations"] if r["labels"] == labels]
    lines = []
    for noise, best in (("r", "pne"), ("t", "cpv")):
        if noise not in spec.noises:
            continue
        for scale in spec.scales:
            for pool in (main_pool(spec), "per-trajectory"):
                rows = {r["metric"]: r["spearman"] for r in corr
                        if r["noise"] == noise and r["scale"] == scale and r["windows"] == pool}
                measured = {m: v for m, v in rows.items() if np.isfinite(v)}
                if best not in measured or len(measured) < 2:  # nothing to compare: no verdict
                    verdict = "undefined (too few metrics measured)"
                else:
                    verdict = "holds" if max(measured, key=measured.get) == best else "does NOT hold"
                lines.append(f"- noise {noise} ×{scale:g}, windows {pool}: {best.upper()} has the highest Spearman of "
                             f"{'/'.join(m.upper() for m in measured) or 'the metrics (none measured)'} — {verdict} "
                             f"({', '.join(f'{m.upper()} {_fmt(v)}' for m, v in rows.items())})")
    for r in tables["multirelation"]:
        if r["labels"] == labels and r["noise"] == "rt":
            verdict = ("undefined" if not np.isfinite(r["mr_pne_cpv_rpe"])
                       else "holds" if r["mr_pne_cpv_rpe"] >= 0.9 else "does NOT hold")
            lines.append(f"- noise rt ×{r['scale']:g}, windows {r['windows']}: Multi-relation(PNE, CPV, RPE) = "
                         f"{_fmt(r['mr_pne_cpv_rpe'])} ≥ 0.9 — {verdict}")
    return lines


def _markdown(rows: list[dict], columns: list[str]) -> str:
    head = "| " + " | ".join(columns) + " |\n|" + "---|" * len(columns) + "\n"
    return head + "\n".join("| " + " | ".join(_fmt(r[c]) if isinstance(r[c], float) else str(r[c]) for c in columns)
                            + " |" for r in rows)


def spearman_pivot(spec: ExperimentSpec, tables: dict, labels: str, pool: str) -> str:
    """Markdown: rows noise × scale, columns metrics, Spearman with RPE (windows pooled as ``pool``)."""
    rows = []
    for noise in spec.noises:
        for scale in spec.scales:
            row = {"noise": noise, "scale": f"{scale:g}"}
            for r in tables["correlations"]:
                if r["labels"] == labels and r["noise"] == noise and r["scale"] == scale and r["windows"] == pool:
                    row[r["metric"].upper()] = r["spearman"]
            rows.append(row)
    cols = ["noise", "scale"] + [m.upper() for m in METRICS if any(m.upper() in r for r in rows)]
    return _markdown([{c: r.get(c, np.nan) for c in cols} for r in rows], cols)


MR_COLUMNS = ["labels", "noise", "scale", "windows", "n", "mr_pne_cpv_rpe", "mr_pne_rpe", "mr_cpv_rpe",
              "mr_pne_cpv_rpe_ranks"]


def _data_section(spec: ExperimentSpec) -> list[str]:
    """What was run: scenes, trajectories, noise model, baselines subset, pooling of windows."""
    scales = ", ".join(f"{s:g}" for s in spec.scales)
    return [f"Data: simulated VLP-32C scans (5 Hz) in {', '.join(spec.scenes)}, {spec.trajectories} "
            f"{'trajectory' if spec.trajectories == 1 else 'trajectories'} "
            f"each (seeds {TRAJECTORY_SEED0}..), {spec.frames} scans per trajectory. Windows of "
            f"{', '.join(map(str, spec.windows))} scans, step = size; correlations at window "
            f"{spec.correlation_window}.",
            f"Noise: every pose of a window is perturbed independently; per window σ = u · scale · base, "
            f"u ~ U(0, 1), base {BASE_NOISE_ROT_DEG}° rotation (about a random axis) and {BASE_NOISE_TRANS_M} m "
            f"translation per axis; modes {', '.join(spec.noises)}, scales {scales}.",
            f"MME, MPV, MOM (radius {spec.radius} m, fast MME/MPV) on a seeded random subset of "
            f"{spec.baseline_windows} windows per trajectory and setting (label independent: the same perturbed "
            f"windows for every label source); PNE and CPV on every window. RPE: Eq. 4. "
            f"Network labels: weights {_label_tag('network')}.",
            "Windows are pooled three ways: 'all' (every window of every trajectory), 'common' (only the windows "
            "that have all five metrics: the fair comparison with the baselines) and 'per-trajectory' (the median "
            "over trajectories of each trajectory's correlation, PNE and CPV only).\n"]


def report(spec: ExperimentSpec, tables: dict, paths: dict, out: Path) -> Path:
    """OUT/REPORT.md: data, noise levels, tables, the paper's claims checked, figures."""
    text = ["# Noise experiment: map-consistency metrics against RPE\n", *_data_section(spec)]
    for labels in spec.labels:
        text += [f"## Spearman correlation with RPE (labels: {labels})\n",
                 f"Windows: {main_pool(spec)}\n", spearman_pivot(spec, tables, labels, main_pool(spec)), "",
                 "Windows: per-trajectory (median over trajectories)\n",
                 spearman_pivot(spec, tables, labels, "per-trajectory"), "",
                 "Claims of the paper on this data:\n", *claims(spec, tables, labels), "",
                 f"![correlations]({Path(paths[f'fig_correlations_{labels}']).name})\n"]
    text += ["## Multi-relation\n", _markdown(tables["multirelation"], MR_COLUMNS), "",
             "![multirelation](multirelation.png)\n",
             "## Time per window (ms, one thread; PNE and CPV with planes cached; MME and MPV share one "
             "neighbourhood pass, half of its time each)\n",
             _markdown(tables["timing"], ["window", "metric", "n", "median_ms", "p90_ms", "max_ms"]), "",
             "![timing](timing.png)\n", "![scatter](scatter.png)\n",
             "All correlations (Pearson, Spearman, Kendall): correlations.csv.\n"]
    path = out / "REPORT.md"
    path.write_text("\n".join(text))
    return path
