"""Where many independent jobs run: on Ray (a local Ray started on demand, or a cluster) or in this process.

``run_tasks(fn, items, engine=..., workers=..., address=...)`` calls ``fn(item, **shared)`` once per item and
yields ``(item, result, error)`` as each finishes (``error`` is None on success, else one line saying why;
``result`` is then None), with a tqdm bar over the items. One item's failure never stops the others.

- ``engine="ray"``: each item is one Ray task (1 CPU, ``max_retries=0``: a worker killed mid-task makes
  that item fail with the reason, the others go on). Without ``address`` a local Ray is started on demand
  with ``workers`` CPUs on the loopback interface (no dashboard), and kept for later calls of this process
  with the same ``workers``; with ``address`` (``HOST:PORT`` of a cluster started with ``ray start --head``,
  or ``auto``) the tasks go to that cluster and its CPUs bound the parallelism. ``shared`` values are put
  in Ray's object store once and handed to every task (the segmentation weights, for instance), not
  pickled into each task. Ctrl-C cancels the tasks still running and raises KeyboardInterrupt.
- ``engine="local"``: a plain loop in this process, in item order (no Ray, ``workers`` unused).

Every task runs with one thread for torch and Open3D (set in the task, either engine): the parallelism is
across items, and the result of a task does not depend on where it ran.
"""
from __future__ import annotations

from typing import Any, Callable, Iterable, Iterator

ENGINES = ("ray", "local")
POLL_S = 1.0  # ray.wait timeout: how often the loop wakes (Ctrl-C is seen within this)

_RAY: dict = {}  # what this process started or joined: {"key": (address or None, workers)}


def single_thread() -> None:
    """One thread for torch and Open3D in this process (a task's share of the machine is one core)."""
    set_threads((1, 1))


def threads() -> tuple[int | None, int | None]:
    """(torch threads, Open3D max threads) of this process; None for a library that is not installed."""
    return _torch_threads(), _open3d_threads()


def set_threads(counts: tuple[int | None, int | None]) -> None:
    """Set torch's and Open3D's thread counts (as threads() gives them; None leaves that library alone)."""
    torch_n, open3d_n = counts
    if torch_n is not None:
        _torch_threads(torch_n)
    if open3d_n is not None:
        _open3d_threads(open3d_n)


def _torch_threads(n: int | None = None) -> int | None:
    try:
        import torch
    except ImportError:
        return None
    if n is not None:
        torch.set_num_threads(n)
    return torch.get_num_threads()


def _open3d_threads(n: int | None = None) -> int | None:
    try:
        import open3d as o3d

        if n is not None:
            o3d.utility.set_max_threads(n)
        return o3d.utility.get_max_threads()
    except (ImportError, AttributeError):
        return None


def _call(fn: Callable, item: Any, shared: dict) -> Any:
    single_thread()
    return fn(item, **shared)


def _call_remote(fn: Callable, item: Any, names: tuple, *values: Any) -> Any:
    """A Ray task: the shared values come as top-level arguments, which Ray resolves from the object store."""
    return _call(fn, item, dict(zip(names, values)))


def describe(exc: BaseException) -> str:
    """One line: what went wrong in a task (the task's own exception for a task error; the crash reason
    for a worker that died)."""
    cause = getattr(exc, "cause", None)
    if isinstance(cause, BaseException):  # ray.exceptions.RayTaskError: the exception raised inside fn
        exc = cause
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    text = lines[0] if lines else ""
    name = type(exc).__name__
    if name.startswith("RayTaskError(") and len(lines) > 1:  # no .cause: the last line is "Error: message"
        text = lines[-1]
    return f"{name}: {text}" if text else name


def run_tasks(fn: Callable, items: Iterable, engine: str = "ray", workers: int = 2, address: str | None = None,
              desc: str = "tasks", progress: bool = True, shared: dict | None = None
              ) -> Iterator[tuple[Any, Any, str | None]]:
    """(item, fn(item, **shared), None) or (item, None, reason) for every item, as they finish. ``fn`` must
    be importable by the workers (a module-level function of an installed package)."""
    from tqdm import tqdm

    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {', '.join(ENGINES)}, got {engine!r}")
    if engine == "ray":
        _check_workers(workers, address)
    items = list(items)
    shared = dict(shared or {})
    if engine == "ray" and items:
        ensure_ray(workers, address)  # before the bar: Ray's start-up lines then stay out of it
    bar = tqdm(total=len(items), desc=desc, unit="task", disable=not progress or not items)
    try:
        if engine == "local" or not items:
            yield from _run_local(fn, items, shared, bar)
            return
        yield from _run_ray(fn, items, shared, bar)
    finally:
        bar.close()


def _run_local(fn: Callable, items: list, shared: dict, bar) -> Iterator[tuple[Any, Any, str | None]]:
    """run_tasks in this process, one thread per task as on Ray (the same numbers); the caller's thread
    counts are back once the tasks are done (or the caller stops asking for them)."""
    before = threads()
    try:
        for item in items:
            try:
                result, error = _call(fn, item, shared), None
            except Exception as e:  # noqa: BLE001 - one item's failure is reported, the others run
                result, error = None, describe(e)
            bar.update()
            set_threads(before)  # the caller's counts while it handles this result
            yield item, result, error
    finally:
        set_threads(before)


def ensure_ray(workers: int = 2, address: str | None = None) -> None:
    """Ray for this process: the cluster at ``address``, else a local Ray with ``workers`` CPUs (loopback,
    no dashboard). One already started by this function with the same settings is reused; one started by
    the caller (``ray.init`` before) is used as it is."""
    import ray

    _check_workers(workers, address)
    if address:
        _check_reachable(address)  # before a running Ray is shut down for it
    key = (address or None, None if address else int(workers))
    if ray.is_initialized():
        if not _RAY or _RAY.get("key") == key:
            return  # the caller's Ray, or ours with the same settings
        ray.shutdown()
    common = dict(include_dashboard=False, log_to_driver=False, configure_logging=False)
    if address:
        ray.init(address=address, **common)
    else:  # "local": a new local Ray even when a cluster runs on this machine
        ray.init(address="local", num_cpus=int(workers), _node_ip_address="127.0.0.1",
                 object_store_memory=256 * 1024 * 1024, **common)
    _RAY["key"] = key


def _check_workers(workers: int, address: str | None) -> None:
    """A local Ray needs one worker or more (a cluster at ``address`` brings its own)."""
    if not address and workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")


def _check_reachable(address: str, timeout_s: float = 5.0) -> None:
    """ValueError when a HOST:PORT cluster address takes no connection within ``timeout_s`` (Ray itself retries
    for minutes); 'auto' and ray:// addresses are left to Ray."""
    import socket

    host, sep, port = address.rpartition(":")
    if not sep or "://" in address or not port.isdigit():
        return
    host = host.strip("[]")  # [::1]:6379
    try:
        socket.create_connection((host, int(port)), timeout=timeout_s).close()
    except OSError as e:
        raise ValueError(f"cannot reach a Ray cluster at {address} ({e.strerror or e}): start one there with "
                         "`ray start --head`, or leave --address out for a local Ray") from None


def shutdown() -> None:
    """Stop the Ray this module started or joined (tests; a process's Ray also stops when it exits)."""
    import ray

    if _RAY and ray.is_initialized():
        ray.shutdown()
    _RAY.clear()


def _run_ray(fn: Callable, items: list, shared: dict, bar) -> Iterator[tuple[Any, Any, str | None]]:
    """run_tasks on the Ray it started (ensure_ray)."""
    import ray

    remote = ray.remote(num_cpus=1, max_retries=0)(_call_remote)
    names, refs = tuple(shared), [ray.put(v) for v in shared.values()]  # once, whatever the number of tasks
    pending = {remote.remote(fn, item, names, *refs): item for item in items}
    try:
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1, timeout=POLL_S)
            for ref in done:
                item = pending.pop(ref)
                try:
                    result, error = ray.get(ref), None
                except Exception as e:  # noqa: BLE001 - RayTaskError, WorkerCrashedError, ...: that item failed
                    result, error = None, describe(e)
                bar.update()
                yield item, result, error
    except BaseException:  # Ctrl-C (KeyboardInterrupt) or the consumer stopped: cancel what still runs
        for ref in pending:
            try:
                ray.cancel(ref, force=True)
            except Exception:  # noqa: BLE001 - already finished or gone
                pass
        raise
