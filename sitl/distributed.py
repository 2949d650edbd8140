"""Ray, the optional scale-out of training sweeps (``python -m sitl.sweep``) and ``swarm_test paper --ray``.

Ray is an extra (``pip install "swarmnav[ray]"``): without it nothing else changes, and the
commands that ask for it say in one line how to install it. One function connects to a
local Ray (started here, on this machine's cores) or to an existing cluster, the same way
for both: the project's code travels with the job (``py_modules``), and every task is
pinned to one CPU with one thread for torch, OpenMP and numba, so a node runs as many
tasks as it has cores without oversubscribing them.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from types import ModuleType

#: What a user without Ray reads (one line).
RAY_INSTALL_HINT = 'Ray is not installed; install the extra with: pip install "swarmnav[ray]" (or pip install "ray[client]")'

#: Environment of every worker: one thread per task (each task holds one CPU).
ONE_THREAD_ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}

#: The ``--address`` that starts a Ray on this machine instead of joining a cluster.
LOCAL = "local"


class RayUnavailable(RuntimeError):
    """Ray is not importable, or the cluster could not be reached (the message says which, in one line)."""


def import_ray() -> ModuleType:
    """The ``ray`` module, or :class:`RayUnavailable` with the install hint."""
    try:
        import ray
    except ImportError:
        raise RayUnavailable(RAY_INSTALL_HINT) from None
    return ray


def ray_available() -> bool:
    """Whether ``import ray`` works (the tests skip without it)."""
    try:
        import_ray()
    except RayUnavailable:
        return False
    return True


def connect(address: str | None = LOCAL, num_cpus: int | None = None, log_to_driver: bool = True) -> ModuleType:
    """Connect to Ray and return the module; a no-op when this process is already connected.

    Args:
        address: ``local`` or None (start a Ray on this machine with ``num_cpus`` cores, all
            by default), ``auto`` (the cluster ``ray start`` runs on this machine), or a
            cluster's address such as ``ray://head:10001`` (Ray Client) or ``head:6379``.
        num_cpus: cores of a local Ray (ignored when joining a cluster).
        log_to_driver: show the tasks' output (progress lines) here.
    """
    ray = import_ray()
    if ray.is_initialized():
        return ray
    import companion
    import sitl

    # The workers import this checkout's code, not whatever a node has installed: on this
    # machine from where it lies (its numba cache included: a fresh one costs ~13 s of
    # compilation per node), on a cluster uploaded with the job.
    packages = [Path(sitl.__file__).parent, Path(companion.__file__).parent]
    env_vars = dict(ONE_THREAD_ENV)
    os.environ.setdefault("RAY_DEDUP_LOGS", "0")  # every task's progress lines, not "repeated 2x"
    local = address in (None, LOCAL)
    if local:
        root = str(packages[0].parent)
        env_vars["PYTHONPATH"] = os.pathsep.join(filter(None, (root, os.environ.get("PYTHONPATH"))))
    # A local Ray gets a second try: its raylet must register within a fixed 30 s, which a
    # machine busy with other work can miss once.
    for attempt in range(2 if local else 1):
        try:
            if local:
                # address="local": a Ray of our own even where `ray start` ran on this machine before
                # (without it ray.init joins that cluster, or fails on its stale address file).
                ray.init(address="local", num_cpus=num_cpus, include_dashboard=False,
                         runtime_env={"env_vars": env_vars}, log_to_driver=log_to_driver, logging_level="warning")
            else:
                ray.init(address=address, runtime_env={"env_vars": env_vars, "py_modules": [str(p) for p in packages]},
                         log_to_driver=log_to_driver, logging_level="warning")
            return ray
        except Exception as err:  # noqa: BLE001 - Ray raises bare Exceptions on start-up failures
            ray.shutdown()
            first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            if attempt or not local:
                raise RayUnavailable(f"cannot {'start' if local else 'connect to'} Ray"
                                     f"{'' if local else ' at ' + str(address)}: {first}") from None
            log(f"starting Ray failed ({first}); trying once more")
    return ray


def single_thread() -> None:
    """Inside a task: one torch thread (the task holds one CPU; the env vars cover OpenMP and numba)."""
    import torch

    torch.set_num_threads(1)


def describe_cluster(ray: ModuleType) -> str:
    """``Ray: 2 CPUs on 1 node(s)`` for the log."""
    resources = ray.cluster_resources()
    nodes = sum(1 for n in ray.nodes() if n.get("Alive"))
    return f"Ray: {resources.get('CPU', 0):g} CPUs on {nodes} node(s)"


def log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)
