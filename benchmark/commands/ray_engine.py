"""``bench4d run-all --engine ray``: a sweep's (scene, seed) groups as tasks of a Ray cluster.

Each group is one Ray task that declares its needs (``--threads`` CPUs, one GPU on ``--device cuda``)
and runs its methods in order, as a local worker does, so the 4D methods find the geometry and field
fits their group made before them. Tasks write results and caches exactly as the local runner does
(atomic writes, per-file locks): a sweep is resumable and its metrics are the local runner's. A task
whose worker dies (killed, out of memory, a lost node) is retried up to ``retries`` times; a run that
raises is reported as failed and the other tasks go on.

Without an address, Ray starts a local instance on this machine; ``--address HOST:PORT`` (or ``auto``)
joins a running cluster, whose nodes must all have bench4d installed and see the same results and
cache folders (a shared file system). Ray is an optional dependency (``pip install 'bench4d[ray]'``).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Callable, Optional

from benchmark.core.errors import InputError

RAY_RETRIES = 2
"""How often a group whose worker died is run again before it is reported as failed."""


def _import_ray():
    try:
        import ray
    except ImportError:
        raise InputError(None, "--engine", "ray is not installed: pip install 'bench4d[ray]' (or pip install ray)") \
            from None
    return ray


def _ray_group(group: list, keep_going: bool, threads: int, git: dict) -> list[dict]:
    """One (scene, seed) group on a Ray worker: the local worker's set-up, then its runs in order."""
    from benchmark.runner import start_worker

    from .run_all import _run_group

    start_worker(threads, git)
    return _run_group(group, keep_going)


def _check_reachable(address: str) -> None:
    """A ``HOST:PORT`` where nothing listens is a one-line error now: Ray itself would wait minutes."""
    import socket

    host, sep, port = address.rpartition(":")
    if not sep or not port.isdigit():
        raise InputError(None, "--address", f"expected HOST:PORT, ray://HOST:PORT or auto, got {address!r}")
    try:
        socket.create_connection((host, int(port)), timeout=5).close()
    except OSError as err:
        raise InputError(None, "--address", f"no Ray cluster answers at {address} ({err.strerror or err})") from None


def connect(address: Optional[str], *, quiet: bool) -> dict:
    """Join the cluster at ``address`` (``None``: start a local instance); its total resources."""
    ray = _import_ray()
    if address and address != "auto" and not address.startswith("ray://"):
        _check_reachable(address)
    if not ray.is_initialized():
        try:
            ray.init(address=address, include_dashboard=False, log_to_driver=not quiet,
                     configure_logging=not quiet)
        except ConnectionError as err:
            raise InputError(None, "--address", f"no Ray cluster at {address!r}: {err}") from None
    return dict(ray.cluster_resources())


def disconnect() -> None:
    """Leave the cluster (a local instance this process started stops with it): a process that stays
    connected is ended by Ray when the cluster goes away."""
    import ray

    if ray.is_initialized():
        ray.shutdown()


def run_groups(groups: list[list], *, address: Optional[str], threads: int, gpus: int, git: dict,
               keep_going: bool, quiet: bool, report: Callable[[list[dict]], None],
               stop: Callable[[], bool], retries: int = RAY_RETRIES) -> None:
    """Run ``groups`` as Ray tasks of ``threads`` CPUs and ``gpus`` GPUs each, handing each finished
    group's outcomes to ``report`` (as :func:`benchmark.commands.run_all._run_group` returns them) in the
    order they finish. Once ``stop()`` is true (a run failed without ``--keep-going``) the tasks still
    pending are cancelled."""
    ray = _import_ray()
    resources = connect(address, quiet=quiet)
    if resources.get("CPU", 0) < threads or resources.get("GPU", 0) < gpus:
        raise InputError(None, "--threads" if resources.get("CPU", 0) < threads else "--device",
                         f"each group needs {threads} CPU(s) and {gpus} GPU(s); the cluster has "
                         f"{resources.get('CPU', 0):g} CPU(s) and {resources.get('GPU', 0):g} GPU(s)")
    task = ray.remote(num_cpus=threads, num_gpus=gpus, max_retries=retries, retry_exceptions=False)(_ray_group)
    pending = {task.remote(group, keep_going, threads, git): group for group in groups}
    done = 0
    if not quiet:
        print(f"run-all (ray): {sum(len(g) for g in groups)} run(s) in {len(groups)} group(s) on "
              f"{resources.get('CPU', 0):g} CPU(s), {threads} per group", file=sys.stderr)
    while pending:
        ready, _ = ray.wait(list(pending), num_returns=1)
        group = pending.pop(ready[0])
        try:
            items = ray.get(ready[0])
        except ray.exceptions.RayError as err:  # the worker died more often than it was retried
            failure = RuntimeError(f"Ray task failed after {retries} retries: {type(err).__name__}: {err}")
            items = [{"method": o.method, "scene": Path(o.scene).name, "seed": o.seed, "error": failure}
                     for o in group]
        done += 1
        report(items)
        if not quiet:
            print(f"run-all (ray): {done}/{len(groups)} group(s) done", file=sys.stderr)
        if stop():
            for ref in pending:
                ray.cancel(ref, force=True)
            return
