"""Independent DIS calls (and their forward-backward checks) on two threads (``dis.threads``).

A new keyframe's edge flows (forward and backward of 2-4 keyframe pairs, some twice: from the reprojection and from
zero) and a frame's two tracking flows do not depend on each other, and OpenCV releases the GIL inside
``DISOpticalFlow.calc``, so on a machine with two cores half of them can run beside the other half: DIS is a good
part of the pipeline thread's time.  An edge's forward-backward check, photometric confidence and pooling (numpy and
OpenCV, mostly outside the GIL) go with its pair (:meth:`DisLanes.map`).

Each thread has its own DIS objects, one per *kind* of call (edge / track, with or without an initial flow): a DIS
object that once got an initial flow keeps using it in later calls without one (see :class:`.pair_flow.FlowPairs`),
so an object only ever serves one kind, and a call's result depends on its inputs alone - the same on either thread,
in any order (test: results bit-equal to one thread).
"""
from __future__ import annotations

import itertools
import os
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor, wait
from typing import Callable, Optional, Sequence

import numpy as np

from . import flow_ops as F

# kind -> whether the call carries an initial flow
KINDS = {"edge": False, "edge_init": True, "track": False, "track_init": True}

Call = tuple[str, np.ndarray, np.ndarray, Optional[np.ndarray]]  # (kind, i0, i1, init): DIS flow i0 -> i1


class DisLanes:
    """``run(calls)`` computes DIS flows, split between the caller's thread and ``threads - 1`` workers."""

    def __init__(self, make: Callable[[str], object], threads: int = 1) -> None:
        self._make = make  # kind -> a new DIS object for that kind of call
        self._local = threading.local()
        self.threads = max(1, int(threads))
        self._pool: Optional[ThreadPoolExecutor] = None
        self._pid = -1  # the process that owns the pool (a forked child gets the pool object, not its threads)

    def _workers(self) -> Optional[ThreadPoolExecutor]:
        if self.threads == 1:
            return None
        if self._pool is None or self._pid != os.getpid():
            self._pool = ThreadPoolExecutor(self.threads - 1, thread_name_prefix="pvslam-dis")
            self._pid = os.getpid()
        return self._pool

    def dis(self, kind: str):
        """This thread's DIS object for ``kind`` (created on first use)."""
        objs = getattr(self._local, "objs", None)
        if objs is None:
            objs = self._local.objs = {}
        if kind not in objs:
            objs[kind] = self._make(kind)
        return objs[kind]

    def flow(self, call: Call) -> tuple[np.ndarray, float]:
        """One DIS call on this thread's object for its kind: the flow and the seconds it took."""
        kind, i0, i1, init = call
        if kind not in KINDS:
            raise ValueError(f"unknown DIS call kind {kind!r}; one of {sorted(KINDS)}")
        if (init is not None) != KINDS[kind]:
            raise ValueError(f"DIS call of kind {kind!r} {'needs' if KINDS[kind] else 'takes no'} initial flow")
        t = time.perf_counter()
        return F.compute_flow(self.dis(kind), i0, i1, init), time.perf_counter() - t

    def map(self, fn: Callable, items: Sequence) -> list:
        """``[fn(item) for item in items]`` on the caller's thread and the workers together: each takes the next item
        nobody has begun, so the caller never waits for a worker that has not started yet (it is busy with a job of
        :meth:`submit`, or not scheduled); ``fn`` may call :meth:`flow`: each thread uses its own DIS objects."""
        pool = self._workers() if len(items) > 1 else None
        if pool is None:
            return [fn(it) for it in items]
        n, out = len(items), [None] * len(items)
        claim = itertools.count()  # next() is atomic: each index is taken by one thread
        failed = threading.Event()

        def drain() -> None:
            while not failed.is_set() and (i := next(claim)) < n:
                try:
                    out[i] = fn(items[i])
                except BaseException:
                    failed.set()  # the others take no new item
                    raise

        futures = [pool.submit(drain) for _ in range(min(self.threads - 1, n - 1))]
        try:
            drain()
        finally:
            # every item is taken now (or abandoned after an error): a worker that has not begun would find nothing
            # to do (cancelled, not waited for); those that did are waited for, so no item runs after this returns
            wait([f for f in futures if not f.cancel()])
        for f in futures:
            if not f.cancelled():
                f.result()  # a worker's error
        return out

    def submit(self, fn: Callable, *args) -> Future:
        """``fn(*args)`` on a worker, after the workers' earlier calls (with one thread: here, at once).  For work that
        nothing needs until later (the motion predictor's per-frame homography): the caller waits on the future
        before it reads what ``fn`` writes, so the result is the same as a call in place."""
        pool = self._workers()
        if pool is not None:
            return pool.submit(fn, *args)
        fut: Future = Future()
        try:
            fut.set_result(fn(*args))
        except BaseException as exc:  # noqa: BLE001 - delivered by fut.result(), as from a worker
            fut.set_exception(exc)
        return fut

    def run(self, calls: Sequence[Call]) -> tuple[list[np.ndarray], float]:
        """The flows of ``calls`` in order, and the summed seconds of the calls."""
        out = self.map(self.flow, calls)
        return [f for f, _ in out], sum(s for _, s in out)

    def close(self) -> None:
        if self._pool is not None and self._pid == os.getpid():
            self._pool.shutdown(wait=True)
        self._pool = None
