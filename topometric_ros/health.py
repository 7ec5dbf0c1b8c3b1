"""Drift alarms: a WindowResult -> OK / WARN / ERROR (or STALE without input) with a human reason.

No per-site tuning: each metric (PNE reacts to rotation drift, CPV to translation drift) is compared
with a robust baseline learned from this run's first ``baseline_windows`` windows (median and MAD, then
rolling over the last ``baseline_history`` calm windows (OK, z below warn_sigma / 2), so neither a drift
episode nor a slow ramp teaches the baseline).
Both are compared on a log scale: PNE is already one (an entropy, ½ ln det Σ + c), CPV (a variance, m²)
through ln CPV, so the spread floors (``pne_min_sigma``, ``cpv_min_sigma``) are unit-free and site-free.
The robust z = (x − median) / max(1.4826·MAD, floor) raises WARN at ``warn_sigma`` and ERROR at
``error_sigma``, once ``warn_persist`` of the last ``persist_windows`` windows (this one included) had that
metric's z at or above warn_sigma (each metric counts its own windows): drift lasts, a single odd window (a view of few planes, seen at 9σ on drift-free
calibration bags) does not, so persistence cuts false alarms at a lower threshold. Absolute limits
(config, in metric units, 0 = off) apply at once, from the first window.
The drift rates of the co-plane groups (metrics/drift_rate.py: deg/s and m/s from one joint fit to the
planes' normals and offsets) are physical rates, the same at every site, so they need no baseline: their
limits (RateLimits) act from the first window; a rate at its ERROR limit alarms at once, one between WARN and
ERROR (relative limits) once it was above WARN in ``rate_persist`` of the last ``persist_windows`` windows: a
SLAM's everyday error pokes over a limit for a window, drift stays. Absolute limits act at once. With
``rate_sigma`` > 0 a rate is judged by its lower bound rate − rate_sigma × its standard error (the drift
rate fit's jackknife over scans): a rate one scan's pose noise could make is no drift alarm. Pose noise itself
(a standard error of at least ``noise_warn`` × the WARN limit: the poses scatter from scan to scan) is a WARN.
They carry most detections; the sigma alarms catch inconsistency without a trend (pose noise, jumps).
A scan placed off by more than the co-plane gates joins no co-plane group, so the robust rate fit never sees
it: its ``agreement`` (the share of its plane inliers that another scan sees in the same place; cpv.py) below
``agreement_warn`` raises WARN at once ("pose jump"): a SLAM that jumped or lost track.
health.warn_sigma is calibrated on simulated calibration bags disjoint from the evaluation ones
(``topometric alarms --calibrate``, alarms.py).

Also here: the diagnostics message builders shared by node.py and replay.py. They take the message
classes as input (rosbags or rclpy), so this module imports no ROS.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from .config import HealthConfig

LEVELS = ("OK", "WARN", "ERROR", "STALE")
RANK = {name: i for i, name in enumerate(LEVELS)}
#: metric -> unit. PNE rises with rotation error only; CPV with translation error and with rotation error (a
#: rotated scan shifts its distant planes): its alarm is named by the drift rate nearer its limit (_meaning).
METRICS = {"pne": "nats", "cpv": "m²"}
#: drift rate -> (what it means, unit).
RATES = {"rot_rate": ("rotation drift", "°/s"), "trans_rate": ("translation drift", "m/s")}
#: The node's default name; statuses are named "<node name>: <task>" (diagnostic_updater's convention).
NODE_NAME = "topometric_monitor"
TASK = "map consistency"
#: Counters that mean a scan (or a window) was lost to a failure, not to load.
FAILURE_COUNTERS = ("dropped_bad_scan", "dropped_no_pose", "dropped_duplicate", "scan_errors", "window_errors")


def status_name(node: str = NODE_NAME, task: str = TASK) -> str:
    """diagnostic_updater's status name: "<node name>: <task>"."""
    return f"{node}: {task}"


STATUS_NAME = status_name()
MAD_TO_SIGMA = 1.4826
CPV_TINY = 1e-12  # m², CPV below this is taken as this on the log scale


def to_scale(metric: str, value: float) -> float:
    """The scale a metric is compared on: PNE as is (nats), CPV as ln CPV."""
    return float(np.log(max(value, CPV_TINY))) if metric == "cpv" else float(value)


def from_scale(metric: str, x: float) -> float:
    """Inverse of :func:`to_scale` (back to metric units)."""
    return float(np.exp(x)) if metric == "cpv" else float(x)


@dataclass
class Assessment:
    """What health.py concluded about one window: level, reason, robust z and thresholds per metric."""

    level: str
    message: str
    z: dict = field(default_factory=dict)  # metric -> robust z (nan while learning)
    warn_at: dict = field(default_factory=dict)  # metric -> value (metric units) where WARN starts
    error_at: dict = field(default_factory=dict)


def assessment_fields(a: "Assessment | None") -> dict:
    """A window record's health columns (windows.json): z_pne, z_cpv, each metric's and rate's warn_at /
    error_at (metric units) and agreement_warn_at (a lower limit), NaN without an assessment."""
    nan = float("nan")
    out = {}
    for metric in (*METRICS, *RATES):
        if metric in METRICS:
            out[f"z_{metric}"] = a.z.get(metric, nan) if a else nan
        out[f"{metric}_warn_at"] = a.warn_at.get(metric, nan) if a else nan
        out[f"{metric}_error_at"] = a.error_at.get(metric, nan) if a else nan
    out["agreement_warn_at"] = a.warn_at.get("agreement", nan) if a else nan
    return out


@dataclass
class _Verdict:
    """One window's level so far, its alarms (they raise the level) and notes (they do not)."""

    level: str = "OK"
    alarms: list = field(default_factory=list)
    notes: list = field(default_factory=list)

    def alarm(self, level: str, text: str) -> None:
        self.level = _worse(self.level, level)
        self.alarms.append(text)

    def message(self) -> str:
        return "; ".join(self.alarms + self.notes)


class Health:
    """Stateful assessor: one per monitored stream. ``assess`` sets result.level / result.message."""

    def __init__(self, config: HealthConfig | None = None):
        self.config = config or HealthConfig()
        self._history = {m: deque(maxlen=max(self.config.baseline_windows, self.config.baseline_history))
                         for m in METRICS}
        self._high = {m: self._recent(self.config.warn_persist) for m in METRICS}  # each metric its own count
        self._rate_high = {r: self._recent(self.config.rate_persist) for r in RATES}
        self.rates = RateLimits(self.config)
        self.last: Assessment | None = None

    def _recent(self, needed: int) -> deque[bool]:
        """The flags a persistence rule counts: the last persist_windows windows (at least ``needed``)."""
        return deque(maxlen=max(1, self.config.persist_windows, needed))

    def reset_clock(self) -> None:
        """Time jumped back: the baseline stays (same robot, same site); nothing else to forget."""

    def baseline(self, metric: str) -> tuple[float, float] | None:
        """(median, robust sigma) of a metric ON ITS COMPARISON SCALE (to_scale) once ``baseline_windows``
        windows are in, else None."""
        h = self._history[metric]
        if len(h) < max(1, self.config.baseline_windows):
            return None
        values = np.asarray(h)
        med = float(np.median(values))
        mad = float(np.median(np.abs(values - med)))
        return med, max(MAD_TO_SIGMA * mad, getattr(self.config, f"{metric}_min_sigma"), 1e-12)

    def assess(self, result: Any) -> Assessment:
        """Level and reason for a WindowResult (its ``level``/``message`` are set too). The message leads with
        the alarms, drift rates first ("rotation drift: 3.5 °/s (limit 1.2 ...)"), then the rest."""
        verdict, warn_at, error_at = _Verdict(), {}, {}
        sigma_z = self._sigma_z(result)
        for metric, high in self._high.items():
            high.append(sigma_z.get(metric, float("nan")) >= self.config.warn_sigma)
        limits = self.rates.limits(result)
        self._judge_rates(result, limits, verdict, warn_at, error_at)
        z, bases = self._judge_metrics(result, limits, sigma_z, verdict, warn_at, error_at)
        self.rates.learn(result)
        self._judge_scans(result, verdict, warn_at)
        self._learn_baselines(result, verdict.level, z, bases)
        self._state_notes(result, verdict, z, learning=any(b is None for b in bases.values()))
        result.level, result.message = verdict.level, verdict.message()
        self.last = Assessment(verdict.level, result.message, z, warn_at, error_at)
        return self.last

    def _judge_rates(self, result: Any, limits: dict, verdict: "_Verdict", warn_at: dict, error_at: dict) -> None:
        """The drift rates against their limits: ERROR at once, WARN once persistent, pose noise a WARN."""
        c = self.config
        for rate, (meaning, unit) in RATES.items():
            value, se, shown = self.rates.judged(result, rate)
            warn, error = warn_at[rate], error_at[rate] = limits[rate]
            high = self._rate_high[rate]
            high.append(bool(np.isfinite(value) and warn > 0 and value >= warn))
            if not np.isfinite(value):
                continue  # no co-plane group: already reported as CPV undefined
            if error > 0 and value >= error:
                verdict.alarm("ERROR", f"{meaning}: {shown} {unit} (limit {error:.3g}{self.rates.why(result)})")
            elif high[-1] and sum(high) >= self.rates.persist:
                verdict.alarm("WARN", f"{meaning}: {shown} {unit} (limit {warn:.3g}{self.rates.why(result)})" +
                              (f" ({sum(high)} of the last {len(high)} windows)" if self.rates.persist > 1 else ""))
            elif high[-1]:
                verdict.notes.append(f"watch: {meaning} {shown} {unit} above limit {warn:.3g} in {sum(high)} of "
                                     f"{self.rates.persist} windows needed")
            if c.noise_warn > 0 and warn > 0 and se >= c.noise_warn * warn:  # NaN never alarms
                verdict.alarm("WARN", f"pose noise: {meaning} {shown} {unit}, its standard error {se / warn:.2g} × "
                              f"the limit {warn:.3g} (the poses scatter from scan to scan)")

    def _judge_metrics(self, result: Any, limits: dict, sigma_z: dict, verdict: "_Verdict", warn_at: dict,
                       error_at: dict) -> tuple[dict, dict]:
        """PNE and CPV against their absolute limits and their baselines (persistent z). Returns (robust z,
        baseline) per metric with a finite value (baseline None while learning)."""
        c = self.config
        z: dict[str, float] = {}
        bases: dict[str, tuple[float, float] | None] = {}
        for metric, unit in METRICS.items():
            value = float(getattr(result, metric))
            if not np.isfinite(value):
                verdict.alarm("WARN", f"{metric.upper()} undefined (no co-planar planes)")
                continue
            meaning = _meaning(metric, result, limits)
            base = bases[metric] = self.baseline(metric)
            lim_warn, lim_err = getattr(c, f"{metric}_warn"), getattr(c, f"{metric}_error")
            warn_at[metric], error_at[metric] = _limits(metric, base, c, lim_warn, lim_err)
            z[metric] = sigma_z.get(metric, float("nan"))
            high = self._high[metric]
            persistent = sum(high) >= c.warn_persist
            if lim_err != 0 and value >= lim_err:
                verdict.alarm("ERROR", f"{meaning}: {metric.upper()} {value:.3g} {unit} above limit {lim_err:g}")
            elif base and z[metric] >= c.error_sigma and persistent:
                verdict.alarm("ERROR", f"{meaning}: {metric.upper()} {z[metric]:.1f}σ above baseline")
            elif lim_warn != 0 and value >= lim_warn:
                verdict.alarm("WARN", f"{meaning}: {metric.upper()} {value:.3g} {unit} above limit {lim_warn:g}")
            elif base and z[metric] >= c.warn_sigma and persistent:
                verdict.alarm("WARN", f"{meaning}: {metric.upper()} {z[metric]:.1f}σ above baseline" +
                              (f" ({sum(high)} of the last {len(high)} windows)" if c.warn_persist > 1 else ""))
            elif base and z[metric] >= c.warn_sigma:
                verdict.notes.append(f"watch: {metric.upper()} {z[metric]:.1f}σ above baseline in "
                                     f"{sum(high)} of {c.warn_persist} windows needed")
        return z, bases

    def _judge_scans(self, result: Any, verdict: "_Verdict", warn_at: dict) -> None:
        """A scan that lines up with no other (pose jump) and too few planes: WARN at once."""
        c = self.config
        agreement = float(getattr(result, "agreement", float("nan")))
        warn_at["agreement"] = c.agreement_warn if c.agreement_warn > 0 else float("nan")
        if agreement < warn_at["agreement"]:  # NaN (no co-plane group, the rule off) never alarms
            verdict.alarm("WARN", f"pose jump: {_which_scan(result)} lines up with the others for {agreement:.0%} "
                          f"of its plane inliers (limit {c.agreement_warn:.0%})")
        if result.n_planes < c.min_planes:
            verdict.alarm("WARN", f"too few planes ({result.n_planes} < {c.min_planes}): metrics unreliable")

    def _learn_baselines(self, result: Any, level: str, z: dict, bases: dict) -> None:
        """Only clearly normal windows (OK, every z under warn_sigma / 2) teach a learnt baseline (no creep);
        every finite window teaches one still learning."""
        calm = all(not np.isfinite(v) or v < self.config.warn_sigma / 2 for v in z.values())
        for metric in METRICS:
            value = float(getattr(result, metric))
            if np.isfinite(value) and (bases[metric] is None or (level == "OK" and calm)):
                self._history[metric].append(to_scale(metric, value))

    def _state_notes(self, result: Any, verdict: "_Verdict", z: dict, learning: bool) -> None:
        """What the assessor is still learning, or "consistent (...)" when nothing else was said."""
        c = self.config
        if learning:
            n = min(len(h) for h in self._history.values())
            verdict.notes.append(f"learning baseline ({n}/{c.baseline_windows} windows)")
        elif not verdict.alarms and not verdict.notes:
            verdict.notes.append("consistent (" + ", ".join(f"{m.upper()} {z[m]:+.1f}σ" for m in z) + ")")
        if self.rates.learning and all(np.isfinite(float(getattr(result, r, np.nan))) for r in RATES):
            verdict.notes.append(f"learning the rates' noise floor ({self.rates.seen}/{c.noise_windows} windows)")

    def _sigma_z(self, result: Any) -> dict:
        """Robust z of each finite metric against the baseline (empty while learning)."""
        out = {}
        for metric in METRICS:
            value, base = float(getattr(result, metric)), self.baseline(metric)
            if np.isfinite(value) and base:
                out[metric] = (to_scale(metric, value) - base[0]) / base[1]
        return out

    def stale(self, now: float, last_scan: float | None, last_pose: float | None) -> tuple[str, str] | None:
        """("STALE", reason) when no scan or no odometry came within stale_after_s before ``now`` (any clock,
        e.g. sim time; a clock that jumped back before the last input is not stale), else None."""
        limit = self.config.stale_after_s
        missing = []
        for what, last in (("scans", last_scan), ("odometry", last_pose)):
            if last is None:
                missing.append(f"no {what} yet")
            elif now - last > limit:
                missing.append(f"no {what} for {now - last:.1f} s")
        return ("STALE", "; ".join(missing)) if missing else None

    def failing(self, now: float, failing_since: float | None, last_processed: float | None, last_error: str,
                counters: Mapping[str, int]) -> tuple[str, str] | None:
        """("ERROR", reason) when every scan since ``failing_since`` (receive time of the first scan that failed
        after the last success; any clock, the same as ``now``) failed for at least fail_after_s, else None.
        The reason names the failure counters and the last error."""
        if failing_since is None or now - failing_since < self.config.fail_after_s:
            return None
        since = ("no scan processed yet" if last_processed is None
                 else f"no scan processed for {now - last_processed:.1f} s")
        lost = ", ".join(f"{k} {counters[k]}" for k in FAILURE_COUNTERS if counters.get(k))
        return "ERROR", f"{since}, every scan fails ({lost or 'no counter'}): {last_error or 'unknown error'}"


def _meaning(metric: str, result: Any, limits: Mapping[str, tuple[float, float]]) -> str:
    """What a metric's rise means: PNE rotation drift; CPV the drift whose rate is nearer its WARN limit
    (translation when the rates cannot tell)."""
    if metric == "pne":
        return RATES["rot_rate"][0]
    share = {r: float(getattr(result, r, np.nan)) / limits[r][0] if limits[r][0] > 0 else np.nan for r in RATES}
    rot, trans = share["rot_rate"], share["trans_rate"]
    return RATES["rot_rate"][0] if np.isfinite(rot) and not (np.isfinite(trans) and trans >= rot) else RATES["trans_rate"][0]


class RateLimits:
    """The WARN and ERROR limits of the two drift rates for a window.

    ``relative`` (default): drift is judged against the motion, as the KITTI odometry benchmark does — the
    rotation limit is rot_floor + rot_per_m × speed + rot_per_deg × turn rate (deg/s), the translation limit
    trans_floor + trans_per_m × speed + trans_per_deg × turn rate (m/s), speed and turn rate from the window's SLAM poses; ERROR at
    error_factor × WARN. The floors (what standing still is allowed) are learned per run from its first
    ``noise_windows`` windows: noise_margin × the noise_quantile of the rates above their motion share,
    between the configured floor and noise_max_factor × it; while learning, the floors are at that maximum.
    So a SLAM whose everyday error is larger (jitter, a noisy sensor) is not alarmed on, with no per-site
    tuning, while real drift, which grows, still is. ``absolute``: the fixed rot_rate_* / trans_rate_* limits.
    """

    def __init__(self, config: HealthConfig):
        self.c = config
        self._excess: dict[str, list[float]] = {r: [] for r in RATES}
        start = config.noise_max_factor if config.noise_windows > 0 else 1.0
        self.floor = {"rot_rate": config.rot_floor * start, "trans_rate": config.trans_floor * start}
        self.seen = 0

    @property
    def persist(self) -> int:
        """Windows of the last persist_windows a rate between WARN and ERROR must be above WARN in before it
        alarms: rate_persist for relative limits; absolute limits act at once."""
        return self.c.rate_persist if self.c.rate_limits == "relative" else 1

    def judged(self, result: Any, rate: str) -> tuple[float, float, str]:
        """(value the limits judge, the rate's standard error ``<rate>_se`` (NaN without one), how the message
        shows the rate) of one drift rate: the rate itself, or with rate_sigma > 0 and a standard error, its
        lower bound rate − rate_sigma × se (≥ 0), shown as "rate ± se"."""
        value = float(getattr(result, rate, float("nan")))
        se = float(getattr(result, f"{rate}_se", float("nan")))
        if self.c.rate_sigma <= 0 or not np.isfinite(se):
            return value, se, f"{value:.3g}"
        return max(value - self.c.rate_sigma * se, 0.0), se, f"{value:.3g} ± {se:.2g}"

    @property
    def learning(self) -> bool:
        return self.c.rate_limits == "relative" and self.seen < self.c.noise_windows

    def _motion_share(self, result: Any) -> dict[str, float]:
        speed, turn = float(getattr(result, "speed", np.nan)), float(getattr(result, "turn_rate", np.nan))
        speed, turn = (speed if np.isfinite(speed) else 0.0), (turn if np.isfinite(turn) else 0.0)
        return {"rot_rate": self.c.rot_per_m * speed + self.c.rot_per_deg * turn,
                "trans_rate": self.c.trans_per_m * speed + self.c.trans_per_deg * turn}

    def limits(self, result: Any) -> dict[str, tuple[float, float]]:
        """rate -> (WARN limit, ERROR limit) in the rate's units (0 = off)."""
        c = self.c
        if c.rate_limits == "absolute":
            return {"rot_rate": (c.rot_rate_warn, c.rot_rate_error), "trans_rate": (c.trans_rate_warn, c.trans_rate_error)}
        share = self._motion_share(result)
        return {r: (self.floor[r] + share[r], c.error_factor * (self.floor[r] + share[r])) for r in RATES}

    def why(self, result: Any) -> str:
        """How a relative limit came about, for the reason text."""
        if self.c.rate_limits == "absolute":
            return ""
        speed, turn = float(getattr(result, "speed", np.nan)), float(getattr(result, "turn_rate", np.nan))
        return f" at {speed:.2g} m/s, {turn:.2g} °/s turning" if np.isfinite(speed) else ""

    def learn(self, result: Any) -> None:
        """Take the window into the noise floor while the first noise_windows windows go by."""
        c = self.c
        if not self.learning:
            return
        share = self._motion_share(result)
        rates = {r: float(getattr(result, r, np.nan)) for r in RATES}
        if not all(np.isfinite(v) for v in rates.values()):
            return
        self.seen += 1
        for r in RATES:
            self._excess[r].append(max(rates[r] - share[r], 0.0))
        if self.seen == c.noise_windows:
            for r, base in (("rot_rate", c.rot_floor), ("trans_rate", c.trans_floor)):
                learned = c.noise_margin * float(np.quantile(self._excess[r], c.noise_quantile))
                self.floor[r] = float(np.clip(learned, base, base * c.noise_max_factor))


def _which_scan(result: Any) -> str:
    """'scan k of n (stamp s)' for the window's least agreeing scan, 'a scan' when it is not known."""
    k, n = int(getattr(result, "agreement_scan", -1)), int(getattr(result, "n_scans", 0))
    stamp = float(getattr(result, "agreement_stamp", float("nan")))
    return f"scan {k + 1} of {n} (stamp {stamp:.2f})" if 0 <= k < n and np.isfinite(stamp) else "a scan"


def _worse(a: str, b: str) -> str:
    return a if RANK[a] >= RANK[b] else b


def _limits(metric: str, base, c: HealthConfig, lim_warn: float, lim_err: float) -> tuple[float, float]:
    """Metric values (metric units) where WARN and ERROR start (the lower of sigma and absolute limits)."""
    sig_w = from_scale(metric, base[0] + c.warn_sigma * base[1]) if base else None
    sig_e = from_scale(metric, base[0] + c.error_sigma * base[1]) if base else None
    warn = [v for v in (sig_w, lim_warn or None) if v is not None]
    err = [v for v in (sig_e, lim_err or None) if v is not None]
    return (min(warn) if warn else float("nan")), (min(err) if err else float("nan"))


# -------------------------------------------------------------------- diagnostics messages
def _fmt(value: Any) -> str:
    """A KeyValue string at full precision: floats as repr (shortest text that reads back the same
    double, e.g. a stamp 1700000012.2), 'nan' / 'inf' / '-inf' when not finite."""
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    return str(value)


def window_values(result: Any, counters: Mapping[str, int] | None = None,
                  extra: Mapping[str, Any] | None = None) -> dict[str, str]:
    """The KeyValue strings of one window's status (docs/design.md's list, then the monitor's counters)."""
    values = {"pne": result.pne, "cpv": result.cpv}
    for name in ("rpe_estimate", *RATES, *(f"{r}_se" for r in RATES), "speed", "turn_rate"):
        values[name] = getattr(result, name, float("nan"))
    for name in ("mme", "mpv", "mom"):
        if getattr(result, name, None) is not None:
            values[name] = getattr(result, name)
    values.update(n_planes=result.n_planes, n_groups=result.n_groups,
                  agreement=getattr(result, "agreement", float("nan")),
                  window_start=result.stamps[0] if result.stamps else float("nan"),
                  window_end=result.stamps[-1] if result.stamps else float("nan"),
                  latency_ms=result.timings.get("latency", float("nan")))
    counters = dict(counters or {})
    values["dropped_windows"] = counters.pop("dropped_windows", 0)
    values.update(extra or {})
    values.update(counters)
    return {k: _fmt(v) for k, v in values.items()}


def diagnostic_status(types: Any, level: str, message: str, values: Mapping[str, str],
                      name: str = STATUS_NAME, hardware_id: str = "") -> Any:
    """diagnostic_msgs/DiagnosticStatus from the message classes in ``types`` (DiagnosticStatus, KeyValue);
    the level constant comes from the class (int in rosbags, bytes in rclpy)."""
    if level not in RANK:
        raise ValueError(f"unknown level {level!r}; one of {LEVELS}")
    return types.DiagnosticStatus(level=getattr(types.DiagnosticStatus, level), name=name, message=message,
                                  hardware_id=hardware_id,
                                  values=[types.KeyValue(key=str(k), value=str(v)) for k, v in values.items()])


def diagnostic_array(types: Any, stamp: float, statuses: list) -> Any:
    """diagnostic_msgs/DiagnosticArray stamped ``stamp`` s (types: DiagnosticArray, Header, Time)."""
    from .cloud import make_header

    return types.DiagnosticArray(header=make_header(stamp, "", types), status=list(statuses))
