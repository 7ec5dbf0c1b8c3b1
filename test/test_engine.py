"""engine.run_tasks on a real local Ray (2 workers) and in-process: results, failures named, shared values (the
segmentation weights shipped once and checked by digest in the worker)."""
from __future__ import annotations

import json
import os
from dataclasses import replace

import pytest

from topometric_ros.audit import BagTask, audit_bag, bag_digest, config_digest, network_digest, weights_files
from topometric_ros.config import load_config
from topometric_ros.engine import run_tasks
from topometric_ros.replay import ReplayOptions, replay
from topometric_ros.sim.drift import DriftSpec
from topometric_ros.sim.writer import SimConfig, simulate


@pytest.fixture(scope="module")
def short_bag(tmp_path_factory):
    path = tmp_path_factory.mktemp("engine") / "office_10"
    simulate(SimConfig(scene="office1", frames=10, rate=5.0, speed=0.8, seed=7, drift=DriftSpec.parse("none")), path,
             progress=False)
    return path


def test_local_and_ray_give_the_same_results_and_name_each_failure(short_bag, tmp_path):
    items = [short_bag, tmp_path / "missing", short_bag / "metadata.yaml"]
    local = list(run_tasks(bag_digest, items, engine="local", progress=False))
    assert [i for i, _, _ in local] == items  # in order, in this process
    assert local[0][1] == bag_digest(short_bag) and local[0][2] is None
    assert local[1][1] is None and local[1][2].startswith("FileNotFoundError: ")
    on_ray = {i: (r, e) for i, r, e in run_tasks(bag_digest, items, engine="ray", workers=2, progress=False)}
    assert on_ray == {i: (r, e) for i, r, e in local}
    with pytest.raises(ValueError, match="engine must be one of ray, local"):
        list(run_tasks(bag_digest, items, engine="dask"))


def test_local_tasks_run_on_one_thread_and_leave_the_callers_threads_as_they_were():
    """Each in-process task gets one torch and one Open3D thread, as a Ray worker does (the same numbers);
    the caller's own counts are back between results and afterwards."""
    import torch

    from topometric_ros.engine import set_threads, threads

    before = threads()
    try:
        set_threads((2, 2))
        seen = []
        for _, result, error in run_tasks(_thread_counts, [0, 1], engine="local", progress=False):
            seen.append((result, threads()))
        assert seen == [((1, 1), (2, 2))] * 2 and error is None
        assert torch.get_num_threads() == 2
    finally:
        set_threads(before)


def _thread_counts(_item):
    from topometric_ros.engine import threads

    return threads()


def test_weights_shipped_to_ray_workers_by_digest_give_the_replay_of_the_shipped_network(short_bag, tmp_path):
    config = load_config(overrides={"segmentation.mode": "network"})
    weights = {name: path.read_bytes() for name, path in weights_files(config).items()}
    assert set(weights) == {"weights", "int8", "norm"}  # the files beside the weights travel with them
    key = {"bag": bag_digest(short_bag), "config": config_digest(config), "weights": network_digest(config)}
    task = BagTask(str(short_bag), short_bag.name, config, key)
    ((_, result, error),) = run_tasks(audit_bag, [task], engine="ray", workers=2, progress=False,
                                      shared={"weights": weights})
    assert error is None, error
    assert result["row"]["status"] == "ok" and result["row"]["scans"] == 10
    assert int(result["row"]["worker"].split(" ")[0].split(":")[1]) != os.getpid()  # ran in a Ray worker
    replay(short_bag, tmp_path / "single", config, ReplayOptions(progress=False, plot=False))
    strip = lambda recs: [{k: v for k, v in r.items() if not k.startswith("ms_")} for r in recs]  # noqa: E731
    shipped = json.loads(result["files"]["windows.json"])
    assert strip(shipped["windows"]) == strip(json.loads((tmp_path / "single" / "windows.json").read_text())["windows"])
    assert shipped["summary"]["config"]["segmentation.weights"].endswith(f"{key['weights']}/rangenet.pt")
    # other bytes under the same digest: the worker refuses them, the task fails with the reason
    ((_, result, error),) = run_tasks(audit_bag, [task], engine="ray", workers=2, progress=False,
                                      shared={"weights": {**weights, "int8": weights["int8"] + b" "}})
    assert result is None and "do not hash to" in error
    ((_, result, error),) = run_tasks(audit_bag, [task], engine="ray", workers=2, progress=False,
                                      shared={"weights": {k: v for k, v in weights.items() if k != "norm"}})
    assert result is None and "do not hash to" in error  # statistics left behind: not the network of the key
    # in-process: the file itself, its digest checked
    bad = replace(task, key={**key, "weights": "0" * 64})
    ((_, result, error),) = run_tasks(audit_bag, [bad], engine="local", progress=False)
    assert result is None and "changed since the audit started" in error


def test_rays_start_up_lines_stay_out_of_the_progress_bar(tmp_path):
    """Ray starts before the bar is drawn, so what Ray prints at start-up (e.g. its token-authentication line)
    is on its own line, not glued to the bar's first state. A fresh process: a Ray already up prints nothing."""
    import subprocess
    import sys

    code = ("import math\nfrom topometric_ros.engine import run_tasks\n"
            "print(sorted(r for _, r, _ in run_tasks(math.sqrt, [1, 4, 9], engine='ray', workers=1, desc='t')))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert done.returncode == 0 and done.stdout.strip() == "[1.0, 2.0, 3.0]", done.stderr
    states = [s for s in done.stderr.replace("\n", "\r").split("\r") if "%|" in s]
    assert states and states[-1].startswith("t: 100%"), done.stderr
    assert all(s.rstrip().endswith("]") for s in states), done.stderr  # nothing printed into a bar's line


def test_a_cluster_address_that_takes_no_connection_is_refused_at_once():
    """Ray itself retries an unreachable --address for minutes (warnings naming another address); a closed port
    is refused in seconds with the address given."""
    import socket
    import time

    from topometric_ros.engine import ensure_ray

    with socket.socket() as s:  # a port nothing listens on once this socket closes
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    started = time.perf_counter()
    with pytest.raises(ValueError, match=rf"cannot reach a Ray cluster at 127\.0\.0\.1:{port} .*ray start --head"):
        ensure_ray(address=f"127.0.0.1:{port}")
    assert time.perf_counter() - started < 10
    with pytest.raises(ValueError, match="workers must be >= 1, got 0"):
        ensure_ray(workers=0)
