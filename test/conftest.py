"""Shared fixtures: small simulated bags, made once per test session."""
from __future__ import annotations

import numpy as np
import pytest

from topometric_ros.sim.drift import DriftSpec
from topometric_ros.sim.writer import SimConfig, simulate


@pytest.fixture(scope="session")
def office_bag(tmp_path_factory):
    """A 30-scan office1 bag with rotation+translation drift, MCAP; returns (path, summary)."""
    path = tmp_path_factory.mktemp("bags") / "office1_rt"
    cfg = SimConfig(scene="office1", frames=30, rate=5.0, speed=0.8, drift=DriftSpec.parse("rt:1.0"))
    return path, simulate(cfg, path, progress=False)


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture
def cli_exit_code():
    """topometric's exit code for an argv, argparse's own refusals (SystemExit) included."""
    from topometric_ros.cli import main

    def run(argv) -> int:
        try:
            return main(argv)
        except SystemExit as e:
            return e.code
    return run


@pytest.fixture
def split_off_odometry():
    """split(bag, recording, sidecar): /odom into a sidecar bag written at its stamps, every other topic into a
    recording whose receive times are 1000 s later (two recordings, two receive clocks)."""
    from topometric_ros import bag
    from topometric_ros.cloud import stamp_seconds

    def split(path, recording, sidecar):
        with bag.BagWriter(recording) as rec, bag.BagWriter(sidecar) as side:
            for topic, t_ns, msg in bag.read_messages(path):
                if topic == "/odom":
                    side.write("/odom", stamp_seconds(msg.header), msg)
                else:
                    rec.write(topic, t_ns * 1e-9 + 1000.0, msg)
        return recording, sidecar

    return split
