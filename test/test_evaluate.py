"""The noise experiment end to end on a tiny scene (`topometric evaluate --quick`)."""
from __future__ import annotations

import csv

import numpy as np
import pytest

from topometric_ros.cli import main
from topometric_ros.experiments.evaluate import METRICS, PLANE_METRICS, ExperimentSpec, _perturb


def _rows(path):
    with open(path) as f:
        return list(csv.DictReader(f))


@pytest.mark.slow
def test_quick_experiment_tables_and_pne_tracks_rotation_noise(tmp_path, capsys):
    out = tmp_path / "results"
    assert main(["evaluate", "--quick", "--out", str(out), "--workers", "1"]) == 0
    spec = ExperimentSpec.quick()
    corr = _rows(out / "correlations.csv")
    settings = len(spec.noises) * len(spec.scales)
    assert len(corr) == settings * (2 * len(METRICS) + len(PLANE_METRICS))  # all, common; per-trajectory
    assert {r["metric"] for r in corr} == set(METRICS)
    mr = _rows(out / "multirelation.csv")
    assert len(mr) == settings * 2  # all, per-trajectory
    assert all(0.0 <= float(r["mr_pne_cpv_rpe"]) <= 1.0 for r in mr)
    timing = {r["metric"] for r in _rows(out / "timing.csv")}
    assert {"pne", "cpv", "pne+cpv", "mme", "mpv"} <= timing
    for r in corr:
        if r["metric"] == "pne" and r["noise"] == "r" and r["windows"] == "all":
            assert float(r["spearman"]) > 0.5, r
    for name in ("REPORT.md", "multirelation.png", "timing.png", f"correlations_{spec.labels[0]}.png"):
        assert (out / name).stat().st_size > 0
    # Resumable: a second run recomputes nothing and gives the same tables.
    before = (out / "correlations.csv").read_text()
    stamps = {p: p.stat().st_mtime_ns for p in (out / "runs").iterdir()}
    assert main(["evaluate", "--quick", "--out", str(out), "--workers", "1"]) == 0
    assert {p: p.stat().st_mtime_ns for p in (out / "runs").iterdir()} == stamps
    assert (out / "correlations.csv").read_text() == before


def test_perturbation_respects_mode_and_scale():
    poses = np.repeat(np.eye(4)[None], 2000, axis=0)
    rng = np.random.default_rng(0)
    r_only = _perturb(poses, "r", 2.0, rng)
    assert np.allclose(r_only[:, :3, 3], 0) and not np.allclose(r_only[:, :3, :3], np.eye(3))
    t_only = _perturb(poses, "t", 2.0, rng)
    assert np.allclose(t_only[:, :3, :3], np.eye(3)) and t_only[:, :3, 3].std() <= 0.05 * 2.0 * 1.05
