"""The next frame's tracking begun early (:meth:`.frontend.FlowFrontend.prefetch`), on one thread of its own.

With two cores the pipeline thread's keyframe work (edges, BA) leaves the second core mostly idle, and a frame's
tracking flows depend on that frame, the reference keyframe and the previous tracked frame alone
(:meth:`.track_starts.TrackStarts.ahead`).  So once a frame has been tracked (and added, when it became a keyframe),
the next frame's gray image and tracking flows are begun here, and the next :meth:`~.frontend.FlowFrontend.track`
takes them when it tracks that frame against that keyframe from that previous frame.
"""
from __future__ import annotations

import os
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Callable, Optional

import numpy as np

from pvslam_core.types import Frame


class Ahead:
    """One job at a time, for one frame: taken only by the frame it was begun for and with the inputs it was begun
    with (``key``).  Its result is a pure function of them, so a run's results do not depend on whether it was
    taken."""

    def __init__(self) -> None:
        self._pool: Optional[ThreadPoolExecutor] = None
        self._pid = -1  # the process that owns the pool (a forked child gets the pool object, not its thread)
        self._job: Optional[tuple[Frame, Any, Future]] = None

    def start(self, frame: Frame, key: tuple, fn: Callable[[], tuple]) -> None:
        """Begin ``fn()`` for ``frame`` with inputs ``key``, after the job before it (if any) has finished."""
        self.wait()
        if self._pool is None or self._pid != os.getpid():
            self._pool = ThreadPoolExecutor(1, thread_name_prefix="pvslam-prefetch")
            self._pid = os.getpid()
        self._job = (frame, key, self._pool.submit(fn))

    def take(self, frame: Frame, key: tuple) -> tuple[Optional[np.ndarray], Any]:
        """``(gray, started)`` of the job begun for ``frame`` with ``key`` (the reference keyframe's id and the
        tracked frame that starts it, the same object), or ``(None, None)``; a job begun for anything else is
        waited for (it reads state that the caller is about to change) and dropped."""
        job = self._job
        out = self.wait()
        if out is None or job[0] is not frame:
            return None, None
        (sid, prev), (sid_now, prev_now) = job[1], key
        return out if sid == sid_now and prev is prev_now else (None, None)

    def wait(self) -> Optional[tuple]:
        """Wait for the job in flight and drop it: its result, or None (no job, or it raised: a caller computes the
        same afresh, and meets the error itself)."""
        job, self._job = self._job, None
        if job is None:
            return None
        try:
            return job[2].result()
        except Exception:  # noqa: BLE001
            return None
