"""Where the cells run: serially in this process, or as Ray tasks (a local instance sized to the machine, or an
existing cluster with ``--address``).  Both take the same payload dicts and return the same result dicts, so a
sweep writes the same files either way; only the driver loop in :mod:`.runner` talks to an executor.

Sizing: ``workers`` runs at a time (default: one per core of the machine, or per CPU of the cluster), each with
``threads = max(1, cores // workers)`` torch/OpenCV threads.  A Ray task asks for ``threads`` CPUs, so Ray never
packs more runs on a node than it has cores, and a thread budget never exceeds the largest node.
"""
from __future__ import annotations

import itertools
import logging
import os
import sys
from contextlib import contextmanager
from typing import Any, Callable, Optional

from . import cells

LOG = logging.getLogger("pvslam")
FUNCTIONS: dict[str, Callable[[dict], dict]] = {"cell": cells.execute_cell, "prepare": cells.prepare_dataset}


def machine_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def ray_available() -> bool:
    try:
        import ray  # noqa: F401
    except ImportError:
        return False
    return True


class SerialExecutor:
    """Runs each task in this process when the driver waits for it (one at a time)."""

    kind = "serial"

    def __init__(self, threads: int = 0):
        self.slots = 1
        self.threads = threads or machine_cores()
        self._ids = itertools.count()
        self._tasks: dict[int, tuple[str, dict]] = {}

    def submit(self, fn: str, payload: dict) -> int:
        h = next(self._ids)
        self._tasks[h] = (fn, payload)
        return h

    def wait(self, handles: list, timeout: float) -> list[tuple[Any, dict]]:
        h = handles[0]
        fn, payload = self._tasks.pop(h)
        return [(h, FUNCTIONS[fn](payload))]

    def cancel(self, handles: list) -> None:
        for h in handles:
            self._tasks.pop(h, None)

    def close(self) -> None:
        pass


#: the address the local Ray instance binds (its node address: Ray binds its servers to that)
LOOPBACK = "127.0.0.1"


@contextmanager
def _single_machine_ray():
    """Ray's single-machine mode while ``ray.init`` runs (its mode on macOS and Windows, ``ENABLE_RAY_CLUSTER``
    False): elsewhere Ray replaces a loopback node address by the machine's network one.  A no-op where the
    installed Ray has no such switch."""
    try:
        from ray._private import ray_constants
    except ImportError:
        yield
        return
    saved = getattr(ray_constants, "ENABLE_RAY_CLUSTER", None)
    if saved is None:
        yield
        return
    ray_constants.ENABLE_RAY_CLUSTER = False
    try:
        yield
    finally:
        ray_constants.ENABLE_RAY_CLUSTER = saved


class RayExecutor:
    """Ray tasks; starts (and later stops) a local instance unless one is running or ``address`` is given."""

    kind = "ray"

    def __init__(self, address: Optional[str] = None, workers: int = 0, threads: int = 0):
        import ray

        self.ray = ray
        self.owned = False
        if not ray.is_initialized():
            common = dict(logging_level=logging.WARNING, log_to_driver=False, configure_logging=True)
            if address:
                ray.init(address=address, **common)
            else:
                cores = machine_cores()
                w = workers or cores
                t = threads or max(1, cores // w)
                # A small object store: payloads and results are a few kB (outputs go to files).  Every port on
                # 127.0.0.1 only: whoever reaches a Ray port can run code as this user.
                with _single_machine_ray():
                    ray.init(num_cpus=max(cores, w * t), include_dashboard=False,
                             object_store_memory=128 * 1024 ** 2, _node_ip_address=LOOPBACK, **common)
                node_ip = ray.util.get_node_ip_address()
                if node_ip != LOOPBACK:
                    LOG.warning("the local Ray instance listens on %s, not only on %s (this Ray version ignores "
                                "the request); anyone who reaches its ports can run code as this user", node_ip,
                                LOOPBACK)
            self.owned = True
        total = int(ray.cluster_resources().get("CPU", 1))
        node_max = max((int(n["Resources"].get("CPU", 0)) for n in ray.nodes() if n.get("Alive")), default=total)
        self.slots = workers or total
        self.threads = max(1, min(threads or total // self.slots, max(1, node_max)))
        self.cluster_cpus = total
        self._remote = {name: ray.remote(fn) for name, fn in FUNCTIONS.items()}
        self._payloads: dict[Any, dict] = {}

    def submit(self, fn: str, payload: dict):
        # Relative paths in a config mean the driver's folder, as with `pvslam run`; a worker on another node
        # without that folder keeps its own.
        ref = self._remote[fn].options(num_cpus=self.threads).remote({**payload, "cwd": os.getcwd()})
        self._payloads[ref] = payload
        return ref

    def wait(self, handles: list, timeout: float) -> list[tuple[Any, dict]]:
        ready, _ = self.ray.wait(handles, num_returns=1, timeout=timeout)
        if ready:  # collect everything that is ready, not only the first
            ready, _ = self.ray.wait(handles, num_returns=len(handles), timeout=0)
        out = []
        for ref in ready:
            payload = self._payloads.pop(ref)
            try:
                out.append((ref, self.ray.get(ref)))
            except Exception as exc:  # the worker died (OOM kill, segfault) or the task was cancelled
                lines = str(exc).strip().splitlines()
                out.append((ref, {"name": payload.get("name", "?"), "status": cells.FAILED, "crashed": True,
                                  "error": f"{type(exc).__name__}: {lines[-1] if lines else ''}",
                                  "traceback": str(exc), "seconds": None}))
        return out

    def cancel(self, handles: list) -> None:
        for ref in handles:
            try:
                self.ray.cancel(ref, force=True)
            except Exception:  # already finished or gone
                pass
            self._payloads.pop(ref, None)

    def close(self) -> None:
        if self.owned and self.ray.is_initialized():
            self.ray.shutdown()


def make_executor(serial: bool = False, address: Optional[str] = None, workers: int = 0, threads: int = 0,
                  log: Callable[[str], None] = lambda m: print(m, file=sys.stderr)):
    """Ray when it is installed (and not ``serial``), else the in-process fallback with the same outputs."""
    if serial:
        if address:
            raise ValueError("--serial and --address exclude each other")
        return SerialExecutor(threads)
    if not ray_available():
        if address:
            raise RuntimeError(f"--address {address}: Ray is not installed; pip install 'pvslam[sweep]'")
        log("pvslam sweep: Ray is not installed, running the cells one after another in this process "
            "(pip install 'pvslam[sweep]' to run them in parallel)")
        return SerialExecutor(threads)
    return RayExecutor(address, workers, threads)
