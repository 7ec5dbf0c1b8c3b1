"""The ROS parameters of the node, without ROS: names, defaults, ranges, descriptions, and their checks.

node.py declares them (it is the only module importing rclpy); this module holds what they are, so the
checks are tested without ROS and docs/ros.md's table is generated from here
(``python -m topometric_ros.parameters`` prints it).

Two kinds: the node's own (topics, QoS, hardware_id, markers, scan-rate and latency limits; NODE_SPEC) and
one read-only parameter per config leaf, named ``section.field`` (config.py holds defaults and units).
rclpy checks a range only when the value has the range's type (an integer YAML value skips a floating
point range), so :func:`check` validates every value against RANGES whatever its type.
"""
from __future__ import annotations

import dataclasses
import inspect
import re
from typing import Any, Mapping

from . import config as config_module
from .config import CHOICES

#: The node's own parameters: name -> (default, description).
NODE_SPEC: dict[str, tuple[Any, str]] = {
    "points_topic": ("/points", "sensor_msgs/PointCloud2 topic (sensor frame)"),
    "odom_topic": ("/odom", "nav_msgs/Odometry topic of the SLAM pose (child frame -> map)"),
    "tf_static_topic": ("/tf_static", "static transforms; give the odometry child -> cloud frame extrinsic"),
    "points_qos": ("sensor_data", "QoS of the points subscription"),
    "odom_qos": ("reliable", "QoS of the odometry subscription"),
    "hardware_id": ("", "DiagnosticStatus hardware_id; empty = the cloud's frame_id"),
    "publish_markers": (False, "publish each window's planes as a MarkerArray on ~/planes (map frame)"),
    "scan_rate_min_hz": (1.0, "Hz, scan rate below this (less 10 %) -> WARN in the 'scan rate' status"),
    "scan_rate_max_hz": (40.0, "Hz, scan rate above this (plus 10 %) -> WARN in the 'scan rate' status"),
    "latency_warn_s": (1.0, "s, scan stamp -> window result (node clock) above this -> WARN in 'latency'"),
    "latency_error_s": (5.0, "s, ... above this -> ERROR in 'latency'"),
}
#: Declared by diagnostic_updater.Updater itself (documented here, checked like ours).
UPDATER_SPEC: dict[str, tuple[Any, str]] = {
    "diagnostic_updater.period": (1.0, "s, how often every status is published (windows are also published "
                                       "as they complete)"),
    "diagnostic_updater.use_fqn": (False, "status names start with the namespace too"),
}
QOS_CHOICES = ("sensor_data", "reliable")
#: Strings that take one of a few values: config leaves and node parameters.
ALL_CHOICES: dict[str, tuple[str, ...]] = {**CHOICES, "points_qos": QOS_CHOICES, "odom_qos": QOS_CHOICES}

#: Ranges of numeric parameters: name -> (min, max), both included (config leaves: config.RANGES).
RANGES: dict[str, tuple[float, float]] = {
    **config_module.RANGES,
    "scan_rate_min_hz": (0.0, 1000.0), "scan_rate_max_hz": (0.0, 1000.0),
    "latency_warn_s": (0.0, 3600.0), "latency_error_s": (0.0, 3600.0),
    "diagnostic_updater.period": (0.05, 60.0),
}


def config_descriptions() -> dict[str, str]:
    """'section.field' -> the comment written next to the field in config.py (one source of truth)."""
    out = {}
    for f in dataclasses.fields(config_module.Config):
        source = inspect.getsource(type(getattr(config_module.Config(), f.name)))
        for m in re.finditer(r"^\s+(\w+): [^=]+=.*?#\s*(.+)$", source, re.M):
            out[f"{f.name}.{m.group(1)}"] = m.group(2).strip()
    return out


def defaults() -> dict[str, Any]:
    """Every parameter the node declares itself -> its default (node, updater, then config leaves)."""
    out = {k: v for k, (v, _) in {**NODE_SPEC, **UPDATER_SPEC}.items()}
    out.update(config_module.flatten(config_module.Config()))
    return out


def check(name: str, value: Any) -> None:
    """ValueError naming the parameter when ``value`` is out of its range or not one of its choices;
    numbers are checked whatever their type (an int for a float leaf, a float for an int leaf)."""
    if name in RANGES and isinstance(value, (int, float)) and not isinstance(value, bool):
        lo, hi = RANGES[name]
        if not lo <= value <= hi:
            raise ValueError(f"parameter {name!r} = {value!r} is out of range [{lo:g}, {hi:g}]")
    if name in config_module.REFUSED and not isinstance(value, bool) and value in config_module.REFUSED[name]:
        raise ValueError(f"parameter {name!r} = {value!r}: {config_module.REFUSED[name][value]}")
    choices = ALL_CHOICES.get(name, ())
    if isinstance(value, bool) and {"on", "off"} <= set(choices):
        value = "on" if value else "off"  # a bare on / off in YAML (rcl reads it as a boolean too)
    if name in ALL_CHOICES and value not in choices:
        raise ValueError(f"parameter {name!r} = {value!r} must be one of: "
                         f"{', '.join(c or repr(c) for c in ALL_CHOICES[name])}")  # '' shows as ''


def check_known(given: list[str] | set[str], declared: set[str]) -> None:
    """ValueError naming every given parameter that the node does not declare (a typo in the YAML)."""
    unknown = sorted(set(given) - set(declared))
    if unknown:
        raise ValueError(f"unknown parameter{'s' if len(unknown) > 1 else ''} {', '.join(map(repr, unknown))} "
                         f"(a typo? `python -m topometric_ros.parameters` lists them all)")


def config_from(values: Mapping[str, Any]) -> config_module.Config:
    """The Config of the node's parameter values (config leaves only; each checked first)."""
    leaves = config_module.flatten(config_module.Config())
    for name, value in values.items():
        check(name, value)
    return config_module.load_config(overrides={k: list(v) if isinstance(leaves[k], list) else v
                                                for k, v in values.items() if k in leaves})


def markdown_table() -> str:
    """docs/ros.md's parameter table: name, default, range or choices, description."""
    texts = {**{k: t for k, (_, t) in {**NODE_SPEC, **UPDATER_SPEC}.items()}, **config_descriptions()}
    rows = ["| parameter | default | range | description |", "| --- | --- | --- | --- |"]
    for name, default in defaults().items():
        if name in RANGES:
            lo, hi = RANGES[name]
            allowed = f"{lo:g} – {hi:g}"
        else:
            allowed = " \\| ".join(ALL_CHOICES.get(name, ()))
        shown = "''" if default == "" else str(default).lower() if isinstance(default, bool) else default
        rows.append(f"| `{name}` | `{shown}` | {allowed} | {texts.get(name, '').replace('|', chr(92) + '|')} |")
    return "\n".join(rows) + "\n"


if __name__ == "__main__":
    print(markdown_table(), end="")
