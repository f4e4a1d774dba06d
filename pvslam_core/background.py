"""Work overlapped with the pipeline thread: frames read ahead, outputs written behind.

A run is one thread of mapping; decoding the next frame's PNGs and encoding the last frame's panoptic PNG do not
depend on it, and OpenCV, zlib and file I/O release the GIL, so on a machine with two cores they run beside the
mapping instead of before or after it.  Both helpers hold a *bounded* queue, so memory stays flat however far the
producer could run ahead: at most ``depth`` frames are decoded ahead, at most ``depth`` writes wait.

* :func:`read_ahead` wraps an iterator: a daemon thread fills the queue, the caller's loop takes from it.  An
  exception raised by the iterator reaches the caller at the item where it happened; closing the generator
  (``break``, an exception in the loop, Ctrl-C) stops the thread.
* :func:`with_next` pairs each item with the next one (read before the item is processed), for work that may begin
  on the next frame early; an error reading the next item reaches the caller after the item before it.
* :class:`BackgroundWriter` runs submitted calls in order on one thread.  An exception of a call is kept and
  re-raised by the next :meth:`~BackgroundWriter.submit`, :meth:`~BackgroundWriter.drain` or
  :meth:`~BackgroundWriter.close` in the caller's thread (so a write error still stops the run, one frame later).
"""
from __future__ import annotations

import queue
import threading
from typing import Any, Callable, Iterable, Iterator, Optional

_DONE = object()


class _Raised:
    def __init__(self, exc: BaseException) -> None:
        self.exc = exc


def read_ahead(items: Iterable[Any], depth: int = 2, name: str = "pvslam-read-ahead") -> Iterator[Any]:
    """Yield the items of ``items``, produced up to ``depth`` ahead by a background thread (``depth`` <= 0: no
    thread, the items as they come)."""
    if depth <= 0:
        yield from items
        return
    q: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def put(item) -> bool:
        while not stop.is_set():
            try:
                q.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        try:
            for item in items:
                if not put(item):
                    return
            put(_DONE)
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer
            put(_Raised(exc))

    t = threading.Thread(target=produce, name=name, daemon=True)
    t.start()
    try:
        while True:
            item = q.get()
            if item is _DONE:
                return
            if isinstance(item, _Raised):
                raise item.exc
            yield item
    finally:
        stop.set()
        t.join(timeout=5.0)


def with_next(frames: Iterable[Any], ahead: bool) -> Iterator[tuple[Any, Any]]:
    """``(frame, the next frame or None)`` for each of ``frames``; with ``ahead`` False the next is always None (the
    iterator is not read ahead of the frame being processed)."""
    if not ahead:
        yield from ((frame, None) for frame in frames)
        return
    it = iter(frames)
    cur = next(it, None)
    while cur is not None:
        try:
            nxt = next(it, None)
        except BaseException:  # the frame read before the failing one is processed first, as without the lookahead
            yield cur, None
            raise
        yield cur, nxt
        cur = nxt


class BackgroundWriter:
    """Runs ``fn(*args)`` calls in submission order on one daemon thread, at most ``depth`` waiting."""

    def __init__(self, depth: int = 4, name: str = "pvslam-writer") -> None:
        self._q: queue.Queue = queue.Queue(maxsize=max(1, int(depth)))
        self._error: Optional[BaseException] = None
        self._lock = threading.Lock()
        self._closed = False
        self._thread = threading.Thread(target=self._work, name=name, daemon=True)
        self._thread.start()

    def _work(self) -> None:
        while True:
            job = self._q.get()
            try:
                if job is _DONE:
                    return
                fn, args = job
                with self._lock:
                    failed = self._error is not None
                if not failed:  # after a failure, later writes are skipped: the run stops at the next submit
                    fn(*args)
            except BaseException as exc:  # noqa: BLE001 - re-raised in the caller's thread
                with self._lock:
                    if self._error is None:
                        self._error = exc
            finally:
                self._q.task_done()

    def _raise(self) -> None:
        with self._lock:
            exc, self._error = self._error, None
        if exc is not None:
            raise exc

    def submit(self, fn: Callable, *args: Any) -> None:
        """Queue ``fn(*args)`` (blocks while ``depth`` calls wait); first re-raises an earlier call's exception."""
        if self._closed:
            raise RuntimeError("BackgroundWriter: submit after close")
        self._raise()
        self._q.put((fn, args))

    def drain(self) -> None:
        """Wait until every submitted call has run; re-raise the first exception among them."""
        self._q.join()
        self._raise()

    def close(self) -> None:
        """Drain, then stop the thread (idempotent)."""
        if self._closed:
            return
        try:
            self.drain()
        finally:
            self._closed = True
            self._q.put(_DONE)
            self._thread.join(timeout=10.0)
