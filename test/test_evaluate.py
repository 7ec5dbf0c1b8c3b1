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
    assert f"{len(list((out / 'runs').iterdir()))} of " in capsys.readouterr().out  # says what it reused


def test_runs_of_another_setup_are_not_reused_under_a_new_spec(tmp_path):
    """Stored runs are named by scene, trajectory, window, noise and scale only: an OUT holding runs made with
    other frames (or seed, radius, baseline windows) is refused before any work, not reported as the new spec."""
    import json
    from dataclasses import asdict, replace

    from topometric_ros.experiments.evaluate import run

    quick = ExperimentSpec.quick()
    (tmp_path / "runs").mkdir()
    (tmp_path / "spec.json").write_text(json.dumps(asdict(quick)))
    with pytest.raises(ValueError, match=r"holds runs made with frames 100 \(now 50\): give another --out"):
        run(replace(quick, frames=50), tmp_path, workers=1, progress=False, engine="local")
    assert json.loads((tmp_path / "spec.json").read_text())["frames"] == 100  # left as it was


def test_the_shipped_report_is_replaced_only_by_the_same_experiment(tmp_path):
    """results/ holds the shipped report without its runs: another spec is refused there (it would replace the
    report), the full experiment is not; a folder without a report takes any spec."""
    import shutil
    from pathlib import Path
    from dataclasses import replace

    from topometric_ros.experiments.evaluate import _same_runs, default_out

    shipped = tmp_path / "results"  # the shipped report as a clone has it (a machine that ran it has runs/ too)
    shipped.mkdir()
    for name in ("spec.json", "REPORT.md"):
        shutil.copy(Path(__file__).resolve().parents[1] / "results" / name, shipped / name)
    _same_runs(ExperimentSpec(), shipped)
    for other in (ExperimentSpec.quick(), replace(ExperimentSpec(), frames=20)):
        with pytest.raises(ValueError, match="holds the report of another experiment"):
            _same_runs(other, shipped)
    _same_runs(ExperimentSpec.quick(), tmp_path)
    assert default_out(ExperimentSpec()) == "results" and default_out(ExperimentSpec.quick(), quick=True) == \
        "out/evaluate_quick"
    assert default_out(replace(ExperimentSpec(), scenes=("office1",))) == "out/evaluate"


@pytest.mark.parametrize("argv, words", [
    (["--frames", "3"], "--frames 3 holds no window of 5 scans"),
    (["--frames", "8", "--win", "10"], "--frames 8 holds no window of 10 scans"),
    (["--scenes", ""], "give at least one scene"),
    (["--noise", ""], "give at least one value"),
    (["--labels", ""], "give at least one value"),
])
def test_an_experiment_that_cannot_run_is_refused_before_any_work(tmp_path, capsys, cli_exit_code, argv, words):
    """Each of these ended in a traceback (IndexError) or a numpy message, and left empty run files behind."""
    out = tmp_path / "ev"
    assert cli_exit_code(["evaluate", "--quick", "--engine", "local", "--out", str(out), *argv]) == 2
    assert words in capsys.readouterr().err
    assert not out.exists()


def test_another_experiment_is_written_apart_from_the_shipped_report(tmp_path, monkeypatch):
    """Without --out, only the full experiment writes results/ (the shipped report); any other goes to
    out/evaluate."""
    monkeypatch.chdir(tmp_path)
    assert main(["evaluate", "--scenes", "office1", "--trajectories", "1", "--frames", "5", "--win", "5", "--noise",
                 "r", "--scales", "1", "--labels", "gt", "--baseline-windows", "1", "--engine", "local"]) == 0
    assert (tmp_path / "out" / "evaluate" / "REPORT.md").is_file() and not (tmp_path / "results").exists()


def test_a_claim_without_the_numbers_to_judge_it_is_undefined_not_holding():
    """Spearman NaN for the claimed metric (no baselines, a 1-scan window): no verdict, and the metrics that
    were not measured are not counted as compared."""
    from topometric_ros.experiments.evaluate import claims, main_pool

    spec = ExperimentSpec(scenes=("office1",), trajectories=1, windows=(5,), noises=("r",), scales=(1.0,),
                          labels=("gt",), baseline_windows=1)
    row = dict(labels="gt", noise="r", scale=1.0)
    nan = float("nan")
    tables = {"multirelation": [dict(row, noise="rt", windows="all", mr_pne_cpv_rpe=nan)], "correlations": [
        dict(row, windows=pool, metric=m, spearman=v) for pool in (main_pool(spec), "per-trajectory")
        for m, v in (("pne", nan), ("cpv", nan), ("mme", nan))]}
    lines = claims(spec, tables, "gt")
    assert lines and all("undefined" in line and "holds" not in line for line in lines), lines
    tables["correlations"] = [dict(r, spearman=0.9 if r["metric"] == "pne" else 0.5 if r["metric"] == "cpv" else nan)
                              for r in tables["correlations"]]
    lines = claims(spec, tables, "gt")
    assert "has the highest Spearman of PNE/CPV — holds (PNE 0.9" in lines[0], lines


def test_perturbation_respects_mode_and_scale():
    poses = np.repeat(np.eye(4)[None], 2000, axis=0)
    rng = np.random.default_rng(0)
    r_only = _perturb(poses, "r", 2.0, rng)
    assert np.allclose(r_only[:, :3, 3], 0) and not np.allclose(r_only[:, :3, :3], np.eye(3))
    t_only = _perturb(poses, "t", 2.0, rng)
    assert np.allclose(t_only[:, :3, :3], np.eye(3)) and t_only[:, :3, 3].std() <= 0.05 * 2.0 * 1.05


def test_a_spec_that_cannot_run_is_refused_when_made_not_when_run():
    """The checks live in ExperimentSpec, so the Python API refuses what the CLI refuses."""
    from dataclasses import replace

    quick = ExperimentSpec.quick()
    for change, words in (({"frames": 4}, "holds no window of 5 scans"), ({"scenes": ()}, "scenes"),
                          ({"noises": ("x",)}, "unknown noise mode or label source: x"),
                          ({"labels": ("network", "oracle")}, "oracle")):
        with pytest.raises(ValueError, match=words):
            replace(quick, **change)


def test_the_correlation_table_pools_windows_three_ways_from_hand_made_runs():
    """Three trajectories of 3 windows (RPE 1, 2, 3): PNE rises with RPE in two, falls in the third; the
    baselines (MME...) exist on the first two windows of each trajectory only. 'all' pools the 9 windows,
    'common' the 6 that have every metric, 'per-trajectory' is the median over trajectories (1.0, not the mean
    1/3), each of exactly 3 windows (enough for a correlation); a run of another scale is left out."""
    from topometric_ros.experiments.evaluate import correlation_table

    spec = ExperimentSpec(scenes=("office1",), trajectories=3, frames=100, windows=(5,), noises=("r",), scales=(1.0,),
                          labels=("gt",), baseline_windows=2)
    rpe = np.array([1.0, 2.0, 3.0])

    def data(pne):
        base = np.array([1.0, 2.0, np.nan])
        return {"window": np.arange(3), "rpe": rpe, "pne": np.asarray(pne, float), "cpv": rpe ** 2,
                "mme": base, "mpv": base, "mom": base}
    runs = [(("gt", "office1", 0, 5, "r", 1.0), data([1, 2, 3])), (("gt", "office1", 1, 5, "r", 1.0), data([1, 2, 4])),
            (("gt", "office1", 2, 5, "r", 1.0), data([3, 2, 1])),
            (("gt", "office1", 3, 5, "r", 2.0), data([np.nan, np.nan, 5.0]))]  # another scale: not this setting's
    rows = {(r["windows"], r["metric"]): r for r in correlation_table(spec, runs)}
    assert rows["all", "pne"]["n"] == 9 and rows["all", "mme"]["n"] == 6
    assert rows["common", "pne"]["n"] == 6 and rows["common", "cpv"]["n"] == 6
    assert rows["common", "mme"]["spearman"] == pytest.approx(1.0)
    assert rows["per-trajectory", "pne"]["n"] == 3 and rows["per-trajectory", "pne"]["spearman"] == pytest.approx(1.0)
    assert rows["per-trajectory", "cpv"]["spearman"] == pytest.approx(1.0)
    assert ("per-trajectory", "mme") not in rows  # the baselines have too few windows per trajectory


def test_the_claims_are_checked_on_common_windows_from_twenty_baseline_windows():
    from topometric_ros.experiments.evaluate import main_pool

    def spec(baseline_windows):
        return ExperimentSpec(scenes=("office1", "garage"), trajectories=2, baseline_windows=baseline_windows)
    assert main_pool(spec(5)) == "common" and main_pool(spec(4)) == "all"  # 5 x 2 x 2 = 20 windows; 16


def test_a_multi_relation_of_exactly_the_claimed_bound_holds():
    """The claim is Multi-relation(PNE, CPV, RPE) >= 0.9: 0.9 itself holds, 0.89 does not."""
    from topometric_ros.experiments.evaluate import claims

    spec = ExperimentSpec(scenes=("office1",), trajectories=1, windows=(5,), noises=("rt",), scales=(1.0,),
                          labels=("gt",), baseline_windows=1)
    for mr, verdict in ((0.9, "— holds"), (0.89, "— does NOT hold")):
        tables = {"correlations": [], "multirelation": [dict(labels="gt", noise="rt", scale=1.0, windows="all",
                                                             mr_pne_cpv_rpe=mr)]}
        (line,) = claims(spec, tables, "gt")
        assert line.endswith(verdict), line
