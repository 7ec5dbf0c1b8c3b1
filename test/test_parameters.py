"""parameters.py without ROS: range and choice checks whatever the value's type, unknown keys, the Config
the node builds, and docs/ros.md's parameter table (generated from the code) being current."""
from pathlib import Path

import pytest

from topometric_ros import config, parameters

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name, value", [
    ("health.stale_after_s", 0),  # an int for a float leaf: rclpy's floating_point_range would not apply
    ("health.stale_after_s", 0.0),
    ("window.size", -1),
    ("window.size", 500.0),  # a float for an int leaf
    ("segmentation.threads", -1),
    ("diagnostic_updater.period", 0),
    ("scan_rate_max_hz", 1e9),
])
def test_out_of_range_values_are_refused_whatever_their_type(name, value):
    with pytest.raises(ValueError, match=name.replace(".", r"\.") + ".*out of range"):
        parameters.check(name, value)


def test_in_range_values_and_choices():
    parameters.check("health.stale_after_s", 5)
    parameters.check("window.size", 10)
    parameters.check("window.size", 0)  # automatic
    with pytest.raises(ValueError, match=r"'window\.size' = 1: a window needs 2 scans or more; 0 = automatic"):
        parameters.check("window.size", 1)
    with pytest.raises(ValueError, match=r"'window\.size' = 1: a window needs 2 scans or more"):
        config.load_config(overrides={"window.size": 1})
    parameters.check("points_qos", "reliable")
    with pytest.raises(ValueError, match="'segmentation.mode' = 'magic' must be one of: network, labels, none"):
        parameters.check("segmentation.mode", "magic")
    with pytest.raises(ValueError, match="odom_qos"):
        parameters.check("odom_qos", "best_effort")


@pytest.mark.parametrize("value, words", [
    (["a", "b"], "must be 7 finite numbers"),
    ([1, 2], "must be 7 finite numbers"),
    ([0, 0, 0, 0, 0, 0, float("nan")], "must be 7 finite numbers"),
    ([0, 0, 0, 0, 0, 0, True], "must be 7 finite numbers"),
    (["0", "0", "0", "0", "0", "0", "1"], "must be 7 finite numbers"),  # strict as every other key
    ([0, 0, 0, 0, 0, 0, 0], "has zero norm"),
])
def test_a_bad_extrinsic_is_refused_naming_its_key(value, words):
    with pytest.raises(ValueError, match=rf"config key 'window\.extrinsic'.*{words}"):
        config.load_config(overrides={"window.extrinsic": value})


def test_an_extrinsic_of_whole_numbers_is_taken_as_floats():
    assert config.load_config(overrides={"window.extrinsic": [0, 0, 1, 0, 0, 0, 1]}).window.extrinsic == \
        [0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]


@pytest.mark.parametrize("text, expected", [("1e-3", 0.001), ("2.5e1", 25.0), ("7", 7.0), ("0.5", 0.5)])
def test_a_float_setting_takes_exponent_notation(text, expected):
    """PyYAML (YAML 1.1) leaves 1e-3 a string; rcl's parser reads it as a double: replay takes it too."""
    import yaml

    assert config.load_config(overrides={"health.cpv_warn": yaml.safe_load(text)}).health.cpv_warn == expected


@pytest.mark.parametrize("text", ["nan", ".nan", "-inf", ".inf", "1e999"])
def test_a_float_setting_must_be_finite(text):
    """NaN and infinities are refused, named as such (a NaN would pass every range check silently)."""
    import yaml

    with pytest.raises(ValueError, match=r"'metrics\.cpv_epsilon' must be a finite number"):
        config.load_config(overrides={"metrics.cpv_epsilon": yaml.safe_load(text)})


def test_every_numeric_setting_has_a_range_holding_its_default():
    """A numeric leaf without a range would take a negative distance or angle silently (and the node would
    declare it without a range)."""
    numeric = {k: v for k, v in config.flatten(config.Config()).items()
               if isinstance(v, (int, float)) and not isinstance(v, bool)}
    assert set(numeric) <= set(config.RANGES), sorted(set(numeric) - set(config.RANGES))
    for key, value in numeric.items():
        lo, hi = config.RANGES[key]
        assert lo <= value <= hi, key
    with pytest.raises(ValueError, match=r"'planes\.inlier_distance' = -0\.1 is out of range"):
        config.load_config(overrides={"planes.inlier_distance": -0.1})


def test_unknown_keys_are_named():
    with pytest.raises(ValueError, match=r"unknown parameter 'window\.sise'"):
        parameters.check_known({"window.sise", "window.size"}, {"window.size"})
    parameters.check_known({"window.size"}, {"window.size", "use_sim_time"})


def test_config_from_node_values_converts_and_checks():
    cfg = parameters.config_from({"health.stale_after_s": 7, "window.size": 10,
                                  "window.extrinsic": (0, 0, 1, 0, 0, 0, 1)})
    assert cfg.health.stale_after_s == 7.0 and isinstance(cfg.health.stale_after_s, float)
    assert cfg.window.size == 10 and cfg.window.extrinsic == [0, 0, 1, 0, 0, 0, 1]
    with pytest.raises(ValueError, match="stale_after_s"):
        parameters.config_from({"health.stale_after_s": 0})
    with pytest.raises(ValueError, match="must be int"):
        parameters.config_from({"window.size": 5.5})


def test_every_range_names_a_parameter_and_node_keys_agree_with_config():
    every = parameters.defaults()
    assert set(parameters.RANGES) <= set(every)
    assert set(config.NODE_PARAMETERS) == set(parameters.NODE_SPEC) | set(parameters.UPDATER_SPEC) | {"use_sim_time"}
    assert set(parameters.config_descriptions()) == set(config.flatten(config.Config()))  # every leaf documented


def test_the_shipped_parameter_file_is_valid_for_the_node_and_replay():
    """config/topometric.yaml: every key is a parameter, every value passes the node's checks, and replay's
    load_config reads it (the '/**' top key matches the node under any namespace)."""
    import yaml

    doc = yaml.safe_load((ROOT / "config" / "topometric.yaml").read_text())
    assert list(doc) == ["/**"]
    values = doc["/**"]["ros__parameters"]
    parameters.check_known(set(values), set(parameters.defaults()))
    for name, value in values.items():
        parameters.check(name, value)
    assert config.load_config(ROOT / "config" / "topometric.yaml").window.size == values["window.size"]


def test_docs_parameter_table_is_current():
    """docs/ros.md holds `python -m topometric_ros.parameters` between its markers; regenerate it when
    this fails."""
    text = (ROOT / "docs" / "ros.md").read_text()
    begin, end = "<!-- parameters:begin -->\n", "<!-- parameters:end -->"
    assert begin in text and end in text
    assert text.split(begin, 1)[1].split(end, 1)[0] == parameters.markdown_table()


def test_a_bare_on_or_off_is_a_choice_not_a_type_error():
    """YAML (and rcl's parameter parser) reads a bare on / off as a boolean: accepted for on|off choices."""
    parameters.check("sensor.deskew", True)
    assert parameters.config_from({"sensor.deskew": False}).sensor.deskew == "off"
    with pytest.raises(ValueError, match="segmentation.mode"):
        parameters.check("segmentation.mode", True)


def test_the_shipped_parameter_file_holds_every_config_leaf_at_its_default():
    """config/topometric.yaml is the node's parameter file and documents every tunable: it names every config
    leaf, each at the default config.py gives (a change of default must reach the file too)."""
    import yaml

    doc = yaml.safe_load((ROOT / "config" / "topometric.yaml").read_text())["/**"]["ros__parameters"]
    assert set(config.flatten(config.Config())) <= set(doc)
    assert config.load_config(ROOT / "config" / "topometric.yaml") == config.Config()


def test_both_ends_of_every_range_are_accepted_and_just_beyond_them_refused():
    """RANGES bounds are both included: each leaf takes its min and its max (an int leaf as an int), and refuses
    a value just outside either end."""
    defaults = config.flatten(config.Config())
    for key, (lo, hi) in config.RANGES.items():
        kind = type(defaults[key])
        for value in (lo, hi):
            if key in config.REFUSED and value in config.REFUSED[key]:
                continue
            cfg = config.load_config(overrides={key: kind(value)})
            assert config.flatten(cfg)[key] == value, key
        step = 1 if kind is int else max(1e-9, 1e-6 * (hi - lo))
        for value in (lo - step, hi + step):
            with pytest.raises(ValueError, match="out of range"):
                config.load_config(overrides={key: kind(value)})


@pytest.mark.parametrize("value", [True, False, 10.0, 2.5, "10"])
def test_a_whole_number_setting_refuses_booleans_floats_and_strings(value):
    """window.size is an int: True (which Python counts as 1), a float, even a whole one, and a string are
    refused as the wrong type, not taken or rounded."""
    with pytest.raises(ValueError, match=r"'window\.size' must be int"):
        config.load_config(overrides={"window.size": value})


def test_a_string_setting_of_few_choices_refuses_any_other_value_in_a_config():
    with pytest.raises(ValueError, match=r"'segmentation\.mode' must be one of network, labels, none"):
        config.load_config(overrides={"segmentation.mode": "magic"})
    with pytest.raises(ValueError, match=r"'planes\.detector' must be one of"):
        config.load_config(overrides={"planes": {"detector": "Ring"}})
    assert config.load_config(overrides={"segmentation.mode": "labels"}).segmentation.mode == "labels"


def test_an_extrinsic_of_any_unit_quaternion_is_taken():
    """A half turn about x (qx = 1, the rest 0) is a valid rotation: only a quaternion of zero norm is refused."""
    for q in ([1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]):
        assert config.load_config(overrides={"window.extrinsic": [0, 0, 0, *q]}).window.extrinsic[3:] == q


def test_a_section_given_a_single_value_is_refused_naming_it():
    with pytest.raises(ValueError, match=r"config key 'window' is a section; give a mapping"):
        config.load_config(overrides={"window": 5})
